"""`sweep`: N runs of the `sim` scenario with parameters drawn from ranges, in parallel.

    sweep --runs N [--vary KEY=LO:HI]... [--fault PATTERN]... [--grid] [--seed S]
          [--control continuous|sampled] [--rate HZ] [--control-law NAME]
          [--duration T] [--params F] [--out DIR] [--workers W]
          [--scheduler ADDRESS | --dask-local W]

Each run is `sim`'s run of the parameter file with the varied keys set (a
scalar ``KEY`` or one list element ``KEY[i]`` as written in the file, of the
keys the runs read), drawn uniformly from [LO, HI] (``--seed``) or, with
``--grid``, on an evenly spaced grid; and with the faults of ``--fault``
(sim's fault syntax, any number drawn per run: ``U(lo,hi)``, ``{a..b}``,
``{a,b,c}``; e.g. ``actuator_dead:leg_{1..6}@U(1,5)``), under sampled control
as `sim` runs faults. Writes DIR/runs.csv (one row per run; varied keys as
``param.KEY``), DIR/summary.json (percentiles per column) and DIR/sweep.png;
prints the percentiles and the wall time of the runs. Local processes by
default, or a Dask cluster (docs/analysis.md). Bad input (an unknown key, a
key the runs do not read, a range a parameter's validation refuses, --runs
0): one line on stderr, exit status 2. A run that diverges or whose law
raises is marked in ``diverged``, not fatal.
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from pathlib import Path

import numpy as np

from stewart63_ros.core.plumbing.params import ParameterError, default_params_path
from stewart63_ros.tools.cli import (
    STRICT_HELP,
    add_control_options,
    announce_compile,
    load_checked,
    quiet_on_closed_pipe,
)

PROG = 'sweep'


def _fail(message) -> int:
    print('%s: error: %s' % (PROG, message), file=sys.stderr)
    return 2


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split('\n\n')[0])
    parser.add_argument('--runs', type=int, required=True, help='number of runs (>= 1)')
    parser.add_argument('--vary', action='append', default=[], metavar='KEY=LO:HI',
                        help='a parameter to vary over [LO, HI]: a scalar key or one list '
                        'element KEY[i] (repeatable)')
    parser.add_argument('--fault', action='append', default=[], metavar='PATTERN',
                        help="a fault in every run, sim's KIND:LEG[:VALUE][@T0[-T1]] where "
                        'any number may be drawn per run: U(lo,hi), {a..b}, {a,b,c}; e.g. '
                        "'actuator_dead:leg_{1..6}@U(1,5)' (repeatable; sampled control)")
    add_control_options(parser)
    parser.add_argument('--grid', action='store_true',
                        help='an even grid instead of uniform draws: every choice of a '
                        '{...} and round((N/choices)^(1/K)) values of each other range, '
                        'every combination')
    parser.add_argument('--seed', type=int, default=None,
                        help='seed of the uniform draws (default: fresh entropy; printed)')
    parser.add_argument('--control-law', default=None, metavar='NAME',
                        help="pd (eq. 40, compiled), pd_gravity, computed_torque or "
                        "package.module:Class (default: the controller's control_law in "
                        'the file, else pd)')
    parser.add_argument('--duration', type=float, default=10.0,
                        help='simulated time per run [s] (10)')
    parser.add_argument('--params', default=None,
                        help='ROS 2 parameter file (default: the packaged config/stewart63.yaml)')
    parser.add_argument('--out', default='out/sweep', help='output directory (out/sweep)')
    parser.add_argument('--workers', type=int, default=None,
                        help='local worker processes (default: one per core)')
    engine = parser.add_mutually_exclusive_group()
    engine.add_argument('--scheduler', default=None, metavar='ADDRESS',
                        help='run on the Dask cluster of this scheduler (tcp://host:8786)')
    engine.add_argument('--dask-local', type=int, default=None, metavar='W',
                        help='run on a Dask LocalCluster of W worker processes started here')
    parser.add_argument('--no-figure', action='store_true', help='skip sweep.png')
    parser.add_argument('--strict', action='store_true', help=STRICT_HELP)
    return parser


def _cell(value) -> str:
    if isinstance(value, float):
        return 'nan' if math.isnan(value) else repr(value)    # exact: reruns match
    return str(value)


def write_runs(path: Path, names, rows) -> None:
    with open(path, 'w', newline='') as fh:
        writer = csv.writer(fh)
        writer.writerow(names)
        for row in rows:
            writer.writerow([_cell(row[name]) for name in names])


def draw_sweep(plan, rows, path: Path, title: str) -> Path:
    """Histograms of the final error, largest force and settling time; the final
    error against each varied key (diverged runs as red crosses on the axis)."""
    import matplotlib  # lazy: matplotlib costs 425 ms; only a figure needs it
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt  # lazy: pyplot costs 794 ms; only a figure needs it
    done = [r for r in rows if not r['diverged']]
    failed = [r for r in rows if r['diverged']]
    metrics = (('final_error_percent', 'final leg error [%]'), ('max_force', 'largest |F| [N]'),
               ('settling_time_s', '2 % settling time [s]'))
    keys = [a.column for a in plan.axes]
    cols = 3
    nrows = 1 + math.ceil(len(keys) / cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(13, 3.6 * nrows), squeeze=False)
    for ax, (name, label) in zip(axes[0], metrics):
        data = np.array([r[name] for r in done], dtype=float)
        data = data[np.isfinite(data)]
        if data.size:
            ax.hist(data, bins=min(40, max(5, int(np.sqrt(data.size)))), color='#4c72b0')
        ax.set_xlabel(label)
        ax.set_ylabel('runs')
        ax.grid(True, alpha=0.3)
    for k, key in enumerate(keys):
        ax = axes[1 + k // cols, k % cols]
        x = np.array([r[key] for r in done], dtype=float)
        y = np.array([r['final_error_percent'] for r in done], dtype=float)
        ax.plot(x, y, '.', markersize=3, color='#4c72b0', label='finished')
        if failed:
            ax.plot([r[key] for r in failed], [0.0] * len(failed), 'x', color='#c0392b',
                    label='diverged (%d)' % len(failed))
            ax.legend(fontsize=8)
        ax.set_xlabel(key)
        ax.set_ylabel('final leg error [%]')
        ax.grid(True, alpha=0.3)
    for k in range(len(keys), (nrows - 1) * cols):
        axes[1 + k // cols, k % cols].axis('off')
    fig.suptitle(title, fontsize=11)
    fig.tight_layout(rect=(0, 0, 1, 0.96))
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


@quiet_on_closed_pipe
def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    # lazy: core.analysis.sweep costs 692 ms (scipy.optimize); --help answers
    from stewart63_ros.core.analysis import sweep, sweep_plan, sweep_report
    if args.runs < 1:
        return _fail('--runs must be at least 1, got %d' % args.runs)
    if not (np.isfinite(args.duration) and args.duration > 0):
        return _fail('--duration must be a positive number of seconds, got %g' % args.duration)
    if args.workers is not None and args.workers < 1:
        return _fail('--workers must be at least 1, got %d' % args.workers)
    if args.dask_local is not None and args.dask_local < 1:
        return _fail('--dask-local must be at least 1 worker, got %d' % args.dask_local)
    if args.scheduler or args.dask_local:
        try:
            # lazy: optional: distributed costs 543 ms; only --scheduler
            import distributed  # noqa: F401
        except ImportError:
            return _fail('--scheduler and --dask-local need Dask: pip install dask distributed')
    params_path = args.params or default_params_path()
    if load_checked(PROG, params_path, node_name='plant', strict=args.strict) is None:
        return 2
    try:
        if args.scheduler:
            sweep.check_scheduler_address(args.scheduler)
        variations = [sweep_plan.parse_vary(text) for text in args.vary]
        patterns = [sweep_plan.parse_fault_pattern(text, n + 1)
                    for n, text in enumerate(args.fault)]
        plan = sweep_plan.make_plan(params_path, variations, args.control_law, args.duration,
                                    patterns, args.control, args.rate)
    except (sweep_plan.SweepError, ParameterError) as exc:
        return _fail(exc)
    seed = args.seed if args.seed is not None else int(np.random.SeedSequence().entropy % 2**32)
    values = sweep_plan.draw_values(plan.axes, args.runs, seed, args.grid)
    if args.grid and len(values) != args.runs:
        print('%s: note: the grid gives %d runs (%s values per axis)' % (
            PROG, len(values), ' x '.join(str(len(np.unique(values[:, j])))
                                          for j in range(values.shape[1])) or 'no'),
            file=sys.stderr)

    announce_compile(PROG)
    try:
        outcome = sweep.run_sweep(plan, values, args.workers, args.scheduler, args.dask_local)
    except OSError as exc:          # a scheduler that cannot be reached
        return _fail('Dask scheduler %s: %s' % (args.scheduler, exc))
    except sweep_plan.SweepError as exc:  # the cluster lost runs
        print('%s: error: %s' % (PROG, exc), file=sys.stderr)
        return 1
    rows = outcome['rows']
    wall = outcome['wall_time_s']

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    names = sweep_report.columns(plan)
    write_runs(out / 'runs.csv', names, rows)
    stats = sweep_report.summary(plan, rows)
    doc = {'runs': len(rows), 'diverged_runs': stats['diverged']['count'],
           'control_law': plan.law, 'duration_s': plan.duration, 'control': plan.control,
           'output_rate_hz': plan.output_rate if plan.control == 'continuous' else None,
           'control_rate_hz': plan.rate if plan.control == 'sampled' else None,
           'seed': None if args.grid else seed,
           'grid': bool(args.grid), 'params': str(params_path),
           'varied': {v.column: [v.low, v.high] for v in plan.variations},
           'faults': [p.text for p in plan.faults],
           'engine': outcome['engine'], 'workers': outcome['workers'],
           'workers_at_start': outcome['workers_at_start'],
           'workers_lost': outcome['workers_lost'],
           'wall_time_s': round(wall, 4), 'columns': stats}
    (out / 'summary.json').write_text(json.dumps(doc, indent=1) + '\n')
    if not args.no_figure:
        draw_sweep(plan, rows, out / 'sweep.png',
                   'sweep: %d runs of %g s, %s law, %s control, %s' % (
                       len(rows), plan.duration, plan.law, plan.control,
                       ', '.join(['%s in [%g, %g]' % (v.key, v.low, v.high)
                                  for v in plan.variations]
                                 + [p.text for p in plan.faults]) or 'nothing varied'))

    print('%-22s %10s %10s %10s %10s %10s' % ('column', 'p5', 'p50', 'p95', 'max', 'count'))
    for key, st in stats.items():
        if key == 'diverged':
            continue
        if st['count']:
            print('%-22s %10.4g %10.4g %10.4g %10.4g %10d' % (key, st['p5'], st['p50'],
                                                              st['p95'], st['p100'],
                                                              st['count']))
        else:
            print('%-22s %10s %10s %10s %10s %10d' % (key, '-', '-', '-', '-', 0))
    print('diverged runs          %d' % stats['diverged']['count'])
    lost = outcome['workers_lost']
    print('%s: %d runs in %.2f s wall (%s, %d worker%s%s, %.0f runs/s); seed %s'
          % (PROG, len(rows), wall, outcome['engine'], outcome['workers'],
             '' if outcome['workers'] == 1 else 's',
             '; %d of the %d at the start lost mid-sweep, their runs done again'
             % (lost, outcome['workers_at_start']) if lost else '',
             len(rows) / wall if wall > 0 else float('inf'),
             'none (grid)' if args.grid else seed))
    print('written: %s, %s%s' % (out / 'runs.csv', out / 'summary.json',
                                 '' if args.no_figure else ', %s' % (out / 'sweep.png')))
    return 0


if __name__ == '__main__':
    sys.exit(main())
