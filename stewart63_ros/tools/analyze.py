"""`analyze`: the mechanism linearized, its modes, frequency responses and workspace.

    analyze linearize [--params F] [--control-law NAME|none] [--pose x y z tx ty tz] --out DIR
    analyze modes     [--params F] [--control-law NAME|none] [--pose ...] [--json]
    analyze freqresp  [--params F] [--control-law NAME|none] [--pose ...]
                      [--fmin 0.01] [--fmax 100] [--points 300] --out DIR
    analyze workspace [--params F] [--orientation tx ty tz] [--step 0.05] --out DIR

From the parameter file alone, no DDS (docs/analysis.md). The equilibrium is
the pose (default: the forward kinematics of ``setpoint_lengths``) held at
rest against gravity; the control law defaults to the controller's
``control_law`` in the file (else pd, eq. 40); ``none`` analyses the plant
alone (inputs: piston forces). Bad input (a pose outside the stroke or near a
singularity, an unknown law): one line on stderr, exit status 2.
"""
from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np

from stewart63_ros.core.analysis import equilibrium, modal
from stewart63_ros.core.analysis.equilibrium import DEFAULT_MAX_CONDITION, AnalysisError
from stewart63_ros.core.analysis.linear import linearize
from stewart63_ros.core.analysis.modal import frequency_table, strongest_couplings
from stewart63_ros.core.analysis.workspace import (
    DEFAULT_STEP,
    REASONS,
    GridTooLarge,
    check_grid_fits,
    grid_axes,
    human_bytes,
    workspace_map,
)
from stewart63_ros.core.controllers.laws import law_class
from stewart63_ros.core.mechanics.rotation import euler_from_matrix, rotation_from_euler
from stewart63_ros.core.plumbing.node_parameters import read as read_declared
from stewart63_ros.core.plumbing.params import (
    ParameterError,
    default_params_path,
    load_setup,
    read_parameter_file,
)
from stewart63_ros.tools.cli import (
    STRICT_HELP,
    announce_compile,
    load_checked,
    quiet_on_closed_pipe,
)
from stewart63_ros.tools.plot import LEG_STYLES

PROG = 'analyze'


def _fail(message) -> int:
    print('%s: error: %s' % (PROG, message), file=sys.stderr)
    return 2


def _common(parser, with_law=True):
    parser.add_argument('--params', default=None,
                        help='ROS 2 parameter file (default: the packaged config/stewart63.yaml)')
    if with_law:
        parser.add_argument('--control-law', default=None, metavar='NAME|none',
                            help="the law closing the loop: pd (eq. 40), pd_gravity, "
                            "computed_torque or package.module:Class (default: the "
                            "controller's control_law in the file, else pd); none: the "
                            'plant alone, inputs the piston forces')
        parser.add_argument('--pose', type=float, nargs=6, default=None,
                            metavar=('X', 'Y', 'Z', 'TX', 'TY', 'TZ'),
                            help='equilibrium pose [m, rad] (default: the forward kinematics '
                            'of setpoint_lengths)')
    parser.add_argument('--max-condition', type=float, default=None, metavar='C',
                        help='refuse (linearize, modes, freqresp) or mark unreachable '
                        '(workspace) poses whose Jacobian condition number exceeds C '
                        '(default 100)')
    parser.add_argument('--strict', action='store_true', help=STRICT_HELP)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split('\n\n')[0])
    sub = parser.add_subparsers(dest='command', metavar='COMMAND', required=True)
    lin = sub.add_parser('linearize', help='state-space model A, B, C, D about the equilibrium')
    _common(lin)
    lin.add_argument('--out', required=True, help='output directory (linear.npz, linear.json)')
    mod = sub.add_parser('modes', help='natural frequencies, damping ratios, mode shapes')
    _common(mod)
    mod.add_argument('--json', action='store_true', help='print JSON instead of a table')
    fr = sub.add_parser('freqresp', help='frequency responses, every input to every output')
    _common(fr)
    fr.add_argument('--fmin', type=float, default=0.01, help='lowest frequency [Hz] (0.01)')
    fr.add_argument('--fmax', type=float, default=100.0, help='highest frequency [Hz] (100)')
    fr.add_argument('--points', type=int, default=300,
                    help='frequencies, log-spaced from fmin to fmax (300)')
    fr.add_argument('--out', required=True, help='output directory (freqresp.csv, bode.png)')
    ws = sub.add_parser('workspace', help='reachable positions at one orientation')
    _common(ws, with_law=False)
    ws.add_argument('--orientation', type=float, nargs=3, default=None,
                    metavar=('TX', 'TY', 'TZ'),
                    help="platform orientation [rad] (default: the setpoint pose's)")
    ws.add_argument('--step', type=float, default=None,
                    help='grid step [m] (0.05)')
    ws.add_argument('--large-output', action='store_true',
                    help='write a workspace.csv larger than 100 MB (refused without it)')
    ws.add_argument('--out', required=True, help='output directory (workspace.csv, '
                    'workspace.png)')
    return parser


# -- linear model -----------------------------------------------------------------------------
def law_of(args, params_path):
    """(law name or None, controller params, controller setup)."""
    params = read_parameter_file(params_path, 'controller')
    law = args.control_law or read_declared(params, 'control_law')
    if law == 'none':
        return None, params, None
    law_class(law)                                   # ParameterError for an unknown law
    return law, params, load_setup(params_path, node_name='controller')


def linear_model(setup, args, params_path):
    law, params, controller = law_of(args, params_path)
    return linearize(setup, law, args.pose, params,
                     args.max_condition or DEFAULT_MAX_CONDITION, controller)


def _loop_label(model) -> str:
    return ('closed loop (%s)' % model.law) if model.closed_loop else 'open loop (plant alone)'


def _clean(values) -> np.ndarray:
    """Values with those that print as -0.000 set to 0."""
    values = np.array(values, dtype=float)
    values[np.abs(values) < 5e-7] = 0.0
    return values + 0.0


def _pose_text(pose) -> str:
    p = _clean(pose)
    return 'x y z (%.4f, %.4f, %.4f) m, theta (%.4f, %.4f, %.4f) rad' % tuple(p)


def write_linear(model, out: Path) -> tuple[Path, Path]:
    out.mkdir(parents=True, exist_ok=True)
    npz = out / 'linear.npz'
    np.savez(npz, A=model.A, B=model.B, C=model.C, D=model.D, x0=model.x0, u0=model.u0,
             y0=model.y0, pose=model.equilibrium.pose, holding_forces=model.equilibrium.forces)
    path = out / 'linear.json'
    path.write_text(readable_json(model.describe()))
    return npz, path


def readable_json(doc: dict) -> str:
    """JSON of a flat dict, one key per line, a matrix one row per line."""
    parts = []
    for key, value in doc.items():
        if isinstance(value, list) and value and all(isinstance(v, list) for v in value):
            rows = ',\n  '.join(json.dumps(row) for row in value)
            parts.append(' %s: [\n  %s]' % (json.dumps(key), rows))
        else:
            parts.append(' %s: %s' % (json.dumps(key), json.dumps(value)))
    return '{\n' + ',\n'.join(parts) + '\n}\n'


def print_modes(model, found) -> None:
    print('%s about %s' % (_loop_label(model), _pose_text(found.pose)))
    print('%4s %9s %9s %7s  %-26s %s' % ('mode', 'f [Hz]', 'damping', 'stable',
                                          'eigenvalues [1/s]', 'shape x y z theta_x theta_y '
                                          'theta_z (largest = 1)'))
    for k in range(len(found.frequencies_hz)):
        a, b = found.eigenvalues[k]
        if abs(a.imag) > 0:
            pair = '%.4g +- %.4gj' % (a.real, abs(a.imag))
        else:
            pair = '%.4g, %.4g' % (a.real, b.real)
        shape = ' '.join('%6.3f' % v for v in _clean(np.round(found.mode_shapes[k], 3)))
        print('%4d %9.4f %9.4f %7s  %-26s %s' % (k + 1, found.frequencies_hz[k],
                                                  found.damping_ratios[k],
                                                  'yes' if found.stable[k] else 'NO', pair,
                                                  shape))


# -- frequency response -----------------------------------------------------------------------
def write_freqresp(model, freqs, response, out: Path) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    path = out / 'freqresp.csv'
    with open(path, 'w', newline='') as fh:
        writer = csv.writer(fh)
        writer.writerow(['f_hz', 'input', 'output', 'magnitude', 'phase_deg'])
        for f, i, o, mag, phase in frequency_table(freqs, response):
            writer.writerow(['%.9g' % f, i, o, '%.9g' % mag, '%.6f' % phase])
    return path


def draw_bode(model, freqs, response, path: Path, couplings: int = 3) -> Path:
    """Magnitude and phase of the six diagonal responses (leg_i to leg_i) and of the
    ``couplings`` largest cross couplings (dashed)."""
    import matplotlib  # lazy: matplotlib costs 425 ms; only a figure needs it
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt  # lazy: pyplot costs 794 ms; only a figure needs it

    fig, (mag_ax, ph_ax) = plt.subplots(2, 1, figsize=(9, 7.5), sharex=True)
    colors = plt.rcParams['axes.prop_cycle'].by_key()['color']
    unit = 'm/m' if model.closed_loop else 'm/N'
    lines = [(i, i, colors[i], LEG_STYLES[i], 1.6, 'leg_%d to leg_%d' % (i + 1, i + 1))
             for i in range(6)]
    for k, (o, i) in enumerate(strongest_couplings(response, couplings)):
        lines.append((o, i, colors[(6 + k) % len(colors)], (':', '--', '-.')[k % 3], 1.2,
                      'leg_%d to leg_%d (cross)' % (i + 1, o + 1)))
    for o, i, color, style, width, label in lines:
        g = response[:, o, i]
        mag_ax.loglog(freqs, np.abs(g), color=color, linestyle=style, linewidth=width,
                      label=label)
        ph_ax.semilogx(freqs, np.degrees(np.unwrap(np.angle(g))), color=color,
                       linestyle=style, linewidth=width)
    source = ('leg-length reference' if model.closed_loop else 'piston force')
    mag_ax.set_ylabel('|L_out / %s_in| [%s]' % (source.split()[-1], unit))
    ph_ax.set_ylabel('phase [deg]')
    ph_ax.set_xlabel('frequency [Hz]')
    for ax in (mag_ax, ph_ax):
        ax.grid(True, which='both', alpha=0.3)
    mag_ax.legend(fontsize=8, ncol=3, loc='lower left')
    mag_ax.set_title('Bode: %s, %s in, leg length out\nabout %s'
                     % (_loop_label(model), source, _pose_text(model.equilibrium.pose)),
                     fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# -- workspace --------------------------------------------------------------------------------
#: Colours of the workspace figure, by reason.
REASON_COLORS = {'ok': '#3a9a4a', 'stroke': '#e6e6e6', 'singular': '#c0392b',
                 'max_force': '#f39c12'}


#: Bytes per row of workspace.csv (53.7 measured on the default grid).
CSV_BYTES_PER_ROW = 54
#: A larger workspace.csv needs --large-output [bytes].
CSV_LIMIT = 100e6


def write_workspace(result, out: Path) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    path = out / 'workspace.csv'
    with open(path, 'w', newline='') as fh:
        writer = csv.writer(fh)
        writer.writerow(['x', 'y', 'z', 'reachable', 'reason', 'condition', 'max_force'])
        for p, ok, why, cond, force in zip(result.points, result.reachable, result.reason,
                                           result.condition, result.max_force):
            writer.writerow(['%.6f' % p[0], '%.6f' % p[1], '%.6f' % p[2], int(ok), why,
                             '%.6g' % cond, '%.6g' % force])
    return path


def draw_workspace(setup, result, setpoint, path: Path, title: str) -> Path:
    """Three slices through the setpoint position (z, y and x constant): the top
    row coloured by reason, the bottom row the largest holding force where the
    legs are within the stroke; the paper's start position (o) and the
    setpoint (*) marked. The axes span the points within the stroke."""
    import matplotlib  # lazy: matplotlib costs 425 ms; only a figure needs it
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt  # lazy: pyplot costs 794 ms; only a figure needs it

    # lazy: matplotlib costs 794 ms; only a figure needs it
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    xs, ys, zs = result.axes
    shape = (len(xs), len(ys), len(zs))
    codes = np.array([REASONS.index(r) for r in result.reason]).reshape(shape)
    force = np.where(result.reason == 'stroke', np.nan, result.max_force).reshape(shape)
    cmap = ListedColormap([REASON_COLORS[r] for r in REASONS])
    ix = int(np.argmin(np.abs(xs - setpoint[0])))
    iy = int(np.argmin(np.abs(ys - setpoint[1])))
    iz = int(np.argmin(np.abs(zs - setpoint[2])))
    start = np.asarray(setup.task.initial_position, float)
    setpoint = _clean(setpoint)
    inside = result.points[result.reason != 'stroke']
    margin = 0.15
    span = [(inside[:, a].min() - margin, inside[:, a].max() + margin) if len(inside)
            else (axis[0], axis[-1]) for a, axis in enumerate(result.axes)]
    slices = [
        ('z = %.3f m' % _clean(zs[iz]), xs, ys, (slice(None), slice(None), iz), (0, 1)),
        ('y = %.3f m' % _clean(ys[iy]), xs, zs, (slice(None), iy, slice(None)), (0, 2)),
        ('x = %.3f m' % _clean(xs[ix]), ys, zs, (ix, slice(None), slice(None)), (1, 2)),
    ]
    names = 'xyz'
    fig, axes = plt.subplots(2, 3, figsize=(15, 10))
    image = None
    for col, (label, h, v, index, (a, b)) in enumerate(slices):
        step_h = h[1] - h[0] if len(h) > 1 else 1.0
        step_v = v[1] - v[0] if len(v) > 1 else 1.0
        extent = (h[0] - step_h / 2, h[-1] + step_h / 2, v[0] - step_v / 2, v[-1] + step_v / 2)
        for row, (data, kwargs) in enumerate((
                (codes[index], dict(cmap=cmap, vmin=-0.5, vmax=len(REASONS) - 0.5)),
                (force[index], dict(cmap='viridis', vmin=0.0,
                                    vmax=float(np.nanmax(force)) if np.any(
                                        np.isfinite(force)) else 1.0)))):
            ax = axes[row, col]
            shown = ax.imshow(data.T, origin='lower', extent=extent, interpolation='nearest',
                              aspect='equal', **kwargs)
            if row == 1:
                image = shown
            ax.plot(setpoint[a], setpoint[b], '*', color='#ffd700', markersize=16,
                    markeredgecolor='k', label='setpoint pose (%.3f, %.3f, %.3f) m'
                    % tuple(setpoint))
            ax.plot(start[a], start[b], 'o', color='#1f4e9c', markersize=7,
                    markeredgecolor='w', label="the paper's start t0 (%.3f, %.3f, %.3f) m"
                    % tuple(start))
            ax.set_xlim(*span[a])
            ax.set_ylim(*span[b])
            ax.set_xlabel('%s [m]' % names[a])
            ax.set_ylabel('%s [m]' % names[b])
            ax.set_title(('slice %s' if row == 0 else 'largest holding force, slice %s')
                         % label, fontsize=10)
    fig.subplots_adjust(top=0.86, bottom=0.05, left=0.05, right=0.9, hspace=0.25, wspace=0.25)
    fig.colorbar(image, cax=fig.add_axes((0.92, 0.08, 0.012, 0.33)),
                 label='largest |holding force| [N]')
    handles = [Patch(color=REASON_COLORS[r], label={'ok': 'reachable', 'stroke':
                                                      'outside the stroke',
                                                      'singular': 'near a singularity',
                                                      'max_force': 'beyond max_force'}[r])
               for r in REASONS]
    handles += axes[0, 0].get_legend_handles_labels()[0]
    fig.legend(handles=handles, loc='upper center', ncol=3, fontsize=9,
               bbox_to_anchor=(0.5, 0.955))
    fig.suptitle(title, fontsize=11)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


# -- main -------------------------------------------------------------------------------------
def _run(args, setup, params_path) -> int:
    mech = setup.mechanism
    out = Path(args.out) if getattr(args, 'out', None) else None
    if args.command == 'workspace':
        step = DEFAULT_STEP if args.step is None else args.step
        if not (np.isfinite(step) and step > 0):
            return _fail('--step must be a positive length [m], got %g' % step)
        position, rotation = equilibrium.setpoint_pose(setup)
        if args.orientation is not None:
            if not np.all(np.isfinite(args.orientation)):
                return _fail('--orientation must be three finite angles [rad]')
            rotation = rotation_from_euler(args.orientation)
        limit = args.max_condition or equilibrium.DEFAULT_MAX_CONDITION
        # Sizes first, before anything is made: memory, then the CSV.
        points = int(np.prod([len(a) for a in grid_axes(mech, step, through=position)],
                             dtype=float))
        try:
            check_grid_fits(points)
        except GridTooLarge as exc:
            return _fail('--step %g: %s' % (step, exc))
        csv_size = points * CSV_BYTES_PER_ROW
        if csv_size > CSV_LIMIT and not args.large_output:
            return _fail('--step %g: workspace.csv would have %d rows, about %s; pass '
                         '--large-output to write it, or use a larger --step'
                         % (step, points, human_bytes(csv_size)))
        print('grid of %d points (step %g m): workspace.csv about %s' % (
            points, step, human_bytes(csv_size)), flush=True)
        result = workspace_map(mech, rotation, step, limit, through=position)
        csv_path = write_workspace(result, out)
        theta = euler_from_matrix(rotation)
        png = draw_workspace(setup, result, position, out / 'workspace.png',
                             'workspace at theta = (%.3f, %.3f, %.3f) rad, step %g m: within '
                             'the stroke [%g, %g] m, condition <= %g, holding force <= %g N'
                             % (*_clean(theta), step, mech.leg_length_min,
                                mech.leg_length_max, limit, mech.max_force))
        counts = {r: int(np.sum(result.reason == r)) for r in ('ok', 'stroke', 'singular',
                                                               'max_force')}
        reach = result.points[result.reachable]
        print('reachable %d, outside the stroke %d, near a singularity %d, beyond '
              'max_force %d' % (counts['ok'], counts['stroke'],
                 counts['singular'], counts['max_force']))
        if len(reach):
            print('reachable: x %.3f..%.3f m, y %.3f..%.3f m, z %.3f..%.3f m; condition '
                  'up to %.3g, holding force up to %.1f N'
                  % (reach[:, 0].min(), reach[:, 0].max(), reach[:, 1].min(),
                     reach[:, 1].max(), reach[:, 2].min(), reach[:, 2].max(),
                     result.condition[result.reachable].max(),
                     result.max_force[result.reachable].max()))
        print('written: %s, %s' % (csv_path, png))
        return 0

    model = linear_model(setup, args, params_path)
    if args.command == 'linearize':
        npz, js = write_linear(model, out)
        print('%s about %s' % (_loop_label(model), _pose_text(model.equilibrium.pose)))
        print('holding forces %s N' % np.array2string(model.equilibrium.forces, precision=3))
        print('u0 %s %s' % (np.array2string(model.u0, precision=6),
                            'm (leg-length references)' if model.closed_loop else 'N'))
        print('written: %s, %s' % (npz, js))
        return 0
    if args.command == 'modes':
        found = modal.modes(model)
        if args.json:
            print(json.dumps(found.to_json()))
        else:
            print_modes(model, found)
        return 0
    # freqresp
    if not (np.isfinite(args.fmin) and np.isfinite(args.fmax) and 0 < args.fmin < args.fmax):
        return _fail('--fmin and --fmax must satisfy 0 < fmin < fmax, got %g, %g'
                     % (args.fmin, args.fmax))
    if args.points < 2:
        return _fail('--points must be at least 2, got %d' % args.points)
    freqs = np.logspace(np.log10(args.fmin), np.log10(args.fmax), args.points)
    response = modal.frequency_response(model, freqs)
    csv_path = write_freqresp(model, freqs, response, out)
    png = draw_bode(model, freqs, response, out / 'bode.png')
    dc = np.abs(response[0])
    print('%s about %s' % (_loop_label(model), _pose_text(model.equilibrium.pose)))
    print('|G| at %g Hz, diagonal: %s %s' % (freqs[0], np.array2string(np.diag(dc),
                                                                        precision=4),
                                             'm/m' if model.closed_loop else 'm/N'))
    print('written: %s (%d rows: %s x 6 inputs x 6 outputs), %s'
          % (csv_path, 36 * len(freqs), len(freqs), png))
    return 0


@quiet_on_closed_pipe
def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.max_condition is not None and not args.max_condition > 1:
        return _fail('--max-condition must be above 1, got %g' % args.max_condition)
    params_path = args.params or default_params_path()
    setup = load_checked(PROG, params_path, node_name='plant', strict=args.strict)
    if setup is None:
        return 2
    announce_compile(PROG)
    try:
        return _run(args, setup, params_path)
    except (AnalysisError, ParameterError) as exc:
        return _fail(exc)


if __name__ == '__main__':
    sys.exit(main())
