"""Planning a calibration: which poses to measure, and a reference that visits them.

Observability index: O3, the smallest singular value of the whitened
identification Jacobian (core/machine/calibration.py), i.e. E-optimality. The
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
``max_condition`` (core/analysis/equilibrium.py), the holding forces against gravity
within ``force_share`` of ``max_force`` (core/analysis/workspace.py's three limits),
and inside the supervisor's limits of the machine (``PlanLimits``: the soft
stroke, ``pose_box``, ``trip_tilt``), each with a margin: the plan is made
on the drawing, and the machine it is flown on stands up to a few
millimetres off it (amplified into centimetres of pose by the Jacobian),
while the law follows a move centimetres behind. The moves between the
poses are checked too (``reference_rows``), and routed through the
setpoint's pose where a direct move would leave the limits.
"""
from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from stewart63_ros.core.analysis.equilibrium import AnalysisError, holding_forces, setpoint_pose
from stewart63_ros.core.machine import calibration_model as cal_model
from stewart63_ros.core.mechanics.dynamics import Dynamics
from stewart63_ros.core.mechanics.fk import ForwardKinematics
from stewart63_ros.core.mechanics.mechanism import Mechanism
from stewart63_ros.core.mechanics.rotation import (
    euler_from_matrix,
    quaternion_from_rotation,
    quaternion_of_rotvec_times,
    rotation_from_euler,
    rotation_from_quaternion,
    rotvec_between,
)
from stewart63_ros.core.mechanics.setup import Setup

if TYPE_CHECKING:
    from stewart63_ros.core.machine.supervisor import Limits

#: Default half-ranges of the candidates around the setpoint's pose: x, y, z
#: [m], then the rotation vector's three components [rad].
DEFAULT_RANGE = (0.3, 0.3, 0.25, 0.35, 0.35, 0.35)
#: The share of the stroke kept free at each end.
STROKE_MARGIN = 0.03
#: How far inside the supervisor's soft stroke and pose box the plan stays [m]:
#: the machine is off its drawing (the packaged simulation of one, `calibrate
#: machine`: 1.7 cm of pose for 5 mm of points and 10 mm of offsets) and
#: pd_gravity follows a quick move up to 2.7 cm behind (docs/calibration.md).
LIMIT_MARGIN = 0.04
#: How far below the supervisor's tilt limit the plan stays [rad]: the
#: machine flown on the drawing's plan tilted up to 0.05 rad off it, and with
#: a margin of 0.05 one of nine simulated runs tripped trip_tilt.
TILT_MARGIN = 0.1
#: The plan's fastest leg, at most this share of the supervisor's trip_leg_speed.
SPEED_SHARE = 0.8
#: A struck pose (a machine off the drawing failed there) takes the candidates
#: this near with it [m] (|dt| + platform radius x angle): a neighbour fails alike.
STRIKE_RADIUS = 0.05


class PlanError(ValueError):
    """A plan that cannot be made; the message says why."""


@dataclasses.dataclass(frozen=True)
class PlanLimits:
    """Where a plan may take the platform: the supervisor's limits less the margins.

    Attributes:
        leg_low, leg_high: the leg lengths [m].
        box: (6,) x, y, z minimum then maximum of the position [m], or None.
        tilt: the largest angle of the platform's z axis from the base's [rad]; 0: any.
        leg_speed: the fastest a leg may move [m/s]; 0: no limit.
    """
    leg_low: float
    leg_high: float
    box: np.ndarray | None = None
    tilt: float = 0.0
    leg_speed: float = 0.0

    def violations(self, positions: np.ndarray, rotations: np.ndarray,
                   lengths: np.ndarray) -> list[str]:
        """Per pose, what it breaks ('' where nothing).

        Args:
            positions: (N, 3) [m]; rotations: (N, 3, 3); lengths: (N, 6) [m].

        Returns:
            N strings, e.g. 'leg_2 1.2312 m below 1.29 m'.
        """
        out = []
        for t, rot, legs in zip(positions, rotations, lengths):
            why = ''
            low, high = int(np.argmin(legs)), int(np.argmax(legs))
            tilt = float(np.arccos(np.clip(rot[2, 2], -1.0, 1.0)))
            if legs[low] < self.leg_low:
                why = 'leg_%d %.4f m below %.4g m' % (low + 1, legs[low], self.leg_low)
            elif legs[high] > self.leg_high:
                why = 'leg_%d %.4f m above %.4g m' % (high + 1, legs[high], self.leg_high)
            elif self.tilt and tilt > self.tilt:
                why = 'tilt %.3f rad above %.3g rad' % (tilt, self.tilt)
            elif self.box is not None:
                for a, axis in enumerate('xyz'):
                    if not self.box[a] <= t[a] <= self.box[3 + a]:
                        why = '%s = %.4f m outside [%.4g, %.4g] m' % (
                            axis, t[a], self.box[a], self.box[3 + a])
                        break
            out.append(why)
        return out


def plan_limits(mech: Mechanism, supervisor: Limits | None = None,
                margin: float = LIMIT_MARGIN,
                tilt_margin: float = TILT_MARGIN) -> PlanLimits:
    """The limits a plan keeps: the stroke less ``STROKE_MARGIN``, and inside the
    supervisor's limits (``core.machine.supervisor.Limits``, or None: none) by the margins.

    Args:
        mech: the mechanism (its stroke).
        supervisor: the supervisor's limits on the machine, or None.
        margin: [m] inside the soft stroke and the pose box.
        tilt_margin: [rad] below the tilt limit.

    Returns:
        The limits.

    Raises:
        PlanError: the margins leave no room (naming the limit).
    """
    stroke = mech.leg_length_max - mech.leg_length_min
    low = mech.leg_length_min + STROKE_MARGIN * stroke
    high = mech.leg_length_max - STROKE_MARGIN * stroke
    if supervisor is None:
        return PlanLimits(low, high)
    low = max(low, supervisor.soft_min + margin)
    high = min(high, supervisor.soft_max - margin)
    if not low < high:
        raise PlanError('the soft stroke [%g, %g] m less %g m on each end leaves no room'
                        % (supervisor.soft_min, supervisor.soft_max, margin))
    box = None
    if supervisor.box is not None:
        box = np.asarray(supervisor.box, dtype=float) + np.repeat([margin, -margin], 3)
        if np.any(box[:3] >= box[3:]):
            raise PlanError('pose_box %s less %g m on each side leaves no room'
                            % (np.asarray(supervisor.box).tolist(), margin))
    tilt = 0.0
    if supervisor.tilt:
        tilt = supervisor.tilt - tilt_margin
        if tilt <= 0:
            raise PlanError('trip_tilt %g rad less %g rad leaves no room'
                            % (supervisor.tilt, tilt_margin))
    return PlanLimits(low, high, box, tilt, SPEED_SHARE * supervisor.leg_speed)


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
                    force_share: float = 0.5,
                    limits: PlanLimits | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Random feasible poses around the setpoint's pose.

    Args:
        setup: the machine as drawn, and its task (the setpoint's pose is the centre).
        count: how many.
        rng: the random generator (seeded by the caller).
        half_range: (6,) half-ranges x, y, z [m], rotation vector [rad].
        max_condition: the largest Jacobian condition number accepted.
        force_share: holding forces must stay within this share of ``max_force``.
        limits: where the poses must lie (default ``plan_limits(mech)``: the stroke).

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
    limits = limits or plan_limits(mech)
    positions, rotations = [], []
    for _ in range(50):
        batch = 4 * count
        pos = centre + rng.uniform(-1, 1, (batch, 3)) * half[:3]
        rot = rotation_from_quaternion(quaternion_of_rotvec_times(
            rng.uniform(-1, 1, (batch, 3)) * half[3:], centre_rot))
        meas = cal_model.Measurements(pos, rot, np.zeros((batch, 6)))
        lengths = cal_model.predict_readings(cal_model.parameter_vector(mech), meas) \
            - mech.leg_length_offset
        inside = np.array([not why for why in limits.violations(pos, rot, lengths)])
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
    raise PlanError('only %d of %d candidate poses are feasible within the range %s and '
                    'the limits: the workspace is smaller than the range asked for'
                    % (len(positions), count, half.tolist()))


def _blocks(mech, positions, rotations, noise, geometry=None):
    """The whitened Jacobian block (6, P) of every candidate (P: 33 for a 6-3, 42 for a
    6-6: the parameters of the fit the poses are for, ``cal_model.parameter_vector``)."""
    meas = cal_model.Measurements(positions, rotations, np.zeros((len(positions), 6)))
    theta = cal_model.parameter_vector(mech, geometry)
    white = cal_model.whitening(theta, meas, noise)
    return np.einsum('nij,njp->nip', white, cal_model.parameter_jacobian(theta, meas))


def indices(blocks: np.ndarray, chosen: ArrayLike) -> tuple[float, float]:
    """O1 and O3 of a design.

    Args:
        blocks: (K, 6, P) whitened Jacobian blocks of the candidates.
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
        blocks: (K, 6, P) whitened Jacobian blocks.
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
    left = list(range(len(positions)))
    here_t, here_r = start
    order = []
    while left:
        dist = pose_distance(mech, positions[left], rotations[left], here_t, here_r)
        nxt = left.pop(int(np.argmin(dist)))
        order.append(nxt)
        here_t, here_r = positions[nxt], rotations[nxt]
    return order


def pose_distance(mech: Mechanism, positions: np.ndarray, rotations: np.ndarray,
                  position: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """|dt| + platform radius x angle [m] of poses (N, 3), (N, 3, 3) from one pose."""
    size = float(np.max(np.linalg.norm(mech.platform_points - mech.platform_points.mean(0),
                                       axis=1)))
    turns = rotvec_between(quaternion_from_rotation(rotations), rotation)
    return np.linalg.norm(positions - position, axis=1) + size * np.linalg.norm(turns, axis=1)


def plan(setup: Setup, count: int, seed: int = 0, noise: cal_model.NoiseModel | None = None,
         candidates: int = 1500, half_range: ArrayLike = DEFAULT_RANGE,
         max_condition: float = 100.0, force_share: float = 0.5,
         limits: PlanLimits | None = None, geometry: str | None = None,
         struck: list | None = None) -> Plan:
    """Choose ``count`` poses that make the identification well conditioned.

    Args:
        setup: the machine as drawn, and its task (the initial pose is the tour's start).
        count: poses, at least ``calibration.MIN_POSES``.
        seed: the candidates' random seed.
        noise: the tracker's noise (the whitening; default ``NoiseModel()``).
        candidates: how many feasible candidates to choose from.
        half_range, max_condition, force_share, limits: as ``candidate_poses``.
        geometry: the layout the fit will identify (default the drawing's):
            '6-6' of a 6-3 plans for the pairs' joints apart (42 parameters).
        struck: poses (position (3,), rotation (3, 3)) not to plan: every
            candidate within ``STRIKE_RADIUS`` of one is dropped
            (``calibration_flight``: a machine off the drawing failed there).

    Returns:
        The plan, in visiting order from the initial pose.

    Raises:
        PlanError: too few poses asked for, or too few feasible candidates.
    """
    if count < cal_model.MIN_POSES:
        raise PlanError('%d poses: a fit needs at least %d' % (count, cal_model.MIN_POSES))
    if candidates < 2 * count:
        raise PlanError('%d candidates for %d poses: give at least twice as many'
                        % (candidates, count))
    noise = noise or cal_model.NoiseModel()
    rng = np.random.default_rng(seed)
    mech = setup.mechanism
    positions, rotations = candidate_poses(setup, candidates, rng, half_range, max_condition,
                                           force_share, limits)
    if struck:
        near = np.zeros(len(positions), dtype=bool)
        for position, rotation in struck:
            near |= pose_distance(mech, positions, rotations, position, rotation) \
                < STRIKE_RADIUS
        positions, rotations = positions[~near], rotations[~near]
        if len(positions) < 2 * count:
            raise PlanError('%d poses struck (machines off the drawing failed there) leave '
                            '%d candidates for %d poses' % (len(struck), len(positions), count))
    blocks = _blocks(mech, positions, rotations, noise, geometry)
    chosen = choose(blocks, count)
    o1, o3 = indices(blocks, chosen)
    start = (np.asarray(setup.task.initial_position), setup.task.initial_rotation)
    order = tour(mech, positions[chosen], rotations[chosen], start)
    chosen = [chosen[j] for j in order]
    return Plan(positions[chosen], rotations[chosen], o1, o3,
                1.0 / o3 if o3 > 0 else np.inf, len(positions))


def reference_rows(setup: Setup, positions: np.ndarray, rotations: np.ndarray,
                   hold: float = 2.0, move: float = 2.0, leg_speed: float = 0.1,
                   row_step: float = 0.05,
                   limits: PlanLimits | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A reference (§7 rows) from the initial pose through every pose, holding each.

    Each move follows a quintic blend (zero velocity and acceleration at both
    ends), written as rows every ``row_step`` seconds so that the tools'
    spline through the rows stays on it; each pose is held ``hold`` seconds.
    A move whose blend would leave ``limits`` goes through the setpoint's
    pose instead (two moves, without a hold between them).

    Args:
        setup: the machine, and its task (the initial pose is the start).
        positions: (N, 3); rotations: (N, 3, 3), in visiting order.
        hold: seconds at each pose.
        move: the shortest move [s].
        leg_speed: the fastest a leg may move [m/s] (each move lasts so that
            its fastest leg stays 3 % under it).
        row_step: [s] between rows.
        limits: where the moves must stay (default ``plan_limits(mech)``).

    Returns:
        (times (M,) [s], poses (M, 6) x, y, z, theta_x, theta_y, theta_z).

    Raises:
        PlanError: a non-positive time or speed; a move that leaves the limits
            directly and through the setpoint's pose (naming the pose).
    """
    if not (hold > 0 and move > 0 and leg_speed > 0 and row_step > 0):
        raise PlanError('hold, move, leg speed and row step must be > 0')
    mech = setup.mechanism
    limits = limits or plan_limits(mech)
    task = setup.task
    start = np.concatenate([task.initial_position, task.initial_orientation])
    targets = np.hstack([positions, euler_from_matrix(rotations)])
    try:
        centre_t, centre_r = setpoint_pose(setup)
    except AnalysisError as exc:
        raise PlanError(str(exc)) from None
    centre = np.concatenate([centre_t, euler_from_matrix(centre_r)])

    # The blend's shape on a fine grid, and its rate (per unit of the move's time).
    fine = np.linspace(0.0, 1.0, 201)
    fine_shape = fine ** 3 * (10 - 15 * fine + 6 * fine ** 2)

    def blend(here, target):
        """The rows of one move (excluding ``here``), their times from its start, and
        its duration: the fastest leg at ``leg_speed`` less 3 % (the legs are not
        linear in the pose, and the spline through the rows overshoots a little)."""
        lengths = _lengths(mech, here + fine_shape[:, None] * (target - here))
        peak = float(np.max(np.abs(np.diff(lengths, axis=0)))) / (fine[1] - fine[0])
        duration = max(move, peak / (0.97 * leg_speed))
        steps = max(2, int(np.ceil(duration / row_step)))
        tau = np.arange(1, steps + 1) / steps
        shape = tau ** 3 * (10 - 15 * tau + 6 * tau ** 2)
        return tau * duration, here + shape[:, None] * (target - here), duration

    def broken(rows):
        return next((why for why in limits.violations(
            rows[:, :3], rotation_from_euler(rows[:, 3:]), _lengths(mech, rows)) if why), '')

    times, rows = [0.0], [start]
    t, here = 0.0, start
    for j, target in enumerate(targets):
        legs = [blend(here, target)]
        why = broken(legs[0][1])
        if why:
            legs = [blend(here, centre)]
            legs.append(blend(centre, target))
            again = broken(np.vstack([legs[0][1], legs[1][1]]))
            if again:
                raise PlanError('the move to pose %d leaves the limits (%s), and through the '
                                'setpoint\'s pose too (%s)' % (j + 1, why, again))
        for offsets, blended, duration in legs:
            times.extend(t + offsets)
            rows.extend(blended)
            t += duration
        holds = max(1, int(np.ceil(hold / row_step)))
        for s in range(1, holds + 1):
            times.append(t + s * hold / holds)
            rows.append(target)
        t += hold
        here = target
    return np.array(times), np.array(rows)


def _lengths(mech, poses):
    """The leg lengths (N, 6) [m] of poses (N, 6) x, y, z, theta (eq. 5)."""
    meas = cal_model.Measurements(poses[:, :3], rotation_from_euler(poses[:, 3:]),
                            np.zeros((len(poses), 6)))
    theta = cal_model.parameter_vector(mech)
    return cal_model.predict_readings(theta, meas) - mech.leg_length_offset


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
