"""controller: the PD law of eq. (40) on every leg_lengths sample.

F_i = Kp_i ((L_i)_0 - L_i) - Kv_i dL_i/dt, saturated at max_force, published
on ``leg_forces`` with the stamp of the sample it answers. Setpoint: the
parameter ``setpoint_lengths``, then the newest ``leg_setpoint`` or
``pose_setpoint`` (turned into lengths by inverse kinematics; a pose outside
the stroke is rejected and reported).

Watchdog: when no valid sample has arrived for ``watchdog_timeout`` seconds
(wall clock; default 0.1 s, 2 s in lockstep) after the first one, the
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
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import JointState

from stewart63_ros import topics
from stewart63_ros.core.control import PDController
from stewart63_ros.core.kinematics import leg_lengths
from stewart63_ros.nodes import wire
from stewart63_ros.nodes.base import RigNode
from stewart63_ros.nodes.checks import Rejected, StampGate, finite_vector, leg_vector
from stewart63_ros.nodes.launcher import run


class ControllerNode(RigNode):
    def __init__(self, options):
        super().__init__('controller')
        self.law = PDController(self.mech)
        # Load the compiled law now (0.7-1.7 s measured), not on the first sample: a
        # realtime plant would integrate that long without forces.
        self.law(np.array(self.law.setpoint), np.zeros(6))
        # Lockstep pauses are the plant's choice, not a failure: longer default.
        lockstep = self.param('clock_mode', 'realtime') == 'lockstep'
        self.watchdog_timeout = self.positive('watchdog_timeout', 2.0 if lockstep else 0.1)
        self.sample_gate = StampGate()
        self.setpoint_gate = StampGate()
        self.pose_gate = StampGate()
        self.last_sample_wall = None
        self.tripped = False
        self.pub_forces = self.publisher(JointState, topics.LEG_FORCES, topics.STREAM_PUB)
        self.forces_out = wire.JointStateTemplates(('effort',))
        self.forces_out.get('base')             # made now, not on the first sample
        wire.warm_up(('position', 'velocity'))
        # Serialized samples in, serialized forces out: see nodes/wire.py.
        self.sub_samples = self.create_subscription(JointState, topics.LEG_LENGTHS,
                                                    self.on_sample, topics.LATEST_SUB, raw=True)
        self.create_subscription(JointState, topics.LEG_SETPOINT, self.on_leg_setpoint,
                                 topics.SETPOINT_QOS)
        self.create_subscription(PoseStamped, topics.POSE_SETPOINT, self.on_pose_setpoint,
                                 topics.SETPOINT_QOS)
        self.create_timer(min(self.watchdog_timeout / 2, 0.05), self.watchdog)

    def on_sample(self, data: bytes):
        """A serialized leg_lengths sample in; its forces out, with its stamp."""
        self.health.received[topics.LEG_LENGTHS] += 1
        try:
            ns, sec, nanosec, frame_id, values = wire.joint_state_sample(
                data, self.sample_gate, ('position', 'velocity'))
        except Rejected as exc:
            self.health.reject(topics.LEG_LENGTHS, exc)
            return
        self.sample_gate.accept(ns)
        self.last_sample_wall = time.monotonic()
        if self.tripped:
            self.tripped = False
            self.health.fault = ''
            self.get_logger().info('samples are back: control resumed')
        force = self.law(values['position'], values['velocity'])
        self.pub_forces.publish(self.forces_out.get(frame_id).fill(sec, nanosec, effort=force))
        self.health.published[topics.LEG_FORCES] += 1

    def set_setpoint(self, lengths, source):
        mech = self.mech
        bad = np.flatnonzero((lengths < mech.leg_length_min) | (lengths > mech.leg_length_max))
        if bad.size:
            raise Rejected('unreachable_setpoint', '%s: leg_%d length %.4f m is outside the '
                           'stroke [%g, %g]' % (source, bad[0] + 1, lengths[bad[0]],
                                                mech.leg_length_min, mech.leg_length_max))
        self.law.setpoint = lengths
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
        from scipy.spatial.transform import Rotation
        self.health.received[topics.POSE_SETPOINT] += 1
        p, q = msg.pose.position, msg.pose.orientation
        try:
            ns = self.pose_gate.check(msg.header.stamp)
            position = finite_vector([p.x, p.y, p.z], 3, 'pose.position')
            quat = finite_vector([q.x, q.y, q.z, q.w], 4, 'pose.orientation')
            norm = np.linalg.norm(quat)
            if not 0.9 < norm < 1.1:
                raise Rejected('bad_quaternion', 'orientation is not a unit quaternion '
                               '(norm %.3g)' % norm)
            rot = Rotation.from_quat(quat / norm).as_matrix()
            self.set_setpoint(leg_lengths(self.mech, position, rot), topics.POSE_SETPOINT)
        except Rejected as exc:
            self.health.reject(topics.POSE_SETPOINT, exc)
            return
        self.pose_gate.accept(ns)

    def run(self):
        self.run_on(self.sub_samples)

    def watchdog(self):
        if self.last_sample_wall is None or self.tripped:
            return
        silent = time.monotonic() - self.last_sample_wall
        if silent > self.watchdog_timeout:
            self.tripped = True
            self.health.fault = ('watchdog: no leg_lengths for %.3f s; forces withheld '
                                 'until samples return' % silent)
            self.get_logger().error(self.health.fault)
            self.health.report()


def main(argv=None):
    sys.exit(run('controller', __doc__.split('\n\n')[0], ControllerNode, argv))


if __name__ == '__main__':
    main()
