"""A node's hot loop: its 1 kHz input taken directly, the rest served in between.

``HotLoop`` is mixed into ``RigNode`` (runtime/base.py). A node's hot loop
(``run_on``, the plant's loops) takes its 1 kHz input with a ``DirectTake``
and calls ``housekeeping`` between two messages for everything else.

A loop outside the node can drive it instead (``drive_by``): the composed rig
(nodes/composed.py) serves plant, controller, fk and recorder in one thread,
so the plant's loops, unchanged, wait on that loop's ``poll`` rather than on
their own input alone, and their housekeeping keeps the outer loop's pace.
"""
from __future__ import annotations

import gc
import time
from typing import Protocol

import rclpy

from stewart63_ros.runtime.launcher import STOP
from stewart63_ros.runtime.rclpy_internals import DirectTake, run_timer_if_ready, take


class OuterLoop(Protocol):
    """What a loop that drives a node's hot loop provides (see ``HotLoop.drive_by``)."""

    #: s: the node's housekeeping runs at most this often (the outer loop
    #: serves the other nodes it drives at that pace too)
    side_period: float

    def start(self, own: DirectTake):
        """The node's loop starts; ``own`` takes its 1 kHz input. Returns what
        the node's loop polls instead of ``own`` (the same ``poll(timeout)``:
        it serves the outer loop's other nodes while it waits)."""


class HotLoop:
    """Housekeeping around a node's 1 kHz subscription (see the module's doc)."""

    #: s: the longest a node in a hot loop (run_on, the plant's loops) goes
    #: without an executor turn, for what only the executor serves: parameter
    #: services and QoS event reports. A turn costs 150-500 us of Python (the
    #: executor rebuilds its wait set of some 30 entities), so it is kept rare:
    #: the node's timers are run directly when due, and its other
    #: subscriptions are taken directly (see housekeeping).
    EXECUTOR_PERIOD = 0.1
    #: the most messages taken in one batch before housekeeping (run_on)
    BATCH_MAX = 1000
    #: the loop that drives this node's hot loop (``drive_by``), or None: its own
    outer_loop: OuterLoop | None = None
    #: monotonic time before which housekeeping does nothing (an outer loop's pace)
    _housekeeping_due = 0.0

    def drive_by(self, outer: OuterLoop) -> None:
        """Let ``outer`` drive this node's hot loop from now on (call it before
        ``run``): ``start_hot_loop`` hands it the node's input and returns its
        ``outer.start(own)``, and ``housekeeping`` runs at most every
        ``outer.side_period`` s (at ten thousand samples a second, a pass after
        every sample would cost more than the controller's work)."""
        self.outer_loop = outer

    def start_hot_loop(self, hot):
        """Set up housekeeping around the 1 kHz subscription ``hot``; returns
        what the loop takes it with (a ``DirectTake``, or what an outer loop
        gives for it: see ``drive_by``).

        Also takes everything made so far (modules, kernels, middleware
        objects: hundreds of thousands) out of Python's cyclic garbage
        collector: a full collection over them stops the process for 20-40 ms
        at some point of every run, 20-40 missed 1 kHz cycles; what the loop
        makes is still collected. No collection first: it found nothing to
        free at this point (0 of 140 000 objects) and cost 80 ms of CPU per
        process in every rig's start-up.
        """
        gc.freeze()
        # From here a stop signal is a flag the loop checks (see StopSignals).
        STOP.interruptible = False
        if STOP.requested:
            raise KeyboardInterrupt
        self._side_subs = [s for s in self.subscriptions if s is not hot]
        self._next_turn = 0.0
        self._next_executor_turn = 0.0
        own = DirectTake(self, hot)
        return own if self.outer_loop is None else self.outer_loop.start(own)

    def housekeeping(self, now: float, turn_ok: bool = True) -> float:
        """Between two messages of the hot loop: take what came in on the
        node's other subscriptions (a microsecond each when nothing did), then,
        if one is due, either run the due timers or give the executor a turn
        (one of the two, to keep each call short). ``turn_ok=False`` puts that
        off (the caller is short of time), by 0.1 s at most. Returns the
        monotonic time of the next due one: the caller should not block past it.
        Driven by an outer loop: all this at most every ``side_period`` s.
        """
        if now < self._housekeeping_due:
            return self._housekeeping_due
        for sub in self._side_subs:
            msg = take(sub)
            if msg is not None:
                sub.callback(msg)
        if now < self._next_turn or not (turn_ok or now > self._next_turn + 0.1):
            wake = self._next_turn
        else:
            if not self._run_due_timers() and now >= self._next_executor_turn:
                self.executor_.spin_once(timeout_sec=0)
                self._next_executor_turn = time.monotonic() + self.EXECUTOR_PERIOD
            turned = time.monotonic()
            wake = self._next_executor_turn
            for timer in self.timers:
                left = timer.time_until_next_call()
                if left is not None:
                    wake = min(wake, turned + max(0.0, left * 1e-9))
            self._next_turn = wake
        if self.outer_loop is not None:
            wake = self._housekeeping_due = min(wake, now + self.outer_loop.side_period)
        return wake

    def _run_due_timers(self) -> bool:
        """Call the node's due timers as the executor would; True if any was."""
        ran = False
        for timer in list(self.timers):
            ran = run_timer_if_ready(timer) or ran
        return ran

    def run_on(self, subscription, batch_period: float = 0.0):
        """Serve ``subscription`` directly (see DirectTake), with housekeeping
        after every message: a turn of the executor then falls in the time
        the peer needs to send the next one.

        ``batch_period`` > 0 [s]: after a message, take what else is queued,
        then let the next ones gather that long (or until housekeeping is
        due) before waiting again: one wake-up per batch instead of one per
        message, for a node nothing waits on (every message is still
        served, in order).

        ``after_batch`` runs after each batch and after each housekeeping:
        the executor's turn there serves ``subscription`` too (as it did all
        through the start-up wait), and a message served that way must be
        reported now, not after the next one, which may never come: the
        plant holds that next one until fk reports (runtime/lockstep.py)."""
        self.wait_for_matches()
        direct = self.start_hot_loop(subscription)
        while rclpy.ok() and not STOP.requested:
            wake = self.housekeeping(time.monotonic())
            if self.after_batch is not None:
                self.after_batch()
            if direct.poll(wake - time.monotonic()) and batch_period > 0:
                n = 1
                while n < self.BATCH_MAX and not STOP.requested and direct.poll(0.0):
                    n += 1
                if self.after_batch is not None:
                    self.after_batch()
                pause = min(batch_period, wake - time.monotonic())
                if pause > 0 and not STOP.requested:
                    time.sleep(pause)
