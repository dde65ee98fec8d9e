"""Calibration (core/machine/calibration.py, core/machine/calibration_plan.py, `calibrate`):
the model's Jacobians against finite differences, recovery of a machine
built off its drawing within the reported uncertainty, that uncertainty
against a Monte-Carlo spread, the refusals, and the plant's simulated
sensors (offset, tracker) the simulation of a calibration relies on.
"""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stewart63_ros.core.controllers.sensor import SensorModel, TrackerModel
from stewart63_ros.core.machine import calibration as cal
from stewart63_ros.core.machine import calibration_model as cal_model
from stewart63_ros.core.machine import calibration_plan as cp
from stewart63_ros.core.plumbing.params import ParameterError, load_setup
from stewart63_ros.tools import calibrate

NOISE = cal_model.NoiseModel(1e-4, 1e-4, 1e-5)


@pytest.fixture(scope='module')
def truth(mech):
    """A machine built off the drawing: points up to 5 mm, offsets up to 10 mm."""
    rng = np.random.default_rng(11)
    theta = cal_model.parameter_vector(mech)
    theta[:27] += rng.uniform(-0.005, 0.005, 27)
    theta[27:] += rng.uniform(-0.01, 0.01, 6)
    return theta


@pytest.fixture(scope='module')
def planned(setup, mech):
    """30 planned poses (seeded)."""
    return cp.plan(setup, 30, seed=5, noise=NOISE)


def tracked(theta, positions, rotations, rng, noise=NOISE):
    """Measurements of a machine ``theta`` at true poses: readings from the
    truth, the poses as a noisy tracker reports them."""
    true = cal_model.Measurements(positions, rotations, np.zeros((len(positions), 6)))
    readings = cal_model.predict_readings(theta, true) + rng.normal(0, noise.reading,
                                                              (len(positions), 6))
    seen_pos = positions + rng.normal(0, noise.position, positions.shape)
    seen_rot = Rotation.from_rotvec(rng.normal(0, noise.orientation, (len(positions), 3))) \
        * Rotation.from_matrix(rotations)
    return cal_model.measurements(seen_pos, seen_rot.as_quat(), readings)


def random_poses(setup, count, seed, half_range=cp.DEFAULT_RANGE):
    return cp.candidate_poses(setup, count, np.random.default_rng(seed), half_range)


# -- the model -----------------------------------------------------------------
def test_parameter_and_pose_jacobians_match_finite_differences(setup, mech, truth):
    positions, rotations = random_poses(setup, 5, 1)
    meas = cal_model.Measurements(positions, rotations, np.zeros((5, 6)))
    jac = cal_model.parameter_jacobian(truth, meas)
    step = 1e-6
    for j in range(cal_model.N_PARAMETERS):
        d = np.zeros(cal_model.N_PARAMETERS)
        d[j] = step
        numeric = (cal_model.predict_readings(truth + d, meas)
                   - cal_model.predict_readings(truth - d, meas)) / (2 * step)
        assert np.allclose(jac[:, :, j], numeric, atol=1e-7), cal_model.PARAMETER_NAMES[j]
    pose_jac = cal_model.pose_jacobian(truth, meas)
    for a in range(6):
        d = np.zeros(3)
        d[a % 3] = step
        if a < 3:
            plus = cal_model.Measurements(positions + d, rotations, meas.readings)
            minus = cal_model.Measurements(positions - d, rotations, meas.readings)
        else:
            turn = Rotation.from_rotvec(d).as_matrix()
            plus = cal_model.Measurements(positions, turn @ rotations, meas.readings)
            minus = cal_model.Measurements(positions, turn.T @ rotations, meas.readings)
        numeric = (cal_model.predict_readings(truth, plus)
                   - cal_model.predict_readings(truth, minus)) \
            / (2 * step)
        assert np.allclose(pose_jac[:, :, a], numeric, atol=1e-7), a


def test_readings_of_the_drawing_are_the_inverse_kinematics_plus_offset(setup, mech):
    from stewart63_ros.core.mechanics.kinematics import leg_lengths
    offset = [0.001, -0.002, 0.003, 0.0, 0.004, -0.005]
    drawn = mech.replace(leg_length_offset=offset)
    positions, rotations = random_poses(setup, 3, 2)
    meas = cal_model.Measurements(positions, rotations, np.zeros((3, 6)))
    predicted = cal_model.predict_readings(cal_model.parameter_vector(drawn), meas)
    for n in range(3):
        assert np.allclose(predicted[n], leg_lengths(mech, positions[n], rotations[n])
                           + offset, atol=1e-12)


# -- recovery and honest uncertainty -------------------------------------------------
def test_planned_poses_recover_the_machine_within_three_reported_sigma(mech, truth, planned):
    meas = tracked(truth, planned.positions, planned.rotations, np.random.default_rng(3))
    result = cal.fit(mech, meas, NOISE)
    assert result.held.shape[1] == 0, 'planned poses must leave nothing to hold'
    z = (result.estimate - truth) / result.std
    print('\nrecovery: max |error| %.3g mm, max |error|/std %.2f, max std %.3g mm, '
          'noise scale %.3f' % (np.abs(result.estimate - truth).max() * 1e3,
                                np.abs(z).max(), result.std.max() * 1e3, result.noise_scale))
    assert np.all(np.abs(z) <= 3.0), dict(zip(cal_model.PARAMETER_NAMES, np.round(z, 2)))
    assert 0.8 < result.noise_scale < 1.25
    # The drawing was millimetres off; the calibrated model predicts to the noise.
    assert result.rms_before > 2e-3 and result.rms_after < 2e-4


def test_reported_sigma_agrees_with_the_spread_over_noise_seeds(mech, truth, planned):
    estimates, stds = [], []
    for seed in range(40):
        meas = tracked(truth, planned.positions, planned.rotations,
                       np.random.default_rng(100 + seed))
        result = cal.fit(mech, meas, NOISE)
        estimates.append(result.estimate)
        stds.append(result.std)
    spread = np.std(estimates, axis=0, ddof=1)
    reported = np.mean(stds, axis=0)
    ratio = spread / reported
    print('\nMonte-Carlo over 40 seeds: spread / reported std: median %.3f, min %.3f, max %.3f;'
          ' reported std %.3g-%.3g mm' % (np.median(ratio), ratio.min(), ratio.max(),
                                          reported.min() * 1e3, reported.max() * 1e3))
    # 40 seeds estimate a spread to about +-11 % (1 sigma).
    assert 0.85 < np.median(ratio) < 1.15
    assert np.all((ratio > 0.6) & (ratio < 1.45)), dict(zip(cal_model.PARAMETER_NAMES,
                                                            np.round(ratio, 2)))
    # Unbiased: the mean estimate within 4 standard errors of the truth.
    assert np.all(np.abs(np.mean(estimates, axis=0) - truth) < 4 * reported / np.sqrt(40))


def test_plan_beats_random_poses_in_its_index(setup, mech, planned):
    blocks_random = cp._blocks(mech, *random_poses(setup, 30, 9), NOISE)
    _, o3_random = cp.indices(blocks_random, range(30))
    print('\nO3: planned %.4g /m, random %.4g /m' % (planned.o3, o3_random))
    assert planned.o3 > 1.5 * o3_random
    assert planned.worst_std < 3e-3


def test_close_poses_hold_the_leg_against_offset_trade_at_the_drawing(setup, mech, truth):
    positions, rotations = random_poses(setup, 40, 4, (0.05, 0.05, 0.05, 0.05, 0.05, 0.05))
    meas = tracked(truth, positions, rotations, np.random.default_rng(4))
    result = cal.fit(mech, meas, NOISE, tolerance=0.005)
    assert result.held.shape[1] >= 1
    # Each held combination is named, and moves a base point with its leg's offset.
    named = cal.report(result)['unidentifiable']
    assert named and all('offset_' in item['combination'] and 'b_' in item['combination']
                         for item in named), named
    # Held: the estimate's component along a held direction is the drawing's.
    assert np.allclose(result.held.T @ (result.estimate - result.nominal), 0, atol=1e-9)


def test_held_out_fk_error_drops_with_the_calibrated_file(setup, mech, truth, planned):
    meas = tracked(truth, planned.positions, planned.rotations, np.random.default_rng(6))
    result = cal.fit(mech, meas, NOISE)
    calibrated = cal_model.mechanism_with(mech, result.estimate)
    positions, rotations = random_poses(setup, 10, 12)
    check = tracked(truth, positions, rotations, np.random.default_rng(7))
    before = cal.pose_errors(mech, check)
    after = cal.pose_errors(calibrated, check)
    print('\nheld-out fk position RMS %.3g mm -> %.3g mm, angle %.3g -> %.3g mrad' % (
        before['position_rms_m'] * 1e3, after['position_rms_m'] * 1e3,
        before['angle_rms_rad'] * 1e3, after['angle_rms_rad'] * 1e3))
    assert before['position_rms_m'] > 2e-3
    assert after['position_rms_m'] < 3 * NOISE.position * np.sqrt(3)
    assert after['position_rms_m'] * 10 < before['position_rms_m']


# -- refusals -------------------------------------------------------------------------
def test_too_few_poses_are_refused(mech, truth, planned):
    meas = tracked(truth, planned.positions[:9], planned.rotations[:9],
                   np.random.default_rng(1))
    with pytest.raises(cal_model.CalibrationError, match='9 poses: the fit needs at least 10'):
        cal.fit(mech, meas, NOISE)


def test_level_poses_are_refused_naming_what_they_leave_unseen(setup, mech, truth):
    positions, _ = random_poses(setup, 30, 2)
    level = np.repeat(np.eye(3)[None], 30, axis=0)
    meas = tracked(truth, positions, level, np.random.default_rng(2),
                   cal_model.NoiseModel(1e-4, 1e-12, 1e-5))
    meas = cal_model.Measurements(positions, level, meas.readings)
    with pytest.raises(cal_model.CalibrationError) as info:
        cal.fit(mech, meas, NOISE)
    text = str(info.value)
    assert 'leave 9 combinations unidentifiable' in text
    assert '{p_1.x, b_1.x, b_2.x}' in text.replace('b_2.x, b_1.x', 'b_1.x, b_2.x') or \
        'p_1.x' in text
    assert 'same orientation' in text


def test_poses_at_one_height_turning_only_about_z_are_refused(setup, mech, truth):
    rng = np.random.default_rng(3)
    from stewart63_ros.core.analysis.equilibrium import setpoint_pose
    centre, _ = setpoint_pose(setup)
    positions = centre + np.column_stack([rng.uniform(-0.2, 0.2, (30, 2)), np.zeros(30)])
    rotations = Rotation.from_euler('z', rng.uniform(-0.3, 0.3, (30, 1))).as_matrix()
    readings = cal_model.predict_readings(truth, cal_model.Measurements(positions, rotations,
                                                            np.zeros((30, 6))))
    meas = cal_model.Measurements(positions, rotations, readings)
    with pytest.raises(cal_model.CalibrationError,
                       match='unidentifiable.*p_1.z.*level.*one height'):
        cal.fit(mech, meas, NOISE)


def test_nan_rows_and_bad_quaternions_are_refused():
    good = np.zeros((3, 3)), np.tile([0, 0, 0, 1.0], (3, 1)), np.ones((3, 6))
    readings = good[2].copy()
    readings[1, 4] = np.nan
    with pytest.raises(cal_model.CalibrationError, match='row 2 holds NaN'):
        cal_model.measurements(good[0], good[1], readings)
    with pytest.raises(cal_model.CalibrationError, match='row 1: the quaternion'):
        cal_model.measurements(good[0], np.tile([0, 0, 0, 2.0], (3, 1)), good[2])


def test_a_calibration_outside_the_stroke_is_not_a_machine(setup, mech, truth):
    positions, rotations = random_poses(setup, 20, 5)
    meas = tracked(truth, positions, rotations, np.random.default_rng(5))
    lengths = cal_model.predict_readings(cal_model.parameter_vector(mech), meas)
    short = mech.replace(leg_length_max=max(float(setup.task.setpoint_lengths.max()) + 0.01,
                                            float(np.percentile(lengths, 90))))
    with pytest.raises(ParameterError, match='outside the stroke.*not the machine'):
        cal.check_assembles(short, meas)


# -- the plant's simulated sensors -------------------------------------------------------
def test_sensor_adds_the_offset_of_its_file():
    offset = [0.01, -0.02, 0.0, 0.003, 0.0, -0.004]
    sensor = SensorModel({'leg_length_offset': offset})
    lengths, _ = sensor.measure(np.full(6, 1.5), np.zeros(6))
    assert np.allclose(lengths, 1.5 + np.array(offset))
    with pytest.raises(ParameterError, match='leg_length_offset: expected 6 numbers'):
        SensorModel({'leg_length_offset': [0.0] * 5})


def test_tracker_samples_at_its_rate_with_its_noise():
    tracker = TrackerModel({'tracker_rate': 100.0, 'sensor_rate': 1000.0,
                            'tracker_position_noise': 2e-4,
                            'tracker_orientation_noise': 3e-4})
    assert [k for k in range(25) if tracker.due(k)] == [0, 10, 20]
    quat = Rotation.from_euler('xyz', [0.1, -0.2, 0.3]).as_quat()
    samples = [tracker.measure(np.array([0.1, 0.2, 1.0]), quat) for _ in range(4000)]
    pos = np.array([s[0] for s in samples])
    turn = (Rotation.from_quat([s[1] for s in samples]) * Rotation.from_quat(quat).inv())
    assert np.allclose(pos.std(axis=0), 2e-4, rtol=0.08)
    assert np.allclose(turn.as_rotvec().std(axis=0), 3e-4, rtol=0.08)
    assert not TrackerModel({}).due(0)
    with pytest.raises(ParameterError, match='tracker_rate: must divide sensor_rate'):
        TrackerModel({'tracker_rate': 300.0, 'sensor_rate': 1000.0})


# -- the command line ---------------------------------------------------------------------
def write_measurements(path, meas):
    quats = Rotation.from_matrix(meas.rotations).as_quat()
    with open(path, 'w', newline='') as stream:
        writer = csv.writer(stream)
        writer.writerow(calibrate.MEASUREMENT_COLUMNS)
        for n in range(meas.count):
            writer.writerow([repr(float(v)) for v in np.concatenate(
                [meas.positions[n], quats[n], meas.readings[n]])])


def test_fit_writes_a_calibrated_file_every_node_reads(setup, tmp_path, mech, truth, planned,
                                                       capsys):
    rng = np.random.default_rng(8)
    positions = np.vstack([planned.positions, random_poses(setup, 8, 21)[0]])
    rotations = np.concatenate([planned.rotations, random_poses(setup, 8, 21)[1]])
    write_measurements(tmp_path / 'm.csv', tracked(truth, positions, rotations, rng))
    assert calibrate.main(['fit', '--measurements', str(tmp_path / 'm.csv'),
                           '--out', str(tmp_path / 'out')]) == 0
    calibrated_setup = load_setup(tmp_path / 'out' / 'calibrated.yaml')
    calibrated = calibrated_setup.mechanism
    error = cal_model.parameter_vector(calibrated) - truth
    assert np.abs(error).max() < 5e-3
    report = json.loads((tmp_path / 'out' / 'report.json').read_text())
    assert set(report['parameters']) == set(cal_model.PARAMETER_NAMES)
    assert {'estimate', 'std'} <= set(report['parameters']['offset_1'])
    assert report['rms_after_m'] < report['rms_before_m'] / 10
    assert report['held_out']['after']['position_rms_m'] < \
        report['held_out']['before']['position_rms_m'] / 10
    assert isinstance(report['unidentifiable'], list) and len(report['singular_values']) == 33
    # The nodes' own keys of the drawing survive (a full parameter file).
    assert calibrated_setup.gains.kp.tolist() == setup.gains.kp.tolist()


def test_fit_refuses_bad_input_in_one_line(tmp_path, mech, truth, planned, capsys):
    meas = tracked(truth, planned.positions, planned.rotations, np.random.default_rng(9))
    write_measurements(tmp_path / 'm.csv', meas)
    lines = (tmp_path / 'm.csv').read_text().splitlines()
    (tmp_path / 'few.csv').write_text('\n'.join(lines[:8]) + '\n')
    lines[5] = ','.join(['nan'] + lines[5].split(',')[1:])
    (tmp_path / 'nan.csv').write_text('\n'.join(lines) + '\n')
    (tmp_path / 'header.csv').write_text('\n'.join(['x,y,z'] + lines[1:]) + '\n')
    for name, words in (('nan.csv', 'row 5 holds NaN'), ('few.csv', '7 poses'),
                        ('header.csv', 'the header must be'), ('none.csv', 'cannot read')):
        code = calibrate.main(['fit', '--measurements', str(tmp_path / name), '--holdout', '0',
                               '--out', str(tmp_path / name / 'out')])
        err = capsys.readouterr().err.strip()
        assert code == 2 and words in err and len(err.splitlines()) == 1, (name, err)
        assert not (tmp_path / name / 'out' / 'calibrated.yaml').exists()


def test_an_impossible_calibration_is_never_written(setup, tmp_path, mech, truth):
    positions, rotations = random_poses(setup, 20, 5)
    meas = tracked(truth, positions, rotations, np.random.default_rng(5))
    write_measurements(tmp_path / 'm.csv', meas)
    lengths = cal_model.predict_readings(cal_model.parameter_vector(mech), meas)
    import yaml
    doc = yaml.safe_load(open(calibrate.default_params_path()))
    doc['/**']['ros__parameters']['leg_length_max'] = max(
        float(setup.task.setpoint_lengths.max()) + 0.01, float(np.percentile(lengths, 90)))
    (tmp_path / 'short.yaml').write_text(yaml.safe_dump(doc))
    code = calibrate.main(['fit', '--measurements', str(tmp_path / 'm.csv'), '--params',
                           str(tmp_path / 'short.yaml'), '--out', str(tmp_path / 'out')])
    assert code == 2
    assert not (tmp_path / 'out' / 'calibrated.yaml').exists()


def test_plan_writes_poses_and_a_reference_the_rig_accepts(tmp_path, mech):
    from stewart63_ros.core.controllers.reference_files import load_reference
    # --machines 0: the flights on machines off the drawing are test_calibration_flight.py's
    assert calibrate.main(['plan', '--poses', '12', '--machines', '0', '--out',
                           str(tmp_path / 'plan'),
                           '--hold', '0.5', '--move', '0.5', '--leg-speed', '0.4',
                           '--seed', '2']) == 0
    reference = load_reference(mech, tmp_path / 'plan' / 'reference.csv')
    with open(tmp_path / 'plan' / 'poses.csv') as stream:
        rows = list(csv.DictReader(stream))
    assert len(rows) == 12
    for row in rows:
        # The reference holds each planned pose from hold_from_s to hold_to_s.
        for t in (float(row['hold_from_s']), float(row['hold_to_s'])):
            pose = reference.poses([t])[0]
            want = [float(row[k]) for k in ('x', 'y', 'z', 'theta_x', 'theta_y', 'theta_z')]
            assert np.allclose(pose, want, atol=1e-6), (row, pose)
    assert json.loads((tmp_path / 'plan' / 'plan.json').read_text())['o3_per_m'] > 0
    assert calibrate.main(['plan', '--poses', '5', '--out', str(tmp_path / 'p2')]) == 2


def test_fit_refuses_unit_mistakes_naming_the_file_and_row(tmp_path, mech, truth, planned,
                                                           capsys):
    """Millimetres read as metres, in every row or in one, and a file whose
    columns were swapped in every other row: exit 2, one line naming the file and
    the row(s), nothing written (it wrote the drawing and exited 0)."""
    meas = tracked(truth, planned.positions, planned.rotations, np.random.default_rng(9))
    readings_mm = meas.readings.copy()
    readings_mm[3] *= 1000
    positions_mm = meas.positions.copy()
    positions_mm[4] *= 1000
    swapped = meas.readings.copy()
    swapped[::2] = swapped[::2, ::-1]
    cases = {
        'mm.csv': (cal_model.Measurements(meas.positions * 1000, meas.rotations,
                                    meas.readings * 1000), 'row 1: leg_1 reads'),
        'mm_reading.csv': (cal_model.Measurements(meas.positions, meas.rotations, readings_mm),
                           'row 4: leg_1 reads'),
        'mm_pose.csv': (cal_model.Measurements(positions_mm, meas.rotations, meas.readings),
                        'row 5: the pose'),
        'swapped.csv': (cal_model.Measurements(meas.positions, meas.rotations, swapped),
                        'the rows it predicts worst: '),
    }
    for name, (bad, words) in cases.items():
        write_measurements(tmp_path / name, bad)
        out = tmp_path / (name + '.out')
        code = calibrate.main(['fit', '--measurements', str(tmp_path / name),
                               '--out', str(out)])
        err = capsys.readouterr().err.strip()
        assert code == 2 and words in err and str(tmp_path / name) in err, (name, err)
        assert len(err.splitlines()) == 1, err
        assert not out.exists(), name
    # The rows named for the swapped file are rows that were swapped (odd ones).
    named = err.split('predicts worst: ')[1].split(', ')
    assert named and all(int(r) % 2 == 1 for r in named), err


def test_held_out_readings_fk_cannot_solve_are_counted_not_infinite(mech):
    meas = cal_model.Measurements(np.array([[0.01, 0.01, 1.0]] * 2), np.array([np.eye(3)] * 2),
                            np.array([[1.2] * 5 + [2.3], [1.2, 2.3] * 3]))
    errors = cal.pose_errors(mech, meas)
    assert errors['unsolved'] == 2 and errors['position_rms_m'] is None
    # report.json is strict JSON: no Infinity, no NaN.
    text = json.dumps(calibrate.finite_or_none({'a': [1.0, float('inf')], 'b': float('nan')}),
                      allow_nan=False)
    assert json.loads(text) == {'a': [1.0, None], 'b': None}


def test_fit_counts_the_poses_of_the_file_before_the_holdout(tmp_path, truth, planned,
                                                              capsys):
    meas = tracked(truth, planned.positions[:11], planned.rotations[:11],
                   np.random.default_rng(3))
    write_measurements(tmp_path / 'm.csv', meas)
    code = calibrate.main(['fit', '--measurements', str(tmp_path / 'm.csv'),
                           '--out', str(tmp_path / 'out')])
    err = capsys.readouterr().err
    assert code == 2 and '11 poses, 2 of them held out (--holdout 0.2): 9 left' in err, err


def test_plan_stays_inside_the_supervisors_limits_with_a_margin(tmp_path, setup, mech, capsys):
    """The plan's poses and the moves between them keep inside the supervisor's
    soft stroke, pose_box and trip_tilt by the margins (a plan tilted to 0.41
    rad against 0.35, legs at 1.22 m against a soft stroke from 1.25 m, and a
    supervised run tripped pose_box); a tighter file's limits are kept too."""
    import yaml

    from stewart63_ros.core.controllers.reference import R_LEN, R_POS, R_RATE, R_ROT
    from stewart63_ros.core.controllers.reference_files import load_reference
    doc = yaml.safe_load(open(calibrate.default_params_path()))
    doc['/**/supervisor'] = {'ros__parameters': {'trip_tilt': 0.3,
                                                 'pose_box': [-0.2, -0.25, 0.5, 0.3, 0.3, 1.5]}}
    (tmp_path / 'tight.yaml').write_text(yaml.safe_dump(doc))
    for params, tilt, box in ((None, 0.35, [-0.3, -0.3, 0.5, 0.3, 0.3, 1.6]),
                              (tmp_path / 'tight.yaml', 0.3, [-0.2, -0.25, 0.5, 0.3, 0.3, 1.5])):
        out = tmp_path / ('plan_%s' % tilt)
        argv = ['plan', '--poses', '10', '--machines', '0', '--out', str(out), '--hold', '0.3',
                '--move', '0.4',
                '--leg-speed', '0.4']
        assert calibrate.main(argv + (['--params', str(params)] if params else [])) == 0
        reference = load_reference(mech, out / 'reference.csv')
        samples = reference.sample_many(np.arange(0.0, reference.duration, 0.005))
        rot = samples[:, R_ROT].reshape(-1, 3, 3)
        tilts = np.arccos(np.clip(rot[:, 2, 2], -1, 1))
        assert tilts.max() <= tilt - cp.TILT_MARGIN + 1e-6, tilts.max()
        pos = samples[:, R_POS]
        assert np.all(pos >= np.array(box[:3]) + cp.LIMIT_MARGIN - 1e-6)
        assert np.all(pos <= np.array(box[3:]) - cp.LIMIT_MARGIN + 1e-6)
        legs = samples[:, R_LEN]
        assert legs.min() >= 1.25 + cp.LIMIT_MARGIN - 1e-6 and legs.max() <= 2.25 - 0.04
        assert np.abs(samples[:, R_RATE]).max() <= 0.4
    capsys.readouterr()
    # Faster than the supervisor allows: refused, naming its limit.
    assert calibrate.main(['plan', '--poses', '10', '--out', str(tmp_path / 'fast'),
                           '--leg-speed', '1.0']) == 2
    assert 'trip_leg_speed 0.5' in capsys.readouterr().err


def test_rig_says_a_run_that_lost_its_reference_failed():
    from stewart63_ros.tools.rig import TRACKING_BOUND, lost_reference
    lost = {'tracking_error': {'samples': 10101, 'position_max_m': 0.2951,
                               'orientation_max_rad': 1.135}}
    kept = {'tracking_error': {'samples': 10101, 'position_max_m': 0.019,
                               'orientation_max_rad': 0.051}}
    assert 'lost its reference' in lost_reference(lost, TRACKING_BOUND)
    assert lost_reference(kept, TRACKING_BOUND) == ''
    assert lost_reference(lost, (0, 0)) == '' and lost_reference(None, TRACKING_BOUND) == ''


# -- bags ---------------------------------------------------------------------------------
def write_bag(path, meas, pose_stamps_ns, length_stamps_ns):
    """A bag with tracker/pose and leg_lengths, one pose and one reading a stamp."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from stewart63_ros import bagio
    store = bagio.typestore()
    pose_t = store.types['geometry_msgs/msg/PoseStamped']
    joint_t = store.types['sensor_msgs/msg/JointState']
    header_t = store.types['std_msgs/msg/Header']
    time_t = store.types['builtin_interfaces/msg/Time']
    point_t = store.types['geometry_msgs/msg/Point']
    quat_t = store.types['geometry_msgs/msg/Quaternion']
    pose_msg_t = store.types['geometry_msgs/msg/Pose']
    quats = Rotation.from_matrix(meas.rotations).as_quat()

    def header(ns):
        return header_t(stamp=time_t(sec=ns // 10**9, nanosec=ns % 10**9), frame_id='base')
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        poses = writer.add_connection('/tracker/pose', pose_t.__msgtype__, typestore=store)
        legs = writer.add_connection('/leg_lengths', joint_t.__msgtype__, typestore=store)
        for n in range(meas.count):
            msg = pose_t(header=header(pose_stamps_ns[n]), pose=pose_msg_t(
                position=point_t(*meas.positions[n]), orientation=quat_t(*quats[n])))
            writer.write(poses, pose_stamps_ns[n], store.serialize_cdr(msg, msg.__msgtype__))
            msg = joint_t(header=header(length_stamps_ns[n]),
                          name=['leg_%d' % (i + 1) for i in range(6)],
                          position=meas.readings[n], velocity=np.zeros(6), effort=np.zeros(0))
            writer.write(legs, length_stamps_ns[n], store.serialize_cdr(msg, msg.__msgtype__))


def test_a_bag_is_matched_by_stamp_and_mismatched_stamps_are_refused(tmp_path, mech, truth,
                                                                     planned, capsys):
    meas = tracked(truth, planned.positions, planned.rotations, np.random.default_rng(10))
    stamps = [10**9 + n * 10**7 for n in range(meas.count)]
    write_bag(tmp_path / 'good', meas, stamps, stamps)
    assert calibrate.main(['fit', '--measurements', str(tmp_path / 'good'),
                           '--out', str(tmp_path / 'out')]) == 0
    report = json.loads((tmp_path / 'out' / 'report.json').read_text())
    assert report['source']['used'] == meas.count and report['source']['unmatched'] == 0
    # The tracker's clock 3 ms behind the sensors': refused, not fitted.
    write_bag(tmp_path / 'skewed', meas, [s - 3_000_000 for s in stamps], stamps)
    code = calibrate.main(['fit', '--measurements', str(tmp_path / 'skewed'),
                           '--out', str(tmp_path / 'out2')])
    err = capsys.readouterr().err.strip()
    assert code == 2 and 'mismatched stamps' in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / 'out2' / 'calibrated.yaml').exists()


def test_rig_refuses_a_plant_file_it_cannot_use(tmp_path):
    from argparse import Namespace

    from stewart63_ros.tools.rig import plant_params_problem
    params = str(calibrate.default_params_path())
    machine = tmp_path / 'machine.yaml'
    assert calibrate.main(['machine', '--out', str(machine)]) == 0
    ok = Namespace(compose=False, nodes='plant,controller,fk', plant_params=str(machine))
    assert plant_params_problem(ok, params) == ''
    composed = Namespace(compose=True, nodes='plant,controller,fk', plant_params=str(machine))
    assert 'not with --compose' in plant_params_problem(composed, params)
    bad = tmp_path / 'bad.yaml'
    bad.write_text('/**:\n  ros__parameters:\n    leg_length_offset: [0.0, 0.0]\n')
    broken = Namespace(compose=False, nodes='plant,controller,fk', plant_params=str(bad))
    assert 'leg_length_offset: expected 6 numbers' in plant_params_problem(broken, params)
