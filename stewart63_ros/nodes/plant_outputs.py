"""The plant's samples out: leg_lengths, ground_truth pose and twist, /clock.

``SampleOutputs`` is the plant's publishing part: it owns the publishers,
their serialized-message templates (runtime/wire.py) and the wall time each
sample went out (the loop latency starts there). ``leg_lengths`` goes out on
every sample; /clock (lockstep) and ground_truth only while somebody
subscribes to them: they are VOLATILE, so no subscriber can tell.
"""
from __future__ import annotations

import time

import numpy as np
from geometry_msgs.msg import PoseStamped, TwistStamped
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState

from stewart63_ros import topics
from stewart63_ros.core.mechanics.dynamics import OMEGA, POS, QUAT, VEL
from stewart63_ros.runtime import wire


class SampleOutputs:
    """What the plant publishes per sample (see the module's doc).

    Args:
        node: the plant (a RigNode): the publishers are its data publishers.
        lockstep: publish /clock too (simulated time).
        tracker: a ``sensor.TrackerModel``; when it has a rate, ``tracker/pose``
            is published (``send_tracked``) with the true pose plus its noise.
        lengths: publish ``leg_lengths`` (False: the plant stands on the
            field bus, and ``canopen_bridge`` publishes them).
    """

    #: s: how often the plant looks up the subscriptions matched on /clock and
    #: ground_truth (a lookup costs a few microseconds, a sample's budget at
    #: ten thousand samples a second is a hundred).
    LISTENERS_PERIOD = 0.005
    #: the most samples whose send time is kept for an answer (the others
    #: never got one)
    SENT_KEPT = 1000

    def __init__(self, node, lockstep: bool, tracker=None, lengths: bool = True):
        self.health = node.health
        self.tracker = tracker if tracker is not None and tracker.every else None
        if self.tracker is not None:
            self.tracker_out = wire.pose_template('base')
            self.send_tracker = self.health.sender(
                topics.TRACKER_POSE,
                node.publisher(PoseStamped, topics.TRACKER_POSE, topics.STREAM_PUB))
        self.pub_lengths = (node.publisher(JointState, topics.LEG_LENGTHS, topics.STREAM_PUB)
                            if lengths else None)
        self.pub_pose = node.publisher(PoseStamped, topics.TRUE_POSE, topics.STREAM_PUB)
        self.pub_twist = node.publisher(TwistStamped, topics.TRUE_TWIST, topics.STREAM_PUB)
        self.pub_clock = (node.publisher(Clock, topics.CLOCK, topics.STREAM_PUB)
                          if lockstep else None)
        # Serialized messages out and forces in: see runtime/wire.py.
        self.lengths_out = wire.JointStateTemplates(('position', 'velocity')).get('base')
        self.pose_out = wire.pose_template('base')
        self.twist_out = wire.twist_template('base')
        self.clock_out = wire.clock_template()
        wire.warm_up(('effort',))
        sender = self.health.sender
        self.send_lengths = sender(topics.LEG_LENGTHS, self.pub_lengths) if lengths else None
        self.send_pose = sender(topics.TRUE_POSE, self.pub_pose)
        self.send_twist = sender(topics.TRUE_TWIST, self.pub_twist)
        self.send_clock = (sender(topics.CLOCK, self.pub_clock)
                           if self.pub_clock is not None else None)
        # Who listens to /clock and ground_truth, looked up every
        # LISTENERS_PERIOD rather than on every sample (see listeners).
        self.to_clock = self.to_pose = self.to_twist = False
        self.listeners_due = 0.0
        self.sent_wall = {}             # sample stamp -> wall time it was published

    def listeners(self, now: float) -> None:
        """Look up who subscribes to /clock and ground_truth (at ``now``, perf_counter)."""
        self.listeners_due = now + self.LISTENERS_PERIOD
        self.to_clock = bool(self.pub_clock is not None and self.pub_clock.get_subscription_count())
        self.to_pose = bool(self.pub_pose.get_subscription_count())
        self.to_twist = bool(self.pub_twist.get_subscription_count())

    def send(self, ns: int, sec: int, nanosec: int, lengths, rates, y) -> None:
        """One sample stamped ``ns`` (= ``sec``, ``nanosec``): the measured
        ``lengths`` and ``rates`` first, then the rest, from the state ``y``,
        while the controller works on the sample."""
        if self.send_lengths is not None:
            data = self.lengths_out.fill(sec, nanosec, position=lengths, velocity=rates)
            sent_wall = self.sent_wall
            sent_wall[ns] = time.perf_counter()
            if len(sent_wall) > self.SENT_KEPT:   # answers that never came
                sent_wall.pop(next(iter(sent_wall)))
            self.send_lengths(data)
        if self.to_clock:
            self.send_clock(self.clock_out.fill(sec, nanosec))
        # ground_truth, to whoever listens (with no subscriber matched on a
        # VOLATILE topic there is nobody to send it to).
        if self.to_pose:
            quat = y[QUAT] / np.sqrt(y[QUAT] @ y[QUAT])
            self.send_pose(self.pose_out.fill(sec, nanosec, position=y[POS], orientation=quat))
        if self.to_twist:
            self.send_twist(self.twist_out.fill(sec, nanosec, linear=y[VEL], angular=y[OMEGA]))

    def send_tracked(self, sample: int, sec: int, nanosec: int, y) -> None:
        """``tracker/pose`` for sample number ``sample`` if the tracker measures
        then: the true pose of the state ``y`` with the tracker's noise."""
        if self.tracker is None or not self.tracker.due(sample):
            return
        quat = y[QUAT] / np.sqrt(y[QUAT] @ y[QUAT])
        position, quat = self.tracker.measure(y[POS], quat)
        self.send_tracker(self.tracker_out.fill(sec, nanosec, position=position,
                                                orientation=quat))
