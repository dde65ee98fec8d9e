"""Reference motions of the platform: pose, twist and acceleration against time.

A reference is a piecewise polynomial in the six pose coordinates
(x, y, z, theta_x, theta_y, theta_z) (R = Rz Ry Rx, docs/interface.md):

- from rows of poses (the reference CSV, or a trajectory message without
  velocities): scipy's ``CubicSpline`` with clamped ends, i.e. C2 (position,
  velocity and acceleration continuous) between the first and the last row,
  at rest (zero velocity) at both ends;
- from poses with velocities and accelerations at every point: quintic
  Hermite pieces (scipy ``BPoly.from_derivatives``), C2; with velocities only,
  cubic Hermite, C1;
- a constant pose or constant leg lengths (a setpoint).

Before the first time the first pose holds, after the last time the last
pose holds (velocity and acceleration zero). Velocities and accelerations
come from the interpolant: omega = E(theta) dtheta/dt,
alpha = E dtheta^2/dt^2 + dE/dt dtheta/dt (base frame), and the desired leg
lengths and rates from inverse kinematics, eqs. (2)-(5), (13).

A sample is one flat array (``SAMPLE_SIZE``), laid out as ``R_*`` below;
``ReferenceSample`` names its parts. Evaluation is compiled (a few
microseconds), so that the controller samples it at 1 kHz.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from stewart63_ros.core.mechanics.fk import ForwardKinematics
from stewart63_ros.core.mechanics.kinematics import leg_kernel
from stewart63_ros.core.mechanics.rotation import (
    euler_from_matrix,
)
from stewart63_ros.core.plumbing._jit import njit

if TYPE_CHECKING:
    from stewart63_ros.core.mechanics.mechanism import Mechanism

#: Layout of a reference sample: position t (3), rotation R row-major (9),
#: velocity v (3), angular velocity omega (3), acceleration (3), angular
#: acceleration alpha (3), all in the base frame; desired leg lengths (6)
#: and leg rates (6). ``I_*``: the index of each part's first element (the
#: compiled kernels index with these; numba freezes them as constants);
#: ``R_*``: the part as a slice.
I_POS, I_ROT, I_VEL, I_OMEGA, I_ACC, I_ALPHA, I_LEN, I_RATE = 0, 3, 12, 15, 18, 21, 24, 30
SAMPLE_SIZE = 36
R_POS, R_ROT = slice(I_POS, I_POS + 3), slice(I_ROT, I_ROT + 9)
R_VEL, R_OMEGA = slice(I_VEL, I_VEL + 3), slice(I_OMEGA, I_OMEGA + 3)
R_ACC, R_ALPHA = slice(I_ACC, I_ACC + 3), slice(I_ALPHA, I_ALPHA + 3)
R_LEN, R_RATE = slice(I_LEN, I_LEN + 6), slice(I_RATE, I_RATE + 6)
CSV_COLUMNS = ('t', 'x', 'y', 'z', 'theta_x', 'theta_y', 'theta_z')


class ReferenceError(ValueError):
    """A reference that cannot be used; the message says where and why."""


class MessageError(ReferenceError):
    """A pose message that cannot be a reference: ``reason`` is a short key
    (the controller counts its refusals under it), the message says why."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason


class ReferenceSample:
    """Named views into one reference sample (a flat array, ``.array``).

    Every property is a view into the array (base frame, SI units), valid as
    long as the array holds this sample.

    Args:
        array: (SAMPLE_SIZE,) to wrap; None: a new one of zeros.
    """

    __slots__ = ('array',)

    def __init__(self, array: np.ndarray | None = None) -> None:
        self.array = np.zeros(SAMPLE_SIZE) if array is None else array

    @property
    def position(self) -> np.ndarray:
        """t_ref (3,) [m], base frame."""
        return self.array[R_POS]

    @property
    def rotation(self) -> np.ndarray:
        """R_ref (3, 3), platform to base."""
        return self.array[R_ROT].reshape(3, 3)

    @property
    def velocity(self) -> np.ndarray:
        """v_ref (3,) [m/s], base frame."""
        return self.array[R_VEL]

    @property
    def omega(self) -> np.ndarray:
        """omega_ref (3,) [rad/s], base frame."""
        return self.array[R_OMEGA]

    @property
    def acceleration(self) -> np.ndarray:
        """d2t_ref/dt2 (3,) [m/s^2], base frame."""
        return self.array[R_ACC]

    @property
    def alpha(self) -> np.ndarray:
        """alpha_ref (3,) [rad/s^2], base frame."""
        return self.array[R_ALPHA]

    @property
    def lengths(self) -> np.ndarray:
        """Desired leg lengths (6,) [m] (inverse kinematics of the reference pose)."""
        return self.array[R_LEN]

    @property
    def rates(self) -> np.ndarray:
        """Desired leg rates dL/dt (6,) [m/s] (eq. 13 at the reference twist)."""
        return self.array[R_RATE]


@njit
def _sample_into(breaks, coeffs, base, plat, fixed, use_fixed, t, out):
    """Evaluate the reference at time t into ``out`` (SAMPLE_SIZE,)."""
    m = breaks.size - 1
    k = coeffs.shape[0]
    if t <= breaks[0]:
        i, dt, moving = 0, 0.0, False
    elif t >= breaks[m]:
        i, dt, moving = m - 1, breaks[m] - breaks[m - 1], False
    else:
        i = np.searchsorted(breaks, t, side='right') - 1
        dt, moving = t - breaks[i], True
    p = np.zeros(6)
    d1 = np.zeros(6)
    d2 = np.zeros(6)
    for j in range(6):
        v, a, b = 0.0, 0.0, 0.0
        for n in range(k):   # Horner with first and second derivative
            b = b * dt + a
            a = a * dt + v
            v = v * dt + coeffs[n, i, j]
        p[j] = v
        if moving:
            d1[j] = a
            d2[j] = 2.0 * b
    cx, sx = np.cos(p[3]), np.sin(p[3])
    cy, sy = np.cos(p[4]), np.sin(p[4])
    cz, sz = np.cos(p[5]), np.sin(p[5])
    rot = ((cz * cy, cz * sy * sx - sz * cx, cz * sy * cx + sz * sx),
           (sz * cy, sz * sy * sx + cz * cx, sz * sy * cx - cz * sx),
           (-sy, cy * sx, cy * cx))
    # omega = E(theta) dtheta/dt; alpha = E ddtheta + dE/dt dtheta
    e = ((cy * cz, -sz, 0.0), (cy * sz, cz, 0.0), (-sy, 0.0, 1.0))
    ty, tz = d1[4], d1[5]
    de = ((-sy * ty * cz - cy * sz * tz, -cz * tz, 0.0),
          (-sy * ty * sz + cy * cz * tz, -sz * tz, 0.0),
          (-cy * ty, 0.0, 0.0))
    for r in range(3):
        out[I_POS + r] = p[r]
        out[I_VEL + r] = d1[r]
        out[I_ACC + r] = d2[r]
        w = 0.0
        al = 0.0
        for c in range(3):
            out[I_ROT + 3 * r + c] = rot[r][c]
            w += e[r][c] * d1[3 + c]
            al += e[r][c] * d2[3 + c] + de[r][c] * d1[3 + c]
        out[I_OMEGA + r] = w
        out[I_ALPHA + r] = al
    pos = (p[0], p[1], p[2])
    vel = (d1[0], d1[1], d1[2])
    omega = (out[I_OMEGA], out[I_OMEGA + 1], out[I_OMEGA + 2])
    for leg in range(6):
        g = leg_kernel(rot, pos, vel, omega, base, plat, leg)
        out[I_LEN + leg] = fixed[leg] if use_fixed else g[3]
        out[I_RATE + leg] = g[10]


@njit
def _sample_many(breaks, coeffs, base, plat, fixed, use_fixed, times):
    out = np.empty((times.size, SAMPLE_SIZE))
    for n in range(times.size):
        _sample_into(breaks, coeffs, base, plat, fixed, use_fixed, times[n], out[n])
    return out


def _leg_accelerations(mech, samples):
    """d2L/dt2 of every leg at each sample (N, 6): s . a_P + (|dS/dt|^2 - (dL/dt)^2) / L,
    a_P = a + alpha x q + omega x (omega x q) (eqs. 16-22)."""
    rot = samples[:, R_ROT].reshape(-1, 3, 3)
    q = np.einsum('nij,kj->nki', rot, mech.leg_platform_points)
    S = q + samples[:, None, R_POS] - mech.base_points[None]
    L = np.linalg.norm(S, axis=2)
    s = S / L[..., None]
    w = np.broadcast_to(samples[:, None, R_OMEGA], q.shape)
    sdot = np.cross(w, q) + samples[:, None, R_VEL]
    alpha = np.broadcast_to(samples[:, None, R_ALPHA], q.shape)
    a_p = samples[:, None, R_ACC] + np.cross(alpha, q) + np.cross(w, np.cross(w, q))
    ldot = np.einsum('nki,nki->nk', s, sdot)
    return np.einsum('nki,nki->nk', s, a_p) + (np.einsum('nki,nki->nk', sdot, sdot) - ldot ** 2) / L


class Reference:
    """A reference motion: ``sample(t)`` gives pose, twist, accelerations and
    the desired leg lengths and rates at time t [s] (from the reference's own
    time 0).

    Built by ``from_poses``, ``constant_pose`` or ``constant_lengths`` rather
    than directly.

    Args:
        mech: the mechanism (geometry for the inverse kinematics).
        breaks: (m + 1,) the pieces' start times [s], increasing.
        coeffs: (k, m, 6) polynomial coefficients per piece and pose
            coordinate, highest power first (scipy's ``PPoly`` layout).
        fixed_lengths: (6,) desired leg lengths to report instead of the
            pose's inverse kinematics (a leg setpoint).
        kind: ``'trajectory'``, ``'pose'`` or ``'lengths'``.
    """

    def __init__(self, mech: Mechanism, breaks: ArrayLike, coeffs: ArrayLike,
                 fixed_lengths: ArrayLike | None = None, kind: str = 'trajectory') -> None:
        self.mech = mech
        self.breaks = np.ascontiguousarray(breaks, dtype=float)
        self.coeffs = np.ascontiguousarray(coeffs, dtype=float)
        self._base = np.ascontiguousarray(mech.base_points, dtype=float)
        self._plat = np.ascontiguousarray(mech.leg_platform_points, dtype=float)
        self._use_fixed = fixed_lengths is not None
        self._fixed = (np.array(fixed_lengths, dtype=float) if self._use_fixed else np.zeros(6))
        self.kind = kind
        self.constant = kind != 'trajectory'

    @property
    def duration(self) -> float:
        """Time of the last pose [s]; the last pose holds after it."""
        return float(self.breaks[-1]) if not self.constant else 0.0

    def sample(self, t: float, out: np.ndarray | None = None) -> np.ndarray:
        """The reference at one time.

        Args:
            t: the time [s] from the reference's time 0.
            out: (SAMPLE_SIZE,) float array to write into (no allocation).

        Returns:
            The sample (SAMPLE_SIZE,) (``out`` when given), laid out as ``R_*``.
        """
        if out is None:
            out = np.empty(SAMPLE_SIZE)
        _sample_into(self.breaks, self.coeffs, self._base, self._plat, self._fixed,
                     self._use_fixed, float(t), out)
        return out

    def sample_many(self, times: ArrayLike) -> np.ndarray:
        """The samples (N, SAMPLE_SIZE) at the times (N,) [s]."""
        return _sample_many(self.breaks, self.coeffs, self._base, self._plat, self._fixed,
                            self._use_fixed, np.ascontiguousarray(times, dtype=float))

    def poses(self, times: ArrayLike) -> np.ndarray:
        """(N, 6) x, y, z, theta_x, theta_y, theta_z at the times (N,) [s] (the CSV layout)."""
        s = self.sample_many(times)
        return np.hstack([s[:, R_POS], euler_from_matrix(s[:, R_ROT].reshape(-1, 3, 3))])

    # -- construction ---------------------------------------------------------
    @classmethod
    def constant_pose(cls, mech: Mechanism, position: ArrayLike,
                      rotation: ArrayLike) -> Reference:
        """Hold one pose: t (3,) [m], R (3, 3)."""
        theta = euler_from_matrix(np.asarray(rotation, float))
        pose = np.concatenate([np.asarray(position, float), theta])
        return cls(mech, [0.0, 1.0], pose[None, None, :], kind='pose')

    @classmethod
    def constant_lengths(cls, mech: Mechanism, lengths: ArrayLike,
                         near: tuple[ArrayLike, ArrayLike] | None = None) -> Reference:
        """Hold leg lengths (a leg setpoint).

        Args:
            mech: the mechanism.
            lengths: (6,) [m], the desired lengths exactly.
            near: (position (3,), rotation (3, 3)): the pose is the forward
                kinematics of ``lengths`` nearest it (default: the machine's
                ``Mechanism.neutral_pose``; a run passes its initial pose); NaN where
                they admit no assembly.

        Returns:
            The reference (``kind`` ``'lengths'``).
        """
        fk = ForwardKinematics(mech)
        lengths = np.array(lengths, dtype=float)
        try:
            mode = fk.nearest(lengths, *near) if near is not None else fk.all_modes(lengths)[0]
            position, rotation = mode.position, mode.rotation
        except ValueError:      # no assembly: a law that needs the pose gets NaN
            position, rotation = np.full(3, np.nan), np.eye(3)
        ref = cls.constant_pose(mech, position, rotation)
        return cls(mech, ref.breaks, ref.coeffs, fixed_lengths=lengths, kind='lengths')

    @classmethod
    def from_poses(cls, mech: Mechanism, times: ArrayLike, poses: ArrayLike,
                   velocities: ArrayLike | None = None,
                   accelerations: ArrayLike | None = None) -> Reference:
        """A reference through given poses (module docstring: the interpolation).

        Args:
            mech: the mechanism.
            times: (N,) [s], from 0 or later, increasing.
            poses: (N, 6) x, y, z [m], theta_x, theta_y, theta_z [rad].
            velocities: (N, 6) d/dt of the same coordinates, or None.
            accelerations: (N, 6) their second derivatives (with ``velocities``), or None.

        Returns:
            The reference, not yet checked (``check``).

        Raises:
            ReferenceError: bad shapes, times or values.
        """
        # Here, not at the top: scipy.interpolate costs every controller's start
        # 0.16-0.3 s (measured after laws), and most runs follow no trajectory.
        # lazy: scipy.interpolate costs 825 ms; only from_poses needs it
        from scipy.interpolate import BPoly, CubicSpline, PPoly
        times = np.asarray(times, dtype=float)
        poses = np.asarray(poses, dtype=float)
        if times.ndim != 1 or poses.shape != (times.size, 6) or times.size == 0:
            raise ReferenceError('expected N times and N poses of 6 values, got %s and %s'
                                 % (times.shape, poses.shape))
        for name, arr in (('t', times), ('pose', poses), ('velocity', velocities),
                          ('acceleration', accelerations)):
            if arr is not None and not np.all(np.isfinite(arr)):
                raise ReferenceError('%s holds NaN or Inf' % name)
        if times[0] < 0:
            raise ReferenceError('t must start at 0 or later, got %g' % times[0])
        bad = np.flatnonzero(np.diff(times) <= 0)
        if bad.size:
            raise ReferenceError('t must increase: %g s follows %g s'
                                 % (times[bad[0] + 1], times[bad[0]]))
        if times.size == 1:
            return cls(mech, [times[0], times[0] + 1.0], poses[None, :1, :])
        if velocities is None:
            pp = CubicSpline(times, poses, bc_type='clamped')
            return cls(mech, pp.x, pp.c)
        cols = [poses, np.asarray(velocities, float)]
        if accelerations is not None:
            cols.append(np.asarray(accelerations, float))
        pieces = []
        for j in range(6):
            derivs = np.stack([c[:, j] for c in cols], axis=1)
            pieces.append(PPoly.from_bernstein_basis(BPoly.from_derivatives(times, derivs)))
        return cls(mech, pieces[0].x, np.stack([p.c for p in pieces], axis=2))

    # -- checks ---------------------------------------------------------------
    def check(self, max_leg_speed: float = 0.0, max_leg_acceleration: float = 0.0,
              step: float = 1.0e-3) -> None:
        """Refuse (ReferenceError naming the time and leg) a reference that puts a
        leg outside the stroke anywhere, or, where the limits are > 0, moves a leg
        faster than ``max_leg_speed`` [m/s] or accelerates it more than
        ``max_leg_acceleration`` [m/s^2]. Checked at every pose given and on a
        grid of ``step`` seconds (at least 10 points between two poses).

        Args:
            max_leg_speed: [m/s], 0: no limit.
            max_leg_acceleration: [m/s^2], 0: no limit.
            step: the grid [s].

        Raises:
            ReferenceError: the first time and leg that break a limit.
        """
        mech = self.mech
        b = self.breaks
        if self.constant:
            grid = b[:1]
        else:
            fine = [np.linspace(b[i], b[i + 1], max(10, int(np.ceil((b[i + 1] - b[i]) / step))),
                                endpoint=False) for i in range(b.size - 1)]
            grid = np.concatenate(fine + [b[-1:]])
            if grid.size > 2_000_000:
                raise ReferenceError('reference too long to check (%d samples)' % grid.size)
        s = self.sample_many(grid)
        L = s[:, R_LEN]
        if not np.all(np.isfinite(L)):
            raise ReferenceError('the reference pose is not defined (no assembly for these '
                                 'leg lengths)')
        checks = [('stroke', (L < mech.leg_length_min) | (L > mech.leg_length_max))]
        if max_leg_speed > 0:
            checks.append(('speed', np.abs(s[:, R_RATE]) > max_leg_speed))
        if max_leg_acceleration > 0:
            checks.append(('acceleration',
                           np.abs(_leg_accelerations(mech, s)) > max_leg_acceleration))
        for what, bad in checks:
            if not bad.any():
                continue
            k, leg = np.argwhere(bad)[0]
            t = grid[k]
            if what == 'stroke':
                why = 'length %.4f m is outside the stroke [%g, %g]' % (
                    L[k, leg], mech.leg_length_min, mech.leg_length_max)
            elif what == 'speed':
                why = 'speed %.4g m/s exceeds max_leg_speed %g' % (
                    abs(s[k, R_RATE][leg]), max_leg_speed)
            else:
                why = 'acceleration exceeds max_leg_acceleration %g m/s^2' % max_leg_acceleration
            raise ReferenceError('at t = %.4f s, leg_%d %s' % (t, leg + 1, why))
