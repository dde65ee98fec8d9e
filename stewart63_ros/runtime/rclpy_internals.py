"""The private rclpy calls the 1 kHz loops need, gathered in one place.

rclpy's executor rebuilds its wait set on every turn (150-500 us of Python
here), too slow for a 1 kHz loop. The hot loops therefore take messages,
wait on one subscription and run due timers themselves, through rclpy's
C extension objects (``Subscription.handle``, ``Timer.handle``, ``WaitSet``),
which are not public API.

Checked against rclpy 9.1.2 (ROS 2 Kilted, the Python wheels) and rclpy 9.x
from a Kilted install. ``test/test_rclpy_internals.py`` exercises every call
here, so a rclpy that changes them fails that test loudly instead of a loop
failing quietly.
"""
from __future__ import annotations

import inspect

from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy


def take(subscription):
    """The next message of ``subscription`` (bytes for a raw one), or None.

    ``Subscription.handle.take_message`` returns (message, info) or None.
    """
    taken = subscription.handle.take_message(subscription.msg_type, subscription.raw)
    return None if taken is None else taken[0]


def take_with_info(subscription):
    """(message, info) of the next message of ``subscription``, or None; ``info``
    is rclpy's dict (``received_timestamp``, ``publisher_gid``, ...)."""
    return subscription.handle.take_message(subscription.msg_type, subscription.raw)


def raw_publisher(publisher):
    """A function that publishes serialized bytes on ``publisher``.

    ``Publisher.publish`` checks the message's type and enters the handle's
    context on every call (a microsecond or two of Python); the 1 kHz paths
    publish bytes they built themselves from the node's own publisher, which
    lives as long as the node: ``Publisher.handle.publish_raw``, bound once.
    """
    return publisher.handle.publish_raw


def run_timer_if_ready(timer) -> bool:
    """Call ``timer``'s callback if it is due, as the executor would; True if it was.

    ``is_timer_ready`` / ``call_timer_with_info`` (the latter starts the
    timer's next period) are the handle's private calls. A timer destroyed
    or cancelled meanwhile is skipped.
    """
    try:
        with timer.handle:
            if not timer.handle.is_timer_ready():
                return False
            timer.handle.call_timer_with_info()
    except (RuntimeError, ValueError, AttributeError):  # destroyed or cancelled meanwhile
        return False
    if timer.callback is not None:
        timer.callback()
    return True


class DirectTake:
    """Wait on one subscription and take its messages without the executor.

    The executor rebuilds its wait set on every spin (100-200 microseconds in
    Python); a 1 kHz loop waits on a single subscription in a wait set of its
    own instead, the way rclpy's own ``wait_for_message`` does. A message that
    is already there is taken without waiting at all: even a wait that
    returns at once costs a futex call with a timeout (25 us here, 75 us with
    the kernel's default 50 us timer slack, see ``reduce_timer_slack``). The
    subscription stays in the executor too: either path hands the message to
    the same callback.
    """

    def __init__(self, node, subscription):
        self.sub = subscription
        # A callback of two arguments gets the message info too (the
        # publisher's GID, the timestamps), as the executor gives it.
        try:
            inspect.signature(subscription.callback).bind(object(), object())
            self.with_info = True
        except TypeError:
            self.with_info = False
        self.wait_set = _rclpy.WaitSet(1, 0, 0, 0, 0, 0, node.context.handle)

    def poll(self, timeout_sec: float) -> bool:
        """Take one message, waiting up to ``timeout_sec`` for it, and run the
        callback on it; False if none came."""
        sub = self.sub
        handle = sub.handle
        taken = handle.take_message(sub.msg_type, sub.raw)     # see take()
        if taken is None:
            if timeout_sec <= 0:
                return False
            ws = self.wait_set
            ws.clear_entities()
            ws.add_subscription(handle)
            ws.wait(int(timeout_sec * 1e9))
            taken = handle.take_message(sub.msg_type, sub.raw)
            if taken is None:
                return False
        if self.with_info:
            sub.callback(taken[0], taken[1])
        else:
            sub.callback(taken[0])
        return True


class WaitAny:
    """Block until one of several subscriptions has a message, without taking it.

    For a loop that serves several nodes' subscriptions in one thread (the
    composed rig): the caller takes from each afterwards (``take`` or
    ``DirectTake.poll(0)``). One wait set, rebuilt in place on each wait.
    """

    def __init__(self, context, subscriptions, guard_conditions=()):
        self.handles = [s.handle for s in subscriptions]
        self.guards = [g.handle for g in guard_conditions]
        self.wait_set = _rclpy.WaitSet(len(self.handles), len(self.guards), 0, 0, 0, 0,
                                       context.handle)

    def wait(self, timeout_sec: float) -> None:
        ws = self.wait_set
        ws.clear_entities()
        for handle in self.handles:
            ws.add_subscription(handle)
        for handle in self.guards:
            ws.add_guard_condition(handle)
        ws.wait(int(max(0.0, timeout_sec) * 1e9))
