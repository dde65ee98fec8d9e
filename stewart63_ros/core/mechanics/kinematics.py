"""Inverse kinematics, leg rates and the Jacobian (paper eqs. 2-5, 13-26).

Pose: platform origin t (base frame) and rotation R (platform -> base).
Twist: (v, omega), velocity of the platform origin and angular velocity,
both in the base frame. Arrays over legs are (6, 3), leg order leg_1..leg_6.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from stewart63_ros.core.plumbing._jit import njit_kernel

if TYPE_CHECKING:
    from stewart63_ros.core.mechanics.mechanism import Mechanism


def vertex_vectors(mech: Mechanism, rot: np.ndarray) -> np.ndarray:
    """q_i = R p_i, eq. (1): each leg's platform vertex relative to t, base frame.

    Args:
        mech: the mechanism (its ``leg_platform_points``).
        rot: R (3, 3), platform to base.

    Returns:
        (6, 3) q_i [m], one row per leg.
    """
    return mech.leg_platform_points @ rot.T


def leg_vectors(mech: Mechanism, position: ArrayLike, rot: np.ndarray) -> np.ndarray:
    """S_i = R p_i + t - b_i, eq. (2).

    Args:
        mech: the mechanism.
        position: t (3,) [m], base frame.
        rot: R (3, 3), platform to base.

    Returns:
        (6, 3) S_i [m], from each U-joint to its platform vertex, base frame.
    """
    return mech.leg_vectors(position, rot)


def leg_lengths(mech: Mechanism, position: ArrayLike, rot: np.ndarray) -> np.ndarray:
    """L_i = |S_i|, eq. (5): inverse kinematics.

    Args:
        mech: the mechanism.
        position: t (3,) [m], base frame.
        rot: R (3, 3), platform to base.

    Returns:
        (6,) leg lengths [m], leg order.
    """
    return np.linalg.norm(leg_vectors(mech, position, rot), axis=1)


class LegState:
    """Everything about the six legs at one pose and twist (eqs. 2-5, 13, 14).

    Attributes (rows are legs): ``q`` (6, 3) R p_i; ``S`` (6, 3) leg vectors;
    ``L`` (6,) lengths; ``s`` (6, 3) unit leg directions; with a twist also
    ``Sdot`` (6, 3) dS_i/dt, ``Ldot`` (6,) dL_i/dt and ``W`` (6, 3) the legs'
    angular velocities (eq. 14), else None. Base frame, SI units.

    Args:
        mech: the mechanism.
        position: t (3,) [m]; rot: R (3, 3), platform to base.
        velocity: dt/dt (3,) [m/s], or None for the geometry only.
        omega: the platform's angular velocity (3,) [rad/s], base frame (with ``velocity``).
    """

    __slots__ = ('q', 'S', 'L', 's', 'Sdot', 'Ldot', 'W')

    def __init__(self, mech: Mechanism, position: ArrayLike, rot: np.ndarray,
                 velocity: ArrayLike | None = None, omega: ArrayLike | None = None) -> None:
        self.q = vertex_vectors(mech, rot)
        self.S = self.q + np.asarray(position) - mech.base_points
        self.L = np.sqrt(np.einsum('ij,ij->i', self.S, self.S))
        self.s = self.S / self.L[:, None]
        if velocity is None:
            self.Sdot = self.Ldot = self.W = None
            return
        # eq. (3): every leg's tip moves with its platform vertex
        self.Sdot = np.cross(omega, self.q) + velocity
        self.Ldot = np.einsum('ij,ij->i', self.s, self.Sdot)           # eq. (13)
        self.W = np.cross(self.s, self.Sdot) / self.L[:, None]          # eq. (14)


def jacobian(mech: Mechanism, rot: np.ndarray, position: ArrayLike | None = None,
             legs: LegState | None = None) -> np.ndarray:
    """6x6 J with dL/dt = J [v; omega]: row i = [s_i, q_i x s_i].

    Its transpose is the paper's H (eq. 38): platform wrench of unit piston forces.

    Args:
        mech: the mechanism.
        rot: R (3, 3), platform to base.
        position: t (3,) [m] (needed unless ``legs`` is given).
        legs: the ``LegState`` at this pose, if already computed.

    Returns:
        (6, 6) J, rows legs, columns (v, omega) in the base frame.
    """
    if legs is None:
        legs = LegState(mech, position, rot)
    return np.hstack([legs.s, np.cross(legs.q, legs.s)])


def leg_rates(mech: Mechanism, position: ArrayLike, rot: np.ndarray, velocity: ArrayLike,
              omega: ArrayLike) -> np.ndarray:
    """dL_i/dt, eq. (13).

    Args:
        mech: the mechanism.
        position: t (3,) [m]; rot: R (3, 3), platform to base.
        velocity: dt/dt (3,) [m/s]; omega: angular velocity (3,) [rad/s], base frame.

    Returns:
        (6,) leg rates [m/s].
    """
    return LegState(mech, position, rot, velocity, omega).Ldot


def leg_accelerations(legs: LegState, accel: ArrayLike, alpha: ArrayLike,
                      omega: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tip acceleration, leg length acceleration and leg angular acceleration.

    eqs. (16)-(22) for a spin-free leg (W_i . s_i = 0, so A_i . s_i = 0 too):
      a_P = dd t + alpha x q + omega x (omega x q)
      ddL = s . a_P + L |W|^2
      A   = (s x a_P - 2 dL W) / L

    Args:
        legs: the ``LegState`` at the pose and twist (with ``velocity``).
        accel: d2t/dt2 (3,) [m/s^2]; alpha: angular acceleration (3,) [rad/s^2];
            omega: angular velocity (3,) [rad/s]; all base frame.

    Returns:
        (a_P (6, 3) [m/s^2], ddL (6,) [m/s^2], A (6, 3) [rad/s^2]).
    """
    a_p = accel + np.cross(alpha, legs.q) + np.cross(omega, np.cross(omega, legs.q))
    w2 = np.einsum('ij,ij->i', legs.W, legs.W)
    ddl = np.einsum('ij,ij->i', legs.s, a_p) + legs.L * w2
    ang = (np.cross(legs.s, a_p) - 2.0 * legs.Ldot[:, None] * legs.W) / legs.L[:, None]
    return a_p, ddl, ang


@njit_kernel
def leg_kernel(rot: tuple | np.ndarray, pos: tuple, vel: tuple, omega: tuple, base: np.ndarray,
               plat: np.ndarray, i: int) -> tuple:
    """Geometry and rates of leg i, scalars: (q, L, s, dS/dt, dL/dt); compiled,
    shared by the dynamics and the forward kinematics.

    q = R p_i (eq. 1), S = t + q - b_i (eq. 2), L = |S| (eq. 5), s = S / L
    (eq. 4), dS/dt = omega x q + v (eq. 3), dL/dt = s . dS/dt (eq. 13).

    Args:
        rot: R (its rows as 3-tuples, or a (3, 3) array), platform to base.
        pos, vel, omega: 3-tuples t [m], dt/dt [m/s], omega [rad/s], base frame.
        base: (6, 3) b_i [m]; plat: (6, 3) each leg's vertex p_k(i) [m].
        i: the leg, 0-based.

    Returns:
        11 floats: qx, qy, qz, L, sx, sy, sz, dSx, dSy, dSz, dL/dt.
    """
    px, py, pz = plat[i, 0], plat[i, 1], plat[i, 2]
    qx = rot[0][0] * px + rot[0][1] * py + rot[0][2] * pz
    qy = rot[1][0] * px + rot[1][1] * py + rot[1][2] * pz
    qz = rot[2][0] * px + rot[2][1] * py + rot[2][2] * pz
    Sx, Sy, Sz = qx + pos[0] - base[i, 0], qy + pos[1] - base[i, 1], qz + pos[2] - base[i, 2]
    L = np.sqrt(Sx * Sx + Sy * Sy + Sz * Sz)
    sx, sy, sz = Sx / L, Sy / L, Sz / L
    wx, wy, wz = omega
    dx = wy * qz - wz * qy + vel[0]
    dy = wz * qx - wx * qz + vel[1]
    dz = wx * qy - wy * qx + vel[2]
    Ldot = sx * dx + sy * dy + sz * dz
    return qx, qy, qz, L, sx, sy, sz, dx, dy, dz, Ldot
