"""controller: a control law on every leg_lengths sample (eq. 40 by default).

The law (parameter ``control_law``: ``pd``, eq. (40); ``pd_gravity``;
``computed_torque``; or ``package.module:Class``, a user's own) turns each
sample into six piston forces, saturated at max_force, published on
``leg_forces`` with the stamp of the sample it answers. It follows a
reference: the parameter ``setpoint_lengths``, then the newest
``leg_setpoint`` or ``pose_setpoint`` (turned into lengths by inverse
kinematics; a pose outside the stroke is rejected and reported), or a
reference motion: ``reference_file`` (a reference CSV, time 0 = the first
sample) or the newest ``pose_trajectory`` (its header.stamp is its time 0;
zero: the next sample). A reference that leaves the stroke is refused whole
and the previous one goes on. Gains and law change at run time
(``ros2 param set``). A law that raises or returns NaN: forces withheld,
ERROR on /diagnostics, the node stays up.

Watchdog: when no valid sample has arrived for ``watchdog_timeout`` seconds
(wall clock; default 0.1 s, 2 s in lockstep, where a sample refused only for
a dropped-out leg counts as one: docs/faults.md) after the first one, the
controller stops publishing forces and reports ERROR on /diagnostics until
samples return. It never invents a force without a measurement: on a hydraulic
platform the actuator driver's own command timeout then closes the servo
valves, which locks each cylinder at its length. Holding the last force could
drive a leg into its end stop, and zero force would let the platform sink
under its own weight.
"""
from __future__ import annotations

import sys
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import MultiDOFJointTrajectory

from stewart63_ros import topics
from stewart63_ros.core.controllers.laws import LAW_PARAMETERS, LAWS, Controller, LawError
from stewart63_ros.core.controllers.reference import MessageError, Reference, ReferenceError
from stewart63_ros.core.controllers.reference_files import (
    load_reference,
    message_quaternion,
    trajectory_points,
    trajectory_poses,
)
from stewart63_ros.core.controllers.tracking import accumulate_tracking, tracking_summary
from stewart63_ros.core.mechanics.kinematics import leg_lengths
from stewart63_ros.core.mechanics.rotation import rotation_from_quaternion
from stewart63_ros.core.plumbing.params import ParameterError
from stewart63_ros.exits import quiet_on_closed_pipe
from stewart63_ros.runtime import wire
from stewart63_ros.runtime.base import RigNode
from stewart63_ros.runtime.checks import (
    RESTART_PAUSE,
    Rejected,
    StampGate,
    finite_vector,
    leg_vector,
    source_of,
    stamp_ns,
)
from stewart63_ros.runtime.commands import CommandInput
from stewart63_ros.runtime.handshake import plant_run
from stewart63_ros.runtime.launcher import run
from stewart63_ros.runtime.rclpy_internals import take, take_with_info
from stewart63_ros.runtime.startup import FirstAnswer

_NO_ROTATION = np.eye(3)


def _unit_quaternion(q, field):
    try:
        return message_quaternion(q, field)
    except MessageError as exc:
        raise Rejected(exc.reason, str(exc)) from None


def reference_from_trajectory(mech, msg, max_leg_speed=0.0, max_leg_acceleration=0.0):
    """(Reference, start stamp in ns or None for "the next sample") from a
    ``MultiDOFJointTrajectory`` of the one joint ``platform``
    (``core.controllers.reference.trajectory_points``); Rejected otherwise.

    Velocities and accelerations are used when every point has them (quintic
    Hermite pieces with both, cubic Hermite with velocities only), otherwise
    the poses are splined as a reference CSV is (clamped cubic)."""
    try:
        times, translations, quats, twists, accels = trajectory_points(msg)
    except MessageError as exc:
        raise Rejected(exc.reason, str(exc)) from None
    poses, rates, accs = trajectory_poses(translations, quats, twists, accels)
    try:
        ref = Reference.from_poses(mech, times, poses, rates, accs)
        ref.check(max_leg_speed, max_leg_acceleration)
    except ReferenceError as exc:
        raise Rejected('unreachable_trajectory' if 'leg_' in str(exc) else 'bad_trajectory',
                       str(exc)) from None
    start = stamp_ns(msg.header.stamp)
    return ref, (start or None)


class ControllerNode(RigNode):
    WITHHOLDS_ON_COLLISION = True

    def __init__(self, options):
        super().__init__('controller')
        mech = self.mech
        self.max_leg_speed = self.param('max_leg_speed')
        self.offset = self.param('leg_length_offset')
        self.max_leg_acceleration = self.param('max_leg_acceleration')
        self.control = Controller(self.setup, self.params)        # ParameterError: exit 2
        # Load the compiled laws now (0.7-1.7 s measured), not on the first sample: a
        # realtime plant would integrate that long without forces.
        self._warm_up()
        self.ref_start_ns = None        # the reference's time 0 on the sample clock
        self.reference_name = 'setpoint_lengths'
        reference_file = self.param('reference_file')
        if reference_file:
            try:
                reference = load_reference(mech, reference_file, self.max_leg_speed,
                                           self.max_leg_acceleration)
            except ReferenceError as exc:
                raise ParameterError('reference_file', str(exc)) from None
            self.control.set_reference(reference, 0.0)
            self.reference_name = reference_file
        self.watchdog_timeout = self.param('watchdog_timeout')   # longer in lockstep
        self.lockstep = self.param('clock_mode') == 'lockstep'
        self.sample_gate = StampGate(RESTART_PAUSE)
        self.setpoint_gate = StampGate()
        self.pose_gate = StampGate()
        self.trajectory_gate = StampGate()
        self.last_sample_wall = None
        self.tripped = False
        self.law_fault = ''
        self.law_failures = 0
        self.tracking = np.zeros(8)
        self.pub_forces = self.publisher(JointState, topics.LEG_FORCES, topics.STREAM_PUB)
        self.forces_out = wire.JointStateTemplates(('effort',))
        self.forces_out.get('base')             # made now, not on the first sample
        self.send_forces = self.health.sender(topics.LEG_FORCES, self.pub_forces)
        # Lockstep: the first answer to a plant waits for the writer's side of
        # its match (startup.FirstAnswer); remapped (a supervisor takes the
        # forces), for whatever the graph shows on that topic.
        self.first_answer = None
        if self.lockstep:
            to_plant = self.pub_forces.topic_name == self.resolve_topic_name(
                topics.LEG_FORCES, only_expand=True)
            self.first_answer = FirstAnswer(self, self.pub_forces, topics.LEG_LENGTHS,
                                            to_source=to_plant)
        wire.warm_up(('position', 'velocity'))
        self.sub_samples = None         # made once its forces are matched
        self.commands = [
            CommandInput(self, JointState, topics.LEG_SETPOINT, self.on_leg_setpoint),
            CommandInput(self, PoseStamped, topics.POSE_SETPOINT, self.on_pose_setpoint),
            CommandInput(self, MultiDOFJointTrajectory, topics.POSE_TRAJECTORY,
                         self.on_trajectory)]
        self.create_timer(min(self.watchdog_timeout / 2, 0.05), self.watchdog)
        # The plant says on /diagnostics when its samples stop on purpose
        # ("run: ended", "run: paused", "run: reset"): the silence that
        # follows is then not a lost sensor. Its "run_number" goes up on a
        # reset: a new run, whose reference starts again at its first sample.
        self.plant_status = topics.status_name(topics.node_full_name(self.get_namespace(),
                                                                     'plant'))
        self.source_ended = False       # or why the plant is silent: 'ended', 'paused', ...
        # The stamp of that announcement (ns): samples stamped before it were
        # in flight when the plant fell silent (over a field bus they arrive
        # after the announcement) and do not end the silence.
        self.silent_from_ns = 0
        self.plant_run = None
        self.sub_diagnostics = self.create_subscription(
            DiagnosticArray, topics.DIAGNOSTICS, self.on_diagnostics, topics.DIAGNOSTICS_QOS)
        # Run-time tuning: the law, every built-in law's gains, the active law's own.
        self.tunable('control_law', self.set_law)
        for name in LAW_PARAMETERS:
            self.tunable(name, self._gain_setter(name))
        self._register_law_parameters()
        self.health.values['control_law'] = self.control.law_name
        self.health.values['reference'] = self.reference_name
        self.withheld = 0

    def subscribe_input(self):
        """``leg_lengths``, once the controller's outputs are matched
        (RigNode.subscribe_input)."""
        if self.sub_samples is not None:
            return
        # Serialized samples in, serialized forces out: see runtime/wire.py.
        self.sub_samples = self.create_subscription(JointState, topics.LEG_LENGTHS,
                                                    self.on_sample, topics.LATEST_SUB, raw=True)
        self.watch_source(self.sub_samples, topics.LEG_LENGTHS, self.sample_gate)

    def _warm_up(self, name=None):
        """Load the compiled kernels of law ``name`` (default: the active one), on a
        throwaway copy: the first sample must not wait for them."""
        mech, task = self.mech, self.setup.task
        rot = task.initial_rotation
        lengths = leg_lengths(mech, task.initial_position, rot)
        still = Reference.constant_pose(mech, task.initial_position, rot)
        # The active law only (another one loads when chosen at run time): loading
        # every law's kernels costs a restarted controller CPU the plant needs.
        name = name or self.control.law_name
        if name in LAWS:
            for reference in (None, still):
                try:
                    Controller(self.setup, self.params, law=name, reference=reference)(
                        lengths, np.zeros(6), 0.0)
                except (LawError, ParameterError):
                    pass            # a law that cannot run here fails on its first sample

    # -- run-time tuning -----------------------------------------------------------------
    def _gain_setter(self, name):
        def apply(value):
            self.control.set_parameter(name, value)
        return apply

    def _register_law_parameters(self):
        for name in getattr(self.control.law, 'parameters', ()):
            if name not in LAW_PARAMETERS:
                self.tunable(name, self._gain_setter(name))

    def set_law(self, value):
        self.control.set_law(value)          # ParameterError refuses it
        self._warm_up(value)
        self._register_law_parameters()
        self.health.values['control_law'] = self.control.law_name
        self.get_logger().info('control law: %s' % value)

    # -- the 1 kHz path --------------------------------------------------------------------
    def on_sample(self, data: bytes, info):
        """A serialized leg_lengths sample in; its forces out, with its stamp."""
        self.health.received[topics.LEG_LENGTHS] += 1
        source = source_of(info)
        self.count_skips(topics.LEG_LENGTHS, source, info)
        try:
            ns, sec, nanosec, frame_id, values = wire.joint_state_sample(
                data, self.sample_gate, ('position', 'velocity'), source=source)
        except Rejected as exc:
            self.health.reject(topics.LEG_LENGTHS, exc)
            if self.lockstep and exc.stamp_ns is not None:
                # A dropout's NaN sample: refused (no force), but the sensor
                # stream is alive and the plant steps on without an answer;
                # in lockstep that is no silence for the watchdog.
                self.last_sample_wall = time.monotonic()
            return
        self.accept_sample(self.sample_gate, ns, source, topics.LEG_LENGTHS)
        if self.sample_gate.new_run:
            self.ref_start_ns = None        # a new run: the reference starts again
        self.last_sample_wall = time.monotonic()
        if self.source_ended and (ns >= self.silent_from_ns or self.sample_gate.new_run):
            self.source_ended = False        # a run goes on (or a new one began)
        if self.tripped:
            self.tripped = False
            self.health.fault = self.law_fault
            self.get_logger().info('samples are back: control resumed')
        if self.health.collision:
            # Samples from mixed sources: no force rather than a wrong one.
            self.withheld += 1
            self.health.values['forces_withheld'] = self.withheld
            return
        if self.ref_start_ns is None:
            self.ref_start_ns = ns
        # The sensors read the true length plus leg_length_offset (the file's).
        lengths, rates = values['position'] - self.offset, values['velocity']
        try:
            force = self.control.forces((ns - self.ref_start_ns) * 1e-9, lengths, rates)
        except LawError as exc:
            self.on_law_error(exc)
            return
        if self.first_answer is not None:
            self.first_answer.wait(source)
        self.send_forces(self.forces_out.get(frame_id).fill(sec, nanosec, effort=force))
        estimate = self.control.estimate
        if estimate is None:
            accumulate_tracking(self.tracking, lengths, self.control.sample.array, lengths,
                                _NO_ROTATION, False)
        else:
            accumulate_tracking(self.tracking, lengths, self.control.sample.array, estimate[0],
                                estimate[1], True)
        if self.law_fault:
            self.get_logger().info('the control law works again: forces resumed')
            self.law_fault = ''
            self.health.fault = ''

    def on_law_error(self, exc):
        self.law_failures += 1
        self.health.values['law_failures'] = self.law_failures
        if not self.law_fault:
            self.law_fault = 'control law failed, forces withheld: %s' % exc
            self.health.fault = self.law_fault
            self.get_logger().error(self.law_fault)
            self.health.report()

    def report(self):
        summary = tracking_summary(self.tracking)
        for key in ('leg_max_m', 'leg_rms_m', 'position_max_m', 'position_rms_m',
                    'orientation_max_rad', 'orientation_rms_rad'):
            if key in summary:
                self.health.values['tracking/' + key] = '%.4g' % summary[key]
            else:
                self.health.values.pop('tracking/' + key, None)
        self.tracking[:] = 0.0
        super().report()

    # -- commands ---------------------------------------------------------------------------
    def check_stroke(self, lengths, source):
        mech = self.mech
        bad = np.flatnonzero((lengths < mech.leg_length_min) | (lengths > mech.leg_length_max))
        if bad.size:
            raise Rejected('unreachable_setpoint', '%s: leg_%d length %.4f m is outside the '
                           'stroke [%g, %g]' % (source, bad[0] + 1, lengths[bad[0]],
                                                mech.leg_length_min, mech.leg_length_max))

    def follow(self, reference, start_ns, name):
        """From now on: ``reference`` from ``start_ns`` (None: the next sample)."""
        self.control.set_reference(reference, 0.0)
        self.ref_start_ns = start_ns
        self.reference_name = name
        self.health.values['reference'] = name

    def set_setpoint(self, lengths, source, pose=None):
        self.check_stroke(lengths, source)
        if pose is not None:
            reference = Reference.constant_pose(self.mech, *pose)
        else:
            estimate = self.control.estimate
            reference = Reference.constant_lengths(self.mech, lengths, near=estimate)
        self.follow(reference, None, source)
        self.health.values['setpoint'] = np.round(lengths, 6).tolist()
        self.get_logger().info('setpoint from %s: %s' % (source, np.round(lengths, 4).tolist()))

    def on_leg_setpoint(self, msg: JointState):
        self.health.received[topics.LEG_SETPOINT] += 1
        try:
            ns = self.setpoint_gate.check(msg.header.stamp)
            self.set_setpoint(leg_vector(msg.name, msg.position, 'position'), topics.LEG_SETPOINT)
        except Rejected as exc:
            self.health.reject(topics.LEG_SETPOINT, exc)
            return
        self.setpoint_gate.accept(ns)

    def on_pose_setpoint(self, msg: PoseStamped):
        self.health.received[topics.POSE_SETPOINT] += 1
        p = msg.pose.position
        try:
            ns = self.pose_gate.check(msg.header.stamp)
            position = finite_vector([p.x, p.y, p.z], 3, 'pose.position')
            rot = rotation_from_quaternion(_unit_quaternion(msg.pose.orientation,
                                                            'pose.orientation'))
            self.set_setpoint(leg_lengths(self.mech, position, rot), topics.POSE_SETPOINT,
                              pose=(position, rot))
        except Rejected as exc:
            self.health.reject(topics.POSE_SETPOINT, exc)
            return
        self.pose_gate.accept(ns)

    def on_trajectory(self, msg: MultiDOFJointTrajectory):
        self.health.received[topics.POSE_TRAJECTORY] += 1
        try:
            ns = self.trajectory_gate.check(msg.header.stamp)
            reference, start = reference_from_trajectory(self.mech, msg, self.max_leg_speed,
                                                         self.max_leg_acceleration)
        except Rejected as exc:
            self.health.reject(topics.POSE_TRAJECTORY, exc)
            self.get_logger().error('pose_trajectory refused, the previous motion goes on: %s'
                                    % exc)
            return
        self.trajectory_gate.accept(ns)
        self.follow(reference, start, '%s (%d points, %.3f s)' % (
            topics.POSE_TRAJECTORY, len(msg.points), reference.duration))
        self.get_logger().info('following %s' % self.reference_name)

    #: the plant's ``run`` values that announce a silence of its samples
    SILENT_RUN = ('ended', 'paused', 'reset')

    def on_diagnostics(self, msg):
        said = plant_run(msg, self.plant_status)
        run = said.get('run')
        if run in self.SILENT_RUN:
            if self.source_ended != run:
                self.silent_from_ns = stamp_ns(msg.header.stamp)
            self.source_ended = run
        elif run in ('running', 'stepping'):
            self.source_ended = False
        number = said.get('run_number')
        if number is not None:
            if self.plant_run is not None and number != self.plant_run:
                self.ref_start_ns = None    # a new run: the reference starts again
            self.plant_run = number

    def run(self):
        self.wait_for_matches()         # (its input: made as the wait ends)
        self.run_on(self.sub_samples)

    def read_queued(self) -> None:
        """Handle what already waits in this process's queues: every
        /diagnostics message, then the newest sample, as the loop would."""
        for msg in iter(lambda: take(self.sub_diagnostics), None):
            self.on_diagnostics(msg)
        taken = take_with_info(self.sub_samples) if self.sub_samples is not None else None
        if taken is not None:
            self.sub_samples.callback(*taken)

    def watchdog(self):
        if self.last_sample_wall is None or self.tripped:
            return
        if time.monotonic() - self.last_sample_wall <= self.watchdog_timeout:
            return
        # A controller starved of CPU wakes to this due timer and its queued
        # messages at once, and the timer may run first: read the queues
        # before judging (a waiting sample, the plant's "run: reset"), so a
        # stall of this process is not taken for a lost sensor.
        self.read_queued()
        silent = time.monotonic() - self.last_sample_wall
        if silent > self.watchdog_timeout:
            self.tripped = True
            if self.source_ended:
                # Forces are withheld all the same (none without a sample).
                why = {'ended': 'ended its run', 'paused': 'paused its run',
                       'reset': 'is starting a new run'}.get(self.source_ended,
                                                             self.source_ended)
                self.source_ended = False
                self.get_logger().info('the plant %s: no leg_lengths; forces withheld '
                                       'until samples return' % why)
                return
            self.health.fault = ('watchdog: no leg_lengths for %.3f s; forces withheld '
                                 'until samples return' % silent)
            self.get_logger().error(self.health.fault)
            self.health.report()


@quiet_on_closed_pipe
def main(argv=None):
    sys.exit(run('controller', __doc__.split('\n\n')[0], ControllerNode, argv))


if __name__ == '__main__':
    main()
