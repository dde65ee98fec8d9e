"""The supervisor node (nodes/supervisor.py) in this process, driven as its
loop drives it: every trip cause, in lockstep and in realtime, is refused a
reset while it holds (naming what holds), accepted once it is gone, and the
node goes on (the return, then the controller's live requests forwarded).

This is the node's own path, where an old bug lived (tripped, the
node parked every request and never handed it to the core, so ``force`` and
``forces_stale`` could never be reset): the node's callbacks are called
directly with serialized messages, its loop's ``attend`` with an injected
monotonic clock (no sleep, no executor, no other process). The core's rule
itself is test_supervisor.py's; the DDS wiring test_supervisor_dds.py's.
"""
from __future__ import annotations

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from ros_harness import lease_domain_id
from std_msgs.msg import String
from std_srvs.srv import Trigger

from stewart63_ros.core.machine.supervisor import CAUSES, HOLD, ZERO
from stewart63_ros.core.mechanics.kinematics import leg_lengths
from stewart63_ros.core.mechanics.rotation import rotation_from_euler
from stewart63_ros.runtime import parameters, wire

#: 200 Hz (the bus's realtime rate on this machine): the return's 0.5 s of
#: settling and hand-over is 100 samples, not 500.
RATE = 200.0
PERIOD_NS = int(1e9 / RATE)
MODES = ('lockstep', 'realtime')
SAMPLES = wire.JointStateTemplates(('position', 'velocity')).get('base')
REQUESTS = wire.JointStateTemplates(('effort',)).get('base')


@pytest.fixture(scope='module')
def ros_in_process():
    """rclpy's default context on a leased domain (the node's DDS entities
    are made, never spun: nothing comes in but what the test hands over)."""
    lease = lease_domain_id()
    own = not rclpy.ok()
    if own:
        rclpy.init(args=[], domain_id=int(lease))
    yield
    if own:
        rclpy.shutdown()
    lease.release()


def supervisor_node(monkeypatch, mode: str, **params):
    """A SupervisorNode with the packaged file and these ``-p`` overrides."""
    from stewart63_ros.nodes.supervisor import SupervisorNode
    argv = ['supervisor', '--ros-args', '-p', 'clock_mode:=%s' % mode,
            '-p', 'sensor_rate:=%r' % RATE]
    for key, value in params.items():
        argv += ['-p', '%s:=%s' % (key, value)]
    monkeypatch.setattr(parameters, '_argv', argv)
    return SupervisorNode(None)


class Loop:
    """Drives ``node`` as its loop (``SupervisorNode.run``) would, sample by
    sample, with the monotonic clock injected into ``attend``.

    Lockstep: the plant sends sample k once k - 1 is answered; the
    controller's request for k comes after the sample (none: ``attend``
    answers without it once ``request_timeout`` passed). Realtime: samples
    every period; the controller answers the even samples in time and the
    odd ones late, after the next sample came (the node gave the sample up
    after a period; the late request is forwarded with its own stamp, or,
    tripped, handed to the core)."""

    def __init__(self, node, mode: str):
        self.node, self.lockstep = node, mode == 'lockstep'
        self.k = 0
        self.base_ns = 0 if self.lockstep else 1_795_000_000 * 10**9   # wall-clock stamps
        self.now = 1000.0
        self.sent = {}              # stamp ns -> forces sent on leg_forces
        self.requested = {}         # stamp ns -> the request the controller sent
        self.late = []
        original = node.send

        def send(header, forces):
            self.sent[header[0]] = np.array(forces, float)
            original(header, forces)
        node.send = send

    def ns(self, k: int) -> int:
        return self.base_ns + k * PERIOD_NS

    def request(self, k: int, forces) -> None:
        ns = self.ns(k)
        self.requested[ns] = np.asarray(forces, float)
        self.node.on_request(REQUESTS.fill(ns // 10**9, ns % 10**9, effort=forces))

    def step(self, lengths, rates, request=None) -> None:
        """One sample with these readings; ``request``: the controller's
        forces for it, or None (it sends none)."""
        node, k, ns = self.node, self.k, self.ns(self.k)
        self.now += 1.0 / RATE
        node.attend(self.now)
        assert node.pending is None, 'a sample still waits for its answer'
        node.on_sample(SAMPLES.fill(ns // 10**9, ns % 10**9, position=lengths,
                                    velocity=rates), None)
        for late_k, forces in self.late:            # realtime: after the next sample
            self.request(late_k, forces)
        self.late = []
        if request is not None and (self.lockstep or k % 2 == 0):
            self.request(k, request)
        elif request is not None:
            self.late.append((k, request))
        node.attend(self.now)           # the loop's next turn
        if node.pending is not None:
            # no request (yet): lockstep answers without one after
            # request_timeout, realtime gives the sample up after a period
            self.now += 1.01 * (node.request_timeout if self.lockstep else 1.0 / RATE)
            node.attend(self.now)
        assert node.pending is None
        if self.lockstep:
            assert ns in self.sent, 'lockstep: sample %d unanswered' % k
        self.k += 1

    def run(self, count: int, stream) -> None:
        """``count`` samples of ``stream``: k -> (lengths, rates, request)."""
        for _ in range(count):
            self.step(*stream(self.k))


def reset(node) -> tuple[bool, str]:
    answer = node.on_reset(Trigger.Request(), Trigger.Response())
    return answer.success, answer.message


def statuses(node, level, message: str) -> DiagnosticArray:
    """/diagnostics from the controller of the node's rig."""
    return DiagnosticArray(status=[DiagnosticStatus(
        name=node.rig_prefix + 'controller', level=level, message=message)])


class Streams:
    """The readings and requests of the cases (the packaged machine)."""

    def __init__(self):
        from stewart63_ros.core.plumbing.params import default_params_path, load_setup
        setup = load_setup(default_params_path())
        self.setpoint = np.array(setup.task.setpoint_lengths, float)
        mech = setup.mechanism
        # 6 cm to the side of the box's x limit 0.1 m (a box override)
        self.aside = leg_lengths(mech, np.array([0.15, 0.01, 1.07]), np.eye(3))
        # rolled 0.3 rad (below trip_tilt): condition number 3.8, the
        # setpoint's 3.3 (trip_condition 3.5 here)
        self.rolled = leg_lengths(mech, np.array([0.0, 0.0, 1.0]),
                                  rotation_from_euler(np.array([0.3, 0.0, 0.0])))

    def steady(self, lengths=None, rates=None, request='live'):
        """k -> (lengths, rates, request): the live request varies by sample
        (so a forwarded one is told from another), 50 to 52 N."""
        lengths = self.setpoint if lengths is None else lengths
        rates = np.zeros(6) if rates is None else rates

        def stream(k):
            forces = np.full(6, 50.0 + k % 3) if request == 'live' else request(k)
            return lengths, rates, forces
        return stream


def leg(i: int, value: float, others: float = 0.0) -> np.ndarray:
    return np.where(np.arange(6) == i, value, others)


def cases(s: Streams) -> dict:
    """cause -> (overrides, how it is provoked: a stream or an event, the
    stream while it holds (None: an event, nothing holds), what the refusal
    names, how it goes (a callback or None), the stream once it is gone)."""
    live = s.steady()
    nan2 = s.setpoint + leg(1, np.nan)
    return {
        'lengths_stale': ({}, None, s.steady(lengths=nan2), 'the leg readings are missing '
                          '(NaN) on the latest sample', None, live),
        'forces_stale': ({}, None, s.steady(request=lambda k: None),
                         'no request from the controller for ', None, live),
        'bad_command': ({}, None, s.steady(request=lambda k: np.full(6, np.nan)),
                        'the latest request: request of shape (6,): [nan', None, live),
        'force': ({}, None, s.steady(request=lambda k: np.full(6, 5000.0)),
                  'the latest request: leg_1 5000.0 N, limit 3000 N', None, live),
        # 1000 N a sample against 1e5 N/s x 5 ms = 500 N; then steady
        'force_rate': ({'trip_force_rate': 1e5}, None,
                       s.steady(request=lambda k: np.full(6, 1000.0 * (k % 2))),
                       'the latest request: leg_1 2e+05 N/s, limit 100000 N/s', None, live),
        'stroke': ({}, None, s.steady(lengths=s.setpoint - leg(2, 0.4)),
                   'leg_3 at 1.2000 m, soft stroke [1.2500, 2.2500] m', None, live),
        'leg_speed': ({}, None, s.steady(rates=np.full(6, 0.6)),
                      'leg_1 at 0.600 m/s, limit 0.5 m/s', None, live),
        'pose_box': ({'pose_box': '[-0.1,-0.1,0.5,0.1,0.1,1.6]'}, None,
                     s.steady(lengths=s.aside), 'x = 0.1500 m outside [-0.1, 0.1] m', None,
                     live),
        'singularity': ({'trip_condition': 3.5}, None, s.steady(lengths=s.rolled),
                        'Jacobian condition number 3.8', None, live),
        'diagnostics_error': ({}, lambda node: node.on_diagnostics(statuses(
            node, DiagnosticStatus.ERROR, 'law failed')), live,
            'controller in ERROR: law failed',
            lambda node: node.on_diagnostics(statuses(node, DiagnosticStatus.OK, 'ok')), live),
        # events: reset at once, nothing holds
        'estop': ({}, lambda node: node.on_estop(Trigger.Request(), Trigger.Response()),
                  None, None, None, live),
        'user_request': ({}, lambda node: node.on_trip_request(String(data='my reason')),
                         None, None, None, live),
        # the safe action moves the platform off its reference: a reset is
        # accepted while leg 1 is still 6 cm off; the check starts over after the return
        'tracking_error': ({'trip_tracking_time': 0.05}, None,
                           s.steady(lengths=s.setpoint + leg(0, 0.06)), None, None, live),
    }


@pytest.fixture(scope='module')
def streams():
    return Streams()


@pytest.mark.parametrize('mode', MODES)
@pytest.mark.parametrize('cause', sorted(set(CAUSES) - {'homing'}))
def test_every_trip_of_the_node_is_reset_once_gone_refused_while_it_holds(
        ros_in_process, streams, monkeypatch, mode, cause):
    """docs/supervisor.md's reset rule on the node: trip; a reset refused
    twice while the cause holds, naming it; accepted once it is gone; then
    the return and the controller's live requests forwarded again, every
    lockstep sample answered. (``homing``: the test below.)"""
    overrides, event, holds, refusal, goes, gone = cases(streams)[cause]
    node = supervisor_node(monkeypatch, mode, **overrides)
    try:
        loop = Loop(node, mode)
        loop.run(20, streams.steady())
        assert node.core.trip is None and node.core.state == 'forwarding'
        if event is not None:
            event(node)
        loop.run(30, holds or streams.steady())
        trip = node.core.trip
        assert trip is not None and trip.cause == cause, node.core.trips
        assert node.health.values['tripped'] == 'true'
        assert node.health.fault.startswith('tripped: %s at sample ' % cause)
        # the safe action answers (realtime: the samples answered at once)
        last = loop.sent[loop.ns(loop.k - 1)]
        if trip.action == ZERO:
            np.testing.assert_array_equal(last, np.zeros(6))
        elif trip.action == HOLD or cause != 'lengths_stale':
            assert not np.array_equal(last, loop.requested.get(loop.ns(loop.k - 1)))
        if refusal is not None:
            for _ in range(2):          # refused, and again: asking changes nothing
                ok, why = reset(node)
                assert not ok and why.startswith(
                    'the cause of the trip (%s) persists: ' % cause), why
                assert refusal in why, why
            assert node.health.values['tripped'] == 'true'
        if goes is not None:
            goes(node)
        loop.run(10, gone)
        ok, why = reset(node)
        assert ok and why.startswith('reset: %s trip of sample ' % cause), why
        assert node.health.values['tripped'] == 'false' and node.health.fault == ''
        first_after = loop.k
        loop.run(2, gone)
        assert node.core.state == 'returning', node.core.state
        loop.run(125, gone)         # the return: 0.2 s settling + 0.3 s hand-over
        assert node.core.trip is None and len(node.core.trips) == 1, node.core.trips
        assert node.core.state == 'forwarding' and node.state == 'forwarding'
        # the controller's live requests go out again, each with its own stamp
        forwarded = [ns for ns in loop.requested if ns >= loop.ns(loop.k - 20)
                     and ns in loop.sent]
        assert len(forwarded) >= (19 if mode == 'lockstep' else 9), len(forwarded)
        for ns in forwarded:
            np.testing.assert_array_equal(loop.sent[ns], loop.requested[ns])
        if mode == 'lockstep':
            assert all(loop.ns(k) in loop.sent for k in range(first_after, loop.k))
    finally:
        node.destroy_node()


class ZeroNode:
    """The node that owns the sensors' zero (the plant, or the bridge), as a
    composed peer: refuses ``homed_offset`` while ``refuse`` says why."""

    def __init__(self):
        self.refuse = 'drive 3: SDO timeout'
        self.offsets = None

    def set_parameters(self, params):
        from rcl_interfaces.msg import SetParametersResult
        if self.refuse:
            return [SetParametersResult(successful=False, reason=self.refuse)]
        self.offsets = np.array(params[0].value, float)
        return [SetParametersResult(successful=True)]


#: the hidden zero of each leg's sensor [m] (test_supervisor_dds.py's)
HIDDEN = np.array([0.003, -0.002, 0.005, 0.0, -0.004, 0.0012])


class HomingLegs:
    """Legs that follow the homing's setpoint exactly: towards their upper
    stops (2.3 m) at the homing's speed from a level pose 1.55 m up, then
    back; resting where they are while tripped; readings = truth + ``shift``
    (the hidden zero until the offsets are set)."""

    SPEED = 0.4

    def __init__(self, node, loop, mech):
        self.core, self.loop, self.stop = node.core, loop, mech.leg_length_max
        self.start = leg_lengths(mech, np.array([0.01, 0.01, 1.55]), np.eye(3))  # 1.9-2.2 m
        self.shift = HIDDEN.copy()
        self.true = self.start - self.SPEED / RATE     # (the first sample reads the start)

    def step(self) -> None:
        core, k = self.core, self.loop.k
        homing = core.homing
        moving = homing is not None and core.trip is None
        if homing is None:                  # homed: back at the start
            self.true = self.start
        elif homing.back is not None and moving:
            self.true = homing.back.at((self.loop.ns(k) - homing.back_ns) * 1e-9)[0]
        elif moving:
            self.true = np.minimum(self.true + self.SPEED / RATE, self.stop)
        rates = np.where(moving & (self.true < self.stop), self.SPEED, 0.0)
        self.loop.step(self.true + self.shift, rates, np.full(6, 50.0))

    def until(self, done, most: int) -> None:
        for _ in range(most):
            self.step()
            if done():
                return


def homing_node(monkeypatch, mode):
    from stewart63_ros.core.plumbing.params import default_params_path, load_setup
    node = supervisor_node(monkeypatch, mode, homing='true', homing_speed=HomingLegs.SPEED,
                           pose_box='[]')
    node.zero_peer = ZeroNode()
    loop = Loop(node, mode)
    return node, loop, HomingLegs(node, loop, load_setup(default_params_path()).mechanism)


@pytest.mark.parametrize('mode', MODES)
def test_a_homing_trip_is_reset_once_the_offsets_are_set_then_the_homing_goes_on(
        ros_in_process, monkeypatch, mode):
    """``homing``: the offsets a homing found could not be set on the node
    that owns the zero. A reset tries again: refused while that node
    refuses, naming its reason; accepted once it takes them. Then the
    homing's way back starts over from where the legs are (readings true
    now), ends homed, and the return to the reference follows (before, a
    reset went on without the offsets ever set: ``homed: true`` on readings
    off by the hidden zero, up to 5 mm)."""
    node, loop, legs = homing_node(monkeypatch, mode)
    core, zero = node.core, node.zero_peer
    try:
        legs.until(lambda: core.trip is not None, 400)
        assert core.trip is not None and core.trip.cause == 'homing', core.trips
        assert 'drive 3: SDO timeout' in core.trip.detail and core.state == 'tripped'
        np.testing.assert_array_equal(loop.sent[loop.ns(loop.k - 1)], np.zeros(6))
        legs.step()
        for _ in range(2):
            ok, why = reset(node)
            assert not ok and why.startswith('the cause of the trip (homing) persists: '), why
            assert 'drive 3: SDO timeout' in why, why
        assert zero.offsets is None
        zero.refuse = ''
        ok, why = reset(node)
        assert ok and why.startswith('reset: homing trip of sample'), why
        # the offsets found went to the zero's owner: the hidden zero, less
        # each stop's spring (the push over 2e6 N/m: under 0.2 mm)
        np.testing.assert_allclose(zero.offsets, HIDDEN, atol=2e-4)
        legs.shift = HIDDEN - zero.offsets
        assert node.health.values['homed'] == 'false' and core.state == 'homing'
        # the way back from where the legs are (at the stops) to the start
        back = core.homing.back
        np.testing.assert_allclose(back.start, legs.stop, atol=2e-4)
        np.testing.assert_allclose(back.end, legs.start, atol=2e-4)
        legs.until(lambda: core.homing is None, 500)
        assert core.homed and node.health.values['homed'] == 'true'
        assert core.trip is None and len(core.trips) == 1, core.trips
        legs.step()
        assert core.state == 'returning', core.state
    finally:
        node.destroy_node()


def test_a_trip_during_the_homing_is_reset_and_the_homing_starts_over(ros_in_process,
                                                                     monkeypatch):
    """~/estop half-way to the stops: the descent; a reset starts the homing
    over from where the legs are (its setpoint went on while tripped: going
    on would jump), which then homes as ever."""
    node, loop, legs = homing_node(monkeypatch, 'lockstep')
    core, zero = node.core, node.zero_peer
    zero.refuse = ''
    try:
        legs.until(lambda: False, 20)
        before = loop.sent[loop.ns(loop.k - 1)]
        node.on_estop(Trigger.Request(), Trigger.Response())
        legs.until(lambda: False, 10)
        assert core.trip.cause == 'estop' and core.state == 'tripped'
        ok, why = reset(node)
        assert ok, why
        assert core.state == 'homing'
        legs.step()
        # no pull towards where the setpoint would have gone meanwhile (0.1 N)
        after = loop.sent[loop.ns(loop.k - 1)]
        assert np.abs(after - before).max() < 10.0, (before, after)
        np.testing.assert_array_equal(core.homing.start, legs.true + legs.shift)
        legs.until(lambda: zero.offsets is not None, 400)
        np.testing.assert_allclose(zero.offsets, HIDDEN, atol=2e-4)
        legs.shift = HIDDEN - zero.offsets
        legs.until(lambda: core.homing is None, 500)
        assert core.homed and [t.cause for t in core.trips] == ['estop']
    finally:
        node.destroy_node()
