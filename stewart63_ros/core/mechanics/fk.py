"""Forward kinematics of the platform, a 6-3 or a 6-6: the pose from six leg lengths.

Two solvers, one model (eqs. 2-5: S_i = t + R p_k - b_i, L_i = |S_i|). For a
6-6 (``Mechanism.layout``) ``ForwardKinematics`` hands ``all_modes`` to
core/mechanics/fk66.py (a 40-path homotopy); tracking is the same Newton
kernel for both, as it takes one platform point per leg. What follows is the
6-3's:

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

from stewart63_ros.core.mechanics.fk66 import ForwardKinematics66
from stewart63_ros.core.mechanics.fk_modes import SIDES, _circles, _mode_vertices, _polish_modes
from stewart63_ros.core.mechanics.fk_tracking import (
    FKResult,
    NoAssemblyError,
    _arr,
    _legs,
    _pose_distance,
    _track,
    _twist,
    checked_lengths,
    condition_number,
)
from stewart63_ros.core.plumbing.node_parameters import DEFAULT_COND_THRESHOLD

if TYPE_CHECKING:
    from stewart63_ros.core.mechanics.mechanism import Mechanism

#: Pair k's legs (0-based): legs 2k and 2k+1 meet at vertex k.
PAIRS = ((0, 1), (2, 3), (4, 5))


class ForwardKinematics:
    """Forward kinematics of one mechanism, a 6-3 or a 6-6; constants gathered once here.

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
        if start is None:
            start = mech.neutral_pose()
        self.reference = (_arr(start[0]), _arr(start[1]))
        self.layout = mech.layout
        self._six = None
        if self.layout == '6-6':
            self._six = ForwardKinematics66(self.base, self.legp, self.cond_threshold,
                                            reference=self.reference)
            return
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

    # -- small helpers --------------------------------------------------------
    def check_lengths(self, lengths: ArrayLike) -> np.ndarray:
        """Six finite positive leg lengths as a float array (6,).

        Raises:
            ValueError: not six finite numbers.
            NoAssemblyError: a length that is not positive.
        """
        return checked_lengths(lengths)

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
            ValueError: the mechanism is a 6-6 (its legs meet no common vertex).
        """
        if self._six is not None:
            raise ValueError('circles: a 6-6 has no leg pairs meeting at a vertex')
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
        if self._six is not None:     # a 6-6: every one of the 40 complex modes (fk66)
            self._six.cond_threshold = self.cond_threshold
            return self._six.all_modes(lengths, self.reference if reference is None
                                       else reference)
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
