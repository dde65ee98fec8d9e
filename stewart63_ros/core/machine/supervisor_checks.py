"""The supervisor's checks of one sample or one request against its limits
(no ROS): each returns None, or (cause, what crossed) with a cause of
``supervisor_limits.CAUSES``.

core/machine/supervisor.py is the supervisor; docs/supervisor.md the user's page.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from stewart63_ros.core.machine.supervisor_limits import Limits

Found = tuple[str, str] | None
#: lengths (6,) -> (position (3,), rotation (3, 3)[, the Jacobian's condition number])
PoseFunction = Callable[[np.ndarray], tuple]


def legs(mask: np.ndarray) -> str:
    """'1,3': the legs (1-based) where ``mask`` holds."""
    return ','.join(str(i + 1) for i in np.flatnonzero(mask))


def readings_complete(lengths: np.ndarray, rates: np.ndarray) -> bool:
    """Every leg has a finite length and rate reading."""
    return bool(np.all(np.isfinite(lengths)) and np.all(np.isfinite(rates)))


def stroke_cause(lim: Limits, lengths: np.ndarray) -> Found:
    """A leg reading outside the soft stroke."""
    low, high = lengths < lim.soft_min, lengths > lim.soft_max
    if low.any() or high.any():
        i = int(np.flatnonzero(low | high)[0])
        return 'stroke', 'leg_%d at %.4f m, soft stroke [%.4f, %.4f] m' % (
            i + 1, lengths[i], lim.soft_min, lim.soft_max)
    return None


def speed_cause(lim: Limits, rates: np.ndarray) -> Found:
    """A leg rate reading above ``trip_leg_speed``. The rate is the sensor's,
    sampled with the length at the sample's stamp (a drive's velocity actual
    value, the plant's leg rate): not a difference over arrival times, so a
    stalled computer that takes two samples late does not read as a fast leg."""
    if lim.leg_speed:
        fast = np.abs(rates) > lim.leg_speed
        if fast.any():
            i = int(np.flatnonzero(fast)[0])
            return 'leg_speed', 'leg_%d at %.3f m/s, limit %g m/s' % (
                i + 1, rates[i], lim.leg_speed)
    return None


def pose_cause(lim: Limits, pose: PoseFunction, lengths: np.ndarray) -> Found:
    """The pose of the readings (forward kinematics): none (``pose_box``),
    outside the box or tilted past ``trip_tilt`` (``pose_box``), or near a
    singularity, its Jacobian's condition number above ``trip_condition``
    (``singularity``)."""
    try:
        found = pose(lengths)
    except ValueError as exc:           # NoAssemblyError: no pose has these lengths
        return 'pose_box', 'no pose has these leg lengths: %s' % exc
    position, rotation = found[0], found[1]
    if lim.box is not None:
        out = (position < lim.box[:3]) | (position > lim.box[3:])
        if out.any():
            i = int(np.flatnonzero(out)[0])
            return 'pose_box', '%s = %.4f m outside [%g, %g] m' % (
                'xyz'[i], position[i], lim.box[i], lim.box[i + 3])
    if lim.tilt:
        tilt = math.acos(max(-1.0, min(1.0, float(rotation[2, 2]))))
        if tilt > lim.tilt:
            return 'pose_box', 'tilt %.4f rad, limit %g rad' % (tilt, lim.tilt)
    if lim.condition and len(found) > 2 and not found[2] <= lim.condition:
        return 'singularity', 'Jacobian condition number %.4g at (%.4f, %.4f, %.4f) m, limit ' \
            '%g: near a singularity, where the platform can change assembly mode' % (
                found[2], *position, lim.condition)
    return None


def request_cause(lim: Limits, forces: np.ndarray | None, last_forwarded: np.ndarray,
                  period: float) -> Found:
    """A request that is not six finite forces (``bad_command``), a force
    above ``trip_force`` (``force``), or one changing from ``last_forwarded``
    faster than ``trip_force_rate`` over ``period`` [s] (``force_rate``)."""
    forces = np.asarray(forces)
    if forces.shape != (6,) or not np.all(np.isfinite(forces)):
        return 'bad_command', 'request of shape %s: %s' % (
            forces.shape, np.array2string(forces.ravel()[:12], precision=4))
    big = np.abs(forces) > lim.force
    if big.any():
        i = int(np.flatnonzero(big)[0])
        return 'force', 'leg_%d %.1f N, limit %g N' % (i + 1, forces[i], lim.force)
    if lim.force_rate:
        rate = np.abs(forces - last_forwarded) / period
        fast = rate > lim.force_rate
        if fast.any():
            i = int(np.flatnonzero(fast)[0])
            return 'force_rate', 'leg_%d %.4g N/s, limit %g N/s' % (
                i + 1, rate[i], lim.force_rate)
    return None


def latest_request_cause(lim: Limits, latest: tuple | None, before: tuple | None,
                         period: float) -> Found:
    """``request_cause`` on the latest request (ns, forces), its rate from
    the one ``before`` it (none, or not six finite forces: no rate check),
    over the samples between them; no request at all: ``forces_stale``."""
    if latest is None:
        return 'forces_stale', 'none yet'
    ns, forces = latest
    if lim.force_rate and before is not None and np.shape(before[1]) == (6,) \
            and np.all(np.isfinite(before[1])) and ns > before[0]:
        lim = dataclasses.replace(lim, force_rate=lim.force_rate * (ns - before[0]) * 1e-9
                                  / period)
        return request_cause(lim, forces, np.asarray(before[1]), period)
    return request_cause(dataclasses.replace(lim, force_rate=0.0), forces, None, period)
