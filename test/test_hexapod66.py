"""The packaged 6-6 (config/hexapod66.yaml) and what a 6-6 gets from the core:
its parameter file's checks, the refusals at load (legs that cannot reach the
start pose, a singular start), forward kinematics through the core's one entry
point (``ForwardKinematics``, ``FKTracker``), and the plant's path (end stops
and faults per leg, ``sim``). Core-level and in-process: cheap.

The 6-6's dynamics are checked in test/test_dynamics.py (energy balances,
Lagrange) and test/test_mujoco.py (10 s against MuJoCo); its all-modes solver
against brute force in test/test_fk66.py; its install beside the 6-3's file in
test/test_colcon.py.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from stewart63_ros.core.mechanics.fk import FKTracker, ForwardKinematics
from stewart63_ros.core.mechanics.fk66 import ForwardKinematics66
from stewart63_ros.core.mechanics.kinematics import leg_lengths
from stewart63_ros.core.mechanics.rotation import rotation_from_euler
from stewart63_ros.core.plumbing.errors import ParameterError
from stewart63_ros.core.plumbing.params import (
    file_parameters,
    load_setup,
    read_parameter_file,
    unknown_keys,
)

REPO = Path(__file__).resolve().parents[1]
HEXAPOD66 = REPO / 'config' / 'hexapod66.yaml'


@pytest.fixture(scope='module')
def setup66():
    return load_setup(HEXAPOD66)


@pytest.fixture(scope='module')
def mech66(setup66):
    return setup66.mechanism


def _azimuths(points):
    return np.degrees(np.arctan2(points[:, 1], points[:, 0])) % 360


# -- the packaged file --
def test_the_packaged_6_6_is_the_semi_regular_hexapod_its_comments_describe(mech66):
    """Six base and six platform joints, each side in three close pairs, the
    platform's pairs turned 60 deg against the base's; radii 1.2 m and 0.6 m."""
    assert mech66.layout == '6-6'
    base, plat = np.asarray(mech66.base_points), np.asarray(mech66.platform_points)
    np.testing.assert_allclose(np.linalg.norm(base, axis=1), 1.2, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(plat, axis=1), 0.6, atol=1e-5)
    np.testing.assert_allclose(_azimuths(base), [350, 10, 110, 130, 230, 250], atol=1e-4)
    np.testing.assert_allclose(_azimuths(plat), [310, 50, 70, 170, 190, 290], atol=1e-4)
    # no two legs share a joint, and each base pair's legs go to two platform pairs
    assert len({tuple(p) for p in np.round(plat, 6)}) == 6


def test_the_packaged_6_6_passes_the_parameter_files_checks(setup66):
    """No unknown key, the same sections and clock mode as the packaged 6-3,
    and the setup round-trips through its flat dictionary."""
    assert unknown_keys(file_parameters(str(HEXAPOD66))) == []
    doc = yaml.safe_load(HEXAPOD66.read_text())
    ours = yaml.safe_load((REPO / 'config' / 'stewart63.yaml').read_text())
    # and a supervisor section: the lower stops for the homing (docs/supervisor.md)
    assert sorted(doc) == sorted([*ours, '/**/supervisor'])
    assert read_parameter_file(HEXAPOD66, node_name='supervisor')['homing_direction'] == 'retract'
    assert sorted(doc['/**']['ros__parameters']) == sorted(ours['/**']['ros__parameters'])
    assert doc['/**']['ros__parameters']['clock_mode'] == \
        ours['/**']['ros__parameters']['clock_mode']
    assert read_parameter_file(HEXAPOD66, node_name='plant')['sensor_rate'] == 1000.0
    again = setup66.replace()
    np.testing.assert_array_equal(again.mechanism.platform_points,
                                  setup66.mechanism.platform_points)
    # the paper's initial state (10 cm higher) and gains; its step sized to this
    # machine (2-5.5 cm a leg, the 6-3's 3.4-5.8 cm) to a pose inside the default pose_box
    np.testing.assert_array_equal(setup66.task.initial_position, [0.01, 0.01, 1.1])
    np.testing.assert_array_equal(setup66.gains.kp, [4000.0] * 6)
    step = setup66.task.setpoint_lengths - leg_lengths(
        setup66.mechanism, setup66.task.initial_position, setup66.task.initial_rotation)
    assert 0.015 < step.min() and step.max() < 0.06, step


# -- refusals at load --
def test_a_start_the_legs_cannot_reach_is_refused_naming_every_leg(setup66):
    """0.3 m sideways: legs 1 and 2 are too short for the stroke; both named."""
    with pytest.raises(ParameterError) as info:
        setup66.replace(initial_position=[0.3, 0.0, 1.0])
    assert info.value.key == 'initial_position'
    lengths = leg_lengths(setup66.mechanism, np.array([0.3, 0.0, 1.0]),
                          setup66.task.initial_rotation)
    short = {i + 1 for i in np.flatnonzero(lengths < setup66.mechanism.leg_length_min)}
    named = {int(n) for n in re.findall(r'leg_(\d)', str(info.value))}
    assert short == named == {1, 2}
    assert 'are outside the stroke' in str(info.value)


def test_a_singular_start_is_refused_naming_the_legs(setup66):
    """The platform turned 90 deg about the vertical over the base centre: the
    semi-regular hexapod's classic (Fichter) singularity, condition ~1e16."""
    fk = ForwardKinematics(setup66.mechanism)
    turned = rotation_from_euler([0.0, 0.0, np.pi / 2])
    assert fk.condition([0.0, 0.0, 1.4], turned) > 1e12
    with pytest.raises(ParameterError) as info:
        setup66.replace(initial_position=[0.0, 0.0, 1.4], initial_orientation=[0.0, 0.0, np.pi / 2],
                        initial_velocity=[0.0] * 3, initial_orientation_rate=[0.0] * 3)
    assert info.value.key == 'initial_position'
    assert 'singular' in str(info.value)
    assert re.search(r'legs \d(, \d)+', str(info.value))
    # 10 deg away it is not singular, and loads
    setup66.replace(initial_position=[0.0, 0.0, 1.4], initial_orientation=[0.0, 0.0, 1.4])


def test_a_6_3_whose_legs_meet_in_one_point_is_refused_as_singular(setup):
    """A platform shrunk to a 50 um triangle: every leg passes next to one
    point, so the legs can hardly resist a moment (condition 4e4)."""
    tiny = (np.asarray(setup.mechanism.platform_points) * 1e-4).ravel().tolist()
    with pytest.raises(ParameterError, match='singular'):
        setup.replace(platform_points=tiny)


# -- forward kinematics through the core's entry points --
def test_forward_kinematics_of_a_6_6_finds_every_mode_and_the_true_pose(mech66, setup66):
    """``ForwardKinematics`` on a 6-6 is fk66's homotopy: the same modes, the
    true pose among them, ordered from the run's start."""
    pose = (np.array([0.05, -0.08, 1.35]), rotation_from_euler([0.06, -0.04, 0.1]))
    lengths = leg_lengths(mech66, *pose)
    start = (setup66.task.initial_position, setup66.task.initial_rotation)
    modes = ForwardKinematics(mech66, start=start).all_modes(lengths)
    direct = ForwardKinematics66(mech66.base_points, mech66.platform_points,
                                 reference=start).all_modes(lengths)
    assert len(modes) == len(direct) >= 2
    for a, b in zip(modes, direct):
        np.testing.assert_allclose(a.position, b.position, atol=1e-9)
    np.testing.assert_allclose(modes[0].position, pose[0], atol=1e-9)
    np.testing.assert_allclose(modes[0].rotation, pose[1], atol=1e-9)
    for mode in modes:
        np.testing.assert_allclose(leg_lengths(mech66, mode.position, mode.rotation), lengths,
                                   atol=1e-9)
    with pytest.raises(ValueError, match='6-6'):
        ForwardKinematics(mech66).circles(lengths)


def test_tracking_a_6_6_follows_it_and_flags_the_singularity(mech66):
    """``FKTracker`` on a 6-6 (Newton from the last pose): it follows a turn
    about the vertical sample by sample and flags the samples next to 90 deg
    (condition 21 at 80 deg, 206 at 89 deg, infinite at 90)."""
    fk = ForwardKinematics(mech66, cond_threshold=150.0)
    tracker = FKTracker(fk, np.array([0.0, 0.0, 1.4]), np.eye(3))
    flagged = []
    for angle in np.linspace(0.0, np.radians(89.5), 180):
        pose = (np.array([0.0, 0.0, 1.4]), rotation_from_euler([0.0, 0.0, angle]))
        result = tracker.solve(leg_lengths(mech66, *pose), np.zeros(6))
        np.testing.assert_allclose(result.rotation, pose[1], atol=1e-8)
        assert not result.fallback
        np.testing.assert_allclose(result.omega, 0.0, atol=1e-9)
        flagged.append(result.singular)
    assert not any(flagged[:60]) and flagged[-1]
    assert result.condition > 150.0


# -- the plant's path --
def test_the_plant_path_on_a_6_6_has_end_stops_and_faults_per_leg(setup66):
    """Sampled as the lockstep plant runs it (``run_faulted``): leg 4 asked
    past its stroke rests on its end stop alone; a dead actuator on leg 2
    applies no force while the others do."""
    from stewart63_ros.core.controllers.laws import PDController
    from stewart63_ros.core.controllers.simulate import run_faulted
    from stewart63_ros.core.mechanics.dynamics import Dynamics
    mech = setup66.mechanism
    law = PDController(setup66, setpoint=[1.6, 1.6, 1.6, 2.3, 1.6, 1.6])
    dyn = Dynamics(mech)
    result = run_faulted(setup66, 1.5, 1000.0, ['actuator_dead:leg_2@0.5'], controller=law,
                         dyn=dyn)
    lengths = np.array([dyn.lengths_and_rates(y)[0] for y in result.states])
    past = lengths > mech.leg_length_max
    assert past[:, 3].any() and not past[:, [0, 1, 2, 4, 5]].any()
    assert result.endstop_samples == int(np.any(past | (lengths < mech.leg_length_min),
                                                 axis=1).sum())
    # the end stop holds leg 4 within millimetres (2e6 N/m against 3000 N at most)
    assert lengths[:, 3].max() < mech.leg_length_max + 3e-3
    dead = result.times >= 0.5
    assert np.all(result.applied[dead, 1] == 0.0) and np.any(result.forces[dead, 1] != 0.0)
    others = [0, 2, 3, 4, 5]
    assert np.all(result.applied[dead][:, others] == result.forces[dead][:, others])



def test_the_packaged_6_6_runs_its_task_under_the_packaged_supervisor_limits(setup66):
    """``rig --params config/hexapod66.yaml --supervisor`` as the core runs it
    (``run_supervised``, sample for sample): every limit at its default
    (trip_leg_speed 0.5 m/s, pose_box +-0.3 m), no trip through the step. (The
    paper's own lengths, the file's task before, tripped leg_speed at sample 2.)"""
    from stewart63_ros.core.machine.supervisor import run_supervised, supervisor_from_params
    sup = supervisor_from_params(setup66, setup66.to_params(), 1000.0)
    out = run_supervised(setup66, sup, 0.5, 1000.0)     # the fastest leg at 0.04 s
    assert sup.trips == []
    np.testing.assert_array_equal(out['forces'], out['requests'])
    speed = np.abs(np.diff(out['lengths'], axis=0)).max() * 1000.0
    assert 0.2 < speed < 0.5, speed          # the fastest leg: 0.35 m/s

def test_sim_runs_the_packaged_6_6(tmp_path, capsys):
    """``sim --params config/hexapod66.yaml``: the paper's scenario, sampled
    at the plant's 1 kHz; 2 s here (10 s of continuous PD end at 0.792 %, README)."""
    from stewart63_ros.tools import sim
    out = tmp_path / 'run'
    assert sim.main(['--params', str(HEXAPOD66), '--duration', '2', '--out', str(out),
                     '--control', 'sampled', '--no-figure']) == 0
    printed = capsys.readouterr().out
    assert 'positioning_error_percent' in printed
    assert re.search(r'^endstop_samples\s+0$', printed, re.M), printed
    assert (out / 'trajectory.csv').is_file()


def test_make_demo_runs_the_packaged_6_6(ros, tmp_path):
    """``make demo GEOMETRY=6-6``: the demo's whole rig (composed, recorded,
    its figure drawn) on config/hexapod66.yaml; 0.5 s here."""
    import subprocess

    from ros_harness import PYTHON, child_env
    done = subprocess.run([PYTHON, '-m', 'stewart63_ros.tools.demo', '--geometry', '6-6',
                           '--duration', '0.5', '--out', str(tmp_path)],
                          env=child_env(ros.domain_id), capture_output=True, text=True,
                          timeout=240)
    assert done.returncode == 0, (done.stdout, done.stderr)
    assert 'on the 6-6, hexapod66.yaml' in done.stdout, done.stdout
    figure = next(tmp_path.glob('run-*/figure.png'))
    assert figure.stat().st_size > 10_000


# -- a 6-6 nobody tuned for the rig (test_calibration_flight.py's hexapod B) --------------------
@pytest.fixture(scope='module')
def hexapod_b_file(tmp_path_factory):
    from test_calibration_flight import hexapod_b_params
    path = tmp_path_factory.mktemp('hexapod_b') / 'hexapod_b.yaml'
    path.write_text(yaml.safe_dump({'/**': {'ros__parameters': hexapod_b_params()}}))
    return path


def test_a_6_6_nobody_tuned_agrees_with_mujoco(hexapod_b_file):
    """Hexapod B (small, yaw-soft, its joints off the frames' planes): MuJoCo's
    model of the same file against our dynamics, continuous PD. 3 s here;
    by hand over 10 s: 1.7e-8 m at 1 ms, 4.3e-9 m at 0.5 ms (the issue's bar 1e-6)."""
    from test_mujoco import _assert_within_convergence, _gaps
    coarse, fine = _gaps(load_setup(hexapod_b_file), 3.0, (1e-3, 5e-4))
    _assert_within_convergence(coarse, fine)
    assert fine['gap_L'] < 1e-6 and fine['gap_pos'] < 1e-6 and fine['gap_rot'] < 1e-6
    assert fine['violation'] < 1e-6


def test_a_6_6_nobody_tuned_runs_sim_and_the_supervised_bus_rig(ros, hexapod_b_file, tmp_path,
                                                                 capsys):
    """One short lockstep rig for several tools at once: the rig, the
    supervisor and the CANopen bus on hexapod B's file; it ends where ``sim``'s
    sampled loop does, but for the bus's force quantisation (by hand, 1 s at
    500 Hz: 0.9740 % against 0.9779 %)."""
    from stewart63_ros.tools import sim
    assert sim.main(['--params', str(hexapod_b_file), '--duration', '1', '--control',
                     'sampled', '--no-figure', '--out', str(tmp_path / 'sim')]) == 0
    expected = float(re.search(r'^positioning_error_percent\s+(\S+)$',
                               capsys.readouterr().out, re.M).group(1))
    proc = ros.python('-m', 'stewart63_ros.tools.rig', '--params', str(hexapod_b_file),
                      '--mode', 'lockstep', '--supervisor', '--bus', 'canopen',
                      '--duration', '1', '--log-dir', str(tmp_path / 'logs'), name='rig')
    assert proc.wait(240) == 0, proc.describe()
    out = proc.stdout()
    assert 'supervisor: no trip' in out, out
    assert re.search(r'canopen_bridge: .* missed cycles 0, force timeouts 0', out), out
    final = float(re.search(r'final positioning error: (\S+) %', out).group(1))
    assert abs(final - expected) < 0.02, (final, expected)
