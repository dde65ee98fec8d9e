"""Calibration: the machine's geometry and its sensors' zero offsets from measured poses.

The model (docs/calibration.md). A tracker registered to the base and the
platform frames measures the platform pose (t_n, R_n); at the same moment the
six length sensors read

    reading_ni = |t_n + R_n p_k - b_i| + o_i,     k the joint of leg i,     (1)

eq. (5) plus ``leg_length_offset`` o_i (a sensor reads the true length plus
its zero offset). The parameters are the base points b_i (18), the
platform points (a 6-3's three vertices p_k, 9, k = ``LEG_VERTEX[i]``; a
6-6's six joints p_i, 18, k = i) and the offsets o_i (6): 33 for a 6-3, 42
for a 6-6, all in metres, so the Jacobian needs no column scaling: a
singular value compares metres of reading with metres of parameter. The
parameter vector's length says which (``platform_rows``): a 6-3 drawing
fitted as a 6-6 (``parameter_vector(mech, '6-6')``) starts with each
vertex as two coincident joints, which the fit may pull apart.

Noise and weights. The tracker's errors sit in the pose, so the six
residuals of one pose are correlated: a pose error (dt, dphi) moves reading i
by s_i . dt + (q_i x s_i) . dphi (the rows of the fk Jacobian, eq. 13). Each
pose's residuals are whitened with the covariance this gives
(``NoiseModel``: the tracker's position and angle noise, and the sensors'
own), so the fit is a generalised least squares and its covariance is
(J^T J)^-1 of the whitened Jacobian times the residual variance, which the
fit estimates (``noise_scale``: 1 when the stated noise is the real one).

Robust loss: Huber, at 3 whitened standard deviations. It is the squared
residual inside (every Gaussian residual but one in 370), so for clean data
the fit and its covariance are plain least squares; a residual beyond it (a
tracker glitch, a sample of a moving platform) pulls with a constant force
instead of a growing one. Its covariance is Huber's (Robust Statistics,
1981, eq. 7.6.4): the sum of psi^2 over the degrees of freedom, divided by
the squared fraction of residuals inside, with his small-sample factor K:
for clean data exactly the least-squares one.

Identifiability. The tracker fixes both frames, so no gauge freedom
remains: every one of the 33 (42) parameters is a physical distance in a frame
the tracker defines, and none is fixed by convention. (A 6-6's legs share no
parameter: each leg's seven, b_i, p_i and o_i, are seen by its own readings
only.) What the poses may leave undetermined is read from the singular value
decomposition of the whitened Jacobian at the drawing:

- a singular value below ``STRUCTURAL_RTOL`` times the largest: a
  combination the poses cannot see at all (all poses level: a vertex and
  its two base points moving together; a 6-6: each joint with its base
  point, 18 combinations instead of 9). ``fit`` refuses, naming it;
- a combination whose standard deviation (noise / singular value) would
  exceed ``tolerance`` (how far the machine may be from its drawing): the
  data know it worse than the drawing does. It is held at the drawing's
  value (the fit moves only in the other directions) and named. Poses close
  together leave the base point moved along its leg against that leg's
  offset (docs/calibration.md): ``calibrate plan`` chooses poses that
  determine it.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from stewart63_ros.core.mechanics.fk import ForwardKinematics
from stewart63_ros.core.mechanics.rotation import (
    rotation_angle_between,
    rotation_from_quaternion,
    rotvec_from_rotation,
)
from stewart63_ros.core.plumbing.legs import LEG_VERTEX
from stewart63_ros.core.plumbing.params import Mechanism, ParameterError

#: The parameter file's key of the sensors' zero offsets (6 numbers, metres).
OFFSET_KEY = 'leg_length_offset'
#: The layouts a fit takes (``mechanism.Mechanism.layout``).
GEOMETRIES = ('6-3', '6-6')


def parameter_names(geometry: str = '6-3') -> tuple[str, ...]:
    """The parameters' names, in the order of the parameter vector.

    Args:
        geometry: '6-3' (platform points p_1 … p_3) or '6-6' (p_1 … p_6).

    Returns:
        33 names for a 6-3, 42 for a 6-6.
    """
    rows = _rows_of(geometry)
    return tuple(['b_%d.%s' % (i + 1, a) for i in range(6) for a in 'xyz']
                 + ['p_%d.%s' % (k + 1, a) for k in range(rows) for a in 'xyz']
                 + ['offset_%d' % (i + 1) for i in range(6)])


def _rows_of(geometry: str) -> int:
    if geometry not in GEOMETRIES:
        raise CalibrationError('geometry must be one of %s, got %r' % (GEOMETRIES, geometry))
    return 3 if geometry == '6-3' else 6


def platform_rows(theta: ArrayLike) -> int:
    """3 (a 6-3's parameter vector, 33 numbers) or 6 (a 6-6's, 42)."""
    size = np.shape(theta)[-1]
    if size not in (33, 42):
        raise CalibrationError('a parameter vector holds 33 numbers (a 6-3) or 42 (a 6-6), '
                               'not %d' % size)
    return (size - 24) // 3


def geometry_of(theta: ArrayLike) -> str:
    """'6-3' or '6-6': the layout of a parameter vector (its length)."""
    return '6-3' if platform_rows(theta) == 3 else '6-6'


def _split(theta):
    """(base (6, 3), platform (3 or 6, 3), offsets (6,)) of a parameter vector."""
    rows = platform_rows(theta)
    return (theta[:18].reshape(6, 3), theta[18:18 + 3 * rows].reshape(rows, 3),
            theta[18 + 3 * rows:])


def _leg_joint(rows: int) -> np.ndarray:
    """The platform point of each leg: ``LEG_VERTEX`` (a 6-3) or leg i's own (a 6-6)."""
    return LEG_VERTEX if rows == 3 else np.arange(6)


#: The 6-3's names, count and slices (the 6-6's: ``parameter_names('6-6')``).
PARAMETER_NAMES: tuple[str, ...] = parameter_names('6-3')
N_PARAMETERS = len(PARAMETER_NAMES)
#: Slices of a 6-3's parameter vector.
BASE, PLATFORM, OFFSETS = slice(0, 18), slice(18, 27), slice(27, 33)
#: A singular value below this times the largest: not seen by the data at all.
STRUCTURAL_RTOL = 1.0e-7
#: The fewest poses ``fit`` accepts: 60 readings for 33 parameters, so that the
#: noise estimate rests on at least 27 degrees of freedom (±14 % in sigma; a
#: 6-6's 42 parameters leave 18, ±17 %).
MIN_POSES = 10
#: A fit whose estimate moves a parameter more than this many tolerances from
#: the drawing diverged: the data are not of this machine (a bad row pulled it).
DIVERGED = 10
#: Huber's threshold, in whitened standard deviations.
HUBER_SCALE = 3.0
#: Default: how far the machine may be from its drawing [m] (a combination the
#: data determine worse than this is held at the drawing).
DEFAULT_TOLERANCE = 0.01


class CalibrationError(ValueError):
    """Measurements or a result that cannot be used; the message says why."""


@dataclasses.dataclass(frozen=True)
class NoiseModel:
    """Standard deviations of the measurement errors.

    Attributes:
        position: tracker position noise per axis [m].
        orientation: tracker angle noise per axis [rad].
        reading: length sensor noise [m].
    """
    position: float = 1.0e-4
    orientation: float = 1.0e-4
    reading: float = 1.0e-5

    def __post_init__(self) -> None:
        for name in ('position', 'orientation', 'reading'):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise CalibrationError('noise %s must be a finite number >= 0, got %r'
                                       % (name, value))
        if self.position == self.orientation == self.reading == 0:
            raise CalibrationError('the noise model needs one non-zero standard deviation')


@dataclasses.dataclass(frozen=True)
class Measurements:
    """Poses measured by the tracker and the six readings at each.

    Attributes:
        positions: (N, 3) t [m], base frame.
        rotations: (N, 3, 3) R, platform to base.
        readings: (N, 6) leg readings [m].
    """
    positions: np.ndarray
    rotations: np.ndarray
    readings: np.ndarray

    @property
    def count(self) -> int:
        """The number of poses."""
        return int(self.positions.shape[0])

    def subset(self, index: ArrayLike) -> Measurements:
        """The poses ``index`` (an index array or a boolean mask).

        Args:
            index: which poses.

        Returns:
            The measurements of those poses.
        """
        return Measurements(self.positions[index], self.rotations[index], self.readings[index])


def measurements(positions: ArrayLike, quaternions: ArrayLike,
                 readings: ArrayLike) -> Measurements:
    """Checked measurements from arrays (quaternions x, y, z, w as in ROS).

    Args:
        positions: (N, 3) [m].
        quaternions: (N, 4) unit quaternions (x, y, z, w); a norm off 1 by
            more than 1e-3 is refused (a wrong column order, a typo).
        readings: (N, 6) [m].

    Returns:
        The measurements.

    Raises:
        CalibrationError: wrong shapes, a NaN or Inf (naming the first row,
            1-based), a quaternion that is not of unit length.
    """
    positions = np.asarray(positions, dtype=float)
    quaternions = np.asarray(quaternions, dtype=float)
    readings = np.asarray(readings, dtype=float)
    n = positions.shape[0] if positions.ndim == 2 else -1
    if (positions.shape != (n, 3) or quaternions.shape != (n, 4)
            or readings.shape != (n, 6)):
        raise CalibrationError('expected N positions (3), quaternions (4) and readings (6), '
                               'got %s, %s, %s' % (positions.shape, quaternions.shape,
                                                   readings.shape))
    table = np.hstack([positions, quaternions, readings])
    bad = np.flatnonzero(~np.all(np.isfinite(table), axis=1))
    if bad.size:
        raise CalibrationError('row %d holds NaN or Inf (%d such rows)' % (bad[0] + 1, bad.size))
    norms = np.linalg.norm(quaternions, axis=1)
    off = np.flatnonzero(np.abs(norms - 1.0) > 1e-3)
    if off.size:
        raise CalibrationError('row %d: the quaternion (qx, qy, qz, qw) has length %.6g, '
                               'not 1' % (off[0] + 1, norms[off[0]]))
    return Measurements(positions, rotation_from_quaternion(quaternions), readings)


def check_plausible(mech: Mechanism, meas: Measurements, tolerance: float = DEFAULT_TOLERANCE,
                    rows: ArrayLike | None = None) -> None:
    """Refuse measurements the machine cannot have made (a unit mistake: millimetres
    read as metres, a column in degrees): a reading outside the stroke, or a pose
    whose legs on the drawing leave it, each by more than the machine may differ
    from its drawing.

    A reading is the true length (inside the stroke: the machine stood there)
    plus the sensor's offset, which the drawing knows to ``tolerance``; a
    pose's legs on the drawing are within 2 ``tolerance`` of the machine's
    (a base point and a platform point, each off by up to ``tolerance``).

    Args:
        mech: the drawing.
        meas: the measurements.
        tolerance: [m] how far the machine may be from its drawing.
        rows: (N,) the row number to name for each pose (default 1, 2, ...).

    Raises:
        CalibrationError: naming the first row, the leg and the value.
    """
    rows = np.arange(1, meas.count + 1) if rows is None else np.asarray(rows)
    low, high = mech.leg_length_min, mech.leg_length_max
    readings = meas.readings - mech.leg_length_offset
    bad = np.argwhere((readings < low - tolerance) | (readings > high + tolerance))
    if bad.size:
        n, i = bad[0]
        raise CalibrationError(
            'row %d: leg_%d reads %.6g m, outside the stroke [%g, %g] m by more than the '
            'tolerance %g m (%s): not a reading of this machine (millimetres for '
            'metres?)' % (rows[n], i + 1, meas.readings[n, i], low, high, tolerance,
                          _rows_count(bad)))
    legs, _ = _legs(parameter_vector(mech), meas)
    lengths = np.linalg.norm(legs, axis=2)
    slack = 2 * tolerance
    bad = np.argwhere((lengths < low - slack) | (lengths > high + slack))
    if bad.size:
        n, i = bad[0]
        raise CalibrationError(
            'row %d: the pose (%.6g, %.6g, %.6g) m puts leg_%d at %.6g m on the drawing, '
            'outside the stroke [%g, %g] m by more than %g m (%s): no assembly of '
            'this machine reaches it (millimetres for metres? a tracker not registered to '
            'the base frame?)' % (rows[n], *meas.positions[n], i + 1, lengths[n, i], low,
                                  high, slack, _rows_count(bad)))


def _rows_count(bad) -> str:
    count = len(np.unique(bad[:, 0]))
    return '1 such row' if count == 1 else '%d such rows' % count


def worst_rows(theta: ArrayLike, meas: Measurements, count: int = 3,
               rows: ArrayLike | None = None) -> list[int]:
    """The rows whose readings the parameters ``theta`` predict worst.

    Args:
        theta: (33,) or (42,) parameters; meas: the measurements.
        count: how many rows.
        rows: (N,) the row number of each pose (default 1, 2, ...).

    Returns:
        Row numbers, the worst first.
    """
    rows = np.arange(1, meas.count + 1) if rows is None else np.asarray(rows)
    worst = np.max(np.abs(predict_readings(theta, meas) - meas.readings), axis=1)
    return [int(rows[n]) for n in np.argsort(-worst)[:count]]


# -- the model -----------------------------------------------------------------
def parameter_vector(mech: Mechanism, geometry: str | None = None) -> np.ndarray:
    """The parameters of a mechanism: b (18), p (9 or 18), offsets (6) [m].

    Args:
        mech: the mechanism (its ``leg_length_offset``).
        geometry: the layout to fit (default: the mechanism's own). '6-6' of
            a 6-3 gives each leg its own joint, the pair's two at their
            vertex, free to come apart in a fit; '6-3' of a 6-6 is refused
            (its joints cannot be merged without a choice the data should make).

    Returns:
        (33,) or (42,) the parameter vector, ordered as ``parameter_names(geometry)``.

    Raises:
        CalibrationError: a 6-6 asked to be fitted as a 6-3, or an unknown geometry.
    """
    geometry = geometry or mech.layout
    _rows_of(geometry)
    if geometry == '6-3' and mech.layout == '6-6':
        raise CalibrationError('a 6-6 cannot be fitted as a 6-3 (its six platform joints '
                               'are not three vertices): fit it as a 6-6')
    plat = mech.platform_points if geometry == mech.layout else mech.leg_platform_points
    return np.concatenate([np.ravel(mech.base_points), np.ravel(plat), mech.leg_length_offset])


def mechanism_with(mech: Mechanism, theta: ArrayLike) -> Mechanism:
    """``mech`` with the geometry and offsets of the parameter vector, validated.

    Args:
        mech: the mechanism to start from (masses, stroke, ... are kept).
        theta: (33,) or (42,) parameters: the new mechanism is a 6-3 or a 6-6.

    Returns:
        The new mechanism.

    Raises:
        ParameterError: the parameters describe an impossible mechanism
            (``mechanism.validated`` names the key).
    """
    base, plat, offsets = _split(np.asarray(theta, dtype=float))
    return mech.replace(base_points=base, platform_points=plat,
                        **{OFFSET_KEY: offsets.tolist()})


def _legs(theta, meas):
    """Leg vectors S (N, 6, 3) and the joints q = R p_k (N, 6, 3), base frame."""
    base, plat, _ = _split(theta)
    plat = plat[_leg_joint(len(plat))]
    q = np.einsum('nab,ib->nia', meas.rotations, plat)
    legs = meas.positions[:, None, :] + q - base[None]
    return legs, q


def predict_readings(theta: ArrayLike, meas: Measurements) -> np.ndarray:
    """Readings the model (1) predicts at the measured poses.

    Args:
        theta: (33,) or (42,) parameters.
        meas: the poses (their readings are not used).

    Returns:
        (N, 6) predicted readings [m].
    """
    theta = np.asarray(theta, dtype=float)
    legs, _ = _legs(theta, meas)
    return np.linalg.norm(legs, axis=2) + _split(theta)[2]


def parameter_jacobian(theta: ArrayLike, meas: Measurements) -> np.ndarray:
    """d reading / d parameters, analytic: -s_i for b_i, R^T s_i for p_k, 1 for o_i.

    Args:
        theta: (P,) parameters (33: a 6-3, 42: a 6-6).
        meas: the poses.

    Returns:
        (N, 6, P) the Jacobian, pose by pose, leg by leg (s_i = S_i / L_i).
    """
    theta = np.asarray(theta, dtype=float)
    rows = platform_rows(theta)
    legs, _ = _legs(theta, meas)
    unit = legs / np.linalg.norm(legs, axis=2, keepdims=True)
    n = meas.count
    jac = np.zeros((n, 6, theta.size))
    through = np.einsum('nba,nib->nia', meas.rotations, unit)      # R^T s_i
    offsets = 18 + 3 * rows
    for i in range(6):
        jac[:, i, 3 * i:3 * i + 3] = -unit[:, i]
        k = _leg_joint(rows)[i]
        jac[:, i, 18 + 3 * k:18 + 3 * k + 3] = through[:, i]
        jac[:, i, offsets + i] = 1.0
    return jac


def pose_jacobian(theta: ArrayLike, meas: Measurements) -> np.ndarray:
    """d reading / d pose: rows [s_i, q_i x s_i] (eq. 13), for the pose perturbed
    as t + dt, exp([dphi]x) R (dphi in the base frame, as the tracker's noise).

    Args:
        theta: (33,) or (42,) parameters.
        meas: the poses.

    Returns:
        (N, 6, 6) per pose.
    """
    legs, q = _legs(np.asarray(theta, dtype=float), meas)
    unit = legs / np.linalg.norm(legs, axis=2, keepdims=True)
    return np.concatenate([unit, np.cross(q, unit)], axis=2)


def whitening(theta: ArrayLike, meas: Measurements, noise: NoiseModel) -> np.ndarray:
    """Per pose, W with W Sigma W^T = I, Sigma the covariance of its six residuals.

    Sigma = sp^2 G_t G_t^T + sa^2 G_r G_r^T + sr^2 I (G = ``pose_jacobian``).

    Args:
        theta: (33,) or (42,) the parameters the weights are computed at.
        meas: the poses.
        noise: the measurement noise.

    Returns:
        (N, 6, 6) inverse Cholesky factors.
    """
    g = pose_jacobian(theta, meas)
    sigma = (noise.position ** 2 * np.einsum('nia,nja->nij', g[:, :, :3], g[:, :, :3])
             + noise.orientation ** 2 * np.einsum('nia,nja->nij', g[:, :, 3:], g[:, :, 3:])
             + noise.reading ** 2 * np.eye(6))
    chol = np.linalg.cholesky(sigma)
    return np.linalg.inv(chol)


# -- identifiability -------------------------------------------------------------
def describe_direction(vector: ArrayLike, share: float = 0.1) -> str:
    """A combination of parameters in words: its largest components, signed.

    Args:
        vector: (P,) a unit direction in parameter space (33: a 6-3, 42: a 6-6).
        share: components below this (in absolute value) are left out.

    Returns:
        e.g. "+0.63 b_1.x -0.41 b_1.z +0.66 offset_1".
    """
    vector = np.asarray(vector, dtype=float)
    vector = vector * (1 if vector[np.argmax(np.abs(vector))] > 0 else -1)
    order = np.argsort(-np.abs(vector))
    names = parameter_names(geometry_of(vector))
    parts = ['%+.2f %s' % (vector[j], names[j]) for j in order
             if abs(vector[j]) >= share]
    return ' '.join(parts)


def parameter_groups(directions: np.ndarray, share: float = 0.05) -> list[dict]:
    """The parameters a set of directions moves, grouped by which move together.

    Two parameters are in one group when the projector onto the directions
    couples them; each group's ``count`` is how many independent combinations
    of its parameters the directions hold.

    Args:
        directions: (P, h) orthonormal columns.
        share: a parameter whose diagonal of the projector is below this is left out.

    Returns:
        [{'parameters': [names], 'count': int}] largest group first.
    """
    proj = directions @ directions.T
    diag = np.diag(proj)
    names = parameter_names(geometry_of(np.zeros(len(directions))))
    involved = [j for j in range(len(directions)) if diag[j] >= share]
    groups: list[list[int]] = []
    seen: set[int] = set()
    for j in involved:
        if j in seen:
            continue
        group, todo = [], [j]
        seen.add(j)
        while todo:
            a = todo.pop()
            group.append(a)
            for b in involved:
                if b not in seen and abs(proj[a, b]) >= share * np.sqrt(diag[a] * diag[b]):
                    seen.add(b)
                    todo.append(b)
        groups.append(sorted(group))
    out = [{'parameters': [names[j] for j in g],
            'count': int(round(np.trace(proj[np.ix_(g, g)])))} for g in groups]
    return sorted(out, key=lambda g: -len(g['parameters']))


def _pose_cause(meas: Measurements, geometry: str = '6-3') -> str:
    """Why poses may leave parameters unseen, in words ('' if nothing obvious)."""
    rotvec = rotvec_from_rotation(meas.rotations)
    tilt = np.linalg.norm(rotvec[:, :2], axis=1)
    heights = np.ptp(meas.positions[:, 2])
    angles = np.ptp(rotvec, axis=0)
    causes = []
    if np.all(angles < 1e-6):
        causes.append('every pose has the same orientation (%s can move together): tilt '
                      'and turn the platform' % ('each vertex and its two base points'
                                                 if geometry == '6-3' else
                                                 'each platform joint and its base point'))
    elif np.all(tilt < 1e-6):
        causes.append('every pose is level: tilt the platform')
    if heights < 1e-6:
        causes.append('every pose is at one height: vary z')
    return '; '.join(causes)


@dataclasses.dataclass
class Identifiability:
    """What a set of poses can determine (the SVD of the whitened Jacobian).

    Attributes:
        singular_values: (P,) of the whitened Jacobian [1/m], descending (P: 33
            for a 6-3, 42 for a 6-6).
        directions: (P, P) right singular vectors, as columns.
        predicted_std: (P,) noise / singular value per direction [m], for
            the stated noise (inf for a structural null direction).
        structural: indices of the directions the data cannot see at all.
    """
    singular_values: np.ndarray
    directions: np.ndarray
    predicted_std: np.ndarray
    structural: np.ndarray

    def weak(self, tolerance: float, noise_scale: float = 1.0) -> np.ndarray:
        """Indices of the directions known worse than ``tolerance``.

        Args:
            tolerance: [m] how far the machine may be from its drawing.
            noise_scale: the fitted noise over the stated noise.

        Returns:
            Indices into ``directions``' columns (structural ones included).
        """
        return np.flatnonzero(self.predicted_std * noise_scale > tolerance)


def identifiability(theta: ArrayLike, meas: Measurements, noise: NoiseModel) -> Identifiability:
    """The SVD of the whitened identification Jacobian at ``theta``.

    Args:
        theta: (33,) or (42,) parameters (the drawing's).
        meas: the poses.
        noise: the measurement noise (the whitening).

    Returns:
        The analysis.
    """
    jac = _whitened_jacobian(theta, meas, whitening(theta, meas, noise))
    count = jac.shape[1]
    _, sv, vt = np.linalg.svd(jac, full_matrices=False)
    if sv.size < count:
        sv = np.concatenate([sv, np.zeros(count - sv.size)])
        vt = np.linalg.svd(np.vstack([jac, np.zeros((count, count))]))[2]
    structural = np.flatnonzero(sv <= STRUCTURAL_RTOL * sv[0])
    with np.errstate(divide='ignore'):
        std = np.where(sv > STRUCTURAL_RTOL * sv[0], 1.0 / np.maximum(sv, 1e-300), np.inf)
    return Identifiability(sv, vt.T, std, structural)


def _whitened_jacobian(theta, meas, white):
    return np.einsum('nij,njp->nip', white, parameter_jacobian(theta, meas)).reshape(
        -1, np.size(theta))


def _whitened_residuals(theta, meas, white):
    raw = predict_readings(theta, meas) - meas.readings
    return np.einsum('nij,nj->ni', white, raw).ravel()


# -- the fit ---------------------------------------------------------------------
@dataclasses.dataclass
class Fit:
    """A calibration's result.

    Attributes:
        nominal: (P,) the drawing's parameters (P: 33 for a 6-3, 42 for a 6-6).
        estimate: (P,) the fitted ones.
        covariance: (P, P) of the estimate [m^2] (zero along held directions).
        held: (P, h) the directions held at the drawing (orthonormal columns).
        held_std: (h,) each held direction's standard deviation from the data
            [m], as judged against the tolerance.
        analysis: the identifiability of the poses fitted.
        noise_scale: fitted noise / stated noise (1: the stated noise is right).
        rms_before: RMS of reading residuals at the drawing [m].
        rms_after: RMS of reading residuals at the estimate [m].
        outliers: residuals beyond Huber's threshold at the estimate.
        residual_count: readings fitted.
        cost_evaluations: the solver's function evaluations.
    """
    nominal: np.ndarray
    estimate: np.ndarray
    covariance: np.ndarray
    held: np.ndarray
    held_std: np.ndarray
    analysis: Identifiability
    noise_scale: float
    rms_before: float
    rms_after: float
    outliers: int
    residual_count: int
    cost_evaluations: int

    @property
    def std(self) -> np.ndarray:
        """(P,) standard deviation of each parameter [m]."""
        return np.sqrt(np.maximum(np.diag(self.covariance), 0.0))

    @property
    def geometry(self) -> str:
        """'6-3' or '6-6': the layout fitted."""
        return geometry_of(self.estimate)

    @property
    def names(self) -> tuple[str, ...]:
        """The parameters' names (``parameter_names``)."""
        return parameter_names(self.geometry)


def _check_structural(analysis: Identifiability, meas: Measurements) -> None:
    if not analysis.structural.size:
        return
    groups = parameter_groups(analysis.directions[:, analysis.structural])
    named = '; '.join('%d of {%s}' % (g['count'], ', '.join(g['parameters'])) for g in groups)
    cause = _pose_cause(meas, geometry_of(analysis.singular_values))
    raise CalibrationError('these poses leave %d combination%s unidentifiable: %s%s'
                           % (analysis.structural.size,
                              '' if analysis.structural.size == 1 else 's', named,
                              ' (%s)' % cause if cause else ''))


def _huber_covariance(jac: np.ndarray, residuals: np.ndarray, threshold: float) -> tuple:
    """Huber's covariance of an M-estimate (module doc), and the outlier count."""
    m, p = jac.shape
    inside = np.abs(residuals) <= threshold
    kappa = max(float(inside.mean()), 1.0 / m)
    psi = np.clip(residuals, -threshold, threshold)
    correction = 1.0 + p * (1.0 - kappa) / (m * kappa)
    variance = correction ** 2 * float(psi @ psi) / (m - p) / kappa ** 2
    info = jac.T @ jac
    return variance * np.linalg.inv(info), variance, int(m - inside.sum())


def _check_converged(solution, nominal, estimate, meas, tolerance, rows) -> None:
    """Refuse a fit that did not converge, diverged (a parameter more than
    ``DIVERGED`` tolerances from the drawing) or explains the readings no
    better than ``tolerance`` RMS (the data are not of this machine: swapped
    columns, a tracker in another frame), naming the rows predicted worst."""
    finite = bool(np.all(np.isfinite(estimate)))
    theta = estimate if finite else nominal
    change = np.abs(theta - nominal)
    worst = int(np.argmax(change))
    rms = float(np.sqrt(np.mean((predict_readings(theta, meas) - meas.readings) ** 2)))
    if solution.status <= 0 or not finite:
        why = 'did not converge (%s)' % solution.message
    elif change[worst] > DIVERGED * tolerance:
        why = ('diverged: %s moved %.4g m from the drawing, more than %d x the tolerance %g m'
               % (parameter_names(geometry_of(nominal))[worst], change[worst], DIVERGED,
                  tolerance))
    elif rms > tolerance:
        why = ('leaves the readings %.4g m RMS from the model, more than the tolerance %g m: '
               'these are not readings of this machine at these poses' % (rms, tolerance))
    else:
        return
    raise CalibrationError('the fit %s; the rows it predicts worst: %s'
                           % (why, ', '.join(map(str, worst_rows(theta, meas, rows=rows)))))


def fit(mech: Mechanism, meas: Measurements, noise: NoiseModel | None = None,
        tolerance: float = DEFAULT_TOLERANCE, rows: ArrayLike | None = None,
        geometry: str | None = None) -> Fit:
    """Identify base points, platform points and offsets from measurements.

    Steps (module doc): refuse poses that leave a combination unseen; a
    least-squares pass from the drawing gives the noise scale; directions
    the data know worse than ``tolerance`` are held at the drawing; the
    final pass uses Huber's loss in the remaining directions.

    Args:
        mech: the drawing (the starting parameter file's mechanism).
        meas: at least ``MIN_POSES`` poses.
        noise: the measurement noise (default ``NoiseModel()``: 0.1 mm,
            0.1 mrad, 0.01 mm).
        tolerance: [m], see ``Identifiability.weak``.
        rows: (N,) the row number of each pose, for the messages (default 1, 2, ...).
        geometry: the layout to fit (``parameter_vector``; default the drawing's):
            '6-6' of a 6-3 drawing lets each vertex's two joints come apart.

    Returns:
        The fit.

    Raises:
        CalibrationError: a 6-6 drawing fitted as a 6-3, too few poses, poses
            that leave a combination unidentifiable (named), a fit that does
            not converge, diverges (a parameter more than ``DIVERGED``
            tolerances from the drawing) or leaves the readings more than
            ``tolerance`` RMS from the model, naming the rows it predicts worst.
    """
    # lazy: scipy.optimize costs 968 ms; only a fit needs it
    from scipy.optimize import least_squares
    noise = noise or NoiseModel()
    nominal = parameter_vector(mech, geometry)
    count = nominal.size
    if meas.count < MIN_POSES:
        raise CalibrationError('%d poses: the fit needs at least %d (%d parameters, 6 readings '
                               'a pose, and degrees of freedom left to estimate the noise)'
                               % (meas.count, MIN_POSES, count))
    if not (np.isfinite(tolerance) and tolerance > 0):
        raise CalibrationError('tolerance must be a positive number, got %r' % (tolerance,))
    white = whitening(nominal, meas, noise)
    analysis = identifiability(nominal, meas, noise)
    _check_structural(analysis, meas)

    def solve(basis, start, loss, f_scale):
        def residuals(z):
            return _whitened_residuals(nominal + basis @ z, meas, white)

        def jacobian(z):
            return _whitened_jacobian(nominal + basis @ z, meas, white) @ basis
        return least_squares(residuals, start, jac=jacobian, loss=loss, f_scale=f_scale,
                             method='trf', x_scale='jac', xtol=1e-12, ftol=1e-12, gtol=1e-12,
                             max_nfev=200)

    first = solve(np.eye(count), np.zeros(count), 'linear', 1.0)
    m = meas.count * 6
    # The noise from the first pass, robust to a few outliers (MAD), with
    # the degrees of freedom the parameters took.
    mad = 1.4826 * float(np.median(np.abs(first.fun))) * np.sqrt(m / (m - count))
    scale = max(mad, 1e-12)
    weak = analysis.weak(tolerance, scale)
    keep = np.setdiff1d(np.arange(count), weak)
    basis = analysis.directions[:, keep]
    held = analysis.directions[:, weak]
    start = basis.T @ first.x
    final = solve(basis, start, 'huber', HUBER_SCALE * scale)
    estimate = nominal + basis @ final.x
    _check_converged(final, nominal, estimate, meas, tolerance, rows)
    jac = _whitened_jacobian(estimate, meas, white) @ basis
    res = _whitened_residuals(estimate, meas, white)
    cov_z, variance, outliers = _huber_covariance(jac, res, HUBER_SCALE * scale)
    raw_before = predict_readings(nominal, meas) - meas.readings
    raw_after = predict_readings(estimate, meas) - meas.readings
    return Fit(nominal=nominal, estimate=estimate, covariance=basis @ cov_z @ basis.T,
               held=held, held_std=analysis.predicted_std[weak] * scale, analysis=analysis,
               noise_scale=float(np.sqrt(variance)),
               rms_before=float(np.sqrt(np.mean(raw_before ** 2))),
               rms_after=float(np.sqrt(np.mean(raw_after ** 2))), outliers=outliers,
               residual_count=m, cost_evaluations=int(first.nfev + final.nfev))


# -- checks on poses the fit did not see -------------------------------------------
def pose_errors(mech: Mechanism, meas: Measurements) -> dict:
    """Forward kinematics of the readings (offsets removed) against the tracked poses.

    Args:
        mech: the mechanism fk runs on (its ``leg_length_offset`` is removed
            from the readings, as the fk node does).
        meas: readings and the poses the tracker measured.

    Returns:
        {'position_rms_m', 'position_max_m', 'angle_rms_rad', 'angle_max_rad',
        'reading_rms_m', 'poses', 'unsolved'}: the fk pose's distance from the
        tracked one (over the poses fk solves; None if it solves none), the
        RMS of the readings' prediction error, and how many poses fk could not
        solve (readings no assembly closes).
    """
    fk = ForwardKinematics(mech)
    offsets = mech.leg_length_offset
    dpos, dang, unsolved = [], [], 0
    for n in range(meas.count):
        try:
            mode = fk.nearest(meas.readings[n] - offsets, meas.positions[n], meas.rotations[n])
        except ValueError:
            unsolved += 1
            continue
        dpos.append(np.linalg.norm(mode.position - meas.positions[n]))
        dang.append(float(rotation_angle_between(meas.rotations[n][None],
                                                 mode.quaternion[None])[0]))
    dpos, dang = np.array(dpos), np.array(dang)
    pred = predict_readings(parameter_vector(mech), meas) - meas.readings

    def stat(values, how):      # None, not inf or NaN: report.json is strict JSON
        return float(how(values)) if values.size else None
    return {'position_rms_m': stat(dpos, lambda v: np.sqrt(np.mean(v ** 2))),
            'position_max_m': stat(dpos, np.max),
            'angle_rms_rad': stat(dang, lambda v: np.sqrt(np.mean(v ** 2))),
            'angle_max_rad': stat(dang, np.max),
            'reading_rms_m': float(np.sqrt(np.mean(pred ** 2))), 'poses': meas.count,
            'unsolved': unsolved}


def check_assembles(mech: Mechanism, meas: Measurements) -> None:
    """Refuse a calibrated mechanism whose legs at the measured poses lie
    outside the stroke: the machine stood there, so it cannot be the machine.

    Args:
        mech: the calibrated mechanism.
        meas: the poses the machine reached.

    Raises:
        ParameterError: naming the first pose (1-based) and leg.
    """
    legs, _ = _legs(parameter_vector(mech), meas)
    lengths = np.linalg.norm(legs, axis=2)
    bad = np.argwhere((lengths < mech.leg_length_min) | (lengths > mech.leg_length_max))
    if bad.size:
        n, i = bad[0]
        raise ParameterError('base_points', 'the calibrated leg_%d would be %.4f m long at '
                             'measured pose %d, outside the stroke [%g, %g]: not the machine '
                             'that stood there' % (i + 1, lengths[n, i], n + 1,
                                                   mech.leg_length_min, mech.leg_length_max))


def holdout_split(count: int, fraction: float, blocks: int = 25) -> np.ndarray:
    """Which of ``count`` poses (in measuring order) to hold out of the fit.

    The poses are cut into ``blocks`` runs in order and every ``1/fraction``-th
    run is held out, so a held-out pose is not a neighbour in time of a
    fitted one (in a bag, the samples of one hold).

    Args:
        count: poses.
        fraction: the share held out, 0 to 0.5.
        blocks: runs.

    Returns:
        (count,) bool, True for a held-out pose.

    Raises:
        CalibrationError: ``fraction`` outside [0, 0.5].
    """
    if not 0 <= fraction <= 0.5:
        raise CalibrationError('the held-out share must be from 0 to 0.5, got %r' % (fraction,))
    mask = np.zeros(count, dtype=bool)
    if fraction == 0 or count == 0:
        return mask
    runs = np.array_split(np.arange(count), min(count, blocks))
    step = max(2, int(round(1.0 / fraction)))
    for j in range(step - 1, len(runs), step):
        mask[runs[j]] = True
    return mask


def pair_separations(fit_result: Fit) -> list[dict] | None:
    """How far a 6-3's pairs came apart, when a 6-3 drawing was fitted as a 6-6.

    For each vertex k, d = p_{2k} - p_{2k-1} (the joints of legs 2k-1 and 2k):
    its length and that length's standard deviation (g^T C g, g = d / |d| on
    the two joints' coordinates). A separation within two or three standard
    deviations of zero is the data saying the pair is one joint.

    Args:
        fit_result: the fit.

    Returns:
        [{'legs': [2k-1, 2k], 'separation_m', 'std_m'}] for k = 1..3, or None
        unless the fit is a 6-6 whose drawing had each pair's joints together.
    """
    f = fit_result
    if f.geometry != '6-6':
        return None
    nominal = _split(f.nominal)[1]
    if np.max(np.linalg.norm(nominal[1::2] - nominal[0::2], axis=1)) > 0:
        return None
    plat = _split(f.estimate)[1]
    out = []
    for k in range(3):
        d = plat[2 * k + 1] - plat[2 * k]
        size = float(np.linalg.norm(d))
        grad = np.zeros(f.estimate.size)
        unit = d / size if size > 0 else np.zeros(3)
        grad[18 + 6 * k:21 + 6 * k], grad[21 + 6 * k:24 + 6 * k] = -unit, unit
        out.append({'legs': [2 * k + 1, 2 * k + 2], 'separation_m': size,
                    'std_m': float(np.sqrt(max(grad @ f.covariance @ grad, 0.0)))})
    return out


def report(fit_result: Fit, held_out: dict | None = None,
           names: Sequence[str] | None = None) -> dict:
    """The report's JSON content (docs/calibration.md, "The report").

    Args:
        fit_result: the fit.
        held_out: {'before': pose_errors, 'after': pose_errors} or None.
        names: the parameters' names (default the fit's: ``Fit.names``).

    Returns:
        A JSON-ready dict.
    """
    f = fit_result
    names = f.names if names is None else names
    std = f.std
    held_share = np.sum(f.held ** 2, axis=1) if f.held.size else np.zeros(f.estimate.size)
    analysis = f.analysis
    return {
        'geometry': f.geometry,
        'parameters': {name: {'estimate': float(f.estimate[j]), 'nominal': float(f.nominal[j]),
                              'change': float(f.estimate[j] - f.nominal[j]),
                              'std': float(std[j]), 'held_share': float(held_share[j])}
                       for j, name in enumerate(names)},
        'rms_before_m': f.rms_before,
        'rms_after_m': f.rms_after,
        'noise_scale': f.noise_scale,
        'outliers': f.outliers,
        'readings': f.residual_count,
        'unidentifiable': [{'combination': describe_direction(f.held[:, j]),
                            'predicted_std_m': float(f.held_std[j])}
                           for j in range(f.held.shape[1])],
        'singular_values': analysis.singular_values.tolist(),
        'direction_std_m': (analysis.predicted_std * f.noise_scale).tolist(),
        'held_out': held_out,
        'pair_separations': pair_separations(f),
    }
