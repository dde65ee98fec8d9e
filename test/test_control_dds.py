"""The controller's laws, references and run-time tuning over real DDS.

- ``ros2 param set`` (the SetParameters service): a new gain or law changes the
  very next force; a NaN, a wrong size, a negative gain, an unknown law and a
  model parameter are refused with a reason and the forces stay as they were;
- command inputs: a setpoint published latched before the controller started
  and one published with the default (volatile) QoS both take effect;
- ``pose_trajectory``: followed from its stamp; one outside the stroke is
  refused and the previous motion goes on;
- a law that raises: forces withheld, ERROR on /diagnostics, the node stays up;
- the lockstep rig with ``--reference`` and each law (the user-law example
  too) equals ``sim``'s sampled run with the same law and reference.

The controller runs as its own process; this test publishes its samples.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pytest
from ros_harness import rig_env, run_to_end, wait_matched

from stewart63_ros.core.controllers.control import pd_forces
from stewart63_ros.core.mechanics.kinematics import LegState, leg_lengths
from stewart63_ros.core.mechanics.rotation import quaternion_from_euler, rotation_from_euler
from stewart63_ros.core.plumbing.params import load_mechanism, load_setup

REPO = Path(__file__).resolve().parents[1]
PARAMS = REPO / 'config' / 'stewart63.yaml'
LEGS = ['leg_%d' % i for i in range(1, 7)]
CTL = 'stewart63/c/controller'
ERROR = 2


@pytest.fixture(scope='module')
def mech():
    return load_mechanism(PARAMS)


def to_time(ns):
    from builtin_interfaces.msg import Time
    return Time(sec=ns // 10**9, nanosec=ns % 10**9)


class Probe:
    """The test's side of one controller process in namespace /c."""

    def __init__(self, ros, mech):
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from rcl_interfaces.srv import SetParameters
        from sensor_msgs.msg import JointState
        from trajectory_msgs.msg import MultiDOFJointTrajectory

        from stewart63_ros import topics as T
        self.ros, self.mech = ros, mech
        self.node = node = ros.node('probe')
        self.forces = {}
        self.diags = []
        self.stamp = 0
        self.JointState, self.PoseStamped = JointState, PoseStamped
        self.pub_lengths = node.create_publisher(JointState, '/c/leg_lengths', T.STREAM_PUB)
        self.pub_trajectory = node.create_publisher(MultiDOFJointTrajectory, '/c/pose_trajectory',
                                                    T.SETPOINT_QOS)
        self.sub = node.create_subscription(JointState, '/c/leg_forces', self.on_forces,
                                            T.RECORD_SUB)
        self.diag_sub = node.create_subscription(DiagnosticArray, '/diagnostics', self.on_diag,
                                                 T.DIAGNOSTICS_QOS)
        self.params = node.create_client(SetParameters, '/c/controller/set_parameters')
        self.proc = None

    def on_forces(self, msg):
        self.forces[msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec] = np.array(
            msg.effort)

    def on_diag(self, msg):
        for status in msg.status:
            if status.name == CTL:
                level = status.level
                level = level[0] if isinstance(level, (bytes, bytearray)) else int(level)
                self.diags.append((time.monotonic(), level, status.message,
                                   {kv.key: kv.value for kv in status.values}))

    def start(self, *params):
        cmd = [str(Path(sys.executable).parent / 'controller'), '--ros-args',
               '-r', '__ns:=/c', '-p', 'watchdog_timeout:=600.0']
        for p in params:
            cmd += ['-p', p]
        self.proc = self.ros.spawn(cmd, name='controller')
        assert wait_matched(self.pub_lengths, 1, 90), self.proc.describe()
        assert wait_matched(self.sub, 1, 30), self.proc.describe()
        assert self.params.wait_for_service(timeout_sec=30), self.proc.describe()

    def sample(self, lengths, rates, dt=0.001, timeout=10.0):
        """One leg_lengths sample; its forces (None if none came: withheld)."""
        self.stamp += int(round(dt * 1e9))
        stamp = self.stamp
        msg = self.JointState(name=LEGS, position=[float(v) for v in lengths],
                              velocity=[float(v) for v in rates])
        msg.header.stamp = to_time(stamp)
        msg.header.frame_id = 'base'
        self.pub_lengths.publish(msg)
        self.ros.spin_until(lambda: stamp in self.forces, timeout)
        return self.forces.get(stamp)

    def set(self, name, value):
        """ros2 param set: (successful, reason)."""
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter
        request = SetParameters.Request(parameters=[Parameter(name, value=value)
                                                    .to_parameter_msg()])
        future = self.params.call_async(request)
        assert self.ros.spin_until(future.done, 20), 'no answer from set_parameters'
        result = future.result().results[0]
        return result.successful, result.reason

    def wait_diag(self, predicate, timeout=10.0):
        since = time.monotonic() - 3.0
        found = []

        def seen():
            found[:] = [d for d in self.diags if d[0] >= since and predicate(d)]
            return bool(found)
        self.ros.spin_until(seen, timeout)
        return found[0] if found else None


def steady(mech):
    task = load_setup(PARAMS).task
    legs = LegState(mech, np.array(task.initial_position),
                    rotation_from_euler(task.initial_orientation),
                    np.array([0.01, -0.02, 0.03]), np.array([0.02, 0.01, -0.01]))
    return legs.L.copy(), legs.Ldot.copy()


def test_run_time_tuning_changes_the_very_next_force(setup, ros, mech):
    probe = Probe(ros, mech)
    probe.start()
    lengths, rates = steady(mech)
    sp = setup.task.setpoint_lengths
    before = probe.sample(lengths, rates)
    gains = setup.gains
    np.testing.assert_allclose(before, pd_forces(lengths, rates, sp, gains.kp, gains.kv, 3000.0),
                               atol=1e-9)
    kp = [1000.0, 1100.0, 1200.0, 1300.0, 1400.0, 1500.0]
    ok, reason = probe.set('kp', kp)
    assert ok, reason
    after = probe.sample(lengths, rates)            # the very next force
    np.testing.assert_allclose(after, pd_forces(lengths, rates, sp, kp, setup.gains.kv, 3000.0),
                               atol=1e-9)
    refused = [('kp', [float('nan')] * 6), ('kp', [1.0] * 5), ('kv', [-1.0] + [300.0] * 5),
               ('control_law', 'no_such_law'), ('control_law', 'nomodule:Law'),
               ('ct_kp', [1.0] * 7), ('platform_mass', 20.0), ('max_force', 10.0)]
    for name, value in refused:
        ok, reason = probe.set(name, value)
        print('\nrefused %s = %r: %s' % (name, value, reason), end='')
        assert not ok and reason and name in reason
        np.testing.assert_array_equal(probe.sample(lengths, rates), after)
    # a new law, at once
    ok, reason = probe.set('control_law', 'pd_gravity')
    assert ok, reason
    gravity = probe.sample(lengths, rates)
    assert np.max(np.abs(gravity - after)) > 10.0      # the holding forces, about 50-90 N a leg
    ok, reason = probe.set('kv', [0.0] * 6)
    assert ok, reason
    no_kv = probe.sample(lengths, rates)
    np.testing.assert_allclose(no_kv - gravity, np.asarray(setup.gains.kv) * rates, atol=1e-6)
    assert probe.proc.returncode is None


def test_latched_and_volatile_setpoints_both_take_effect(setup, ros, mech):
    from rclpy.qos import QoSProfile

    from stewart63_ros import topics as T
    node = ros.node('commander')
    latched = node.create_publisher(ros_msg('JointState'), '/c/leg_setpoint', T.SETPOINT_QOS)
    first = np.array(setup.task.setpoint_lengths) + [0.02, -0.01, 0.03, 0.0, -0.02, 0.01]
    msg = ros_msg('JointState')(name=LEGS, position=first.tolist())
    msg.header.stamp = to_time(10**9)
    latched.publish(msg)                    # before the controller exists
    probe = Probe(ros, mech)
    probe.start()
    lengths, rates = steady(mech)

    def forces_for(setpoint, timeout=10.0):
        want = pd_forces(lengths, rates, setpoint, setup.gains.kp, setup.gains.kv, 3000.0)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            got = probe.sample(lengths, rates)
            if got is not None and np.allclose(got, want, atol=1e-6):
                return True
            ros.spin_until(lambda: False, 0.05)
        return False
    assert forces_for(first), 'the latched leg_setpoint published before start had no effect'
    # `ros2 topic pub` default QoS: reliable, volatile, depth 10
    volatile = node.create_publisher(ros_msg('PoseStamped'), '/c/pose_setpoint',
                                     QoSProfile(depth=10))
    assert wait_matched(volatile, 1, 20), 'a volatile publisher did not match the controller'
    position, theta = np.array([0.0, 0.02, 1.06]), np.array([0.02, -0.01, 0.03])
    pose = ros_msg('PoseStamped')()
    pose.header.stamp = to_time(2 * 10**9)
    pose.pose.position.x, pose.pose.position.y, pose.pose.position.z = position.tolist()
    q = pose.pose.orientation
    q.x, q.y, q.z, q.w = quaternion_from_euler(theta).tolist()
    volatile.publish(pose)
    assert forces_for(leg_lengths(mech, position, rotation_from_euler(theta))), \
        'the volatile pose_setpoint had no effect'


def ros_msg(name):
    if name == 'JointState':
        from sensor_msgs.msg import JointState
        return JointState
    from geometry_msgs.msg import PoseStamped
    return PoseStamped


def trajectory_msg(times, poses, stamp_ns=0):
    from builtin_interfaces.msg import Duration
    from geometry_msgs.msg import Transform
    from trajectory_msgs.msg import MultiDOFJointTrajectory, MultiDOFJointTrajectoryPoint
    msg = MultiDOFJointTrajectory(joint_names=['platform'])
    msg.header.stamp = to_time(stamp_ns)
    for t, pose in zip(times, poses):
        tr = Transform()
        tr.translation.x, tr.translation.y, tr.translation.z = [float(v) for v in pose[:3]]
        q = quaternion_from_euler(pose[3:])
        tr.rotation.x, tr.rotation.y, tr.rotation.z, tr.rotation.w = q.tolist()
        ns = int(round(t * 1e9))
        msg.points.append(MultiDOFJointTrajectoryPoint(
            transforms=[tr], time_from_start=Duration(sec=ns // 10**9, nanosec=ns % 10**9)))
    return msg


def test_pose_trajectory_is_followed_and_a_bad_one_refused(setup, ros, mech):
    from stewart63_ros.core.controllers.reference import R_LEN, R_RATE, Reference
    probe = Probe(ros, mech)
    probe.start()
    assert wait_matched(probe.pub_trajectory, 1, 20)
    lengths, rates = steady(mech)
    centre = np.concatenate([setup.task.initial_position, setup.task.initial_orientation])
    times = np.array([0.0, 0.5, 1.0, 1.5])
    poses = centre + np.outer(np.sin(times), [0.02, -0.01, 0.03, 0.02, 0.01, -0.02])
    start = 5 * 10**9
    probe.pub_trajectory.publish(trajectory_msg(times, poses, start))
    reference = Reference.from_poses(mech, times, poses)
    deadline = time.monotonic() + 10
    matched = False
    while time.monotonic() < deadline and not matched:
        probe.stamp = max(probe.stamp, start)
        got = probe.sample(lengths, rates, dt=0.1)
        s = reference.sample((probe.stamp - start) * 1e-9)
        want = np.clip(setup.gains.kp * (s[R_LEN] - lengths)
                       - setup.gains.kv * (rates - s[R_RATE]), -3000, 3000)
        matched = got is not None and np.allclose(got, want, atol=1e-6)
    assert matched, 'the controller did not follow the pose_trajectory'
    # the tracking error on /diagnostics: |L_ref - L| of these samples (about 0.1 m here)
    report = None
    deadline = time.monotonic() + 10
    while report is None and time.monotonic() < deadline:
        probe.sample(lengths, rates, dt=0.1)        # a running rig keeps sampling
        report = probe.wait_diag(lambda d: 'tracking/leg_max_m' in d[3], 0.2)
    assert report is not None, 'no tracking error on /diagnostics'
    assert 'pose_trajectory' in report[3]['reference']
    assert 0.0 < float(report[3]['tracking/leg_max_m']) < 1.0
    # a trajectory that leaves the stroke: refused, the previous motion goes on
    bad = poses.copy()
    bad[2, 2] += 1.0
    probe.pub_trajectory.publish(trajectory_msg(times, bad, start + 10**9))
    report = probe.wait_diag(lambda d: any(k.startswith('rejected/pose_trajectory/')
                                           for k in d[3]), 10)
    assert report is not None, 'no rejection reported'
    print('\n' + report[2])
    got = probe.sample(lengths, rates, dt=0.1)
    s = reference.sample((probe.stamp - start) * 1e-9)
    want = np.clip(setup.gains.kp * (s[R_LEN] - lengths)
                   - setup.gains.kv * (rates - s[R_RATE]), -3000, 3000)
    np.testing.assert_allclose(got, want, atol=1e-6)


def test_a_raising_law_is_caught_and_the_node_stays_up(ros, mech):
    probe = Probe(ros, mech)
    probe.start('control_law:=stewart63_ros.examples.my_law:Failing', 'failing_after:=0.005')
    lengths, rates = steady(mech)
    assert probe.sample(lengths, rates) is not None            # t = 0: still fine
    probe.stamp += 10 * 10**6
    assert probe.sample(lengths, rates, timeout=2.0) is None   # t > 0.005 s: withheld
    report = probe.wait_diag(lambda d: d[1] == ERROR, 10)
    assert report is not None, 'no ERROR on /diagnostics'
    print('\n' + report[2])
    assert 'fails on purpose' in report[2]
    assert probe.proc.returncode is None
    ok, reason = probe.set('control_law', 'pd')                # still serving; back to pd
    assert ok, reason
    assert probe.sample(lengths, rates) is not None


# -- the lockstep rig equals sim, law by law ------------------------------------------------------
LOCKSTEP_DURATION = 1.5       # s: the tracking error counts from 1 s


@pytest.mark.parametrize('law', ['pd', 'pd_gravity', 'computed_torque',
                                 'stewart63_ros.examples.my_law:LegPD'])
def test_lockstep_rig_with_a_reference_equals_sim(setup, ros, monkeypatch, tmp_path, mech, law):
    from test_laws import six_axis_reference

    from stewart63_ros.core.controllers.reference_files import write_reference_csv
    from stewart63_ros.core.controllers.simulate import run_sampled, sensor_reading
    from stewart63_ros.core.controllers.tracking import tracking_errors
    from stewart63_ros.tools.rig import control_params
    from stewart63_ros.tools.rig_process import Rig
    from stewart63_ros.tools.sim import make_controller
    ref_csv = tmp_path / 'reference.csv'
    write_reference_csv(ref_csv, *six_axis_reference(setup, duration=3.0))
    controller, reference = make_controller(PARAMS, law, ref_csv)
    offline = run_sampled(setup, LOCKSTEP_DURATION, 1000.0, controller=controller)
    from stewart63_ros.core.mechanics.dynamics import Dynamics
    final, _ = sensor_reading(Dynamics(mech), offline.states[-1])
    expected = tracking_errors(mech, reference, offline.times, offline.states)

    rig_env(ros, monkeypatch)
    rig = Rig(PARAMS, mode='lockstep', duration=LOCKSTEP_DURATION, log_dir=tmp_path / 'rig',
              extra_params=control_params(law, ref_csv))
    ok, codes, logs = run_to_end(rig, 150)
    assert ok and set(codes.values()) == {0}, '%s\n%s' % (codes, logs)
    summary = rig.summary()
    assert summary['samples'] == len(offline.times) and summary['force_timeouts'] == 0, summary
    diff = np.max(np.abs(np.array(summary['final_leg_lengths_m']) - final))
    got = summary['tracking_error']
    print('\n%s: lockstep rig vs sim: final |dL| %.2e m; tracking position max %.3e vs %.3e m, '
          'orientation max %.3e vs %.3e rad' % (law, diff, got['position_max_m'],
                                                expected['position_max_m'],
                                                got['orientation_max_rad'],
                                                expected['orientation_max_rad']))
    assert diff <= 1e-9
    for key in ('leg_max_m', 'leg_rms_m', 'position_max_m', 'position_rms_m',
                'orientation_max_rad', 'orientation_rms_rad'):
        assert abs(got[key] - expected[key]) <= 1e-9, (key, got[key], expected[key])
    assert got['samples'] == expected['samples']


def test_a_stalled_controller_reads_its_queue_before_its_watchdog_judges(ros):
    """A controller starved of CPU wakes to its due watchdog and a queued sample
    at once: the sample proves the sensor alive, so no ERROR (a loaded machine's
    stall is not a lost sensor). test/watchdog_probe.py stages it in one process."""
    result = watchdog_probe(ros, 'stall')
    assert result == {'first_handled': True, 'tripped': False, 'fault': '', 'received': 2,
                      'rejected': {}}, result


def watchdog_probe(ros, *args) -> dict:
    """test/watchdog_probe.py's scenario ``args``, run in its own process: its result."""
    import json
    proc = ros.python(str(REPO / 'test' / 'watchdog_probe.py'), *args, name='watchdog_probe')
    assert proc.wait(60) == 0, proc.describe()
    return json.loads(proc.stdout().strip().splitlines()[-1])


@pytest.mark.parametrize('mode', ['lockstep', 'realtime'])
def test_a_dropout_is_no_silence_for_the_lockstep_watchdog(ros, mode):
    """A sensor dropout (a leg NaN) longer than the watchdog's timeout: the
    controller refuses every such sample. In lockstep they are samples all
    the same (the plant steps on without an answer), so the watchdog does
    not report a lost sensor; in realtime it does (docs/faults.md)."""
    result = watchdog_probe(ros, 'dropout', mode)
    refused = result['received'] - 1
    assert refused > 10 and result['rejected'] == {'leg_lengths/non_finite': refused}, result
    if mode == 'lockstep':
        assert not result['tripped'] and result['fault'] == '', result
    else:
        assert result['tripped'] and result['fault'].startswith('watchdog: no leg_lengths'), \
            result
