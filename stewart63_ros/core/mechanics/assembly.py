"""Which assembly mode the platform is in, along its path (no ROS).

Forward kinematics has several poses for one set of leg lengths (core/mechanics/fk.py,
"all assembly modes"); they are separated by singular poses, where the
Jacobian J of dL/dt = J [v; omega] (kinematics.jacobian, the transpose of
the paper's H, eq. 38) loses rank. A platform that moves through such a
pose changes its assembly mode: det J changes sign. On a machine that means
legs or joints past their limits, and leg-length control that now pushes
the wrong way. ``AssemblyWatch`` follows the sign of det J along the true
states (the plant's, ``sim``'s) and names the sample of each crossing; the
supervisor trips before one (its ``singularity`` cause, from the condition
number of the pose the readings give).
"""
from __future__ import annotations

import math

import numpy as np

from stewart63_ros.core.mechanics.kinematics import leg_kernel
from stewart63_ros.core.mechanics.rotation import rotation_rows
from stewart63_ros.core.plumbing._jit import njit

_ZERO3 = (0.0, 0.0, 0.0)


@njit
def jacobian_determinant(base: np.ndarray, plat: np.ndarray, y: np.ndarray) -> float:
    """det J at the state ``y`` (13,): row i of J = [s_i, q_i x s_i] (eqs. 1-4).

    Args:
        base: (6, 3) b_i [m]; plat: (6, 3) each leg's vertex [m]
            (``Dynamics.kernel_args``' middle two).
        y: the state (position, unit quaternion x y z w, ...).

    Returns:
        det J (its sign: the assembly mode's side of the singular poses).
    """
    norm = math.sqrt(y[3] * y[3] + y[4] * y[4] + y[5] * y[5] + y[6] * y[6])
    rot = rotation_rows(y[3] / norm, y[4] / norm, y[5] / norm, y[6] / norm)
    pos = (y[0], y[1], y[2])
    jac = np.empty((6, 6))
    for i in range(6):
        leg = leg_kernel(rot, pos, _ZERO3, _ZERO3, base, plat, i)
        qx, qy, qz, sx, sy, sz = leg[0], leg[1], leg[2], leg[4], leg[5], leg[6]
        jac[i, 0], jac[i, 1], jac[i, 2] = sx, sy, sz
        jac[i, 3] = qy * sz - qz * sy
        jac[i, 4] = qz * sx - qx * sz
        jac[i, 5] = qx * sy - qy * sx
    return np.linalg.det(jac)


class AssemblyWatch:
    """The sign of det J sample after sample: ``check`` names a crossing.

    Args:
        base, plat: as ``jacobian_determinant``'s (``Dynamics.kernel_args()[1:3]``).
        rate: the sample rate [Hz] (the time in the message).
    """

    def __init__(self, base: np.ndarray, plat: np.ndarray, rate: float) -> None:
        self.base, self.plat, self.rate = base, plat, rate
        self.start_sign = 0.0           # the start's mode: det J's sign at the first sample
        self.sign = 0.0
        self.last_det = math.nan
        #: the sample of each crossing, in order
        self.crossings: list[int] = []

    @property
    def in_start_mode(self) -> bool:
        """True while det J has the sign it had at the first sample."""
        return self.sign == self.start_sign

    def check(self, k: int, y: np.ndarray) -> str:
        """Sample ``k``'s true state ``y``: '' or, on the sample where det J
        changed sign since the previous one, what happened (ERROR words)."""
        det = jacobian_determinant(self.base, self.plat, y)
        sign = math.copysign(1.0, det)
        before, self.last_det = self.last_det, det
        if not self.start_sign:
            self.start_sign = self.sign = sign
            return ''
        if sign == self.sign:
            return ''
        self.sign = sign
        self.crossings.append(k)
        if sign == self.start_sign:
            return ('assembly mode back to the start\'s at sample %d (t = %.4f s): det J %.3g '
                    '-> %.3g' % (k, k / self.rate, before, det))
        return ('assembly mode changed at sample %d (t = %.4f s): det J %.3g -> %.3g, the '
                'platform crossed a singular pose into another assembly mode (legs or joints '
                'may be past their limits)' % (k, k / self.rate, before, det))


def crossings(base: np.ndarray, plat: np.ndarray, states: np.ndarray,
              rate: float) -> list[str]:
    """What ``AssemblyWatch`` says along the states (N, 13) sampled at
    ``rate`` [Hz]: one message a crossing, in order."""
    watch = AssemblyWatch(base, plat, rate)
    return [note for k, y in enumerate(states) for note in (watch.check(k, y),) if note]
