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
#: packaged mechanism stays below ~10; a singular pose sends it to infinity.
DEFAULT_COND_THRESHOLD = 1.0e3
#: Pair k's legs (0-based): legs 2k and 2k+1 meet at vertex k.
PAIRS = ((0, 1), (2, 3), (4, 5))
#: Platform sides (i, j), in the order the equations are chained 1-2, 2-3, 3-1.
SIDES = ((0, 1), (1, 2), (2, 0))
_N_SAMPLES = 32          # > 16: the degree-16 resultant is recovered exactly
_HALF_ANGLE = np.array([[1.0, 0.0, -1.0],   # (1 + t^2) [cos, sin, 1] = T [1, t, t^2]
                        [0.0, 2.0, 0.0],
                        [1.0, 0.0, 1.0]])


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
    for i in range(6):
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
    n = 6
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
    """Newton on L(t, R) = lengths; returns t, R, iterations, converged, residual, cond.

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
        for k in range(6):
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
    return t, rot, it, ok, worst, _cond(jac)


# -- all assembly modes --------------------------------------------------------

def _frame(points):
    """Orthonormal frame (columns) of three points: x along 1->2, z normal to the plane."""
    x = points[1] - points[0]
    z = np.cross(x, points[2] - points[0])
    x = x / np.linalg.norm(x)
    z = z / np.linalg.norm(z)
    return np.column_stack([x, np.cross(z, x), z])


def _homogeneous_roots(c):
    """Roots of c0 w^2 + c1 x w + c2 x^2 (rows of c) as pairs (x, w), stable for c2 -> 0.

    With q = -(c1 + s)/2, s = sqrt(c1^2 - 4 c0 c2) signed so |q| is large, the
    roots are x/w = q/c2 and c0/q, i.e. (q, c2) and (c0, q), and
    (x c2 - w q)(x q - w c0) = q * (polynomial): the factor q divides the
    resultant (see ``_resultant_samples``).
    """
    c0, c1, c2 = c[..., 0], c[..., 1], c[..., 2]
    s = np.sqrt(c1 * c1 - 4.0 * c0 * c2 + 0j)
    s = np.where((np.conj(c1) * s).real >= 0, s, -s)
    q = -0.5 * (c1 + s)
    x = np.stack([q, c0], -1)
    w = np.stack([c2, q], -1)
    return x, w, q


class ForwardKinematics:
    """Forward kinematics of one mechanism; constants gathered once here."""

    def __init__(self, mech, cond_threshold: float = DEFAULT_COND_THRESHOLD):
        self.mech = mech
        self.cond_threshold = float(cond_threshold)
        self.base = np.ascontiguousarray(mech.base_points, dtype=float)
        self.plat = np.ascontiguousarray(mech.platform_points, dtype=float)
        self.legp = np.ascontiguousarray(mech.leg_platform_points, dtype=float)
        # Poses are compared with |dt| + size * (rotation angle).
        self.size = float(np.max(np.linalg.norm(self.plat - self.plat.mean(0), axis=1)))
        self.scale = float(max(self.size, np.ptp(self.base, axis=0).max()))
        self.sides = np.array([np.linalg.norm(self.plat[i] - self.plat[j]) for i, j in SIDES])
        self._plat_frame = _frame(self.plat)
        self._plat_centroid = self.plat.mean(0)
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
        z = np.exp(2j * np.pi * np.arange(_N_SAMPLES) / _N_SAMPLES)
        self._m1_samples = np.stack([np.ones_like(z), z, z * z], -1)

    # -- small helpers --------------------------------------------------------
    def check_lengths(self, lengths) -> np.ndarray:
        lengths = np.asarray(lengths, dtype=float)
        if lengths.shape != (6,) or not np.all(np.isfinite(lengths)):
            raise ValueError('leg lengths must be 6 finite numbers, got %r' % (lengths,))
        bad = np.flatnonzero(lengths <= 0)
        if bad.size:
            raise NoAssemblyError('leg_%d length %g m is not positive'
                                  % (bad[0] + 1, lengths[bad[0]]))
        return lengths

    def condition(self, position, rotation) -> float:
        """2-norm condition number of the Jacobian at a pose."""
        return float(np.linalg.cond(self.jacobian(position, rotation)))

    def jacobian(self, position, rotation) -> np.ndarray:
        jac, res = np.empty((6, 6)), np.empty(6)
        _legs(self.base, self.legp, np.asarray(position, float), np.asarray(rotation, float),
              np.zeros(6), jac, res)
        return jac

    def twist(self, position, rotation, rates):
        """(v, omega), base frame, from leg rates: J [v; omega] = dL/dt (eq. 13)."""
        x = np.linalg.solve(self.jacobian(position, rotation), np.asarray(rates, float))
        return x[:3], x[3:]

    def distance(self, position, rotation, ref_position, ref_rotation) -> float:
        """|dt| + size * angle(R_ref^T R): metres, the angle weighted by the platform radius."""
        cos = (np.trace(np.asarray(ref_rotation).T @ rotation) - 1.0) / 2.0
        return float(np.linalg.norm(np.asarray(position) - ref_position)
                     + self.size * np.arccos(np.clip(cos, -1.0, 1.0)))

    def refine(self, lengths, position, rotation, max_iter: int = 30,
               step_tol: float = 1e-12) -> FKResult | None:
        """Newton from a pose; None when it does not converge."""
        t, rot, it, ok, res, cond = _newton(self.base, self.legp, lengths,
                                            np.asarray(position, float),
                                            np.asarray(rotation, float), max_iter, step_tol)
        if not ok or res > 1e-9 * self.scale:
            return None
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

    def _side_matrices(self, centre, radius):
        """M_ij with |P_i - P_j|^2 - l_ij^2 = [cos_i, sin_i, 1] M_ij [cos_j, sin_j, 1]^T."""
        out = []
        for (i, j), side in zip(SIDES, self.sides):
            d = centre[i] - centre[j]
            ui = radius[i] * np.stack([self.e1[i], self.e2[i]])    # (2, 3)
            uj = radius[j] * np.stack([self.e1[j], self.e2[j]])
            m = np.empty((3, 3))
            m[:2, :2] = -2.0 * ui @ uj.T
            m[:2, 2] = 2.0 * ui @ d
            m[2, :2] = -2.0 * uj @ d
            m[2, 2] = d @ d + radius[i] ** 2 + radius[j] ** 2 - side ** 2
            out.append(m)
        return out

    def _resultant_samples(self, q12, q23, q31):
        """The degree-16 resultant D(t1) at the sample points, by its root form.

        For fixed t1, E12 = 0 is a quadratic a(t2) with homogeneous roots
        (x_a, w_a) and E31 = 0 a quadratic b(t3) with roots (y_b, v_b). Then
        Res_t3(b, Res_t2(a, E23)) = prod_ab E23(x_a, w_a; y_b, v_b) / (q_a^4 q_b^4)
        with q the normalising factors of ``_homogeneous_roots``: a polynomial
        of degree 16 in t1 (Nanua et al. 1990), whatever the root labelling.
        """
        m1 = self._m1_samples
        alpha = m1 @ q12                 # coefficients of t2^0, t2^1, t2^2
        beta = m1 @ q31.T                # coefficients of t3^0..2
        x, w, qa = _homogeneous_roots(alpha)
        y, v, qb = _homogeneous_roots(beta)
        mx = np.stack([w * w, x * w, x * x], -1)    # (N, 2, 3): [w^2, x w, x^2]
        my = np.stack([v * v, y * v, y * y], -1)
        e = np.einsum('nai,ij,nbj->nab', mx, q23, my)
        return np.prod(e.reshape(len(e), 4), axis=1) / (qa ** 4 * qb ** 4)

    def _vertex_candidates(self, centre, radius, mats, qs):
        """Real roots of D(t1) and the angles of vertices 2 and 3 that go with them."""
        q12, q23, q31 = qs
        coeffs = np.fft.fft(self._resultant_samples(q12, q23, q31)) / _N_SAMPLES
        coeffs = coeffs[:17].real
        roots = np.roots(coeffs[::-1]) if np.any(coeffs[1:]) else np.zeros(0)
        with np.errstate(all='ignore'):
            phi1 = 2.0 * np.arctan(roots)            # complex for complex roots
        # Accept generously; Newton decides. Near-double roots come out as a
        # complex pair with a small imaginary part.
        phi1 = phi1.real[np.abs(phi1.imag) < 1e-3]
        if coeffs[16] == 0.0 or abs(coeffs[16]) < 1e-12 * np.abs(coeffs).max():
            phi1 = np.append(phi1, np.pi)          # a root at t1 = infinity
        if phi1.size == 0:
            return np.zeros((0, 3))
        # Homogeneous half-angle monomials of phi1: [cos^2, cos sin, sin^2](phi/2).
        c, s = np.cos(phi1 / 2), np.sin(phi1 / 2)
        m1 = np.stack([c * c, c * s, s * s], -1)
        x, w, _ = _homogeneous_roots((m1 @ q12).real + 0j)
        y, v, _ = _homogeneous_roots((m1 @ q31.T).real + 0j)
        phi2 = 2.0 * np.arctan2((x * np.conj(w)).real, (w * np.conj(w)).real)   # (n, 2)
        phi3 = 2.0 * np.arctan2((y * np.conj(v)).real, (v * np.conj(v)).real)
        cs2 = np.stack([np.cos(phi2), np.sin(phi2), np.ones_like(phi2)], -1)     # (n, 2, 3)
        cs3 = np.stack([np.cos(phi3), np.sin(phi3), np.ones_like(phi3)], -1)
        r23 = np.abs(np.einsum('nai,ij,nbj->nab', cs2, mats[1], cs3)).reshape(-1, 4)
        keep = (r23 <= 1e-2 * self.sides[1] ** 2) | (r23 == r23.min(1, keepdims=True))
        n, combo = np.nonzero(keep)
        return np.stack([phi1[n], phi2[n, combo // 2], phi3[n, combo % 2]], -1)

    def all_modes(self, lengths, reference=None) -> list:
        """Every real assembly mode, nearest the reference pose first.

        reference: (position, rotation); default the mechanism's initial pose.
        Raises NoAssemblyError when a leg pair cannot meet or no mode exists.
        """
        lengths = self.check_lengths(lengths)
        centre, radius = self.circles(lengths)
        mats = self._side_matrices(centre, radius)
        qs = [_HALF_ANGLE.T @ m @ _HALF_ANGLE for m in mats]
        qs = [q / np.abs(q).max() for q in qs]
        angles = self._vertex_candidates(centre, radius, mats, qs)
        modes = []
        for phi in angles:
            vertices = centre + radius[:, None] * (np.cos(phi)[:, None] * self.e1
                                                   + np.sin(phi)[:, None] * self.e2)
            rot = _frame(vertices) @ self._plat_frame.T
            if not np.all(np.isfinite(rot)):
                continue
            t = vertices.mean(0) - rot @ self._plat_centroid
            found = self.refine(lengths, t, rot)
            if found is None:
                continue
            if all(self.distance(found.position, found.rotation, m.position, m.rotation)
                   > 1e-7 * self.scale for m in modes):
                modes.append(found)
        if not modes:
            raise NoAssemblyError('no assembly mode: the six leg lengths %s m do not close '
                                  'the platform triangle' % np.round(lengths, 6).tolist())
        if reference is None:
            reference = (self.mech.initial_position,
                         rotation_from_euler(self.mech.initial_orientation))
        modes.sort(key=lambda m: self.distance(m.position, m.rotation, *reference))
        for m in modes:
            m.fallback = True
        return modes

    def nearest(self, lengths, position, rotation) -> FKResult:
        """The assembly mode nearest a pose."""
        return self.all_modes(lengths, (np.asarray(position, float),
                                        np.asarray(rotation, float)))[0]


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
        self.position = np.array(mech.initial_position if position is None else position, float)
        self.rotation = np.array(rotation_from_euler(mech.initial_orientation)
                                 if rotation is None else rotation, float)
        self.max_move = max_move
        self.max_iter = max_iter

    def reset(self, position, rotation):
        self.position = np.array(position, float)
        self.rotation = np.array(rotation, float)

    def solve(self, lengths, rates=None) -> FKResult:
        """Pose (and twist, if leg rates are given) for one sample of leg lengths."""
        fk = self.fk
        lengths = np.asarray(lengths, dtype=float)
        if lengths.shape != (6,) or not np.all(np.isfinite(lengths)):
            lengths = fk.check_lengths(lengths)     # raises with a clear message
        t, rot, it, ok, res, cond = _newton(fk.base, fk.legp, lengths, self.position,
                                            self.rotation, self.max_iter, 1e-12)
        if ok and res <= 1e-9 * fk.scale and (
                fk.distance(t, rot, self.position, self.rotation) <= self.max_move):
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
