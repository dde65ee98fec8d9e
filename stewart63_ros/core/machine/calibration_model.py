"""The calibration's model (``calibration`` has the whole story, eq. (1)):
the parameter vector (base points, platform points of a 6-3 or a 6-6, the
sensors' offsets) and its names, the measured poses and readings
(``Measurements``) with their plausibility checks, the readings predicted
from a parameter vector, the Jacobians, and the whitening of a pose's
correlated residuals (``NoiseModel``).
"""
from __future__ import annotations

import dataclasses

import numpy as np
from numpy.typing import ArrayLike

from stewart63_ros.core.mechanics.rotation import (
    rotation_from_quaternion,
)
from stewart63_ros.core.plumbing.legs import LEG_VERTEX
from stewart63_ros.core.plumbing.params import Mechanism

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
