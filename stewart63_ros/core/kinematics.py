"""Inverse kinematics, leg rates and the Jacobian (paper eqs. 2-5, 13-26).

Pose: platform origin t (base frame) and rotation R (platform -> base).
Twist: (v, omega), velocity of the platform origin and angular velocity,
both in the base frame. Arrays over legs are (6, 3), leg order leg_1..leg_6.
"""
from __future__ import annotations

import numpy as np


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
