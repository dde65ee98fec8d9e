"""`plot`: the paper's Fig. 4 (leg lengths, position, orientation against time).

    plot SOURCE [--out FILE.png] [--reference CSV] [--params FILE] [--title TEXT] [--run N]
    plot --animate SOURCE [--out FILE.gif|FILE.mp4] [--fps N] [--params FILE] [--run N]

SOURCE is a trajectory CSV, a folder holding one (``sim --out DIR``), or a
rosbag2 directory recorded from the rig (docs/interface.md: "Trajectory CSV",
"Bags"). The title names the run; the setpoint lengths of the parameter file
(``--params``, default the packaged one) are drawn as dashed lines. With a
reference motion (--reference, or a reference.csv beside the source, as `sim
--reference` writes it; time 0 = the first sample), the reference is drawn
dashed against the actual motion and a fourth panel shows the error.
``--animate`` writes an animation of the run instead: the platform in 3D
beside the leg lengths (tools/animate.py). Faulted intervals are shaded: from
``faults.json`` beside a trajectory (``sim --fault``) or from the plant's
statuses on a bag's /diagnostics (docs/faults.md). A bag that spans a reset
holds several runs (``bagruns.bag_runs``): each is drawn on its own, the last
to --out (figure.png), each earlier run N beside it (figure_runN.png);
``--run N`` draws only run N.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from stewart63_ros.core.machine.faults import interval_from_status
from stewart63_ros.core.plumbing.trajectory import read_csv
from stewart63_ros.tools.animate import Animator
from stewart63_ros.tools.cli import load_checked, quiet_on_closed_pipe

#: Line styles of the six legs: legs with equal lengths (1 and 2, 3 to 6 in
#: the paper's scenario) stay told apart where their curves lie on each other.
LEG_STYLES = ('-', (0, (6, 2)), '-.', (0, (1, 1.5)), (0, (8, 2, 1, 2, 1, 2)), (0, (3, 3)))


def draw_figure(columns: dict, out_path, title: str = '', reference: dict | None = None,
                setpoint=None, faults: list | None = None, layout: str = '6-3') -> Path:
    """Write Fig. 4 from {column: array} (the CSV layout) to ``out_path``; with
    ``reference`` ({t, x, y, z, theta_x, theta_y, theta_z: array}) also the
    reference (dashed) and the error actual - reference. ``setpoint``: the six
    desired lengths (L_i)_0, drawn as thin dashed black lines, so the final
    sag of the legs below or above them shows. ``faults``: dicts with
    ``fault``, ``active_from_s`` and ``active_until_s`` (None: to the end;
    times from the first sample), shaded on every panel. ``layout``: the
    machine's ('6-3' or '6-6'), named in the title."""
    import matplotlib  # lazy: matplotlib costs 425 ms; only a figure needs it
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt  # lazy: pyplot costs 794 ms; only a figure needs it

    t = columns['t']
    panels = 3 if reference is None else 4
    fig, axes = plt.subplots(panels, 1, figsize=(8, 3 * panels), sharex=True)
    colors = plt.rcParams['axes.prop_cycle'].by_key()['color']
    for i in range(1, 7):
        axes[0].plot(t, columns['L%d' % i], label='$L_%d$' % i,
                     color=colors[(i - 1) % len(colors)], linestyle=LEG_STYLES[i - 1],
                     linewidth=1.6)
    if setpoint is not None and len(t):
        levels = sorted(set(round(float(v), 12) for v in setpoint))
        for k, value in enumerate(levels):
            axes[0].axhline(value, color='black', linestyle='--', linewidth=0.8,
                            label='setpoint $(L_i)_0$' if k == 0 else None)
        # axhline does not widen the axis: keep the setpoints inside it.
        lengths = np.concatenate([np.asarray(columns['L%d' % i], float) for i in range(1, 7)])
        lengths = lengths[np.isfinite(lengths)]
        lo = min(levels + ([float(lengths.min())] if lengths.size else []))
        hi = max(levels + ([float(lengths.max())] if lengths.size else []))
        pad = 0.05 * max(hi - lo, 1e-3)
        axes[0].set_ylim(lo - pad, hi + pad)
    axes[0].set_ylabel('leg length [m]')
    for name, label in (('x', '$t_x$'), ('y', '$t_y$'), ('z', '$t_z$')):
        axes[1].plot(t, columns[name], label=label)
    axes[1].set_ylabel('position [m]')
    for name, label in (('theta_x', r'$\theta_x$'), ('theta_y', r'$\theta_y$'),
                        ('theta_z', r'$\theta_z$')):
        axes[2].plot(t, columns[name], label=label)
    axes[2].set_ylabel('orientation [rad]')
    if reference is not None:
        # lazy: scipy.interpolate costs 825 ms; only a figure needs it
        from scipy.interpolate import CubicSpline
        names = ('x', 'y', 'z', 'theta_x', 'theta_y', 'theta_z')
        rt = np.asarray(reference['t'], float)
        poses = np.column_stack([reference[name] for name in names])
        # the tools' interpolation of a reference (clamped cubic spline, holding the ends)
        at = (CubicSpline(rt, poses, bc_type='clamped')(np.clip(t, rt[0], rt[-1]))
              if rt.size > 1 else np.repeat(poses, len(t), axis=0))
        for k, name in enumerate(names):
            ref = at[:, k]
            axes[1 if k < 3 else 2].plot(t, ref, '--', color='k', lw=0.8,
                                         label='reference' if k in (0, 3) else None)
            scale, unit = (1e3, 'mm') if k < 3 else (1e3, 'mrad')
            axes[3].plot(t, scale * (columns[name] - ref), label='%s [%s]' % (name, unit))
        axes[3].set_ylabel('error (actual - reference)')
    axes[-1].set_xlabel('time [s]')
    if faults:
        _shade_faults(axes, faults, t)
    for ax in axes:
        ax.grid(True, alpha=0.3)
        ax.legend(loc='best', fontsize='small', ncol=3)
    fig.suptitle('%s Stewart platform, PD control (Yurt & Ozkol, Fig. 4)' % layout
                 + ('\n' + title if title else ''))
    fig.tight_layout()
    out_path = Path(out_path)
    fig.savefig(out_path, dpi=100)
    plt.close(fig)
    return out_path


def _shade_faults(axes, faults, t) -> None:
    """One shaded band per fault that acted, labelled on the first panel."""
    finite = np.asarray(t, float)[np.isfinite(t)]
    if not finite.size:
        return
    t0, t_end = float(finite[0]), float(finite[-1])
    colors = ('tab:red', 'tab:orange', 'tab:purple', 'tab:brown', 'tab:pink', 'tab:olive')
    shown = [f for f in faults if f.get('active_from_s') is not None]
    for k, fault in enumerate(shown):
        start = t0 + fault['active_from_s']
        end = t_end if fault.get('active_until_s') is None else t0 + fault['active_until_s']
        for i, ax in enumerate(axes):
            ax.axvspan(start, max(end, start), color=colors[k % len(colors)], alpha=0.12,
                       label='fault %s' % fault['fault'] if i == 0 else None)


def is_bag(source) -> bool:
    """A rosbag2 directory (not ``sim``'s output folder)."""
    source = Path(source)
    return source.is_dir() and (source / 'metadata.yaml').exists()


def load_faults(source, run=None) -> list | None:
    """The faults of a run: ``faults.json`` beside a trajectory (``sim``), or
    the last state of each ``fault: <fault>`` value of the plant's statuses in
    a bag's /diagnostics during ``run`` (a ``bagio.BagRun``; default the bag's
    last run). None when the source has none."""
    source = Path(source)
    if not is_bag(source):
        path = (source if source.is_dir() else source.parent) / 'faults.json'
        return json.loads(path.read_text()) if path.is_file() else None
    # lazy: bagio costs 197 ms (tempfile, csv); plot --help needs no bag
    from stewart63_ros import bagio, bagruns
    if run is None:
        runs = bagruns.bag_runs(source)
        run = runs[-1] if runs else None
    found: dict = {}
    number = None if run is None or run.number is None else str(run.number)
    try:
        for _, _, msg in bagio.read_messages(source, ['/diagnostics'], run=run):
            for status in msg.status:
                if not status.name.endswith('/plant'):
                    continue
                values = {kv.key: kv.value for kv in status.values}
                if number is not None and values.get('run_number') != number:
                    continue        # the next run announced, a quiet second before it
                for key, text in values.items():
                    if key.startswith('fault: '):
                        found[key[len('fault: '):]] = text
    except bagio.BagError:
        return None         # no /diagnostics in the bag: nothing to shade
    faults = []
    for name, text in found.items():
        interval = interval_from_status(text)
        faults.append({'fault': name, 'status': text,
                       'active_from_s': interval[0] if interval else None,
                       'active_until_s': interval[1] if interval else None})
    return faults or None


def load_columns(source, run=None) -> dict:
    """Trajectory columns from a CSV file, a bag directory (of ``run``, a
    ``bagio.BagRun``; default its last run), or a folder that holds a
    ``trajectory.csv`` (what ``sim --out DIR`` writes)."""
    source = Path(source)
    if source.is_dir():
        if (source / 'trajectory.csv').is_file() and not (source / 'metadata.yaml').exists():
            source = source / 'trajectory.csv'
        else:
            # lazy: bagio costs 197 ms (tempfile, csv); plot --help needs no bag
            from stewart63_ros.bagruns import trajectory_from_bag
            return trajectory_from_bag(source, run=run)
    return read_csv(source)


def source_runs(source, number=None) -> list:
    """The runs to draw of a source: [None] for a trajectory; for a bag, each
    run it holds (``bagruns.bag_runs``: a reset starts a new one), or only run
    ``number`` (``--run``). Raises BagError for a run the bag does not hold."""
    if not is_bag(source):
        if number is not None:
            # lazy: bagio costs 197 ms (tempfile, csv); plot --help needs no bag
            from stewart63_ros.bagio import BagError
            raise BagError('--run is for a bag; %s is a trajectory of one run' % source)
        return [None]
    # lazy: bagio costs 197 ms (tempfile, csv); plot --help needs no bag
    from stewart63_ros import bagruns
    runs = bagruns.bag_runs(source)
    if number is not None or not runs:
        return [bagruns.select_run(runs, number)]
    return runs


def run_output(out: Path, run, runs: list) -> Path:
    """Where a run's figure goes: ``out`` for the last run drawn (the run the
    plant's summary reports), ``<stem>_<run label><suffix>`` beside it for each
    earlier run of a bag that spans a reset."""
    if run is None or run is runs[-1]:
        return out
    return out.with_name('%s_%s%s' % (out.stem, run.label, out.suffix))


def run_title(source: Path, columns: dict, run=None) -> str:
    """What the figure shows: the run's folder (or file), which run of a bag
    that holds several, and its length."""
    t = columns['t']
    finite = t[np.isfinite(t)]
    span = float(finite[-1] - finite[0]) if finite.size else 0.0
    source = Path(source)
    kind = 'bag' if source.is_dir() and not (source / 'trajectory.csv').is_file() else 'trajectory'
    if run is not None and run.count > 1:
        kind += ', %s, %d of %d in the bag' % (run.name, run.index, run.count)
    return '%s (%s, %.3g s, %d samples)' % (source, kind, span, len(t))


@quiet_on_closed_pipe
def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='plot', description=__doc__.split('\n\n')[0])
    parser.add_argument('source', help="trajectory CSV, rosbag2 directory, or sim's --out folder")
    parser.add_argument('--out', help='PNG to write (default: figure.png beside the source)')
    parser.add_argument('--reference', metavar='CSV', help='reference motion to draw against '
                        'the actual one (default: reference.csv beside the source, if any)')
    parser.add_argument('--params', metavar='FILE',
                        help='parameter file whose setpoint_lengths are drawn (default: the '
                        'packaged one)')
    parser.add_argument('--title', help='figure title (default: the source and its length)')
    parser.add_argument('--animate', action='store_true',
                        help='write an animation (GIF, or MP4 where ffmpeg is installed) of '
                        'the platform in 3D beside the leg lengths instead of the figure '
                        '(default --out: animation.gif beside the source)')
    parser.add_argument('--fps', type=float, default=15.0,
                        help='--animate: frames per second (default 15; a run longer than '
                        '300 frames plays faster)')
    parser.add_argument('--run', type=int, default=None, metavar='N',
                        help='a bag that spans a reset: draw only its run N (default: every '
                        'run, the last to --out, each earlier one beside it as '
                        '<name>_runN.png)')
    args = parser.parse_args(argv)
    source = Path(args.source)
    if not source.exists():
        parser.exit(2, 'plot: error: %s does not exist\n' % source)
    if args.animate:
        return animate_main(parser, args, source)
    if args.fps != 15.0:
        parser.exit(2, 'plot: error: --fps goes with --animate\n')
    # lazy: bagio costs 197 ms (tempfile, csv); plot --help needs no bag
    from stewart63_ros.bagio import BagError
    reference = None
    ref_path = Path(args.reference) if args.reference else (
        source / 'reference.csv' if source.is_dir() else source.with_name('reference.csv'))
    try:
        runs = source_runs(source, args.run)
        drawn = [(run, load_columns(source, run), load_faults(source, run)) for run in runs]
        if args.reference or ref_path.is_file():
            # lazy: core.controllers.reference costs 570 ms (numba); only --reference
            from stewart63_ros.core.controllers.reference import CSV_COLUMNS
            from stewart63_ros.core.controllers.reference_files import read_reference_csv
            times, poses = read_reference_csv(ref_path)
            reference = dict(zip(CSV_COLUMNS, np.column_stack([times, poses]).T))
    except (ValueError, OSError, BagError) as exc:  # TrajectoryError, BagError, ReferenceError
        text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        parser.exit(2, 'plot: error: %s\n' % text)
    for _, columns, _ in drawn:
        if len(columns['t']) == 0 or not np.all(np.isfinite(columns['t'])):
            parser.exit(2, 'plot: error: %s holds no samples\n' % source)
    setup = load_checked('plot', args.params, node_name='controller')
    if setup is None:
        return 2
    setpoint = setup.task.setpoint_lengths
    out = Path(args.out) if args.out else (
        source / 'figure.png' if source.is_dir() else source.with_name('figure.png'))
    for run, columns, faults in drawn:
        # a bag's times are stamps: the reference's time 0 is the run's first sample
        # (the controller starts it again on a reset)
        moved = None if reference is None else dict(reference,
                                                     t=reference['t'] + columns['t'][0])
        path = run_output(out, run, runs)
        title = run_title(source, columns, run)
        draw_figure(columns, path, title=title if not args.title else
                    args.title + ('' if len(drawn) == 1 else ' (%s)' % run.name),
                    reference=moved, setpoint=setpoint, faults=faults,
                    layout=setup.mechanism.layout)
        print(path if len(drawn) == 1 else '%s (%s)' % (path, title))
    return 0


def animate_main(parser, args, source) -> int:
    # lazy: bagio costs 197 ms (tempfile, csv); plot --help needs no bag
    from stewart63_ros.bagio import BagError
    if not 0 < args.fps <= 60:
        parser.exit(2, 'plot: error: --fps must be in (0, 60]\n')
    out = Path(args.out) if args.out else (
        source / 'animation.gif' if source.is_dir() else source.with_name('animation.gif'))
    if out.suffix.lower() not in ('.gif', '.mp4'):
        parser.exit(2, 'plot: error: %s: --animate writes a .gif or an .mp4\n' % out)
    setup = load_checked('plot', args.params)
    if setup is None:
        return 2
    try:
        runs = source_runs(source, args.run)
        for run in runs:
            columns = load_columns(source, run)
            if len(columns['t']) == 0:
                raise ValueError('%s holds no samples' % source)
            title = source.name if run is None or run.count == 1 else '%s, %s (%d of %d)' % (
                source.name, run.name, run.index, run.count)
            path, frames, speed = Animator(columns, setup.mechanism, title=title).save(
                run_output(out, run, runs), args.fps)
            print('%s (%d frames at %g fps%s%s)' % (
                path, frames, args.fps, ', %.1fx real time' % speed if speed > 1 else '',
                '' if run is None or run.count == 1 else ', %s of the bag' % run.name))
    except (ValueError, OSError, BagError) as exc:  # TrajectoryError, no poses, no ffmpeg
        parser.exit(2, 'plot: error: %s\n' % exc)
    return 0


if __name__ == '__main__':
    sys.exit(main())
