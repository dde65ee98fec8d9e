"""`calibrate`: identify the machine's geometry and sensor offsets; plan the poses.

    calibrate plan --params P --poses N --out DIR [--seed S] [--hold S] [--move S]
        [--leg-speed V] [--candidates K] [--tolerance POINTS OFFSETS] [--machines N]
        [--tracker-noise POS ANG] [--geometry G]
    calibrate fit --measurements F --params P --out DIR [--holdout SHARE]
        [--tolerance M] [--tracker-noise POS ANG] [--reading-noise M]
        [--tracker-topic T] [--stamp-tolerance S] [--still V] [--geometry G]
    calibrate machine --params P --out FILE [--seed S] [--points M] [--offsets M]
        [--geometry G]

``--geometry 6-6`` on a 6-3's file identifies six platform joints (its
pairs allowed to come apart: 42 parameters instead of 33) and writes 18
numbers; the default is the file's own layout.

``plan`` flies its reference in simulation on machines off the drawing
(core/machine/calibration_flight.py), strikes the poses where one fails, and
writes DIR/poses.csv (the poses, and when the reference holds each),
DIR/reference.csv (``t,x,y,z,theta_x,theta_y,theta_z`` for ``rig
--reference``) and DIR/plan.json (the observability indices O1 and O3, the
flights, the poses struck).
``fit`` reads a measurements CSV (``x,y,z,qx,qy,qz,qw,L1..L6``) or a bag
(a ``geometry_msgs/PoseStamped`` tracker topic and ``leg_lengths``, matched
by stamp) and writes DIR/calibrated.yaml (the starting file with the
identified ``base_points``, ``platform_points`` and ``leg_length_offset``)
and DIR/report.json. ``machine`` writes a parameter file of a machine built
off its drawing (for the simulation: ``rig --plant-params``). Bad input: one
line on stderr, exit 2. docs/calibration.md.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import sys
import time
from pathlib import Path

# One BLAS thread, set before numpy loads it: the fit's tall SVDs (thousands
# of readings by 33) took 1.4 s each with two threads on this shared two-core
# machine under load, and 0.04 s with one (measured 2026-11-25).
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

import numpy as np  # noqa: E402
import yaml

from stewart63_ros import bagio
from stewart63_ros.core.controllers.reference import Reference, ReferenceError
from stewart63_ros.core.controllers.reference_files import write_reference_csv
from stewart63_ros.core.controllers.sensor import TrackerModel
from stewart63_ros.core.machine import calibration as cal
from stewart63_ros.core.machine import calibration_flight as flight
from stewart63_ros.core.machine import calibration_model as cal_model
from stewart63_ros.core.machine import calibration_plan as cp
from stewart63_ros.core.machine.supervisor import limits_from_params
from stewart63_ros.core.mechanics.rotation import euler_from_matrix
from stewart63_ros.core.plumbing.node_parameters import read as read_declared
from stewart63_ros.core.plumbing.params import (  # noqa: E402
    ParameterError,
    default_params_path,
    load_mechanism,
    read_parameter_file,
)
from stewart63_ros.tools.cli import (
    load_checked,
    quiet_on_closed_pipe,  # noqa: E402
)

PROG = 'calibrate'
MEASUREMENT_COLUMNS = ('x', 'y', 'z', 'qx', 'qy', 'qz', 'qw', 'L1', 'L2', 'L3', 'L4', 'L5', 'L6')
POSE_COLUMNS = ('pose', 'x', 'y', 'z', 'theta_x', 'theta_y', 'theta_z', 'hold_from_s',
                'hold_to_s')
#: Keys ``fit`` writes into the calibrated file.
CALIBRATED_KEYS = ('base_points', 'platform_points', 'leg_length_offset')


class InputError(ValueError):
    """Bad input: one line, exit 2."""


def _fail(message) -> int:
    print('%s: error: %s' % (PROG, message), file=sys.stderr)
    return 2


# -- reading measurements ------------------------------------------------------
def read_measurements_csv(path: Path):
    """The measurements of a CSV with the columns ``MEASUREMENT_COLUMNS``."""
    try:
        with open(path, newline='') as stream:
            rows = [r for r in csv.reader(stream) if r and any(c.strip() for c in r)]
    except OSError as exc:
        raise InputError('cannot read %s: %s' % (path, exc.strerror)) from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise InputError('%s is not a measurements CSV: %s' % (path, exc)) from None
    if not rows or tuple(c.strip() for c in rows[0]) != MEASUREMENT_COLUMNS:
        raise InputError('%s: the header must be %s' % (path, ','.join(MEASUREMENT_COLUMNS)))
    table = np.empty((len(rows) - 1, len(MEASUREMENT_COLUMNS)))
    for n, row in enumerate(rows[1:]):
        if len(row) != len(MEASUREMENT_COLUMNS):
            raise InputError('%s: row %d has %d values, not %d' % (
                path, n + 1, len(row), len(MEASUREMENT_COLUMNS)))
        try:
            table[n] = [float(c) for c in row]
        except ValueError:
            raise InputError('%s: row %d: not a number in %s' % (path, n + 1, row)) from None
    try:
        return cal_model.measurements(table[:, 0:3], table[:, 3:7], table[:, 7:13])
    except cal_model.CalibrationError as exc:
        raise InputError('%s: %s' % (path, exc)) from None


def read_measurements_bag(path: Path, tracker_topic: str, tolerance: float, still: float):
    """Tracker poses matched by stamp to ``leg_lengths`` samples, from a bag.

    Every tracker sample takes the leg_lengths sample nearest in stamp; more
    than 1 % of them without one within ``tolerance`` seconds: refused (the
    two clocks do not agree). With ``still`` > 0 only samples where every
    leg moves slower than ``still`` m/s are kept (a real tracker and real
    sensors are not sampled at one instant).
    """
    poses, lengths = {}, {}
    try:
        for topic, _, msg in bagio.read_messages(path, [tracker_topic, 'leg_lengths']):
            ns = bagio.header_stamp_ns(msg)
            if topic.endswith('leg_lengths'):
                lengths[ns] = (np.asarray(msg.position, float), np.asarray(msg.velocity, float))
            else:
                p, o = msg.pose.position, msg.pose.orientation
                poses[ns] = [p.x, p.y, p.z, o.x, o.y, o.z, o.w]
    except bagio.BagError as exc:
        raise InputError(str(exc)) from None
    if not poses or not lengths:
        raise InputError('%s: no %s samples' % (path, 'tracker' if not poses else 'leg_lengths'))
    leg_stamps = np.array(sorted(lengths))
    rows, off = [], []
    for ns in sorted(poses):
        j = int(np.clip(np.searchsorted(leg_stamps, ns), 1, len(leg_stamps) - 1))
        near = leg_stamps[j - 1] if abs(leg_stamps[j - 1] - ns) <= abs(
            leg_stamps[j] - ns) or len(leg_stamps) == 1 else leg_stamps[j]
        if len(leg_stamps) == 1:
            near = leg_stamps[0]
        gap = abs(int(near) - ns) * 1e-9
        if gap > tolerance:
            off.append(gap)
            continue
        position, velocity = lengths[int(near)]
        if position.size != 6:
            raise InputError('%s: a leg_lengths sample holds %d positions, not 6'
                             % (path, position.size))
        if still > 0 and (velocity.size != 6 or np.max(np.abs(velocity)) > still):
            continue
        rows.append(poses[ns] + position.tolist())
    if len(off) > 0.01 * len(poses):
        raise InputError('%s: %d of %d tracker samples have no leg_lengths sample within '
                         '%g s (the nearest %.4g s off): mismatched stamps'
                         % (path, len(off), len(poses), tolerance, min(off)))
    if not rows:
        raise InputError('%s: no tracker sample left (matched, legs still)' % path)
    table = np.array(rows)
    try:
        return cal_model.measurements(table[:, 0:3], table[:, 3:7], table[:, 7:13]), {
            'tracker_samples': len(poses), 'unmatched': len(off), 'used': len(rows)}
    except cal_model.CalibrationError as exc:
        raise InputError('%s: %s' % (path, exc)) from None


# -- writing the calibrated file -------------------------------------------------
def calibrated_document(params_path: Path, mech) -> dict:
    """The starting file's YAML with the calibrated keys in ``/**`` (and out
    of every node section, where they would override it)."""
    doc = yaml.safe_load(Path(params_path).read_text())
    values = mech.to_params()
    shared = None
    for key, section in doc.items():
        params = section.get('ros__parameters') or {}
        if str(key).strip() in ('/**', '**'):
            shared = params
        else:
            for name in CALIBRATED_KEYS:
                params.pop(name, None)
    if shared is None:
        shared = {}
        doc = {'/**': {'ros__parameters': shared}, **doc}
    for name in CALIBRATED_KEYS:
        shared[name] = [round(float(v), 9) for v in np.ravel(values[name])]
    return doc


def write_calibrated(out: Path, params_path: Path, mech, note: str) -> Path:
    """Write DIR/calibrated.yaml only once it reads back as a valid mechanism."""
    doc = calibrated_document(params_path, mech)
    text = '# %s\n' % note + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None)
    path = out / 'calibrated.yaml'
    partial = out / '.calibrated.yaml.partial'
    partial.write_text(text)
    try:
        load_mechanism(partial)
    except ParameterError:
        partial.unlink()
        raise
    partial.replace(path)
    return path


# -- the subcommands -------------------------------------------------------------------
def _noise(args):
    try:
        return cal_model.NoiseModel(args.tracker_noise[0], args.tracker_noise[1],
                              getattr(args, 'reading_noise', cal_model.NoiseModel.reading))
    except cal_model.CalibrationError as exc:
        raise InputError(str(exc)) from None


def run_fit(args, mech, params_path: Path) -> int:
    path = Path(args.measurements)
    source = {'file': str(path)}
    if path.is_dir():
        meas, source_counts = read_measurements_bag(path, args.tracker_topic,
                                                    args.stamp_tolerance, args.still)
        source.update(source_counts)
    else:
        meas = read_measurements_csv(path)
    noise = _noise(args)
    what = 'tracker sample' if path.is_dir() else 'row'
    try:
        cal_model.check_plausible(mech, meas, args.tolerance)
        held_mask = cal.holdout_split(meas.count, args.holdout)
    except cal_model.CalibrationError as exc:
        raise InputError('%s: %s' % (path, str(exc).replace('row', what, 1))) from None
    fitted, held = meas.subset(~held_mask), meas.subset(held_mask)
    if fitted.count < cal_model.MIN_POSES:
        raise InputError('%s: %d poses, %d of them held out (--holdout %g): %d left to fit, '
                         'the fit needs at least %d' % (path, meas.count, held.count,
                                                        args.holdout, fitted.count,
                                                        cal_model.MIN_POSES))
    rows = np.flatnonzero(~held_mask) + 1        # each fitted pose's row in the file
    started = time.perf_counter()
    try:
        result = cal.fit(mech, fitted, noise, args.tolerance, rows=rows, geometry=args.geometry)
    except cal_model.CalibrationError as exc:
        raise InputError('%s: %s' % (path, str(exc).replace('rows', what + 's', 1))) from None
    try:
        calibrated = cal_model.mechanism_with(mech, result.estimate)
        cal.check_assembles(calibrated, meas)
    except ParameterError as exc:
        together = ' (a 6-3 fitted as a 6-6 whose pair stayed together: fit it without '\
            '--geometry 6-6)' if 'coincide' in str(exc) and args.geometry == '6-6' else ''
        raise InputError('the calibrated mechanism is impossible, nothing written: %s%s'
                         % (exc, together)) from None
    fit_seconds = time.perf_counter() - started
    held_out = None
    if held.count:
        held_out = {'before': cal.pose_errors(mech, held),
                    'after': cal.pose_errors(calibrated, held)}
    report = cal.report(result, held_out)
    report.update({'source': source, 'poses_fitted': fitted.count,
                   'poses_held_out': held.count, 'fit_seconds': fit_seconds,
                   'tolerance_m': args.tolerance,
                   'noise_model': {'tracker_position_m': noise.position,
                                   'tracker_orientation_rad': noise.orientation,
                                   'reading_m': noise.reading},
                   'params': str(params_path)})
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    try:
        written = write_calibrated(out, params_path, calibrated,
                                   'calibrated by `calibrate fit` from %s (%d poses) on %s'
                                   % (path, fitted.count, params_path))
    except ParameterError as exc:
        raise InputError('the calibrated file would be invalid, nothing written: %s'
                         % exc) from None
    (out / 'report.json').write_text(json.dumps(finite_or_none(report), indent=1,
                                                allow_nan=False))
    print('calibrate: %d poses: %d fitted, %d held out; a %s, %d parameters, fitted in '
          '%.2f s; reading RMS %.4g m -> %.4g m (noise scale %.3g)'
          % (meas.count, fitted.count, held.count, result.geometry, result.estimate.size,
             fit_seconds, result.rms_before, result.rms_after, result.noise_scale))
    for pair in report['pair_separations'] or ():
        print('calibrate: the joints of legs %d and %d came %.4g m apart (std %.3g m)'
              % (*pair['legs'], pair['separation_m'], pair['std_m']))
    if held_out:
        before, after = held_out['before'], held_out['after']
        print('calibrate: held-out fk error: position RMS %s -> %s, angle RMS %s -> %s%s' % (
            _figure(before['position_rms_m'], 'm'), _figure(after['position_rms_m'], 'm'),
            _figure(before['angle_rms_rad'], 'rad'), _figure(after['angle_rms_rad'], 'rad'),
            ''.join('; fk solved no pose for %d of %d held-out readings %s' % (
                errors['unsolved'], errors['poses'], when)
                for errors, when in ((before, 'on the drawing'), (after, 'calibrated'))
                if errors['unsolved'])))
    for item in report['unidentifiable']:
        print('calibrate: warning: held at the drawing (the data know it to only %.3g m): %s'
              % (item['predicted_std_m'], item['combination']), file=sys.stderr)
    print('calibrate: wrote %s and %s' % (written, out / 'report.json'))
    return 0


def supervisor_limits(setup, params_path: Path):
    """The supervisor's limits on the machine of ``params_path`` (its section's
    keys, else their defaults): a plan must fly under them."""
    try:
        params = dict(setup.to_params(), **read_parameter_file(params_path, 'supervisor'))
        return limits_from_params(setup.mechanism, params)
    except ParameterError as exc:
        raise InputError('%s: %s' % (params_path, exc)) from None


def finite_or_none(value):
    """``value`` (dicts, lists, numbers) with every NaN or infinity as None:
    report.json is strict JSON, which has neither."""
    if isinstance(value, dict):
        return {k: finite_or_none(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_or_none(v) for v in value]
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def _figure(value, unit) -> str:
    return 'none' if value is None else '%.4g %s' % (value, unit)


def run_plan(args, setup, params_path: Path) -> int:
    noise = _noise(args)
    try:
        sup_params = dict(setup.to_params(), **read_parameter_file(params_path, 'supervisor'))
        rate = float(read_declared(read_parameter_file(params_path, 'plant'), 'sensor_rate'))
    except ParameterError as exc:
        raise InputError('%s: %s' % (params_path, exc)) from None
    try:
        limits = cp.plan_limits(setup.mechanism, supervisor_limits(setup, params_path))
        if limits.leg_speed and args.leg_speed > limits.leg_speed:
            raise InputError('--leg-speed %g m/s: the supervisor trips at trip_leg_speed %g '
                             'm/s, and a plan keeps its legs under %g m/s (%g of it)'
                             % (args.leg_speed, limits.leg_speed / cp.SPEED_SHARE,
                                limits.leg_speed, cp.SPEED_SHARE))
        flown = flight.flown_plan(
            setup, args.poses, rate, sup_params,
            {'noise': noise, 'candidates': args.candidates, 'limits': limits,
             'geometry': args.geometry},
            {'hold': args.hold, 'move': args.move, 'leg_speed': args.leg_speed,
             'limits': limits},
            points=args.tolerance[0], offsets=args.tolerance[1], machines=args.machines,
            seed=args.seed)
    except (cp.PlanError, cal_model.CalibrationError) as exc:
        raise InputError(exc) from None
    except ParameterError as exc:
        raise InputError('%s: %s' % (params_path, exc)) from None
    plan, times, rows = flown.plan, flown.times, flown.rows
    for _, _, why in flown.struck:
        print('calibrate: struck %s' % why)
    try:
        Reference.from_poses(setup.mechanism, times, rows).check(max_leg_speed=limits.leg_speed)
    except ReferenceError as exc:
        raise InputError('the planned reference breaks a limit: %s' % exc) from None
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_reference_csv(out / 'reference.csv', times, rows)
    windows = cp.hold_windows(times, rows)
    euler = euler_from_matrix(plan.rotations)
    with open(out / 'poses.csv', 'w', newline='') as stream:
        writer = csv.writer(stream)
        writer.writerow(POSE_COLUMNS)
        for j in range(len(plan.positions)):
            writer.writerow([j + 1] + [repr(float(v)) for v in plan.positions[j]]
                            + [repr(float(v)) for v in euler[j]]
                            + ['%.6f' % windows[j][0], '%.6f' % windows[j][1]])
    summary = {'poses': len(plan.positions), 'seed': args.seed, 'o1_per_m': plan.o1,
               'o3_per_m': plan.o3, 'worst_std_m': plan.worst_std,
               'candidates': plan.candidates, 'duration_s': float(times[-1]),
               'hold_s': args.hold, 'tracker_noise': list(args.tracker_noise),
               'tolerance_m': {'points': args.tolerance[0], 'offsets': args.tolerance[1]},
               'flights': [{'machine': m + 1, 'trip': f.trip, 'position_max_m': f.position_max,
                            'angle_max_rad': f.angle_max} for m, f in enumerate(flown.flights)],
               'struck': [why for _, _, why in flown.struck]}
    (out / 'plan.json').write_text(json.dumps(finite_or_none(summary), indent=1, allow_nan=False))
    print('calibrate: %d poses from %d candidates: O3 %.4g /m (worst combination std %.3g m '
          'at the stated noise), O1 %.4g /m; reference %.1f s' % (
              len(plan.positions), plan.candidates, plan.o3, plan.worst_std, plan.o1,
              times[-1]))
    if flown.flights:
        print('calibrate: flown on %d machines off the drawing (points +-%g m, offsets +-%g m) '
              'with %s and the supervisor: no trip, within %.1f mm and %.1f mrad of the plan'
              % (len(flown.flights), args.tolerance[0], args.tolerance[1], flight.LAW,
                 max(f.position_max for f in flown.flights) * 1e3,
                 max(f.angle_max for f in flown.flights) * 1e3))
    print('calibrate: wrote %s, %s and %s' % (out / 'poses.csv', out / 'reference.csv',
                                             out / 'plan.json'))
    return 0


def run_machine(args, mech, params_path: Path) -> int:
    """A machine built off its drawing: every point moved by up to --points,
    every offset up to --offsets (uniform, seeded); with --geometry 6-6 a 6-3's
    pair joints each moved on their own (the machine a 6-6 file describes)."""
    rng = np.random.default_rng(args.seed)
    try:
        machine = flight.machine_off_drawing(mech, rng, args.points, args.offsets, args.geometry)
    except cal_model.CalibrationError as exc:
        raise InputError(exc) from None
    except ParameterError as exc:
        raise InputError('the perturbed machine is impossible: %s' % exc) from None
    doc = calibrated_document(params_path, machine)
    if args.tracker_rate:
        plant = doc.setdefault('/**/plant', {}).setdefault('ros__parameters', {})
        plant.update({'tracker_rate': args.tracker_rate,
                      'tracker_position_noise': args.tracker_noise[0],
                      'tracker_orientation_noise': args.tracker_noise[1]})
        try:        # a rate the plant would refuse: refused here
            TrackerModel(dict(read_parameter_file(params_path, 'plant'), **plant))
        except ParameterError as exc:
            raise InputError(str(exc)) from None
    out = Path(args.out)
    out.write_text('# a machine built off the drawing %s (calibrate machine --seed %d: points '
                   '+-%g m, offsets +-%g m)\n' % (params_path, args.seed, args.points,
                                                  args.offsets)
                   + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None))
    print('calibrate: wrote %s' % out)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split('\n\n')[0])
    sub = parser.add_subparsers(dest='command', required=True)

    def common(p):
        p.add_argument('--params', metavar='FILE',
                       help='the drawing: a parameter file (default: the packaged %s)'
                       % default_params_path())
        p.add_argument('--tracker-noise', type=float, nargs=2, default=(1e-4, 1e-4),
                           metavar=('POS', 'ANG'),
                           help="the tracker's standard deviations per axis: position [m] "
                           'and angle [rad] (default 1e-4 1e-4)')
        p.add_argument('--geometry', choices=cal_model.GEOMETRIES, default=None,
                       help="the layout to identify: 6-3 (three platform vertices) or 6-6 "
                       "(six joints; of a 6-3's file: its pairs allowed to come apart, 18 "
                       "numbers written). Default: the file's own")

    fit = sub.add_parser('fit', help='identify base points, platform points and offsets')
    common(fit)
    fit.add_argument('--measurements', required=True, metavar='F',
                     help='a CSV x,y,z,qx,qy,qz,qw,L1..L6, or a bag directory')
    fit.add_argument('--out', required=True, metavar='DIR')
    fit.add_argument('--holdout', type=float, default=0.2, metavar='SHARE',
                     help='share of the poses held out of the fit for the fk check, '
                     '0 to 0.5 (default 0.2)')
    fit.add_argument('--tolerance', type=float, default=0.01, metavar='M',
                     help='how far the machine may be from its drawing [m]: a combination '
                     'the data know worse than this is held at the drawing (default 0.01)')
    fit.add_argument('--reading-noise', type=float, default=1e-5, metavar='M',
                     help="the length sensors' standard deviation [m] (default 1e-5)")
    fit.add_argument('--tracker-topic', default='tracker/pose', metavar='T',
                     help='bag: the PoseStamped topic of the tracker (default tracker/pose)')
    fit.add_argument('--stamp-tolerance', type=float, default=5e-4, metavar='S',
                     help='bag: the largest stamp difference of a matched pair [s] '
                     '(default 5e-4)')
    fit.add_argument('--still', type=float, default=0.0, metavar='V',
                     help='bag: keep only samples where every leg moves slower than V m/s '
                     '(default 0: every matched sample)')

    plan = sub.add_parser('plan', help='choose poses and write a reference for rig')
    common(plan)
    plan.add_argument('--poses', type=int, required=True, metavar='N')
    plan.add_argument('--out', required=True, metavar='DIR')
    plan.add_argument('--seed', type=int, default=0)
    plan.add_argument('--hold', type=float, default=2.0, metavar='S',
                      help='seconds at each pose (default 2)')
    plan.add_argument('--move', type=float, default=2.0, metavar='S',
                      help='the shortest move between poses [s] (default 2)')
    plan.add_argument('--leg-speed', type=float, default=0.1, metavar='V',
                      help='the fastest a leg moves on average in a move [m/s] (default 0.1)')
    plan.add_argument('--candidates', type=int, default=1500, metavar='K',
                      help='random feasible poses to choose from (default 1500)')
    plan.add_argument('--tolerance', type=float, nargs=2, metavar=('POINTS', 'OFFSETS'),
                      default=(flight.POINTS_TOLERANCE, flight.OFFSETS_TOLERANCE),
                      help='how far the machine may be off its drawing [m]: each point '
                      'coordinate within +-POINTS, each sensor offset within +-OFFSETS. The '
                      'plan is flown in simulation on --machines such machines and a pose '
                      'where one fails is struck (default %g %g)'
                      % (flight.POINTS_TOLERANCE, flight.OFFSETS_TOLERANCE))
    plan.add_argument('--machines', type=int, default=flight.MACHINES, metavar='N',
                      help='machines off the drawing the plan is flown on (default %d; 0: '
                      'none, the plan is not checked on a machine)' % flight.MACHINES)

    machine = sub.add_parser('machine', help='a parameter file of a machine built off its '
                             'drawing, for the simulation')
    common(machine)
    machine.add_argument('--out', required=True, metavar='FILE')
    machine.add_argument('--seed', type=int, default=0)
    machine.add_argument('--points', type=float, default=0.005, metavar='M',
                         help='largest move of a point per axis [m] (default 0.005)')
    machine.add_argument('--offsets', type=float, default=0.01, metavar='M',
                         help='largest sensor offset [m] (default 0.01)')
    machine.add_argument('--tracker-rate', type=float, default=100.0, metavar='HZ',
                         help="the plant's simulated tracker on tracker/pose (default 100; "
                         '0: none)')
    return parser


def option_problem(args) -> str:
    """Why an option's value cannot be used ('' if all can)."""
    checks = [('--tracker-noise', min(args.tracker_noise) >= 0)]
    if args.command == 'fit':
        checks += [('--stamp-tolerance', args.stamp_tolerance > 0), ('--still', args.still >= 0),
                   ('--reading-noise', args.reading_noise >= 0)]
    elif args.command == 'plan':
        checks += [('--tolerance', min(args.tolerance) >= 0), ('--machines', args.machines >= 0)]
    elif args.command == 'machine':
        checks += [('--points', args.points >= 0), ('--offsets', args.offsets >= 0),
                   ('--tracker-rate', args.tracker_rate >= 0)]
    for name, ok in checks:
        if not ok:       # NaN fails every comparison
            return '%s must be a number >= 0 (> 0 for --stamp-tolerance)' % name
    return ''


@quiet_on_closed_pipe
def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    problem = option_problem(args)
    if problem:
        return _fail(problem)
    params_path = Path(args.params or default_params_path())
    setup = load_checked(PROG, params_path)
    if setup is None:
        return 2
    try:
        if args.command == 'fit':
            return run_fit(args, setup.mechanism, params_path)
        if args.command == 'plan':
            return run_plan(args, setup, params_path)
        return run_machine(args, setup.mechanism, params_path)
    except InputError as exc:
        return _fail(exc)
    except OSError as exc:
        return _fail('%s: %s' % (exc.filename or 'output', exc.strerror))


if __name__ == '__main__':
    sys.exit(main())
