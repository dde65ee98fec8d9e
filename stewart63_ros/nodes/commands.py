"""Command inputs that match every publisher a user would start.

A command topic (``leg_setpoint``, ``pose_setpoint``, ``pose_trajectory``,
``external_wrench``) is subscribed twice: VOLATILE, which matches volatile and
latched publishers alike (``ros2 topic pub`` with its default QoS), and
TRANSIENT_LOCAL, which also receives the command a latched publisher sent
before the node started. A sample from a latched publisher comes through
both: the second copy (the same message, through the other subscription,
within a second) is dropped, so each command acts once.
"""
from __future__ import annotations

import time

from stewart63_ros import topics

#: Two copies of one sample arrive within this [s] (the same host's middleware).
DUPLICATE_WINDOW = 1.0


class CommandInput:
    """Both subscriptions of one command topic, handing ``callback`` each sample once."""

    def __init__(self, node, msg_type, topic, callback):
        self.callback = callback
        self._last = None           # (subscription tag, message, monotonic time)
        self.subscriptions = [
            node.create_subscription(msg_type, topic, self._on('volatile'),
                                     topics.COMMAND_VOLATILE_QOS),
            node.create_subscription(msg_type, topic, self._on('latched'), topics.SETPOINT_QOS)]

    def _on(self, tag):
        def on_message(msg):
            now = time.monotonic()
            last = self._last
            if last is not None and last[0] != tag and now - last[2] < DUPLICATE_WINDOW \
                    and last[1] == msg:
                return
            self._last = (tag, msg, now)
            self.callback(msg)
        return on_message

    def get_publisher_count(self) -> int:
        """Publishers matched by the volatile subscription (it matches every one)."""
        return self.subscriptions[0].get_publisher_count()
