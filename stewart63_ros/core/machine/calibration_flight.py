"""A calibration plan flown in simulation on machines off its drawing, before it is written.

A plan is made on the drawing, and flown on a machine that is not the
drawing: the controller drives the legs to the drawing's lengths of each
pose, so the machine stands where *its* legs have those lengths, up to
several centimetres and a tenth of a radian away on a small hexapod a few
millimetres off (the error grows where the Jacobian is poorly conditioned),
and the law's gravity compensation, computed on the drawing, pushes a
little wrong. Near a pose where the holding forces change fast with the
pose, that is enough for the platform to sag through a singularity into
another assembly mode, although the drawing flies the same plan within
5 mm (docs/calibration.md, "The plan and the machine").

No margin in pose space states that: it depends on the machine's
sensitivity, its law and its loads. So the plan is flown: on the drawing
(a plan it cannot fly is too fast for the law) and on ``machines``
machines built off the drawing within the stated tolerance (each point
coordinate uniform in +-``points``, each sensor offset in +-``offsets``,
seeded: what ``calibrate machine`` builds), by ``pd_gravity`` and the
supervisor on the drawing, sample for sample as the lockstep rig runs them
(``supervisor.run_supervised``). A flight must not trip and must track the
reference within the rig's tracking bound (``rig --tracking-bound``, 5 cm
and 0.1 rad after the first second) times ``BOUND_SHARE``: the user's machine
is not one of those flown. A pose where a flight fails is struck and the
plan made again (``tools/calibrate.py``).
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

from stewart63_ros.core.controllers.laws import Controller
from stewart63_ros.core.controllers.reference import R_POS, R_ROT, Reference
from stewart63_ros.core.controllers.sensor import SensorModel
from stewart63_ros.core.machine import calibration_model as cal_model
from stewart63_ros.core.machine import calibration_plan as cp
from stewart63_ros.core.machine.supervisor import (
    Supervisor,
    limits_from_params,
    run_supervised,
)
from stewart63_ros.core.mechanics.fk import FKTracker, ForwardKinematics
from stewart63_ros.core.mechanics.mechanism import Mechanism
from stewart63_ros.core.mechanics.rotation import (
    quaternion_from_rotation,
    rotation_angle_between,
)
from stewart63_ros.core.mechanics.setup import Setup

#: rig's --tracking-bound default (tools/rig.py TRACKING_BOUND): metres, radians.
TRACKING_BOUND = (0.05, 0.1)
#: A flown machine must track within this share of the bound: the machine the
#: plan is flown on for real is another one within the same tolerance.
BOUND_SHARE = 0.8
#: The tracking bound applies after this long [s] (as rig's: the start settles).
SETTLE = 1.0
#: The law a plan is flown with: the documented one (docs/calibration.md, step 3).
LAW = 'pd_gravity'
#: Machines off the drawing flown: with 4 (and strikes alone) 4 and 6 of 30
#: other machines 3 mm off a small 6-6 failed the written plan; with 8 and the
#: narrowing, 0 and 1 (docs/calibration.md).
MACHINES = 8
#: The flights' sample rate at most [Hz]: a flight at 100, 200 and 500 Hz of
#: one plan on one machine tripped on the same pose within 1 mm.
MAX_RATE = 200.0
#: The share of the range kept at each failed flight.
NARROWING = 0.9
#: The default tolerance [m]: calibrate machine's defaults (points, offsets).
POINTS_TOLERANCE = 0.005
OFFSETS_TOLERANCE = 0.01


def machine_off_drawing(mech: Mechanism, rng: np.random.Generator, points: float,
                        offsets: float, geometry: str | None = None) -> Mechanism:
    """A machine built off its drawing: every point coordinate moved by up to
    ``points``, every sensor offset by up to ``offsets`` [m] (uniform).

    Args:
        mech: the drawing.
        rng: the random generator (seeded by the caller).
        points, offsets: the largest moves [m].
        geometry: '6-6' of a 6-3: its pairs' joints moved each on its own.

    Returns:
        The machine.

    Raises:
        CalibrationError: a geometry the drawing cannot take.
        ParameterError: the moved machine is impossible.
    """
    theta = cal_model.parameter_vector(mech, geometry)
    count = theta.size - 6
    theta[:count] += rng.uniform(-points, points, count)
    theta[count:] += rng.uniform(-offsets, offsets, 6)
    return cal_model.mechanism_with(mech, theta)


def machine_at_corner(mech: Mechanism, rng: np.random.Generator, points: float,
                      offsets: float, geometry: str | None = None) -> Mechanism:
    """A machine at a corner of the tolerance: every point coordinate moved by
    +-``points``, every sensor offset by +-``offsets`` [m] (the signs random):
    as far off as the tolerance allows on every parameter at once, so farther
    off than a machine drawn uniformly inside it (``machine_off_drawing``)."""
    theta = cal_model.parameter_vector(mech, geometry)
    count = theta.size - 6
    theta[:count] += points * rng.choice([-1.0, 1.0], count)
    theta[count:] += offsets * rng.choice([-1.0, 1.0], 6)
    return cal_model.mechanism_with(mech, theta)


@dataclasses.dataclass(frozen=True)
class Flight:
    """One plan flown on one machine.

    Attributes:
        trip: the supervisor's first trip ('cause: detail'), or ''.
        position_max, angle_max: the true pose's largest distance from the
            reference after ``SETTLE`` [m], [rad] (to the trip, if one).
        failed_at: when it first tripped or left the bound [s], or None.
    """
    trip: str
    position_max: float
    angle_max: float
    failed_at: float | None

    @property
    def ok(self) -> bool:
        """True when the machine flew the whole plan without a trip and within the bound."""
        return self.failed_at is None

    def describe(self) -> str:
        """One line for the plan's report: tripped, tracked or left the bound, and how close."""
        what = 'tripped %s' % self.trip if self.trip else (
            'tracked' if self.ok else 'left %g of the tracking bound' % BOUND_SHARE)
        return '%s, within %.1f mm and %.1f mrad of the reference' % (
            what, self.position_max * 1e3, self.angle_max * 1e3)


def fly(setup: Setup, machine: Mechanism, reference: Reference, rate: float,
        supervisor_params: Mapping[str, Any]) -> Flight:
    """Fly ``reference`` on ``machine``: the plant is the machine, its sensors
    read its offsets; the law (``LAW``) and the supervisor run on the drawing
    (``setup``), which subtracts its own offsets, as ``rig --plant-params``.
    The flight starts at the file's initial pose, without the supervisor's
    homing.

    Args:
        setup: the drawing, its gains and task.
        machine: the machine the plant plays.
        reference: the plan's reference (on the drawing).
        rate: the sample rate [Hz] (the plant's ``sensor_rate``).
        supervisor_params: the supervisor's parameters (over ``setup.to_params()``).

    Returns:
        The flight.
    """
    params = dict(setup.to_params(), **supervisor_params)
    mech = setup.mechanism
    start = (setup.task.initial_position, setup.task.initial_rotation)
    tracker = FKTracker(mech, *start)

    def pose(lengths):
        result = tracker.solve(lengths)
        return result.position, result.rotation, result.condition

    supervisor = Supervisor(setup, limits_from_params(mech, params, rate), rate, reference,
                            pose)
    plant = dataclasses.replace(setup, mechanism=machine)
    sensor = SensorModel({'leg_length_offset': list(machine.leg_length_offset
                                                    - mech.leg_length_offset)})
    out = run_supervised(plant, supervisor, reference.duration, rate,
                         controller=Controller(setup, law=LAW, reference=reference),
                         sensor=sensor)
    times = np.arange(len(out['states'])) / rate
    states = out['states']
    # the reference holds its last pose past its end, as the controller's does
    samples = reference.sample_many(np.clip(times, 0.0, reference.duration))
    position = np.linalg.norm(states[:, :3] - samples[:, R_POS], axis=1)
    angle = rotation_angle_between(samples[:, R_ROT].reshape(-1, 3, 3), states[:, 3:7])
    trip = supervisor.trips[0] if supervisor.trips else None
    end = len(times) if trip is None else int(round(trip.sample_ns * 1e-9 * rate)) + 1
    judged = (times >= SETTLE) & (np.arange(len(times)) < end)
    bound_position, bound_angle = (BOUND_SHARE * b for b in TRACKING_BOUND)
    beyond = judged & ((position > bound_position) | (angle > bound_angle))
    failed_at = None
    if beyond.any():
        failed_at = float(times[np.flatnonzero(beyond)[0]])
    if trip is not None:
        at = trip.sample_ns * 1e-9
        failed_at = at if failed_at is None else min(failed_at, at)
    return Flight('%s: %s' % (trip.cause, trip.detail) if trip else '',
                  float(position[judged].max()) if judged.any() else 0.0,
                  float(angle[judged].max()) if judged.any() else 0.0, failed_at)



def standing_error(drawing: Mechanism, machine: Mechanism, position: np.ndarray,
                   rotation: np.ndarray) -> tuple[float, float]:
    """How far the machine stands from a pose of the drawing when its sensors read
    the drawing's lengths of it (what the controller drives them to), at rest.

    Returns:
        (distance [m], angle [rad]).
    """
    meas = cal_model.Measurements(np.asarray(position, float)[None],
                                  np.asarray(rotation, float)[None], np.zeros((1, 6)))
    readings = cal_model.predict_readings(cal_model.parameter_vector(drawing), meas)[0]
    found = ForwardKinematics(machine).nearest(readings - machine.leg_length_offset,
                                               position, rotation)
    angle = rotation_angle_between(np.asarray(rotation, float)[None],
                                   quaternion_from_rotation(found.rotation)[None])[0]
    return float(np.linalg.norm(found.position - position)), float(angle)


@dataclasses.dataclass
class FlownPlan:
    """A plan whose reference every flown machine tracked.

    Attributes:
        plan: the plan (``calibration_plan.Plan``).
        times, rows: its reference (``calibration_plan.reference_rows``).
        flights: the last round's flights, one per machine off the drawing.
        struck: the poses struck on the way, each (position (3,), rotation
            (3, 3), why: the failed flight, described).
    """
    plan: Any
    times: np.ndarray
    rows: np.ndarray
    flights: list[Flight]
    struck: list[tuple[np.ndarray, np.ndarray, str]]


def flown_plan(setup: Setup, count: int, rate: float, supervisor_params: Mapping[str, Any],
               plan_options: Mapping[str, Any], reference_options: Mapping[str, Any],
               points: float = POINTS_TOLERANCE, offsets: float = OFFSETS_TOLERANCE,
               machines: int = MACHINES, seed: int = 0, rounds: int = 10) -> FlownPlan:
    """Plan ``count`` poses, fly the reference on the drawing and on ``machines``
    machines off it (``fly``), strike the pose the first failed flight was
    going to or holding, and plan again, until every flight passes.

    Args:
        setup: the drawing and its task.
        count: poses.
        rate: the plant's sample rate [Hz] (the flights': at most ``MAX_RATE``).
        supervisor_params: the supervisor's parameters of the file.
        plan_options: keyword arguments of ``calibration_plan.plan`` (not ``struck``).
        reference_options: of ``calibration_plan.reference_rows``.
        points, offsets: the tolerance of the machines flown [m]; both 0 or
            ``machines`` 0: no flight (the plan as made).
        machines: how many machines (seeded from ``seed``).
        seed: the plan's seed (the machines: seeds ``seed`` * 1000 + 1 ...).
        rounds: plans made at most.

    Returns:
        The flown plan.

    Raises:
        PlanError: a plan cannot be made, or its flights still fail after
            ``rounds`` (naming the pose, the machine and what happened).
    """
    mech = setup.mechanism
    fleet = [machine_off_drawing(mech, np.random.default_rng(seed * 1000 + 1 + m), points,
                               offsets, plan_options.get('geometry'))
             for m in range(machines if points or offsets else 0)]
    for m, machine in enumerate(fleet):
        off = standing_error(mech, machine, setup.task.initial_position,
                             setup.task.initial_rotation)
        if off[0] > BOUND_SHARE * TRACKING_BOUND[0] or off[1] > BOUND_SHARE * TRACKING_BOUND[1]:
            raise cp.PlanError(
                'machine %d of %d off the drawing (+-%g m points, +-%g m offsets), its legs at '
                'the drawing\'s lengths of the start pose, stands %.1f mm and %.1f mrad from '
                'it: beyond %g of the tracking bound (%g m, %g rad) before any move, so no '
                'plan tracks such a machine. State the tolerance the machine is known to '
                '(--tolerance), measured better if need be'
                % (m + 1, len(fleet), points, offsets, off[0] * 1e3, off[1] * 1e3, BOUND_SHARE,
                   *TRACKING_BOUND))
    struck: list[tuple[np.ndarray, np.ndarray, str]] = []
    options = dict(plan_options)
    half_range = np.asarray(options.pop('half_range', cp.DEFAULT_RANGE), float)
    for _ in range(rounds):
        # each failure narrows the range too: the poses machines off the drawing
        # fail on are its outer ones (tilted, off centre, legs long), and a
        # struck pose's neighbours beyond STRIKE_RADIUS fail alike
        plan = cp.plan(setup, count, seed, struck=[(t, r) for t, r, _ in struck],
                       half_range=half_range * NARROWING ** len(struck), **options)
        times, rows = cp.reference_rows(setup, plan.positions, plan.rotations,
                                        **reference_options)
        reference = Reference.from_poses(mech, times, rows)
        flights, failed = [], None
        # the drawing first: a plan it cannot fly is too fast for the law, not
        # too wide for the machine
        for m, machine in enumerate([mech] + fleet if fleet else []):
            flight = fly(setup, machine, reference, min(rate, MAX_RATE), supervisor_params)
            if m:
                flights.append(flight)
            if not flight.ok:
                failed = (m, flight)
                break
        if failed is None:
            return FlownPlan(plan, times, rows, flights, struck)
        m, flight = failed
        windows = cp.hold_windows(times, rows)
        pose = next((j for j, (_, end) in enumerate(windows) if end >= flight.failed_at),
                    len(windows) - 1)
        who = 'the drawing itself' if m == 0 else \
            'machine %d of %d off the drawing (+-%g m points, +-%g m offsets)' % (
                m, len(fleet), points, offsets)
        why = 'pose %d (%s), %s at %.2f s: %s' % (
            pose + 1, ', '.join('%.3f' % v for v in rows[np.searchsorted(
                times, windows[pose][0])]), who, flight.failed_at, flight.describe())
        struck.append((plan.positions[pose], plan.rotations[pose], why))
    drawing = sum(1 for _, _, why in struck if 'the drawing itself' in why)
    raise cp.PlanError(
        'the plan still fails in simulation after %d poses struck (%d of them on the drawing '
        'itself: the moves too fast for the law); the last: %s. Slow it (--leg-speed, '
        '--move)%s' % (len(struck), drawing, struck[-1][2],
                       '' if drawing == len(struck) else ', or state a narrower tolerance '
                       'if the machine is known better (--tolerance)'))
