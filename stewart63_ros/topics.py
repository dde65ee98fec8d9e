"""Topic names and QoS profiles of CONTRACT section 2, shared by every node.

Why these profiles (README, "Topics and QoS"):
- State streams (``leg_lengths``, ``leg_forces``, poses, twists, ``/clock``)
  are published RELIABLE with a deep KEEP_LAST history, so a recorder that
  subscribes RELIABLE with a deep queue loses nothing, while the plant and the
  controller subscribe RELIABLE with depth 1 and so always act on the newest
  sample, never on a backlog. A BEST_EFFORT subscriber (a driver, rviz) also
  matches these publishers.
- Setpoints are TRANSIENT_LOCAL depth 1 ("latched"): a setpoint published
  before the controller starts still reaches it.
"""
from __future__ import annotations

from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile,
                       ReliabilityPolicy)

LEG_LENGTHS = 'leg_lengths'
LEG_FORCES = 'leg_forces'
LEG_SETPOINT = 'leg_setpoint'
POSE_SETPOINT = 'pose_setpoint'
PLATFORM_POSE = 'platform_pose'
PLATFORM_TWIST = 'platform_twist'
TRUE_POSE = 'ground_truth/pose'
TRUE_TWIST = 'ground_truth/twist'
EXTERNAL_WRENCH = 'external_wrench'
CLOCK = '/clock'
DIAGNOSTICS = '/diagnostics'

#: Publisher history: 1 s of samples at 1 kHz, so a reliable recorder that
#: falls briefly behind is re-sent what it missed instead of losing it.
STREAM_DEPTH = 1000

STREAM_PUB = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=STREAM_DEPTH,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
#: Acting on the newest sample only.
LATEST_SUB = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
#: Recording: keep everything.
RECORD_SUB = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=STREAM_DEPTH * 10,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
#: User commands: latched.
SETPOINT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                          reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
DIAGNOSTICS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                             reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.VOLATILE)

#: Every topic of CONTRACT section 2 with its message type name.
TOPIC_TYPES = {
    LEG_LENGTHS: 'sensor_msgs/msg/JointState',
    LEG_FORCES: 'sensor_msgs/msg/JointState',
    LEG_SETPOINT: 'sensor_msgs/msg/JointState',
    POSE_SETPOINT: 'geometry_msgs/msg/PoseStamped',
    PLATFORM_POSE: 'geometry_msgs/msg/PoseStamped',
    PLATFORM_TWIST: 'geometry_msgs/msg/TwistStamped',
    TRUE_POSE: 'geometry_msgs/msg/PoseStamped',
    TRUE_TWIST: 'geometry_msgs/msg/TwistStamped',
    EXTERNAL_WRENCH: 'geometry_msgs/msg/WrenchStamped',
    CLOCK: 'rosgraph_msgs/msg/Clock',
    DIAGNOSTICS: 'diagnostic_msgs/msg/DiagnosticArray',
}
