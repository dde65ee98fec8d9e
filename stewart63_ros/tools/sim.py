"""`sim`: the paper's scenario offline, in one process, without DDS.

    sim --params FILE --duration S --out DIR [--control continuous|sampled] [--rate HZ]

Writes DIR/trajectory.csv (docs/interface.md) and DIR/figure.png (Fig. 4),
prints the final leg-length errors and the positioning error in %.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from stewart63_ros.core.params import ParameterError, default_params_path, load_mechanism


def summarize(mech, dyn, result) -> dict:
    """Final errors of a run, as printed by `sim` and the rig's summary."""
    errors = result.final_leg_error_percent(dyn, mech.setpoint_lengths)
    lengths, _ = dyn.lengths_and_rates(result.states[-1])
    return {
        'final_time_s': float(result.times[-1]),
        'final_leg_lengths_m': [round(float(v), 6) for v in lengths],
        'final_leg_errors_percent': [round(float(v), 4) for v in errors],
        'positioning_error_percent': round(float(errors.max()), 4),
        'endstop_samples': int(result.endstop_samples),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='sim', description=__doc__.split('\n\n')[0])
    parser.add_argument('--params', default=None,
                        help='ROS 2 parameter file (default: the packaged config/stewart63.yaml)')
    parser.add_argument('--duration', type=float, default=10.0, help='simulated time [s] (10)')
    parser.add_argument('--out', required=True, help='output directory')
    parser.add_argument('--control', choices=('continuous', 'sampled'), default='continuous',
                        help='PD inside the ODE (RK45, as the paper) or sampled and held')
    parser.add_argument('--rate', type=float, default=None,
                        help='sample rate [Hz]: control rate for sampled (default: the '
                        "plant's sensor_rate), CSV rate for continuous (default 100, "
                        "the paper's h)")
    parser.add_argument('--no-figure', action='store_true', help='skip figure.png')
    args = parser.parse_args(argv)
    if not (np.isfinite(args.duration) and args.duration > 0):
        parser.error('--duration must be a positive number of seconds')
    if args.rate is not None and not (np.isfinite(args.rate) and args.rate > 0):
        parser.error('--rate must be a positive number of Hz')

    params_path = args.params or default_params_path()
    try:
        mech = load_mechanism(params_path, node_name='plant')
    except ParameterError as exc:
        print('sim: error: %s: %s' % (params_path, exc), file=sys.stderr)
        return 2

    from stewart63_ros.core.dynamics import Dynamics
    from stewart63_ros.core.simulate import run_continuous, run_sampled
    from stewart63_ros.core.trajectory import write_csv

    dyn = Dynamics(mech)
    start = time.perf_counter()
    if args.control == 'sampled':
        rate = args.rate or float(mech.extra.get('sensor_rate', 1000.0))
        result = run_sampled(mech, args.duration, rate, dyn=dyn)
    else:
        rate = args.rate or 100.0
        result = run_continuous(mech, args.duration, output_rate=rate, dyn=dyn)
    wall = time.perf_counter() - start
    if not np.all(np.isfinite(result.states)):
        print('sim: error: the simulation diverged (non-finite state)', file=sys.stderr)
        return 3

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    table = result.table(dyn)
    write_csv(out / 'trajectory.csv', table)
    if not args.no_figure:
        from stewart63_ros.core.trajectory import COLUMNS
        from stewart63_ros.tools.plot import draw_figure
        draw_figure({name: table[:, i] for i, name in enumerate(COLUMNS)}, out / 'figure.png',
                    title='sim, %s control, %g Hz' % (args.control, rate))
    summary = summarize(mech, dyn, result)
    summary.update(control=args.control, rate_hz=rate, wall_time_s=round(wall, 4),
                   csv=str(out / 'trajectory.csv'))
    if summary['endstop_samples']:
        print('sim: warning: a leg met an end stop in %d samples' % summary['endstop_samples'],
              file=sys.stderr)
    for key, value in summary.items():
        print('%-28s %s' % (key, json.dumps(value)))
    return 0


if __name__ == '__main__':
    sys.exit(main())
