"""Newton-Euler dynamics of the 6-3 platform with massive legs (paper eqs. 8-38).

Model (CONTRACT section 4): each leg is a cylinder (mass m_d, centre of mass
l_d from b_i) on a universal joint at b_i and a piston (mass m_u, centre of
mass l_u from the platform vertex) sliding in it; both are axisymmetric and
spin-free, so they share the angular velocity W_i = s_i x dS_i/dt / L_i
(eq. 14). The pair of legs 2k-1, 2k meets at vertex k through spherical joints.
Piston force F_i acts along s_i; friction is -C_p dL_i/dt along the leg and
the moment -C_u W_i on the leg at the universal joint.

Per leg, the piston's axial balance (the paper's force balance of section IV)
and the moment balance of the whole leg about b_i (eq. 27's Newton-Euler
form) give the force f_i the leg exerts on the platform vertex, linear in the
vertex acceleration a_P (eqs. 16-26):

    f_i = F_i s_i - K_i a_P,i + f0_i
    K_i = m_u s s^T + (I_eff / L^2) (1 - s s^T),
    I_eff = m_d l_d^2 + m_u (L - l_u)^2 + I_td + I_tu      (transverse inertia about b_i)

The axial inertias never enter: a spin-free axisymmetric leg has W . s = 0.
The platform's Newton and Euler equations about its origin (eq. 37) then
assemble into eq. (38),

    J [dd t; alpha] + eta = H F + [R F_ext; R M_ext],

with J symmetric positive definite and H = Jacobian^T (row i of the Jacobian
is [s_i, q_i x s_i]).
"""
from __future__ import annotations

import numpy as np

from stewart63_ros.core.kinematics import LegState
from stewart63_ros.core.rotation import matrix_from_quaternion, quaternion_rate

#: State vector layout: position t (3), quaternion (x, y, z, w) (4),
#: velocity dt/dt (3), angular velocity omega (3); all in the base frame.
STATE_SIZE = 13
POS, QUAT, VEL, OMEGA = slice(0, 3), slice(3, 7), slice(7, 10), slice(10, 13)

#: End-stop model (CONTRACT section 4): past a stroke limit, a stiff
#: spring-damper inside the leg pushes it back; override with the parameters
#: ``endstop_stiffness`` [N/m] and ``endstop_damping`` [N s/m].
DEFAULT_ENDSTOP_STIFFNESS = 2.0e6
DEFAULT_ENDSTOP_DAMPING = 5.0e3


def _skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices, [v]x w = v x w."""
    z = np.zeros(v.shape[:-1])
    return np.stack([np.stack([z, -v[..., 2], v[..., 1]], -1),
                     np.stack([v[..., 2], z, -v[..., 0]], -1),
                     np.stack([-v[..., 1], v[..., 0], z], -1)], -2)


class Dynamics:
    """The model of one mechanism; constants are gathered once here."""

    def __init__(self, mech):
        self.mech = mech
        self.mass = mech.platform_mass
        self.com = np.asarray(mech.platform_com)
        self.inertia_body = np.asarray(mech.platform_inertia)
        self.g = np.asarray(mech.gravity)
        self.m_d, self.m_u = mech.leg_lower_mass, mech.leg_upper_mass
        self.l_d, self.l_u = mech.leg_lower_com, mech.leg_upper_com
        self.i_t = mech.leg_lower_inertia[1] + mech.leg_upper_inertia[1]
        self.c_p, self.c_u = mech.piston_damping, mech.ujoint_damping
        extra = mech.extra
        self.k_stop = float(extra.get('endstop_stiffness', DEFAULT_ENDSTOP_STIFFNESS))
        self.c_stop = float(extra.get('endstop_damping', DEFAULT_ENDSTOP_DAMPING))
        self.l_min, self.l_max = mech.leg_length_min, mech.leg_length_max

    # -- eq. (38) -------------------------------------------------------------
    def equation_terms(self, rot, position, velocity, omega, legs: LegState | None = None):
        """J (6x6), eta (6,) and H (6x6) of eq. (38) at one state."""
        if legs is None:
            legs = LegState(self.mech, position, rot, velocity, omega)
        s, L, q, W, Ldot = legs.s, legs.L, legs.q, legs.W, legs.Ldot
        m_u = self.m_u
        arm_u = L - self.l_u                                  # piston COM distance from b_i
        i_eff = self.m_d * self.l_d ** 2 + m_u * arm_u ** 2 + self.i_t
        c_perp = i_eff / L ** 2
        ss = s[:, :, None] * s[:, None, :]
        K = m_u * ss + c_perp[:, None, None] * (np.eye(3) - ss)     # (6,3,3)

        # Velocity, gravity and friction part of f_i (a_P = 0, F = 0).
        w2 = np.einsum('ij,ij->i', W, W)
        axial = -self.c_p * Ldot + m_u * (s @ self.g) - m_u * self.l_u * w2
        moment = (((-2.0 * i_eff / L + 2.0 * m_u * arm_u) * Ldot + self.c_u)[:, None] * W
                  - (self.m_d * self.l_d + m_u * arm_u)[:, None] * np.cross(s, self.g))
        f0 = axial[:, None] * s + np.cross(s, moment) / L[:, None]
        # Centripetal part of the vertex acceleration, eq. (18).
        u1 = np.cross(omega, np.cross(omega, q))
        leg_bias = np.einsum('ijk,ik->ij', K, u1) - f0

        # Legs: sum_i G_i^T K_i G_i with G_i = [1, -[q_i]x].
        qx = _skew(q)
        Kq = K @ qx
        J = np.empty((6, 6))
        J[:3, :3] = K.sum(0)
        J[:3, 3:] = -Kq.sum(0)
        J[3:, :3] = J[:3, 3:].T
        J[3:, 3:] = -(qx @ Kq).sum(0)

        # Rigid platform about its origin (com offset c, parallel axis).
        c = rot @ self.com
        i_world = rot @ self.inertia_body @ rot.T
        i_origin = i_world + self.mass * (c @ c * np.eye(3) - np.outer(c, c))
        cx = _skew(c)
        M = self.mass
        J[:3, :3] += M * np.eye(3)
        J[:3, 3:] -= M * cx
        J[3:, :3] += M * cx
        J[3:, 3:] += i_origin

        eta = np.empty(6)
        eta[:3] = (M * np.cross(omega, np.cross(omega, c)) - M * self.g
                   + leg_bias.sum(0))
        eta[3:] = (np.cross(omega, i_origin @ omega) - np.cross(c, M * self.g)
                   + np.cross(q, leg_bias).sum(0))
        H = np.vstack([s.T, np.cross(q, s).T])
        return J, eta, H

    def endstop_forces(self, lengths, rates):
        """Extra piston force from the end stops (zero inside the stroke)."""
        below = np.minimum(lengths - self.l_min, 0.0)
        above = np.maximum(lengths - self.l_max, 0.0)
        pen = below + above
        force = -self.k_stop * pen - self.c_stop * rates * (pen != 0)
        return force

    def accelerations(self, rot, position, velocity, omega, forces, wrench=None,
                      legs: LegState | None = None):
        """Forward dynamics: (dd t, alpha) from state and piston forces, eq. (38).

        ``wrench`` = (F_ext, M_ext) in the platform frame at its origin.
        """
        J, eta, H = self.equation_terms(rot, position, velocity, omega, legs)
        rhs = H @ forces - eta
        if wrench is not None:
            rhs[:3] += rot @ wrench[0]
            rhs[3:] += rot @ wrench[1]
        x = np.linalg.solve(J, rhs)
        return x[:3], x[3:]

    def inverse_dynamics(self, rot, position, velocity, omega, accel, alpha, wrench=None):
        """Piston forces that produce (dd t, alpha) at this state: H F = J x + eta - ext."""
        J, eta, H = self.equation_terms(rot, position, velocity, omega)
        rhs = J @ np.concatenate([accel, alpha]) + eta
        if wrench is not None:
            rhs[:3] -= rot @ wrench[0]
            rhs[3:] -= rot @ wrench[1]
        return np.linalg.solve(H, rhs)

    # -- state vector ---------------------------------------------------------
    def derivative(self, y, forces, wrench=None, with_endstops=True):
        """dy/dt for the 13-vector state with piston forces ``forces``."""
        quat = y[QUAT] / np.linalg.norm(y[QUAT])
        rot = matrix_from_quaternion(quat)
        position, velocity, omega = y[POS], y[VEL], y[OMEGA]
        legs = LegState(self.mech, position, rot, velocity, omega)
        if with_endstops:
            forces = forces + self.endstop_forces(legs.L, legs.Ldot)
        accel, alpha = self.accelerations(rot, position, velocity, omega, forces, wrench, legs)
        dy = np.empty(STATE_SIZE)
        dy[POS] = velocity
        dy[QUAT] = quaternion_rate(quat, omega)
        dy[VEL] = accel
        dy[OMEGA] = alpha
        return dy

    def legs(self, y) -> LegState:
        quat = y[QUAT] / np.linalg.norm(y[QUAT])
        return LegState(self.mech, y[POS], matrix_from_quaternion(quat), y[VEL], y[OMEGA])

    # -- energy (for checks and diagnostics) -----------------------------------
    def energy(self, y):
        """(kinetic, potential) of platform and both parts of every leg [J]."""
        quat = y[QUAT] / np.linalg.norm(y[QUAT])
        rot = matrix_from_quaternion(quat)
        legs = LegState(self.mech, y[POS], rot, y[VEL], y[OMEGA])
        omega = y[OMEGA]
        c = rot @ self.com
        v_com = y[VEL] + np.cross(omega, c)
        i_world = rot @ self.inertia_body @ rot.T
        kinetic = 0.5 * self.mass * v_com @ v_com + 0.5 * omega @ i_world @ omega
        w2 = np.einsum('ij,ij->i', legs.W, legs.W)
        arm_u = legs.L - self.l_u
        kinetic += 0.5 * np.sum((self.m_d * self.l_d ** 2 + self.i_t + self.m_u * arm_u ** 2) * w2
                                + self.m_u * legs.Ldot ** 2)
        base = self.mech.base_points
        potential = -self.mass * self.g @ (y[POS] + c)
        potential -= np.sum((self.m_d + self.m_u) * (base @ self.g)
                            + (self.m_d * self.l_d + self.m_u * arm_u) * (legs.s @ self.g))
        return float(kinetic), float(potential)

    def dissipation(self, y):
        """Power lost to friction: sum C_p dL^2 + C_u |W|^2 [W]."""
        legs = self.legs(y)
        return float(self.c_p * legs.Ldot @ legs.Ldot + self.c_u * np.sum(legs.W * legs.W))
