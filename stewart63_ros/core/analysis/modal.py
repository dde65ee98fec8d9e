"""A linear model's modes and frequency responses (``linear.LinearModel``).

Modes: the eigenvalues of A in pairs (complex conjugates, or two real ones
matched by the shape of their eigenvectors); a pair (l1, l2) has natural
frequency sqrt(l1 l2) / 2 pi and damping ratio -(l1 + l2) / (2 sqrt(l1 l2)),
which holds for an underdamped pair (zeta < 1) and an overdamped one
(zeta > 1) alike. A pair with l1 l2 < 0 (one eigenvalue positive: a negative
stiffness, the platform falls away from the pose) gets sqrt(|l1 l2|) and is
marked unstable.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from numpy.typing import ArrayLike

from stewart63_ros.core.analysis.equilibrium import AnalysisError
from stewart63_ros.core.analysis.linear import LinearModel
from stewart63_ros.core.mechanics.rotation import euler_rate_matrix
from stewart63_ros.core.plumbing.legs import LEG_NAMES


# -- modes ------------------------------------------------------------------------------------
@dataclasses.dataclass
class Modes:
    """The six modes of a linear model, slowest first.

    Attributes:
        frequencies_hz: (6,) sqrt(|l1 l2|) / 2 pi [Hz].
        damping_ratios: (6,) -(l1 + l2) / (2 sqrt(|l1 l2|)).
        mode_shapes: (6, 6) one row per mode, in pose coordinates (x, y, z [m],
            theta_x, theta_y, theta_z [rad]), largest component +1.
        eigenvalues: (6, 2) complex, each mode's pair [1/s].
        stable: (6,) False where the pair has a positive real part.
        pose: (6,) the equilibrium pose.
    """
    frequencies_hz: np.ndarray
    damping_ratios: np.ndarray
    mode_shapes: np.ndarray
    eigenvalues: np.ndarray
    stable: np.ndarray
    pose: np.ndarray

    def to_json(self) -> dict:
        """The modes as plain JSON types.

        Returns:
            {'frequencies_hz', 'damping_ratios', 'mode_shapes', 'pose': lists as
            the attributes, 'stable': six bools, 'eigenvalues': (6, 2) pairs
            [real, imag] [1/s]}.
        """
        return {
            'frequencies_hz': self.frequencies_hz.tolist(),
            'damping_ratios': self.damping_ratios.tolist(),
            'mode_shapes': self.mode_shapes.tolist(),
            'pose': self.pose.tolist(),
            'stable': [bool(s) for s in self.stable],
            'eigenvalues': [[[float(v.real), float(v.imag)] for v in pair]
                            for pair in self.eigenvalues],
        }


def pair_eigenvalues(values: ArrayLike, vectors: np.ndarray) -> list[tuple[int, int]]:
    """Index pairs of the eigenvalues of a second-order system (12 -> 6 pairs).

    Complex conjugates pair with each other. The real eigenvalues left over
    are matched greedily by the shape of their eigenvectors' position parts
    (the largest |cos| of the angle between them first): the two real roots
    of one overdamped (or divergent) mode move the same coordinates.

    Args:
        values: (2n,) eigenvalues [1/s], complex; vectors: (2n, 2n) eigenvectors
            as columns (``np.linalg.eig``), positions in their first n rows.

    Returns:
        n pairs (i, j) of indices into ``values``: the complex pairs first.

    Raises:
        AnalysisError: an odd number of real eigenvalues.
    """
    values = np.asarray(values)
    n = len(values)
    scale = max(1.0, float(np.max(np.abs(values))))
    is_real = np.abs(values.imag) <= 1e-9 * scale
    pairs, used = [], set()
    for i in np.flatnonzero(~is_real & (values.imag > 0)):
        rest = [j for j in np.flatnonzero(~is_real & (values.imag < 0)) if j not in used]
        j = min(rest, key=lambda k: abs(values[k] - np.conj(values[i])))
        pairs.append((int(i), int(j)))
        used.add(j)
    reals = [int(i) for i in np.flatnonzero(is_real)]
    shapes = np.real(vectors[: n // 2, :])
    shapes = shapes / np.maximum(np.linalg.norm(shapes, axis=0), 1e-300)
    while len(reals) >= 2:
        best = max(((a, b) for k, a in enumerate(reals) for b in reals[k + 1:]),
                   key=lambda ab: abs(shapes[:, ab[0]] @ shapes[:, ab[1]]))
        pairs.append(best)
        reals = [k for k in reals if k not in best]
    if reals:
        raise AnalysisError('an odd number of real eigenvalues: not a second-order system')
    return pairs


def pair_figures(l1: complex, l2: complex) -> tuple[float, float, bool]:
    """Natural frequency, damping ratio and stability of an eigenvalue pair.

    Args:
        l1, l2: the pair [1/s] (complex conjugates, or two real roots).

    Returns:
        (sqrt(|l1 l2|) / 2 pi [Hz], -(l1 + l2) / (2 sqrt(|l1 l2|)) (inf for a
        zero frequency), both real parts negative).
    """
    product = (l1 * l2).real
    omega = np.sqrt(abs(product))
    zeta = -(l1 + l2).real / (2.0 * omega) if omega > 0 else np.inf
    stable = bool(max(l1.real, l2.real) < 0)
    return float(omega / (2.0 * np.pi)), float(zeta), stable


def modes(model: LinearModel) -> Modes:
    """The six modes of ``model`` (see the module docstring), slowest first.

    A mode's shape is the position part of the eigenvector of its eigenvalue
    with the larger real part (the slower, or the growing, root), rotation
    converted to Euler-angle increments (d theta = E(theta0)^-1 d phi), made
    real (the phase of its largest component removed) and scaled to +1 there.

    Args:
        model: the linear model (A (12, 12): a second-order system).

    Returns:
        The ``Modes``, six, slowest first.

    Raises:
        AnalysisError: the eigenvalues do not pair (``pair_eigenvalues``).
    """
    values, vectors = np.linalg.eig(model.A)
    e_inv = np.linalg.inv(euler_rate_matrix(model.equilibrium.theta))
    rows = []
    for i, j in pair_eigenvalues(values, vectors):
        lead = i if values[i].real >= values[j].real else j
        shape = vectors[:6, lead].astype(complex)
        shape[3:6] = e_inv @ shape[3:6]
        big = int(np.argmax(np.abs(shape)))
        shape = np.real(shape * np.exp(-1j * np.angle(shape[big])))
        shape = shape / shape[big]
        freq, zeta, stable = pair_figures(values[i], values[j])
        pair = sorted((values[i], values[j]), key=lambda v: (v.real, v.imag))
        rows.append((freq, zeta, shape, pair, stable))
    rows.sort(key=lambda row: row[0])
    return Modes(np.array([r[0] for r in rows]), np.array([r[1] for r in rows]),
                 np.array([r[2] for r in rows]), np.array([r[3] for r in rows]),
                 np.array([r[4] for r in rows]), model.equilibrium.pose)


# -- frequency responses ----------------------------------------------------------------------
def frequency_response(model: LinearModel, frequencies_hz: ArrayLike) -> np.ndarray:
    """G(j 2 pi f) = C (j 2 pi f I - A)^-1 B + D at each frequency.

    Args:
        model: the linear model.
        frequencies_hz: (F,) [Hz].

    Returns:
        (F, 6, 6) complex, [f, output, input]: output units per input unit
        (m/N open loop, m/m closed loop).
    """
    f = np.asarray(frequencies_hz, dtype=float)
    s = 2j * np.pi * f
    n = model.A.shape[0]
    pencil = s[:, None, None] * np.eye(n)[None] - model.A[None]
    rhs = np.broadcast_to(model.B, (len(f),) + model.B.shape)
    return model.C[None] @ np.linalg.solve(pencil, rhs) + model.D[None]


def frequency_table(frequencies_hz: ArrayLike,
                    response: np.ndarray) -> list[tuple[float, str, str, float, float]]:
    """``frequency_response``'s result as rows, by input, then output, then frequency.

    Args:
        frequencies_hz: (F,) [Hz].
        response: (F, 6, 6) complex, [f, output, input] (``frequency_response``).

    Returns:
        36 F rows (f [Hz], input leg name, output leg name, magnitude (output
        units per input unit), phase [deg]); the phase is unwrapped along
        frequency (continuous).
    """
    f = np.asarray(frequencies_hz, dtype=float)
    rows = []
    for i in range(response.shape[2]):
        for o in range(response.shape[1]):
            g = response[:, o, i]
            phase = np.degrees(np.unwrap(np.angle(g)))
            for k in range(len(f)):
                rows.append((float(f[k]), LEG_NAMES[i], LEG_NAMES[o], float(abs(g[k])),
                             float(phase[k])))
    return rows


def strongest_couplings(response: np.ndarray, count: int = 3) -> list[tuple[int, int]]:
    """The off-diagonal responses with the largest peak magnitude over frequency; of
    responses whose peaks agree to 1e-6 (legs that mirror each other) only the first.

    Args:
        response: (F, 6, 6) complex, [f, output, input] (``frequency_response``).
        count: how many to return (fewer when fewer are distinct).

    Returns:
        Up to ``count`` (output, input) 0-based leg indices, strongest first.
    """
    peak = np.max(np.abs(response), axis=0)
    chosen, seen = [], []
    for flat in np.argsort(peak, axis=None)[::-1]:
        o, i = np.unravel_index(flat, peak.shape)
        if o == i or any(abs(peak[o, i] - p) <= 1e-6 * p for p in seen):
            continue
        chosen.append((int(o), int(i)))
        seen.append(peak[o, i])
        if len(chosen) == count:
            break
    return chosen
