"""Inverse kinematics, leg rates and the Jacobian (paper eqs. 2-5, 13-26).

Pose: platform origin t (base frame) and rotation R (platform -> base).
Twist: (v, omega), velocity of the platform origin and angular velocity,
both in the base frame. Arrays over legs are (6, 3), leg order leg_1..leg_6.
"""
from __future__ import annotations

import numpy as np

from stewart63_ros.core._jit import njit_kernel


def vertex_vectors(mech, rot: np.ndarray) -> np.ndarray:
    """q_i = R p_i, eq. (1): each leg's platform vertex relative to t, base frame."""
    return mech.leg_platform_points @ rot.T


def leg_vectors(mech, position, rot) -> np.ndarray:
    """S_i = R p_i + t - b_i, eq. (2)."""
    return vertex_vectors(mech, rot) + np.asarray(position) - mech.base_points


def leg_lengths(mech, position, rot) -> np.ndarray:
    """L_i = |S_i|, eq. (5)."""
    return np.linalg.norm(leg_vectors(mech, position, rot), axis=1)


class LegState:
    """Everything about the six legs at one pose and twist (eqs. 2-5, 13, 14)."""

    __slots__ = ('q', 'S', 'L', 's', 'Sdot', 'Ldot', 'W')

    def __init__(self, mech, position, rot, velocity=None, omega=None):
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


def jacobian(mech, rot, position=None, legs: LegState | None = None) -> np.ndarray:
    """6x6 J with dL/dt = J [v; omega]: row i = [s_i, q_i x s_i].

    Its transpose is the paper's H (eq. 38): platform wrench of unit piston forces.
    """
    if legs is None:
        legs = LegState(mech, position, rot)
    return np.hstack([legs.s, np.cross(legs.q, legs.s)])


def leg_rates(mech, position, rot, velocity, omega) -> np.ndarray:
    """dL_i/dt, eq. (13)."""
    return LegState(mech, position, rot, velocity, omega).Ldot


def leg_accelerations(legs: LegState, accel, alpha, omega):
    """Tip acceleration, leg length acceleration and leg angular acceleration.

    eqs. (16)-(22) for a spin-free leg (W_i . s_i = 0, so A_i . s_i = 0 too):
      a_P = dd t + alpha x q + omega x (omega x q)
      ddL = s . a_P + L |W|^2
      A   = (s x a_P - 2 dL W) / L
    Returns (a_P (6,3), ddL (6,), A (6,3)).
    """
    a_p = accel + np.cross(alpha, legs.q) + np.cross(omega, np.cross(omega, legs.q))
    w2 = np.einsum('ij,ij->i', legs.W, legs.W)
    ddl = np.einsum('ij,ij->i', legs.s, a_p) + legs.L * w2
    ang = (np.cross(legs.s, a_p) - 2.0 * legs.Ldot[:, None] * legs.W) / legs.L[:, None]
    return a_p, ddl, ang


@njit_kernel
def leg_kernel(rot, pos, vel, omega, base, plat, i):
    """Geometry and rates of leg i, scalars: (q, L, s, dS/dt, dL/dt); compiled,
    shared by the dynamics and the forward kinematics.

    ``rot`` is R (its rows as tuples, or a (3, 3) array), ``pos``, ``vel``,
    ``omega`` are 3-tuples (t, dt/dt, omega, base frame), ``base`` and
    ``plat`` the (6, 3) arrays b_i and p_k(i).

    q = R p_i (eq. 1), S = t + q - b_i (eq. 2), L = |S| (eq. 5), s = S / L
    (eq. 4), dS/dt = omega x q + v (eq. 3), dL/dt = s . dS/dt (eq. 13).
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
