"""The positions the platform can be held at, at one orientation, on a grid.

A grid point (position t, the given rotation R) is reachable when, in this
order (``reason`` names the first limit a point breaks):

1. ``stroke``: every leg length L_i = |t + R p_i - b_i| (eq. 5) lies in
   [leg_length_min, leg_length_max];
2. ``singular``: the Jacobian (rows [s_i, q_i x s_i], eq. 13) has a 2-norm
   condition number at most ``max_condition`` (near a singularity the pose
   cannot be held or measured: the holding forces and the pose error per
   length error grow without bound);
3. ``max_force``: the forces that hold platform and legs still there against
   gravity, H F = eta(q, 0) (eq. 38 at rest, leg masses included), are all
   within +-max_force.

A reachable point has reason ``ok``. One compiled pass per grid computes
the lengths, the condition number and the holding forces of every point.
"""
from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from stewart63_ros.core.mechanics.dynamics import Dynamics, inverse_dynamics_forces
from stewart63_ros.core.mechanics.fk_tracking import condition_number
from stewart63_ros.core.mechanics.kinematics import leg_kernel
from stewart63_ros.core.mechanics.mechanism import Mechanism
from stewart63_ros.core.plumbing._jit import njit

#: Reasons, in the order the limits are checked.
REASONS = ('ok', 'stroke', 'singular', 'max_force')
#: Default grid step [m].
DEFAULT_STEP = 0.05
#: Memory ``workspace_map`` takes per grid point at its peak [bytes]: 198
#: measured (tracemalloc), with a margin (test_analysis checks the bound).
BYTES_PER_POINT = 240
#: The largest share of the available memory a grid may take.
MEMORY_SHARE = 0.5


class GridTooLarge(ValueError):
    """A grid that would not fit in memory; the message says how large it is."""


def available_memory() -> int:
    """The memory this process can still take [bytes]: MemAvailable of
    /proc/meminfo (Linux), else the free physical pages.

    Returns:
        Bytes (0 when it cannot be told).
    """
    try:
        with open('/proc/meminfo') as fh:
            for line in fh:
                if line.startswith('MemAvailable:'):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf('SC_AVPHYS_PAGES')) * int(os.sysconf('SC_PAGE_SIZE'))
    except (ValueError, OSError, AttributeError):
        return 0


def human_bytes(count: float) -> str:
    """``count`` bytes as a person reads it (``1.6 GB``, ``13 MB``; powers of 1000).

    Args:
        count: bytes.

    Returns:
        The text.
    """
    for unit in ('B', 'kB', 'MB', 'GB', 'TB', 'PB'):
        if count < 1000 or unit == 'PB':
            return ('%.0f %s' if count >= 10 or unit == 'B' else '%.1f %s') % (count, unit)
        count /= 1000.0
    return '%.0f PB' % count


@njit
def _grid_limits(const, base, plat, inertia, rot, points):
    """Per point of ``points`` (N, 3) at rotation ``rot`` (3, 3): leg lengths
    (N, 6) [m], holding forces (N, 6) [N] (NaN where H is singular) and the
    Jacobian's condition number (N,)."""
    n = points.shape[0]
    lengths = np.empty((n, 6))
    forces = np.empty((n, 6))
    cond = np.empty(n)
    jac = np.empty((6, 6))
    zero3 = np.zeros(3)
    zero6 = np.zeros(6)
    rows = ((rot[0, 0], rot[0, 1], rot[0, 2]), (rot[1, 0], rot[1, 1], rot[1, 2]),
            (rot[2, 0], rot[2, 1], rot[2, 2]))
    still = (0.0, 0.0, 0.0)
    for k in range(n):
        pos = (points[k, 0], points[k, 1], points[k, 2])
        for i in range(6):
            qx, qy, qz, L, sx, sy, sz, _, _, _, _ = leg_kernel(rows, pos, still, still, base,
                                                               plat, i)
            lengths[k, i] = L
            jac[i, 0], jac[i, 1], jac[i, 2] = sx, sy, sz
            jac[i, 3] = qy * sz - qz * sy
            jac[i, 4] = qz * sx - qx * sz
            jac[i, 5] = qx * sy - qy * sx
        cond[k] = condition_number(jac)
        forces[k] = inverse_dynamics_forces(const, base, plat, inertia, rot, points[k], zero3,
                                            zero3, zero6)
    return lengths, forces, cond


@dataclasses.dataclass
class WorkspaceMap:
    """A grid of positions at one orientation and what limits each.

    Attributes:
        points: (N, 3) positions [m], base frame.
        reachable: (N,) bool.
        reason: (N,) str, one of ``REASONS``.
        condition: (N,) Jacobian condition number.
        max_force: (N,) largest |holding force| [N] over the six legs (inf where
            the pose cannot be held at all).
        lengths: (N, 6) leg lengths [m].
        forces: (N, 6) holding forces [N].
        rotation: (3, 3) the orientation.
        axes: the grid's x, y, z values [m].
    """
    points: np.ndarray
    reachable: np.ndarray
    reason: np.ndarray
    condition: np.ndarray
    max_force: np.ndarray
    lengths: np.ndarray
    forces: np.ndarray
    rotation: np.ndarray
    axes: tuple


def default_bounds(mech: Mechanism) -> tuple[float, float, float, float, float, float]:
    """The default box of the grid: the base points' circle in x and y, the base
    plane to the longest leg in z.

    Args:
        mech: the mechanism (``base_points``, ``leg_length_max``).

    Returns:
        (xmin, xmax, ymin, ymax, zmin, zmax) [m], base frame.
    """
    radius = float(np.max(np.linalg.norm(np.asarray(mech.base_points)[:, :2], axis=1)))
    return (-radius, radius, -radius, radius, 0.0, float(mech.leg_length_max))


def grid_axis(low: float, high: float, step: float, through: float) -> np.ndarray:
    """Values of [low, high] spaced by ``step`` with one of them at ``through``.

    Args:
        low, high: the interval [m]; step: the spacing [m] (> 0).
        through: a value on the axis [m] (inside the interval or not).

    Returns:
        (n,) increasing values [m] (empty when none lies in the interval).
    """
    first = through - step * np.floor((through - low) / step + 1e-9)
    count = int(np.floor((high - first) / step + 1e-9)) + 1
    return first + step * np.arange(max(count, 0))


def grid_axes(mech: Mechanism, step: float = DEFAULT_STEP,
              bounds: Sequence[float] | None = None,
              through: ArrayLike | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The x, y and z values of the grid ``workspace_map`` covers (cheap: no
    point is made, so a grid's size is known before it is).

    Args:
        mech: the mechanism; step: grid spacing [m] (> 0).
        bounds: (xmin, xmax, ymin, ymax, zmin, zmax) [m], default ``default_bounds``.
        through: (3,) a point that lies on the grid (default the origin).

    Returns:
        (x, y, z) axis values [m]; the grid has their lengths' product of points.

    Raises:
        ValueError: ``step`` is not a positive finite length.
    """
    if not (np.isfinite(step) and step > 0):
        raise ValueError('step must be a positive length, got %r' % (step,))
    xmin, xmax, ymin, ymax, zmin, zmax = bounds if bounds is not None else default_bounds(mech)
    through = np.zeros(3) if through is None else np.asarray(through, float)
    return (grid_axis(xmin, xmax, step, through[0]), grid_axis(ymin, ymax, step, through[1]),
            grid_axis(zmin, zmax, step, through[2]))


def check_grid_fits(points: int, available: int | None = None) -> None:
    """Refuse a grid whose map would take more than ``MEMORY_SHARE`` of the memory.

    Args:
        points: the grid's point count.
        available: bytes available (default ``available_memory()``; 0: unknown,
            nothing is refused).

    Raises:
        GridTooLarge: naming the point count, the memory it needs and what is
            available.
    """
    available = available_memory() if available is None else available
    need = float(points) * BYTES_PER_POINT
    if available and need > MEMORY_SHARE * available:
        raise GridTooLarge('a grid of %d points needs about %s of memory; %s is available '
                           '(at most half of it is used): use a larger --step'
                           % (points, human_bytes(need), human_bytes(available)))


def workspace_map(mech: Mechanism, rotation: ArrayLike, step: float = DEFAULT_STEP,
                  max_condition: float = 100.0,
                  bounds: Sequence[float] | None = None,
                  through: ArrayLike | None = None) -> WorkspaceMap:
    """Reachability of every grid point at ``rotation`` (see the module docstring).

    Args:
        mech: the mechanism.
        rotation: (3, 3) platform orientation R.
        step: grid spacing [m] (> 0).
        max_condition: the largest condition number accepted.
        bounds: (xmin, xmax, ymin, ymax, zmin, zmax) [m], default ``default_bounds``.
        through: (3,) a point that lies on the grid (default the origin).

    Returns:
        The ``WorkspaceMap`` (points ordered x slowest, z fastest).

    Raises:
        ValueError: ``step`` is not a positive finite length.
        GridTooLarge: the grid would not fit in memory (``check_grid_fits``),
            refused before any of it is made.
    """
    axes = grid_axes(mech, step, bounds, through)
    check_grid_fits(int(np.prod([len(a) for a in axes], dtype=float)))
    grid = np.stack(np.meshgrid(*axes, indexing='ij'), axis=-1).reshape(-1, 3)
    points = np.ascontiguousarray(grid)
    rot = np.ascontiguousarray(rotation, dtype=float)
    lengths, forces, cond = _grid_limits(*Dynamics(mech).kernel_args(), rot, points)
    outside = np.any((lengths < mech.leg_length_min) | (lengths > mech.leg_length_max), axis=1)
    singular = ~(cond <= max_condition)
    with np.errstate(invalid='ignore'):
        largest = np.max(np.abs(forces), axis=1)
    largest[~np.isfinite(largest)] = np.inf
    too_strong = ~(largest <= mech.max_force)
    reason = np.full(len(points), 'ok', dtype=object)
    reason[too_strong] = 'max_force'
    reason[singular] = 'singular'
    reason[outside] = 'stroke'
    return WorkspaceMap(points, reason == 'ok', reason.astype(str), cond, largest, lengths,
                        forces, rot, axes)
