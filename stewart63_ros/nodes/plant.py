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

io ``canopen``: the plant stands on the field bus as the legs' CiA 402 drives
instead of publishing ``leg_lengths`` and taking ``leg_forces`` (each SYNC
advances it one period; ``canopen_bridge`` links the bus to the topics):
nodes/plant_bus.py, docs/bus.md.
"""
from __future__ import annotations

import math
import sys
import time

import numpy as np
from geometry_msgs.msg import WrenchStamped
from sensor_msgs.msg import JointState

from stewart63_ros import topics
from stewart63_ros.core.controllers.sensor import SensorModel, TrackerModel
from stewart63_ros.core.controllers.simulate import initial_state, substeps_for
from stewart63_ros.core.mechanics.assembly import AssemblyWatch
from stewart63_ros.core.mechanics.dynamics import Dynamics
from stewart63_ros.exits import quiet_on_closed_pipe
from stewart63_ros.nodes.plant_bus import PlantBus
from stewart63_ros.nodes.plant_control import PlantControl
from stewart63_ros.nodes.plant_outputs import SampleOutputs
from stewart63_ros.nodes.plant_summary import TRACKING_FROM, TrackingError, run_summary
from stewart63_ros.runtime.base import RigNode
from stewart63_ros.runtime.checks import (
    RESTART_PAUSE,
    Rejected,
    StampGate,
    finite_vector,
    ros_time,
)
from stewart63_ros.runtime.commands import CommandInput
from stewart63_ros.runtime.launcher import STOP, run
from stewart63_ros.runtime.lockstep import AnswerWatch, PeerWindow
from stewart63_ros.runtime.startup import PlantStartup


class PlantNode(PlantBus, PlantControl, RigNode):
    """The plant node (see the module's doc). Its parts: the samples out
    (plant_outputs.SampleOutputs), what it waits for before the first one
    (startup.PlantStartup), faults and simulation control (a PlantControl),
    the run's summary (plant_summary)."""

    def __init__(self, options):
        super().__init__('plant')
        self.rate = self.param('sensor_rate')
        self.mode = self.param('clock_mode')
        self.on_bus = self.param('io') == 'canopen'     # the drives on the bus: plant_bus.py
        self.duration = self.param('duration')      # simulated seconds; 0 = forever
        self.force_timeout = self.param('force_timeout')
        # Matched leg_lengths subscriptions, and the nodes whose subscription
        # the graph must show, before the first sample (runtime/handshake.py).
        self.lengths_subscribers = self.param('lengths_subscribers')
        self.lengths_peers = self.peer_names('lengths_peers')
        # Lockstep flow control (runtime/lockstep.py): the readers of
        # leg_lengths outside the control loop (fk, the rig's recorder) that
        # the plant never runs more than lockstep_window samples ahead of.
        self.peers = None
        lockstep_peers = self.peer_names('lockstep_peers')
        window = self.param('lockstep_window')
        peer_timeout = self.param('lockstep_peer_timeout')
        if lockstep_peers and self.mode == 'lockstep':
            self.peers = PeerWindow(self, lockstep_peers, window,
                                    int(round(1e9 / self.rate)), peer_timeout)
        self.answers = AnswerWatch(self.health, self.get_logger(), peer_timeout)
        if lockstep_peers and self.mode != 'lockstep':
            self.get_logger().info('lockstep_peers apply in lockstep only: in realtime a '
                                   'reader that falls behind skips samples (counted)')
        self.sensor = SensorModel(self.params)
        # The reference motion the controller follows (rig --reference), read
        # here only to report the true tracking error in the summary.
        reference_file = self.param('reference_file')
        self.tracking = TrackingError(self.mech, reference_file) if reference_file else None

        self.dyn = Dynamics(self.mech)
        self.period = 1.0 / self.rate
        self.substeps = substeps_for(self.period)
        self.y = initial_state(self.setup.task)
        # Load the kernels now: a first call costs milliseconds, a realtime
        # loop would start that far behind its deadlines.
        self.dyn.step(self.y, np.zeros(6), self.period, self.substeps)
        self.dyn.lengths_and_rates(self.y)
        self.assembly = AssemblyWatch(*self.dyn.kernel_args()[1:3], self.rate)
        self.assembly.check(0, self.y)          # (its kernel loaded now, too)
        self.k = 0
        self.force = np.zeros(6)
        self.force_ns = None            # stamp of the sample the held force answers
        self.wrench = None
        self.force_gate = StampGate(RESTART_PAUSE)
        self.wrench_gate = StampGate()
        self.timeouts = 0
        self.missed = 0
        self.late = 0
        self.endstop_samples = 0

        self.outputs = SampleOutputs(self, lockstep=self.mode == 'lockstep',
                                     tracker=TrackerModel(self.params), lengths=not self.on_bus)
        # The same dict as the outputs': on_forces pops the answered samples.
        self.sent_wall = self.outputs.sent_wall
        self.sub_forces = None      # on the bus the forces come from the drives
        if not self.on_bus:
            self.sub_forces = self.create_subscription(
                JointState, topics.LEG_FORCES, self.on_forces, topics.LATEST_SUB, raw=True)
        self.wrench_in = CommandInput(self, WrenchStamped, topics.EXTERNAL_WRENCH, self.on_wrench)
        if not self.on_bus:
            self.watch_source(self.sub_forces, topics.LEG_FORCES, self.force_gate)
        self.plant_startup = PlantStartup(self)
        self.t0_wall = None
        #: time.time() as the run began (t0_wall moves with a realtime pause):
        #: what came before it was start-up (rig's summary says so)
        self.run_began_unix = None
        self.t0_mono = None         # realtime: monotonic time of sample 0
        self.t_phys = 0.0           # realtime: simulated time the state is at
        self.forces_in = None       # DirectTake, made when the loop starts
        self.init_control()         # faults, ~/pause, ~/reset, ~/step (plant_control.py)
        self.devices = self.init_bus() if self.on_bus else None    # plant_bus.py

    # -- inputs ---------------------------------------------------------------
    def on_forces(self, data: bytes, info):
        """A serialized leg_forces message: the newest force, from now on."""
        received = time.perf_counter()      # the loop latency ends here, at the take
        taken = self.take_forces(data, info, self.force_gate)
        if taken is None:
            return
        ns, force = taken
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

    def publish_sample(self, after_sync=None):
        """Sample ``self.k`` out: the sensors' readings (faults applied) and the
        rest (see SampleOutputs); returns its stamp [ns]. ``after_sync``: on
        the bus, the drives' answers armed for the next SYNC (``bus_sample``)."""
        out = self.outputs
        now = time.perf_counter()
        if now >= out.listeners_due:
            out.listeners(now)
        ns = int(round(self.sample_time(self.k) * 1e9))
        sec, nanosec = divmod(ns, 1_000_000_000)
        if self.fault_model.states:
            self.begin_faults()
        lengths, rates = self.dyn.lengths_and_rates(self.y)
        self.watch_assembly()
        if self.tracking is not None and self.k * self.period >= TRACKING_FROM - 1e-12:
            self.tracking.add(self.k * self.period, lengths, self.y)
        listed = lengths.tolist()           # (min and max of six: cheaper on a list)
        if min(listed) < self.mech.leg_length_min or max(listed) > self.mech.leg_length_max:
            self.endstop_samples += 1
            self.health.warning = ('a leg is at an end stop (%d samples so far)'
                                   % self.endstop_samples)
        if self.encoder_shift is not None:     # incremental sensors not homed
            lengths = lengths + self.encoder_shift
        lengths, rates = self.sensor.measure(lengths, rates)
        lengths, rates, self.sample_complete = self.fault_model.sense(lengths, rates)
        if self.devices is not None:
            self.bus_sample(lengths, rates, after_sync)
        out.send(ns, sec, nanosec, lengths, rates, self.y)
        out.send_tracked(self.k, sec, nanosec, self.y)
        return ns

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
        if self.devices is not None:
            self.report_bus()
        if not self.started:
            return
        if self.mode == 'lockstep':
            h.report(ros_time(self.k * self.period), final=self.closing)
        else:
            h.report(final=self.closing)
        h.warning = ''

    # -- main loops -----------------------------------------------------------
    def run(self):
        self.wait_for_matches(self.plant_startup.missing)     # the start-up order: handshake.py
        self.forces_in = self.start_hot_loop(self.sub_forces if self.sub_forces is not None
                                             else self.wrench_in.subscriptions[0])
        self.announce_run('running')
        self.t0_wall = self.run_began_unix = time.time()
        n_samples = int(round(self.duration * self.rate)) if self.duration > 0 else None
        self.get_logger().info('%s at %g Hz%s' % (
            self.mode, self.rate, ', %d samples' % n_samples if n_samples else ''))
        if self.devices is not None:
            self.run_bus(n_samples)
        elif self.mode == 'lockstep':
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
        self.close_bus()

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
            timeout = self.answers.wait(self.force_timeout) if self.k else max(
                self.force_timeout, self.discovery_timeout)
            # A sample with a dropped-out leg (NaN) gets no answer: the
            # controller refuses it, the held force goes on (as in sim). A
            # supervisor answers every sample (answer_every_sample).
            if self.sample_complete or self.answer_every_sample:
                if self.wait_for_answer(ns, timeout):
                    self.answers.answered()
                else:
                    if STOP.requested:
                        return
                    self.timeouts += 1
                    self.health.warning = 'no force for sample %d within %.3f s' % (
                        self.k, timeout)
                    self.answers.missed(timeout)
            if n_samples is not None and self.k >= n_samples:
                if self.peers is not None:     # the end: every peer has the last one
                    self.peers.drain(ns, self.serve)
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

    def watch_assembly(self) -> None:
        """ERROR on /diagnostics, naming the sample, while the platform is in
        another assembly mode than at the run's start (core/mechanics/assembly.py)."""
        if self.k == 0:         # (each run: a reset starts from the initial state)
            self.assembly = AssemblyWatch(*self.dyn.kernel_args()[1:3], self.rate)
        note = self.assembly.check(self.k, self.y)
        if not note:
            return
        self.health.values['assembly_crossings'] = list(self.assembly.crossings)
        if self.assembly.in_start_mode:
            self.health.fault = ''
            self.get_logger().info(note)
        else:
            self.health.fault = note
            self.get_logger().error(note)
        self.health.report()

    def advance_to(self, t: float) -> None:
        """Integrate from the physics time to ``t`` [s since start] with the held force."""
        dt = t - self.t_phys
        if dt <= 1e-7:
            return
        self.y = self.dyn.step(self.y, self.applied_force(), dt, substeps_for(dt), self.wrench)
        if not np.all(np.isfinite(self.y)):
            raise RuntimeError('the simulation diverged (non-finite state)')
        self.t_phys = t

    def write_summary(self, stopped=False):
        summary = run_summary(self, stopped)
        self.write_summary_file(summary)
        self.get_logger().info('done: %d samples, final error %.3f %%, latency %s' % (
            summary['samples'], summary['positioning_error_percent'], summary['loop_latency']))


@quiet_on_closed_pipe
def main(argv=None):
    sys.exit(run('plant', __doc__.split('\n\n')[0], PlantNode, argv))


if __name__ == '__main__':
    main()
