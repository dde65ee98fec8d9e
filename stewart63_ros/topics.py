"""Topic names and QoS profiles, shared by every node (docs/interface.md, "Topics").

Why these profiles:
- State streams (``leg_lengths``, ``leg_forces``, poses, twists, ``/clock``)
  are published RELIABLE with a deep KEEP_LAST history, so a recorder that
  subscribes RELIABLE with a deep queue loses nothing, while the plant and the
  controller subscribe RELIABLE with depth 1 and so always act on the newest
  sample, never on a backlog. A BEST_EFFORT subscriber (a driver, rviz) also
  matches these publishers.
- Commands: ``leg_setpoint``, ``pose_setpoint`` and ``pose_trajectory`` are
  published TRANSIENT_LOCAL depth 1 ("latched") by the package's tools
  (``view``, ``play``); ``external_wrench`` is not latched (``play``
  replays it with the stream profile; no other tool publishes it). A node
  receives every command, ``external_wrench`` included, through two subscriptions
  (``runtime/commands.py``): a VOLATILE one, which matches every reliable
  publisher (``ros2 topic pub`` with its defaults included), and a
  TRANSIENT_LOCAL one, which receives the command a latched publisher sent
  before the node started; a sample that comes through both is used once.
  rmw's BEST_AVAILABLE durability is not enough on its own: a subscription
  resolves it once, when it is created, and with no publisher yet it becomes
  TRANSIENT_LOCAL, which a later volatile publisher never matches (checked
  with rclpy 9.1.2 and Fast DDS).
"""
from __future__ import annotations

import time

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

LEG_LENGTHS = 'leg_lengths'
LEG_FORCES = 'leg_forces'
LEG_SETPOINT = 'leg_setpoint'
POSE_SETPOINT = 'pose_setpoint'
PLATFORM_POSE = 'platform_pose'
PLATFORM_TWIST = 'platform_twist'
TRUE_POSE = 'ground_truth/pose'
TRUE_TWIST = 'ground_truth/twist'
EXTERNAL_WRENCH = 'external_wrench'
POSE_TRAJECTORY = 'pose_trajectory'
CLOCK = '/clock'
DIAGNOSTICS = '/diagnostics'
MARKERS = 'markers'
#: A pose tracker's measurements (the plant's simulated tracker, or a real one).
TRACKER_POSE = 'tracker/pose'

#: Publisher history: 1 s of samples at 1 kHz, so a reliable recorder that
#: falls briefly behind is re-sent what it missed instead of losing it.
STREAM_DEPTH = 1000

#: The 1 kHz streams. VOLATILE: TRANSIENT_LOCAL (so that a recorder that
#: matched a publisher late is sent what it missed) was tried and lost
#: samples in mid-run in 2 of 3 recorded fresh-clone runs (56 of 1001
#: platform_pose, 6 of 96 markers); not understood, so not used.
STREAM_PUB = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=STREAM_DEPTH,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
#: Acting on the newest sample only.
LATEST_SUB = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
#: Consumers that must see every sample (fk): a queue of 1 s at 1 kHz absorbs a
#: process starved of CPU for that long (100 lost replayed samples on a loaded
#: two-core machine).
EVERY_SUB = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                       reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)
#: Recording: keep everything.
RECORD_SUB = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=STREAM_DEPTH * 10,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
#: User commands: latched (publishers; and the subscription that receives a
#: command published before the node started).
SETPOINT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                          reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: User commands, the subscription that matches volatile publishers too.
COMMAND_VOLATILE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                                  reliability=ReliabilityPolicy.RELIABLE,
                                  durability=DurabilityPolicy.VOLATILE)
#: ``markers`` (20-60 Hz): reliable, with a history of some 3 s of arrays, so
#: a recorder that falls behind is re-sent what it missed; RViz2's and
#: Foxglove's default subscriptions match.
MARKERS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
DIAGNOSTICS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                             reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.VOLATILE)

#: Every topic of the rig with its message type name.
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
    POSE_TRAJECTORY: 'trajectory_msgs/msg/MultiDOFJointTrajectory',
    CLOCK: 'rosgraph_msgs/msg/Clock',
    DIAGNOSTICS: 'diagnostic_msgs/msg/DiagnosticArray',
    MARKERS: 'visualization_msgs/msg/MarkerArray',
    TRACKER_POSE: 'geometry_msgs/msg/PoseStamped',
}

#: Topics whose publishers are latched (TRANSIENT_LOCAL): a recorder asks for
#: their history, so a setpoint published before recording started is in the bag.
LATCHED_TOPICS = (LEG_SETPOINT, POSE_SETPOINT, POSE_TRAJECTORY)
#: Command inputs: each node subscribes them volatile and latched (see above).
COMMAND_TOPICS = (LEG_SETPOINT, POSE_SETPOINT, POSE_TRAJECTORY, EXTERNAL_WRENCH)


def relative_name(topic: str) -> str:
    """``/rig2/leg_lengths`` and ``leg_lengths`` -> ``leg_lengths`` (absolute
    rig topics such as ``/clock`` stay as they are)."""
    if topic in (CLOCK, DIAGNOSTICS):
        return topic
    for name in TOPIC_TYPES:
        if not name.startswith('/') and (topic == name or topic.endswith('/' + name)):
            return name
    return topic


def publisher_qos(topic: str) -> QoSProfile:
    """The profile a publisher of ``topic`` (relative or fully qualified) uses."""
    name = relative_name(topic)
    if name in LATCHED_TOPICS:
        return SETPOINT_QOS
    if name == DIAGNOSTICS:
        return DIAGNOSTICS_QOS
    if name == MARKERS:
        return MARKERS_QOS
    return STREAM_PUB


def recorder_qos(topic: str) -> QoSProfile:
    """The profile a recorder subscribes ``topic`` with: RECORD_SUB, and
    TRANSIENT_LOCAL for latched topics so their last sample is recorded too."""
    if relative_name(topic) in LATCHED_TOPICS:
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=RECORD_SUB.depth,
                          reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
    return RECORD_SUB


def can_match(offered, requested) -> bool:
    """Whether a publisher offering QoS ``offered`` matches a subscription
    requesting ``requested`` (for example one the ROS graph shows), on the
    two policies the rig's profiles differ in: a best-effort publisher does
    not match a reliable subscription, a volatile one does not match a
    TRANSIENT_LOCAL one. (rclpy's ``qos_check_compatible`` reports every
    profile the graph returns as incompatible with one made in Python: the
    graph gives deadline and liveliness lease as "infinite", which it reads
    as set.)"""
    if (requested.reliability == ReliabilityPolicy.RELIABLE
            and offered.reliability == ReliabilityPolicy.BEST_EFFORT):
        return False
    return not (requested.durability == DurabilityPolicy.TRANSIENT_LOCAL
                and offered.durability == DurabilityPolicy.VOLATILE)


def wait_for_subscribers(publishers, min_count: int = 1, timeout: float = 10.0,
                         poll: float = 0.01) -> bool:
    """Block until every publisher in ``publishers`` has at least ``min_count``
    matched subscriptions, at most ``timeout`` seconds; True if they all have.

    Matching is done by the middleware's own threads, so no spinning is needed.
    Publishers of a rig call this before their first sample, so that a
    recorder started first misses nothing (docs/bags.md, readiness handshake).
    """
    deadline = time.monotonic() + timeout
    while True:
        if all(p.get_subscription_count() >= min_count for p in publishers):
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(poll)


def node_full_name(namespace: str, name: str) -> str:
    """'/ns/name' (or '/name') of a node the graph names by namespace and name,
    as ``Node.get_fully_qualified_name`` gives it."""
    return '%s/%s' % (namespace.rstrip('/'), name)


def endpoint_node_name(info) -> str:
    """The full name of the node of a ROS graph endpoint ``info`` (rclpy's
    TopicEndpointInfo)."""
    return node_full_name(info.node_namespace, info.node_name)


#: Every /diagnostics status of the package is named this + the node's full name.
STATUS_PREFIX = 'stewart63'


def status_name(full_name: str) -> str:
    """The /diagnostics status name of the package's node ``full_name``."""
    return STATUS_PREFIX + full_name
