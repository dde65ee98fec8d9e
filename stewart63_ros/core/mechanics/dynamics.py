"""Newton-Euler dynamics of the platform, a 6-3 or a 6-6, with massive legs (paper eqs. 8-38).

Model (docs/interface.md): each leg is a cylinder (mass m_d, centre of mass
l_d from b_i) on a universal joint at b_i and a piston (mass m_u, centre of
mass l_u from the platform vertex) sliding in it; both are axisymmetric and
spin-free, so they share the angular velocity W_i = s_i x dS_i/dt / L_i
(eq. 14). Leg i meets the platform at its joint p_i (``Mechanism.leg_platform_points``):
on the paper's 6-3 the pair of legs 2k-1, 2k meets at vertex k through
spherical joints, on a 6-6 each leg has its own; nothing below depends on which.
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

The compiled right-hand side is scalar code: R and the 3-vectors of the state
travel as tuples of floats, J, H, eta, L and dL/dt are written into one work
array, so that an evaluation allocates nothing but its result
(``derivative_pd``; ``rk4`` allocates once per call), and the small kernels
(``njit_kernel``) are inlined into their compiled callers.

Why this long: one equation, eq. (38): the derivation above, the private
kernels that assemble and solve it (inlined into each other), and the
``Dynamics`` class over them; apart, the kernels would be imported across
files by their private names, and the derivation read in two places.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from stewart63_ros.core.controllers.control import PDGains, pd_leg
from stewart63_ros.core.mechanics.kinematics import LegState, leg_kernel
from stewart63_ros.core.mechanics.linalg import solve_linear
from stewart63_ros.core.mechanics.rotation import matrix_from_quaternion, rotation_rows
from stewart63_ros.core.plumbing._jit import njit, njit_kernel

if TYPE_CHECKING:
    from stewart63_ros.core.mechanics.mechanism import Mechanism

#: State vector layout: position t (3), quaternion (x, y, z, w) (4),
#: velocity dt/dt (3), angular velocity omega (3); all in the base frame.
STATE_SIZE = 13
POS, QUAT, VEL, OMEGA = slice(0, 3), slice(3, 7), slice(7, 10), slice(10, 13)

#: End-stop model (docs/interface.md): past a stroke limit, a stiff
#: spring-damper inside the leg pushes it back; override with the parameters
#: ``endstop_stiffness`` [N/m] and ``endstop_damping`` [N s/m].

NO_WRENCH = np.zeros(6)
NO_GAINS = np.zeros((0, 6))

# Indices into the constants vector handed to the compiled kernels.
_MASS, _G, _COM, _MD, _MU, _LD, _LU, _IT, _CP, _CU, _KSTOP, _CSTOP, _LMIN, _LMAX = (
    0, 1, 4, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17)
_NCONST = 18

# Rows of the work array (_WORK_ROWS, 6) that the kernels below fill instead
# of allocating small arrays: J (6 rows), H (6 rows), eta, L, dL/dt, F.
# Small vectors travel as tuples of floats (no allocation, no reference count).
_J, _H, _ETA, _L, _LDOT, _F = 0, 6, 12, 13, 14, 15
_WORK_ROWS = 16


# -- kinematics, scalar form ----------------------------------------------------------------
@njit_kernel
def _unit_quaternion(x, y, z, w):
    """The quaternion (x, y, z, w) divided by its norm."""
    n = np.sqrt(x ** 2 + y ** 2 + z ** 2 + w ** 2)
    return x / n, y / n, z / n, w / n


@njit_kernel
def _state_tuples(y):
    """(unit quaternion, t, dt/dt, omega) of the 13-state y as tuples."""
    return (_unit_quaternion(y[3], y[4], y[5], y[6]), (y[0], y[1], y[2]), (y[7], y[8], y[9]),
            (y[10], y[11], y[12]))


# -- eq. (38) -------------------------------------------------------------------------------
@njit_kernel
def _add_offset_coupling(out, k, x, y, z):
    """Add k [r]x to J's moment-force block (lower left: rows 3-5, columns
    0-2): the coupling of a mass k at offset r = (x, y, z) from the platform
    origin (a leg's share at its vertex, or the platform's own COM)."""
    out[_J + 4, 0] += k * z
    out[_J + 5, 0] -= k * y
    out[_J + 3, 1] -= k * z
    out[_J + 5, 1] += k * x
    out[_J + 3, 2] += k * y
    out[_J + 4, 2] -= k * x


@njit_kernel
def _platform_inertia(rot, ib, mass, cx, cy, cz):
    """Lower triangle (xx, yx, yy, zx, zy, zz) of the platform inertia about its
    origin in the base frame, I_o = R I_body R^T + m (|c|^2 1 - c c^T)."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = rot
    # Rows of R I_body.
    a0 = r00 * ib[0, 0] + r01 * ib[1, 0] + r02 * ib[2, 0]
    a1 = r00 * ib[0, 1] + r01 * ib[1, 1] + r02 * ib[2, 1]
    a2 = r00 * ib[0, 2] + r01 * ib[1, 2] + r02 * ib[2, 2]
    b0 = r10 * ib[0, 0] + r11 * ib[1, 0] + r12 * ib[2, 0]
    b1 = r10 * ib[0, 1] + r11 * ib[1, 1] + r12 * ib[2, 1]
    b2 = r10 * ib[0, 2] + r11 * ib[1, 2] + r12 * ib[2, 2]
    d0 = r20 * ib[0, 0] + r21 * ib[1, 0] + r22 * ib[2, 0]
    d1 = r20 * ib[0, 1] + r21 * ib[1, 1] + r22 * ib[2, 1]
    d2 = r20 * ib[0, 2] + r21 * ib[1, 2] + r22 * ib[2, 2]
    cc = cx * cx + cy * cy + cz * cz
    ixx = a0 * r00 + a1 * r01 + a2 * r02 + mass * (cc - cx * cx)
    iyx = b0 * r00 + b1 * r01 + b2 * r02 - mass * (cy * cx)
    iyy = b0 * r10 + b1 * r11 + b2 * r12 + mass * (cc - cy * cy)
    izx = d0 * r00 + d1 * r01 + d2 * r02 - mass * (cz * cx)
    izy = d0 * r10 + d1 * r11 + d2 * r12 - mass * (cz * cy)
    izz = d0 * r20 + d1 * r21 + d2 * r22 + mass * (cc - cz * cz)
    return ixx, iyx, iyy, izx, izy, izz


@njit_kernel
def _terms_into(const, base, plat, inertia_body, rot, pos, vel, omega, out):
    """J, eta, H of eq. (38) plus L, dL/dt, written into the rows _J, _ETA, _H,
    _L, _LDOT of ``out``; ``rot`` (rows), ``pos``, ``vel``, ``omega`` are tuples.

    Written with scalars so that the compiled kernel allocates nothing.
    The leg inertia K_i = c_i 1 + d_i s s^T (c = I_eff/L^2, d = m_u - c) maps
    through the vertex map G_i = [1, -[q_i]x] as
    G^T K G = c_i G^T G + d_i h_i h_i^T with h_i = [s_i, q_i x s_i] (column i of H).
    J is symmetric: its lower triangle is summed, then mirrored.
    """
    mass = const[_MASS]
    gx, gy, gz = const[_G], const[_G + 1], const[_G + 2]
    m_d, m_u, l_d, l_u = const[_MD], const[_MU], const[_LD], const[_LU]
    i_t, c_p, c_u = const[_IT], const[_CP], const[_CU]
    wx, wy, wz = omega
    for a in range(6):
        out[_ETA, a] = 0.0
        for b in range(a + 1):
            out[_J + a, b] = 0.0
    for i in range(6):
        qx, qy, qz, L, sx, sy, sz, dx, dy, dz, Ldot = leg_kernel(rot, pos, vel, omega,
                                                                 base, plat, i)
        # (14)
        Wx, Wy, Wz = (sy * dz - sz * dy) / L, (sz * dx - sx * dz) / L, (sx * dy - sy * dx) / L
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
        bx = c * ux + d * su * sx - f0x
        by = c * uy + d * su * sy - f0y
        bz = c * uz + d * su * sz - f0z
        out[_ETA, 0] += bx
        out[_ETA, 1] += by
        out[_ETA, 2] += bz
        out[_ETA, 3] += qy * bz - qz * by
        out[_ETA, 4] += qz * bx - qx * bz
        out[_ETA, 5] += qx * by - qy * bx
        h = (sx, sy, sz, qy * sz - qz * sy, qz * sx - qx * sz, qx * sy - qy * sx)
        for a in range(6):
            out[_H + a, i] = h[a]
            for b in range(a + 1):
                out[_J + a, b] += d * h[a] * h[b]
        # c_i G^T G = c [[1, -[q]x], [[q]x, |q|^2 1 - q q^T]]; [q]x = [[0, -qz, qy], ...]
        qq = qx * qx + qy * qy + qz * qz
        qv = (qx, qy, qz)
        for a in range(3):
            out[_J + a, a] += c
            out[_J + 3 + a, 3 + a] += c * qq
            for b in range(a + 1):
                out[_J + 3 + a, 3 + b] -= c * qv[a] * qv[b]
        _add_offset_coupling(out, c, qx, qy, qz)
        out[_L, i] = L
        out[_LDOT, i] = Ldot
    # Rigid platform about its origin: COM offset c = R c_body, parallel-axis
    # inertia I_o = R I_body R^T + m (|c|^2 1 - c c^T), cf. eq. (37).
    c0, c1, c2 = const[_COM], const[_COM + 1], const[_COM + 2]
    cx = rot[0][0] * c0 + rot[0][1] * c1 + rot[0][2] * c2
    cy = rot[1][0] * c0 + rot[1][1] * c1 + rot[1][2] * c2
    cz = rot[2][0] * c0 + rot[2][1] * c1 + rot[2][2] * c2
    ixx, iyx, iyy, izx, izy, izz = _platform_inertia(rot, inertia_body, mass, cx, cy, cz)
    out[_J + 3, 3] += ixx
    out[_J + 4, 3] += iyx
    out[_J + 4, 4] += iyy
    out[_J + 5, 3] += izx
    out[_J + 5, 4] += izy
    out[_J + 5, 5] += izz
    for a in range(3):
        out[_J + a, a] += mass
    _add_offset_coupling(out, mass, cx, cy, cz)
    for a in range(6):
        for b in range(a):
            out[_J + b, a] = out[_J + a, b]
    # Platform velocity and gravity terms: m (omega x (omega x c) - g) and
    # omega x (I_o omega) - m c x g.
    ax, ay, az = wy * cz - wz * cy, wz * cx - wx * cz, wx * cy - wy * cx
    out[_ETA, 0] += mass * (wy * az - wz * ay - gx)
    out[_ETA, 1] += mass * (wz * ax - wx * az - gy)
    out[_ETA, 2] += mass * (wx * ay - wy * ax - gz)
    lx = ixx * wx + iyx * wy + izx * wz
    ly = iyx * wx + iyy * wy + izy * wz
    lz = izx * wx + izy * wy + izz * wz
    out[_ETA, 3] += wy * lz - wz * ly - mass * (cy * gz - cz * gy)
    out[_ETA, 4] += wz * lx - wx * lz - mass * (cz * gx - cx * gz)
    out[_ETA, 5] += wx * ly - wy * lx - mass * (cx * gy - cy * gx)


@njit
def _terms(const, base, plat, inertia_body, rot, pos, vel, omega):
    """J, eta, H of eq. (38) plus L, dL/dt (new arrays); see ``_terms_into``."""
    out = np.empty((_WORK_ROWS, 6))
    rows = ((rot[0, 0], rot[0, 1], rot[0, 2]), (rot[1, 0], rot[1, 1], rot[1, 2]),
            (rot[2, 0], rot[2, 1], rot[2, 2]))
    _terms_into(const, base, plat, inertia_body, rows, (pos[0], pos[1], pos[2]),
                (vel[0], vel[1], vel[2]), (omega[0], omega[1], omega[2]), out)
    return (out[_J:_J + 6].copy(), out[_ETA].copy(), out[_H:_H + 6].copy(), out[_L].copy(),
            out[_LDOT].copy())


@njit
def inverse_dynamics_forces(const: np.ndarray, base: np.ndarray, plat: np.ndarray,
                            inertia_body: np.ndarray, rot: np.ndarray, pos: np.ndarray,
                            vel: np.ndarray, omega: np.ndarray, acc: np.ndarray) -> np.ndarray:
    """Piston forces F with H F = J acc + eta at the pose (R, t) and twist (v, omega):
    eq. (38) solved for F, without external wrench and end stops. With a zero
    twist and acc = 0 it gives the forces that hold the mechanism against
    gravity. Compiled.

    Args:
        const, base, plat, inertia_body: ``Dynamics.kernel_args()``.
        rot: R (3, 3); pos: t (3,) [m]; vel: v (3,) [m/s]; omega: (3,) [rad/s].
        acc: [dd t; alpha] (6,) [m/s^2, rad/s^2], base frame.

    Returns:
        (6,) piston forces [N]; NaN where H is singular.
    """
    out = np.empty((_WORK_ROWS, 6))
    rows = ((rot[0, 0], rot[0, 1], rot[0, 2]), (rot[1, 0], rot[1, 1], rot[1, 2]),
            (rot[2, 0], rot[2, 1], rot[2, 2]))
    _terms_into(const, base, plat, inertia_body, rows, (pos[0], pos[1], pos[2]),
                (vel[0], vel[1], vel[2]), (omega[0], omega[1], omega[2]), out)
    rhs = np.empty(6)
    for a in range(6):
        v = out[_ETA, a]
        for b in range(6):
            v += out[_J + a, b] * acc[b]
        rhs[a] = v
    return solve_linear(out[_H:_H + 6], rhs)


@njit
def lengths_rates(base: np.ndarray, plat: np.ndarray,
                  y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """L_i and dL_i/dt of the state y, eqs. (2)-(5), (13): the arithmetic of ``_terms``.

    Args:
        base: (6, 3) b_i [m]; plat: (6, 3) each leg's vertex [m] (``kernel_args``).
        y: the state (13,) (``POS``, ``QUAT``, ``VEL``, ``OMEGA``).

    Returns:
        (L (6,) [m], dL/dt (6,) [m/s]).
    """
    quat, pos, vel, omega = _state_tuples(y)
    rot = rotation_rows(*quat)
    L = np.empty(6)
    Ldot = np.empty(6)
    for i in range(6):
        leg = leg_kernel(rot, pos, vel, omega, base, plat, i)
        L[i] = leg[3]
        Ldot[i] = leg[10]
    return L, Ldot


@njit_kernel
def _endstop_leg(const, L, Ldot):
    """End-stop force of one leg (zero inside the stroke) [N]."""
    pen = min(L - const[_LMIN], 0.0) + max(L - const[_LMAX], 0.0)
    if pen != 0.0:
        return -const[_KSTOP] * pen - const[_CSTOP] * Ldot
    return 0.0


@njit_kernel
def _solve_spd_into(A, b, k, n):
    """Cholesky solve of the n x n symmetric positive definite J = A[:n, :n] in
    place (no LAPACK call): A's lower triangle is overwritten by the factor,
    the right-hand side b[k:k + n] by the solution."""
    for j in range(n):
        d = A[j, j]
        for m in range(j):
            d -= A[j, m] * A[j, m]
        A[j, j] = np.sqrt(d)
        for i in range(j + 1, n):
            v = A[i, j]
            for m in range(j):
                v -= A[i, m] * A[j, m]
            A[i, j] = v / A[j, j]
    for i in range(n):              # forward substitution, L z = b
        v = b[k + i]
        for m in range(i):
            v -= A[i, m] * b[k + m]
        b[k + i] = v / A[i, i]
    for i in range(n - 1, -1, -1):  # back substitution, L^T x = z
        v = b[k + i]
        for m in range(i + 1, n):
            v -= A[m, i] * b[k + m]
        b[k + i] = v / A[i, i]


@njit_kernel
def _derivative_into(const, base, plat, inertia_body, y, forces, wrench, endstops, pd,
                     max_force, dy, work):
    """dy/dt written into ``dy`` (13,); ``work`` (_WORK_ROWS, 6) is scratch space.

    With ``pd`` = [setpoint; kp; kv] (3, 6) the PD law of eq. (40) adds its
    force from the same L, dL/dt (continuous control inside the ODE)."""
    quat, pos, vel, omega = _state_tuples(y)
    rot = rotation_rows(*quat)
    _terms_into(const, base, plat, inertia_body, rot, pos, vel, omega, work)
    # Piston forces: applied, plus eq. (40), plus the end stops.
    with_pd = pd.shape[0] == 3
    for i in range(6):
        L, Ldot = work[_L, i], work[_LDOT, i]
        f = forces[i]
        if with_pd:
            f = f + pd_leg(L, Ldot, pd[0, i], 0.0, pd[1, i], pd[2, i], max_force)
        if endstops:
            f = f + _endstop_leg(const, L, Ldot)
        work[_F, i] = f
    # Right-hand side of eq. (38), H F - eta + [R F_ext; R M_ext], into dy[7:13] ...
    for a in range(6):
        v = 0.0
        for i in range(6):
            v += work[_H + a, i] * work[_F, i]
        dy[7 + a] = v - work[_ETA, a]
    for a in range(3):
        r = rot[a]
        dy[7 + a] += r[0] * wrench[0] + r[1] * wrench[1] + r[2] * wrench[2]
        dy[10 + a] += r[0] * wrench[3] + r[1] * wrench[4] + r[2] * wrench[5]
    # ... and [dd t; alpha] = J^-1 (...) there (J's lower triangle is overwritten).
    _solve_spd_into(work, dy, 7, 6)
    dy[0] = y[7]
    dy[1] = y[8]
    dy[2] = y[9]
    x, qy, z, w = quat
    ox, oy, oz = omega
    # dq/dt = 1/2 [omega, 0] (x) q, omega in the base frame
    dy[3] = 0.5 * (ox * w + oy * z - oz * qy)
    dy[4] = 0.5 * (-ox * z + oy * w + oz * x)
    dy[5] = 0.5 * (ox * qy - oy * x + oz * w)
    dy[6] = 0.5 * (-ox * x - oy * qy - oz * z)


@njit
def _derivative(const, base, plat, inertia_body, y, forces, wrench, endstops):
    return derivative_pd(const, base, plat, inertia_body, y, forces, wrench, endstops,
                          NO_GAINS, 0.0)


@njit
def derivative_pd(const: np.ndarray, base: np.ndarray, plat: np.ndarray,
                  inertia_body: np.ndarray, y: np.ndarray, forces: np.ndarray,
                  wrench: np.ndarray, endstops: bool, pd: np.ndarray,
                  max_force: float) -> np.ndarray:
    """dy/dt (a new array); see ``_derivative_into``. Compiled.

    Args:
        const, base, plat, inertia_body: ``Dynamics.kernel_args()``.
        y: the state (13,); forces: applied piston forces (6,) [N].
        wrench: (F_ext, M_ext) (6,) [N, N m], platform frame, at its origin.
        endstops: whether the end stops act.
        pd: [setpoint; kp; kv] (3, 6) for eq. (40) inside the ODE, or
            ``NO_GAINS`` (0, 6) for none; max_force: its saturation [N].

    Returns:
        dy/dt (13,).
    """
    dy = np.empty(13)
    _derivative_into(const, base, plat, inertia_body, y, forces, wrench, endstops, pd,
                     max_force, dy, np.empty((_WORK_ROWS, 6)))
    return dy


@njit
def rk4(const: np.ndarray, base: np.ndarray, plat: np.ndarray, inertia_body: np.ndarray,
        y: np.ndarray, forces: np.ndarray, wrench: np.ndarray, dt: float,
        steps: int) -> np.ndarray:
    """Classical RK4 with the forces held (zero-order hold) over ``steps`` steps.

    Stages and work array are allocated once per call; the loops over j are
    the vector expressions y + dt/2 k1, ..., y + dt/6 (k1 + 2 k2 + 2 k3 + k4),
    component by component. The quaternion is normalised after each step;
    the end stops act.

    Args:
        const, base, plat, inertia_body: ``Dynamics.kernel_args()``.
        y: the state (13,) (not modified); forces: (6,) [N], held.
        wrench: (6,) [N, N m], platform frame; dt: one step [s]; steps: how many.

    Returns:
        The new state (13,).
    """
    y = y.copy()
    k = np.empty((5, 13))          # k1, k2, k3, k4 and the stage state
    work = np.empty((_WORK_ROWS, 6))
    half, sixth = 0.5 * dt, dt / 6.0
    for _ in range(steps):
        _derivative_into(const, base, plat, inertia_body, y, forces, wrench, True,
                         NO_GAINS, 0.0, k[0], work)
        for j in range(13):
            k[4, j] = y[j] + half * k[0, j]
        _derivative_into(const, base, plat, inertia_body, k[4], forces, wrench, True,
                         NO_GAINS, 0.0, k[1], work)
        for j in range(13):
            k[4, j] = y[j] + half * k[1, j]
        _derivative_into(const, base, plat, inertia_body, k[4], forces, wrench, True,
                         NO_GAINS, 0.0, k[2], work)
        for j in range(13):
            k[4, j] = y[j] + dt * k[2, j]
        _derivative_into(const, base, plat, inertia_body, k[4], forces, wrench, True,
                         NO_GAINS, 0.0, k[3], work)
        for j in range(13):
            y[j] = y[j] + sixth * (k[0, j] + 2.0 * k[1, j] + 2.0 * k[2, j] + k[3, j])
        n = np.sqrt(y[3] ** 2 + y[4] ** 2 + y[5] ** 2 + y[6] ** 2)
        for j in range(3, 7):
            y[j] = y[j] / n
    return y



def wrench6(wrench: tuple[ArrayLike, ArrayLike] | None) -> np.ndarray:
    """(F_ext, M_ext) as one array (6,) [N, N m]; None gives ``NO_WRENCH`` (zeros)."""
    if wrench is None:
        return NO_WRENCH
    return np.concatenate([np.asarray(wrench[0], float), np.asarray(wrench[1], float)])


class Dynamics:
    """The model of one mechanism; constants are gathered once here.

    The state ``y`` is a float array (13,): t [m], quaternion (x, y, z, w),
    v [m/s], omega [rad/s], all in the base frame (``POS``, ``QUAT``, ``VEL``,
    ``OMEGA``). The end stops are the mechanism's (``endstop_stiffness``,
    ``endstop_damping``).

    Args:
        mech: the mechanism.
    """

    def __init__(self, mech: Mechanism) -> None:
        self.mech = mech
        const = np.zeros(_NCONST)
        const[_MASS] = mech.platform_mass
        const[_G:_G + 3] = mech.gravity
        const[_COM:_COM + 3] = mech.platform_com
        const[_MD], const[_MU] = mech.leg_lower_mass, mech.leg_upper_mass
        const[_LD], const[_LU] = mech.leg_lower_com, mech.leg_upper_com
        const[_IT] = mech.leg_lower_inertia[1] + mech.leg_upper_inertia[1]
        const[_CP], const[_CU] = mech.piston_damping, mech.ujoint_damping
        const[_KSTOP] = mech.endstop_stiffness
        const[_CSTOP] = mech.endstop_damping
        const[_LMIN], const[_LMAX] = mech.leg_length_min, mech.leg_length_max
        #: Arrays the compiled kernels take (see ``kernel_args``).
        self.constants = const
        self.base_points = np.ascontiguousarray(mech.base_points, dtype=float)
        self.leg_points = np.ascontiguousarray(mech.leg_platform_points, dtype=float)
        self.platform_inertia = np.ascontiguousarray(mech.platform_inertia, dtype=float)
        self.g = np.asarray(mech.gravity)
        self.mass = mech.platform_mass

    def kernel_args(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The first four arguments of every compiled kernel of this module
        (``derivative_pd``, ``rk4``); ``lengths_rates`` takes the middle two.

        Returns:
            (constants, base_points (6, 3), leg_points (6, 3), platform_inertia (3, 3)).
        """
        return self.constants, self.base_points, self.leg_points, self.platform_inertia

    # -- eq. (38) -------------------------------------------------------------
    def equation_terms(self, rot: ArrayLike, position: ArrayLike, velocity: ArrayLike,
                       omega: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The terms of eq. (38) at one pose and twist.

        Args:
            rot: R (3, 3); position: t (3,) [m]; velocity: v (3,) [m/s];
                omega: (3,) [rad/s]; base frame.

        Returns:
            (J (6, 6) symmetric positive definite, eta (6,), H (6, 6)).
        """
        f = np.asarray
        J, eta, H, _, _ = _terms(*self.kernel_args(), f(rot, float), f(position, float),
                                 f(velocity, float), f(omega, float))
        return J, eta, H

    def accelerations(self, rot: ArrayLike, position: ArrayLike, velocity: ArrayLike,
                      omega: ArrayLike, forces: ArrayLike,
                      wrench: tuple[ArrayLike, ArrayLike] | None = None,
                      ) -> tuple[np.ndarray, np.ndarray]:
        """Forward dynamics: (dd t, alpha) from state and piston forces, eq. (38).

        Args:
            rot: R (3, 3); position, velocity, omega: (3,) each, base frame.
            forces: (6,) piston forces [N] (no end stops here).
            wrench: (F_ext (3,) [N], M_ext (3,) [N m]) in the platform frame, at
                its origin; None: none.

        Returns:
            (dd t (3,) [m/s^2], alpha (3,) [rad/s^2]), base frame.
        """
        J, eta, H = self.equation_terms(rot, position, velocity, omega)
        rhs = H @ np.asarray(forces, float) - eta
        w = wrench6(wrench)
        rhs[:3] += rot @ w[:3]
        rhs[3:] += rot @ w[3:]
        x = np.linalg.solve(J, rhs)
        return x[:3], x[3:]

    def inverse_dynamics(self, rot: ArrayLike, position: ArrayLike, velocity: ArrayLike,
                         omega: ArrayLike, accel: ArrayLike, alpha: ArrayLike,
                         wrench: tuple[ArrayLike, ArrayLike] | None = None) -> np.ndarray:
        """Piston forces that produce (dd t, alpha) at this state: H F = J x + eta - ext.

        Args:
            rot: R (3, 3); position, velocity, omega: (3,) each, base frame.
            accel: dd t (3,) [m/s^2]; alpha: (3,) [rad/s^2]; base frame.
            wrench: (F_ext, M_ext), platform frame; None: none.

        Returns:
            (6,) piston forces [N].
        """
        J, eta, H = self.equation_terms(rot, position, velocity, omega)
        rhs = J @ np.concatenate([accel, alpha]) + eta
        w = wrench6(wrench)
        rhs[:3] -= rot @ w[:3]
        rhs[3:] -= rot @ w[3:]
        return np.linalg.solve(H, rhs)

    # -- state vector ---------------------------------------------------------
    def derivative(self, y: ArrayLike, forces: ArrayLike,
                   wrench: tuple[ArrayLike, ArrayLike] | None = None,
                   with_endstops: bool = True) -> np.ndarray:
        """dy/dt of the state under piston forces.

        Args:
            y: the state (13,); forces: (6,) [N].
            wrench: (F_ext, M_ext), platform frame; None: none.
            with_endstops: whether the end stops act.

        Returns:
            dy/dt (13,).
        """
        return _derivative(*self.kernel_args(), np.asarray(y, float), np.asarray(forces, float),
                           wrench6(wrench), with_endstops)

    def step(self, y: ArrayLike, forces: ArrayLike, dt: float, substeps: int = 1,
             wrench: tuple[ArrayLike, ArrayLike] | None = None) -> np.ndarray:
        """Advance ``dt`` with forces held constant (RK4, ``substeps`` steps).

        Args:
            y: the state (13,); forces: (6,) [N], held over the step.
            dt: the time to advance [s]; substeps: RK4 steps in it.
            wrench: (F_ext, M_ext), platform frame; None: none.

        Returns:
            The new state (13,) (``y`` is not modified).
        """
        return rk4(*self.kernel_args(), np.array(y, float), np.asarray(forces, float),
                    wrench6(wrench), dt / substeps, substeps)

    def lengths_and_rates(self, y: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """What ideal linear sensors read at the state.

        Args:
            y: the state (13,).

        Returns:
            (L (6,) [m], dL/dt (6,) [m/s]).
        """
        return lengths_rates(self.base_points, self.leg_points, np.asarray(y, float))

    def derivative_with(self, y: ArrayLike, gains: PDGains,
                        wrench: tuple[ArrayLike, ArrayLike] | None = None) -> np.ndarray:
        """dy/dt under continuous PD control, eq. (40) inside the ODE.

        Args:
            y: the state (13,).
            gains: eq. (40)'s setpoint, gains and saturation (``Controller.pd_gains()``).
            wrench: (F_ext, M_ext), platform frame; None: none.

        Returns:
            dy/dt (13,).
        """
        return derivative_pd(*self.kernel_args(), np.asarray(y, float), np.zeros(6),
                              wrench6(wrench), True, gains.rows(), float(gains.max_force))

    def legs(self, y: np.ndarray) -> LegState:
        """The six legs (``LegState``, with rates) at the state y (13,)."""
        quat = y[QUAT] / np.linalg.norm(y[QUAT])
        return LegState(self.mech, y[POS], matrix_from_quaternion(quat), y[VEL], y[OMEGA])

    # -- energy (for checks and diagnostics) -----------------------------------
    def energy(self, y: np.ndarray) -> tuple[float, float]:
        """The mechanism's energy at a state.

        Args:
            y: the state (13,).

        Returns:
            (kinetic, potential) [J] of the platform and both parts of every leg.
        """
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

    def dissipation(self, y: np.ndarray) -> float:
        """Power lost to friction at the state y (13,): sum C_p dL^2 + C_u |W|^2 [W]."""
        legs = self.legs(y)
        return float(self.mech.piston_damping * legs.Ldot @ legs.Ldot
                     + self.mech.ujoint_damping * np.sum(legs.W * legs.W))
