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

from stewart63_ros.core._jit import njit
from stewart63_ros.core.control import _pd
from stewart63_ros.core.kinematics import LegState
from stewart63_ros.core.rotation import matrix_from_quaternion

#: State vector layout: position t (3), quaternion (x, y, z, w) (4),
#: velocity dt/dt (3), angular velocity omega (3); all in the base frame.
STATE_SIZE = 13
POS, QUAT, VEL, OMEGA = slice(0, 3), slice(3, 7), slice(7, 10), slice(10, 13)

#: End-stop model (CONTRACT section 4): past a stroke limit, a stiff
#: spring-damper inside the leg pushes it back; override with the parameters
#: ``endstop_stiffness`` [N/m] and ``endstop_damping`` [N s/m].
DEFAULT_ENDSTOP_STIFFNESS = 2.0e6
DEFAULT_ENDSTOP_DAMPING = 5.0e3

_NO_WRENCH = np.zeros(6)
_NO_GAINS = np.zeros((0, 6))

# Indices into the constants vector handed to the compiled kernels.
_MASS, _G, _COM, _MD, _MU, _LD, _LU, _IT, _CP, _CU, _KSTOP, _CSTOP, _LMIN, _LMAX = (
    0, 1, 4, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17)
_NCONST = 18


@njit
def _rotation(quat):
    n = np.sqrt(quat[0] ** 2 + quat[1] ** 2 + quat[2] ** 2 + quat[3] ** 2)
    x, y, z, w = quat[0] / n, quat[1] / n, quat[2] / n, quat[3] / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


@njit
def _terms(const, base, plat, inertia_body, rot, pos, vel, omega):
    """J, eta, H of eq. (38) plus L, dL/dt; see the module docstring.

    Written with scalars so that the compiled kernel allocates almost nothing.
    The leg inertia K_i = c_i 1 + d_i s s^T (c = I_eff/L^2, d = m_u - c) maps
    through the vertex map G_i = [1, -[q_i]x] as
    G^T K G = c_i G^T G + d_i h_i h_i^T with h_i = [s_i, q_i x s_i] (column i of H).
    """
    mass = const[_MASS]
    gx, gy, gz = const[_G], const[_G + 1], const[_G + 2]
    m_d, m_u, l_d, l_u = const[_MD], const[_MU], const[_LD], const[_LU]
    i_t, c_p, c_u = const[_IT], const[_CP], const[_CU]
    wx, wy, wz = omega[0], omega[1], omega[2]
    J = np.zeros((6, 6))
    eta = np.zeros(6)
    H = np.empty((6, 6))
    L_out = np.empty(6)
    Ld_out = np.empty(6)
    for i in range(6):
        px, py, pz = plat[i, 0], plat[i, 1], plat[i, 2]
        qx = rot[0, 0] * px + rot[0, 1] * py + rot[0, 2] * pz          # eq. (1)
        qy = rot[1, 0] * px + rot[1, 1] * py + rot[1, 2] * pz
        qz = rot[2, 0] * px + rot[2, 1] * py + rot[2, 2] * pz
        Sx, Sy, Sz = qx + pos[0] - base[i, 0], qy + pos[1] - base[i, 1], qz + pos[2] - base[i, 2]
        L = np.sqrt(Sx * Sx + Sy * Sy + Sz * Sz)                          # eq. (5)
        sx, sy, sz = Sx / L, Sy / L, Sz / L                               # eq. (4)
        # eq. (3): dS/dt = omega x q + v
        dx = wy * qz - wz * qy + vel[0]
        dy = wz * qx - wx * qz + vel[1]
        dz = wx * qy - wy * qx + vel[2]
        Ldot = sx * dx + sy * dy + sz * dz                                # eq. (13)
        Wx, Wy, Wz = (sy * dz - sz * dy) / L, (sz * dx - sx * dz) / L, (sx * dy - sy * dx) / L  # (14)
        arm_u = L - l_u
        i_eff = m_d * l_d * l_d + m_u * arm_u * arm_u + i_t
        c = i_eff / (L * L)
        d = m_u - c
        w2 = Wx * Wx + Wy * Wy + Wz * Wz
        # Velocity, gravity and friction part f0 of the force on the vertex.
        axial = -c_p * Ldot + m_u * (sx * gx + sy * gy + sz * gz) - m_u * l_u * w2
        kw = (-2.0 * i_eff / L + 2.0 * m_u * arm_u) * Ldot + c_u
        kg = m_d * l_d + m_u * arm_u
        Mx = kw * Wx - kg * (sy * gz - sz * gy)
        My = kw * Wy - kg * (sz * gx - sx * gz)
        Mz = kw * Wz - kg * (sx * gy - sy * gx)
        f0x = axial * sx + (sy * Mz - sz * My) / L
        f0y = axial * sy + (sz * Mx - sx * Mz) / L
        f0z = axial * sz + (sx * My - sy * Mx) / L
        # Centripetal vertex acceleration u1 = omega x (omega x q), eq. (18).
        ax, ay, az = wy * qz - wz * qy, wz * qx - wx * qz, wx * qy - wy * qx
        ux, uy, uz = wy * az - wz * ay, wz * ax - wx * az, wx * ay - wy * ax
        su = sx * ux + sy * uy + sz * uz
        bx, by, bz = c * ux + d * su * sx - f0x, c * uy + d * su * sy - f0y, c * uz + d * su * sz - f0z
        eta[0] += bx
        eta[1] += by
        eta[2] += bz
        eta[3] += qy * bz - qz * by
        eta[4] += qz * bx - qx * bz
        eta[5] += qx * by - qy * bx
        h = (sx, sy, sz, qy * sz - qz * sy, qz * sx - qx * sz, qx * sy - qy * sx)
        for a in range(6):
            H[a, i] = h[a]
            for b in range(6):
                J[a, b] += d * h[a] * h[b]
        # c_i G^T G = c [[1, -[q]x], [[q]x, |q|^2 1 - q q^T]]; -[q]x = [[0, qz, -qy], ...]
        qq = qx * qx + qy * qy + qz * qz
        qv = (qx, qy, qz)
        for a in range(3):
            J[a, a] += c
            J[3 + a, 3 + a] += c * qq
            for b in range(3):
                J[3 + a, 3 + b] -= c * qv[a] * qv[b]
        J[0, 4] += c * qz
        J[0, 5] -= c * qy
        J[1, 3] -= c * qz
        J[1, 5] += c * qx
        J[2, 3] += c * qy
        J[2, 4] -= c * qx
        L_out[i] = L
        Ld_out[i] = Ldot
    # Rigid platform about its origin: COM offset c, parallel-axis inertia.
    com = rot @ const[_COM:_COM + 3]
    i_origin = rot @ inertia_body @ rot.T + mass * ((com @ com) * np.eye(3) - np.outer(com, com))
    J[3:, 3:] += i_origin
    for a in range(3):
        J[a, a] += mass
    cx, cy, cz = com[0], com[1], com[2]
    J[0, 4] += mass * cz
    J[0, 5] -= mass * cy
    J[1, 3] -= mass * cz
    J[1, 5] += mass * cx
    J[2, 3] += mass * cy
    J[2, 4] -= mass * cx
    for a in range(3):
        for b in range(3):
            J[3 + b, a] = J[a, 3 + b]
    # Platform velocity and gravity terms.
    ax, ay, az = wy * cz - wz * cy, wz * cx - wx * cz, wx * cy - wy * cx
    eta[0] += mass * (wy * az - wz * ay - gx)
    eta[1] += mass * (wz * ax - wx * az - gy)
    eta[2] += mass * (wx * ay - wy * ax - gz)
    lx = i_origin[0, 0] * wx + i_origin[0, 1] * wy + i_origin[0, 2] * wz
    ly = i_origin[1, 0] * wx + i_origin[1, 1] * wy + i_origin[1, 2] * wz
    lz = i_origin[2, 0] * wx + i_origin[2, 1] * wy + i_origin[2, 2] * wz
    eta[3] += wy * lz - wz * ly - mass * (cy * gz - cz * gy)
    eta[4] += wz * lx - wx * lz - mass * (cz * gx - cx * gz)
    eta[5] += wx * ly - wy * lx - mass * (cx * gy - cy * gx)
    return J, eta, H, L_out, Ld_out


@njit
def _lengths_rates(base, plat, y):
    """L_i and dL_i/dt of the state y, eqs. (2)-(5), (13)."""
    rot = _rotation(y[3:7])
    L = np.empty(6)
    Ldot = np.empty(6)
    w = y[10:13]
    for i in range(6):
        q = rot @ plat[i]
        S = q + y[0:3] - base[i]
        L[i] = np.sqrt(S @ S)
        Sdot = np.array([w[1] * q[2] - w[2] * q[1], w[2] * q[0] - w[0] * q[2],
                         w[0] * q[1] - w[1] * q[0]]) + y[7:10]
        Ldot[i] = (S @ Sdot) / L[i]
    return L, Ldot


@njit
def _endstop(const, L, Ldot):
    out = np.zeros(6)
    for i in range(6):
        pen = min(L[i] - const[_LMIN], 0.0) + max(L[i] - const[_LMAX], 0.0)
        if pen != 0.0:
            out[i] = -const[_KSTOP] * pen - const[_CSTOP] * Ldot[i]
    return out


@njit
def _solve_spd(A, b):
    """Cholesky solve of the 6x6 symmetric positive definite J (no LAPACK call)."""
    n = A.shape[0]
    Lc = np.zeros((n, n))
    for j in range(n):
        d = A[j, j]
        for k in range(j):
            d -= Lc[j, k] * Lc[j, k]
        Lc[j, j] = np.sqrt(d)
        for i in range(j + 1, n):
            v = A[i, j]
            for k in range(j):
                v -= Lc[i, k] * Lc[j, k]
            Lc[i, j] = v / Lc[j, j]
    z = np.empty(n)
    for i in range(n):
        v = b[i]
        for k in range(i):
            v -= Lc[i, k] * z[k]
        z[i] = v / Lc[i, i]
    x = np.empty(n)
    for i in range(n - 1, -1, -1):
        v = z[i]
        for k in range(i + 1, n):
            v -= Lc[k, i] * x[k]
        x[i] = v / Lc[i, i]
    return x


@njit
def _derivative(const, base, plat, inertia_body, y, forces, wrench, endstops):
    return _derivative_pd(const, base, plat, inertia_body, y, forces, wrench, endstops,
                          _NO_GAINS, 0.0)


@njit
def _derivative_pd(const, base, plat, inertia_body, y, forces, wrench, endstops, pd, max_force):
    """dy/dt; with ``pd`` = [setpoint; kp; kv] (3, 6) the PD law of eq. (40) adds
    its force from the same L, dL/dt (continuous control inside the ODE)."""
    rot = _rotation(y[3:7])
    n = np.sqrt(y[3] ** 2 + y[4] ** 2 + y[5] ** 2 + y[6] ** 2)
    x, qy, z, w = y[3] / n, y[4] / n, y[5] / n, y[6] / n
    omega = y[10:13]
    J, eta, H, L, Ldot = _terms(const, base, plat, inertia_body, rot, y[0:3], y[7:10], omega)
    f = forces
    if pd.shape[0] == 3:
        f = f + _pd(L, Ldot, pd[0], pd[1], pd[2], max_force)
    if endstops:
        f = f + _endstop(const, L, Ldot)
    rhs = H @ f - eta
    rhs[:3] += rot @ wrench[:3]
    rhs[3:] += rot @ wrench[3:]
    acc = _solve_spd(J, rhs)
    dy = np.empty(13)
    dy[0:3] = y[7:10]
    ox, oy, oz = omega[0], omega[1], omega[2]
    # dq/dt = 1/2 [omega, 0] (x) q, omega in the base frame
    dy[3] = 0.5 * (ox * w + oy * z - oz * qy)
    dy[4] = 0.5 * (-ox * z + oy * w + oz * x)
    dy[5] = 0.5 * (ox * qy - oy * x + oz * w)
    dy[6] = 0.5 * (-ox * x - oy * qy - oz * z)
    dy[7:10] = acc[:3]
    dy[10:13] = acc[3:]
    return dy


@njit
def _rk4(const, base, plat, inertia_body, y, forces, wrench, dt, steps):
    """Classical RK4 with the forces held (zero-order hold) over ``steps`` steps."""
    for _ in range(steps):
        k1 = _derivative(const, base, plat, inertia_body, y, forces, wrench, True)
        k2 = _derivative(const, base, plat, inertia_body, y + 0.5 * dt * k1, forces, wrench, True)
        k3 = _derivative(const, base, plat, inertia_body, y + 0.5 * dt * k2, forces, wrench, True)
        k4 = _derivative(const, base, plat, inertia_body, y + dt * k3, forces, wrench, True)
        y = y + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        n = np.sqrt(y[3] ** 2 + y[4] ** 2 + y[5] ** 2 + y[6] ** 2)
        y[3:7] = y[3:7] / n
    return y




def _wrench6(wrench):
    if wrench is None:
        return _NO_WRENCH
    return np.concatenate([np.asarray(wrench[0], float), np.asarray(wrench[1], float)])


class Dynamics:
    """The model of one mechanism; constants are gathered once here."""

    def __init__(self, mech):
        self.mech = mech
        extra = mech.extra
        const = np.zeros(_NCONST)
        const[_MASS] = mech.platform_mass
        const[_G:_G + 3] = mech.gravity
        const[_COM:_COM + 3] = mech.platform_com
        const[_MD], const[_MU] = mech.leg_lower_mass, mech.leg_upper_mass
        const[_LD], const[_LU] = mech.leg_lower_com, mech.leg_upper_com
        const[_IT] = mech.leg_lower_inertia[1] + mech.leg_upper_inertia[1]
        const[_CP], const[_CU] = mech.piston_damping, mech.ujoint_damping
        const[_KSTOP] = float(extra.get('endstop_stiffness', DEFAULT_ENDSTOP_STIFFNESS))
        const[_CSTOP] = float(extra.get('endstop_damping', DEFAULT_ENDSTOP_DAMPING))
        const[_LMIN], const[_LMAX] = mech.leg_length_min, mech.leg_length_max
        self._const = const
        self._base = np.ascontiguousarray(mech.base_points, dtype=float)
        self._plat = np.ascontiguousarray(mech.leg_platform_points, dtype=float)
        self._inertia = np.ascontiguousarray(mech.platform_inertia, dtype=float)
        self.g = np.asarray(mech.gravity)
        self.mass = mech.platform_mass

    def _args(self):
        return self._const, self._base, self._plat, self._inertia

    # -- eq. (38) -------------------------------------------------------------
    def equation_terms(self, rot, position, velocity, omega):
        """J (6x6, symmetric positive definite), eta (6,) and H (6x6) of eq. (38)."""
        f = np.asarray
        J, eta, H, _, _ = _terms(*self._args(), f(rot, float), f(position, float),
                                 f(velocity, float), f(omega, float))
        return J, eta, H

    def accelerations(self, rot, position, velocity, omega, forces, wrench=None):
        """Forward dynamics: (dd t, alpha) from state and piston forces, eq. (38).

        ``wrench`` = (F_ext, M_ext) in the platform frame, at its origin.
        """
        J, eta, H = self.equation_terms(rot, position, velocity, omega)
        rhs = H @ np.asarray(forces, float) - eta
        w = _wrench6(wrench)
        rhs[:3] += rot @ w[:3]
        rhs[3:] += rot @ w[3:]
        x = np.linalg.solve(J, rhs)
        return x[:3], x[3:]

    def inverse_dynamics(self, rot, position, velocity, omega, accel, alpha, wrench=None):
        """Piston forces that produce (dd t, alpha) at this state: H F = J x + eta - ext."""
        J, eta, H = self.equation_terms(rot, position, velocity, omega)
        rhs = J @ np.concatenate([accel, alpha]) + eta
        w = _wrench6(wrench)
        rhs[:3] -= rot @ w[:3]
        rhs[3:] -= rot @ w[3:]
        return np.linalg.solve(H, rhs)

    # -- state vector ---------------------------------------------------------
    def derivative(self, y, forces, wrench=None, with_endstops=True):
        """dy/dt of the 13-vector state under piston forces ``forces`` [N]."""
        return _derivative(*self._args(), np.asarray(y, float), np.asarray(forces, float),
                           _wrench6(wrench), with_endstops)

    def step(self, y, forces, dt, substeps=1, wrench=None):
        """Advance ``dt`` with forces held constant (RK4, ``substeps`` steps)."""
        return _rk4(*self._args(), np.array(y, float), np.asarray(forces, float),
                    _wrench6(wrench), dt / substeps, substeps)

    def lengths_and_rates(self, y):
        """L_i [m] and dL_i/dt [m/s] at the state y: what ideal linear sensors read."""
        return _lengths_rates(self._base, self._plat, np.asarray(y, float))

    def derivative_with(self, y, controller, wrench=None):
        """dy/dt under continuous PD control (a ``PDController``), eq. (40) inside the ODE."""
        gains = np.vstack([controller.setpoint, controller.kp, controller.kv])
        return _derivative_pd(*self._args(), np.asarray(y, float), np.zeros(6),
                              _wrench6(wrench), True, gains, controller.max_force)

    def endstop_forces(self, lengths, rates):
        """Extra piston force from the end stops (zero inside the stroke) [N]."""
        return _endstop(self._const, np.asarray(lengths, float), np.asarray(rates, float))

    def legs(self, y) -> LegState:
        quat = y[QUAT] / np.linalg.norm(y[QUAT])
        return LegState(self.mech, y[POS], matrix_from_quaternion(quat), y[VEL], y[OMEGA])

    # -- energy (for checks and diagnostics) -----------------------------------
    def energy(self, y):
        """(kinetic, potential) of platform and both parts of every leg [J]."""
        mech = self.mech
        legs = self.legs(y)
        rot = matrix_from_quaternion(y[QUAT] / np.linalg.norm(y[QUAT]))
        omega = y[OMEGA]
        c = rot @ mech.platform_com
        v_com = y[VEL] + np.cross(omega, c)
        i_world = rot @ mech.platform_inertia @ rot.T
        kinetic = 0.5 * self.mass * v_com @ v_com + 0.5 * omega @ i_world @ omega
        m_d, m_u, l_d, l_u = (mech.leg_lower_mass, mech.leg_upper_mass,
                              mech.leg_lower_com, mech.leg_upper_com)
        i_t = mech.leg_lower_inertia[1] + mech.leg_upper_inertia[1]
        w2 = np.einsum('ij,ij->i', legs.W, legs.W)
        arm_u = legs.L - l_u
        kinetic += 0.5 * np.sum((m_d * l_d ** 2 + i_t + m_u * arm_u ** 2) * w2
                                + m_u * legs.Ldot ** 2)
        potential = -self.mass * self.g @ (y[POS] + c)
        potential -= np.sum((m_d + m_u) * (mech.base_points @ self.g)
                            + (m_d * l_d + m_u * arm_u) * (legs.s @ self.g))
        return float(kinetic), float(potential)

    def dissipation(self, y):
        """Power lost to friction: sum C_p dL^2 + C_u |W|^2 [W]."""
        legs = self.legs(y)
        return float(self.mech.piston_damping * legs.Ldot @ legs.Ldot
                     + self.mech.ujoint_damping * np.sum(legs.W * legs.W))
