"""Forward kinematics of the general 6-6 Gough-Stewart platform: every assembly mode.

Leg i joins base point b_i to platform point p_i (six distinct points on each
side); S_i = t + R p_i - b_i, L_i = |S_i| (the model of ``core/mechanics/fk.py``, eqs. 2-5).
The general 6-6 has 40 complex assembly modes, all of which can be real
(Dietmaier 1998). ``ForwardKinematics66.all_modes`` finds every real one by a
polynomial homotopy, which follows each of the 40 complex solutions and so
cannot miss one (unlike Newton from random starts):

* Unknowns: Study parameters z = (e, g) of the pose, e a quaternion (the
  rotation, R x = e x e* / (e.e)) and g with t = 2 vec(g e*) / (e.e) (the
  translation), subject to Study's quadric e.g = 0. Then
  R p_i + t - b_i = (e p_i + 2 g - b_i e) e* / (e.e), so leg i reads
  |K_i e + 2 g|^2 = L_i^2 (e.e), K_i e = e p_i - b_i e: seven homogeneous
  quadrics in P^7 (Wampler, "Forward displacement analysis of general
  six-in-parallel SPS (Stewart) platform manipulators using soma coordinates",
  Mech. Mach. Theory 31(3), 1996), made affine by a random complex patch a.z = 1.
  Its 128 Bezout solutions are the 40 poses and a degenerate set at e = 0.
* Start system, once per process: the quadrics for random complex geometry and
  lengths, solved by a total-degree homotopy (128 paths, gamma trick); the 40
  finite nonsingular end points are kept (checked: exactly 40).
* Each solve: a coefficient-parameter homotopy (Morgan & Sommese 1989) from
  those random complex parameters to the machine's (b_i, p_i, L_i^2) along
  a straight line; 40 paths, RK4 predictor and Newton corrector with step
  control. The line through complex parameters avoids the discriminant with
  probability one, so every isolated solution of the target ends a path.
  Safeguards: two paths ending on the same nonsingular point (a path jump)
  re-run with smaller steps; a path stopping midway (t > 0.01: the line passed
  near the degenerate set), or an odd number of real modes beside stopped
  paths (non-real solutions come in conjugate pairs, so a real mode's path
  may be lost), re-run the paths through a random complex midpoint.
* End points with a real pose (imaginary part small) are polished by Newton on
  the six leg equations (``core/mechanics/fk.py``'s kernel), deduplicated, and returned
  with the Jacobian's condition number and a ``singular`` flag.

``FKTracker66`` follows a moving 6-6 by Newton from the last pose: the
kernels ``_track``/``_newton`` of ``core/mechanics/fk.py`` take one platform point per
leg (``legp``) and so serve six distinct points unchanged.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from stewart63_ros.core.mechanics.fk_tracking import (
    FKResult,
    NoAssemblyError,
    _legs,
    _newton,
    _pose_distance,
    _track,
    _twist,
    checked_lengths,
    condition_number,
)
from stewart63_ros.core.plumbing._jit import njit
from stewart63_ros.core.plumbing.node_parameters import DEFAULT_COND_THRESHOLD

#: Complex solutions of the general 6-6 forward kinematics (Raghavan 1993; Lazard 1993).
GENERIC_MODES = 40
#: A Jacobian condition number above this flags a mode ``singular``
#: (the fk node's default ``singularity_threshold``).
COND_THRESHOLD = DEFAULT_COND_THRESHOLD
_SEED = 20260127


def _arr(x) -> np.ndarray:
    return np.array(x, dtype=np.float64, order='C')


# -- the polynomial system and its homotopy (compiled) ------------------------

@njit
def _solve_complex(a, b):
    """x = a^-1 b, Gaussian elimination with partial pivoting (a, b copied)."""
    a = a.copy()
    x = b.copy()
    n = x.shape[0]
    for k in range(n):
        p = k
        for i in range(k + 1, n):
            if abs(a[i, k]) > abs(a[p, k]):
                p = i
        if a[p, k] == 0:
            x[:] = np.nan
            return x
        if p != k:
            for j in range(n):
                a[k, j], a[p, j] = a[p, j], a[k, j]
            x[k], x[p] = x[p], x[k]
        for i in range(k + 1, n):
            f = a[i, k] / a[k, k]
            for j in range(k, n):
                a[i, j] -= f * a[k, j]
            x[i] -= f * x[k]
    for k in range(n - 1, -1, -1):
        acc = x[k]
        for j in range(k + 1, n):
            acc -= a[k, j] * x[j]
        x[k] = acc / a[k, k]
    return x


@njit
def _k_times(e, d, s):
    """K e = e p - b e for pure quaternions p, b, with d = p - b, s = p + b."""
    return (-(e[1] * d[0] + e[2] * d[1] + e[3] * d[2]),
            e[0] * d[0] + e[2] * s[2] - e[3] * s[1],
            e[0] * d[1] + e[3] * s[0] - e[1] * s[2],
            e[0] * d[2] + e[1] * s[1] - e[2] * s[0])


@njit
def _eval(z, t, par, dpar, patch, gamma, total_degree, h, jac, ht):
    """H(z, t), dH/dz and dH/dt of the homotopy at z (8,), t in [0, 1].

    par (6, 7): per leg d = p - b, s = p + b, L^2 at t = 0 (the target);
    dpar: their change to t = 1 (the start). Parameter homotopy: the legs'
    parameters are par + t dpar. Total degree (``total_degree``): H =
    (1 - t) F(par) + gamma t G, G_j = z_{j+1}^2 - z_0^2.
    Rows 0-5 legs, 6 Study's quadric e.g, 7 the patch a.z - 1.
    """
    w = 1.0 - t if total_degree else 1.0
    tp = 0.0 if total_degree else t
    e = (z[0], z[1], z[2], z[3])
    g = (z[4], z[5], z[6], z[7])
    ee = e[0] * e[0] + e[1] * e[1] + e[2] * e[2] + e[3] * e[3]
    for i in range(6):
        # scalars, not slices: an array per leg and call would dominate the cost
        d = (par[i, 0] + tp * dpar[i, 0], par[i, 1] + tp * dpar[i, 1],
             par[i, 2] + tp * dpar[i, 2])
        s = (par[i, 3] + tp * dpar[i, 3], par[i, 4] + tp * dpar[i, 4],
             par[i, 5] + tp * dpar[i, 5])
        l2 = par[i, 6] + tp * dpar[i, 6]
        k0, k1, k2, k3 = _k_times(e, d, s)
        v0, v1, v2, v3 = k0 + 2 * g[0], k1 + 2 * g[1], k2 + 2 * g[2], k3 + 2 * g[3]
        h[i] = w * (v0 * v0 + v1 * v1 + v2 * v2 + v3 * v3 - l2 * ee)
        # d/de = 2 K^T v - 2 L^2 e; d/dg = 4 v
        jac[i, 0] = w * (2 * (d[0] * v1 + d[1] * v2 + d[2] * v3) - 2 * l2 * e[0])
        jac[i, 1] = w * (2 * (-d[0] * v0 - s[2] * v2 + s[1] * v3) - 2 * l2 * e[1])
        jac[i, 2] = w * (2 * (-d[1] * v0 + s[2] * v1 - s[0] * v3) - 2 * l2 * e[2])
        jac[i, 3] = w * (2 * (-d[2] * v0 - s[1] * v1 + s[0] * v2) - 2 * l2 * e[3])
        jac[i, 4], jac[i, 5], jac[i, 6], jac[i, 7] = w * 4 * v0, w * 4 * v1, w * 4 * v2, w * 4 * v3
        if total_degree:
            ht[i] = -h[i] / w if w != 0 else -(v0 * v0 + v1 * v1 + v2 * v2 + v3 * v3 - l2 * ee)
        else:
            m0, m1, m2, m3 = _k_times(e, (dpar[i, 0], dpar[i, 1], dpar[i, 2]),
                                      (dpar[i, 3], dpar[i, 4], dpar[i, 5]))
            ht[i] = 2 * (v0 * m0 + v1 * m1 + v2 * m2 + v3 * m3) - dpar[i, 6] * ee
    h[6] = w * (e[0] * g[0] + e[1] * g[1] + e[2] * g[2] + e[3] * g[3])
    for j in range(4):
        jac[6, j] = w * g[j]
        jac[6, 4 + j] = w * e[j]
    ht[6] = -(e[0] * g[0] + e[1] * g[1] + e[2] * g[2] + e[3] * g[3]) if total_degree else 0.0
    acc = -1.0 + 0j
    for j in range(8):
        acc += patch[j] * z[j]
        jac[7, j] = patch[j]
    h[7] = acc
    ht[7] = 0.0
    if total_degree:
        for r in range(7):
            gz = z[r + 1] * z[r + 1] - z[0] * z[0]
            h[r] += gamma * t * gz
            ht[r] += gamma * gz
            jac[r, r + 1] += gamma * t * 2 * z[r + 1]
            jac[r, 0] -= gamma * t * 2 * z[0]


@njit
def _velocity(z, t, par, dpar, patch, gamma, td, h, jac, ht):
    _eval(z, t, par, dpar, patch, gamma, td, h, jac, ht)
    return -_solve_complex(jac, ht)


@njit
def _norm(x):
    acc = 0.0
    for k in range(x.shape[0]):
        acc += x[k].real ** 2 + x[k].imag ** 2
    return np.sqrt(acc)


@njit
def _correct(z, t, par, dpar, patch, gamma, td, h, jac, ht, tol, iters):
    """Newton on H(., t) from z; returns (z, converged)."""
    for _ in range(iters):
        _eval(z, t, par, dpar, patch, gamma, td, h, jac, ht)
        dz = _solve_complex(jac, h)
        z = z - dz
        step = _norm(dz)
        if not step < 1e3:
            return z, False
        if step < tol * (1.0 + _norm(z)):
            return z, True
    return z, False


@njit
def _track_paths(starts, par, dpar, patch, gamma, td, max_step, max_steps):
    """Follow every start solution from t = 1 to t = 0.

    RK4 predictor on dz/dt = -H_z^-1 H_t, up to 3 Newton corrections that must
    meet 1e-9 (relative) — else the step is halved; after three good steps it
    doubles, up to max_step (small steps keep paths from jumping). A path that
    needs a step below 1e-12 (a singular end, a diverging path) stops there.
    Returns the end points (n, 8), their t and whether they reached t = 0.
    """
    n = starts.shape[0]
    ends = starts.copy()
    t_end = np.ones(n)
    done = np.zeros(n, np.bool_)
    h = np.empty(8, np.complex128)
    jac = np.empty((8, 8), np.complex128)
    ht = np.empty(8, np.complex128)
    for p in range(n):
        z = starts[p].copy()
        t = 1.0
        dt = min(0.02, max_step)
        good = 0
        steps = 0
        while t > 0.0 and steps < max_steps:
            steps += 1
            dt = min(dt, t)
            k1 = _velocity(z, t, par, dpar, patch, gamma, td, h, jac, ht)
            k2 = _velocity(z - 0.5 * dt * k1, t - 0.5 * dt, par, dpar, patch, gamma, td, h,
                           jac, ht)
            k3 = _velocity(z - 0.5 * dt * k2, t - 0.5 * dt, par, dpar, patch, gamma, td, h,
                           jac, ht)
            k4 = _velocity(z - dt * k3, t - dt, par, dpar, patch, gamma, td, h, jac, ht)
            zp = z - dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
            zc, ok = _correct(zp, t - dt, par, dpar, patch, gamma, td, h, jac, ht, 1e-9, 3)
            # a corrector that moves far from the prediction left its path
            if ok and _norm(zc - zp) < 0.1 * (1.0 + _norm(z)) * dt + 1e-8:
                z = zc
                t = t - dt if dt < t else 0.0
                good += 1
                # near the end with e.e -> 0: the pose runs off to infinity (a real
                # pose has e.e = |e|^2); stop rather than halve the step for nothing
                if t < 1e-3 and not td:
                    ee = z[0] * z[0] + z[1] * z[1] + z[2] * z[2] + z[3] * z[3]
                    if abs(ee) < 1e-6 * (abs(z[0]) ** 2 + abs(z[1]) ** 2 + abs(z[2]) ** 2
                                         + abs(z[3]) ** 2):
                        break
                if good >= 3:
                    dt = min(2.0 * dt, max_step)
                    good = 0
            else:
                dt *= 0.5
                good = 0
                if dt < 1e-12:
                    break
        if t == 0.0:
            z, _ = _correct(z, 0.0, par, dpar, patch, gamma, td, h, jac, ht, 1e-14, 3)
        ends[p] = z
        t_end[p] = t
        done[p] = t == 0.0
    return ends, t_end, done


@njit
def _end_condition(z, par, dpar, patch):
    """1-norm condition number of H_z at t = 0 (the inverse column by column):
    large at a singular end point, where two paths may meet legitimately."""
    h = np.empty(8, np.complex128)
    jac = np.empty((8, 8), np.complex128)
    ht = np.empty(8, np.complex128)
    _eval(z, 0.0, par, dpar, patch, 0j, False, h, jac, ht)
    norm_a = 0.0
    for j in range(8):
        col = 0.0
        for i in range(8):
            col += abs(jac[i, j])
        norm_a = max(norm_a, col)
    norm_inv = 0.0
    unit = np.zeros(8, np.complex128)
    for j in range(8):
        unit[:] = 0.0
        unit[j] = 1.0
        x = _solve_complex(jac, unit)
        col = 0.0
        for i in range(8):
            col += abs(x[i])
        if not np.isfinite(col):
            return np.inf
        norm_inv = max(norm_inv, col)
    return norm_a * norm_inv


def _parameters(base: np.ndarray, plat: np.ndarray, lengths2: np.ndarray) -> np.ndarray:
    """(6, 7) complex: per leg d = p - b, s = p + b, L^2."""
    return np.ascontiguousarray(np.hstack([plat - base, plat + base, lengths2[:, None]]),
                                dtype=np.complex128)


def _pose_of_study(z: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(t, R) complex from Study parameters z, and |e.e| / |e|^2 (0 at infinity).

    The matrix of a complex, unnormalised quaternion: core/mechanics/rotation.py's
    conversions take real unit quaternions (x, y, z, w)."""
    e, g = z[:4], z[4:]
    ee = e @ e
    size = np.sum(np.abs(e) ** 2)
    if size == 0.0 or abs(ee) < 1e-10 * size:
        return np.zeros(3, complex), np.eye(3, dtype=complex), 0.0
    w, x, y, zz = e
    rot = np.array([[w * w + x * x - y * y - zz * zz, 2 * (x * y - w * zz), 2 * (x * zz + w * y)],
                    [2 * (x * y + w * zz), w * w - x * x + y * y - zz * zz, 2 * (y * zz - w * x)],
                    [2 * (x * zz - w * y), 2 * (y * zz + w * x), w * w - x * x - y * y + zz * zz]]
                   ) / ee
    ev, gv = e[1:], g[1:]
    t = 2.0 * (e[0] * gv - g[0] * ev - np.cross(gv, ev)) / ee
    return t, rot, abs(ee) / size


class _StartSystem:
    """The 40 solutions of the quadrics for one random complex geometry (once per process)."""

    _cached: _StartSystem | None = None

    def __init__(self, seed: int = _SEED) -> None:
        rng = np.random.default_rng(seed)

        def crandn(*shape):
            return rng.standard_normal(shape) + 1j * rng.standard_normal(shape)

        self.patch = crandn(8)
        self.par = np.ascontiguousarray(np.hstack([crandn(6, 6), crandn(6, 1)]))
        zero = np.zeros((6, 7), complex)
        found: list[np.ndarray] = []
        for attempt in range(6):
            gamma = complex(np.exp(2j * np.pi * rng.random()))
            # the 2^7 start points z = (1, +-1, ..., +-1) of G_j = z_{j+1}^2 - z_0^2
            signs = np.array([[1.0] + [(-1.0) ** ((k >> j) & 1) for j in range(7)]
                              for k in range(128)], dtype=complex)
            starts = signs / (signs @ self.patch)[:, None]
            ends, _, done = _track_paths(starts, self.par, zero, self.patch, gamma, True,
                                         0.05 / (attempt + 1), 20000)
            for z, ok in zip(ends, done):
                if not ok or _pose_of_study(z)[2] < 1e-6:
                    continue
                if _end_condition(z, self.par, zero, self.patch) > 1e8:
                    continue
                if all(np.linalg.norm(z - f) > 1e-6 * np.linalg.norm(f) for f in found):
                    found.append(z)
            if len(found) == GENERIC_MODES:
                break
        if len(found) != GENERIC_MODES:
            raise RuntimeError('the 6-6 start system gave %d solutions, not %d'
                               % (len(found), GENERIC_MODES))
        self.solutions = np.ascontiguousarray(found)

    @classmethod
    def get(cls) -> _StartSystem:
        if cls._cached is None:
            cls._cached = cls()
        return cls._cached


class ForwardKinematics66:
    """Forward kinematics of a 6-6 platform: leg i from b_i to p_i.

    Args:
        base_points: (6, 3) b_i [m], base frame.
        platform_points: (6, 3) p_i [m], platform frame (six distinct points).
        cond_threshold: a mode whose Jacobian's condition number exceeds this
            is flagged ``singular``.
        reference: (position (3,), rotation (3, 3)) the modes are ordered by
            nearness to; None: upright over the base centre.

    Raises:
        ValueError: not (6, 3) finite arrays, or coincident points on one side.
    """

    def __init__(self, base_points: ArrayLike, platform_points: ArrayLike,
                 cond_threshold: float = COND_THRESHOLD,
                 reference: tuple[ArrayLike, ArrayLike] | None = None) -> None:
        self.base = _arr(base_points)
        self.legp = _arr(platform_points)
        for name, pts in (('base_points', self.base), ('platform_points', self.legp)):
            if pts.shape != (6, 3) or not np.all(np.isfinite(pts)):
                raise ValueError('%s must be 6 x 3 finite numbers, got shape %s'
                                 % (name, pts.shape))
            for i in range(6):
                for j in range(i + 1, 6):
                    if np.linalg.norm(pts[i] - pts[j]) < 1e-9:
                        raise ValueError('%s: legs %d and %d share a joint; a 6-6 needs six '
                                         'distinct points (for a 6-3 use core.mechanics.fk)'
                                         % (name, i + 1, j + 1))
        self.plat = self.legp
        self.cond_threshold = float(cond_threshold)
        self.size = float(np.max(np.linalg.norm(self.legp - self.legp.mean(0), axis=1)))
        self.scale = float(max(self.size, np.ptp(self.base, axis=0).max()))
        self.reference = None if reference is None else (_arr(reference[0]),
                                                         _arr(reference[1]))
        self.reruns = 0

    def check_lengths(self, lengths: ArrayLike) -> np.ndarray:
        """Six finite positive lengths as a float array; ValueError / NoAssemblyError if not."""
        return checked_lengths(lengths)

    def lengths(self, position: ArrayLike, rotation: ArrayLike) -> np.ndarray:
        """L_i = |t + R p_i - b_i| (eqs. 2, 5) at the pose t (3,), R (3, 3)."""
        return np.linalg.norm(_arr(position) + self.legp @ _arr(rotation).T - self.base, axis=1)

    def jacobian(self, position: ArrayLike, rotation: ArrayLike) -> np.ndarray:
        """6x6 J, row i = [s_i, q_i x s_i]: dL/dt = J [v; omega] (eq. 13)."""
        jac = np.empty((6, 6))
        _legs(self.base, self.legp, _arr(position), _arr(rotation), np.zeros(6), jac,
              np.empty(6))
        return jac

    def twist(self, position: ArrayLike, rotation: ArrayLike,
              rates: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """(v, omega) from leg rates: J [v; omega] = dL/dt (eq. 13), base frame."""
        x = _twist(self.base, self.legp, _arr(position), _arr(rotation), _arr(rates))
        return x[:3], x[3:]

    def complex_solutions(self, lengths: ArrayLike, max_step: float = 0.1,
                          detour: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """The 40 homotopy end points (Study parameters z (40, 8), complex) and
        whether each path reached the target (False: a singular or diverging end).

        Lengths are scaled by ``scale`` so the system is of order one.
        ``detour``: go through a random complex midpoint from the start (a
        different set of paths, to the same end points).
        """
        lengths = self.check_lengths(lengths)
        start = _StartSystem.get()
        target = _parameters(self.base / self.scale, self.legp / self.scale,
                             (lengths / self.scale) ** 2)
        dpar = np.ascontiguousarray(start.par - target)
        #: how many times the last solve re-ran its paths (a jump, or a path lost midway)
        self.reruns = 0
        rng = np.random.default_rng(_SEED + 1)
        ends, t_end, done = _track_paths(start.solutions, target, dpar, start.patch, 0j, False,
                                         max_step, 20000)
        while self.reruns < 3:
            if self._jumped(ends, done, target, dpar, start.patch):
                max_step /= 4.0     # two paths met at a regular point: one jumped
            elif not (np.any(t_end > 1e-2) or detour and self.reruns == 0):
                break
            # else a path stopped midway: the straight line passed near a point where a
            # solution meets infinity or the degenerate set e = 0. Go round it through
            # a random complex midpoint (two segments), which moves every path.
            self.reruns += 1
            mid = target + 0.5 * dpar + 0.5 * (rng.standard_normal(target.shape)
                                               + 1j * rng.standard_normal(target.shape))
            mids, _, ok = _track_paths(start.solutions, mid, np.ascontiguousarray(start.par - mid),
                                       start.patch, 0j, False, max_step, 20000)
            if not ok.all():
                continue
            ends, t_end, done = _track_paths(mids, target, np.ascontiguousarray(mid - target),
                                             start.patch, 0j, False, max_step, 20000)
        return ends, done

    @staticmethod
    def _jumped(ends, done, target, dpar, patch) -> bool:
        regular = [z for z, ok in zip(ends, done)
                   if ok and _end_condition(z, target, dpar, patch) < 1e8]
        for i in range(len(regular)):
            for j in range(i + 1, len(regular)):
                if np.linalg.norm(regular[i] - regular[j]) < 1e-6 * np.linalg.norm(regular[i]):
                    return True
        return False

    def all_modes(self, lengths: ArrayLike,
                  reference: tuple[ArrayLike, ArrayLike] | None = None,
                  imag_tol: float = 1e-4) -> list[FKResult]:
        """Every real assembly mode, nearest the reference pose first.

        Args:
            lengths: L (6,) [m].
            reference: (position (3,), rotation (3, 3)); default the one given
                at construction, else upright over the base centre.
            imag_tol: the largest imaginary part (of R, and of t / scale) of a
                homotopy end point taken as a real pose before Newton polishes
                it (a double root at a singular pose is real only to ~sqrt(eps)).

        Returns:
            The modes, each an ``FKResult`` (``fallback`` True).

        Raises:
            NoAssemblyError: no real mode fits the lengths.
        """
        lengths = self.check_lengths(lengths)
        ends, done = self.complex_solutions(lengths)
        ts, rots, iters, resid = self._real_poses(lengths, ends, imag_tol)
        if len(ts) % 2 and not done.all():
            # Non-real solutions come in conjugate pairs: an odd count of real
            # ones beside lost paths hints that a real mode's path was lost near
            # its end. Other paths, through a complex midpoint, settle it.
            more, _ = self.complex_solutions(lengths, detour=True)
            ts, rots, iters, resid = self._real_poses(lengths, np.vstack([ends, more]),
                                                      imag_tol)
        if not ts:
            raise NoAssemblyError('no assembly mode: the six leg lengths %s m admit no real '
                                  'pose' % np.round(lengths, 6).tolist())
        if reference is None:
            reference = self.reference
        if reference is None:
            reference = (self.base.mean(0) - self.legp.mean(0)
                         + np.array([0.0, 0.0, lengths.mean()]), np.eye(3))
        ref_t, ref_r = _arr(reference[0]), _arr(reference[1])
        order = sorted(range(len(ts)),
                       key=lambda k: _pose_distance(ts[k], rots[k], ref_t, ref_r, self.size))
        out = []
        for k in order:
            cond = condition_number(self.jacobian(ts[k], rots[k]))
            out.append(FKResult(ts[k], rots[k], cond, cond > self.cond_threshold, resid[k],
                                iters[k], True))
        return out

    def _real_poses(self, lengths, ends, imag_tol):
        """The distinct real poses among homotopy end points, polished by Newton
        on the six leg equations: lists t, R, iterations, residual."""
        ts, rots, iters, resid = [], [], [], []
        for z in ends:
            t, rot, finite = _pose_of_study(z)
            if finite == 0.0:
                continue
            t = t * self.scale
            if max(np.abs(rot.imag).max(), np.abs(t.imag).max() / self.scale) > imag_tol:
                continue
            tr, rr, it, ok, res = _newton(self.base, self.legp, lengths, _arr(t.real),
                                          _arr(rot.real), 30, 1e-12)
            if not ok or res > 1e-9 * self.scale:
                continue
            if any(_pose_distance(tr, rr, t2, r2, self.size) < 1e-7 * max(self.size, 1.0)
                   for t2, r2 in zip(ts, rots)):
                continue
            ts.append(tr)
            rots.append(rr)
            iters.append(it)
            resid.append(res)
        return ts, rots, iters, resid

    def nearest(self, lengths: ArrayLike, position: ArrayLike,
                rotation: ArrayLike) -> FKResult:
        """The real mode nearest the pose t (3,), R (3, 3); NoAssemblyError if none."""
        return self.all_modes(lengths, (position, rotation))[0]


class FKTracker66:
    """A moving 6-6 platform, sample after sample: Newton from the pose
    extrapolated from the last two samples (``core/mechanics/fk.py``'s ``_track``);
    when it fails or jumps more than ``max_move`` (|dt| + size x angle, m), the
    all-modes solver picks the mode nearest the prediction.

    Args:
        fk: the ``ForwardKinematics66``.
        position, rotation: the start pose (3,), (3, 3).
        max_move: the largest jump from the prediction Newton may make [m].
        max_iter: Newton iterations at most per sample.
    """

    def __init__(self, fk: ForwardKinematics66, position: ArrayLike, rotation: ArrayLike,
                 max_move: float = 0.05, max_iter: int = 12) -> None:
        self.fk = fk
        self.max_move = float(max_move)
        self.max_iter = int(max_iter)
        self.reset(position, rotation)

    def reset(self, position: ArrayLike, rotation: ArrayLike) -> None:
        """Continue from the pose t (3,), R (3, 3), at rest."""
        self.position, self.rotation = _arr(position), _arr(rotation)
        self._prev = (self.position, self.rotation)
        self._moving = False

    def solve(self, lengths: ArrayLike, rates: ArrayLike | None = None) -> FKResult:
        """The pose for one sample of leg lengths L (6,) [m], with the twist
        (``velocity``, ``omega``) when leg rates dL/dt (6,) [m/s] are given.

        Raises:
            ValueError: not six lengths; NoAssemblyError: no real mode.
        """
        fk = self.fk
        lengths = _arr(lengths)
        if lengths.shape != (6,):
            fk.check_lengths(lengths)
        t, rot, it, ok, res, move, cond, t0, r0 = _track(
            fk.base, fk.legp, lengths, self._prev[0], self._prev[1], self.position,
            self.rotation, self._moving, self.max_iter, fk.size)
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
