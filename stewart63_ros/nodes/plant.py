"""plant: integrates the platform dynamics and publishes simulated leg sensors.

Every sample period 1/sensor_rate it publishes ``leg_lengths`` (L_i, dL_i/dt),
``ground_truth/pose`` and ``ground_truth/twist`` (and /clock in lockstep;
these three are skipped while nobody subscribes to them: they are VOLATILE,
so no subscriber can tell), and applies the newest ``leg_forces`` with
zero-order hold (plus ``external_wrench``).

clock_mode ``lockstep``: simulated time on /clock; sample k+1 is computed only
once the force answering sample k has arrived (or ``force_timeout`` passed,
which is counted and reported), so a distributed run is deterministic and as
fast as the machine allows. clock_mode ``realtime``: paced by the wall clock;
a force takes effect when it arrives (the real loop delay acts on the
physics); an answer that has not arrived by the next sample is a missed
cycle, counted and reported.

Faults (parameter ``faults``) and the simulation control services
``~/pause``, ``~/reset`` and ``~/step``: nodes/plant_control.py, docs/faults.md.
"""
from __future__ import annotations

import math
import sys
import time

import numpy as np
from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState

from stewart63_ros import topics
from stewart63_ros.core.dynamics import OMEGA, POS, QUAT, VEL, Dynamics
from stewart63_ros.core.params import ParameterError
from stewart63_ros.core.sensor import SensorModel
from stewart63_ros.core.simulate import initial_state, substeps_for
from stewart63_ros.nodes import wire
from stewart63_ros.nodes.base import RigNode
from stewart63_ros.nodes.checks import (
    RESTART_PAUSE,
    Rejected,
    StampGate,
    finite_vector,
    ros_time,
    source_of,
)
from stewart63_ros.nodes.commands import CommandInput
from stewart63_ros.nodes.launcher import STOP, run
from stewart63_ros.nodes.plant_control import PlantControl
from stewart63_ros.nodes.rclpy_internals import raw_publisher

#: The tracking error in the summary counts samples from this time [s] on.
TRACKING_FROM = 1.0


class PlantNode(PlantControl, RigNode):
    def __init__(self, options):
        super().__init__('plant')
        self.rate = self.param('sensor_rate')
        self.mode = self.param('clock_mode')
        self.duration = self.param('duration')      # simulated seconds; 0 = forever
        self.force_timeout = self.param('force_timeout')
        # Matched leg_lengths subscriptions to wait for before the first sample
        # (rig: controller + fk + recorder).
        self.lengths_subscribers = self.param('lengths_subscribers')
        # Nodes (names relative to this namespace) whose leg_lengths
        # subscription the graph must show before the first sample. A count
        # alone is not enough: a recorder started first fills it while fk,
        # still loading, has no subscription yet, and fk misses the run.
        self.lengths_peers = self.peer_names('lengths_peers')
        # Lockstep flow control (nodes/lockstep.py): the readers of
        # leg_lengths outside the control loop (fk, the rig's recorder) that
        # the plant never runs more than lockstep_window samples ahead of.
        self.peers = None
        lockstep_peers = self.peer_names('lockstep_peers')
        window = self.param('lockstep_window')
        peer_timeout = self.param('lockstep_peer_timeout')
        if lockstep_peers and self.mode == 'lockstep':
            from stewart63_ros.nodes.lockstep import PeerWindow
            self.peers = PeerWindow(self, lockstep_peers, window,
                                    int(round(1e9 / self.rate)), peer_timeout)
        elif lockstep_peers:
            self.get_logger().info('lockstep_peers apply in lockstep only: in realtime a '
                                   'reader that falls behind skips samples (counted)')
        self.sensor = SensorModel(self.params)
        # The reference motion the controller follows (rig --reference), read
        # here only to report the true tracking error in the summary.
        self.reference = None
        reference_file = self.param('reference_file')
        if reference_file:
            from stewart63_ros.core.reference import ReferenceError, load_reference
            try:
                self.reference = load_reference(self.mech, reference_file)
            except ReferenceError as exc:
                raise ParameterError('reference_file', str(exc)) from None
        self.tracking = np.zeros(8)
        self.ref_sample = np.empty(36)

        self.dyn = Dynamics(self.mech)
        self.period = 1.0 / self.rate
        self.substeps = substeps_for(self.period)
        self.y = initial_state(self.mech)
        # Load the kernels now: a first call costs milliseconds, a realtime
        # loop would start that far behind its deadlines.
        self.dyn.step(self.y, np.zeros(6), self.period, self.substeps)
        self.dyn.lengths_and_rates(self.y)
        self.k = 0
        self.force = np.zeros(6)
        self.force_ns = None            # stamp of the sample the held force answers
        self.wrench = None
        self.sent_wall = {}             # sample stamp -> wall time it was published
        self.force_gate = StampGate(RESTART_PAUSE)
        self.wrench_gate = StampGate()
        self.timeouts = 0
        self.missed = 0
        self.late = 0
        self.endstop_samples = 0

        self.pub_lengths = self.publisher(JointState, topics.LEG_LENGTHS, topics.STREAM_PUB)
        self.pub_pose = self.publisher(PoseStamped, topics.TRUE_POSE, topics.STREAM_PUB)
        self.pub_twist = self.publisher(TwistStamped, topics.TRUE_TWIST, topics.STREAM_PUB)
        self.pub_clock = (self.publisher(Clock, topics.CLOCK, topics.STREAM_PUB)
                          if self.mode == 'lockstep' else None)
        # Serialized messages out and forces in: see nodes/wire.py.
        self.lengths_out = wire.JointStateTemplates(('position', 'velocity')).get('base')
        self.pose_out = wire.pose_template('base')
        self.twist_out = wire.twist_template('base')
        self.clock_out = wire.clock_template()
        wire.warm_up(('effort',))
        self.send_lengths = raw_publisher(self.pub_lengths)
        self.send_pose = raw_publisher(self.pub_pose)
        self.send_twist = raw_publisher(self.pub_twist)
        self.send_clock = raw_publisher(self.pub_clock) if self.pub_clock is not None else None
        # Who listens to /clock and ground_truth, looked up every
        # LISTENERS_PERIOD rather than on every sample (see listeners).
        self.to_clock = self.to_pose = self.to_twist = False
        self.listeners_due = 0.0
        self.sub_forces = self.create_subscription(JointState, topics.LEG_FORCES,
                                                   self.on_forces, topics.LATEST_SUB, raw=True)
        self.wrench_in = CommandInput(self, WrenchStamped, topics.EXTERNAL_WRENCH, self.on_wrench)
        self.watch_source(self.sub_forces, topics.LEG_FORCES, self.force_gate)
        self.t0_wall = None
        self.t0_mono = None         # realtime: monotonic time of sample 0
        self.t_phys = 0.0           # realtime: simulated time the state is at
        self.forces_in = None       # DirectTake, made when the loop starts
        self.init_control()         # faults, ~/pause, ~/reset, ~/step (plant_control.py)

    # -- inputs ---------------------------------------------------------------
    def on_forces(self, data: bytes, info):
        """A serialized leg_forces message: the newest force, from now on."""
        received = time.perf_counter()      # the loop latency ends here, at the take
        self.health.received[topics.LEG_FORCES] += 1
        source = source_of(info)
        self.count_skips(topics.LEG_FORCES, source, info)
        try:
            ns, _, _, _, values = wire.joint_state_sample(data, self.force_gate, ('effort',),
                                                          source=source)
        except Rejected as exc:
            self.health.reject(topics.LEG_FORCES, exc)
            return
        force = values['effort']
        self.accept_sample(self.force_gate, ns, source, topics.LEG_FORCES)
        if self.t0_mono is not None:
            # Realtime: the old force acted until now; the new one from now on.
            self.advance_to(min(time.monotonic() - self.t0_mono, (self.k + 1) * self.period))
        self.force, self.force_ns = force, ns
        sent = self.sent_wall.pop(ns, None)
        if sent is not None:
            self.health.latency.add(received - sent)

    def on_wrench(self, msg: WrenchStamped):
        self.health.received[topics.EXTERNAL_WRENCH] += 1
        try:
            ns = self.wrench_gate.check(msg.header.stamp)
            f, m = msg.wrench.force, msg.wrench.torque
            force = finite_vector([f.x, f.y, f.z], 3, 'wrench.force')
            torque = finite_vector([m.x, m.y, m.z], 3, 'wrench.torque')
        except Rejected as exc:
            self.health.reject(topics.EXTERNAL_WRENCH, exc)
            return
        self.wrench_gate.accept(ns)
        if self.t0_mono is not None:
            self.advance_to(min(time.monotonic() - self.t0_mono, (self.k + 1) * self.period))
        self.wrench = (force, torque)

    # -- outputs --------------------------------------------------------------
    def sample_time(self, k: int) -> float:
        base = 0.0 if self.mode == 'lockstep' else self.t0_wall
        return base + k * self.period

    #: s: how often the plant looks up the subscriptions matched on /clock and
    #: ground_truth (a lookup costs a few microseconds, a sample's budget at
    #: ten thousand samples a second is a hundred).
    LISTENERS_PERIOD = 0.005

    def listeners(self, now: float) -> None:
        self.listeners_due = now + self.LISTENERS_PERIOD
        self.to_clock = bool(self.pub_clock is not None and self.pub_clock.get_subscription_count())
        self.to_pose = bool(self.pub_pose.get_subscription_count())
        self.to_twist = bool(self.pub_twist.get_subscription_count())

    def publish_sample(self):
        now = time.perf_counter()
        if now >= self.listeners_due:
            self.listeners(now)
        ns = int(round(self.sample_time(self.k) * 1e9))
        sec, nanosec = divmod(ns, 1_000_000_000)
        if self.fault_model.states:
            self.begin_faults()
        lengths, rates = self.dyn.lengths_and_rates(self.y)
        if self.reference is not None and self.k * self.period >= TRACKING_FROM - 1e-12:
            self.add_tracking(lengths)
        listed = lengths.tolist()           # (min and max of six: cheaper on a list)
        if min(listed) < self.mech.leg_length_min or max(listed) > self.mech.leg_length_max:
            self.endstop_samples += 1
            self.health.warning = ('a leg is at an end stop (%d samples so far)'
                                   % self.endstop_samples)
        lengths, rates = self.sensor.measure(lengths, rates)
        lengths, rates, self.sample_complete = self.fault_model.sense(lengths, rates)
        data = self.lengths_out.fill(sec, nanosec, position=lengths, velocity=rates)
        self.sent_wall[ns] = time.perf_counter()
        if len(self.sent_wall) > 1000:   # answers that never came
            self.sent_wall.pop(next(iter(self.sent_wall)))
        self.send_lengths(data)
        # The rest goes out while the controller works on the sample.
        if self.to_clock:
            self.send_clock(self.clock_out.fill(sec, nanosec))
            self.health.published[topics.CLOCK] += 1
        self.publish_truth(sec, nanosec)
        self.health.published[topics.LEG_LENGTHS] += 1
        return ns

    def publish_truth(self, sec, nanosec):
        """ground_truth pose and twist, to whoever listens (the topics are
        VOLATILE: with no subscriber matched there is nobody to send them to)."""
        y = self.y
        if self.to_pose:
            quat = y[QUAT] / np.sqrt(y[QUAT] @ y[QUAT])
            self.send_pose(self.pose_out.fill(sec, nanosec, position=y[POS], orientation=quat))
            self.health.published[topics.TRUE_POSE] += 1
        if self.to_twist:
            self.send_twist(self.twist_out.fill(sec, nanosec, linear=y[VEL], angular=y[OMEGA]))
            self.health.published[topics.TRUE_TWIST] += 1

    def step(self):
        """Lockstep: one sample period with the force answering this sample."""
        y = self.y = self.dyn.step(self.y, self.applied_force(), self.period, self.substeps,
                                   self.wrench)
        if not math.isfinite(y @ y):       # a nan or inf anywhere (or beyond 1e154)
            raise RuntimeError('the simulation diverged (non-finite state)')
        self.k += 1

    def report(self):
        h = self.health
        h.values.update({'sample': self.k, 'sim_time_s': '%.6f' % (self.k * self.period),
                         'clock_mode': self.mode, 'force_timeouts': self.timeouts,
                         'missed_cycles': self.missed, 'late_cycles': self.late,
                         'endstop_samples': self.endstop_samples})
        self.report_faults()
        if not self.started:
            return
        if self.mode == 'lockstep':
            h.report(ros_time(self.k * self.period), final=self.closing)
        else:
            h.report(final=self.closing)
        h.warning = ''

    # -- main loops -----------------------------------------------------------
    def run(self):
        # Lockstep cannot start before the controller is there to answer.
        need_forces = 1 if self.mode == 'lockstep' else 0

        def missing():
            out = []
            if self.sub_forces.get_publisher_count() < need_forces:
                out.append('a %s publisher (a controller: lockstep steps only on its '
                           'answers)' % self.sub_forces.topic_name)
            have = self.pub_lengths.get_subscription_count()
            if have < self.lengths_subscribers:
                out.append('%s: %d of %d subscriptions matched (lengths_subscribers)'
                           % (self.pub_lengths.topic_name, have, self.lengths_subscribers))
            shown = {topics.endpoint_node_name(info) for info in
                     self.get_subscriptions_info_by_topic(self.pub_lengths.topic_name)}
            for peer in self.lengths_peers:
                if peer not in shown:
                    out.append('%s: no subscription from %s yet (lengths_peers)'
                               % (self.pub_lengths.topic_name, peer))
            if self.peers is not None:
                out += self.peers.missing_publishers()
            return out
        self.wait_for_matches(missing)
        self.forces_in = self.start_hot_loop(self.sub_forces)
        self.announce_run('running')
        self.t0_wall = time.time()
        n_samples = int(round(self.duration * self.rate)) if self.duration > 0 else None
        self.get_logger().info('%s at %g Hz%s' % (
            self.mode, self.rate, ', %d samples' % n_samples if n_samples else ''))
        if self.mode == 'lockstep':
            self.run_lockstep(n_samples)
        else:
            self.run_realtime(n_samples)
        self.announce_end()
        self.write_summary(stopped=STOP.requested)
        return 0

    def announce_end(self):
        """Tell the controller, on /diagnostics (``run: ended``), that no more
        samples come because the run is over: its watchdog then says so
        instead of reporting a lost sensor."""
        self.ended = True           # the simulation control services refuse from now on
        if self.health.values.get('run') != 'ended':
            self.health.values['run'] = 'ended'
            if self.started:
                self.report()

    def close(self):
        self.announce_end()       # stopped by a signal: the run is over too
        # Stopped by a signal mid-run: the summary of the part it ran.
        if self.t0_wall is not None and not self.summary_written:
            self.write_summary(stopped=True)
        self.summary_written = True     # stopped before its first sample: no summary
        super().close()

    def wait_for_answer(self, ns, timeout, until=None, housekeeping=True) -> bool:
        """Take leg_forces until the answer to sample ``ns`` is in, or time is up.

        With ``housekeeping``, the node's other topics and the executor (timers,
        parameter services) are served first, while the controller works.
        """
        deadline = time.monotonic() + timeout if until is None else until
        while self.force_ns != ns:
            now = time.monotonic()
            if now >= deadline or STOP.requested:
                return False
            wake = deadline
            if housekeeping:
                wake = min(wake, self.housekeeping(now))
                if self.force_ns == ns:     # an executor turn may have taken it
                    break
            self.forces_in.poll(wake - time.monotonic())
        return True

    def serve(self, timeout: float) -> None:
        """While holding for lockstep peers: the other inputs, the executor,
        and a wait of at most ``timeout`` s."""
        self.housekeeping(time.monotonic())
        self.forces_in.poll(timeout)

    def run_lockstep(self, n_samples):
        while True:
            if self.hold_due and not self.sample_boundary():     # pause, step, reset
                return
            if self.peers is not None and not self.peers.hold(
                    self.k * self.peers.period_ns, self.serve):
                return
            ns = self.publish_sample()
            # Sample 0 races discovery: our side of every match is complete,
            # a peer's side may not be yet, and reliable delivery repairs the
            # sample only at the next heartbeat (about 1 s later). Give it the
            # discovery bound rather than step without its force.
            timeout = self.force_timeout if self.k else max(self.force_timeout,
                                                              self.discovery_timeout)
            # A sample with a dropped-out leg (NaN) gets no answer: the
            # controller refuses it, the held force goes on (as in sim).
            if self.sample_complete and not self.wait_for_answer(ns, timeout):
                if STOP.requested:
                    return
                self.timeouts += 1
                self.health.warning = 'no force for sample %d within %.3f s' % (
                    self.k, timeout)
            if n_samples is not None and self.k >= n_samples:
                return
            self.step()

    def run_realtime(self, n_samples):
        """Physics in wall-clock time: a force takes effect when it arrives.

        Between sample k and the arrival of its answer the previous force
        holds (the real loop delay); the step to t_k+1 is integrated in up to
        two pieces, split at the arrival (see on_forces). An answer that has
        not arrived by the next sample is a missed cycle.
        """
        self.t0_mono = time.monotonic()
        self.t0_wall = time.time()
        while not STOP.requested:
            if self.hold_due and not self.sample_boundary():     # pause, reset
                return
            ns = self.publish_sample()
            if n_samples is not None and self.k >= n_samples:
                self.wait_for_answer(ns, 0.1)
                return
            deadline = self.t0_mono + (self.k + 1) * self.period
            # Sleep in the wait set until the answer, taking forces; serve the
            # rest once it is in (an executor turn only with time to spare).
            answered = self.wait_for_answer(ns, 0.0, until=deadline, housekeeping=False)
            now = time.monotonic()
            self.housekeeping(now, turn_ok=deadline - now > 0.6 * self.period)
            while time.monotonic() < deadline:
                self.forces_in.poll(deadline - time.monotonic())
            # A loop running behind its deadlines waits for nothing above:
            # still take the forces that came in, or it would never apply one.
            while self.force_ns != ns and self.forces_in.poll(0.0):
                pass
            if STOP.requested:
                return
            if not answered and self.force_ns != ns and self.sample_complete:
                self.missed += 1
            self.advance_to((self.k + 1) * self.period)
            self.k += 1
            if time.monotonic() - deadline > 0.5 * self.period:
                self.late += 1

    def advance_to(self, t: float) -> None:
        """Integrate from the physics time to ``t`` [s since start] with the held force."""
        dt = t - self.t_phys
        if dt <= 1e-7:
            return
        self.y = self.dyn.step(self.y, self.applied_force(), dt, substeps_for(dt), self.wrench)
        if not np.all(np.isfinite(self.y)):
            raise RuntimeError('the simulation diverged (non-finite state)')
        self.t_phys = t

    def add_tracking(self, lengths):
        """The true tracking error of this sample (reference time = k / rate)."""
        from stewart63_ros.core.reference import accumulate_tracking
        from stewart63_ros.core.rotation import matrix_from_quaternion
        self.reference.sample(self.k * self.period, self.ref_sample)
        quat = self.y[QUAT] / np.sqrt(self.y[QUAT] @ self.y[QUAT])
        accumulate_tracking(self.tracking, lengths, self.ref_sample, self.y[POS],
                            matrix_from_quaternion(quat), True)

    def write_summary(self, stopped=False):
        lengths, _ = self.dyn.lengths_and_rates(self.y)
        setpoint = self.mech.setpoint_lengths
        errors = 100.0 * np.abs(lengths - setpoint) / setpoint
        summary = {
            'clock_mode': self.mode, 'rate_hz': self.rate, 'samples': self.k + 1,
            'sim_time_s': self.k * self.period,
            'final_leg_lengths_m': lengths.tolist(),
            'final_leg_errors_percent': errors.tolist(),
            'positioning_error_percent': float(errors.max()),
            'loop_latency': self.health.latency.summary(),
            'force_timeouts': self.timeouts, 'missed_cycles': self.missed,
            'late_cycles': self.late, 'endstop_samples': self.endstop_samples,
            'wall_time_s': time.time() - self.t0_wall,
            'skipped': dict(self.health.skipped),
            'stopped_by_signal': stopped,
            'run_number': self.run_number, 'resets': self.resets,
            'faults': self.fault_model.summary(),
        }
        if self.peers is not None:
            summary['lockstep_peers'] = {
                'window': self.peers.window, 'held_s': round(self.peers.held_s, 3),
                'held_samples': self.peers.holds, 'dropped': dict(self.peers.dropped)}
        if self.reference is not None:
            from stewart63_ros.core.reference import tracking_summary
            summary['tracking_error'] = dict(from_s=TRACKING_FROM,
                                             **tracking_summary(self.tracking))
        self.write_summary_file(summary)
        self.get_logger().info('done: %d samples, final error %.3f %%, latency %s' % (
            summary['samples'], summary['positioning_error_percent'], summary['loop_latency']))


def main(argv=None):
    sys.exit(run('plant', __doc__.split('\n\n')[0], PlantNode, argv))


if __name__ == '__main__':
    main()
