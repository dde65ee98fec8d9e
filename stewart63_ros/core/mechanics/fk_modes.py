"""Every real assembly mode of the 6-3 platform from six leg lengths: the kernels.

The method (a degree-16 polynomial recovered by a discrete Fourier
transform, its real roots, Newton polishing) is described in ``fk``, whose
``ForwardKinematics.all_modes`` calls these kernels.
"""
from __future__ import annotations

import numpy as np

from stewart63_ros.core.mechanics.fk_tracking import (
    _legs,
    _newton,
    _pose_distance,
    condition_number,
)
from stewart63_ros.core.plumbing._jit import njit

#: Platform sides (0-based vertices) in the order the equations are chained: 1-2, 2-3, 3-1.
SIDES = ((0, 1), (1, 2), (2, 0))
#: (1 + t^2) [cos phi, sin phi, 1] = HALF_ANGLE [1, t, t^2] with t = tan(phi / 2).
HALF_ANGLE = np.array([[1.0, 0.0, -1.0], [0.0, 2.0, 0.0], [1.0, 0.0, 1.0]])
_SAMPLES = 32          # > 16: the degree-16 resultant is recovered exactly
_SAMPLE_OFFSET = 0.1234   # keep the samples off t = +-1, +-i (special for symmetric designs)


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
