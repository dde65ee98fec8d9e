"""`plot`: the paper's Fig. 4 (leg lengths, position, orientation against time).

    plot SOURCE [--out FILE.png] [--reference CSV]

SOURCE is a trajectory CSV or a rosbag2 directory recorded from the rig
(docs/interface.md: "Trajectory CSV", "Bags"). With a reference motion
(--reference, or a reference.csv beside the source, as `sim --reference`
writes it; time 0 = the first sample), the reference is drawn dashed against
the actual motion and a fourth panel shows the error.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def draw_figure(columns: dict, out_path, title: str = '', reference: dict | None = None) -> Path:
    """Write Fig. 4 from {column: array} (the CSV layout) to ``out_path``; with
    ``reference`` ({t, x, y, z, theta_x, theta_y, theta_z: array}) also the
    reference (dashed) and the error actual - reference."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    t = columns['t']
    panels = 3 if reference is None else 4
    fig, axes = plt.subplots(panels, 1, figsize=(8, 3 * panels), sharex=True)
    for i in range(1, 7):
        axes[0].plot(t, columns['L%d' % i], label='$L_%d$' % i)
    axes[0].set_ylabel('leg length [m]')
    for name, label in (('x', '$t_x$'), ('y', '$t_y$'), ('z', '$t_z$')):
        axes[1].plot(t, columns[name], label=label)
    axes[1].set_ylabel('position [m]')
    for name, label in (('theta_x', r'$\theta_x$'), ('theta_y', r'$\theta_y$'),
                        ('theta_z', r'$\theta_z$')):
        axes[2].plot(t, columns[name], label=label)
    axes[2].set_ylabel('orientation [rad]')
    if reference is not None:
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
    for ax in axes:
        ax.grid(True, alpha=0.3)
        ax.legend(loc='best', fontsize='small', ncol=3)
    fig.suptitle(title or '6-3 Stewart platform, PD control (Yurt & Ozkol, Fig. 4)')
    fig.tight_layout()
    out_path = Path(out_path)
    fig.savefig(out_path, dpi=100)
    plt.close(fig)
    return out_path


def load_columns(source) -> dict:
    """Trajectory columns from a CSV file or a bag directory."""
    source = Path(source)
    if source.is_dir():
        from stewart63_ros.bagio import trajectory_from_bag
        return trajectory_from_bag(source)
    from stewart63_ros.core.trajectory import read_csv
    return read_csv(source)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='plot', description=__doc__.split('\n\n')[0])
    parser.add_argument('source', help='trajectory CSV or rosbag2 directory')
    parser.add_argument('--out', help='PNG to write (default: figure.png beside the source)')
    parser.add_argument('--reference', metavar='CSV', help='reference motion to draw against '
                        'the actual one (default: reference.csv beside the source, if any)')
    args = parser.parse_args(argv)
    source = Path(args.source)
    if not source.exists():
        parser.exit(2, 'plot: error: %s does not exist\n' % source)
    reference = None
    ref_path = Path(args.reference) if args.reference else (
        source / 'reference.csv' if source.is_dir() else source.with_name('reference.csv'))
    try:
        columns = load_columns(source)
        if args.reference or ref_path.is_file():
            from stewart63_ros.core.reference import CSV_COLUMNS, read_reference_csv
            times, poses = read_reference_csv(ref_path)
            reference = dict(zip(CSV_COLUMNS, np.column_stack([times, poses]).T))
    except (ValueError, OSError) as exc:  # TrajectoryError, BagError, ReferenceError
        parser.exit(2, 'plot: error: %s\n' % exc)
    if len(columns['t']) == 0 or not np.all(np.isfinite(columns['t'])):
        parser.exit(2, 'plot: error: %s holds no samples\n' % source)
    out = Path(args.out) if args.out else (
        source / 'figure.png' if source.is_dir() else source.with_name('figure.png'))
    if reference is not None and len(columns['t']):
        # a bag's times are stamps: the reference's time 0 is the first sample
        reference = dict(reference, t=reference['t'] + columns['t'][0])
    draw_figure(columns, out, title=source.name, reference=reference)
    print(out)
    return 0


if __name__ == '__main__':
    sys.exit(main())
