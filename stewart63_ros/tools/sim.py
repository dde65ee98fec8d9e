"""`sim`: the paper's scenario offline, in one process, without DDS.

    sim --params FILE --duration S --out DIR [--control continuous|sampled] [--rate HZ]
        [--control-law NAME] [--reference CSV] [--fault KIND:LEG[:VALUE][@T0[-T1]]]...

Writes DIR/trajectory.csv (docs/interface.md) and DIR/figure.png (Fig. 4),
prints the final leg-length errors and the positioning error in %. With
--reference, the reference motion is followed from t = 0, DIR/reference.csv
holds it at the output times, the figure draws it against the actual motion,
and the tracking error (max and RMS after the first second) is printed.
With faults (--fault, repeatable, and the plant's ``faults`` in the
parameter file; docs/faults.md) the control is sampled (at the plant's
sensor_rate unless --rate says otherwise; --control continuous is refused),
each fault's interval is printed and written to DIR/faults.json, and the
figure shades it.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from stewart63_ros.core.controllers.laws import Controller, LawError
from stewart63_ros.core.controllers.reference import CSV_COLUMNS, ReferenceError
from stewart63_ros.core.controllers.reference_files import load_reference, write_reference_csv
from stewart63_ros.core.controllers.simulate import run_continuous, run_sampled
from stewart63_ros.core.controllers.tracking import tracking_errors
from stewart63_ros.core.machine.faults import FaultError, FaultModel, parse_fault, parse_faults
from stewart63_ros.core.mechanics.assembly import crossings
from stewart63_ros.core.mechanics.dynamics import Dynamics
from stewart63_ros.core.plumbing.node_parameters import read as read_declared
from stewart63_ros.core.plumbing.params import (
    ParameterError,
    default_params_path,
    load_setup,
    read_parameter_file,
)
from stewart63_ros.core.plumbing.trajectory import COLUMNS, write_csv
from stewart63_ros.tools.cli import (
    STRICT_HELP,
    add_control_options,
    announce_compile,
    load_checked,
    quiet_on_closed_pipe,
)
from stewart63_ros.tools.plot import draw_figure


def summarize(setup, dyn, result) -> dict:
    """Final errors of a run, as printed by `sim` and the rig's summary."""
    errors = result.final_leg_error_percent(dyn, setup.task.setpoint_lengths)
    lengths, _ = dyn.lengths_and_rates(result.states[-1])
    return {
        'final_time_s': float(result.times[-1]),
        'final_leg_lengths_m': [round(float(v), 6) for v in lengths],
        'final_leg_errors_percent': [round(float(v), 4) for v in errors],
        'positioning_error_percent': round(float(errors.max()), 4),
        'endstop_samples': int(result.endstop_samples),
    }


def format_tracking(err: dict) -> str:
    """The tracking-error lines `sim` and `rig` print."""
    if not err.get('samples'):
        return 'tracking error: the run is shorter than its first second'
    return ('tracking error after %gs (%d samples): leg length max %.3e m, RMS %.3e m; '
            'position max %.3e m, RMS %.3e m; orientation max %.3e rad, RMS %.3e rad' % (
                err['from_s'], err['samples'], err['leg_max_m'], err['leg_rms_m'],
                err['position_max_m'], err['position_rms_m'], err['orientation_max_rad'],
                err['orientation_rms_rad']))


def fault_list(params_path, extra=()) -> list:
    """The plant's ``faults`` of the parameter file, then ``extra`` (--fault),
    parsed (FaultError naming the first bad one). A blank ``--fault`` is
    refused: the file's ``['']`` stands for no faults, an option for one."""
    for text in extra:
        parse_fault(text)
    listed = read_parameter_file(params_path, 'plant').get('faults') or []
    if isinstance(listed, str):
        listed = [listed]
    if not isinstance(listed, list):
        raise FaultError('faults in %s: expected a list of strings, got %r'
                         % (params_path, listed))
    return parse_faults([f.text for f in parse_faults(listed)] + list(extra))


def format_fault(fault: dict) -> str:
    """One line per fault, as `sim` and `rig` print them."""
    if fault['active_from_s'] is None:
        when = 'never active' + (' (removed)' if fault['state'] == 'removed' else '')
    elif fault['active_until_s'] is None:
        when = 'active from %.4f s to the end' % fault['active_from_s']
    else:
        when = 'active %.4f-%.4f s' % (fault['active_from_s'], fault['active_until_s'])
    run = ' (run %d)' % fault['run'] if fault.get('run', 1) != 1 else ''
    return 'fault %-34s %s%s' % (fault['fault'], when, run)


def make_controller(params_path, law=None, reference_csv=None):
    """(controller, reference) for a run: a ``Controller`` with the law (``law`` or
    the controller's ``control_law`` in the file) and the reference CSV (None:
    hold the setpoint, eq. (40) towards fixed lengths runs compiled, as
    ``Controller.pd_gains`` says). Raises ParameterError or ReferenceError."""
    params = read_parameter_file(params_path, 'controller')
    setup = load_setup(params_path, node_name='controller')
    law = law or read_declared(params, 'control_law')
    reference = None
    if reference_csv is not None:
        reference = load_reference(setup.mechanism, reference_csv,
                                   read_declared(params, 'max_leg_speed'),
                                   read_declared(params, 'max_leg_acceleration'))
    return Controller(setup, params, law=law, reference=reference), reference


@quiet_on_closed_pipe
def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='sim', description=__doc__.split('\n\n')[0])
    parser.add_argument('--params', default=None,
                        help='ROS 2 parameter file (default: the packaged config/stewart63.yaml)')
    parser.add_argument('--duration', type=float, default=10.0, help='simulated time [s] (10)')
    parser.add_argument('--out', required=True, help='output directory')
    add_control_options(parser)
    parser.add_argument('--control-law', default=None, metavar='NAME',
                        help='pd (eq. 40), pd_gravity, computed_torque or package.module:Class '
                        "(default: the controller's control_law in the parameter file, else pd)")
    parser.add_argument('--reference', default=None, metavar='CSV',
                        help='reference motion t,x,y,z,theta_x,theta_y,theta_z to follow')
    parser.add_argument('--fault', action='append', default=[], metavar='FAULT',
                        help='inject a fault KIND:LEG[:VALUE][@T_START[-T_END]], e.g. '
                        'sensor_stuck:leg_2@1.0 (repeatable; added to the plant\'s faults of '
                        'the parameter file; docs/faults.md)')
    parser.add_argument('--no-figure', action='store_true', help='skip figure.png')
    parser.add_argument('--strict', action='store_true', help=STRICT_HELP)
    args = parser.parse_args(argv)
    if not (np.isfinite(args.duration) and args.duration > 0):
        parser.error('--duration must be a positive number of seconds')
    if args.rate is not None and not (np.isfinite(args.rate) and args.rate > 0):
        parser.error('--rate must be a positive number of Hz')

    params_path = args.params or default_params_path()
    setup = load_checked('sim', params_path, node_name='plant', strict=args.strict)
    if setup is None:
        return 2
    mech = setup.mechanism
    try:
        controller, reference = make_controller(params_path, args.control_law, args.reference)
    except (ParameterError, ReferenceError) as exc:
        print('sim: error: %s' % (exc,), file=sys.stderr)
        return 2
    try:
        faults = fault_list(params_path, args.fault)
        bus = [f.text for f in faults if f.bus]
        if bus:
            raise FaultError('fault %r acts on the field bus: it needs the plant on the bus '
                             '(rig --bus canopen, docs/bus.md), not sim' % bus[0])
    except FaultError as exc:
        print('sim: error: %s' % (exc,), file=sys.stderr)
        return 2
    if faults:
        if args.control == 'continuous':
            print('sim: error: faults act on the sensor samples: use --control sampled '
                  '(the default with faults)', file=sys.stderr)
            return 2
        args.control = 'sampled'
    args.control = args.control or 'continuous'

    announce_compile('sim')

    dyn = Dynamics(mech)
    start = time.perf_counter()
    try:
        if args.control == 'sampled':
            rate = args.rate or setup.setting('sensor_rate')
            model = None
            if faults:
                model = FaultModel(faults, rate, setup.setting('sensor_seed'))
            result = run_sampled(setup, args.duration, rate, dyn=dyn, controller=controller,
                                 faults=model)
        else:
            rate = args.rate or 100.0
            result = run_continuous(setup, args.duration, output_rate=rate, dyn=dyn,
                                    controller=controller)
    except LawError as exc:
        print('sim: error: the control law failed: %s' % exc, file=sys.stderr)
        return 3
    wall = time.perf_counter() - start
    if not np.all(np.isfinite(result.states)):
        print('sim: error: the simulation diverged (non-finite state)', file=sys.stderr)
        return 3

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    table = result.table(dyn)
    write_csv(out / 'trajectory.csv', table)
    ref_columns = None
    if reference is not None:
        poses = reference.poses(result.times)
        write_reference_csv(out / 'reference.csv', result.times, poses)
        ref_columns = dict(zip(CSV_COLUMNS, np.column_stack([result.times, poses]).T))
    law = controller.law_name
    if result.faults is not None:
        (out / 'faults.json').write_text(json.dumps(result.faults, indent=1))
    if not args.no_figure:
        draw_figure({name: table[:, i] for i, name in enumerate(COLUMNS)}, out / 'figure.png',
                    title='sim %s: %s, %s control, %g Hz, %g s, %s' % (
                        out, law, args.control, rate, args.duration,
                        Path(args.params).name if args.params else 'packaged parameters'),
                    reference=ref_columns, setpoint=setup.task.setpoint_lengths,
                    faults=result.faults)
    summary = summarize(setup, dyn, result)
    summary.update(control=args.control, control_law=law, rate_hz=rate,
                   wall_time_s=round(wall, 4), csv=str(out / 'trajectory.csv'))
    if not args.no_figure:
        summary['figure'] = str(out / 'figure.png')
    if result.faults is not None:
        summary['faults'] = str(out / 'faults.json')
    if reference is not None:
        summary['tracking_error'] = {k: (round(v, 9) if isinstance(v, float) else v) for k, v in
                                     tracking_errors(mech, reference, result.times,
                                                     result.states).items()}
    # the platform through a singular pose into another assembly mode: an ERROR
    crossed = crossings(*dyn.kernel_args()[1:3], result.states, rate)
    if crossed:
        summary['assembly_crossings'] = len(crossed)
    for note in crossed:
        print('sim: error: %s' % note, file=sys.stderr)
    if summary['endstop_samples']:
        print('sim: warning: a leg met an end stop in %d samples' % summary['endstop_samples'],
              file=sys.stderr)
    for key, value in summary.items():
        if key == 'tracking_error':
            continue
        print('%-28s %s' % (key, json.dumps(value)))
    if 'tracking_error' in summary:
        print(format_tracking(summary['tracking_error']))
    for fault in result.faults or ():
        print(format_fault(fault))
    return 0


if __name__ == '__main__':
    sys.exit(main())
