"""Forward kinematics by Newton on the six leg equations: the tracking kernels.

Newton from the previous pose, with the analytic Jacobian (row i =
[s_i, q_i x s_i], so dL = J [dt; dw], paper eq. 13) and the orientation
updated on SO(3) by a rotation vector (``_newton``); one tracking step with
its distance moved and condition number (``_track``, ``FKTracker``'s); the
pose and twist from lengths and rates (``pose_and_twist``, the laws'). The
all-modes solver (``fk_modes``) polishes its modes with the same Newton.
The classes around these kernels are ``fk``'s (and ``fk66``'s); their result
(``FKResult``), error and input check live here, where both solvers reach
them without importing each other.

The hot loops are numba kernels written with scalar loops: numba's array
expressions and ``@`` (a BLAS call) are slow at 3x3 and 6x6, and slow to
compile.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from stewart63_ros.core.mechanics.kinematics import leg_kernel
from stewart63_ros.core.mechanics.linalg import solve_linear
from stewart63_ros.core.mechanics.rotation import euler_from_matrix, quaternion_of_matrix
from stewart63_ros.core.plumbing._jit import njit


class NoAssemblyError(ValueError):
    """Leg lengths for which the platform cannot be assembled."""


def checked_lengths(lengths: ArrayLike) -> np.ndarray:
    """Six finite positive leg lengths as a float array (6,) (the 6-3's and
    the 6-6's solvers both check their input here).

    Raises:
        ValueError: not six finite numbers.
        NoAssemblyError: a length that is not positive.
    """
    lengths = _arr(lengths)
    if lengths.shape != (6,) or not np.all(np.isfinite(lengths)):
        raise ValueError('leg lengths must be 6 finite numbers, got %r' % (lengths,))
    bad = np.flatnonzero(lengths <= 0)
    if bad.size:
        raise NoAssemblyError('leg_%d length %g m is not positive'
                              % (bad[0] + 1, lengths[bad[0]]))
    return lengths


class FKResult:
    """One pose from the leg lengths.

    position (3,) and rotation (3, 3) (platform -> base); ``condition`` the
    2-norm condition number of the Jacobian there, ``singular`` whether it is
    above the threshold; ``residual`` max |L_i(pose) - L_i| [m]; ``iterations``
    of Newton; ``fallback`` True when the all-modes solver chose the branch;
    ``velocity``, ``omega`` the twist (base frame) when leg rates were given.

    Args:
        position: t (3,) [m]; rotation: R (3, 3).
        condition, singular, residual, iterations, fallback: as the attributes.
    """

    __slots__ = ('position', 'rotation', 'condition', 'singular', 'residual',
                 'iterations', 'fallback', 'velocity', 'omega')

    def __init__(self, position: np.ndarray, rotation: np.ndarray, condition: float,
                 singular: bool, residual: float, iterations: int = 0,
                 fallback: bool = False) -> None:
        self.position = position
        self.rotation = rotation
        self.condition = float(condition)
        self.singular = bool(singular)
        self.residual = float(residual)
        self.iterations = int(iterations)
        self.fallback = fallback
        self.velocity = self.omega = None

    @property
    def theta(self) -> np.ndarray:
        """(theta_x, theta_y, theta_z), R = Rz Ry Rx (docs/interface.md)."""
        return euler_from_matrix(self.rotation)

    @property
    def quaternion(self) -> np.ndarray:
        """(x, y, z, w) with w >= 0."""
        return quaternion_of_matrix(self.rotation)

    def __repr__(self) -> str:
        return ('FKResult(position=%s, theta=%s, condition=%.3g%s)'
                % (np.round(self.position, 6).tolist(), np.round(self.theta, 6).tolist(),
                   self.condition, ', SINGULAR' if self.singular else ''))


def _arr(x) -> np.ndarray:
    """A writable C-contiguous float64 copy: numba compiles (and caches) one
    variant per layout and read-only flag, so every kernel sees one kind."""
    return np.array(x, dtype=np.float64, order='C')




@njit
def _rotate_left(w, rot):
    """exp([w]x) rot (Rodrigues): rot turned by the base-frame rotation vector w."""
    th2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    if th2 < 1e-16:   # series of sin(t)/t and (1 - cos t)/t^2
        a, b = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
    else:
        th = np.sqrt(th2)
        a, b = np.sin(th) / th, (1.0 - np.cos(th)) / th2
    x, y, z = w[0], w[1], w[2]
    e = np.empty((3, 3))
    e[0, 0] = 1.0 - b * (y * y + z * z)
    e[1, 1] = 1.0 - b * (x * x + z * z)
    e[2, 2] = 1.0 - b * (x * x + y * y)
    e[0, 1] = -a * z + b * x * y
    e[1, 0] = a * z + b * x * y
    e[0, 2] = a * y + b * x * z
    e[2, 0] = -a * y + b * x * z
    e[1, 2] = -a * x + b * y * z
    e[2, 1] = a * x + b * y * z
    out = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            out[i, j] = e[i, 0] * rot[0, j] + e[i, 1] * rot[1, j] + e[i, 2] * rot[2, j]
    return out


@njit
def _legs(base, legp, t, rot, lengths, jac, res):
    """jac rows [s_i, q_i x s_i] (eqs. 1-5, 13) and res = lengths - L; returns max |res|."""
    worst = 0.0
    pos, still = (t[0], t[1], t[2]), (0.0, 0.0, 0.0)
    for i in range(base.shape[0]):
        q0, q1, q2, length, s0, s1, s2, _, _, _, _ = leg_kernel(rot, pos, still, still, base,
                                                               legp, i)
        jac[i, 0], jac[i, 1], jac[i, 2] = s0, s1, s2
        jac[i, 3] = q1 * s2 - q2 * s1
        jac[i, 4] = q2 * s0 - q0 * s2
        jac[i, 5] = q0 * s1 - q1 * s0
        res[i] = lengths[i] - length
        worst = max(worst, abs(res[i]))
    return worst


@njit
def condition_number(jac: np.ndarray) -> float:
    """2-norm condition number sigma_max / sigma_min of a square matrix.

    One-sided Jacobi (Hestenes 1958): rotate pairs of columns until all are
    orthogonal; the column norms are then the singular values, small ones to
    full relative accuracy. Cheaper than a LAPACK call at 6x6. Compiled.

    Args:
        jac: (n, n) float array (not modified).

    Returns:
        sigma_max / sigma_min (inf for a singular matrix).
    """
    a = jac.copy()
    m, n = a.shape
    for _ in range(30):
        off = 0.0
        for i in range(n - 1):
            for j in range(i + 1, n):
                alpha = beta = gamma = 0.0
                for k in range(m):
                    alpha += a[k, i] * a[k, i]
                    beta += a[k, j] * a[k, j]
                    gamma += a[k, i] * a[k, j]
                if gamma == 0.0:
                    continue
                off = max(off, abs(gamma) / np.sqrt(alpha * beta))
                zeta = (beta - alpha) / (2.0 * gamma)
                # the smaller root of tan^2 + 2 zeta tan - 1 = 0 (a rotation of at most 45 deg)
                tan = 1.0 if zeta == 0.0 else (
                    np.sign(zeta) / (abs(zeta) + np.sqrt(1.0 + zeta * zeta)))
                cos = 1.0 / np.sqrt(1.0 + tan * tan)
                sin = cos * tan
                for k in range(m):
                    ai, aj = a[k, i], a[k, j]
                    a[k, i] = cos * ai - sin * aj
                    a[k, j] = sin * ai + cos * aj
        if off < 1e-15:
            break
    smax, smin = 0.0, np.inf
    for j in range(n):
        norm = 0.0
        for k in range(m):
            norm += a[k, j] * a[k, j]
        smax, smin = max(smax, norm), min(smin, norm)
    return np.sqrt(smax / smin) if smin > 0.0 else np.inf


@njit
def _newton(base, legp, lengths, t0, rot0, max_iter, step_tol):
    """Newton on L(t, R) = lengths; returns t, R, iterations, converged, max |residual|.

    Step: J [dt; dw] = lengths - L, then t += dt, R = exp([dw]x) R. Converged
    when the step is below step_tol (quadratic convergence then leaves an
    error of order step_tol^2), or when the residual is down to rounding
    (a few ulp of the longest leg): at a singular pose the step in the
    singular direction never settles, but the lengths cannot tell more.
    """
    t = t0.copy()
    rot = rot0.copy()
    jac = np.empty((6, 6))
    res = np.empty(6)
    w = np.empty(3)
    floor = 0.0
    for i in range(lengths.shape[0]):
        floor = max(floor, 4.0 * 2.220446049250313e-16 * abs(lengths[i]))
    ok = False
    it = 0
    while it < max_iter:
        if _legs(base, legp, t, rot, lengths, jac, res) <= floor:
            ok = True
            break
        it += 1
        d = solve_linear(jac, res)
        size = 0.0
        for k in range(d.shape[0]):
            size = max(size, abs(d[k]))
        if not size < 1e3:      # also catches NaN
            break
        for k in range(3):
            t[k] += d[k]
            w[k] = d[3 + k]
        rot = _rotate_left(w, rot)
        if size < step_tol:
            ok = True
            break
    # Gram-Schmidt: keep R orthonormal over many tracked samples.
    n0 = np.sqrt(rot[0, 0] ** 2 + rot[1, 0] ** 2 + rot[2, 0] ** 2)
    for i in range(3):
        rot[i, 0] /= n0
    dot = rot[0, 0] * rot[0, 1] + rot[1, 0] * rot[1, 1] + rot[2, 0] * rot[2, 1]
    for i in range(3):
        rot[i, 1] -= dot * rot[i, 0]
    n1 = np.sqrt(rot[0, 1] ** 2 + rot[1, 1] ** 2 + rot[2, 1] ** 2)
    for i in range(3):
        rot[i, 1] /= n1
    rot[0, 2] = rot[1, 0] * rot[2, 1] - rot[2, 0] * rot[1, 1]
    rot[1, 2] = rot[2, 0] * rot[0, 1] - rot[0, 0] * rot[2, 1]
    rot[2, 2] = rot[0, 0] * rot[1, 1] - rot[1, 0] * rot[0, 1]
    worst = _legs(base, legp, t, rot, lengths, jac, res)
    return t, rot, it, ok, worst


@njit
def _pose_distance(t, rot, t_ref, rot_ref, size):
    """|t - t_ref| + size * angle(R_ref^T R): position and orientation in one length.

    The angle comes from both the sine and the cosine of R_ref^T R, accurate
    at small and large angles alike.
    """
    m = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            m[i, j] = (rot_ref[0, i] * rot[0, j] + rot_ref[1, i] * rot[1, j]
                       + rot_ref[2, i] * rot[2, j])
    sin2 = np.sqrt((m[2, 1] - m[1, 2]) ** 2 + (m[0, 2] - m[2, 0]) ** 2 + (m[1, 0] - m[0, 1]) ** 2)
    angle = np.arctan2(sin2, m[0, 0] + m[1, 1] + m[2, 2] - 1.0)
    dt = np.sqrt((t[0] - t_ref[0]) ** 2 + (t[1] - t_ref[1]) ** 2 + (t[2] - t_ref[2]) ** 2)
    return dt + size * angle


@njit
def _track(base, legp, lengths, t_prev, rot_prev, t_cur, rot_cur, extrapolate, max_iter, size):
    """One tracking step: Newton from the pose predicted by the last two samples.

    The prediction assumes constant velocity and angular velocity:
    t = 2 t_k - t_{k-1}, R = (R_k R_{k-1}^T) R_k. Besides saving a Newton step,
    it carries the solution through a singular pose on its own branch, where
    starting from t_k would fall back onto the branch that meets it there.
    Returns t, R, iterations, converged, residual, distance from the
    prediction, cond J and the prediction (t, R).
    """
    t0 = t_cur.copy()
    r0 = rot_cur.copy()
    if extrapolate:
        for i in range(3):
            t0[i] = 2.0 * t_cur[i] - t_prev[i]
            for j in range(3):
                acc = 0.0
                for k in range(3):
                    # (R_k R_{k-1}^T R_k)_ij = sum_k (R_k R_{k-1}^T)_ik (R_k)_kj
                    acc += (rot_cur[i, 0] * rot_prev[k, 0] + rot_cur[i, 1] * rot_prev[k, 1]
                            + rot_cur[i, 2] * rot_prev[k, 2]) * rot_cur[k, j]
                r0[i, j] = acc
    t, rot, it, ok, res = _newton(base, legp, lengths, t0, r0, max_iter, 1e-12)
    jac = np.empty((6, 6))
    _legs(base, legp, t, rot, lengths, jac, np.empty(6))
    return t, rot, it, ok, res, _pose_distance(t, rot, t0, r0, size), condition_number(jac), t0, r0


@njit
def pose_and_twist(base: np.ndarray, legp: np.ndarray, lengths: np.ndarray,
                   rates: np.ndarray, t0: np.ndarray, rot0: np.ndarray,
                   max_iter: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """Tracking FK in one compiled call: Newton on the six leg equations from the
    pose (t0, R0) (the previous estimate), then [v; omega] = J^-1 dL/dt (eq. 13).

    A caller falls back on ``ForwardKinematics.nearest`` when it did not
    converge (a jump, or lengths with no assembly).

    Args:
        base: (6, 3) b_i [m]; legp: (6, 3) each leg's vertex p_k(i) [m].
        lengths: L (6,) [m]; rates: dL/dt (6,) [m/s].
        t0: (3,) [m] and rot0: (3, 3), the pose to start from.
        max_iter: Newton iterations at most.

    Returns:
        (t (3,), R (3, 3), twist (6,) = v, omega in the base frame, converged:
        also the residual down to 1e-9 of the longest leg).
    """
    t, rot, _, ok, res = _newton(base, legp, lengths, t0, rot0, max_iter, 1e-12)
    scale = 0.0
    for i in range(lengths.shape[0]):
        scale = max(scale, abs(lengths[i]))
    ok = ok and res <= 1e-9 * scale
    return t, rot, _twist(base, legp, t, rot, rates), ok


@njit
def _twist(base, legp, t, rot, rates):
    """[v; omega] = J^-1 dL/dt (eq. 13 solved for the twist), base frame."""
    jac = np.empty((6, 6))
    _legs(base, legp, t, rot, np.zeros(6), jac, np.empty(6))
    return solve_linear(jac, rates)
