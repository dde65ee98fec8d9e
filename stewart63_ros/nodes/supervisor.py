"""supervisor: between the controller and the machine; trips, latches, brings it down.

With ``rig --supervisor`` the controller's ``leg_forces`` is remapped to
``leg_forces_request``; the supervisor answers every ``leg_lengths`` sample
on ``leg_forces``, stamped with it: the controller's request forwarded while
no limit is crossed, else the safe action of the trip's cause (zero force,
hold, or a descent to the rest pose): core/machine/supervisor.py, docs/supervisor.md.

A trip latches: ERROR on /diagnostics naming the cause, the sample and the
safe action (and in the node's summary), until ``~/reset``
(std_srvs/Trigger), refused with the reason while the cause persists.
``~/estop`` (Trigger) trips at once. ``trip_request`` (std_msgs/String, the
reason) trips too: a user's node or tool asks for a stop there; a control
law asks by raising (the controller's ERROR on /diagnostics trips).

Lockstep: sample k is answered once the controller's request for k is in (a
sample with a missing reading at once: the controller refuses it), or an
ERROR from a node of the rig arrived meanwhile, or ``request_timeout`` passed;
the plant waits for that answer, so the run stays deterministic.
"""
from __future__ import annotations

import sys
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger

from stewart63_ros import topics
from stewart63_ros.core.machine.supervisor import (
    LIMIT_KEYS,
    limits_from_params,
    supervisor_from_params,
)
from stewart63_ros.core.plumbing.stamps import NS_PER_S, SampleSpacing, ns_of
from stewart63_ros.exits import quiet_on_closed_pipe
from stewart63_ros.nodes.supervisor_homing import SupervisorHoming
from stewart63_ros.runtime import wire
from stewart63_ros.runtime.base import RigNode
from stewart63_ros.runtime.checks import (
    RESTART_PAUSE,
    Rejected,
    StampGate,
    ros_time,
    source_of,
    stamp_ns,
)
from stewart63_ros.runtime.launcher import STOP, run
from stewart63_ros.runtime.rclpy_internals import WaitAny, take_with_info
from stewart63_ros.runtime.startup import FirstAnswer

#: The controller's forces, remapped here when the supervisor is in the rig.
REQUEST_TOPIC = 'leg_forces_request'
#: A user's stop: std_msgs/String, the reason.
TRIP_TOPIC = 'trip_request'


class SupervisorNode(SupervisorHoming, RigNode):
    def __init__(self, options):
        super().__init__('supervisor')
        self.lockstep = self.param('clock_mode') == 'lockstep'
        self.rate = self.param('sensor_rate')
        self.spacing = SampleSpacing(NS_PER_S / self.rate)     # the plant's rate, checked
        self.request_timeout = self.param('request_timeout')
        self.trip_on_diagnostics = self.param('trip_on_diagnostics')
        # Load the kernels (forward kinematics, the hold's model) on a throwaway
        # copy now, not on the first sample or the first trip.
        warm = supervisor_from_params(self.setup, self.params, self.rate)    # exit 2
        warm.on_sample(0, np.array(self.setup.task.setpoint_lengths, float), np.zeros(6))
        warm.trip_now('estop', 'warm-up')
        warm.safe_forces(0)
        self.core = supervisor_from_params(self.setup, self.params, self.rate)
        for limit_key in LIMIT_KEYS:
            self.tunable(limit_key, self._limit_setter(limit_key))
        self.tunable('trip_on_diagnostics',
                     lambda value: setattr(self, 'trip_on_diagnostics', value))
        self.sample_gate = StampGate(RESTART_PAUSE)
        # The sensors read the true length plus leg_length_offset (the file's).
        self.length_offset = self.param('leg_length_offset')
        self.pending = None         # (ns, sec, nanosec, frame_id) of the sample to answer
        self.waiting_since = None   # monotonic s: since when ``pending`` waits (attend)
        self.answered_ns = -1
        self.early = {}             # requests that came before their sample: ns -> forces
        self.headers = {}           # realtime: the newest sample's (ns, sec, nanosec, frame_id)
        self.state = None           # the core's state, on /diagnostics when it changes
        self.async_trip = None      # (cause, detail) to latch before the next answer
        self.node_errors = {}       # node of the rig -> its ERROR message, while in ERROR
        self.late_requests = 0
        self.timeouts = 0
        self.pub_forces = self.publisher(JointState, topics.LEG_FORCES, topics.STREAM_PUB)
        self.send_forces = self.health.sender(topics.LEG_FORCES, self.pub_forces)
        # lockstep: its first answer to a plant waits for its writer's side of the match
        self.first_answer = FirstAnswer(self, self.pub_forces, topics.LEG_LENGTHS) \
            if self.lockstep else None
        self.forces_out = wire.JointStateTemplates(('effort',))
        self.forces_out.get('base')
        wire.warm_up(('position', 'velocity'))
        self.sub_samples = None         # made once its forces are matched
        self.sub_requests = self.create_subscription(JointState, REQUEST_TOPIC,
                                                     self.on_request, topics.EVERY_SUB, raw=True)
        self.sub_diagnostics = self.create_subscription(
            DiagnosticArray, topics.DIAGNOSTICS, self.on_diagnostics, topics.DIAGNOSTICS_QOS)
        self.sub_trip = self.create_subscription(String, TRIP_TOPIC, self.on_trip_request,
                                                 topics.COMMAND_VOLATILE_QOS)
        self.create_service(Trigger, '~/estop', self.on_estop)
        self.create_service(Trigger, '~/reset', self.on_reset)
        # The statuses of the nodes of this rig: 'stewart63/<ns>/<node>'.
        own = topics.node_full_name(self.get_namespace(), 'x')
        self.rig_prefix = topics.status_name(own[:-1])
        if self.core.homing is not None:
            # The node that owns the sensors' zero: the plant, or on the bus
            # the bridge (it writes the drives' home offset 0x607C).
            self.zero_node = self.param('homed_offset_node')
            self.connect_zero_node()
            self.health.values['homed'] = 'false'
        self.health.values.update({'tripped': 'false', 'trips': 0,
                                   'rest_lengths': np.round(self.core.rest, 4).tolist()})

    def subscribe_input(self):
        """``leg_lengths``, once its forces are matched (RigNode.subscribe_input):
        the plant, which waits for this subscription, then sends its first
        sample only once the supervisor can answer it."""
        if self.sub_samples is None:
            self.sub_samples = self.create_subscription(
                JointState, topics.LEG_LENGTHS, self.on_sample, topics.LATEST_SUB, raw=True)

    # -- run-time limits -------------------------------------------------------------
    def _limit_setter(self, name):
        def apply(value):
            params = dict(self.params, **{name: value})
            # the same checks as at start-up
            self.core.set_limits(limits_from_params(self.mech, params, self.rate))
        return apply

    # -- inputs ----------------------------------------------------------------------
    def on_sample(self, data: bytes, info):
        """A leg_lengths sample: checked; answered at once when tripped or when
        no request will come (a missing reading), else when its request does."""
        self.health.received[topics.LEG_LENGTHS] += 1
        if self.pending is not None:
            # (realtime, while the homing sets the plant's offsets: this
            # sample goes unanswered, the plant holds the force it has)
            self.health.values['samples_unanswered'] = \
                self.health.values.get('samples_unanswered', 0) + 1
            return
        try:
            ns, sec, nanosec, frame_id, values = wire.joint_state_sample(
                data, self.sample_gate, ('position', 'velocity'), source=source_of(info))
            lengths, rates, complete = values['position'], values['velocity'], True
        except Rejected as exc:
            # A reading with NaN (a sensor dropout) is a missing reading, not
            # a bad message: it counts towards stale_lengths_ms.
            msg = wire.deserialize(data, JointState) if exc.reason == 'non_finite' else None
            if msg is None or len(msg.position) != 6:
                self.health.reject(topics.LEG_LENGTHS, exc)
                return
            ns = stamp_ns(msg.header.stamp)
            sec, nanosec, frame_id = msg.header.stamp.sec, msg.header.stamp.nanosec, \
                msg.header.frame_id
            lengths = np.array(msg.position, float)
            rates = np.array(msg.velocity, float) if len(msg.velocity) == 6 else \
                np.full(6, np.nan)
            complete = False
        lengths = lengths - self.length_offset
        if self.sample_gate.new_run:        # a plant's ~/reset: its stamps start again
            self.core.new_run()
        self.sample_gate.accept(ns, source_of(info))
        if self.first_answer is not None:
            self.first_answer.wait(source_of(info))
        wrong_rate = self.spacing.add(ns)
        if wrong_rate:
            # a setting to fix, not a fault of the machine: WARN, no trip
            self.health.warning = wrong_rate
            self.health.values['sample_spacing_ms'] = self.spacing.smallest * 1e-6
            self.get_logger().warning(wrong_rate)
        self.latch_async(ns)
        core = self.core
        core.on_sample(ns, lengths, rates)
        self.pending = (ns, sec, nanosec, frame_id)
        if not self.lockstep:       # a late request answers its own sample (on_request)
            self.headers[ns] = self.pending
            if len(self.headers) > 16:
                del self.headers[min(self.headers)]
        if core.trip is not None:
            self.answer(core.safe_forces(ns))
        elif core.homing is not None:
            self.answer(self.home(ns))
        elif not complete:
            self.answer(core.no_request(ns))
        else:
            early = self.early.pop(ns, None)
            if early is not None:
                self.answer(core.on_request(ns, early))
        for old in [k for k in self.early if k < ns]:
            # (a request for a sample this node skipped: its controller lives)
            self.core.note_request(old, self.early.pop(old))

    def on_request(self, data: bytes, info=None):
        """The controller's forces for a sample: checked and answered if that
        sample waits; kept if it has not come yet; a late one is counted."""
        self.health.received[REQUEST_TOPIC] += 1
        # (the plain request read straight from its bytes, 2 us, not a full
        # deserialize, 12 us, in this 1 kHz loop; anything else the long way)
        fast = wire.read_joint_state(data, ('effort',))
        if fast is not None:
            ns = ns_of(fast[0], fast[1])
            forces = fast[3]['effort']
        else:
            msg = wire.deserialize(data, JointState)
            if msg is None:
                self.health.reject(REQUEST_TOPIC, Rejected('undecodable', 'not a JointState'))
                return
            ns = stamp_ns(msg.header.stamp)
            forces = np.array(msg.effort, float)
        if self.core.homing is not None:
            return                  # withheld until every leg is homed
        if self.pending is not None and ns == self.pending[0]:
            self.latch_async(ns)
            self.answer(self.core.on_request(ns, forces))
        elif self.core.trip is not None:
            # Tripped, the safe force answers a sample at once: its request
            # comes after, and is the latest the controller wants, which a
            # reset judges (a request parked here would leave the core the
            # one from before the trip, and forces_stale for ever).
            self.core.note_request(ns, forces)
        elif ns > self.answered_ns and ns in self.headers and (
                self.pending is None or ns < self.pending[0]):
            # Realtime: its sample went unanswered (it waited a period, or a
            # newer one overtook it); the plant holds an older force until
            # a newer one comes: this is it, stamped with its own sample.
            self.count_late()
            self.send(self.headers[ns], self.core.on_request(ns, forces))
            self.answered_ns = ns
        elif self.pending is None or ns > self.pending[0]:
            self.early[ns] = forces
        else:
            self.count_late()
            self.core.note_request(ns, forces)      # late, but the controller lives

    def on_diagnostics(self, msg):
        """A node of this rig whose status turns ERROR (or names a new error)
        trips; one that stays in the same ERROR does not trip again, and a
        reset after such a trip is refused until no node of the rig is in ERROR."""
        for status in msg.status:
            name = status.name
            if name == self.health.status_name or not name.startswith(self.rig_prefix) \
                    or '/' in name[len(self.rig_prefix):]:
                continue
            node = name[len(topics.STATUS_PREFIX):]
            if status.level != DiagnosticStatus.ERROR:
                self.node_errors.pop(node, None)
                continue
            if self.node_errors.get(node) == status.message:
                continue
            self.node_errors[node] = status.message
            if self.trip_on_diagnostics:
                self.request_trip('diagnostics_error', '%s: %s' % (node, status.message))

    def on_trip_request(self, msg):
        self.request_trip('user_request', msg.data or '(no reason given)')

    def on_estop(self, request, response):
        response.success = True
        if self.core.trip is not None:
            trip = self.core.trip
            response.message = 'already tripped (%s at sample %d): %s' % (
                trip.cause, self.core.sample_index(trip.sample_ns), trip.action)
        else:
            self.request_trip('estop', '~/estop')
            response.message = 'tripped: the next answer is the descent to rest'
        self.get_logger().warning('~/estop: %s' % response.message)
        return response

    def on_reset(self, request, response):
        trip = self.core.trip
        if trip is not None and trip.cause == 'diagnostics_error' and self.node_errors:
            response.success = False
            response.message = 'the cause of the trip (diagnostics_error) persists: %s' % (
                '; '.join('%s in ERROR: %s' % item for item in self.node_errors.items()))
        elif trip is not None and trip.cause == 'homing' and (refused := self.set_zero_again()):
            response.success = False
            response.message = 'the cause of the trip (homing) persists: %s' % refused
        else:
            response.success, response.message = self.core.reset()
        if response.success:
            self.async_trip = None
            self.health.fault = ''
            self.health.values['tripped'] = 'false'
            self.report()
        self.get_logger().info('~/reset: %s' % response.message)
        return response

    # -- trips and answers -------------------------------------------------------------
    def request_trip(self, cause: str, detail: str) -> None:
        """A trip from outside the samples: latched before the next answer
        (the sample that answer belongs to is the trip's)."""
        if self.core.trip is None and self.async_trip is None:
            self.async_trip = (cause, detail)

    def latch_async(self, ns: int) -> None:
        if self.async_trip is not None:
            cause, detail = self.async_trip
            self.async_trip = None
            self.core.trip_now(cause, detail, ns)

    def count_late(self) -> None:
        self.late_requests += 1
        self.health.values['late_requests'] = self.late_requests

    def send(self, header, forces) -> None:
        """``forces`` on leg_forces, stamped as the sample ``header``
        (ns, sec, nanosec, frame_id) it answers."""
        _, sec, nanosec, frame_id = header
        self.send_forces(self.forces_out.get(frame_id).fill(sec, nanosec, effort=forces))

    def answer(self, forces) -> None:
        header, self.pending = self.pending, None
        self.answered_ns = header[0]
        self.send(header, forces)
        trip = self.core.trip
        if trip is not None and self.health.values.get('tripped') == 'false':
            self.announce(trip)
        state = self.core.state
        if state != self.state:
            # (descended: a reset can lead back; returning, then forwarding)
            self.state = self.health.values['state'] = state
            self.report()

    def announce(self, trip) -> None:
        self.state = self.health.values['state'] = self.core.state
        report = self.core.trip_report(trip)
        self.health.fault = 'tripped: %s at sample %d (%s); safe action: %s; latency %s ' \
            'samples' % (trip.cause, report['sample'], trip.detail, trip.action,
                         report['latency_samples'])
        self.health.values.update({'tripped': 'true', 'trips': len(self.core.trips)})
        self.health.values.update({'trip/%s' % key: value for key, value in report.items()})
        self.get_logger().error(self.health.fault)
        self.health.report(ros_time(trip.sample_ns * 1e-9) if self.lockstep else None)

    # -- the loop ----------------------------------------------------------------------
    def run(self):
        self.wait_for_matches()
        self.start_hot_loop(self.sub_samples)
        waiter = WaitAny(self.context, [self.sub_samples, self.sub_requests,
                                        self.sub_diagnostics, self.sub_trip])
        while not STOP.requested:
            now = time.monotonic()
            wake = self.housekeeping(now)       # requests, /diagnostics, services, timers
            self.attend(now)
            if self.pending is None:
                taken = take_with_info(self.sub_samples)
                if taken is not None:
                    self.on_sample(*taken)
                    continue
            timeout = max(0.0, wake - time.monotonic())
            if self.pending is not None:
                timeout = min(timeout, 0.005)
            waiter.wait(timeout)
        return 0

    def attend(self, now: float) -> None:
        """The sample waiting for its request (``pending``), at ``now``
        (monotonic): answered at once with the safe action when a trip came
        meanwhile; lockstep: answered without a request after
        ``request_timeout``; realtime: given up after a period (the plant
        holds the last force). Its own loop calls this, and so does the
        composed rig's (nodes/composed.py)."""
        if self.pending is None:
            self.waiting_since = None
            return
        if self.waiting_since is None:
            self.waiting_since = now
        if self.async_trip is not None:
            self.latch_async(self.pending[0])
            self.answer(self.core.safe_forces(self.pending[0]))
        elif self.lockstep and now - self.waiting_since > (
                self.request_timeout if self.health.received[REQUEST_TOPIC]
                else max(self.request_timeout, self.discovery_timeout)):
            # (the first request races discovery, as the plant's first
            # answer does: a reliable repair can take a heartbeat, ~1 s)
            self.timeouts += 1
            self.health.values['request_timeouts'] = self.timeouts
            self.health.warning = ('no request for the sample stamped %d ns within '
                                   '%g s (request_timeout): answered without one'
                                   % (self.pending[0], self.request_timeout))
            if self.timeouts <= 10:
                self.get_logger().warning(self.health.warning)
            self.answer(self.core.no_request(self.pending[0]))
        elif not self.lockstep and now - self.waiting_since > 1.0 / self.rate:
            self.pending = None         # realtime: the plant holds the last force
        if self.pending is None:
            self.waiting_since = None

    def summary(self) -> dict:
        out = super().summary()
        out['trips'] = [self.core.trip_report(t) for t in self.core.trips]
        return out


@quiet_on_closed_pipe
def main(argv=None):
    sys.exit(run('supervisor', __doc__.split('\n\n')[0], SupervisorNode, argv))


if __name__ == '__main__':
    main()
