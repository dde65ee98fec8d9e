"""Input checks for the nodes: what a message must be before it reaches the model.

No ROS types are needed: the checks take plain values, so the fast
serialized-bytes path (``wire``) and the ordinary rclpy messages are judged
by the same code. Rejection reasons are listed in docs/interface.md.
"""
from __future__ import annotations

import time

import numpy as np
from builtin_interfaces.msg import Time

from stewart63_ros.core.plumbing.params import LEG_NAMES
from stewart63_ros.core.plumbing.stamps import stamp_ns


class Rejected(ValueError):
    """An input message that must not reach the model; ``reason`` is a short key.

    ``stamp_ns``: the stamp [ns] of a sample refused for its content only (a
    leg ``NaN`` from a sensor dropout) whose stamp was in order, else None.
    Such a sample was received and handled, only not used: lockstep flow
    control counts it as handled, the controller's lockstep watchdog as a
    sample (not as silence).
    """

    def __init__(self, reason: str, detail: str):
        super().__init__('%s: %s' % (reason, detail))
        self.reason = reason
        self.stamp_ns = None


def ros_time(seconds: float):
    """builtin_interfaces/Time from seconds (exact to the nanosecond)."""
    ns = int(round(seconds * 1e9))
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def leg_vector(names, values, field: str) -> np.ndarray:
    """The six values of a JointState field, in leg order, or Rejected.

    Names must be exactly leg_1..leg_6 in order (an empty name list is taken
    as that order); values must be six finite numbers.
    """
    names = list(names)
    if names and names != list(LEG_NAMES):
        unknown = [n for n in names if n not in LEG_NAMES]
        if unknown:
            raise Rejected('unknown_joint_names', 'unknown joint names %s' % unknown[:6])
        raise Rejected('bad_joint_order', 'joint names %s are not leg_1..leg_6 in order' % names)
    arr = np.asarray(values, dtype=float)
    if arr.shape != (6,):
        raise Rejected('wrong_size', '%s has %d entries, expected 6' % (field, arr.size))
    if not np.all(np.isfinite(arr)):
        raise Rejected('non_finite', '%s holds NaN or Inf' % field)
    return arr


def source_of(info) -> bytes | None:
    """The sending publisher's GID from a take's message info (None if not given)."""
    gid = info.get('publisher_gid') if info else None
    return bytes(gid['data']) if gid else None


#: s: a 1 kHz input quiet this long, whose stamps then jump back, starts a new run
RESTART_PAUSE = 0.5


class StampGate:
    """Stamps of one topic in order, within each run of its source.

    Rejects a sample older than the last accepted one (``stamp_from_past``),
    except when it starts a new run of the source: a restarted sensor driver
    or plant, a bag replayed again. A new run is recognised, and accepted, by

    - a new publisher (``source``: its GID) after the old one went quiet, or
    - the stamps jumping back after the topic was quiet for ``restart_pause``
      seconds (wall clock), as ROS time handles a clock jumping back.

    ``restart_pause`` None (setpoints, wrenches: rare messages whose order
    matters however far apart) turns new runs off: every older stamp is
    refused.

    A second publisher whose samples come while the first one still sends
    (two rigs on one topic) is no new run: its samples are refused
    (``second_source``) and counted in ``interleaved``. Out-of-order samples
    within a run stay refused. ``restarts`` counts the new runs accepted;
    ``new_run`` says why the last checked sample starts one ('' if not).
    """

    def __init__(self, restart_pause: float | None = None, clock=time.monotonic):
        self.restart_pause = restart_pause
        self.clock = clock
        self.last_ns = None
        self.source = None          # GID of the publisher of the current run
        self.last_wall = None       # when the last sample was accepted
        self.restarts = 0
        self.interleaved = 0
        self.other_source = None    # GID of the last refused second publisher
        self.other_wall = None      # when it sent
        self.previous_source = None     # the source of the run before this one
        self.previous_wall = None       # its last accepted sample
        self.new_run = ''
        self.second = False

    def check(self, stamp, source=None) -> int:
        return self.check_ns(stamp_ns(stamp), source)

    def check_ns(self, ns: int, source=None) -> int:
        """The stamp checked (Rejected if from the past); a sample of a second
        publisher passes here and is refused by ``check_source``, which the
        caller runs after the content checks (so bad content is reported as
        such, whoever sent it)."""
        self.new_run = ''
        self.second = False
        if self.last_ns is None:
            return ns
        quiet = (self.restart_pause is not None
                 and self.clock() - self.last_wall > self.restart_pause)
        if source is not None and self.source is not None and source != self.source:
            if quiet:
                self.new_run = 'a new publisher'
                return ns
            self.second = True
        if ns < self.last_ns:
            if not quiet:
                raise Rejected('stamp_from_past', 'stamp %.9f s is older than the last '
                               'accepted %.9f s' % (ns * 1e-9, self.last_ns * 1e-9))
            self.new_run = 'stamps jumped back by %.3f s' % ((self.last_ns - ns) * 1e-9)
        return ns

    def senders(self, window: float) -> set:
        """GIDs of the publishers that sent a sample in the last ``window``
        seconds: two or more is a collision (two rigs feeding one input),
        whether their samples interleave or alternate in runs."""
        now = self.clock()
        found = set()
        for gid, wall in ((self.source, self.last_wall), (self.other_source, self.other_wall),
                          (self.previous_source, self.previous_wall)):
            if gid is not None and wall is not None and now - wall <= window:
                found.add(gid)
        return found

    def check_source(self, source=None) -> None:
        """Rejected if the sample just checked comes from a second publisher
        while the first one still sends."""
        if self.second:
            self.interleaved += 1
            self.other_source = source
            self.other_wall = self.clock()
            raise Rejected('second_source', 'a sample from a second publisher while the '
                           'first one still sends (two rigs on one topic?)')

    def accept(self, ns: int, source=None) -> None:
        if self.new_run:
            self.restarts += 1
            if source is not None and source != self.source:
                self.previous_source, self.previous_wall = self.source, self.last_wall
        self.last_ns = ns
        self.last_wall = self.clock()
        if source is not None:
            self.source = source


def finite_vector(values, size: int, field: str) -> np.ndarray:
    arr = np.asarray(values, dtype=float)
    if arr.shape != (size,) or not np.all(np.isfinite(arr)):
        raise Rejected('non_finite' if arr.shape == (size,) else 'wrong_size',
                       '%s must be %d finite numbers' % (field, size))
    return arr


class SkipCounter:
    """Messages of one topic that never reached this reader.

    Every DDS writer numbers its messages 1, 2, ... (``publication_sequence_number``
    in a take's info): a jump from n to n + k means k - 1 messages of that
    publisher were skipped here (a depth-1 reader that took only the newest,
    a queue that overflowed, a sample the writer could no longer re-send).
    Counted per publisher; a new publisher starts its own count.
    """

    def __init__(self):
        self.last: dict[bytes, int] = {}
        self.skipped = 0

    def note(self, source: bytes | None, info) -> int:
        """Count the gap before the message ``info`` describes; returns it."""
        seq = info.get('publication_sequence_number') if info else None
        if not seq or source is None:
            return 0
        last = self.last.get(source)
        self.last[source] = seq
        if last is None or seq <= last + 1:
            return 0
        gap = seq - last - 1
        self.skipped += gap
        return gap


class StaleForce:
    """Fail safe of a node that applies the held force (the plant, or the bus
    bridge for its drives): a force that answers a sample more than
    ``force_stale_ms`` before the current one is not applied, zero is (a
    supervisor or controller that died leaves no force acting). The first
    sample of each such stretch goes on /diagnostics
    (``stale_force_from_sample``) and into the log.

    Args:
        stale_ms: ``force_stale_ms`` (0: never stale).
        values: the node's status values (``health.values``).
        log_error: ``log_error(text)``, the node's logger.
    """

    def __init__(self, stale_ms: float, values: dict, log_error) -> None:
        self.stale_ns = int(round(stale_ms * 1e6))
        self.values = values
        self.log_error = log_error
        self.since = None       # (sample, stamp of the force gone stale)

    def __call__(self, k: int, now_ns: int, force_ns: int | None) -> bool:
        """True if the force stamped ``force_ns`` is stale at sample ``k``
        (stamp ``now_ns``); none held yet is not stale (it is zero anyway)."""
        if not self.stale_ns or force_ns is None or now_ns - force_ns <= self.stale_ns:
            return False
        if self.since is None or self.since[1] != force_ns:
            self.since = (k, force_ns)
            self.values['stale_force_from_sample'] = k
            self.log_error('no force newer than %.1f ms: zero force from sample %d '
                           '(force_stale_ms)' % (self.stale_ns * 1e-6, k))
        return True
