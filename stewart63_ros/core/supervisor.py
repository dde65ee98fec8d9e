"""The supervisor's trip logic: limits, latched trips and the safe actions (no ROS).

The ``supervisor`` node (nodes/supervisor.py) sits between the controller and
the machine; per sample it hands this core the sample (``on_sample``) and the
controller's request for it (``on_request``), or says that none came
(``no_request``), and sends on ``leg_forces`` what comes back: the request
forwarded, or, once a limit is crossed, the safe action of that cause.
docs/supervisor.md is the user's page.

A trip latches: it names its cause, the sample (stamp) on which the limit was
crossed, and the sample whose answer was the first safe force (the trip's
latency in samples is the difference: 0 here, by construction, since the
answer to the sample that crosses a limit is already the safe force). It
holds until ``reset``, refused while the cause persists.

Safe actions (one per cause, ``CAUSES``):

- ``zero``: no force. For causes that leave no measurement to close a loop on
  (stale or NaN leg readings): the platform settles onto its lower end stops.
- ``hold``: leg-length PD, eq. (40), on the last good lengths (those of the
  last sample that passed every check), with the model's ``kp``, ``kv``,
  ``max_force``: for a bad command (the controller's forces) while the
  sensors are sound.
- ``descend``: a profiled descent in leg space from the lengths at the trip
  to the rest lengths (``rest_lengths``), each leg's setpoint on a cosine
  profile whose peak speed is ``descent_speed``, tracked by PD with the
  profile's rate as feed-forward; then held at rest.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from stewart63_ros.core.dynamics import Dynamics
from stewart63_ros.core.errors import ParameterError
from stewart63_ros.core.faults import FaultModel, parse_faults
from stewart63_ros.core.fk import FKTracker, ForwardKinematics, NoAssemblyError
from stewart63_ros.core.kinematics import leg_lengths
from stewart63_ros.core.laws import Controller, LawError, PDGravityLaw
from stewart63_ros.core.node_parameters import read as read_declared
from stewart63_ros.core.reference import R_LEN, Reference, ReferenceError, load_reference
from stewart63_ros.core.rotation import rotation_from_euler

if TYPE_CHECKING:
    from stewart63_ros.core.mechanism import Mechanism
    from stewart63_ros.core.reference import Reference
    from stewart63_ros.core.setup import Setup

ZERO, HOLD, DESCEND = 'zero', 'hold', 'descend'

#: cause -> (safe action, what crossed)
CAUSES: dict[str, tuple[str, str]] = {
    'lengths_stale': (ZERO, 'no valid leg_lengths reading (NaN or missing) for longer than '
                            'stale_lengths_ms'),
    'forces_stale': (HOLD, 'no request from the controller for longer than stale_forces_ms'),
    'bad_command': (HOLD, 'a request that is not six finite forces'),
    'force': (HOLD, 'a requested force above trip_force'),
    'force_rate': (HOLD, 'a requested force changing faster than trip_force_rate'),
    'stroke': (DESCEND, 'a leg outside the soft stroke (stroke_margin inside leg_length_min/max)'),
    'leg_speed': (DESCEND, 'a leg faster than trip_leg_speed'),
    'tracking_error': (DESCEND, 'a leg farther than trip_tracking_error from its reference for '
                                'trip_tracking_time'),
    'pose_box': (DESCEND, 'the platform outside pose_box or tilted more than trip_tilt'),
    'diagnostics_error': (DESCEND, 'an ERROR on /diagnostics from a node of the rig'),
    'user_request': (DESCEND, 'a trip asked for on the supervisor\'s trip_request topic'),
    'estop': (DESCEND, '~/estop'),
    'homing': (ZERO, 'the offsets the homing found could not be set on the drives'),
}

#: The supervisor's keys of core/node_parameters.py that ``Limits`` reads.
LIMIT_KEYS = ('stroke_margin', 'trip_leg_speed', 'trip_force', 'trip_force_rate',
              'trip_tracking_error', 'trip_tracking_time', 'pose_box', 'trip_tilt',
              'stale_lengths_ms', 'stale_forces_ms', 'descent_speed', 'rest_clearance')


@dataclasses.dataclass(frozen=True)
class Limits:
    """The supervisor's limits, checked against each other and the mechanism.

    Attributes (0 turns a check off where the key's doc says so):
        soft_min, soft_max: the soft stroke [m].
        leg_speed [m/s]; force [N]; force_rate [N/s].
        tracking_error [m]; tracking_time [s].
        box: (6,) x, y, z min then max [m], or None; tilt [rad].
        stale_lengths, stale_forces [s] (from the keys in ms).
        descent_speed [m/s]; rest_clearance [m].
    """
    soft_min: float
    soft_max: float
    leg_speed: float
    force: float
    force_rate: float
    tracking_error: float
    tracking_time: float
    box: np.ndarray | None
    tilt: float
    stale_lengths: float
    stale_forces: float
    descent_speed: float
    rest_clearance: float


def limits_from_params(mech: Mechanism, params: Mapping[str, Any],
                       rate: float | None = None) -> Limits:
    """The limits of ``params`` (the supervisor's keys), checked together.

    Args:
        mech: the mechanism (stroke, max_force).
        params: the node's parameters.
        rate: the sample rate [Hz] (the force-rate check's period); None:
            ``sensor_rate`` of ``params``.

    Returns:
        The ``Limits``.

    Raises:
        ParameterError: a key out of its range, or limits that contradict
            each other or the mechanism; the message names the key.
    """
    value = {name: read_declared(params, name) for name in LIMIT_KEYS}
    stroke = mech.leg_length_max - mech.leg_length_min
    margin = value['stroke_margin']
    if not 2 * margin < stroke:
        raise ParameterError('stroke_margin', '%g m on each end leaves no soft stroke of '
                             'the %g m between leg_length_min and leg_length_max'
                             % (margin, stroke))
    soft_min, soft_max = mech.leg_length_min + margin, mech.leg_length_max - margin
    box = value['pose_box']         # (its check: each minimum below its maximum)
    force = value['trip_force'] or float(mech.max_force)
    rate = read_declared(params, 'sensor_rate') if rate is None else rate
    # Requests above `force` trip first: no change between two samples is
    # larger than 2 force, so a force-rate limit above 2 force x rate would
    # be accepted and never act.
    if value['trip_force_rate'] and value['trip_force_rate'] >= 2 * force * rate:
        raise ParameterError('trip_force_rate', '%g N/s can never trip: with trip_force %g N '
                             'at %g Hz the largest change between two samples is %g N/s '
                             '(0 turns the check off)' % (value['trip_force_rate'], force,
                                                           rate, 2 * force * rate))
    if value['descent_speed'] <= 0:
        raise ParameterError('descent_speed', 'must be > 0 (the descent must end)')
    if value['trip_leg_speed'] and value['descent_speed'] >= value['trip_leg_speed']:
        raise ParameterError('descent_speed', '%g m/s is not below trip_leg_speed (%g m/s): '
                             'the descent would trip on its own speed'
                             % (value['descent_speed'], value['trip_leg_speed']))
    if value['rest_clearance'] >= soft_max - soft_min:
        raise ParameterError('rest_clearance', '%g m above the soft lower limit is past the '
                             'soft upper one (soft stroke %g m)'
                             % (value['rest_clearance'], soft_max - soft_min))
    return Limits(soft_min=soft_min, soft_max=soft_max, leg_speed=value['trip_leg_speed'],
                  force=force, force_rate=value['trip_force_rate'],
                  tracking_error=value['trip_tracking_error'],
                  tracking_time=value['trip_tracking_time'], box=box, tilt=value['trip_tilt'],
                  stale_lengths=value['stale_lengths_ms'] * 1e-3,
                  stale_forces=value['stale_forces_ms'] * 1e-3,
                  descent_speed=value['descent_speed'],
                  rest_clearance=value['rest_clearance'])


def rest_lengths(setup: Setup, limits: Limits) -> np.ndarray:
    """The rest pose's leg lengths: the platform level (zero Euler angles),
    over the initial position's x, y, lowered until its shortest leg is
    ``rest_clearance`` above the soft lower limit.

    Lowering a level platform shortens every leg (each leg's length grows
    with z where the platform is above its base points), so the rest pose is
    found by bisection on z.

    Args:
        setup: the machine and the task (its initial position).
        limits: the supervisor's limits.

    Returns:
        (6,) lengths [m], inside the soft stroke.

    Raises:
        ParameterError: (``rest_clearance``) no such level pose inside the soft
            stroke; (``pose_box``) the rest pose outside ``pose_box``.
    """
    mech = setup.mechanism
    rot = rotation_from_euler(np.zeros(3))
    x, y = float(setup.task.initial_position[0]), float(setup.task.initial_position[1])
    target = limits.soft_min + limits.rest_clearance

    def shortest(z):
        return float(np.min(leg_lengths(mech, np.array([x, y, z]), rot)))

    low, high = 1e-3, mech.leg_length_max * 2
    if not shortest(low) < target < shortest(high):
        raise ParameterError('rest_clearance', 'no level pose has its shortest leg at %g m'
                             % target)
    for _ in range(100):
        mid = 0.5 * (low + high)
        low, high = (mid, high) if shortest(mid) < target else (low, mid)
    lengths = leg_lengths(mech, np.array([x, y, high]), rot)
    if np.max(lengths) > limits.soft_max:
        raise ParameterError('rest_clearance', 'the level rest pose (z = %.4f m) puts a leg at '
                             '%.4f m, past the soft upper limit %.4f m'
                             % (high, np.max(lengths), limits.soft_max))
    box = limits.box
    rest = np.array([x, y, high])
    if box is not None and ((rest < box[:3]) | (rest > box[3:])).any():
        # a platform at rest would trip on the box, and no reset would clear it
        raise ParameterError('pose_box', 'the rest pose (%.4f, %.4f, %.4f) m is outside the '
                             'box %s m: a platform at rest could never be reset'
                             % (x, y, high, np.round(box, 4).tolist()))
    return lengths


class Descent:
    """Each leg's setpoint from ``start`` to ``end`` on a cosine profile:
    L(t) = start + (end - start) (1 - cos(pi t / T)) / 2, the peak speed
    pi D / (2 T) = ``speed`` for the leg that moves farthest (D).

    Args:
        start, end: (6,) lengths [m]; speed: the peak leg speed [m/s].
    """

    def __init__(self, start: ArrayLike, end: ArrayLike, speed: float) -> None:
        self.start = np.array(start, float)
        self.end = np.array(end, float)
        distance = float(np.max(np.abs(self.end - self.start)))
        self.duration = math.pi * distance / (2.0 * speed) if distance > 0 else 0.0

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(setpoint (6,) [m], its rate (6,) [m/s]) at ``t`` [s] after the start."""
        if t >= self.duration:
            return self.end, np.zeros(6)
        w = math.pi / self.duration
        span = self.end - self.start
        return (self.start + span * 0.5 * (1.0 - math.cos(w * t)),
                span * 0.5 * w * math.sin(w * t))


class Homing:
    """Homing of incremental leg sensors against the end stops (docs/supervisor.md).

    Every leg's setpoint moves from its reading at the start towards its end
    stop (``extend``: ``leg_length_max``; ``retract``: ``leg_length_min``) at
    ``speed``, tracked by PD with the gravity load held. A leg that stalls
    (its rate below a quarter of ``speed``) while pushing more than ``force``
    beyond its load is at its stop: its offset is its reading there minus the
    stop's length (the stop's spring compressed by that push, ``endstop
    stiffness``), and it keeps that force until every leg is found. Then the
    offsets are to be set on the drives (``zero_to_set``; the readings are
    true from the next sample), and every leg returns to its starting length
    on the cosine profile at ``speed``; then the homing is done.

    Args:
        setup: the machine (stroke, ``max_force``) and the gains (``kp``, ``kv``).
        direction: ``extend`` or ``retract``.
        speed: [m/s]; force: [N]; stiffness: the end stops' [N/m].
    """

    def __init__(self, setup: Setup, direction: str, speed: float, force: float,
                 stiffness: float) -> None:
        mech = setup.mechanism
        self.sign = 1.0 if direction == 'extend' else -1.0
        self.stop = mech.leg_length_max if direction == 'extend' else mech.leg_length_min
        self.speed, self.force, self.stiffness = speed, force, stiffness
        self.kp, self.kv = np.array(setup.gains.kp, float), np.array(setup.gains.kv, float)
        self.max_force = float(mech.max_force)
        self.start: np.ndarray | None = None
        self.start_ns = 0
        self.at_stop = np.zeros(6, bool)
        self.held = np.zeros(6)
        self.offsets = np.full(6, np.nan)
        self.found_ns = np.zeros(6, dtype=np.int64)
        self.back: Descent | None = None
        self.back_ns = 0
        self.zero_to_set: np.ndarray | None = None
        self.done = False

    def forces(self, ns: int, lengths: np.ndarray, rates: np.ndarray,
               holding: np.ndarray) -> np.ndarray:
        """The forces (6,) [N] for sample ``ns`` with these readings; ``holding``:
        the forces that hold the mechanism against gravity there."""
        if self.start is None:
            self.start, self.start_ns = lengths.copy(), ns
        if self.back is not None:           # the readings are true now
            setpoint, rate = self.back.at((ns - self.back_ns) * 1e-9)
            self.done = ns - self.back_ns >= (self.back.duration + 0.5) * 1e9
            force = holding + self.kp * (setpoint - lengths) + self.kv * (rate - rates)
            return np.clip(force, -self.max_force, self.max_force)
        velocity = self.sign * self.speed
        target = self.start + velocity * (ns - self.start_ns) * 1e-9
        force = holding + self.kp * (target - lengths) + self.kv * (velocity - rates)
        force = np.clip(force, -self.max_force, self.max_force)
        force[self.at_stop] = self.held[self.at_stop]
        push = self.sign * (force - holding)
        found = ~self.at_stop & (np.abs(rates) < 0.25 * self.speed) & (push > self.force)
        for i in np.flatnonzero(found):
            self.at_stop[i] = True
            self.held[i] = force[i]
            squeeze = push[i] / self.stiffness if math.isfinite(self.stiffness) else 0.0
            self.offsets[i] = lengths[i] - (self.stop + self.sign * squeeze)
            self.found_ns[i] = ns
        if self.at_stop.all():
            self.zero_to_set = self.offsets.copy()
            self.back = Descent(lengths - self.offsets, self.start - self.offsets, self.speed)
            self.back_ns = ns
        return force


def check_homing(mech: Mechanism, direction: str) -> None:
    """Raise ParameterError (``homing_direction``) if no pose has every leg at
    the end stops of ``direction``: the legs could not all reach them.

    Args:
        mech: the mechanism.
        direction: ``extend`` or ``retract``.

    Raises:
        ParameterError: with the forward kinematics' reason.
    """
    stop = mech.leg_length_max if direction == 'extend' else mech.leg_length_min
    try:
        ForwardKinematics(mech).all_modes(np.full(6, stop))
    except NoAssemblyError as exc:
        raise ParameterError('homing_direction', '%s: the legs cannot all be at their %s '
                             'end stops (%g m): %s' % (direction, 'upper' if direction ==
                                                      'extend' else 'lower', stop, exc)) from None


@dataclasses.dataclass
class Trip:
    """A latched trip: its cause, its words, the samples (stamps [ns])."""
    cause: str
    detail: str
    sample_ns: int              # the sample on which the limit was crossed
    safe_ns: int | None = None  # the sample whose answer was the first safe force

    @property
    def action(self) -> str:
        """The safe action of its cause: ``zero``, ``hold`` or ``descend``."""
        return CAUSES[self.cause][0]


class Supervisor:
    """Per-sample checks, the latch, the safe actions (see the module's doc).

    Args:
        setup: the machine (stroke), the gains for hold and descent, the task
            (the rest pose's x, y).
        limits: from ``limits_from_params``.
        rate: the sample rate [Hz].
        reference: what the controller follows (the tracking check), or None
            (no tracking check).
        pose: a function lengths (6,) -> (position (3,), rotation (3, 3)),
            the forward kinematics for the pose box, or None (no box check).
    """

    def __init__(self, setup: Setup, limits: Limits, rate: float,
                 reference: Reference | None = None,
                 pose: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
                 homing: Homing | None = None) -> None:
        self.setup = setup
        self.mech = mech = setup.mechanism
        self.period = 1.0 / rate
        self.reference = reference
        self.pose = pose
        self.kp = np.array(setup.gains.kp, float)
        self.kv = np.array(setup.gains.kv, float)
        self.max_force = float(mech.max_force)
        self.set_limits(limits)
        self.trip: Trip | None = None
        self.trips: list[Trip] = []
        self.last_good: np.ndarray | None = None     # lengths of the last good sample
        self.last_good_ns: int | None = None
        self.last_request_ns: int | None = None
        self.last_forwarded = np.zeros(6)
        self.last_request = self.previous_request = None
        self.start_ns: int | None = None             # the reference's time 0
        self.first_ns: int | None = None             # the run's sample 0
        self.tracking_since: int | None = None       # first sample of the current excess
        self.descent: Descent | None = None
        self.sample_ns = -1
        self.lengths = np.full(6, np.nan)
        self.rates = np.full(6, np.nan)
        self._ref = None
        self._gravity = None
        self.checked = 0
        #: the homing under way (None: done, or none asked for)
        self.homing = homing
        self.homed = homing is None
        self.offsets = np.zeros(6)          # what the homing found [m]

    def set_limits(self, limits: Limits) -> None:
        """New limits (checked by ``limits_from_params``); the rest pose follows."""
        self.rest = rest_lengths(self.setup, limits)
        self.limits = limits

    def new_run(self) -> None:
        """The samples' source started a new run (stamps from 0 again): the
        clocks of the checks start over; a latched trip stays."""
        self.start_ns = self.last_request_ns = self.last_good_ns = self.first_ns = None
        self.tracking_since = None

    # -- the checks -------------------------------------------------------------------
    def on_sample(self, ns: int, lengths: np.ndarray, rates: np.ndarray) -> None:
        """Sample ``ns`` [ns] came with these readings (NaN: a leg's reading is
        missing): check every limit on it; a crossing trips."""
        self.sample_ns = ns
        self.lengths, self.rates = lengths, rates
        if self.start_ns is None:
            self.start_ns = ns
        if self.first_ns is None:
            self.first_ns = ns
        if self.last_request_ns is None:
            self.last_request_ns = ns       # the controller's silence counts from here
        cause = self._sample_cause(ns, lengths, rates)
        if cause is None:
            if self.trip is None:       # hold keeps the lengths of the trip
                self.last_good = lengths
            self.last_good_ns = ns
        elif self.trip is None:
            self.trip_now(*cause)

    def _sample_cause(self, ns, lengths, rates):
        lim = self.limits
        self.checked += 1
        if not (np.all(np.isfinite(lengths)) and np.all(np.isfinite(rates))):
            since = self.last_good_ns if self.last_good_ns is not None else self.start_ns
            if (ns - since) * 1e-9 > lim.stale_lengths - 1e-12:
                return 'lengths_stale', 'no valid reading for %.1f ms (legs %s NaN)' % (
                    (ns - since) * 1e-6, _legs(~np.isfinite(lengths) | ~np.isfinite(rates)))
            return 'missing', ''
        if self.homing is not None:       # homing: the other limits do not apply yet
            return None
        if (ns - self.last_request_ns) * 1e-9 > lim.stale_forces - 1e-12 and self.trip is None:
            return 'forces_stale', 'no request for %.1f ms' % ((ns - self.last_request_ns) * 1e-6)
        cause = self._stroke_cause(lengths) or self._speed_cause(rates)
        if cause is not None:
            return cause
        if self.reference is not None and lim.tracking_error:
            ref = self._ref = self.reference.sample((ns - self.start_ns) * 1e-9, self._ref)
            error = np.abs(lengths - ref[R_LEN])
            if error.max() > lim.tracking_error:
                if self.tracking_since is None:
                    self.tracking_since = ns
                if (ns - self.tracking_since) * 1e-9 >= lim.tracking_time - 1e-12:
                    i = int(np.argmax(error))
                    return 'tracking_error', 'leg_%d %.4f m from its reference for %.3f s ' \
                        '(limits %g m, %g s)' % (i + 1, error[i], (ns - self.tracking_since)
                                                 * 1e-9, lim.tracking_error, lim.tracking_time)
            else:
                self.tracking_since = None
        if self.pose is not None and (lim.box is not None or lim.tilt):
            cause = self._pose_cause(lengths)
            if cause is not None:
                return cause
        return None

    def _stroke_cause(self, lengths):
        lim = self.limits
        low, high = lengths < lim.soft_min, lengths > lim.soft_max
        if low.any() or high.any():
            i = int(np.flatnonzero(low | high)[0])
            return 'stroke', 'leg_%d at %.4f m, soft stroke [%.4f, %.4f] m' % (
                i + 1, lengths[i], lim.soft_min, lim.soft_max)
        return None

    def _speed_cause(self, rates):
        lim = self.limits
        if lim.leg_speed:
            fast = np.abs(rates) > lim.leg_speed
            if fast.any():
                i = int(np.flatnonzero(fast)[0])
                return 'leg_speed', 'leg_%d at %.3f m/s, limit %g m/s' % (
                    i + 1, rates[i], lim.leg_speed)
        return None

    def _pose_cause(self, lengths):
        lim = self.limits
        try:
            position, rotation = self.pose(lengths)
        except ValueError as exc:           # NoAssemblyError: no pose has these lengths
            return 'pose_box', 'no pose has these leg lengths: %s' % exc
        if lim.box is not None:
            out = (position < lim.box[:3]) | (position > lim.box[3:])
            if out.any():
                i = int(np.flatnonzero(out)[0])
                return 'pose_box', '%s = %.4f m outside [%g, %g] m' % (
                    'xyz'[i], position[i], lim.box[i], lim.box[i + 3])
        if lim.tilt:
            tilt = math.acos(max(-1.0, min(1.0, float(rotation[2, 2]))))
            if tilt > lim.tilt:
                return 'pose_box', 'tilt %.4f rad, limit %g rad' % (tilt, lim.tilt)
        return None

    def on_request(self, ns: int, forces: np.ndarray) -> np.ndarray:
        """The controller's request answering sample ``ns``: checked, then the
        forces to send (the request itself, or the safe action's).

        Args:
            ns: the stamp of the sample it answers [ns].
            forces: what the controller asked for (any shape: checked here).

        Returns:
            (6,) forces [N] to send, stamped ``ns``.
        """
        self.last_request_ns = max(ns, self.last_request_ns or ns)
        self.previous_request, self.last_request = self.last_request, forces
        if self.trip is None:
            cause = self._request_cause(forces)
            if cause is not None:
                self.trip_now(*cause)
        if self.trip is not None:
            return self.safe_forces(ns)
        self.last_forwarded = forces
        return forces

    def _request_cause(self, forces):
        lim = self.limits
        forces = np.asarray(forces)
        if forces.shape != (6,) or not np.all(np.isfinite(forces)):
            return 'bad_command', 'request of shape %s: %s' % (
                forces.shape, np.array2string(forces.ravel()[:12], precision=4))
        big = np.abs(forces) > lim.force
        if big.any():
            i = int(np.flatnonzero(big)[0])
            return 'force', 'leg_%d %.1f N, limit %g N' % (i + 1, forces[i], lim.force)
        if lim.force_rate:
            rate = np.abs(forces - self.last_forwarded) / self.period
            fast = rate > lim.force_rate
            if fast.any():
                i = int(np.flatnonzero(fast)[0])
                return 'force_rate', 'leg_%d %.4g N/s, limit %g N/s' % (
                    i + 1, rate[i], lim.force_rate)
        return None

    def no_request(self, ns: int) -> np.ndarray:
        """No request will answer sample ``ns`` (a sample with a missing
        reading, which the controller refuses; or none came in time): the
        forces to send instead. Untripped: the last forwarded force, which is
        what the plant would hold; the silence counts towards stale_forces_ms
        (checked on the next sample)."""
        if self.trip is not None:
            return self.safe_forces(ns)
        return self.last_forwarded

    # -- the latch --------------------------------------------------------------------
    def sample_index(self, ns: int) -> int:
        """The index of the sample stamped ``ns`` in this run, counted from its
        first sample (realtime stamps are wall-clock times; a homing does not
        restart the count)."""
        return int(round((ns - (self.first_ns or 0)) * 1e-9 / self.period))

    def trip_report(self, trip: Trip) -> dict[str, Any]:
        """What a trip says (/diagnostics, the summary): cause, detail, safe
        action, the sample that crossed the limit, its stamp, and the latency
        in samples from it to the first safe force (None: not yet answered)."""
        sample = self.sample_index(trip.sample_ns)
        return {'cause': trip.cause, 'detail': trip.detail, 'action': trip.action,
                'sample': sample, 'stamp_ns': trip.sample_ns,
                'latency_samples': None if trip.safe_ns is None else
                self.sample_index(trip.safe_ns) - sample}

    def trip_now(self, cause: str, detail: str, ns: int | None = None) -> Trip | None:
        """Trip for ``cause`` (a key of CAUSES) on sample ``ns`` (default: the
        current one). An existing trip stays (the first cause is the one named).
        'missing' (one reading missing, not yet stale) trips nothing."""
        if cause == 'missing':
            return None
        if self.trip is not None:
            return None
        trip = Trip(cause, detail, self.sample_ns if ns is None else ns)
        self.trip = trip
        self.trips.append(trip)
        self.descent = None
        return trip

    def safe_forces(self, ns: int) -> np.ndarray:
        """The forces of the latched trip's safe action for sample ``ns``."""
        trip = self.trip
        if trip.safe_ns is None:
            trip.safe_ns = ns
        lengths, rates = self.lengths, self.rates
        if trip.action == ZERO or self.last_good is None or not (
                np.all(np.isfinite(lengths)) and np.all(np.isfinite(rates))):
            return np.zeros(6)      # no reading to close a loop on
        if trip.action == HOLD:
            setpoint, setpoint_rate = self.last_good, np.zeros(6)
        else:
            if self.descent is None:        # from where the legs are
                self.descent = Descent(lengths, self.rest, self.limits.descent_speed)
                self.descent_start_ns = ns
            setpoint, setpoint_rate = self.descent.at((ns - self.descent_start_ns) * 1e-9)
        return self._pd_gravity(lengths, rates, setpoint, setpoint_rate)

    def homing_forces(self, ns: int) -> np.ndarray:
        """The homing's forces for sample ``ns`` (see ``Homing``); when it is
        done, the supervisor forwards the controller from the next sample on,
        its checks starting over there."""
        homing = self.homing
        lengths, rates = self.lengths, self.rates
        if not (np.all(np.isfinite(lengths)) and np.all(np.isfinite(rates))):
            return np.zeros(6)
        force = homing.forces(ns, lengths, rates, self._holding(lengths, rates))
        if homing.done:
            self.homing, self.homed, self.offsets = None, True, homing.offsets
            self.start_ns = self.last_request_ns = ns
            self.tracking_since = None
            self.last_forwarded = np.zeros(6)
        return force

    def take_zero_to_set(self) -> np.ndarray | None:
        """The offsets the homing found, once, on the sample it found the last
        one: to be set on the drives (subtracted from the readings from the
        next sample on); else None."""
        homing = self.homing
        if homing is None or homing.zero_to_set is None:
            return None
        zero, homing.zero_to_set = homing.zero_to_set, None
        self.offsets = zero
        return zero

    def _holding(self, lengths, rates):
        """The forces that hold the mechanism against gravity at the pose the
        readings give (``PDGravityLaw.holding_forces``); readings that no pose
        has (a lying sensor, the ``pose_box`` trip's) keep those of the last
        pose they gave (none yet: zero), so the safe action still acts."""
        if self._gravity is None:
            self._gravity = PDGravityLaw(self.mech, self.setup.to_params())
            self._last_holding = np.zeros(6)
        try:
            position, rotation, _ = self._gravity.estimator(lengths, rates)
        except ValueError:                  # NoAssemblyError
            return self._last_holding
        self._last_holding = self._gravity.holding_forces(position, rotation)
        return self._last_holding

    def _pd_gravity(self, lengths, rates, setpoint, setpoint_rate):
        """Eq. (40) towards ``setpoint`` (its rate as feed-forward) plus the
        forces that hold the mechanism against gravity at the pose the
        readings give (``PDGravityLaw.holding_forces``): without them the
        platform would sag below the rest pose by load / kp (6 cm on the
        default machine's legs 3-6)."""
        holding = self._holding(lengths, rates)
        force = self.kp * (setpoint - lengths) + self.kv * (setpoint_rate - rates) + holding
        return np.clip(force, -self.max_force, self.max_force)

    @property
    def descended(self) -> bool:
        """The descent's profile has reached the rest lengths."""
        return self.descent is not None and (
            self.sample_ns - self.descent_start_ns) * 1e-9 >= self.descent.duration

    def cause_holds(self) -> str:
        """Why a reset would be refused now ('' : it would not): the trip's own
        cause, judged on the latest sample and request, and a reading to
        resume on. Causes that are events (``estop``, ``user_request``) and
        ``tracking_error`` (the safe action itself moves the platform off its
        reference; the check starts over from the reset) do not persist;
        ``diagnostics_error`` is judged by the node (the rig's statuses)."""
        trip = self.trip
        if trip is None:
            return ''
        ns, lengths, rates, lim = self.sample_ns, self.lengths, self.rates, self.limits
        if not (np.all(np.isfinite(lengths)) and np.all(np.isfinite(rates))):
            return 'the leg readings are missing (NaN) on the latest sample'
        cause = trip.cause
        if cause == 'forces_stale' and (ns - self.last_request_ns) * 1e-9 > lim.stale_forces:
            return 'no request from the controller for %.1f ms' % (
                (ns - self.last_request_ns) * 1e-6)
        if cause in ('bad_command', 'force', 'force_rate') and self.last_request is not None:
            saved = self.last_forwarded
            previous = self.previous_request
            if previous is not None and np.shape(previous) == (6,) \
                    and np.all(np.isfinite(previous)):
                self.last_forwarded = previous
            found = self._request_cause(self.last_request)
            self.last_forwarded = saved
            if found is not None and found[0] == cause:
                return 'the latest request: %s' % found[1]
        checks = {'stroke': lambda: self._stroke_cause(lengths),
                  'leg_speed': lambda: self._speed_cause(rates),
                  'pose_box': lambda: self._pose_cause(lengths) if self.pose else None}
        found = checks.get(cause, lambda: None)()
        return found[1] if found else ''

    def reset(self) -> tuple[bool, str]:
        """``~/reset``: clear the trip unless its cause persists.

        Returns:
            (accepted, the reason or what was cleared).
        """
        if self.trip is None:
            return True, 'not tripped'
        why = self.cause_holds()
        if why:
            return False, 'the cause of the trip (%s) persists: %s' % (self.trip.cause, why)
        cleared = self.trip
        self.trip = None
        self.descent = None
        self.tracking_since = None
        # A request that comes now is checked against a rate from zero, not
        # from the force forwarded before the trip.
        self.last_forwarded = np.zeros(6)
        self.last_request_ns = self.sample_ns
        return True, 'reset: %s trip of sample %d cleared' % (
            cleared.cause, self.sample_index(cleared.sample_ns))


def _legs(mask) -> str:
    return ','.join(str(i + 1) for i in np.flatnonzero(mask))


def run_supervised(setup: Setup, supervisor: Supervisor, duration: float, rate: float,
                   faults: Any = None, controller: Any = None,
                   y0: ArrayLike | None = None, sensor: Any = None,
                   homing_offset: ArrayLike | None = None,
                   wrench: ArrayLike | None = None) -> dict[str, np.ndarray]:
    """The closed loop with the supervisor between controller and plant, as a
    lockstep rig with ``rig --supervisor`` runs it, sample for sample.

    Sample k (stamp k / rate): the faults begin k; the sensors read; the
    supervisor checks the sample; tripped, it answers with its safe action;
    else the controller's request (none for a sample with a missing reading)
    is checked and forwarded; the pistons apply the answer (actuator faults)
    over the period (the plant's RK4, ``Dynamics.step``). A law that raises
    (``LawError``) trips it on that sample (``diagnostics_error``), as the
    controller's ERROR does on the rig.

    Args:
        setup: the machine, gains and task.
        supervisor: a fresh ``Supervisor`` at ``rate``.
        duration: simulated seconds; rate: samples per second [Hz].
        faults: a ``FaultModel`` or fault strings (core/faults.py), or None.
        controller: a ``laws.Controller`` (default: eq. (40) to the setpoint).
        y0: the initial state (default: the parameters').
        sensor: a ``SensorModel`` (core/sensor.py) the readings go through, as
            the plant's do, or None (ideal sensors).
        homing_offset: (6,) the sensors' hidden zero [m] (the plant's key of
            that name), added to the readings until the supervisor's homing
            sets its offsets (from the sample after it found them).
        wrench: (N, 6) the external wrench [N, N m] (platform frame) held over
            each sample's period (``scenario.wrench_samples``), or None.

    Returns:
        {'states' (N, 13), 'lengths' (N, 6) the true lengths [m], 'measured'
        (N, 6), 'forces' (N, 6) sent [N], 'requests' (N, 6) the controller's
        (NaN: none)}, N = duration * rate + 1.
    """
    # lazy: core.simulate costs 990 ms (scipy.optimize); the node never runs it
    from stewart63_ros.core.simulate import initial_state, sensor_reading, substeps_for
    if not isinstance(faults, FaultModel):
        faults = FaultModel(parse_faults(faults or []), rate)
    controller = controller or Controller(setup)
    n = int(round(duration * rate))
    if wrench is not None:
        wrench = np.asarray(wrench, float)
        if wrench.shape != (n + 1, 6):
            raise ValueError('wrench must be (%d, 6), one row per sample, got %s'
                             % (n + 1, wrench.shape))
    dyn = Dynamics(setup.mechanism)
    period = 1.0 / rate
    steps = substeps_for(period)
    y = initial_state(setup.task) if y0 is None else np.array(y0, float)
    out = {key: np.full((n + 1, size), np.nan) for key, size in (
        ('states', 13), ('lengths', 6), ('measured', 6), ('forces', 6), ('requests', 6))}
    shift = np.zeros(6) if homing_offset is None else np.array(homing_offset, float)
    for k in range(n + 1):
        ns = int(round(k * period * 1e9))
        faults.begin(k)
        true_lengths, rates = sensor_reading(dyn, y)
        out['states'][k], out['lengths'][k] = y, true_lengths
        lengths = true_lengths + shift if shift.any() else true_lengths
        if sensor is not None:
            lengths, rates = sensor.measure(lengths, rates)
        lengths, rates, complete = faults.sense(lengths, rates)
        out['measured'][k] = lengths
        supervisor.on_sample(ns, lengths, rates)
        if supervisor.trip is not None:
            forces = supervisor.safe_forces(ns)
        elif supervisor.homing is not None:
            forces = supervisor.homing_forces(ns)
            zero = supervisor.take_zero_to_set()
            if zero is not None:            # the plant's homed_offset, set before k + 1
                shift = np.array(homing_offset, float) - zero
        elif complete:
            try:
                request = controller.forces(k * period, lengths, rates)
            except LawError as exc:
                # the controller withholds the forces and reports ERROR:
                # the supervisor trips on that sample (a law asks by raising)
                supervisor.trip_now('diagnostics_error', 'controller: %s' % exc)
                forces = supervisor.safe_forces(ns)
            else:
                out['requests'][k] = request
                forces = supervisor.on_request(ns, request)
        else:
            forces = supervisor.no_request(ns)
        out['forces'][k] = forces
        if k < n:
            push = None if wrench is None else (wrench[k, :3], wrench[k, 3:])
            y = dyn.step(y, faults.actuate(forces), period, steps, wrench=push)
    return out


def supervisor_from_params(setup: Setup, params: Mapping[str, Any],
                           rate: float) -> Supervisor:
    """The supervisor a node with ``params`` runs: its limits, the reference
    the controller follows (``reference_file``, else ``setpoint_lengths``),
    the forward kinematics (core/fk.py ``FKTracker``) for the pose box.

    Args:
        setup: the machine, gains and task.
        params: the node's parameters.
        rate: the sample rate [Hz].

    Returns:
        A fresh ``Supervisor``.

    Raises:
        ParameterError: a limit out of range or contradicting another, the
            reference file unreadable (key ``reference_file``).
    """
    mech = setup.mechanism
    limits = limits_from_params(mech, params, rate)
    start = (setup.task.initial_position, setup.task.initial_rotation)
    path = read_declared(params, 'reference_file')
    if path:
        try:
            reference = load_reference(mech, path)
        except ReferenceError as exc:
            raise ParameterError('reference_file', str(exc)) from None
    else:
        reference = Reference.constant_lengths(mech, setup.task.setpoint_lengths, near=start)
    tracker = FKTracker(mech, *start)

    def pose(lengths):
        result = tracker.solve(lengths)
        return result.position, result.rotation

    homing = None
    if read_declared(params, 'homing'):
        direction = read_declared(params, 'homing_direction')
        check_homing(mech, direction)
        speed = read_declared(params, 'homing_speed')
        if limits.leg_speed and speed >= limits.leg_speed:
            raise ParameterError('homing_speed', '%g m/s is not below trip_leg_speed (%g m/s)'
                                 % (speed, limits.leg_speed))
        homing = Homing(setup, direction, speed, read_declared(params, 'homing_force'),
                        mech.endstop_stiffness)
    return Supervisor(setup, limits, rate, reference, pose, homing)
