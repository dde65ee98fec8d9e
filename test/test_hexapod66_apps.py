"""Everything that knows the mechanism, on a 6-6, in the core:
each once, cheaply, against what does not share its arithmetic.

The 6-6 is test/geometry66.py's: the packaged 6-3 with each vertex split into
two joints 6 cm apart and the base turned 1 deg; its parameter file is
written here (``params66``). The 6-3's own tests stay as they are.

- control laws: ``pd`` sags, ``pd_gravity`` removes the sag, its holding forces
  equal the virtual-work answer, ``computed_torque`` tracks a six-axis reference;
- supervisor: the rest pose, the pose box, homing to the upper stops (offsets
  recovered), the lower stops refused naming the pair that cannot reach them;
- analysis: the linear model against the nonlinear one, modes, the frequency
  response at 0 Hz, the workspace against inverse kinematics, a sweep's row
  against ``sim``'s arithmetic, ``analyze modes`` on the file;
- markers: six platform joints, the legs ending on them, a hexagon plate;
  ``flat`` equals the shapes; the ghost's pose read back from its plate;
- scenarios: a scenario pointing at a 6-6 parameter file, and one giving
  18 ``platform_points`` over a 6-3 file.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from geometry66 import setup66, split_platform_points
from scipy.spatial.transform import Rotation
from test_analysis import DIRECTION, linear_step, nonlinear_step
from test_laws import potential, six_axis_reference

from stewart63_ros.core.analysis import linear, modal
from stewart63_ros.core.analysis.workspace import workspace_map
from stewart63_ros.core.controllers.laws import Controller, PDGravityLaw
from stewart63_ros.core.controllers.reference import Reference
from stewart63_ros.core.controllers.simulate import run_continuous, run_sampled
from stewart63_ros.core.controllers.tracking import tracking_errors
from stewart63_ros.core.machine.supervisor import (
    limits_from_params,
    rest_lengths,
    run_supervised,
    supervisor_from_params,
)
from stewart63_ros.core.mechanics import markers as M
from stewart63_ros.core.mechanics.dynamics import Dynamics
from stewart63_ros.core.mechanics.kinematics import jacobian, leg_lengths
from stewart63_ros.core.mechanics.rotation import rotation_from_euler
from stewart63_ros.core.plumbing.params import ParameterError, load_setup

RATE = 1000.0
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope='module')
def setup(default_setup):
    return setup66(default_setup)


@pytest.fixture(scope='module')
def mech(setup):
    assert setup.mechanism.layout == '6-6'
    return setup.mechanism


@pytest.fixture(scope='module')
def dyn(mech):
    return Dynamics(mech)


@pytest.fixture(scope='module')
def params66(setup, tmp_path_factory):
    """The 6-6 as a parameter file, as a lab would write it (18 platform numbers)."""
    path = tmp_path_factory.mktemp('hexapod66') / 'hexapod66.yaml'
    path.write_text(yaml.safe_dump({'/**': {'ros__parameters': setup.to_params()}}))
    return path


# -- control laws -------------------------------------------------------------------------------
def test_pd_gravity_removes_the_sag_pd_leaves_on_a_6_6(setup, dyn):
    errors = {name: run_sampled(setup, 3.0, RATE, dyn=dyn, controller=Controller(setup, law=name))
              .final_leg_error_percent(dyn, setup.task.setpoint_lengths).max()
              for name in ('pd', 'pd_gravity')}
    print('\n6-6, 3 s at 1 kHz: final error pd %.4f %%, pd_gravity %.3g %%'
          % (errors['pd'], errors['pd_gravity']))
    assert 0.5 < errors['pd'] < 1.5
    assert errors['pd_gravity'] < 0.01


def test_a_6_6_whose_pairs_nearly_meet_runs_as_the_6_3(default_setup):
    """Pairs 10 µm apart, the base not turned: the 6-6's model (its own joint per
    leg everywhere) runs the paper's scenario as the 6-3's does, to what 10 µm
    can change."""
    near = setup66(default_setup, split=1e-5, base_turn=0.0)
    runs = [run_sampled(s, 1.0, RATE, controller=Controller(s, law='pd_gravity'))
            for s in (default_setup, near)]
    gap = np.abs(runs[1].states - runs[0].states).max()
    print('\n6-6 with pairs 10 um apart against the 6-3: largest state difference %.2e' % gap)
    assert gap < 1e-4
    assert np.abs(runs[1].forces - runs[0].forces).max() < 1.0


def test_holding_forces_on_a_6_6_equal_the_virtual_work_answer(setup, mech, dyn):
    law = PDGravityLaw(mech, setup.to_params())
    rng = np.random.default_rng(4)
    worst, h = 0.0, 1e-6
    for _ in range(3):
        position = setup.task.initial_position + rng.uniform(-0.05, 0.05, 3)
        rotation = rotation_from_euler(setup.task.initial_orientation + rng.uniform(-0.1, 0.1, 3))
        grad = np.empty(6)
        for k in range(6):
            d = np.zeros(3)
            d[k % 3] = h
            if k < 3:
                plus, minus = (potential(dyn, position + d, rotation),
                               potential(dyn, position - d, rotation))
            else:
                plus = potential(dyn, position, Rotation.from_rotvec(d).as_matrix() @ rotation)
                minus = potential(dyn, position, Rotation.from_rotvec(-d).as_matrix() @ rotation)
            grad[k] = (plus - minus) / (2 * h)
        work = jacobian(mech, rotation, position).T @ law.holding_forces(position, rotation)
        worst = max(worst, np.max(np.abs(work - grad)) / np.max(np.abs(grad)))
    assert worst < 1e-6


def test_computed_torque_tracks_a_six_axis_reference_on_a_6_6(setup, mech, dyn):
    ref = Reference.from_poses(mech, *six_axis_reference(setup, 4.0))   # on past the run
    result = run_sampled(setup, 3.0, RATE, dyn=dyn,
                         controller=Controller(setup, law='computed_torque', reference=ref))
    e = tracking_errors(mech, ref, result.times, result.states, after=1.5)
    print('\n6-6 computed_torque after 1.5 s: position max %.3e m, orientation max %.3e rad'
          % (e['position_max_m'], e['orientation_max_rad']))
    assert e['position_max_m'] < 1e-4 and e['orientation_max_rad'] < 1e-4


# -- supervisor -----------------------------------------------------------------------------------
@pytest.fixture(scope='module')
def sup_params(setup):
    # The paper's step moves this 6-6's leg 3 at 0.502 m/s for a sample: over the
    # packaged 0.5 m/s trip_leg_speed (the 6-3's fastest leg: 0.498 m/s).
    return dict(setup.to_params(), trip_leg_speed=0.6)


def test_the_rest_pose_of_a_6_6_is_level_inside_the_soft_stroke(setup, mech, sup_params):
    limits = limits_from_params(mech, sup_params)
    rest = rest_lengths(setup, limits)
    assert rest.min() == pytest.approx(limits.soft_min + limits.rest_clearance, abs=1e-9)
    assert rest.max() < limits.soft_max
    # level: the lengths of a level pose over the start's x, y (bisection on z, checked here)
    x, y = setup.task.initial_position[:2]
    z = np.linspace(0.2, 2.0, 2001)
    shortest = [leg_lengths(mech, [x, y, zz], np.eye(3)).min() for zz in z]
    z_rest = np.interp(rest.min(), shortest, z)
    np.testing.assert_allclose(leg_lengths(mech, [x, y, z_rest], np.eye(3)), rest, atol=1e-5)


def test_the_supervisor_passes_the_paper_scenario_and_trips_the_box_on_a_6_6(setup, mech,
                                                                             sup_params):
    sup = supervisor_from_params(setup, sup_params, RATE)
    out = run_supervised(setup, sup, 1.0, RATE)
    assert sup.trips == []
    np.testing.assert_array_equal(out['forces'], out['requests'])
    # the setpoint's pose is 7 cm above the start: a box under it trips on the way up
    low = dict(sup_params, pose_box=[-0.3, -0.3, 0.5, 0.3, 0.3, 1.04])
    sup = supervisor_from_params(setup, low, RATE)
    run_supervised(setup, sup, 1.0, RATE)
    assert sup.trips and sup.trips[0].cause == 'pose_box' and 'z = 1.04' in sup.trips[0].detail
    # readings no pose has: legs 1 and 2 too short to reach their joints 6 cm apart
    sup = supervisor_from_params(setup, sup_params, RATE)
    lying = np.where(np.arange(6) < 2, 1.3, setup.task.setpoint_lengths)
    sup.on_sample(0, lying, np.zeros(6))
    assert sup.trip.cause == 'pose_box' and 'no pose has these leg lengths' in sup.trip.detail


def test_the_packaged_6_6_homes_to_its_lower_stops_and_recovers_the_offsets():
    """config/hexapod66.yaml homes with ``retract`` (docs/supervisor.md, "Which
    stops"): every offset within the sensor's resolution, and the legs reached
    their lower stops. (To its upper stops a leg pushed back by the others
    stalls short of its stop and is taken for it: leg 6 1.3 mm early.)"""
    from stewart63_ros.core.controllers.sensor import SensorModel
    setup = load_setup(REPO / 'config' / 'hexapod66.yaml')
    mech = setup.mechanism
    resolution = 1e-4
    hidden = np.array([3.0, -2.0, 5.0, 0.0, -4.0, 1.2]) * 1e-3
    # the packaged limits (trip_leg_speed 0.5 m/s, pose_box +-0.3 m): the homing and
    # the file's step after it pass them
    params = dict(setup.to_params(), homing=True, homing_speed=0.2, homing_direction='retract')
    sup = supervisor_from_params(setup, params, RATE)
    out = run_supervised(setup, sup, 3.3, RATE, homing_offset=hidden,   # homed at 3.1 s
                         sensor=SensorModel({'sensor_resolution': resolution}))
    assert sup.homed and sup.trips == []
    assert np.all(np.abs(sup.offsets - hidden) <= resolution), sup.offsets - hidden
    assert np.all(out['lengths'].min(axis=0) < mech.leg_length_min)


def test_homing_a_6_6_to_stops_no_pose_reaches_is_refused_naming_the_pair(setup, sup_params):
    """As on the packaged 6-3, this 6-6's legs 1 and 2 reach joints 6 cm apart
    over base points 2.95 m apart: they cannot both be 1.2 m long, so the
    lower stops are refused. The packaged hexapod66 (base pairs 0.42 m apart)
    can home either way."""
    with pytest.raises(ParameterError) as exc:
        supervisor_from_params(setup, dict(sup_params, homing=True,
                                           homing_direction='retract'), RATE)
    assert exc.value.key == 'homing_direction'
    assert 'legs 1 and 2 cannot both be 1.2 m long' in str(exc.value), str(exc.value)


# -- analysis ----------------------------------------------------------------------------------
def test_linear_model_modes_and_dc_gain_of_a_6_6(setup, mech, dyn):
    open_model = linear.linearize(setup, None)
    pd_model = linear.linearize(setup, 'pd')
    times = np.linspace(0.0, 0.4, 9)
    for model, size in ((open_model, 2.0), (pd_model, 2e-3)):
        du = size * DIRECTION
        lin = linear_step(model, du, times)
        gap = np.abs(nonlinear_step(dyn, model, du, times, setup) - lin).max()
        half = np.abs(nonlinear_step(dyn, model, du / 2, times, setup)
                      - linear_step(model, du / 2, times)).max()
        print('\n6-6 %s loop: nonlinear - linear %.3e, half the step %.3e (ratio %.3f)'
              % ('closed' if model.closed_loop else 'open', gap, half, gap / half))
        assert gap < 1e-2 * np.abs(lin).max() and 3.5 < gap / half < 4.5   # second order
    closed = modal.modes(pd_model)
    assert len(closed.frequencies_hz) == 6 and np.all(closed.stable)
    assert not np.all(modal.modes(open_model).stable)      # the platform falls without control
    # 0 Hz: the static gain -C A^-1 B; the pd loop holds every leg at its reference
    dc = modal.frequency_response(pd_model, [0.0])[0]
    np.testing.assert_allclose(dc, -pd_model.C @ np.linalg.solve(pd_model.A, pd_model.B),
                               atol=1e-9)
    assert np.allclose(np.diag(dc.real), 1.0, atol=0.05)


def test_workspace_of_a_6_6_agrees_with_inverse_kinematics(mech, dyn):
    rot = rotation_from_euler([0.1, -0.05, 0.2])
    result = workspace_map(mech, rot, 0.2, bounds=(-1.0, 1.0, -1.0, 1.0, 0.4, 2.0))
    assert {'ok', 'stroke'} <= set(result.reason.tolist())
    zero = np.zeros(3)
    for k in np.random.default_rng(2).choice(len(result.points), 60, replace=False):
        p = result.points[k]
        lengths = leg_lengths(mech, p, rot)
        assert np.allclose(lengths, result.lengths[k], atol=1e-12)
        outside = np.any(lengths < mech.leg_length_min) or np.any(lengths > mech.leg_length_max)
        assert (result.reason[k] == 'stroke') == outside
        if result.reason[k] == 'ok':
            forces = dyn.inverse_dynamics(rot, p, zero, zero, zero, zero)
            assert result.max_force[k] == pytest.approx(np.abs(forces).max(), rel=1e-9)


def test_a_sweep_row_of_a_6_6_is_sims_arithmetic(params66):
    from stewart63_ros.core.analysis import sweep, sweep_plan
    variations = [sweep_plan.parse_vary('platform_points[4]=0.40:0.46')]
    plan = sweep_plan.make_plan(params66, variations, duration=2.0)
    row = sweep.run_one(plan, [0.43])
    assert row['diverged'] == 0, row
    run_setup = load_setup(params66, 'plant', {'platform_points': np.r_[
        load_setup(params66).mechanism.to_params()['platform_points'][:4], 0.43,
        load_setup(params66).mechanism.to_params()['platform_points'][5:]].tolist()})
    assert run_setup.mechanism.layout == '6-6'
    dyn = Dynamics(run_setup.mechanism)
    result = run_continuous(run_setup, 2.0, dyn=dyn)
    assert row['final_error_percent'] == result.final_leg_error_percent(
        dyn, run_setup.task.setpoint_lengths).max()


def test_analyze_modes_reads_a_6_6_file(params66, capsys):
    from stewart63_ros.tools import analyze
    assert analyze.main(['modes', '--params', str(params66), '--control-law', 'pd',
                         '--json']) == 0
    doc = json.loads(capsys.readouterr().out)
    assert len(doc['frequencies_hz']) == 6 and np.shape(doc['mode_shapes']) == (6, 6)
    expected = modal.modes(linear.linearize(load_setup(params66), 'pd'))
    assert np.allclose(doc['frequencies_hz'], expected.frequencies_hz)


# -- markers -------------------------------------------------------------------------------------
def test_markers_draw_six_platform_joints_and_the_legs_end_on_them(setup, mech):
    rot = Rotation.from_euler('xyz', [0.05, -0.03, 0.1]).as_matrix()
    t = np.array([0.02, -0.01, 1.05])
    joints = t + mech.platform_points @ rot.T           # independent: from the file's numbers
    lengths = np.linalg.norm(joints - mech.base_points, axis=1)
    scene = M.Scene(mech)
    shapes = {(s.ns, s.id): s for s in scene.shapes(t, rot, lengths, np.zeros(6), (t, rot))}
    np.testing.assert_allclose(shapes[('platform_joints', 0)].points, joints, atol=1e-12)
    for i in range(6):
        np.testing.assert_allclose(shapes[('piston', i)].points[1], joints[i], atol=1e-12)
    plate = shapes[('platform', 0)].points
    assert plate.shape == (24, 3)                       # 4 triangles, both windings
    # the hexagon covers the joints' polygon: its area is the shoelace area of the six
    # joints in turn about their centre (platform frame, z = 0)
    p = mech.platform_points[:, :2]
    ring = p[np.argsort(np.arctan2(*(p - p.mean(0)).T[::-1]))]
    shoelace = 0.5 * abs(np.dot(ring[:, 0], np.roll(ring[:, 1], -1))
                         - np.dot(ring[:, 1], np.roll(ring[:, 0], -1)))
    tri = plate[:12].reshape(4, 3, 3)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    assert area.sum() == pytest.approx(shoelace, rel=1e-9)
    ghost_legs = shapes[('ghost_legs', 0)].points
    np.testing.assert_allclose(ghost_legs[1::2], joints, atol=1e-12)
    # the vectorized numbers are those of the shapes, shown and hidden ghost alike
    for ghost in ((t + 0.1, rot), None):
        a8, a4 = M.flatten(scene.shapes(t, rot, lengths, np.zeros(6), ghost))
        b8, b4 = scene.flat(t, rot, lengths, np.zeros(6), ghost)
        assert a8.shape == b8.shape and np.allclose(a8, b8, rtol=0, atol=1e-12)
        assert np.array_equal(a4, b4)
    # the 6-3 is drawn as before: one triangle, three vertices
    tri63 = M.Scene(load_setup().mechanism)
    assert tri63.plate_faces.tolist() == [[0, 1, 2]]


def test_the_fk_nodes_marker_bytes_of_a_6_6_are_the_message_built_field_by_field(setup, mech):
    """The serialized template the fk node fills (24 markers, a 6-6's longer
    point lists) decodes to the MarkerArray rclpy builds from the same shapes."""
    from rclpy.serialization import deserialize_message, serialize_message
    from visualization_msgs.msg import MarkerArray

    from stewart63_ros.nodes.markers import MarkerArrayBuilder, MarkerTemplate
    scene = M.Scene(mech)
    template = MarkerTemplate(scene.shapes(setup.task.initial_position, np.eye(3)))
    rot = Rotation.from_euler('xyz', [0.02, 0.04, -0.1]).as_matrix()
    t = np.array([0.03, 0.0, 1.1])
    shapes = scene.shapes(t, rot, None, np.array([100.0, -200, 3000, 0, 0, 5]), (t, rot))
    got = deserialize_message(template.fill(1234, 5678, *M.flatten(shapes)), MarkerArray)
    want = deserialize_message(serialize_message(MarkerArrayBuilder().build(shapes, 1234, 5678)),
                               MarkerArray)
    assert len(got.markers) == len(want.markers) == len(shapes)
    for a, b in zip(got.markers, want.markers):
        assert a == b, (a.ns, a.id)
    joints = {m.ns: m for m in got.markers}['platform_joints']
    assert len(joints.points) == 6


def test_the_views_ghost_pose_is_read_back_from_a_6_6_plate(mech):
    from stewart63_ros.tools.view_sources import _pose_from_vertices
    rot = Rotation.from_euler('xyz', [0.2, -0.1, 0.4]).as_matrix()
    t = np.array([0.1, -0.05, 1.2])
    scene = M.Scene(mech)
    plate = {s.ns: s for s in scene.ghost_shapes((t, rot))}['ghost'].points
    joints = M.plate_faces(mech.platform_points).ravel()
    position, rotation = _pose_from_vertices(plate[:joints.size], mech, joints)
    np.testing.assert_allclose(position, t, atol=1e-12)
    np.testing.assert_allclose(rotation, rot, atol=1e-12)


# -- scenarios -----------------------------------------------------------------------------------
def test_a_scenario_runs_a_6_6_parameter_file(params66, default_setup, tmp_path):
    from stewart63_ros.core.scenarios.parsing import load_scenarios
    from stewart63_ros.core.scenarios.running import run_sim
    from stewart63_ros.core.scenarios.verdicts import evaluate
    split = split_platform_points(default_setup.mechanism.platform_points, 0.06).ravel()
    (tmp_path / 'hexapod66.yaml').write_text(params66.read_text())
    path = tmp_path / 'six.yaml'
    path.write_text('scenarios:\n'
                    '  - name: file66\n'
                    '    params_file: hexapod66.yaml\n'
                    '    duration: 2.0\n'
                    '    control_law: pd_gravity\n'
                    '    expect:\n'
                    '      final_error_percent: {max: 0.01}\n'
                    '  - name: points66\n'
                    '    duration: 0.5\n'
                    '    params:\n'
                    '      platform_points: %s\n'
                    '    expect:\n'
                    '      endstop_samples: {max: 0}\n' % split.tolist())
    file66, points66 = load_scenarios(path)
    assert file66.params_file == str(tmp_path / 'hexapod66.yaml')
    verdicts = evaluate(run_sim(file66), file66.expect)
    assert all(v.passed for v in verdicts), [v.text for v in verdicts]
    trace = run_sim(points66)
    assert all(v.passed for v in evaluate(trace, points66.expect))
