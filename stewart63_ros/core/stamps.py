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
