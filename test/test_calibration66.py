"""Calibration of a 6-6: 18 platform coordinates, 42 parameters.

- the Jacobian of a 6-6's model against finite differences;
- a simulated 6-6 built off its drawing (points 5 mm, offsets 10 mm) is
  recovered within three reported standard deviations;
- what the poses cannot see is named per leg (a 6-6's legs share no parameter);
- a 6-3 machine whose pairs came apart: ``calibrate machine --geometry 6-6``
  builds it, ``calibrate fit --geometry 6-6`` on the 6-3 drawing finds each
  pair's separation and writes 18 numbers every node reads.
The 6-3's own tests are test_calibration.py (unchanged).
"""
from __future__ import annotations

import json

import numpy as np
import pytest
from geometry66 import setup66
from test_calibration import NOISE, tracked, write_measurements

from stewart63_ros.core.machine import calibration as cal
from stewart63_ros.core.machine import calibration_model as cal_model
from stewart63_ros.core.machine import calibration_plan as cp
from stewart63_ros.core.plumbing.params import load_setup
from stewart63_ros.tools import calibrate


@pytest.fixture(scope='module')
def setup(default_setup):
    return setup66(default_setup)


@pytest.fixture(scope='module')
def poses(setup):
    """40 random feasible poses of the 6-6 (seeded): cheaper than a plan, and enough."""
    return cp.candidate_poses(setup, 40, np.random.default_rng(4))


def built_off(theta, seed):
    """The machine of ``theta`` built off it: points up to 5 mm, offsets up to 10 mm."""
    rng = np.random.default_rng(seed)
    theta = np.array(theta, float)
    theta[:-6] += rng.uniform(-0.005, 0.005, theta.size - 6)
    theta[-6:] += rng.uniform(-0.01, 0.01, 6)
    return theta


def test_a_6_6_has_42_parameters_and_its_jacobian_matches_finite_differences(setup, poses):
    mech = setup.mechanism
    theta = cal_model.parameter_vector(mech)
    names = cal_model.parameter_names('6-6')
    assert theta.size == len(names) == 42 and names[18:21] == ('p_1.x', 'p_1.y', 'p_1.z')
    assert names[33:36] == ('p_6.x', 'p_6.y', 'p_6.z') and names[-1] == 'offset_6'
    meas = cal_model.Measurements(poses[0][:5], poses[1][:5], np.zeros((5, 6)))
    jac = cal_model.parameter_jacobian(theta, meas)
    step = 1e-6
    for j in range(theta.size):
        d = np.zeros(theta.size)
        d[j] = step
        numeric = (cal_model.predict_readings(theta + d, meas)
                   - cal_model.predict_readings(theta - d, meas)) / (2 * step)
        assert np.allclose(jac[:, :, j], numeric, atol=1e-7), names[j]
    # leg i sees its own joint only
    assert np.all(jac[:, :, 18:36].reshape(5, 6, 6, 3).any(axis=(0, 3)) == np.eye(6, dtype=bool))
    # the readings of the drawing are its inverse kinematics plus the offsets
    legs = poses[0][:5, None] + np.einsum('nab,ib->nia', poses[1][:5],
                                          mech.leg_platform_points) - mech.base_points
    np.testing.assert_allclose(cal_model.predict_readings(theta, meas),
                               np.linalg.norm(legs, axis=2) + mech.leg_length_offset, atol=1e-12)


def test_a_simulated_6_6_with_known_errors_is_recovered(setup, poses):
    mech = setup.mechanism
    truth = built_off(cal_model.parameter_vector(mech), 11)
    meas = tracked(truth, *poses, np.random.default_rng(3))
    result = cal.fit(mech, meas, NOISE)
    assert result.geometry == '6-6' and result.held.shape[1] == 0
    z = (result.estimate - truth) / result.std
    print('\n6-6 recovery: max |error| %.3g mm, max |error|/std %.2f, max std %.3g mm, '
          'noise scale %.3f' % (np.abs(result.estimate - truth).max() * 1e3, np.abs(z).max(),
                                result.std.max() * 1e3, result.noise_scale))
    assert np.all(np.abs(z) <= 3.0), dict(zip(result.names, np.round(z, 2)))
    assert 0.8 < result.noise_scale < 1.25
    assert result.rms_before > 2e-3 and result.rms_after < 2e-4
    calibrated = cal_model.mechanism_with(mech, result.estimate)
    assert calibrated.layout == '6-6' and calibrated.platform_points.shape == (6, 3)
    report = cal.report(result)
    assert report['geometry'] == '6-6' and list(report['parameters']) == list(result.names)
    assert report['pair_separations'] is None         # the drawing was a 6-6 already


def test_poses_at_one_orientation_leave_each_joint_with_its_base_point_unseen(setup, poses):
    """No gauge freedom (the tracker fixes both frames), but poses at one
    orientation cannot tell a joint from its base point: 3 combinations per
    leg, 18 for a 6-6 (9 for a 6-3, whose pair shares its vertex)."""
    truth = built_off(cal_model.parameter_vector(setup.mechanism), 12)
    level = np.repeat(np.eye(3)[None], len(poses[0]), axis=0)
    readings = cal_model.predict_readings(truth, cal_model.Measurements(poses[0], level,
                                                            np.zeros((len(level), 6))))
    with pytest.raises(cal_model.CalibrationError) as info:
        cal.fit(setup.mechanism, cal_model.Measurements(poses[0], level, readings), NOISE)
    text = str(info.value)
    assert 'leave 18 combinations unidentifiable' in text, text
    assert '{b_6.z, p_6.z}' in text or '{p_6.z, b_6.z}' in text
    assert 'each platform joint and its base point' in text
    # a 6-6 is not three vertices
    with pytest.raises(cal_model.CalibrationError, match='cannot be fitted as a 6-3'):
        cal.fit(setup.mechanism, cal_model.Measurements(poses[0], level, readings), NOISE,
                geometry='6-3')


def test_a_6_3_machine_whose_pairs_came_apart_is_fitted_as_a_6_6(default_setup, tmp_path,
                                                                capsys):
    """The packaged 6-3's drawing; the machine's pair joints 4, 0.5 and 6 mm apart
    (along the vertex circle's tangent, as the split of geometry66), its
    points and offsets off by millimetres. ``fit --geometry 6-6`` writes 18
    numbers, finds each separation within three reported standard
    deviations, and recovers the machine."""
    drawing = default_setup.mechanism
    split = np.array([0.004, 0.0005, 0.006])
    joints = drawing.leg_platform_points.copy()
    for k in range(3):
        p = joints[2 * k]
        tangent = np.array([-p[1], p[0], 0.0]) / np.hypot(p[0], p[1])
        joints[2 * k] -= 0.5 * split[k] * tangent
        joints[2 * k + 1] += 0.5 * split[k] * tangent
    truth = built_off(np.concatenate([np.ravel(drawing.base_points), np.ravel(joints),
                                      drawing.leg_length_offset]), 13)
    # the platform's joints off by 0.5 mm only, so that the splits stay what they are
    truth[18:36] = np.ravel(joints) + (truth[18:36] - np.ravel(joints)) * 0.1
    positions, rotations = cp.candidate_poses(default_setup, 40, np.random.default_rng(5))
    write_measurements(tmp_path / 'm.csv', tracked(truth, positions, rotations,
                                                   np.random.default_rng(6)))
    assert calibrate.main(['fit', '--measurements', str(tmp_path / 'm.csv'), '--geometry',
                           '6-6', '--holdout', '0', '--out', str(tmp_path / 'out')]) == 0
    out = capsys.readouterr().out
    assert 'a 6-6, 42 parameters' in out and 'legs 1 and 2 came' in out
    calibrated = load_setup(tmp_path / 'out' / 'calibrated.yaml').mechanism
    assert calibrated.layout == '6-6' and len(calibrated.to_params()['platform_points']) == 18
    report = json.loads((tmp_path / 'out' / 'report.json').read_text())
    assert report['geometry'] == '6-6' and len(report['singular_values']) == 42
    std = np.array([report['parameters'][n]['std'] for n in cal_model.parameter_names('6-6')])
    z = (cal_model.parameter_vector(calibrated) - truth) / std
    assert np.all(np.abs(z) <= 3.0), np.round(z, 2)
    true_joints = truth[18:36].reshape(6, 3)
    true_gap = np.linalg.norm(true_joints[1::2] - true_joints[0::2], axis=1)
    for pair, gap in zip(report['pair_separations'], true_gap):
        print('\nlegs %s: separation %.3f mm (std %.3f mm), true %.3f mm'
              % (pair['legs'], pair['separation_m'] * 1e3, pair['std_m'] * 1e3, gap * 1e3))
        assert abs(pair['separation_m'] - gap) <= 3 * pair['std_m'] + 1e-5


def test_calibrate_machine_geometry_6_6_moves_a_pairs_joints_apart(default_setup, tmp_path,
                                                                   capsys):
    """A simulated 6-3 machine whose pairs are not one joint: 18 numbers, the pair's
    two joints moved on their own; a 6-6 file asked for --geometry 6-3 is refused."""
    assert calibrate.main(['machine', '--geometry', '6-6', '--seed', '2', '--out',
                           str(tmp_path / 'machine.yaml')]) == 0
    machine = load_setup(tmp_path / 'machine.yaml').mechanism
    assert machine.layout == '6-6'
    gaps = np.linalg.norm(machine.platform_points[1::2] - machine.platform_points[0::2], axis=1)
    assert np.all((gaps > 1e-4) & (gaps < 0.02)), gaps
    assert calibrate.main(['machine', '--params', str(tmp_path / 'machine.yaml'), '--geometry',
                           '6-3', '--out', str(tmp_path / 'back.yaml')]) == 2
    assert 'cannot be fitted as a 6-3' in capsys.readouterr().err
    assert not (tmp_path / 'back.yaml').exists()


def test_a_plan_for_a_6_6_fit_sees_all_42_parameters(default_setup):
    """``plan --geometry 6-6`` on a 6-3 drawing: its index is of the 42-parameter fit."""
    plan = cp.plan(default_setup, 12, seed=1, candidates=60, geometry='6-6')
    blocks = cp._blocks(default_setup.mechanism, plan.positions, plan.rotations,
                        cal_model.NoiseModel(), '6-6')
    assert blocks.shape == (12, 6, 42) and plan.o3 > 0
    assert cp.indices(blocks, range(12))[1] == pytest.approx(plan.o3)
