"""Time stamps (builtin_interfaces/Time: ``sec``, ``nanosec``) as integer
nanoseconds, in one place. A leaf module: no ROS, no numpy."""
from __future__ import annotations

from typing import Any

#: Nanoseconds per second.
NS_PER_S = 1_000_000_000


def ns_of(sec: int, nanosec: int) -> int:
    """The stamp (``sec``, ``nanosec``) in integer nanoseconds, exactly.

    Args:
        sec: whole seconds; nanosec: the nanoseconds beyond them.

    Returns:
        sec * 1e9 + nanosec [ns], a Python int.
    """
    return int(sec) * NS_PER_S + int(nanosec)


def stamp_ns(stamp: Any) -> int:
    """A builtin_interfaces/Time (anything with ``sec`` and ``nanosec``) in nanoseconds.

    Args:
        stamp: the time stamp.

    Returns:
        [ns], a Python int.
    """
    return ns_of(stamp.sec, stamp.nanosec)


class SampleSpacing:
    """The sample period the stamps show, against the one a node was given.

    A node that numbers a plant's samples at its own ``sensor_rate`` (the
    supervisor: its trips' samples, its force-rate check) counts wrongly when
    that rate is not the plant's. The stamps tell: consecutive samples of a
    run are one plant period apart, in lockstep exactly and in realtime to a
    few hundred ns (a missed cycle makes one gap longer, never shorter). So
    the smallest gap over ``gaps`` consecutive pairs is the plant's period.

    Args:
        period_ns: the period the node was given [ns].
        gaps: how many gaps to see before judging.
        tolerance: the relative difference still taken as equal.
    """

    def __init__(self, period_ns: float, gaps: int = 10, tolerance: float = 0.01) -> None:
        self.period_ns = float(period_ns)
        self.gaps = gaps
        self.tolerance = tolerance
        self.previous: int | None = None
        self.smallest: int | None = None
        self.seen = 0
        self.judged = False

    def add(self, ns: int) -> str:
        """Sample stamped ``ns`` [ns] came. Returns, once, after ``gaps`` gaps:
        why the stamps disagree with the period given; else ''."""
        if self.previous is not None and ns > self.previous:    # (a new run goes back)
            gap = ns - self.previous
            self.smallest = gap if self.smallest is None else min(self.smallest, gap)
            self.seen += 1
        self.previous = ns
        if self.judged or self.seen < self.gaps:
            return ''
        self.judged = True
        if abs(self.smallest - self.period_ns) <= self.tolerance * self.period_ns:
            return ''
        return ('the samples come %.6g ms apart, but sensor_rate %.6g Hz says %.6g ms: give '
                'this node the plant\'s sensor_rate (%.6g Hz), or its sample numbers are wrong'
                % (self.smallest * 1e-6, NS_PER_S / self.period_ns, self.period_ns * 1e-6,
                   NS_PER_S / self.smallest))
