"""Planning a calibration: which poses to measure, and a reference that visits them.

Observability index: O3, the smallest singular value of the whitened
identification Jacobian (core/calibration.py), i.e. E-optimality. The
standard deviation of the worst-determined combination of parameters is
noise / O3, and that combination is what a calibration fails on (a base
point moved along its leg against that leg's offset, docs/calibration.md): maximising
O3 bounds every parameter's uncertainty at once, in metres, for the stated
tracker noise. O1 (the geometric mean of the singular values, D-optimality)
rewards making the already well-determined directions better while a weak
one stays weak; it is used only to grow the first design (greedy, one pose
at a time, with the determinant lemma: cheap over thousands of candidates,
and defined while fewer than 33 directions are seen), which an exchange
then improves in O3. Both are reported.

Candidates: random poses (seeded) around the setpoint's pose, kept only
where the analysis toolbox says the machine can stand: every leg inside the
stroke with a margin, the Jacobian's condition number at most
``max_condition`` (core/analysis.py), the holding forces against gravity
within ``force_share`` of ``max_force`` (core/workspace.py's three limits).
"""
from __future__ import annotations

import dataclasses

import numpy as np
from numpy.typing import ArrayLike

from stewart63_ros.core import calibration as cal
from stewart63_ros.core.dynamics import Dynamics
from stewart63_ros.core.equilibrium import AnalysisError, holding_forces, setpoint_pose
from stewart63_ros.core.fk import ForwardKinematics
from stewart63_ros.core.mechanism import Mechanism
from stewart63_ros.core.rotation import (
    euler_from_matrix,
    quaternion_from_rotation,
    quaternion_of_rotvec_times,
    rotation_from_euler,
    rotation_from_quaternion,
    rotvec_between,
)
from stewart63_ros.core.setup import Setup

#: Default half-ranges of the candidates around the setpoint's pose: x, y, z
#: [m], then the rotation vector's three components [rad].
DEFAULT_RANGE = (0.3, 0.3, 0.25, 0.35, 0.35, 0.35)
#: The share of the stroke kept free at each end.
STROKE_MARGIN = 0.03


class PlanError(ValueError):
    """A plan that cannot be made; the message says why."""


@dataclasses.dataclass
class Plan:
    """The chosen poses, in the order the reference visits them.

    Attributes:
        positions: (N, 3) [m].
        rotations: (N, 3, 3).
        o1: geometric mean of the whitened Jacobian's singular values [1/m].
        o3: its smallest singular value [1/m].
        worst_std: noise / O3 [m]: the worst-determined combination's
            standard deviation at the stated noise.
        candidates: the feasible candidates the poses were chosen from.
    """
    positions: np.ndarray
    rotations: np.ndarray
    o1: float
    o3: float
    worst_std: float
    candidates: int


def candidate_poses(setup: Setup, count: int, rng: np.random.Generator,
                    half_range: ArrayLike = DEFAULT_RANGE, max_condition: float = 100.0,
                    force_share: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Random feasible poses around the setpoint's pose.

    Args:
        setup: the machine as drawn, and its task (the setpoint's pose is the centre).
        count: how many.
        rng: the random generator (seeded by the caller).
        half_range: (6,) half-ranges x, y, z [m], rotation vector [rad].
        max_condition: the largest Jacobian condition number accepted.
        force_share: holding forces must stay within this share of ``max_force``.

    Returns:
        (positions (count, 3), rotations (count, 3, 3)).

    Raises:
        PlanError: fewer than ``count`` feasible poses in 50 x ``count`` draws.
    """
    mech = setup.mechanism
    try:
        centre, centre_rot = setpoint_pose(setup)
    except AnalysisError as exc:
        raise PlanError(str(exc)) from None
    half = np.asarray(half_range, dtype=float)
    if half.shape != (6,) or not np.all(np.isfinite(half)) or np.any(half < 0):
        raise PlanError('the pose range must be 6 numbers >= 0, got %r' % (half_range,))
    fk = ForwardKinematics(mech, start=(setup.task.initial_position, setup.task.initial_rotation))
    dyn = Dynamics(mech)
    stroke = mech.leg_length_max - mech.leg_length_min
    low = mech.leg_length_min + STROKE_MARGIN * stroke
    high = mech.leg_length_max - STROKE_MARGIN * stroke
    positions, rotations = [], []
    for _ in range(50):
        batch = 4 * count
        pos = centre + rng.uniform(-1, 1, (batch, 3)) * half[:3]
        rot = rotation_from_quaternion(quaternion_of_rotvec_times(
            rng.uniform(-1, 1, (batch, 3)) * half[3:], centre_rot))
        meas = cal.Measurements(pos, rot, np.zeros((batch, 6)))
        lengths = cal.predict_readings(cal.parameter_vector(mech), meas) \
            - mech.leg_length_offset
        inside = np.all((lengths >= low) & (lengths <= high), axis=1)
        for n in np.flatnonzero(inside):
            if fk.condition(pos[n], rot[n]) > max_condition:
                continue
            forces = holding_forces(dyn, pos[n], rot[n])
            if not np.all(np.abs(forces) <= force_share * mech.max_force):
                continue
            positions.append(pos[n])
            rotations.append(rot[n])
            if len(positions) == count:
                return np.array(positions), np.array(rotations)
    raise PlanError('only %d of %d candidate poses are feasible within the range %s: '
                    'the workspace is smaller than the range asked for'
                    % (len(positions), count, half.tolist()))


def _blocks(mech, positions, rotations, noise):
    """The whitened Jacobian block (6, 33) of every candidate."""
    meas = cal.Measurements(positions, rotations, np.zeros((len(positions), 6)))
    theta = cal.parameter_vector(mech)
    white = cal.whitening(theta, meas, noise)
    return np.einsum('nij,njp->nip', white, cal.parameter_jacobian(theta, meas))


def indices(blocks: np.ndarray, chosen: ArrayLike) -> tuple[float, float]:
    """O1 and O3 of a design.

    Args:
        blocks: (K, 6, 33) whitened Jacobian blocks of the candidates.
        chosen: the candidates in the design.

    Returns:
        (O1, O3) [1/m]: the geometric mean and the smallest singular value.
    """
    jac = blocks[np.asarray(chosen)].reshape(-1, blocks.shape[2])
    sv = np.linalg.svd(jac, compute_uv=False)
    sv = np.concatenate([sv, np.zeros(max(0, blocks.shape[2] - sv.size))])
    with np.errstate(divide='ignore'):
        o1 = float(np.exp(np.mean(np.log(sv)))) if sv[-1] > 0 else 0.0
    return o1, float(sv[-1])


def choose(blocks: np.ndarray, count: int, rounds: int = 300, screened: int = 30) -> list[int]:
    """A design of ``count`` candidates: greedy in O1, then exchanges in O3.

    Args:
        blocks: (K, 6, 33) whitened Jacobian blocks.
        count: poses wanted (at most K).
        rounds: exchange rounds at most.
        screened: exchanges evaluated exactly per round (the best by the
            first-order change of the smallest eigenvalue).

    Returns:
        Indices of the chosen candidates.
    """
    k, _, p = blocks.shape
    info_of = np.einsum('nip,niq->npq', blocks, blocks)
    ridge = 1e-9 * np.trace(info_of.sum(0)) / p
    info = ridge * np.eye(p)
    chosen: list[int] = []
    for _ in range(count):
        inv = np.linalg.inv(info)
        gain = np.linalg.slogdet(np.eye(6) + np.einsum('nip,pq,njq->nij', blocks, inv,
                                                         blocks))[1]
        gain[chosen] = -np.inf
        best = int(np.argmax(gain))
        chosen.append(best)
        info = info + info_of[best]
    info = info - ridge * np.eye(p)
    low = np.linalg.eigvalsh(info)[0]
    for _ in range(rounds):
        values, vectors = np.linalg.eigh(info)
        weak = vectors[:, :6]
        # First-order change of the weakest eigenvalues, per swap (out, in).
        seen = np.einsum('nip,pk->nik', blocks, weak) ** 2
        score_in = seen.sum(1)                        # (K, 6)
        gain = score_in[None, :, 0] - score_in[chosen][:, None, 0]
        gain[:, chosen] = -np.inf
        flat = np.argsort(gain, axis=None)[::-1][:screened]
        improved = False
        for f in flat:
            out, into = np.unravel_index(f, gain.shape)
            trial = info - info_of[chosen[out]] + info_of[into]
            value = np.linalg.eigvalsh(trial)[0]
            if value > low * (1 + 1e-9):
                chosen[out] = int(into)
                info, low, improved = trial, value, True
                break
        if not improved:
            break
    return chosen


def tour(mech: Mechanism, positions: np.ndarray, rotations: np.ndarray,
         start: tuple[np.ndarray, np.ndarray]) -> list[int]:
    """An order to visit the poses: always the nearest unvisited next
    (|dt| + platform radius x angle).

    Args:
        mech: the mechanism (the platform's size).
        positions: (N, 3); rotations: (N, 3, 3).
        start: (position, rotation) where the platform is first.

    Returns:
        The order, a permutation of range(N).
    """
    size = float(np.max(np.linalg.norm(mech.platform_points - mech.platform_points.mean(0),
                                       axis=1)))
    left = list(range(len(positions)))
    here_t, here_r = start
    order = []
    while left:
        turns = rotvec_between(quaternion_from_rotation(rotations[left]), here_r)
        dist = np.linalg.norm(positions[left] - here_t, axis=1) + size * np.linalg.norm(
            turns, axis=1)
        nxt = left.pop(int(np.argmin(dist)))
        order.append(nxt)
        here_t, here_r = positions[nxt], rotations[nxt]
    return order


def plan(setup: Setup, count: int, seed: int = 0, noise: cal.NoiseModel | None = None,
         candidates: int = 1500, half_range: ArrayLike = DEFAULT_RANGE,
         max_condition: float = 100.0, force_share: float = 0.5) -> Plan:
    """Choose ``count`` poses that make the identification well conditioned.

    Args:
        setup: the machine as drawn, and its task (the initial pose is the tour's start).
        count: poses, at least ``calibration.MIN_POSES``.
        seed: the candidates' random seed.
        noise: the tracker's noise (the whitening; default ``NoiseModel()``).
        candidates: how many feasible candidates to choose from.
        half_range, max_condition, force_share: as ``candidate_poses``.

    Returns:
        The plan, in visiting order from the initial pose.

    Raises:
        PlanError: too few poses asked for, or too few feasible candidates.
    """
    if count < cal.MIN_POSES:
        raise PlanError('%d poses: a fit needs at least %d' % (count, cal.MIN_POSES))
    if candidates < 2 * count:
        raise PlanError('%d candidates for %d poses: give at least twice as many'
                        % (candidates, count))
    noise = noise or cal.NoiseModel()
    rng = np.random.default_rng(seed)
    mech = setup.mechanism
    positions, rotations = candidate_poses(setup, candidates, rng, half_range, max_condition,
                                           force_share)
    blocks = _blocks(mech, positions, rotations, noise)
    chosen = choose(blocks, count)
    o1, o3 = indices(blocks, chosen)
    start = (np.asarray(setup.task.initial_position), setup.task.initial_rotation)
    order = tour(mech, positions[chosen], rotations[chosen], start)
    chosen = [chosen[j] for j in order]
    return Plan(positions[chosen], rotations[chosen], o1, o3,
                1.0 / o3 if o3 > 0 else np.inf, len(positions))


def reference_rows(setup: Setup, positions: np.ndarray, rotations: np.ndarray,
                   hold: float = 2.0, move: float = 2.0, leg_speed: float = 0.1,
                   row_step: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """A reference (§7 rows) from the initial pose through every pose, holding each.

    Each move follows a quintic blend (zero velocity and acceleration at both
    ends), written as rows every ``row_step`` seconds so that the tools'
    spline through the rows stays on it; each pose is held ``hold`` seconds.

    Args:
        setup: the machine, and its task (the initial pose is the start).
        positions: (N, 3); rotations: (N, 3, 3), in visiting order.
        hold: seconds at each pose.
        move: the shortest move [s].
        leg_speed: the fastest a leg may move [m/s] (the blend's peak
            speed is 1.875 x the mean).
        row_step: [s] between rows.

    Returns:
        (times (M,) [s], poses (M, 6) x, y, z, theta_x, theta_y, theta_z).

    Raises:
        PlanError: a non-positive time or speed.
    """
    if not (hold > 0 and move > 0 and leg_speed > 0 and row_step > 0):
        raise PlanError('hold, move, leg speed and row step must be > 0')
    task = setup.task
    theta = cal.parameter_vector(setup.mechanism)
    start = np.concatenate([task.initial_position, task.initial_orientation])
    targets = np.hstack([positions, euler_from_matrix(rotations)])
    meas = cal.Measurements(np.vstack([task.initial_position, positions]),
                            np.concatenate([[_rot(task.initial_orientation)], rotations]),
                            np.zeros((len(positions) + 1, 6)))
    lengths = cal.predict_readings(theta, meas)
    times, rows = [0.0], [start]
    t, here = 0.0, start
    for j, target in enumerate(targets):
        change = float(np.max(np.abs(lengths[j + 1] - lengths[j])))
        duration = max(move, 1.875 * change / leg_speed)
        steps = max(2, int(np.ceil(duration / row_step)))
        for s in range(1, steps + 1):
            tau = s / steps
            blend = tau ** 3 * (10 - 15 * tau + 6 * tau ** 2)
            times.append(t + tau * duration)
            rows.append(here + blend * (target - here))
        t += duration
        for s in range(1, max(1, int(np.ceil(hold / row_step))) + 1):
            times.append(t + s * hold / max(1, int(np.ceil(hold / row_step))))
            rows.append(target)
        t += hold
        here = target
    return np.array(times), np.array(rows)


def _rot(theta):
    return rotation_from_euler(theta)


def hold_windows(times: np.ndarray, poses: np.ndarray) -> list[tuple[float, float]]:
    """The intervals where a reference from ``reference_rows`` holds a pose.

    Args:
        times: (M,) [s]; poses: (M, 6), as ``reference_rows`` returns them.

    Returns:
        [(start, end)] [s], one per held pose, in order.
    """
    same = np.all(np.abs(np.diff(poses, axis=0)) < 1e-12, axis=1)
    windows, begin = [], None
    for j, flat in enumerate(same):
        if flat and begin is None:
            begin = times[j]
        if not flat and begin is not None:
            windows.append((float(begin), float(times[j])))
            begin = None
    if begin is not None:
        windows.append((float(begin), float(times[-1])))
    return windows
