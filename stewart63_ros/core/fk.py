"""Forward kinematics of the 6-3 platform: the pose from six leg lengths.

Two solvers, one model (CONTRACT section 4: S_i = t + R p_k - b_i, L_i = |S_i|):

* ``ForwardKinematics.all_modes`` finds every real assembly mode (up to 16).
  Legs 2k-1 and 2k meet at vertex P_k, so P_k lies on a circle about the base
  line b_{2k-1} b_{2k}; its centre, radius and axis follow from the two
  lengths. With P_k = c_k + r_k (cos phi_k e1_k + sin phi_k e2_k), the three
  side lengths |P_i - P_j| = |p_i - p_j| are three equations, each bilinear
  in (cos phi_i, sin phi_i, 1) x (cos phi_j, sin phi_j, 1). The half-angle
  substitution t_k = tan(phi_k / 2) makes them biquadratic; eliminating t_2
  and then t_3 by resultants leaves one polynomial of degree 16 in t_1
  (Nanua, Waldron & Murthy, "Direct kinematic solution of a Stewart platform",
  IEEE Trans. Robotics and Automation 6(4), 1990). Here the polynomial is
  never expanded symbolically: it is evaluated on the unit circle through the
  root form of the resultant and interpolated by an FFT (well conditioned),
  then its real roots give the circle angles, the three vertices give the
  pose, and Newton on the six leg equations polishes every mode to machine
  precision. Lengths with no real mode raise ``NoAssemblyError``.

* ``FKTracker`` follows a moving platform: Newton on the six leg equations from
  the previous pose, with the analytic Jacobian (row i = [s_i, q_i x s_i], so
  dL = J [dt; dw]) and orientation updated on SO(3) by a rotation vector.
  If Newton fails or moves too far, it falls back on ``all_modes`` and keeps
  the mode nearest the previous pose.

Every result carries the 2-norm condition number of J and a ``singular`` flag
when it exceeds a threshold: near a singular pose branches meet, and the
answer, although it fits the lengths, may not be the platform's.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from stewart63_ros.core.rotation import euler_from_matrix, rotation_from_euler

#: Flag a pose whose 6x6 Jacobian (metres; rotation columns carry q x s in m)
#: has a 2-norm condition number above this. The default workspace of the
#: packaged mechanism stays between 3 and 6 (5000 random poses); a singular
#: pose sends it to infinity. At 100, a length error dL moves the pose by up to
#: ~100 dL (metres and radians x platform size): an estimate no longer to trust.
DEFAULT_COND_THRESHOLD = 100.0
#: Pair k's legs (0-based): legs 2k and 2k+1 meet at vertex k.
PAIRS = ((0, 1), (2, 3), (4, 5))
#: Platform sides (i, j), in the order the equations are chained 1-2, 2-3, 3-1.
SIDES = ((0, 1), (1, 2), (2, 0))


class NoAssemblyError(ValueError):
    """Leg lengths for which the platform cannot be assembled."""


class FKResult:
    """One pose from the leg lengths.

    position (3,) and rotation (3, 3) (platform -> base); ``condition`` the
    2-norm condition number of the Jacobian there, ``singular`` whether it is
    above the threshold; ``residual`` max |L_i(pose) - L_i| [m]; ``iterations``
    of Newton; ``fallback`` True when the all-modes solver chose the branch.
    """

    __slots__ = ('position', 'rotation', 'condition', 'singular', 'residual',
                 'iterations', 'fallback', 'velocity', 'omega')

    def __init__(self, position, rotation, condition, singular, residual, iterations=0,
                 fallback=False, velocity=None, omega=None):
        self.position = position
        self.rotation = rotation
        self.condition = condition
        self.singular = singular
        self.residual = residual
        self.iterations = iterations
        self.fallback = fallback
        self.velocity = velocity
        self.omega = omega

    @property
    def theta(self) -> np.ndarray:
        """(theta_x, theta_y, theta_z), R = Rz Ry Rx (CONTRACT section 4)."""
        return euler_from_matrix(self.rotation)

    @property
    def quaternion(self) -> np.ndarray:
        """(x, y, z, w), w >= 0."""
        return _quaternion(self.rotation)

    def __repr__(self):
        return ('FKResult(position=%s, theta=%s, condition=%.3g%s)'
                % (np.round(self.position, 6).tolist(), np.round(self.theta, 6).tolist(),
                   self.condition, ', SINGULAR' if self.singular else ''))


def _arr(x) -> np.ndarray:
    """A writable C-contiguous float64 copy (one numba signature for every caller)."""
    return np.array(x, dtype=np.float64, order='C')


def _quaternion(rot):
    from scipy.spatial.transform import Rotation
    q = Rotation.from_matrix(rot).as_quat()
    return -q if q[3] < 0 else q


# -- numba kernels: Newton on the six leg equations ----------------------------

@njit(cache=True)
def _rodrigues_left(w, rot):
    """exp([w]x) @ rot: a base-frame rotation vector applied to rot."""
    th2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    if th2 < 1e-16:   # series: sin(t)/t ~ 1 - t^2/6, (1 - cos t)/t^2 ~ 1/2 - t^2/24
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
    for i in range(3):   # a hand loop: numba's @ calls BLAS, slow for 3x3
        for j in range(3):
            out[i, j] = e[i, 0] * rot[0, j] + e[i, 1] * rot[1, j] + e[i, 2] * rot[2, j]
    return out


@njit(cache=True)
def _legs(base, legp, t, rot, lengths, jac, res):
    """Fill jac (rows [s_i, q_i x s_i]) and res = lengths - L(pose); return max |res|."""
    worst = 0.0
    for i in range(base.shape[0]):
        q0 = rot[0, 0] * legp[i, 0] + rot[0, 1] * legp[i, 1] + rot[0, 2] * legp[i, 2]
        q1 = rot[1, 0] * legp[i, 0] + rot[1, 1] * legp[i, 1] + rot[1, 2] * legp[i, 2]
        q2 = rot[2, 0] * legp[i, 0] + rot[2, 1] * legp[i, 1] + rot[2, 2] * legp[i, 2]
        s0, s1, s2 = q0 + t[0] - base[i, 0], q1 + t[1] - base[i, 1], q2 + t[2] - base[i, 2]
        length = np.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
        s0, s1, s2 = s0 / length, s1 / length, s2 / length
        jac[i, 0], jac[i, 1], jac[i, 2] = s0, s1, s2
        jac[i, 3] = q1 * s2 - q2 * s1
        jac[i, 4] = q2 * s0 - q0 * s2
        jac[i, 5] = q0 * s1 - q1 * s0
        res[i] = lengths[i] - length
        worst = max(worst, abs(res[i]))
    return worst


@njit(cache=True)
def _solve6(a, b):
    """Gaussian elimination with partial pivoting on copies; NaN when singular."""
    a = a.copy()
    x = b.copy()
    n = b.shape[0]      # not a constant: a fully unrolled 6x6 elimination compiles for ages
    for k in range(n):
        p = k
        for i in range(k + 1, n):
            if abs(a[i, k]) > abs(a[p, k]):
                p = i
        if a[p, k] == 0.0:
            x[:] = np.nan
            return x
        if p != k:
            for j in range(n):
                a[k, j], a[p, j] = a[p, j], a[k, j]
            x[k], x[p] = x[p], x[k]
        for i in range(k + 1, n):
            f = a[i, k] / a[k, k]
            for j in range(k + 1, n):
                a[i, j] -= f * a[k, j]
            x[i] -= f * x[k]
    for i in range(n - 1, -1, -1):
        v = x[i]
        for j in range(i + 1, n):
            v -= a[i, j] * x[j]
        x[i] = v / a[i, i]
    return x


@njit(cache=True)
def _cond(jac):
    """2-norm condition number sigma_max / sigma_min of a square matrix.

    One-sided Jacobi (Hestenes 1958): rotate column pairs until all columns
    are orthogonal; the column norms are then the singular values, small ones
    to full relative accuracy. A LAPACK call costs ~20 us here, this ~2 us.
    """
    a = jac.copy()
    n = a.shape[1]
    for _ in range(30):
        off = 0.0
        for i in range(n - 1):
            for j in range(i + 1, n):
                alpha = beta = gamma = 0.0
                for k in range(a.shape[0]):
                    alpha += a[k, i] * a[k, i]
                    beta += a[k, j] * a[k, j]
                    gamma += a[k, i] * a[k, j]
                if gamma == 0.0:
                    continue
                off = max(off, abs(gamma) / np.sqrt(alpha * beta))
                zeta = (beta - alpha) / (2.0 * gamma)
                tan = np.sign(zeta) / (abs(zeta) + np.sqrt(1.0 + zeta * zeta)) if zeta != 0 else 1.0
                cos = 1.0 / np.sqrt(1.0 + tan * tan)
                sin = cos * tan
                for k in range(a.shape[0]):
                    ai, aj = a[k, i], a[k, j]
                    a[k, i] = cos * ai - sin * aj
                    a[k, j] = sin * ai + cos * aj
        if off < 1e-15:
            break
    smax, smin = 0.0, np.inf
    for j in range(n):
        norm = 0.0
        for k in range(a.shape[0]):
            norm += a[k, j] * a[k, j]
        smax, smin = max(smax, norm), min(smin, norm)
    return np.sqrt(smax / smin) if smin > 0 else np.inf


@njit(cache=True)
def _newton(base, legp, lengths, t0, rot0, max_iter, step_tol):
    """Newton on L(t, R) = lengths; returns t, R, iterations, converged, residual.

    Step: J [dt; dw] = lengths - L, t += dt, R = exp([dw]x) R (eq. 13 with the
    twist replaced by a small displacement). Converged when the step is below
    step_tol: quadratic convergence then leaves an error of order step_tol^2.
    """
    t = t0.copy()
    rot = rot0.copy()
    jac = np.empty((6, 6))
    res = np.empty(6)
    ok = False
    it = 0
    while it < max_iter:
        it += 1
        _legs(base, legp, t, rot, lengths, jac, res)
        d = _solve6(jac, res)
        size = 0.0
        for k in range(d.shape[0]):
            size = max(size, abs(d[k]))
        if not np.isfinite(size) or size > 1e3:
            break
        t += d[:3]
        rot = _rodrigues_left(d[3:], rot)
        if size < step_tol:
            ok = True
            break
    # Re-orthonormalise (Gram-Schmidt on the columns): many tracked samples
    # would otherwise let rounding drift accumulate.
    c0 = rot[:, 0] / np.sqrt(rot[0, 0] ** 2 + rot[1, 0] ** 2 + rot[2, 0] ** 2)
    c1 = rot[:, 1] - (c0[0] * rot[0, 1] + c0[1] * rot[1, 1] + c0[2] * rot[2, 1]) * c0
    c1 /= np.sqrt(c1[0] ** 2 + c1[1] ** 2 + c1[2] ** 2)
    rot[:, 0] = c0
    rot[:, 1] = c1
    rot[0, 2] = c0[1] * c1[2] - c0[2] * c1[1]
    rot[1, 2] = c0[2] * c1[0] - c0[0] * c1[2]
    rot[2, 2] = c0[0] * c1[1] - c0[1] * c1[0]
    worst = _legs(base, legp, t, rot, lengths, jac, res)
    return t, rot, it, ok, worst


@njit(cache=True)
def _track(base, legp, lengths, t0, rot0, max_iter, size):
    """One tracking step: Newton from the previous pose, then its move and the condition."""
    t, rot, it, ok, res = _newton(base, legp, lengths, t0, rot0, max_iter, 1e-12)
    jac = np.empty((6, 6))
    _legs(base, legp, t, rot, lengths, jac, np.empty(6))
    return t, rot, it, ok, res, _pose_distance(t, rot, t0, rot0, size), _cond(jac)


@njit(cache=True)
def _twist(base, legp, t, rot, rates):
    """[v; omega] = J^-1 dL/dt (eq. 13 inverted), base frame."""
    jac = np.empty((6, 6))
    _legs(base, legp, t, rot, np.zeros(6), jac, np.empty(6))
    return _solve6(jac, rates)


@njit(cache=True)
def _pose_distance(t, rot, t_ref, rot_ref, size):
    """|t - t_ref| + size * angle(R_ref^T R): one length for position and orientation."""
    # The angle from both the sine and the cosine of R_ref^T R: accurate at
    # small and large angles alike.
    m = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            m[i, j] = rot_ref[0, i] * rot[0, j] + rot_ref[1, i] * rot[1, j] + rot_ref[2, i] * rot[2, j]
    sin2 = np.sqrt((m[2, 1] - m[1, 2]) ** 2 + (m[0, 2] - m[2, 0]) ** 2 + (m[1, 0] - m[0, 1]) ** 2)
    angle = np.arctan2(sin2, m[0, 0] + m[1, 1] + m[2, 2] - 1.0)
    dt = np.sqrt((t[0] - t_ref[0]) ** 2 + (t[1] - t_ref[1]) ** 2 + (t[2] - t_ref[2]) ** 2)
    return dt + size * angle


@njit(cache=True)
def _triangle_frame(p):
    """Columns: x along p0->p1, z normal to the triangle, y = z x x."""
    f = np.empty((3, 3))
    x = p[1] - p[0]
    y = p[2] - p[0]
    z = np.array([x[1] * y[2] - x[2] * y[1], x[2] * y[0] - x[0] * y[2], x[0] * y[1] - x[1] * y[0]])
    x = x / np.sqrt(x[0] ** 2 + x[1] ** 2 + x[2] ** 2)
    z = z / np.sqrt(z[0] ** 2 + z[1] ** 2 + z[2] ** 2)
    f[:, 0] = x
    f[:, 2] = z
    f[0, 1] = z[1] * x[2] - z[2] * x[1]
    f[1, 1] = z[2] * x[0] - z[0] * x[2]
    f[2, 1] = z[0] * x[1] - z[1] * x[0]
    return f


@njit(cache=True)
def _polish_modes(base, legp, lengths, vertices, plat, size, res_tol):
    """Candidate vertex triples -> distinct poses satisfying the six leg equations.

    The rotation maps the platform triangle's frame onto the candidate's
    (exact when the side lengths match, a good start otherwise); Newton then
    polishes it; non-converged candidates and duplicates are dropped.
    """
    n = vertices.shape[0]
    ts = np.empty((n, 3))
    rots = np.empty((n, 3, 3))
    iters = np.empty(n, np.int64)
    resid = np.empty(n)
    conds = np.empty(n)
    fp = _triangle_frame(plat)
    cp = (plat[0] + plat[1] + plat[2]) / 3.0
    count = 0
    for c in range(n):
        fv = _triangle_frame(vertices[c])
        rot = np.zeros((3, 3))
        for i in range(3):
            for j in range(3):
                rot[i, j] = fv[i, 0] * fp[j, 0] + fv[i, 1] * fp[j, 1] + fv[i, 2] * fp[j, 2]
        if not np.all(np.isfinite(rot)):
            continue
        cv = (vertices[c, 0] + vertices[c, 1] + vertices[c, 2]) / 3.0
        t0 = np.empty(3)
        for i in range(3):
            t0[i] = cv[i] - (rot[i, 0] * cp[0] + rot[i, 1] * cp[1] + rot[i, 2] * cp[2])
        t, r, it, ok, res = _newton(base, legp, lengths, t0, rot, 30, 1e-12)
        if not ok or res > res_tol:
            continue
        new = True
        for k in range(count):
            if _pose_distance(t, r, ts[k], rots[k], size) < 1e-7 * max(size, 1.0):
                new = False
                break
        if new:
            jac = np.empty((6, 6))
            _legs(base, legp, t, r, lengths, jac, np.empty(6))
            conds[count] = _cond(jac)
            ts[count] = t
            rots[count] = r
            iters[count] = it
            resid[count] = res
            count += 1
    return ts[:count], rots[:count], iters[:count], resid[:count], conds[:count]


# -- all assembly modes --------------------------------------------------------

@njit(cache=True)
def _hroots(c0, c1, c2):
    """Roots of c2 t^2 + c1 t + c0 as homogeneous pairs t = x / w, stable as c2 -> 0.

    With q = -(c1 + s) / 2, s = +-sqrt(c1^2 - 4 c0 c2) signed so |q| is large,
    the roots are (x, w) = (q, c2) and (c0, q), and
    (x c2 - w q)(x q - w c0) = q (c2 x^2 + c1 x w + c0 w^2): q is the factor
    the resultant's root form must divide by. Returns x0, w0, x1, w1, q.
    """
    s = np.sqrt(c1 * c1 - 4.0 * c0 * c2)
    if (np.conj(c1) * s).real < 0.0:
        s = -s
    q = -0.5 * (c1 + s)
    return q, c2, c0, q, q


@njit(cache=True)
def _bilinear(m, x, w, y, v):
    """[w^2, x w, x^2] m [v^2, y v, y^2]^T: a biquadratic at homogeneous (x:w), (y:v)."""
    a = (w * w, x * w, x * x)
    b = (v * v, y * v, y * y)
    out = 0.0 * x
    for i in range(3):
        for j in range(3):
            out += a[i] * m[i, j] * b[j]
    return out


@njit(cache=True)
def _circle_residual(m, phi_i, phi_j):
    """[cos, sin, 1](phi_i) M [cos, sin, 1](phi_j)^T = |P_i - P_j|^2 - l_ij^2."""
    a = (np.cos(phi_i), np.sin(phi_i), 1.0)
    b = (np.cos(phi_j), np.sin(phi_j), 1.0)
    out = 0.0
    for i in range(3):
        for j in range(3):
            out += a[i] * m[i, j] * b[j]
    return out


@njit(cache=True)
def _real_angles(coeffs):
    """Circle angles phi = 2 atan(t) of the (nearly) real roots t of sum_k coeffs[k] t^k.

    Roots are the eigenvalues of the companion matrix. A vanishing leading
    coefficient means a root at t = infinity, phi = pi: it is added by hand.
    With coplanar base points the mirror image through the base plane maps
    t -> -t, so the polynomial is even: then the degree-8 polynomial in t^2
    is solved instead (an 8x8 eigenproblem costs a quarter of a 16x16 one).
    Acceptance is generous (|Im phi| < 1e-3); Newton decides later. A near
    double real root comes out as a complex pair with a small imaginary part.
    """
    top = np.max(np.abs(coeffs))
    even = True
    for k in range(1, 17, 2):
        even = even and abs(coeffs[k]) <= 1e-10 * top
    step = 2 if even else 1
    poly = coeffs[::step].copy()
    deg = poly.size - 1
    phis = np.empty(17)
    n = 0
    while deg > 0 and abs(poly[deg]) <= 1e-13 * top:
        deg -= 1
    if deg < poly.size - 1:
        phis[n] = np.pi
        n += 1
    if deg == 0:
        return phis[:n]
    comp = np.zeros((deg, deg), np.complex128)
    for k in range(deg):
        comp[0, k] = -poly[deg - 1 - k] / poly[deg]
    for k in range(1, deg):
        comp[k, k - 1] = 1.0
    for root in np.linalg.eigvals(comp):
        for sign in (1.0, -1.0):
            t = np.sqrt(root) * sign if even else root
            x, y = t.real, t.imag
            den = x * x + (1.0 - y) ** 2
            if den > 0.0 and abs(0.5 * np.log((x * x + (1.0 + y) ** 2) / den)) < 1e-3:
                phis[n] = np.arctan2(2.0 * x, 1.0 - x * x - y * y)   # 2 atan(t)
                n += 1
            if not even:
                break
    return phis[:n]


@njit(cache=True)
def _mode_candidates(centre, radius, e1, e2, sides):
    """Circle angles (n, 3) of candidate modes: the real roots of the degree-16 resultant.

    M_ij: |P_i - P_j|^2 - l_ij^2 = [cos_i, sin_i, 1] M_ij [cos_j, sin_j, 1]^T
    with P_k = c_k + r_k (cos phi_k e1_k + sin phi_k e2_k). The half-angle
    substitution (1 + t^2)[cos, sin, 1] = T [1, t, t^2] gives Q = T^T M T,
    biquadratic equations E12(t1, t2), E23(t2, t3), E31(t3, t1). For fixed
    t1, E12 is a quadratic in t2 with roots (x_a : w_a) and E31 one in t3 with
    roots (y_b : v_b), so
        D(t1) = Res_t3(E31, Res_t2(E12, E23)) = prod_ab E23(x_a:w_a, y_b:v_b) / (q12^4 q31^4),
    a polynomial of degree 16 (Nanua, Waldron & Murthy 1990). It is sampled
    on the unit circle, its coefficients recovered by a DFT (exact for
    32 > 16 samples, and well conditioned), and its roots taken as the
    eigenvalues of the companion matrix.
    """
    half = np.array([[1.0, 0.0, -1.0], [0.0, 2.0, 0.0], [1.0, 0.0, 1.0]])
    mats = np.empty((3, 3, 3))
    qs = np.empty((3, 3, 3))
    for k in range(3):
        i, j = k, (k + 1) % 3          # sides 1-2, 2-3, 3-1
        d = centre[i] - centre[j]
        ui = np.empty((2, 3))
        uj = np.empty((2, 3))
        ui[0], ui[1] = radius[i] * e1[i], radius[i] * e2[i]
        uj[0], uj[1] = radius[j] * e1[j], radius[j] * e2[j]
        m = mats[k]
        for a in range(2):
            for b in range(2):
                m[a, b] = -2.0 * np.sum(ui[a] * uj[b])
            m[a, 2] = 2.0 * np.sum(ui[a] * d)
            m[2, a] = -2.0 * np.sum(uj[a] * d)
        m[2, 2] = np.sum(d * d) + radius[i] ** 2 + radius[j] ** 2 - sides[k] ** 2
        q = half.T @ m @ half
        qs[k] = q / np.max(np.abs(q))
    q12, q23, q31 = qs[0], qs[1], qs[2]

    # D at N points of the unit circle, offset from +-1, +-i (special for
    # symmetric mechanisms).
    n_samp = 32
    offset = 0.1234
    dvals = np.empty(n_samp, np.complex128)
    for n in range(n_samp):
        z = np.exp(1j * (2.0 * np.pi * n / n_samp + offset))
        m1 = (1.0 + 0j, z, z * z)
        al = [0j, 0j, 0j]
        be = [0j, 0j, 0j]
        for a in range(3):
            for b in range(3):
                al[b] += m1[a] * q12[a, b]
                be[a] += q31[a, b] * m1[b]
        x0, w0, x1, w1, qa = _hroots(al[0], al[1], al[2])
        y0, v0, y1, v1, qb = _hroots(be[0], be[1], be[2])
        prod = (_bilinear(q23, x0, w0, y0, v0) * _bilinear(q23, x0, w0, y1, v1)
                * _bilinear(q23, x1, w1, y0, v0) * _bilinear(q23, x1, w1, y1, v1))
        dvals[n] = prod / (qa ** 4 * qb ** 4)
    coeffs = np.zeros(17)
    for n in range(n_samp):
        step = np.exp(-1j * (2.0 * np.pi * n / n_samp + offset))
        power = dvals[n] / n_samp
        for k in range(17):          # DFT: exp(-i k theta_n) by recurrence
            coeffs[k] += power.real
            power *= step

    phi1 = _real_angles(coeffs)
    n_phi = phi1.size

    # For each phi1: both roots of E12 in t2 and of E31 in t3; keep the
    # combinations that close side 2-3 (all near ones: several modes may share
    # vertex 1).
    out = np.empty((4 * n_phi, 3))
    count = 0
    for p in range(n_phi):
        c, s = np.cos(0.5 * phi1[p]), np.sin(0.5 * phi1[p])
        m1 = (c * c, c * s, s * s)
        al = np.zeros(3)
        be = np.zeros(3)
        for a in range(3):
            for b in range(3):
                al[b] += m1[a] * q12[a, b]
                be[a] += q31[a, b] * m1[b]
        phi2 = np.empty(2)
        phi3 = np.empty(2)
        ok = True
        for poly, ang in ((al, phi2), (be, phi3)):
            disc = max(poly[1] * poly[1] - 4.0 * poly[0] * poly[2], 0.0)   # near-real: real part
            sq = np.sqrt(disc) if poly[1] >= 0 else -np.sqrt(disc)
            q = -0.5 * (poly[1] + sq)
            if q == 0.0:
                ok = False
                break
            ang[0] = 2.0 * np.arctan2(q, poly[2])
            ang[1] = 2.0 * np.arctan2(poly[0], q)
        if not ok:
            continue
        res = np.empty(4)
        for k in range(4):
            res[k] = abs(_circle_residual(mats[1], phi2[k // 2], phi3[k % 2]))
        best = np.min(res)
        for k in range(4):
            if res[k] == best or res[k] <= 1e-2 * sides[1] ** 2:
                out[count, 0] = phi1[p]
                out[count, 1] = phi2[k // 2]
                out[count, 2] = phi3[k % 2]
                count += 1
    return out[:count]


class ForwardKinematics:
    """Forward kinematics of one mechanism; constants gathered once here."""

    def __init__(self, mech, cond_threshold: float = DEFAULT_COND_THRESHOLD):
        self.mech = mech
        self.cond_threshold = float(cond_threshold)
        # Writable C-contiguous float copies: numba compiles (and caches) one
        # variant per array layout and read-only flag, so every kernel call
        # passes the same kinds (see _arr).
        self.base = _arr(mech.base_points)
        self.plat = _arr(mech.platform_points)
        self.legp = _arr(mech.leg_platform_points)
        # Poses are compared with |dt| + size * (rotation angle).
        self.size = float(np.max(np.linalg.norm(self.plat - self.plat.mean(0), axis=1)))
        self.scale = float(max(self.size, np.ptp(self.base, axis=0).max()))
        self.sides = np.array([np.linalg.norm(self.plat[i] - self.plat[j]) for i, j in SIDES])
        # Circle axes u_k and the reference directions e1_k, e2_k. e2_k is the
        # base-plane normal made orthogonal to u_k: for coplanar base points
        # the mirror image through the base plane is then phi -> -phi, and
        # the usual modes (above or below the base) sit near t = +-1, where
        # the half-angle polynomial is best conditioned.
        centred = self.base - self.base.mean(0)
        normal = np.linalg.svd(centred)[2][2]
        normal = normal if normal[2] >= 0 else -normal
        self.axis, self.e1, self.e2, self.pair_distance = [], [], [], []
        for a, b in PAIRS:
            d = self.base[b] - self.base[a]
            dist = np.linalg.norm(d)
            u = d / dist
            e2 = normal - (normal @ u) * u
            if np.linalg.norm(e2) < 1e-6:   # pair line along the normal: any perpendicular
                e2 = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
            e2 = e2 / np.linalg.norm(e2)
            self.axis.append(u)
            self.e1.append(np.cross(e2, u))
            self.e2.append(e2)
            self.pair_distance.append(dist)
        self.axis, self.e1, self.e2 = map(np.array, (self.axis, self.e1, self.e2))
        self.pair_distance = np.array(self.pair_distance)
        self.reference = (_arr(mech.initial_position),
                          _arr(rotation_from_euler(mech.initial_orientation)))

    # -- small helpers --------------------------------------------------------
    def check_lengths(self, lengths) -> np.ndarray:
        lengths = _arr(lengths)
        if lengths.shape != (6,) or not np.all(np.isfinite(lengths)):
            raise ValueError('leg lengths must be 6 finite numbers, got %r' % (lengths,))
        bad = np.flatnonzero(lengths <= 0)
        if bad.size:
            raise NoAssemblyError('leg_%d length %g m is not positive'
                                  % (bad[0] + 1, lengths[bad[0]]))
        return lengths

    def condition(self, position, rotation) -> float:
        """2-norm condition number of the Jacobian at a pose."""
        return float(_cond(self.jacobian(position, rotation)))

    def jacobian(self, position, rotation) -> np.ndarray:
        jac, res = np.empty((6, 6)), np.empty(6)
        _legs(self.base, self.legp, _arr(position), _arr(rotation), np.zeros(6), jac, res)
        return jac

    def twist(self, position, rotation, rates):
        """(v, omega), base frame, from leg rates: J [v; omega] = dL/dt (eq. 13)."""
        x = _twist(self.base, self.legp, _arr(position), _arr(rotation), _arr(rates))
        return x[:3], x[3:]

    def distance(self, position, rotation, ref_position, ref_rotation) -> float:
        """|dt| + size * angle(R_ref^T R): metres, the angle weighted by the platform radius."""
        return _pose_distance(_arr(position), _arr(rotation), _arr(ref_position),
                              _arr(ref_rotation), self.size)

    def refine(self, lengths, position, rotation, max_iter: int = 30,
               step_tol: float = 1e-12) -> FKResult | None:
        """Newton from a pose; None when it does not converge."""
        t, rot, it, ok, res = _newton(self.base, self.legp, self.check_lengths(lengths),
                                      _arr(position), _arr(rotation), int(max_iter),
                                      float(step_tol))
        if not ok or res > 1e-9 * self.scale:
            return None
        cond = self.condition(t, rot)
        return FKResult(t, rot, cond, cond > self.cond_threshold, res, it)

    # -- the circles ----------------------------------------------------------
    def circles(self, lengths):
        """Centre (3, 3) and radius (3,) of each vertex's circle; NoAssemblyError if none."""
        lengths = self.check_lengths(lengths)
        la, lb = lengths[0::2], lengths[1::2]
        d = self.pair_distance
        along = (la * la - lb * lb + d * d) / (2.0 * d)
        r2 = la * la - along * along
        for k in np.flatnonzero(r2 < -1e-12 * self.scale ** 2):
            a, b = PAIRS[k]
            if abs(la[k] - lb[k]) > d[k]:
                why = '|L%d - L%d| = %.6g m exceeds' % (a + 1, b + 1, abs(la[k] - lb[k]))
            else:
                why = 'L%d + L%d = %.6g m is shorter than' % (a + 1, b + 1, la[k] + lb[k])
            raise NoAssemblyError('legs %d and %d cannot meet: %s their base distance '
                                  '|b%d - b%d| = %.6g m' % (a + 1, b + 1, why, a + 1, b + 1, d[k]))
        centre = self.base[0::2] + along[:, None] * self.axis
        return centre, np.sqrt(np.maximum(r2, 0.0))

    def all_modes(self, lengths, reference=None) -> list:
        """Every real assembly mode, nearest the reference pose first.

        reference: (position, rotation); default the mechanism's initial pose.
        Raises NoAssemblyError when a leg pair cannot meet or no mode exists.
        """
        lengths = self.check_lengths(lengths)
        centre, radius = self.circles(lengths)
        angles = _mode_candidates(centre, radius, self.e1, self.e2, self.sides)
        vertices = centre + radius[:, None] * (np.cos(angles)[..., None] * self.e1
                                               + np.sin(angles)[..., None] * self.e2)
        t, rot, iters, res, cond = _polish_modes(self.base, self.legp, lengths, vertices,
                                                 self.plat, self.size, 1e-9 * self.scale)
        modes = [FKResult(t[k], rot[k], cond[k], cond[k] > self.cond_threshold, res[k],
                          iters[k], True) for k in range(len(t))]
        if not modes:
            raise NoAssemblyError('no assembly mode: the six leg lengths %s m do not close '
                                  'the platform triangle' % np.round(lengths, 6).tolist())
        ref_t, ref_r = self.reference if reference is None else (
            _arr(reference[0]), _arr(reference[1]))
        modes.sort(key=lambda m: _pose_distance(m.position, m.rotation, ref_t, ref_r, self.size))
        return modes

    def nearest(self, lengths, position, rotation) -> FKResult:
        """The assembly mode nearest a pose."""
        return self.all_modes(lengths, (position, rotation))[0]


class FKTracker:
    """Forward kinematics of a moving platform, sample after sample.

    Newton from the previous pose (a few steps at a 1 kHz sample rate); when
    it fails, or moves more than ``max_move`` (|dt| + platform radius x angle,
    metres) in one sample, the all-modes solver picks the mode nearest the
    previous pose. Start at ``position``/``rotation``, default the mechanism's
    initial pose.
    """

    def __init__(self, mech_or_fk, position=None, rotation=None,
                 cond_threshold: float | None = None, max_move: float = 0.05,
                 max_iter: int = 12):
        fk = mech_or_fk if isinstance(mech_or_fk, ForwardKinematics) else ForwardKinematics(
            mech_or_fk, DEFAULT_COND_THRESHOLD if cond_threshold is None else cond_threshold)
        if cond_threshold is not None:
            fk.cond_threshold = float(cond_threshold)
        self.fk = fk
        mech = fk.mech
        self.position = _arr(mech.initial_position if position is None else position)
        self.rotation = _arr(rotation_from_euler(mech.initial_orientation)
                             if rotation is None else rotation)
        self.max_move = max_move
        self.max_iter = max_iter

    def reset(self, position, rotation):
        """Continue from this pose (a known start, or after a jump in the data)."""
        self.position = _arr(position)
        self.rotation = _arr(rotation)

    def solve(self, lengths, rates=None) -> FKResult:
        """Pose (and twist, if leg rates are given) for one sample of leg lengths."""
        fk = self.fk
        lengths = _arr(lengths)
        if lengths.shape != (6,):
            lengths = fk.check_lengths(lengths)     # raises with a clear message
        # NaN or negative lengths fail Newton and are reported by all_modes.
        t, rot, it, ok, res, move, cond = _track(fk.base, fk.legp, lengths, self.position,
                                                 self.rotation, self.max_iter, fk.size)
        if ok and res <= 1e-9 * fk.scale and move <= self.max_move:
            result = FKResult(t, rot, cond, cond > fk.cond_threshold, res, it)
        else:
            result = fk.nearest(lengths, self.position, self.rotation)
        if rates is not None:
            result.velocity, result.omega = fk.twist(result.position, result.rotation, rates)
        self.position, self.rotation = result.position, result.rotation
        return result


def assembly_modes(mech, lengths, reference=None) -> list:
    """Every real assembly mode for six leg lengths (see ForwardKinematics.all_modes)."""
    return ForwardKinematics(mech).all_modes(lengths, reference)


def twist(mech, position, rotation, rates):
    """(v, omega) in the base frame from leg rates: solve(J, dL/dt)."""
    return ForwardKinematics(mech).twist(position, rotation, rates)
