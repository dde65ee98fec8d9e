"""plant, controller and fk as node processes over real DDS.

One module fixture starts, on a private ROS domain, once each:

- ``/a``: ``fk`` and ``controller`` (watchdog 600 s, so it never trips here),
  fed by this test standing in for the plant: synthetic ``leg_lengths`` from a
  known smooth trajectory, so their answers can be checked to 1e-9;
- ``/wd``: a ``controller`` with ``watchdog_timeout:=0.2`` for the watchdog;
- ``/p``: a realtime ``plant`` (100 Hz, running on) in closed loop with its
  own ``controller``, for bad ``leg_forces`` / ``external_wrench``.

Every wait is bounded, nothing assumes a message arrives (samples are
re-published until their answer is seen), every process is stopped by pid
(process group) at the end. Diagnostics are told apart by status name:
``stewart63/<namespace>/<node>``.
"""
from __future__ import annotations

import contextlib
import math
import os
import shutil
import signal
import time
from pathlib import Path

import numpy as np
import pytest
from ros_harness import PYTHON, REPO, RosTest, lease_domain_id, wait_matched, wait_until

from stewart63_ros.core.controllers.control import pd_forces
from stewart63_ros.core.mechanics.kinematics import LegState, leg_lengths
from stewart63_ros.core.mechanics.rotation import (
    euler_rate_matrix,
    quaternion_from_euler,
    rotation_from_euler,
)
from stewart63_ros.core.plumbing.params import load_mechanism, load_setup

PARAMS = REPO / 'config' / 'stewart63.yaml'
#: Node processes over DDS: `make test-fast` leaves this file out.
pytestmark = [pytest.mark.dds, pytest.mark.slow]
LEGS = ['leg_%d' % i for i in range(1, 7)]
OK, WARN, ERROR = 0, 1, 2
POSE_TOL = 1e-9          # m, rad
TWIST_TOL = 1e-8         # m/s, rad/s
FORCE_TOL = 1e-9         # N (the node runs the same arithmetic)


def executable(name: str) -> str:
    """The console script of this venv (``plant``, ``controller``, ``fk``)."""
    path = Path(PYTHON).parent / name
    if path.exists():
        return str(path)
    found = shutil.which(name)
    assert found, '%s is not installed in this environment' % name
    return found


def to_time(ns: int):
    from builtin_interfaces.msg import Time
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def from_time(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def level_of(status) -> int:
    lvl = status.level
    return lvl[0] if isinstance(lvl, (bytes, bytearray)) else int(lvl)


def quat_angle(q1, q2) -> float:
    """Rotation angle [rad] between two unit quaternions (x, y, z, w), sign-blind."""
    from scipy.spatial.transform import Rotation
    return float((Rotation.from_quat(q1).inv() * Rotation.from_quat(q2)).magnitude())


# -- the known trajectory ------------------------------------------------------
class Trajectory:
    """pose(t): small sinusoids around the mechanism's initial pose; exact twist."""

    A = np.array([0.02, 0.015, 0.01])       # m
    F = np.array([1.0, 1.3, 0.7])           # Hz
    PH = np.array([0.3, 1.1, 2.0])
    B = np.array([0.02, 0.015, 0.025])      # rad
    G = np.array([0.8, 1.1, 1.5])           # Hz
    PS = np.array([0.5, 0.2, 1.4])

    def __init__(self, mech):
        self.mech = mech
        task = load_setup(PARAMS).task
        self.p0 = np.array(task.initial_position, float)
        self.th0 = np.array(task.initial_orientation, float)

    def pose(self, t):
        w, g = 2 * np.pi * self.F, 2 * np.pi * self.G
        position = self.p0 + self.A * np.sin(w * t + self.PH)
        theta = self.th0 + self.B * np.sin(g * t + self.PS)
        velocity = self.A * w * np.cos(w * t + self.PH)
        theta_rate = self.B * g * np.cos(g * t + self.PS)
        omega = euler_rate_matrix(theta) @ theta_rate
        return position, theta, velocity, omega

    def sample(self, position, theta, velocity, omega):
        legs = LegState(self.mech, position, rotation_from_euler(theta), velocity, omega)
        return legs.L.copy(), legs.Ldot.copy()


# -- the rig -------------------------------------------------------------------
class Rig:
    def __init__(self, rt: RosTest, mech):
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState

        from stewart63_ros import topics as T
        self.rt, self.mech = rt, mech
        self.setpoint = np.array(load_setup(PARAMS).task.setpoint_lengths, float)   # /a's
        self.stamp = {'a': 1_000 * 10**9, 'wd': 1_000 * 10**9}    # last leg_lengths stamp
        self.setpoint_stamp = 10**9
        self.node = node = rt.node('probe')
        self.procs = {}
        # answers, keyed by stamp
        self.forces = {'a': {}, 'wd': {}}
        self.force_log = {'a': [], 'wd': []}      # (receive time, stamp ns)
        self.poses, self.twists = {}, {}
        self.truth = []                           # (receive time, position, quaternion)
        self.diags = []                           # (receive time, name, level, message, values)

        def keep(store, log=None):
            def callback(msg):
                ns = from_time(msg.header.stamp)
                store[ns] = msg
                if log is not None:
                    log.append((time.monotonic(), ns))
            return callback

        self.pub_lengths = {ns: node.create_publisher(JointState, '/%s/leg_lengths' % ns,
                                                      T.STREAM_PUB) for ns in ('a', 'wd')}
        self.pub_leg_setpoint = node.create_publisher(JointState, '/a/leg_setpoint',
                                                      T.SETPOINT_QOS)
        self.pub_pose_setpoint = node.create_publisher(PoseStamped, '/a/pose_setpoint',
                                                       T.SETPOINT_QOS)
        self.pub_plant_forces = node.create_publisher(JointState, '/p/leg_forces', T.STREAM_PUB)
        self.pub_wrench = node.create_publisher(WrenchStamped, '/p/external_wrench',
                                                T.STREAM_PUB)
        self.subs = [
            node.create_subscription(JointState, '/%s/leg_forces' % ns,
                                     keep(self.forces[ns], self.force_log[ns]), T.RECORD_SUB)
            for ns in ('a', 'wd')]
        self.subs.append(node.create_subscription(PoseStamped, '/a/platform_pose',
                                                  keep(self.poses), T.RECORD_SUB))
        self.subs.append(node.create_subscription(TwistStamped, '/a/platform_twist',
                                                  keep(self.twists), T.RECORD_SUB))
        self.subs.append(node.create_subscription(
            PoseStamped, '/p/ground_truth/pose', self.on_truth,
            QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)))
        self.diag_sub = node.create_subscription(DiagnosticArray, '/diagnostics',
                                                 self.on_diag, T.DIAGNOSTICS_QOS)
        # standing in for a plant's "run: ..." announcements
        self.pub_diag = node.create_publisher(DiagnosticArray, '/diagnostics',
                                              T.DIAGNOSTICS_QOS)
        self.msg = {'JointState': JointState, 'PoseStamped': PoseStamped,
                    'WrenchStamped': WrenchStamped, 'DiagnosticArray': DiagnosticArray}

    # -- callbacks -----------------------------------------------------------
    def on_truth(self, msg):
        p, q = msg.pose.position, msg.pose.orientation
        self.truth.append((time.monotonic(), np.array([p.x, p.y, p.z]),
                           np.array([q.x, q.y, q.z, q.w])))

    def on_diag(self, msg):
        now = time.monotonic()
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            self.diags.append((now, status.name, level_of(status), status.message, values))

    # -- processes -----------------------------------------------------------
    def start(self, key, exe, ns, *params):
        # No --params-file: the nodes read the packaged file anyway, and with
        # rcl a file's '/**/plant' section beats '-p' overrides (they sit
        # under '/**'), so '-p clock_mode:=realtime' would not win over it.
        cmd = [executable(exe), '--ros-args', '-r', '__ns:=/' + ns]
        for p in params:
            cmd += ['-p', p]
        self.procs[key] = self.rt.spawn(cmd, name=key.replace('/', '_'))

    def check_alive(self, *keys):
        for key in keys or self.procs:
            proc = self.procs[key]
            assert proc.returncode is None, '%s died:\n%s' % (key, proc.describe())

    def spin_until(self, predicate, timeout) -> bool:
        return self.rt.spin_until(predicate, timeout)

    def spin_for(self, seconds):
        self.rt.rc.spin_for(seconds)

    # -- diagnostics -----------------------------------------------------------
    def reports(self, name, since=0.0):
        return [d for d in self.diags if d[1] == name and d[0] >= since]

    def last_report(self, name):
        found = self.reports(name)
        return found[-1] if found else None

    def count(self, name, key) -> int:
        last = self.last_report(name)
        return int(last[4].get(key, 0)) if last else 0

    def wait_report(self, name, predicate, timeout, since=0.0):
        """The first report of ``name`` received after ``since`` that satisfies
        ``predicate(report)``, spinning up to ``timeout`` s; None if none."""
        def find():
            return next((d for d in self.reports(name, since) if predicate(d)), None)
        self.spin_until(lambda: find() is not None, timeout)
        return find()

    # -- samples ---------------------------------------------------------------
    def joint_state(self, stamp_ns, position=(), velocity=(), effort=(), names=LEGS):
        msg = self.msg['JointState']()
        msg.header.stamp = to_time(stamp_ns)
        msg.header.frame_id = 'base'
        msg.name = list(names)
        msg.position = [float(v) for v in position]
        msg.velocity = [float(v) for v in velocity]
        msg.effort = [float(v) for v in effort]
        return msg

    def announce_run(self, ns, run, stamp_ns):
        """``run: <run>`` from ``/<ns>/plant`` on /diagnostics, stamped ``stamp_ns``."""
        from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
        msg = self.msg['DiagnosticArray'](status=[DiagnosticStatus(
            name='stewart63/%s/plant' % ns, values=[KeyValue(key='run', value=run)])])
        msg.header.stamp = to_time(stamp_ns)
        self.pub_diag.publish(msg)

    def next_stamp(self, ns='a', dt=0.01) -> int:
        self.stamp[ns] += int(round(dt * 1e9))
        return self.stamp[ns]

    def exchange(self, lengths, rates, ns='a', stamp=None, fk=True, timeout=6.0):
        """Publish one leg_lengths sample until the controller (and on /a the fk)
        answered it; returns (stamp, force msg, pose msg, twist msg)."""
        stamp = self.next_stamp(ns) if stamp is None else stamp
        msg = self.joint_state(stamp, lengths, rates)
        want_fk = fk and ns == 'a'

        def answered():
            return stamp in self.forces[ns] and (
                not want_fk or (stamp in self.poses and stamp in self.twists))
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.pub_lengths[ns].publish(msg)   # same stamp again: accepted (not older)
            if self.spin_until(answered, min(0.5, deadline - time.monotonic())):
                break
        assert answered(), 'no answer to the sample stamped %d on /%s within %g s' % (
            stamp, ns, timeout)
        return stamp, self.forces[ns][stamp], self.poses.get(stamp), self.twists.get(stamp)

    def expected_force(self, lengths, rates, setpoint=None):
        gains = load_setup(PARAMS).gains            # the /a controller's
        return pd_forces(np.asarray(lengths), np.asarray(rates),
                         self.setpoint if setpoint is None else setpoint,
                         gains.kp, gains.kv, self.mech.max_force)


NAMES = {'fk': 'stewart63/a/fk', 'ctl': 'stewart63/a/controller',
         'wd': 'stewart63/wd/controller', 'plant': 'stewart63/p/plant',
         'pctl': 'stewart63/p/controller'}


@pytest.fixture(scope='module')
def mech():
    return load_mechanism(PARAMS)


@pytest.fixture(scope='module')
def rig(tmp_path_factory, mech):
    tmp = tmp_path_factory.mktemp('nodes')
    rt = RosTest(lease_domain_id(), tmp / 'logs')
    try:
        r = Rig(rt, mech)
        r.start('fk', 'fk', 'a')
        r.start('ctl', 'controller', 'a', 'watchdog_timeout:=600.0')
        r.start('wd', 'controller', 'wd', 'watchdog_timeout:=0.2')
        r.start('pctl', 'controller', 'p', 'watchdog_timeout:=5.0')

        def up(names):   # a node's first report comes after its start gate
            return r.spin_until(lambda: all(r.last_report(n) for n in names) or any(
                p.returncode is not None for p in r.procs.values()), 90)
        # The realtime plant last, once the others are through their start-up:
        # a controller starved of CPU for a few hundred ms lets the platform
        # drop (zero-order hold of stale forces), on this 2-core machine.
        ok = up([n for k, n in NAMES.items() if k != 'plant'])
        r.check_alive()
        r.start('plant', 'plant', 'p', 'clock_mode:=realtime', 'duration:=0.0',
                'sensor_rate:=100.0', 'lengths_subscribers:=1')
        ok = ok and up(NAMES.values())
        r.check_alive()
        assert ok, 'not every node reported on /diagnostics: %s\n%s' % (
            sorted({d[1] for d in r.diags}), '\n'.join(p.describe() for p in r.procs.values()))
        pairs = [(r.pub_lengths['a'], 2), (r.pub_lengths['wd'], 1), (r.pub_leg_setpoint, 1),
                 (r.pub_pose_setpoint, 1), (r.pub_plant_forces, 1), (r.pub_wrench, 1),
                 *[(s, 1) for s in r.subs],
                 # every /diagnostics reader the graph shows (each node has reported)
                 (r.pub_diag, r.node.count_subscribers('/diagnostics'))]
        for entity, n in pairs:
            assert wait_matched(entity, n, timeout=20), 'not matched: %s' % entity.topic_name
        yield r
    finally:
        # Ctrl-C to every node at once (each flushes for up to a few seconds),
        # then the harness stops whatever is left (SIGTERM, SIGKILL).
        for proc in rt.procs:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(proc.pid, signal.SIGINT)
        wait_until(lambda: all(p.returncode is not None for p in rt.procs), 10.0)
        rt.cleanup()


# -- 1. the stand-in sensor: fk and controller answer a known trajectory --------
def test_fk_and_controller_follow_a_known_trajectory(rig, mech):
    traj = Trajectory(mech)
    samples = []
    for k in range(40):
        samples.append(traj.pose(0.01 * k))
    # Fast samples on the same path (a 20 m/s or 10 rad/s twist) saturate the PD law.
    t_fast = 0.4
    position, theta, _, _ = traj.pose(t_fast)
    for v, w in (([0.0, 0.0, -20.0], [0, 0, 0]), ([0.0, 0.0, 20.0], [0, 0, 0]),
                 ([0.0, 0.0, 0.0], [0.0, 0.0, 10.0])):
        samples.append((position, theta, np.array(v, float), np.array(w, float)))
    samples += [traj.pose(0.4 + 0.01 * k) for k in range(1, 6)]

    pos_err = ang_err = lin_err = rot_err = force_err = 0.0
    saturated_hi = saturated_lo = unsaturated = 0
    for position, theta, velocity, omega in samples:
        lengths, rates = traj.sample(position, theta, velocity, omega)
        stamp, force, pose, twist = rig.exchange(lengths, rates)
        # fk: the pose and twist the lengths came from, with the sample's stamp
        assert from_time(pose.header.stamp) == stamp and pose.header.frame_id == 'base'
        assert from_time(twist.header.stamp) == stamp
        p, q = pose.pose.position, pose.pose.orientation
        pos_err = max(pos_err, float(np.abs(np.array([p.x, p.y, p.z]) - position).max()))
        quat = np.array([q.x, q.y, q.z, q.w])
        want_q = quaternion_from_euler(theta)
        assert abs(np.linalg.norm(quat) - 1.0) < 1e-12
        ang_err = max(ang_err, quat_angle(quat, want_q),
                      float(min(np.abs(quat - want_q).max(), np.abs(quat + want_q).max())))
        lin, ang = twist.twist.linear, twist.twist.angular
        lin_err = max(lin_err, float(np.abs(np.array([lin.x, lin.y, lin.z]) - velocity).max()))
        rot_err = max(rot_err, float(np.abs(np.array([ang.x, ang.y, ang.z]) - omega).max()))
        # controller: eq. (40) on this sample, with its stamp
        assert list(force.name) == LEGS
        effort = np.array(force.effort)
        want_f = rig.expected_force(lengths, rates)
        force_err = max(force_err, float(np.abs(effort - want_f).max()))
        saturated_hi += int(np.any(want_f == mech.max_force))
        saturated_lo += int(np.any(want_f == -mech.max_force))
        unsaturated += int(np.all(np.abs(want_f) < mech.max_force))
    print('\nfk over %d samples: position %.2e m, orientation %.2e rad, velocity %.2e m/s, '
          'omega %.2e rad/s; controller |F - eq.40| %.2e N' % (
              len(samples), pos_err, ang_err, lin_err, rot_err, force_err))
    assert pos_err <= POSE_TOL and ang_err <= POSE_TOL
    assert lin_err <= TWIST_TOL and rot_err <= TWIST_TOL
    assert force_err <= FORCE_TOL
    assert saturated_hi and saturated_lo and unsaturated, (saturated_hi, saturated_lo, unsaturated)
    rig.check_alive('fk', 'ctl')


# -- 2. setpoints ----------------------------------------------------------------
def _steady_sample(mech):
    task = load_setup(PARAMS).task
    legs = LegState(mech, np.array(task.initial_position), rotation_from_euler(
        task.initial_orientation), np.array([0.01, -0.02, 0.03]), np.array([0.02, 0.01, -0.01]))
    return legs.L.copy(), legs.Ldot.copy()


def _forces_until(rig, lengths, rates, setpoint, timeout=6.0):
    """Exchange samples until the forces are eq. (40) with ``setpoint`` (the
    setpoint travels on another topic: it may land a sample later)."""
    want = rig.expected_force(lengths, rates, setpoint)
    deadline = time.monotonic() + timeout
    effort = None
    while time.monotonic() < deadline:
        _, force, _, _ = rig.exchange(lengths, rates, fk=False)
        effort = np.array(force.effort)
        if np.allclose(effort, want, rtol=0, atol=1e-6):
            return effort, want
        rig.spin_for(0.05)
    return effort, want


def test_setpoints(setup, rig, mech):
    lengths, rates = _steady_sample(mech)
    # the current setpoint first
    _, force, _, _ = rig.exchange(lengths, rates, fk=False)
    before = np.array(force.effort)
    np.testing.assert_allclose(before, rig.expected_force(lengths, rates), rtol=0, atol=FORCE_TOL)

    # leg_setpoint: eq. (40) with the new lengths
    new = rig.setpoint + np.array([0.05, -0.03, 0.02, -0.04, 0.01, 0.03])
    rig.setpoint_stamp += 10**9
    rig.pub_leg_setpoint.publish(rig.joint_state(rig.setpoint_stamp, new))
    effort, want = _forces_until(rig, lengths, rates, new)
    np.testing.assert_allclose(effort, want, rtol=0, atol=FORCE_TOL)
    # the change is Kp (new - old), as eq. (40) says (no saturation here)
    np.testing.assert_allclose(effort - before, np.asarray(setup.gains.kp) * (new - rig.setpoint),
                               rtol=1e-9, atol=1e-6)
    rig.setpoint = new

    # reachable pose_setpoint: setpoint = IK(pose)
    PoseStamped = rig.msg['PoseStamped']
    position, theta = np.array([0.0, 0.02, 1.06]), np.array([0.02, -0.01, 0.03])
    ik = leg_lengths(mech, position, rotation_from_euler(theta))
    assert np.all((ik > mech.leg_length_min) & (ik < mech.leg_length_max))
    pose = PoseStamped()
    rig.setpoint_stamp += 10**9
    pose.header.stamp = to_time(rig.setpoint_stamp)
    pose.header.frame_id = 'base'
    pose.pose.position.x, pose.pose.position.y, pose.pose.position.z = position.tolist()
    q = pose.pose.orientation
    q.x, q.y, q.z, q.w = quaternion_from_euler(theta).tolist()
    rig.pub_pose_setpoint.publish(pose)
    effort, want = _forces_until(rig, lengths, rates, ik)
    np.testing.assert_allclose(effort, want, rtol=0, atol=1e-6)   # IK via another rotation path
    rig.setpoint = ik

    # unreachable pose_setpoint (legs beyond leg_length_max): rejected, setpoint kept
    key = 'rejected/pose_setpoint/unreachable_setpoint'
    n0 = rig.count(NAMES['ctl'], key)
    far = np.array([0.0, 0.0, 2.6])
    assert np.any(leg_lengths(mech, far, np.eye(3)) > mech.leg_length_max)
    bad = PoseStamped()
    bad.header.frame_id = 'base'
    bad.pose.position.z = float(far[2])
    bad.pose.orientation.w = 1.0
    report = None
    deadline = time.monotonic() + 10.0
    while report is None and time.monotonic() < deadline:
        rig.setpoint_stamp += 10**9
        bad.header.stamp = to_time(rig.setpoint_stamp)
        rig.pub_pose_setpoint.publish(bad)
        report = rig.wait_report(NAMES['ctl'], lambda d: int(d[4].get(key, 0)) > n0, 2.5)
    assert report is not None, 'no %s on /diagnostics' % key
    assert report[2] == WARN and 'unreachable' in report[3], report[:4]
    _, force, _, _ = rig.exchange(lengths, rates, fk=False)
    np.testing.assert_allclose(np.array(force.effort), rig.expected_force(lengths, rates),
                               rtol=0, atol=1e-6)
    rig.check_alive('ctl')


# -- 3. bad input ----------------------------------------------------------------
def _wait_rejections(rig, name, expected: dict, resend: dict, timeout=12.0):
    """Wait until /diagnostics of ``name`` counts ``expected[key]`` rejections;
    re-sends (``resend[key]()``) what has not been counted after a while."""
    def missing():
        return [k for k, n in expected.items() if rig.count(name, k) < n]
    deadline = time.monotonic() + timeout
    while missing() and time.monotonic() < deadline:
        if rig.spin_until(lambda: not missing(), min(2.5, deadline - time.monotonic())):
            break
        for key in missing():
            resend[key]()
            rig.spin_for(0.05)
    assert not missing(), '%s did not report %s: last %s\nnow %.2f, last reports %s' % (
        name, missing(), rig.last_report(name), time.monotonic(),
        {n: round(rig.last_report(n)[0], 2) for n in NAMES.values()})


def test_bad_leg_lengths_are_rejected_and_reported(rig, mech):
    traj = Trajectory(mech)
    lengths, rates = traj.sample(*traj.pose(0.0))
    nan, inf = lengths.copy(), rates.copy()
    nan[2] = math.nan
    inf[4] = -math.inf
    reordered = LEGS[::-1]
    unknown = LEGS[:5] + ['leg_7']
    cases = {   # key -> (names, position, velocity); stamp: the next one
        'non_finite#nan': (LEGS, nan, rates),
        'non_finite#inf': (LEGS, lengths, inf),
        'wrong_size#5': (LEGS, lengths[:5], rates),
        'wrong_size#7': (LEGS, lengths, np.append(rates, 0.0)),
        'unknown_joint_names': (unknown, lengths, rates),
        'bad_joint_order': (reordered, lengths, rates),
        'stamp_from_past': (LEGS, lengths, rates),
    }
    # Everything counted so far, per node and reason
    base = {n: {} for n in ('fk', 'ctl')}
    for node in base:
        for case in cases:
            reason = case.split('#')[0]
            base[node][reason] = rig.count(NAMES[node], 'rejected/leg_lengths/' + reason)
    t_first = time.monotonic()

    def send(case):
        names, position, velocity = cases[case]
        if case == 'stamp_from_past':
            stamp = rig.stamp['a'] - 1_000_000          # 1 ms before the last accepted
        else:
            stamp = rig.stamp['a'] + 1_000_000          # newer (and then not accepted)
        rig.pub_lengths['a'].publish(rig.joint_state(stamp, position, velocity, names=names))

    answered = 0
    for case in cases:
        send(case)
        rig.spin_for(0.1)              # the controller keeps only the newest sample
        stamp, force, pose, _ = rig.exchange(lengths, rates)   # a good sample still answered
        np.testing.assert_allclose(np.array(force.effort), rig.expected_force(lengths, rates),
                                   rtol=0, atol=FORCE_TOL)
        assert pose is not None
        answered += 1
    rig.check_alive('fk', 'ctl')

    for node in ('fk', 'ctl'):
        expected = {}
        for case in cases:
            reason = case.split('#')[0]
            key = 'rejected/leg_lengths/' + reason
            expected[key] = expected.get(key, base[node][reason]) + 1
        resend = {}
        for case in cases:
            key = 'rejected/leg_lengths/' + case.split('#')[0]
            resend.setdefault(key, (lambda c=case: send(c)))
        _wait_rejections(rig, NAMES[node], expected, resend)
        warn = [d for d in rig.reports(NAMES[node], t_first) if d[2] == WARN]
        assert warn and 'rejected' in warn[0][3], rig.reports(NAMES[node], t_first)[:3]
        assert not [d for d in rig.reports(NAMES[node], t_first) if d[2] == ERROR]
    # after the bad input stops, both return to OK, and still answer
    for node in ('fk', 'ctl'):
        t = time.monotonic()
        assert rig.wait_report(NAMES[node], lambda d: d[2] == OK, 4.0, since=t), \
            rig.last_report(NAMES[node])
    rig.exchange(lengths, rates)
    rig.check_alive('fk', 'ctl')
    print('\nleg_lengths: %d bad samples (7 kinds) rejected by fk and controller, '
          'each followed by an answered good one' % answered)


def test_bad_plant_inputs_are_rejected_and_do_not_corrupt_the_simulation(rig):
    name = NAMES['plant']
    WrenchStamped = rig.msg['WrenchStamped']
    first = rig.last_report(name)
    base = dict(first[4])

    def accepted(values):   # leg_forces taken by the plant: received - rejected
        return int(values.get('received/leg_forces', 0)) - sum(
            int(v) for k, v in values.items() if k.startswith('rejected/leg_forces/'))
    accepted0 = accepted(base)
    good = np.full(6, 10.0)
    future = int(time.time() * 1e9) + 1000 * 10**9     # passes the stamp gate; then rejected

    def forces(stamp, effort, names=LEGS):
        return rig.joint_state(stamp, effort=effort, names=names)

    def wrench(stamp, force=(0.0, 0.0, 0.0), torque=(0.0, 0.0, 0.0)):
        msg = WrenchStamped()
        msg.header.stamp = to_time(stamp)
        msg.header.frame_id = 'platform'
        f, m = msg.wrench.force, msg.wrench.torque
        f.x, f.y, f.z = (float(v) for v in force)
        m.x, m.y, m.z = (float(v) for v in torque)
        return msg

    nan, inf = good.copy(), good.copy()
    nan[0], inf[5] = math.nan, math.inf
    # one good wrench first, so that an older one is "from the past"
    wrench_stamp = int(time.time() * 1e9)
    F, W = rig.pub_plant_forces.publish, rig.pub_wrench.publish
    def both(first, second):   # the plant keeps only the newest: one at a time
        first()
        rig.spin_for(0.05)
        second()

    sends = {
        'rejected/leg_forces/non_finite': lambda: both(lambda: F(forces(future, nan)),
                                                       lambda: F(forces(future, inf))),
        'rejected/leg_forces/wrong_size': lambda: F(forces(future, good[:5])),
        'rejected/leg_forces/unknown_joint_names': lambda: F(forces(
            future, good, ['a', 'b', 'c', 'd', 'e', 'f'])),
        'rejected/leg_forces/bad_joint_order': lambda: F(forces(future, good, LEGS[::-1])),
        'rejected/leg_forces/stamp_from_past': lambda: F(forces(10**9, good)),   # t = 1 s
        'rejected/external_wrench/non_finite': lambda: both(
            lambda: W(wrench(future, force=(math.nan, 0, 0))),
            lambda: W(wrench(future, torque=(0, math.inf, 0)))),
        'rejected/external_wrench/stamp_from_past': lambda: W(wrench(wrench_stamp - 10**9)),
    }
    counts = {'rejected/leg_forces/non_finite': 2, 'rejected/external_wrench/non_finite': 2}
    expected = {k: int(base.get(k, 0)) + counts.get(k, 1) for k in sends}
    n_truth = len(rig.truth)
    t_first = time.monotonic()
    W(wrench(wrench_stamp))
    rig.spin_for(0.05)
    for send in sends.values():
        send()
        rig.spin_for(0.05)
    _wait_rejections(rig, name, expected, sends)
    rig.check_alive('plant', 'pctl')
    report = rig.last_report(name)
    assert int(report[4]['received/external_wrench']) >= int(base.get(
        'received/external_wrench', 0)) + 4
    # This probe is a second publisher on /p/leg_forces beside the controller:
    # the plant reports that as a collision (ERROR) rather than a WARN.
    warn = [d for d in rig.reports(name, t_first)
            if d[2] == WARN or (d[2] == ERROR and d[3].startswith('collision'))]
    assert warn, rig.reports(name, t_first)[:3]
    # the plant runs on: truth keeps coming, finite; forces are still applied
    t_after = time.monotonic()
    assert rig.spin_until(lambda: sum(1 for r in rig.truth if r[0] > t_after) >= 50, 5.0)
    truth = rig.truth[n_truth:]
    assert all(np.all(np.isfinite(p)) and np.all(np.isfinite(q)) for _, p, q in truth)
    z = [p[2] for _, p, _ in truth]
    assert 0.5 < min(z) and max(z) < 2.0, (min(z), max(z), [
        (round(d[0], 2), d[2], d[4].get('sample'), d[4].get('endstop_samples'),
         d[4].get('missed_cycles'), d[4].get('late_cycles')) for d in rig.reports(name)])
    later = rig.wait_report(name, lambda d: accepted(d[4]) > accepted0 + 50, 4.0, since=t_after)
    assert later is not None, 'the plant stopped taking the controller\'s forces'
    assert int(later[4]['sample']) > int(base['sample'])
    rig.check_alive('plant', 'pctl')
    print('\nplant: %d ground-truth poses during and after the bad input, all finite, '
          'z in [%.4f, %.4f] m' % (len(truth), min(z), max(z)))


# -- 4. the controller's watchdog ---------------------------------------------------
def test_watchdog(setup, rig, mech):
    name = NAMES['wd']
    lengths, rates = _steady_sample(mech)
    want = pd_forces(lengths, rates, setup.task.setpoint_lengths, setup.gains.kp, setup.gains.kv,
                     mech.max_force)

    def stream(seconds, until=None):
        """leg_lengths at ~50 Hz for up to ``seconds`` (or until ``until()``)."""
        end = time.monotonic() + seconds
        sent = []
        while time.monotonic() < end and not (until and until()):
            stamp = rig.next_stamp('wd', 0.02)
            rig.pub_lengths['wd'].publish(rig.joint_state(stamp, lengths, rates))
            last_publish[0] = time.monotonic()
            sent.append(stamp)
            rig.spin_for(0.02)
        return sent
    last_publish = [0.0]

    # samples flowing: forces come back, status OK
    t0 = time.monotonic()

    def flowing():
        recent = [d for d in rig.reports(name, t0 + 0.3)]
        answered = sum(1 for s in rig.forces['wd'] if s > rig.stamp['wd'] - 10**9)
        return answered >= 10 and recent and recent[-1][2] == OK
    sent = stream(6.0, until=flowing)
    got = [s for s in sent if s in rig.forces['wd']]
    assert len(got) >= 10, 'only %d forces for %d samples' % (len(got), len(sent))
    np.testing.assert_allclose(np.array(rig.forces['wd'][got[-1]].effort), want, rtol=0,
                               atol=FORCE_TOL)
    assert rig.reports(name, t0 + 0.3)[-1][2] == OK, rig.reports(name, t0)

    # samples stop: ERROR mentioning the watchdog, and no forces
    t_stop = last_publish[0]
    err = rig.wait_report(name, lambda d: d[2] == ERROR, 3.0, since=t_stop)
    assert err is not None, rig.reports(name, t_stop)
    assert 'watchdog' in err[3].lower(), err[3]
    delay = err[0] - t_stop
    assert 0.2 <= delay < 1.5, delay
    published = int(err[4].get('published/leg_forces', 0))
    n_forces = len(rig.force_log['wd'])
    later = rig.wait_report(name, lambda d: d[0] > err[0] + 0.5, 3.0, since=err[0] + 0.5)
    assert later is not None and later[2] == ERROR and 'watchdog' in later[3].lower(), later
    assert int(later[4].get('published/leg_forces', 0)) == published
    assert not [t for t, _ in rig.force_log['wd'][n_forces:]], 'forces published while tripped'
    assert not [t for t, _ in rig.force_log['wd'] if t > t_stop + 0.15]

    # samples resume: forces resume, status back to OK
    t_resume = time.monotonic()
    sent = stream(6.0, until=lambda: any(d[2] == OK for d in rig.reports(name, t_resume)))
    ok = [d for d in rig.reports(name, t_resume) if d[2] == OK]
    assert ok, rig.reports(name, t_resume)
    got = [s for s in sent if s in rig.forces['wd']]
    assert got and len(got) >= len(sent) // 2, (len(got), len(sent))
    for s in got:
        np.testing.assert_allclose(np.array(rig.forces['wd'][s].effort), want, rtol=0,
                                   atol=FORCE_TOL)
    assert int(ok[0][4]['published/leg_forces']) > published
    rig.check_alive('wd')
    print('\nwatchdog 0.2 s: ERROR %.3f s after the last sample; resumed with %d forces '
          'for %d samples' % (delay, len(got), len(sent)))

    # The plant pauses: it says "run: paused", stamped with its next sample,
    # and its last sample (stamped before that) comes after the word, as it
    # does over a field bus (through the bridge). That late sample is no
    # resumed run: the silence after it is the pause, not a lost sensor.
    in_flight = rig.next_stamp('wd', 0.02)
    rig.announce_run('wd', 'paused', in_flight + 20_000_000)
    rig.spin_for(0.1)                   # the word first, then the late sample
    t_late = time.monotonic()
    rig.pub_lengths['wd'].publish(rig.joint_state(in_flight, lengths, rates))
    assert rig.wait_report(name, lambda d: d[0] > t_late + 0.8, 3.0) is not None
    levels = [d[2] for d in rig.reports(name, t_late)]
    assert ERROR not in levels, rig.reports(name, t_late)
    assert in_flight in rig.forces['wd'], 'the late sample was answered'
    # the plant runs on: its next sample ends the pause
    rig.announce_run('wd', 'running', in_flight + 20_000_000)


# -- 6. diagnostics at about 1 Hz ----------------------------------------------------
def test_every_node_reports_at_about_1_hz(rig):
    rig.spin_for(0.6)                 # past the /wd controller's trip after test_watchdog
    t0 = time.monotonic()
    rig.spin_for(4.5)
    periods = {}
    for key, name in NAMES.items():
        times = [d[0] for d in rig.reports(name, t0)]
        assert len(times) >= 3, (name, times)
        gaps = np.diff(times)
        periods[key] = (float(gaps.mean()), float(gaps.min()), float(gaps.max()))
        assert 0.5 <= gaps.min() and gaps.max() <= 2.0, (name, gaps)
        assert 0.8 <= gaps.mean() <= 1.25, (name, gaps)
    print('\n/diagnostics periods (mean, min, max) [s]: %s' % {
        k: tuple(round(v, 3) for v in p) for k, p in periods.items()})
    rig.check_alive()


# -- 5. parameter errors stop a node at start-up ----------------------------------------
def test_parameter_errors_stop_the_node(ros, tmp_path):
    text = PARAMS.read_text()
    line = next(s for s in text.splitlines() if s.strip().startswith('kp:'))
    bad_file = tmp_path / 'nan.yaml'
    bad_file.write_text(text.replace(line, '    kp: [4000.0, .nan, 4000.0, 4000.0, 4000.0, '
                                           '4000.0]'))
    cases = [
        ('controller', ['-p', 'platform_mass:=-1.0'], 'platform_mass'),
        ('controller', ['--params-file', str(bad_file)], 'kp'),
        ('plant', ['-p', 'clock_mode:=bogus'], 'clock_mode'),
        ('fk', ['-p', 'singularity_threshold:=-5.0'], 'singularity_threshold'),
        ('controller', ['-p', 'realtime_priority:=100'], 'realtime_priority'),
    ]
    procs = [(ros.spawn([executable(exe), '--ros-args', '-r', '__ns:=/bad%d' % i, *args],
                        name=exe), exe, key) for i, (exe, args, key) in enumerate(cases)]
    for proc, exe, key in procs:
        rc = proc.wait(60)
        assert rc is not None, '%s did not stop on a bad %s:\n%s' % (exe, key, proc.describe())
        err, out = proc.stderr(), proc.stdout()
        assert rc != 0, proc.describe()
        assert 'Traceback' not in err + out, proc.describe()
        lines = [s for s in err.splitlines() if 'parameter error' in s]
        assert len(lines) == 1 and key in lines[0] and lines[0].startswith(exe + ':'), err
        print('\n%s exit %d: %s' % (exe, rc, lines[0]))


# -- 6. the serialized hot-path messages (runtime/wire.py), no DDS ---------------------
def _joint_state(names, position, velocity, effort, frame_id='base', ns=1_234_567_891):
    from sensor_msgs.msg import JointState
    msg = JointState(name=list(names), position=list(position), velocity=list(velocity),
                     effort=list(effort))
    msg.header.stamp = to_time(ns)
    msg.header.frame_id = frame_id
    return msg


def _object_path(msg, gate, want, optional=()):
    """What the nodes did with a message object: the reference for the fast path."""
    from stewart63_ros.runtime.checks import leg_vector
    ns = gate.check(msg.header.stamp)
    values = {f: leg_vector(msg.name, getattr(msg, f), f) for f in want}
    for f in optional:
        if len(getattr(msg, f)):
            values[f] = leg_vector(msg.name, getattr(msg, f), f)
    return ns, msg.header.frame_id, values


def test_serialized_joint_states_read_as_message_objects_do():
    """Every variant of names, sizes, non-finite numbers and frame ids: the
    bytes path gives the values, stamp and frame id of the object path, or
    the same Rejected reason."""
    import itertools

    from rclpy.serialization import serialize_message

    from stewart63_ros.runtime import wire
    from stewart63_ros.runtime.checks import Rejected, StampGate
    rng = np.random.default_rng(7)
    six = rng.normal(size=6)
    arrays = {'empty': [], 'six': six, 'five': six[:5], 'seven': np.append(six, 1.0),
              'nan': np.where(np.arange(6) == 2, np.nan, six),
              'inf': np.where(np.arange(6) == 5, -np.inf, six)}
    names = {'legs': LEGS, 'none': [], 'reversed': LEGS[::-1], 'unknown': LEGS[:5] + ['leg_7'],
             'five': LEGS[:5]}
    uses = [(('position', 'velocity'), ()), (('effort',), ()), (('position',), ('velocity',))]
    checked = fast = 0
    for (nk, nm), fields, frame_id, (want, optional) in itertools.product(
            names.items(), itertools.product(['six', 'empty', 'nan', 'five', 'seven', 'inf'],
                                             repeat=3),
            ['', 'base', 'base_link', 'ünï'], uses):
        msg = _joint_state(nm, *(arrays[f] for f in fields), frame_id=frame_id)
        data = serialize_message(msg)
        try:
            expected = _object_path(msg, StampGate(), want, optional)
        except Rejected as exc:
            expected = exc.reason
        try:
            ns, sec, nanosec, frame, values = wire.joint_state_sample(data, StampGate(), want,
                                                                      optional)
            got = (ns, frame, values)
            assert (sec, nanosec) == (msg.header.stamp.sec, msg.header.stamp.nanosec)
        except Rejected as exc:
            got = exc.reason
        if isinstance(expected, str):
            assert got == expected, (nk, fields, want)
        else:
            assert not isinstance(got, str), (nk, fields, want, got)
            assert got[:2] == expected[:2]
            assert sorted(got[2]) == sorted(expected[2])
            for key, value in expected[2].items():
                assert np.array_equal(got[2][key], value) and got[2][key].dtype == float
        fast += wire.read_joint_state(data, want, optional) is not None
        checked += 1
    # the old stamp is rejected on either path, before the fields are looked at
    gate = StampGate()
    gate.accept(2_000_000_000)
    for msg in (_joint_state(LEGS, six, six, []), _joint_state(LEGS, arrays['nan'], six, [])):
        with pytest.raises(Rejected) as exc:
            wire.joint_state_sample(serialize_message(msg), gate, ('position', 'velocity'))
        assert exc.value.reason == 'stamp_from_past'
    with pytest.raises(Rejected) as exc:
        wire.joint_state_sample(b'\x00\x01\x00\x00\xff', StampGate(), ('effort',))
    assert exc.value.reason == 'undecodable'
    assert fast > 100
    print('\n%d serialized JointState variants: bytes path == object path (%d on the fast path)'
          % (checked, fast))


def test_message_templates_serialize_like_rclpy():
    from geometry_msgs.msg import PoseStamped, TwistStamped
    from rclpy.serialization import deserialize_message
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import JointState

    from stewart63_ros.runtime import wire
    rng = np.random.default_rng(3)
    for frame_id in ('', 'base', 'base_link', b'base', 'ünï'):
        text = frame_id.decode() if isinstance(frame_id, bytes) else frame_id
        pos, vel = rng.normal(size=6), rng.normal(size=6)
        data = wire.JointStateTemplates(('position', 'velocity')).get(frame_id).fill(
            3, 999_999_999, position=pos, velocity=vel)
        assert deserialize_message(data, JointState) == _joint_state(LEGS, pos, vel, [], text,
                                                                     3_999_999_999)
        assert len(data) == _exact_size(data, JointState)
        effort = rng.normal(size=6)
        data = wire.JointStateTemplates(('effort',)).get(frame_id).fill(-2, 5, effort=effort)
        assert deserialize_message(data, JointState) == _joint_state(LEGS, [], [], effort, text,
                                                                     -2 * 10**9 + 5)
        assert len(data) == _exact_size(data, JointState)
    p, q = rng.normal(size=3), rng.normal(size=4)
    msg = deserialize_message(wire.pose_template('base').fill(1, 2, position=p, orientation=q),
                              PoseStamped)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (1, 2, 'base')
    pp, qq = msg.pose.position, msg.pose.orientation
    assert [pp.x, pp.y, pp.z] == p.tolist() and [qq.x, qq.y, qq.z, qq.w] == q.tolist()
    lin, ang = rng.normal(size=3), rng.normal(size=3)
    msg = deserialize_message(wire.twist_template('odom').fill(4, 5, linear=lin, angular=ang),
                              TwistStamped)
    assert msg.header.frame_id == 'odom' and msg.header.stamp.nanosec == 5
    tl, ta = msg.twist.linear, msg.twist.angular
    assert [tl.x, tl.y, tl.z] == lin.tolist() and [ta.x, ta.y, ta.z] == ang.tolist()
    msg = deserialize_message(wire.clock_template().fill(7, 8), Clock)
    assert (msg.clock.sec, msg.clock.nanosec) == (7, 8)
    for tpl, msg_type in ((wire.pose_template('base'), PoseStamped),
                          (wire.twist_template(''), TwistStamped), (wire.clock_template(), Clock)):
        assert len(tpl.fill(1, 2)) == _exact_size(tpl.fill(1, 2), msg_type)


def _exact_size(data, msg_type):
    """The shortest prefix of ``data`` that still deserializes: the size the
    middleware puts on the wire (strict readers such as rosbags refuse more)."""
    from rclpy.serialization import deserialize_message
    size = len(data)
    while size > 4:
        try:
            deserialize_message(data[:size - 1], msg_type)
        except Exception:  # noqa: BLE001 - too short
            return size
        size -= 1
    return size
