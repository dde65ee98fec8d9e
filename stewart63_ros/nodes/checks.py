"""Input checks for the nodes: what a message must be before it reaches the model.

No ROS types are needed: the checks take plain values, so the fast
serialized-bytes path (``wire``) and the ordinary rclpy messages are judged
by the same code. Rejection reasons are listed in docs/interface.md.
"""
from __future__ import annotations

import numpy as np

from stewart63_ros.core.params import LEG_NAMES


class Rejected(ValueError):
    """An input message that must not reach the model; ``reason`` is a short key."""

    def __init__(self, reason: str, detail: str):
        super().__init__('%s: %s' % (reason, detail))
        self.reason = reason


def stamp_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ros_time(seconds: float):
    """builtin_interfaces/Time from seconds (exact to the nanosecond)."""
    from builtin_interfaces.msg import Time
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


class StampGate:
    """Rejects a sample whose stamp is older than the last accepted one on its topic."""

    def __init__(self):
        self.last_ns = None

    def check(self, stamp) -> int:
        return self.check_ns(stamp_ns(stamp))

    def check_ns(self, ns: int) -> int:
        if self.last_ns is not None and ns < self.last_ns:
            raise Rejected('stamp_from_past', 'stamp %.9f s is older than the last accepted %.9f s'
                           % (ns * 1e-9, self.last_ns * 1e-9))
        return ns

    def accept(self, ns: int) -> None:
        self.last_ns = ns


def finite_vector(values, size: int, field: str) -> np.ndarray:
    arr = np.asarray(values, dtype=float)
    if arr.shape != (size,) or not np.all(np.isfinite(arr)):
        raise Rejected('non_finite' if arr.shape == (size,) else 'wrong_size',
                       '%s must be %d finite numbers' % (field, size))
    return arr
