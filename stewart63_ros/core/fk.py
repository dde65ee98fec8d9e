"""Forward kinematics of the 6-3 platform: the pose from six leg lengths.

Two solvers, one model (eqs. 2-5: S_i = t + R p_k - b_i, L_i = |S_i|):

* ``ForwardKinematics.all_modes`` finds every real assembly mode (up to 16).
  Legs 2k-1 and 2k meet at vertex P_k, so P_k lies on a circle about the base
  line b_{2k-1} b_{2k}; its centre, radius and axis follow from the two
  lengths. With P_k = c_k + r_k (cos phi_k e1_k + sin phi_k e2_k), the three
  side lengths |P_i - P_j| = |p_i - p_j| are three equations, each bilinear
  in (cos phi_i, sin phi_i, 1) x (cos phi_j, sin phi_j, 1). The half-angle
  substitution t_k = tan(phi_k / 2) makes them biquadratic; eliminating t_2
  and then t_3 by resultants leaves one polynomial of degree 16 in t_1
  (Nanua, Waldron & Murthy, "Direct kinematic solution of a Stewart
  platform", IEEE Trans. Robotics and Automation 6(4), 1990). Here that
  polynomial is never expanded symbolically: it is evaluated on the unit
  circle through the root form of the resultants and its coefficients are
  recovered by a discrete Fourier transform (well conditioned); its real
  roots give the circle angles, the three vertices give the pose, and Newton
  on the six leg equations polishes every mode to machine precision. Lengths
  with no real mode raise ``NoAssemblyError``.

* ``FKTracker`` follows a moving platform: Newton on the six leg equations from
  the previous pose, with the analytic Jacobian (row i = [s_i, q_i x s_i], so
  dL = J [dt; dw], paper eq. 13) and the orientation updated on SO(3) by a
  rotation vector. If Newton fails or moves too far, it falls back on
  ``all_modes`` and keeps the mode nearest the previous pose.

Every result carries the 2-norm condition number of J and a ``singular`` flag
when it exceeds a threshold: near a singular pose branches meet, and the
answer, although it fits the lengths, may not be the platform's.

The hot loops are numba kernels written with scalar loops: numba's array
expressions and ``@`` (a BLAS call) are slow at 3x3 and 6x6, and slow to
compile.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from stewart63_ros.core._jit import njit
from stewart63_ros.core.kinematics import leg_kernel
from stewart63_ros.core.linalg import solve_linear
from stewart63_ros.core.node_parameters import DEFAULT_COND_THRESHOLD
from stewart63_ros.core.rotation import (
    euler_from_matrix,
    quaternion_of_matrix,
)

if TYPE_CHECKING:
    from stewart63_ros.core.mechanism import Mechanism

#: Pair k's legs (0-based): legs 2k and 2k+1 meet at vertex k.
PAIRS = ((0, 1), (2, 3), (4, 5))
#: Platform sides (0-based vertices) in the order the equations are chained: 1-2, 2-3, 3-1.
SIDES = ((0, 1), (1, 2), (2, 0))
#: (1 + t^2) [cos phi, sin phi, 1] = HALF_ANGLE [1, t, t^2] with t = tan(phi / 2).
HALF_ANGLE = np.array([[1.0, 0.0, -1.0], [0.0, 2.0, 0.0], [1.0, 0.0, 1.0]])
_SAMPLES = 32          # > 16: the degree-16 resultant is recovered exactly
_SAMPLE_OFFSET = 0.1234   # keep the samples off t = +-1, +-i (special for symmetric designs)


class NoAssemblyError(ValueError):
    """Leg lengths for which the platform cannot be assembled."""


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


# -- numba kernels: Newton on the six leg equations ----------------------------

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


# -- all assembly modes --------------------------------------------------------

@njit
def _hroots(c0, c1, c2):
    """Roots of c2 t^2 + c1 t + c0 as homogeneous pairs t = x / w, stable as c2 -> 0.

    With q = -(c1 + s) / 2, s = +-sqrt(c1^2 - 4 c0 c2) signed so |q| is large,
    the roots are (x, w) = (q, c2) and (c0, q), and
    (x c2 - w q)(x q - w c0) = q (c2 x^2 + c1 x w + c0 w^2): q is the factor
    the resultant's root form divides by. Returns x0, w0, x1, w1, q.
    """
    s = np.sqrt(c1 * c1 - 4.0 * c0 * c2)
    if (np.conj(c1) * s).real < 0.0:
        s = -s
    q = -0.5 * (c1 + s)
    return q, c2, c0, q, q


@njit
def _biquadratic(m, x, w, y, v):
    """[w^2, x w, x^2] m [v^2, y v, y^2]^T: sum m_ab t^a u^b at t = x/w, u = y/v, homogenised."""
    a0, a1, a2 = w * w, x * w, x * x
    b0, b1, b2 = v * v, y * v, y * y
    return (a0 * (m[0, 0] * b0 + m[0, 1] * b1 + m[0, 2] * b2)
            + a1 * (m[1, 0] * b0 + m[1, 1] * b1 + m[1, 2] * b2)
            + a2 * (m[2, 0] * b0 + m[2, 1] * b1 + m[2, 2] * b2))


@njit
def _resultant_coefficients(q12, q23, q31):
    """Coefficients c_0..c_16 of D(t1) = Res_t3(E31, Res_t2(E12, E23)).

    E_ij = [1, t_i, t_i^2] Q_ij [1, t_j, t_j^2]^T. For fixed t1, E12 is a
    quadratic in t2 with roots (x_a : w_a) and E31 a quadratic in t3 with
    roots (y_b : v_b); the resultants in root form give
        D(t1) = prod_{a, b} E23(x_a : w_a, y_b : v_b) / (q12^4 q31^4),
    a polynomial of degree 16 (Nanua et al. 1990), whatever the root order.
    It is sampled at 32 points of the unit circle; the DFT returns its
    coefficients exactly (up to rounding; 32 > 16, so no aliasing).
    """
    coeffs = np.zeros(17)
    for n in range(_SAMPLES):
        angle = 2.0 * np.pi * n / _SAMPLES + _SAMPLE_OFFSET
        z = np.cos(angle) + 1j * np.sin(angle)
        z2 = z * z
        a0 = q12[0, 0] + q12[1, 0] * z + q12[2, 0] * z2   # E12 = a0 + a1 t2 + a2 t2^2
        a1 = q12[0, 1] + q12[1, 1] * z + q12[2, 1] * z2
        a2 = q12[0, 2] + q12[1, 2] * z + q12[2, 2] * z2
        b0 = q31[0, 0] + q31[0, 1] * z + q31[0, 2] * z2   # E31 = b0 + b1 t3 + b2 t3^2
        b1 = q31[1, 0] + q31[1, 1] * z + q31[1, 2] * z2
        b2 = q31[2, 0] + q31[2, 1] * z + q31[2, 2] * z2
        x0, w0, x1, w1, qa = _hroots(a0, a1, a2)
        y0, v0, y1, v1, qb = _hroots(b0, b1, b2)
        value = (_biquadratic(q23, x0, w0, y0, v0) * _biquadratic(q23, x0, w0, y1, v1)
                 * _biquadratic(q23, x1, w1, y0, v0) * _biquadratic(q23, x1, w1, y1, v1))
        value /= (qa * qa) ** 2 * (qb * qb) ** 2 * _SAMPLES
        step = np.cos(angle) - 1j * np.sin(angle)
        for k in range(17):     # DFT, exp(-i k angle) by recurrence
            coeffs[k] += value.real
            value *= step
    return coeffs


@njit
def real_angles(coeffs: np.ndarray) -> np.ndarray:
    """Angles phi = 2 atan(t) of the (nearly) real roots t of sum_k coeffs[k] t^k.

    Roots are the eigenvalues of the companion matrix. A vanishing leading
    coefficient means a root at t = infinity, phi = pi, added by hand. With
    coplanar base points the mirror image through the base plane maps
    t -> -t, so the polynomial is even: then the degree-8 polynomial in t^2 is
    solved instead (an 8x8 eigenproblem costs a quarter of a 16x16 one).
    Acceptance is generous (|Im phi| < 1e-3) and Newton decides later: a
    near-double real root comes out as a complex pair with a small imaginary part.

    Args:
        coeffs: (n + 1,) the polynomial's coefficients, constant term first.

    Returns:
        (m,) the angles phi [rad] of its real roots.
    """
    top = 0.0
    for k in range(17):
        top = max(top, abs(coeffs[k]))
    even = True
    for k in range(1, 17, 2):
        if abs(coeffs[k]) > 1e-10 * top:
            even = False
    step = 2 if even else 1
    size = 16 // step + 1
    poly = np.empty(size)
    for k in range(size):
        poly[k] = coeffs[k * step]
    deg = size - 1
    phis = np.empty(17)
    n = 0
    while deg > 0 and abs(poly[deg]) <= 1e-13 * top:
        deg -= 1
    if deg < size - 1:
        phis[n] = np.pi
        n += 1
    if deg == 0:
        return phis[:n]
    comp = np.zeros((deg, deg), np.complex128)
    for k in range(deg):
        comp[0, k] = -poly[deg - 1 - k] / poly[deg]
    for k in range(1, deg):
        comp[k, k - 1] = 1.0
    roots = np.linalg.eigvals(comp)
    for r in range(deg):
        for sign in range(2 if even else 1):
            t = np.sqrt(roots[r]) if even else roots[r]
            if sign == 1:
                t = -t
            x, y = t.real, t.imag
            den = x * x + (1.0 - y) ** 2
            # Im(2 atan t) = ln(|t + i| / |t - i|), written out for t = x + iy
            if den > 0.0 and abs(0.5 * np.log((x * x + (1.0 + y) ** 2) / den)) < 1e-3:
                phis[n] = np.arctan2(2.0 * x, 1.0 - x * x - y * y)   # Re(2 atan t)
                n += 1
    return phis[:n]


@njit
def _side_residual(m, phi_i, phi_j):
    """[cos, sin, 1](phi_i) M [cos, sin, 1](phi_j)^T = |P_i - P_j|^2 - l_ij^2."""
    ci, si, cj, sj = np.cos(phi_i), np.sin(phi_i), np.cos(phi_j), np.sin(phi_j)
    return (ci * (m[0, 0] * cj + m[0, 1] * sj + m[0, 2])
            + si * (m[1, 0] * cj + m[1, 1] * sj + m[1, 2])
            + m[2, 0] * cj + m[2, 1] * sj + m[2, 2])


@njit
def _angle_candidates(phi1, q12, q13, m23, side23):
    """(n, 3) circle angles: each phi1 with the roots of E12 (in t2) and E31 (in t3).

    q13 = Q31^T, so both are [1, t1, t1^2] q [1, t, t^2]^T.
    Of the four pairs, keep every one that nearly closes side 2-3 (several
    modes may share vertex 1, as in the symmetric default design), and at
    least the best.
    """
    out = np.empty((4 * phi1.size, 3))
    count = 0
    phi2 = np.empty(2)
    phi3 = np.empty(2)
    res = np.empty(4)
    for p in range(phi1.size):
        c, s = np.cos(0.5 * phi1[p]), np.sin(0.5 * phi1[p])
        m0, m1, m2 = c * c, c * s, s * s       # [1, t1, t1^2] homogenised
        ok = True
        for which in range(2):
            q = q12 if which == 0 else q13
            k0 = m0 * q[0, 0] + m1 * q[1, 0] + m2 * q[2, 0]
            k1 = m0 * q[0, 1] + m1 * q[1, 1] + m2 * q[2, 1]
            k2 = m0 * q[0, 2] + m1 * q[1, 2] + m2 * q[2, 2]
            # Real roots of k2 t^2 + k1 t + k0; a slightly negative
            # discriminant (a near-double root) is rounded to zero.
            disc = np.sqrt(max(k1 * k1 - 4.0 * k0 * k2, 0.0))
            big = -0.5 * (k1 + disc if k1 >= 0.0 else k1 - disc)
            if big == 0.0:
                ok = False
                break
            ang = phi2 if which == 0 else phi3
            ang[0] = 2.0 * np.arctan2(big, k2)      # t = big / k2
            ang[1] = 2.0 * np.arctan2(k0, big)      # t = k0 / big
        if not ok:
            continue
        for k in range(4):
            res[k] = abs(_side_residual(m23, phi2[k // 2], phi3[k % 2]))
        best = res.min()
        for k in range(4):
            if res[k] == best or res[k] <= 1e-2 * side23 * side23:
                out[count, 0] = phi1[p]
                out[count, 1] = phi2[k // 2]
                out[count, 2] = phi3[k % 2]
                count += 1
    return out[:count]


@njit
def _circles(base, axis, pair_distance, lengths, tol):
    """Centre (3, 3) and radius (3,) of each vertex's circle, and the first pair
    (0-based) whose legs cannot meet, or -1.

    Pair k: the vertex is L_a from b_a and L_b from b_b, d = |b_b - b_a|
    apart, so it lies x = (L_a^2 - L_b^2 + d^2) / 2d along the axis from b_a,
    on a circle of radius sqrt(L_a^2 - x^2): real iff |L_a - L_b| <= d <= L_a + L_b.
    """
    centre = np.empty((3, 3))
    radius = np.empty(3)
    bad = -1
    for k in range(3):
        la, lb, d = lengths[2 * k], lengths[2 * k + 1], pair_distance[k]
        along = (la * la - lb * lb + d * d) / (2.0 * d)
        r2 = la * la - along * along
        if r2 < -tol and bad < 0:
            bad = k
        radius[k] = np.sqrt(max(r2, 0.0))
        for i in range(3):
            centre[k, i] = base[2 * k, i] + along * axis[k, i]
    return centre, radius, bad


@njit
def _side_matrices(centre, radius, e1, e2, sides):
    """M_ij (3, 3, 3) with |P_i - P_j|^2 - l_ij^2 = [cos_i, sin_i, 1] M_ij [cos_j, sin_j, 1]^T
    for sides 1-2, 2-3, 3-1, and Q_ij = T^T M_ij T / max|.| (half-angle form)."""
    mats = np.zeros((3, 3, 3))
    qs = np.zeros((3, 3, 3))
    for k in range(3):
        i, j = SIDES[k]
        m = mats[k]
        dd = 0.0
        for c in range(3):
            d = centre[i, c] - centre[j, c]
            dd += d * d
            ui = (radius[i] * e1[i, c], radius[i] * e2[i, c])
            uj = (radius[j] * e1[j, c], radius[j] * e2[j, c])
            for a in range(2):
                for b in range(2):
                    m[a, b] -= 2.0 * ui[a] * uj[b]
                m[a, 2] += 2.0 * ui[a] * d
                m[2, a] -= 2.0 * uj[a] * d
        m[2, 2] = dd + radius[i] ** 2 + radius[j] ** 2 - sides[k] ** 2
        top = 0.0
        for a in range(3):
            for b in range(3):
                acc = 0.0
                for c in range(3):
                    for e in range(3):
                        acc += HALF_ANGLE[c, a] * m[c, e] * HALF_ANGLE[e, b]
                qs[k, a, b] = acc
                top = max(top, abs(acc))
        for a in range(3):
            for b in range(3):
                qs[k, a, b] /= top
    return mats, qs


@njit
def _mode_vertices(centre, radius, e1, e2, sides):
    """Candidate vertex triples (n, 3, 3) from the real roots of the degree-16 resultant."""
    mats, qs = _side_matrices(centre, radius, e1, e2, sides)
    phi1 = real_angles(_resultant_coefficients(qs[0], qs[1], qs[2]))
    angles = _angle_candidates(phi1, qs[0], qs[2].T.copy(), mats[1], sides[1])
    out = np.empty((angles.shape[0], 3, 3))
    for n in range(angles.shape[0]):
        for k in range(3):
            c, s = np.cos(angles[n, k]), np.sin(angles[n, k])
            for i in range(3):
                out[n, k, i] = centre[k, i] + radius[k] * (c * e1[k, i] + s * e2[k, i])
    return out


@njit
def _triangle_frame(p):
    """Columns x, y, z: x along p0 -> p1, z normal to the triangle, y = z x x."""
    f = np.empty((3, 3))
    x0, x1, x2 = p[1, 0] - p[0, 0], p[1, 1] - p[0, 1], p[1, 2] - p[0, 2]
    y0, y1, y2 = p[2, 0] - p[0, 0], p[2, 1] - p[0, 1], p[2, 2] - p[0, 2]
    z0, z1, z2 = x1 * y2 - x2 * y1, x2 * y0 - x0 * y2, x0 * y1 - x1 * y0
    nx = np.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
    nz = np.sqrt(z0 * z0 + z1 * z1 + z2 * z2)
    x0, x1, x2 = x0 / nx, x1 / nx, x2 / nx
    z0, z1, z2 = z0 / nz, z1 / nz, z2 / nz
    f[0, 0], f[1, 0], f[2, 0] = x0, x1, x2
    f[0, 2], f[1, 2], f[2, 2] = z0, z1, z2
    f[0, 1], f[1, 1], f[2, 1] = z1 * x2 - z2 * x1, z2 * x0 - z0 * x2, z0 * x1 - z1 * x0
    return f


@njit
def _polish_modes(base, legp, lengths, vertices, plat, size, res_tol):
    """Candidate vertex triples (n, 3, 3) -> the distinct poses fitting the six lengths.

    The start maps the platform triangle's frame onto the candidate's (exact
    when the sides match, a good start otherwise); Newton polishes it; those
    that do not converge, and duplicates, are dropped.
    Returns t (m, 3), R (m, 3, 3), iterations, residual, cond J.
    """
    n = vertices.shape[0]
    ts = np.empty((n, 3))
    rots = np.empty((n, 3, 3))
    iters = np.empty(n, np.int64)
    resid = np.empty(n)
    conds = np.empty(n)
    jac = np.empty((6, 6))
    t0 = np.empty(3)
    rot = np.empty((3, 3))
    fp = _triangle_frame(plat)
    count = 0
    for c in range(n):
        fv = _triangle_frame(vertices[c])
        for i in range(3):
            for j in range(3):
                rot[i, j] = fv[i, 0] * fp[j, 0] + fv[i, 1] * fp[j, 1] + fv[i, 2] * fp[j, 2]
        for i in range(3):   # centroid onto centroid
            t0[i] = 0.0
            for k in range(3):
                t0[i] += (vertices[c, k, i] - (rot[i, 0] * plat[k, 0] + rot[i, 1] * plat[k, 1]
                                               + rot[i, 2] * plat[k, 2])) / 3.0
        if not (np.isfinite(t0[0]) and np.isfinite(rot[0, 0]) and np.isfinite(rot[2, 2])):
            continue
        t, r, it, ok, res = _newton(base, legp, lengths, t0, rot, 30, 1e-12)
        if not ok or res > res_tol:
            continue
        new = True
        for k in range(count):
            if _pose_distance(t, r, ts[k], rots[k], size) < 1e-7 * max(size, 1.0):
                new = False
                break
        if new:
            _legs(base, legp, t, r, lengths, jac, np.empty(6))
            conds[count] = condition_number(jac)
            for i in range(3):
                ts[count, i] = t[i]
                for j in range(3):
                    rots[count, i, j] = r[i, j]
            iters[count] = it
            resid[count] = res
            count += 1
    return ts[:count], rots[:count], iters[:count], resid[:count], conds[:count]


class ForwardKinematics:
    """Forward kinematics of one mechanism; constants gathered once here.

    Args:
        mech: the mechanism.
        cond_threshold: a pose whose Jacobian's condition number exceeds this
            is flagged ``singular``.
        start: (position (3,) [m], rotation (3, 3)) the pose modes are ordered
            by nearness to (``all_modes``), a run's start (``Setup.task``);
            None: the machine's ``Mechanism.neutral_pose``.
    """

    def __init__(self, mech: Mechanism, cond_threshold: float = DEFAULT_COND_THRESHOLD,
                 start: tuple[ArrayLike, ArrayLike] | None = None) -> None:
        self.mech = mech
        self.cond_threshold = float(cond_threshold)
        self.base = _arr(mech.base_points)
        self.plat = _arr(mech.platform_points)
        self.legp = _arr(mech.leg_platform_points)
        # Poses are compared by |dt| + size * (rotation angle).
        self.size = float(np.max(np.linalg.norm(self.plat - self.plat.mean(0), axis=1)))
        self.scale = float(max(self.size, np.ptp(self.base, axis=0).max()))
        self.sides = np.array([np.linalg.norm(self.plat[i] - self.plat[j]) for i, j in SIDES])
        # Circle axes u_k and reference directions e1_k, e2_k. e2_k is the
        # base-plane normal made orthogonal to u_k: for coplanar base points
        # the mirror image through the base plane is then phi -> -phi, and
        # the usual modes (above or below the base) sit near t = +-1, where
        # the half-angle polynomial is best conditioned.
        normal = np.linalg.svd(self.base - self.base.mean(0))[2][2]
        normal = normal if normal[2] >= 0 else -normal
        axis, e1, e2 = [], [], []
        for a, b in PAIRS:
            u = self.base[b] - self.base[a]
            u = u / np.linalg.norm(u)
            v = normal - (normal @ u) * u
            if np.linalg.norm(v) < 1e-6:   # pair line along the normal: any perpendicular
                v = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
            v = v / np.linalg.norm(v)
            axis.append(u)
            e1.append(np.cross(v, u))
            e2.append(v)
        self.axis, self.e1, self.e2 = np.array(axis), np.array(e1), np.array(e2)
        self.pair_distance = np.linalg.norm(self.base[1::2] - self.base[0::2], axis=1)
        if start is None:
            start = mech.neutral_pose()
        self.reference = (_arr(start[0]), _arr(start[1]))

    # -- small helpers --------------------------------------------------------
    def check_lengths(self, lengths: ArrayLike) -> np.ndarray:
        """Six finite positive leg lengths as a float array (6,).

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

    def jacobian(self, position: ArrayLike, rotation: ArrayLike) -> np.ndarray:
        """6x6 J, row i = [s_i, q_i x s_i]: dL/dt = J [v; omega].

        Args:
            position: t (3,) [m]; rotation: R (3, 3).

        Returns:
            (6, 6) J.
        """
        jac = np.empty((6, 6))
        _legs(self.base, self.legp, _arr(position), _arr(rotation), np.zeros(6), jac,
              np.empty(6))
        return jac

    def condition(self, position: ArrayLike, rotation: ArrayLike) -> float:
        """2-norm condition number of the Jacobian at the pose t (3,), R (3, 3)."""
        return float(condition_number(self.jacobian(position, rotation)))

    def twist(self, position: ArrayLike, rotation: ArrayLike,
              rates: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """The twist from leg rates: J [v; omega] = dL/dt (eq. 13).

        Args:
            position: t (3,) [m]; rotation: R (3, 3); rates: dL/dt (6,) [m/s].

        Returns:
            (v (3,) [m/s], omega (3,) [rad/s]), base frame.
        """
        x = _twist(self.base, self.legp, _arr(position), _arr(rotation), _arr(rates))
        return x[:3], x[3:]

    def distance(self, position: ArrayLike, rotation: ArrayLike, ref_position: ArrayLike,
                 ref_rotation: ArrayLike) -> float:
        """|dt| + size * angle(R_ref^T R) [m]: the angle weighted by the platform radius.

        Args:
            position, ref_position: (3,) [m]; rotation, ref_rotation: (3, 3).
        """
        return _pose_distance(_arr(position), _arr(rotation), _arr(ref_position),
                              _arr(ref_rotation), self.size)

    # -- all assembly modes ---------------------------------------------------
    def circles(self, lengths: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Where each vertex can be: the circle its leg pair leaves it.

        Args:
            lengths: L (6,) [m].

        Returns:
            (centre (3, 3) [m], radius (3,) [m]), one row per vertex.

        Raises:
            NoAssemblyError: a leg pair cannot meet.
        """
        return self._circles(self.check_lengths(lengths))

    def _circles(self, lengths):
        centre, radius, bad = _circles(self.base, self.axis, self.pair_distance, lengths,
                                       1e-12 * self.scale ** 2)
        if bad >= 0:
            a, b = PAIRS[bad]
            la, lb, d = lengths[a], lengths[b], self.pair_distance[bad]
            if abs(la - lb) > d:
                why = '|L%d - L%d| = %.6g m exceeds' % (a + 1, b + 1, abs(la - lb))
            else:
                why = 'L%d + L%d = %.6g m is shorter than' % (a + 1, b + 1, la + lb)
            raise NoAssemblyError('legs %d and %d cannot meet: %s their base distance '
                                  '|b%d - b%d| = %.6g m' % (a + 1, b + 1, why, a + 1, b + 1, d))
        return centre, radius

    def all_modes(self, lengths: ArrayLike,
                  reference: tuple[ArrayLike, ArrayLike] | None = None) -> list[FKResult]:
        """Every real assembly mode, nearest the reference pose first.

        Args:
            lengths: L (6,) [m].
            reference: (position (3,), rotation (3, 3)); default the
                mechanism's initial pose.

        Returns:
            The modes, each an ``FKResult`` (``fallback`` True).

        Raises:
            NoAssemblyError: a leg pair cannot meet, or no mode exists.
        """
        lengths = self.check_lengths(lengths)
        centre, radius = self._circles(lengths)
        candidates = _mode_vertices(centre, radius, self.e1, self.e2, self.sides)
        t, rot, iters, res, cond = _polish_modes(self.base, self.legp, lengths, candidates,
                                                 self.plat, self.size, 1e-9 * self.scale)
        if not len(t):
            raise NoAssemblyError('no assembly mode: the six leg lengths %s m do not close '
                                  'the platform triangle' % np.round(lengths, 6).tolist())
        ref_t, ref_r = self.reference if reference is None else (
            _arr(reference[0]), _arr(reference[1]))
        order = sorted(range(len(t)),
                       key=lambda k: _pose_distance(t[k], rot[k], ref_t, ref_r, self.size))
        return [FKResult(t[k], rot[k], cond[k], cond[k] > self.cond_threshold, res[k],
                         iters[k], True) for k in order]

    def nearest(self, lengths: ArrayLike, position: ArrayLike,
                rotation: ArrayLike) -> FKResult:
        """The assembly mode nearest the pose t (3,), R (3, 3), for L (6,) [m].

        Raises:
            NoAssemblyError: as ``all_modes``.
        """
        return self.all_modes(lengths, (position, rotation))[0]


class FKTracker:
    """Forward kinematics of a moving platform, sample after sample.

    Newton from the pose extrapolated from the last two samples (two or three
    steps at a 1 kHz sample rate); when it fails, or lands more than
    ``max_move`` (|dt| + platform radius x angle, metres) from the
    prediction, the all-modes solver picks the mode nearest the prediction.
    Starts at ``position``/``rotation``, by default the mechanism's initial
    pose. Results flagged ``singular`` lie where branches meet: the lengths
    alone cannot tell which one the platform took.

    Args:
        mech_or_fk: the mechanism, or a ``ForwardKinematics`` to share.
        position: (3,) [m] and rotation: (3, 3), the start; default the
            ``ForwardKinematics``'s reference pose (its ``start``).
        cond_threshold: overrides the ``ForwardKinematics``'s.
        max_move: the largest jump from the prediction Newton may make [m].
        max_iter: Newton iterations at most per sample.
        extrapolate: predict from the last two samples (else: the last one).
    """

    def __init__(self, mech_or_fk: Mechanism | ForwardKinematics,
                 position: ArrayLike | None = None, rotation: ArrayLike | None = None,
                 cond_threshold: float | None = None, max_move: float = 0.05,
                 max_iter: int = 12, extrapolate: bool = True) -> None:
        if isinstance(mech_or_fk, ForwardKinematics):
            fk = mech_or_fk
        else:       # the start is the reference of its modes too
            fk = ForwardKinematics(mech_or_fk, start=None if position is None or rotation is None
                                   else (position, rotation))
        if cond_threshold is not None:
            fk.cond_threshold = float(cond_threshold)
        self.fk = fk
        self.max_move = float(max_move)
        self.max_iter = int(max_iter)
        self.extrapolate = bool(extrapolate)
        self.reset(fk.reference[0] if position is None else position,
                   fk.reference[1] if rotation is None else rotation)

    def reset(self, position: ArrayLike, rotation: ArrayLike) -> None:
        """Continue from the pose t (3,), R (3, 3), at rest (a known start, or
        after a gap in the data)."""
        self.position = _arr(position)
        self.rotation = _arr(rotation)
        self._prev = (self.position, self.rotation)
        self._moving = False

    def solve(self, lengths: ArrayLike, rates: ArrayLike | None = None) -> FKResult:
        """Pose (and twist, if leg rates are given) for one sample of leg lengths.

        Args:
            lengths: L (6,) [m]; rates: dL/dt (6,) [m/s], or None.

        Returns:
            The pose, with ``velocity`` and ``omega`` when ``rates`` was given.

        Raises:
            ValueError: not six lengths.
            NoAssemblyError: the lengths admit no assembly.
        """
        fk = self.fk
        lengths = _arr(lengths)
        if lengths.shape != (6,):
            fk.check_lengths(lengths)     # raises with a clear message
        # NaN or non-positive lengths fail Newton; all_modes then says why.
        t, rot, it, ok, res, move, cond, t0, r0 = _track(
            fk.base, fk.legp, lengths, self._prev[0], self._prev[1], self.position,
            self.rotation, self._moving and self.extrapolate, self.max_iter, fk.size)
        if ok and res <= 1e-9 * fk.scale and move <= self.max_move:
            result = FKResult(t, rot, cond, cond > fk.cond_threshold, res, it)
        else:
            result = fk.nearest(lengths, t0, r0)
        if rates is not None:
            result.velocity, result.omega = fk.twist(result.position, result.rotation, rates)
        self._prev = (self.position, self.rotation)
        self.position, self.rotation = result.position, result.rotation
        self._moving = not result.fallback
        return result

