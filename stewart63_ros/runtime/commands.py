"""Command inputs that match every publisher a user would start.

A command topic (``leg_setpoint``, ``pose_setpoint``, ``pose_trajectory``,
``external_wrench``) is subscribed twice: VOLATILE, which matches volatile and
latched publishers alike (``ros2 topic pub`` with its default QoS), and
TRANSIENT_LOCAL, which also receives the command a latched publisher sent
before the node started. A sample from a latched publisher comes through
both: the second copy (the same message, through the other subscription,
within a second) is dropped, so each command acts once. The recorder
subscribes latched topics the same way and drops the copies alike
(``LatchedCopies``).
"""
from __future__ import annotations

import collections
import time

from stewart63_ros import topics

#: Two copies of one sample arrive within this [s] (the same host's middleware).
DUPLICATE_WINDOW = 1.0


class LatchedCopies:
    """Tells the first copy of a sample from the second, of a topic subscribed
    twice (volatile and transient-local).

    A copy is the same message through the other subscription within
    ``DUPLICATE_WINDOW``; each first copy waits for its second among the last
    ``depth`` ones (several commands can be in flight through both
    subscriptions at once), and is forgotten once it is met.
    """

    def __init__(self, depth: int = 32):
        self._recent = collections.deque(maxlen=depth)  # (tag, sample, monotonic time)

    def first(self, tag: str, sample) -> bool:
        """False for the second copy of ``sample`` (received through the
        subscription ``tag``), True otherwise."""
        now = time.monotonic()
        recent = self._recent
        for i, (other, seen, when) in enumerate(recent):
            if other != tag and now - when < DUPLICATE_WINDOW and seen == sample:
                del recent[i]
                return False
        recent.append((tag, sample, now))
        return True


class CommandInput:
    """Both subscriptions of one command topic, handing ``callback`` each sample once."""

    def __init__(self, node, msg_type, topic, callback):
        self.callback = callback
        self._copies = LatchedCopies()
        self.subscriptions = [
            node.create_subscription(msg_type, topic, self._on('volatile'),
                                     topics.COMMAND_VOLATILE_QOS),
            node.create_subscription(msg_type, topic, self._on('latched'), topics.SETPOINT_QOS)]

    def _on(self, tag):
        def on_message(msg):
            if self._copies.first(tag, msg):
                self.callback(msg)
        return on_message

    def get_publisher_count(self) -> int:
        """Publishers matched by the volatile subscription (it matches every one)."""
        return self.subscriptions[0].get_publisher_count()
