"""The supervisor's trip logic: limits, latched trips and the safe actions (no ROS).

The ``supervisor`` node (nodes/supervisor.py) sits between the controller and
the machine; per sample it hands this core the sample (``on_sample``) and the
controller's request for it (``on_request``), or says that none came
(``no_request``), and sends on ``leg_forces`` what comes back: the request
forwarded, or, once a limit is crossed, the safe action of that cause.
While tripped the node still hands over every sample and every request
(``note_request``): a reset judges the cause on the live state.
docs/supervisor.md is the user's page.

A trip latches: it names its cause, the sample (stamp) on which the limit was
crossed, and the sample whose answer was the first safe force (the trip's
latency in samples is the difference: 0 here, by construction, since the
answer to the sample that crosses a limit is already the safe force). It
holds until ``reset``, refused while the cause persists; an accepted reset
starts the return (supervisor_motion.Return): the setpoint goes from where
the legs are to the controller's reference at ``return_speed``, then the
controller's forces take over.

Safe actions (one per cause, ``CAUSES``):

- ``zero``: no force. For causes that leave no measurement to close a loop on
  (stale or NaN leg readings): the platform settles onto its lower end stops.
- ``hold``: leg-length PD, eq. (40), on the last good lengths (those of the
  last sample that passed every check), with the model's ``kp``, ``kv``,
  ``max_force``: for a bad command (the controller's forces) while the
  sensors are sound, and near a singularity.
- ``descend``: a profiled descent in leg space from the lengths at the trip
  to the rest lengths (``rest_lengths``), each leg's setpoint on a cosine
  profile whose peak speed is ``descent_speed``, tracked by PD with the
  profile's rate as feed-forward; then held at rest.

The parts: supervisor_limits.py (causes, limits, the rest pose),
supervisor_checks.py (the checks), supervisor_motion.py (descent, return,
homing, the PD with gravity held).
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from stewart63_ros.core.controllers.laws import Controller, LawError
from stewart63_ros.core.controllers.reference import R_LEN, Reference, ReferenceError
from stewart63_ros.core.controllers.reference_files import load_reference
from stewart63_ros.core.machine.faults import FaultModel, parse_faults
from stewart63_ros.core.machine.supervisor_checks import (
    PoseFunction,
    latest_request_cause,
    legs,
    pose_cause,
    readings_complete,
    request_cause,
    speed_cause,
    stroke_cause,
)
from stewart63_ros.core.machine.supervisor_limits import (  # noqa: F401 (the supervisor's names)
    CAUSES,
    DESCEND,
    HOLD,
    LIMIT_KEYS,
    ZERO,
    Limits,
    limits_from_params,
    rest_lengths,
)
from stewart63_ros.core.machine.supervisor_motion import (  # noqa: F401 (the supervisor's names)
    Descent,
    GravityPD,
    Homing,
    Return,
    check_homing,
)
from stewart63_ros.core.mechanics.dynamics import Dynamics
from stewart63_ros.core.mechanics.fk import FKTracker
from stewart63_ros.core.plumbing.errors import ParameterError
from stewart63_ros.core.plumbing.node_parameters import read as read_declared

if TYPE_CHECKING:
    from stewart63_ros.core.mechanics.setup import Setup


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
    """Per-sample checks, the latch, the safe actions, the return after a
    reset (see the module's doc).

    Args:
        setup: the machine (stroke), the gains for hold and descent, the task
            (the rest pose's x, y).
        limits: from ``limits_from_params``.
        rate: the sample rate [Hz].
        reference: what the controller follows (the tracking check, the
            return's target), or None (no tracking check).
        pose: the forward kinematics for the pose box and the singularity
            check (``supervisor_checks.PoseFunction``), or None (neither).
        homing: the homing to run first, or None.
        return_at_start: begin with the return a reset makes.
    """

    def __init__(self, setup: Setup, limits: Limits, rate: float,
                 reference: Reference | None = None, pose: PoseFunction | None = None,
                 homing: Homing | None = None, return_at_start: bool = False) -> None:
        self.setup = setup
        self.mech = setup.mechanism
        self.period = 1.0 / rate
        self.reference = reference
        self.pose = pose
        self.pd = GravityPD(setup)
        self.set_limits(limits)
        self.trip: Trip | None = None
        self.trips: list[Trip] = []
        self.last_good: np.ndarray | None = None     # lengths of the last good sample
        self.last_good_ns: int | None = None
        self.last_request_ns: int | None = None
        self.heard_ns = -1          # the sample current when the latest request came
        self.last_forwarded = np.zeros(6)
        self.last_request = self.previous_request = None
        self.start_ns: int | None = None             # the reference's time 0
        self.first_ns: int | None = None             # the run's sample 0
        self.tracking_since: int | None = None       # first sample of the current excess
        self.descent: Descent | None = None
        self.descent_start_ns = 0
        #: after a reset (or at the start): True until its first complete
        #: sample, then the Return under way
        self.return_at_start = return_at_start
        self.returning: Return | bool | None = True if return_at_start else None
        self.sample_ns = -1
        self.lengths = np.full(6, np.nan)
        self.rates = np.full(6, np.nan)
        self._ref = None
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
        self.returning = True if self.return_at_start else None

    @property
    def state(self) -> str:
        """``tripped``, ``descended`` (tripped, the descent at rest),
        ``homing``, ``returning`` (after a reset) or ``forwarding``."""
        if self.trip is not None:
            return 'descended' if self.descended else 'tripped'
        if self.homing is not None:
            return 'homing'
        return 'returning' if self.returning else 'forwarding'

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
        if self.returning is True and self.trip is None and readings_complete(lengths, rates):
            self.returning = Return(lengths, ns, self.reference,
                                    (ns - self.start_ns) * 1e-9, self.limits.return_speed)
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
        if not readings_complete(lengths, rates):
            since = self.last_good_ns if self.last_good_ns is not None else self.start_ns
            if (ns - since) * 1e-9 > lim.stale_lengths - 1e-12:
                return 'lengths_stale', 'no valid reading for %.1f ms (legs %s NaN)' % (
                    (ns - since) * 1e-6, legs(~np.isfinite(lengths) | ~np.isfinite(rates)))
            return 'missing', ''
        if self.homing is not None:       # homing: the other limits do not apply yet
            return None
        if (ns - self.last_request_ns) * 1e-9 > lim.stale_forces - 1e-12 and self.trip is None:
            return 'forces_stale', 'no request for %.1f ms' % ((ns - self.last_request_ns) * 1e-6)
        cause = stroke_cause(lim, lengths) or speed_cause(lim, rates)
        if cause is not None:
            return cause
        if self.reference is not None and lim.tracking_error and not self.returning:
            cause = self._tracking_cause(ns, lengths)
            if cause is not None:
                return cause
        if self.pose is not None and (lim.box is not None or lim.tilt or lim.condition):
            return pose_cause(lim, self.pose, lengths)
        return None

    def _tracking_cause(self, ns, lengths):
        lim = self.limits
        ref = self._ref = self.reference.sample((ns - self.start_ns) * 1e-9, self._ref)
        error = np.abs(lengths - ref[R_LEN])
        if error.max() <= lim.tracking_error:
            self.tracking_since = None
            return None
        if self.tracking_since is None:
            self.tracking_since = ns
        if (ns - self.tracking_since) * 1e-9 >= lim.tracking_time - 1e-12:
            i = int(np.argmax(error))
            return 'tracking_error', 'leg_%d %.4f m from its reference for %.3f s ' \
                '(limits %g m, %g s)' % (i + 1, error[i], (ns - self.tracking_since) * 1e-9,
                                         lim.tracking_error, lim.tracking_time)
        return None

    def on_request(self, ns: int, forces: np.ndarray) -> np.ndarray:
        """The controller's request answering sample ``ns``: checked, then the
        forces to send (the request itself, or the safe action's, or during
        the return after a reset the return's blended with it).

        Args:
            ns: the stamp of the sample it answers [ns].
            forces: what the controller asked for (any shape: checked here).

        Returns:
            (6,) forces [N] to send, stamped ``ns``.
        """
        self.note_request(ns, forces)
        if self.trip is None:
            cause = request_cause(self.limits, forces, self.last_forwarded, self.period)
            if cause is not None:
                self.trip_now(*cause)
        if self.trip is not None:
            return self.safe_forces(ns)
        self.last_forwarded = forces
        if self.returning:
            return self.return_forces(ns, forces)
        return forces

    def note_request(self, ns: int, forces: np.ndarray | None) -> None:
        """A request the controller sent for sample ``ns``: the latest, which
        a reset judges (``forces_stale``, ``bad_command``, ``force``,
        ``force_rate``). Tripped, the node hands over every request here
        (the answer, the safe force, has gone out already)."""
        self.last_request_ns = max(ns, self.last_request_ns or ns)
        # when it came, on the samples' clock: tripped in lockstep the plant
        # does not wait for the controller, whose requests then lag behind
        # the samples while it is alive
        self.heard_ns = self.sample_ns
        self.previous_request, self.last_request = self.last_request, (ns, forces)

    def no_request(self, ns: int) -> np.ndarray:
        """No request will answer sample ``ns`` (a sample with a missing
        reading, which the controller refuses; or none came in time): the
        forces to send instead. Untripped: the last forwarded force, which is
        what the plant would hold (during the return: the return's own); the
        silence counts towards stale_forces_ms (checked on the next sample)."""
        if self.trip is not None:
            return self.safe_forces(ns)
        if self.returning and readings_complete(self.lengths, self.rates):
            return self.return_forces(ns, None)
        return self.last_forwarded

    def return_forces(self, ns: int, request: np.ndarray | None) -> np.ndarray:
        """The return's forces for sample ``ns``: ``GravityPD`` on its
        setpoint, blended into ``request`` (None: none came) at the hand-over."""
        back = self.returning
        if back is True:            # (no complete reading since the reset yet)
            return self.last_forwarded if request is None else request
        own = self.pd(self.lengths, self.rates, *back.setpoint(ns))
        share = back.blend(ns) if request is not None else 0.0
        if back.done:
            self.returning = None           # the controller's alone from now on
            self.tracking_since = None      # the tracking check starts over here
        return own if share == 0.0 else (1.0 - share) * own + share * np.asarray(request)

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
        if cause == 'missing' or self.trip is not None:
            return None
        trip = Trip(cause, detail, self.sample_ns if ns is None else ns)
        self.trip = trip
        self.trips.append(trip)
        self.descent = None
        self.returning = None
        return trip

    def safe_forces(self, ns: int) -> np.ndarray:
        """The forces of the latched trip's safe action for sample ``ns``."""
        trip = self.trip
        if trip.safe_ns is None:
            trip.safe_ns = ns
        lengths, rates = self.lengths, self.rates
        if trip.action == ZERO or self.last_good is None or not readings_complete(lengths,
                                                                                  rates):
            return np.zeros(6)      # no reading to close a loop on
        if trip.action == HOLD:
            return self.pd(lengths, rates, self.last_good, np.zeros(6))
        if self.descent is None:        # from where the legs are
            self.descent = Descent(lengths, self.rest, self.limits.descent_speed)
            self.descent_start_ns = ns
        return self.pd(lengths, rates, *self.descent.at((ns - self.descent_start_ns) * 1e-9))

    def homing_forces(self, ns: int) -> np.ndarray:
        """The homing's forces for sample ``ns`` (see ``Homing``); when it is
        done, the supervisor forwards the controller from the next sample on,
        its checks starting over there."""
        homing = self.homing
        lengths, rates = self.lengths, self.rates
        if not readings_complete(lengths, rates):
            return np.zeros(6)
        force = homing.forces(ns, lengths, rates, self.pd.holding(lengths, rates))
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

    @property
    def descended(self) -> bool:
        """The descent's profile has reached the rest lengths."""
        return self.descent is not None and (
            self.sample_ns - self.descent_start_ns) * 1e-9 >= self.descent.duration

    def cause_holds(self) -> str:
        """Why a reset would be refused now ('' : it would not): the trip's own
        cause, judged on the latest sample and the latest request (handed
        over while tripped too), and a reading to resume on. Causes that are
        events (``estop``, ``user_request``) and ``tracking_error`` (the safe
        action itself moves the platform off its reference; the check starts
        over after the return) do not persist; ``diagnostics_error`` is judged
        by the node (the rig's statuses), and so is ``homing`` (the node
        sets the offsets again: refused while their owner refuses them)."""
        if self.trip is None:
            return ''
        ns, lengths, rates, lim = self.sample_ns, self.lengths, self.rates, self.limits
        if not readings_complete(lengths, rates):
            return 'the leg readings are missing (NaN) on the latest sample'
        cause = self.trip.cause
        if cause == 'forces_stale' and (ns - self.heard_ns) * 1e-9 > lim.stale_forces:
            return 'no request from the controller for %.1f ms' % ((ns - self.heard_ns) * 1e-6)
        if cause in ('bad_command', 'force', 'force_rate'):
            found = latest_request_cause(lim, self.last_request, self.previous_request,
                                         self.period)
            if found is not None and found[0] == cause:
                return 'the latest request: %s' % found[1]
        checks = {'stroke': lambda: stroke_cause(lim, lengths),
                  'leg_speed': lambda: speed_cause(lim, rates),
                  'pose_box': lambda: pose_cause(lim, self.pose, lengths) if self.pose else None,
                  'singularity': lambda: pose_cause(lim, self.pose, lengths) if self.pose
                  else None}
        found = checks.get(cause, lambda: None)()
        return found[1] if found and found[0] == cause else ''

    def reset(self) -> tuple[bool, str]:
        """``~/reset``: clear the trip unless its cause persists; then the
        return (``Return``) brings the platform to the controller's reference
        before the controller's forces go through alone.

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
        if self.homing is not None:     # (a homing trip: the node has set the offsets now)
            self.homing = self.homing.after_reset(self.lengths, self.sample_ns,
                                                  zero_just_set=cleared.cause == 'homing')
        self.tracking_since = None
        self.returning = True           # from the next complete sample
        # the controller's silence counts from here (it was heard: above)
        self.last_request_ns = max(self.last_request_ns, self.sample_ns)
        # The force-rate check goes on from the controller's latest request:
        # the step from the safe action to the controller is the return's.
        latest = None if self.last_request is None else np.asarray(self.last_request[1])
        self.last_forwarded = latest if latest is not None and latest.shape == (6,) and \
            np.all(np.isfinite(latest)) else np.zeros(6)
        return True, 'reset: %s trip of sample %d cleared' % (
            cleared.cause, self.sample_index(cleared.sample_ns))


def run_supervised(setup: Setup, supervisor: Supervisor, duration: float, rate: float,
                   faults: Any = None, controller: Any = None,
                   y0: ArrayLike | None = None, sensor: Any = None,
                   homing_offset: ArrayLike | None = None,
                   wrench: ArrayLike | None = None) -> dict[str, np.ndarray]:
    """The closed loop with the supervisor between controller and plant, as a
    lockstep rig with ``rig --supervisor`` runs it, sample for sample.

    Sample k (stamp k / rate): the faults begin k; the sensors read; the
    supervisor checks the sample; tripped, it answers with its safe action
    (and the controller's request, computed as the rig's controller does on
    every sample, reaches it after: ``note_request``); else the controller's
    request (none for a sample with a missing reading) is checked and
    forwarded (during a return, blended); the pistons apply the answer (actuator faults)
    over the period (the plant's RK4, ``Dynamics.step``). A law that raises
    (``LawError``) trips it on that sample (``diagnostics_error``), as the
    controller's ERROR does on the rig.

    Args:
        setup: the machine, gains and task.
        supervisor: a fresh ``Supervisor`` at ``rate``.
        duration: simulated seconds; rate: samples per second [Hz].
        faults: a ``FaultModel`` or fault strings (core/machine/faults.py), or None.
        controller: a ``laws.Controller`` (default: eq. (40) to the setpoint).
        y0: the initial state (default: the parameters').
        sensor: a ``SensorModel`` (core/controllers/sensor.py) the readings go through, as
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
    # lazy: core.controllers.simulate costs 990 ms (scipy.optimize); the node never runs it
    from stewart63_ros.core.controllers.simulate import initial_state, sensor_reading, substeps_for
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
            # the safe force goes out at once; the controller's request for
            # this sample still comes (the node hands it over: a reset judges it)
            forces = supervisor.safe_forces(ns)
            if complete:
                try:
                    request = controller.forces(k * period, lengths, rates)
                except LawError:
                    pass
                else:
                    out['requests'][k] = request
                    supervisor.note_request(ns, request)
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
    the forward kinematics (core/mechanics/fk.py ``FKTracker``) for the pose box.

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
        return result.position, result.rotation, result.condition

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
    return Supervisor(setup, limits, rate, reference, pose, homing,
                      return_at_start=read_declared(params, 'return_at_start'))
