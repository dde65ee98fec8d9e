"""What the poses determine (``calibration``, "Identifiability"): the
singular value decomposition of the whitened Jacobian at the drawing,
the combinations the poses cannot see or see worse than the drawing, each
named by the parameters it moves.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from numpy.typing import ArrayLike

from stewart63_ros.core.machine.calibration_model import (
    STRUCTURAL_RTOL,
    Measurements,
    NoiseModel,
    geometry_of,
    parameter_jacobian,
    parameter_names,
    predict_readings,
    whitening,
)
from stewart63_ros.core.mechanics.rotation import (
    rotvec_from_rotation,
)


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
