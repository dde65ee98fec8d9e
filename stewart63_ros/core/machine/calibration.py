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

from stewart63_ros.core.machine.calibration_identify import (
    Identifiability,
    _pose_cause,
    _whitened_jacobian,
    _whitened_residuals,
    describe_direction,
    identifiability,
    parameter_groups,
)
from stewart63_ros.core.machine.calibration_model import (
    DEFAULT_TOLERANCE,
    DIVERGED,
    HUBER_SCALE,
    MIN_POSES,
    CalibrationError,
    Measurements,
    NoiseModel,
    _legs,
    _split,
    geometry_of,
    parameter_names,
    parameter_vector,
    predict_readings,
    whitening,
    worst_rows,
)
from stewart63_ros.core.mechanics.fk import ForwardKinematics
from stewart63_ros.core.mechanics.rotation import (
    rotation_angle_between,
)
from stewart63_ros.core.plumbing.params import Mechanism, ParameterError


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
