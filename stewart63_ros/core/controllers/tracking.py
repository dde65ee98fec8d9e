"""How far the platform is from its reference: the rotation error (angle of
R_ref R^T), the per-sample accumulation of the tracking errors the rig's
summary prints, and the errors of a whole run (``sim``, scenarios).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from stewart63_ros.core.mechanics.dynamics import POS, QUAT, lengths_rates
from stewart63_ros.core.mechanics.rotation import (
    rotation_angle_between,
)
from stewart63_ros.core.plumbing._jit import njit

if TYPE_CHECKING:
    from stewart63_ros.core.mechanics.mechanism import Mechanism
from stewart63_ros.core.controllers.reference import (
    I_LEN,
    I_POS,
    I_ROT,
    R_LEN,
    R_POS,
    R_ROT,
    Reference,
)


@njit
def _relative_rotation(ref: np.ndarray, rot: np.ndarray) -> tuple:
    """The rotation R_ref R^T that takes R to R_ref, as angle and axis.

    Args:
        ref: a reference sample (SAMPLE_SIZE,), whose ``R_ROT`` part is R_ref.
        rot: R (3, 3), platform to base.

    Returns:
        (angle, vx, vy, vz, s): the angle [rad] in [0, pi], and the axial
        vector v of the matrix's antisymmetric part with its norm s = sin(angle).
    """
    m = np.empty((3, 3))            # R_ref R^T
    for i in range(3):
        for j in range(3):
            m[i, j] = (ref[I_ROT + 3 * i] * rot[j, 0] + ref[I_ROT + 1 + 3 * i] * rot[j, 1]
                       + ref[I_ROT + 2 + 3 * i] * rot[j, 2])
    vx, vy, vz = 0.5 * (m[2, 1] - m[1, 2]), 0.5 * (m[0, 2] - m[2, 0]), 0.5 * (m[1, 0] - m[0, 1])
    s = np.sqrt(vx * vx + vy * vy + vz * vz)
    angle = np.arctan2(s, 0.5 * (m[0, 0] + m[1, 1] + m[2, 2] - 1.0))
    return angle, vx, vy, vz, s


@njit
def rotation_error(ref: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """The rotation vector of R_ref R^T (base frame): the rotation that takes R to R_ref.

    Args:
        ref: a reference sample (SAMPLE_SIZE,), whose ``R_ROT`` part is R_ref.
        rot: R (3, 3), platform to base.

    Returns:
        (3,) axis times angle [rad].
    """
    angle, vx, vy, vz, s = _relative_rotation(ref, rot)
    k = angle / s if s > 1e-300 else 1.0
    return np.array([k * vx, k * vy, k * vz])


@njit
def accumulate_tracking(acc: np.ndarray, lengths: np.ndarray, ref: np.ndarray,
                        pos: np.ndarray, rot: np.ndarray, with_pose: bool) -> None:
    """Add one sample's tracking error to ``acc`` (8,): count, max and sum of
    squares of the leg-length error, of |t_ref - t| and of the angle of R_ref R^T
    (the last two with ``with_pose``).

    Args:
        acc: (8,) the running sums, updated in place (``tracking_summary`` reads them).
        lengths: (6,) measured leg lengths [m].
        ref: the reference sample (SAMPLE_SIZE,).
        pos: (3,) the estimated position [m]; rot: (3, 3) the estimated rotation.
        with_pose: whether ``pos`` and ``rot`` hold an estimate.
    """
    acc[0] += 1.0
    e = 0.0
    for i in range(6):
        d = abs(ref[I_LEN + i] - lengths[i])
        e = max(e, d)
        acc[2] += d * d
    acc[1] = max(acc[1], e)
    if with_pose:
        d = np.sqrt((ref[I_POS] - pos[0]) ** 2 + (ref[I_POS + 1] - pos[1]) ** 2
                    + (ref[I_POS + 2] - pos[2]) ** 2)
        acc[3] = max(acc[3], d)
        acc[4] += d * d
        angle = _relative_rotation(ref, rot)[0]
        acc[5] = max(acc[5], angle)
        acc[6] += angle * angle
        acc[7] += 1.0


def tracking_summary(acc: np.ndarray) -> dict:
    """Max and RMS from an ``accumulate_tracking`` array.

    Args:
        acc: (8,) as ``accumulate_tracking`` filled it.

    Returns:
        ``samples``, ``leg_max_m``, ``leg_rms_m`` and, with a pose, ``position_*``
        [m] and ``orientation_*`` [rad]; an empty dict when there was no sample.
    """
    if acc[0] == 0:
        return {}
    out = {'samples': int(acc[0]), 'leg_max_m': float(acc[1]),
           'leg_rms_m': float(np.sqrt(acc[2] / (6 * acc[0])))}
    if acc[7]:
        out.update(position_max_m=float(acc[3]), position_rms_m=float(np.sqrt(acc[4] / acc[7])),
                   orientation_max_rad=float(acc[5]),
                   orientation_rms_rad=float(np.sqrt(acc[6] / acc[7])))
    return out


def tracking_errors(mech: Mechanism, reference: Reference, times: ArrayLike,
                    states: ArrayLike, after: float = 1.0) -> dict:
    """Max and RMS of the leg-length error, the position error |t_ref - t| and
    the orientation error (angle of R_ref R^T) over the samples at or after
    ``after`` seconds.

    Args:
        mech: the mechanism; reference: what was followed.
        times: (N,) [s] on the reference's clock; states: (N, 13) as in the dynamics.
        after: the first time counted [s].

    Returns:
        ``from_s``, ``samples``, ``leg_max_m``, ``leg_rms_m``, ``position_max_m``,
        ``position_rms_m``, ``orientation_max_rad``, ``orientation_rms_rad``;
        an empty dict when no sample is that late.
    """
    times = np.asarray(times, float)
    keep = times >= after - 1e-12
    if not keep.any():
        return {}
    s = reference.sample_many(times[keep])
    st = np.asarray(states, float)[keep]
    base = np.ascontiguousarray(mech.base_points, float)
    plat = np.ascontiguousarray(mech.leg_platform_points, float)
    legs = np.array([lengths_rates(base, plat, y)[0] for y in st])
    dl = np.abs(legs - s[:, R_LEN])
    dp = np.linalg.norm(st[:, POS] - s[:, R_POS], axis=1)
    da = rotation_angle_between(s[:, R_ROT].reshape(-1, 3, 3), st[:, QUAT])
    return {'from_s': after, 'samples': int(keep.sum()),
            'leg_max_m': float(dl.max()), 'leg_rms_m': float(np.sqrt(np.mean(dl ** 2))),
            'position_max_m': float(dp.max()), 'position_rms_m': float(np.sqrt(np.mean(dp ** 2))),
            'orientation_max_rad': float(da.max()),
            'orientation_rms_rad': float(np.sqrt(np.mean(da ** 2)))}
