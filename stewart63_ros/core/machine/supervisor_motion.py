"""The supervisor's motions: the cosine profile of a descent or a return, and
the homing against the end stops (no ROS).

core/machine/supervisor.py is the supervisor; docs/supervisor.md the user's page.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from stewart63_ros.core.controllers.laws import PDGravityLaw
from stewart63_ros.core.controllers.reference import R_LEN, R_RATE
from stewart63_ros.core.mechanics.fk import ForwardKinematics, NoAssemblyError
from stewart63_ros.core.plumbing.errors import ParameterError

if TYPE_CHECKING:
    from stewart63_ros.core.controllers.reference import Reference
    from stewart63_ros.core.mechanics.mechanism import Mechanism
    from stewart63_ros.core.mechanics.setup import Setup

#: After the return's profile: this long [s] on the reference under the
#: supervisor's PD before the hand-over, and the hand-over's length [s]: the
#: forces blend from the supervisor's to the controller's on a cosine.
SETTLE, HANDOVER = 0.2, 0.3


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
        self.settings = (setup, direction, speed, force, stiffness)
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


    def after_reset(self, lengths: np.ndarray, ns: int, zero_just_set: bool) -> Homing:
        """The homing after a reset of a trip during it, at sample ``ns``
        whose readings are ``lengths``: its setpoint went on while tripped,
        so it starts over from where the legs are. Not every leg found yet:
        a new homing towards the stops. Else the way back to the start
        again, from ``lengths`` (true readings; ``zero_just_set``: the
        offsets were set only now, so ``lengths`` still hold them).

        Returns:
            The homing to go on with (this one, or a new one).
        """
        if self.back is None:
            return Homing(*self.settings)
        true = lengths - self.offsets if zero_just_set else lengths
        self.back = Descent(true, self.start - self.offsets, self.speed)
        self.back_ns = ns
        self.done = False
        return self


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
        # a 6-3's fk names its pair itself ('cannot meet'); a 6-6's says only 'no pose'
        pair = _pair_apart(mech, stop) if mech.layout == '6-6' else ''
        raise ParameterError('homing_direction', '%s: the legs cannot all be at their %s '
                             'end stops (%g m): %s%s' % (
                                 direction, 'upper' if direction == 'extend' else 'lower',
                                 stop, exc, '; ' + pair if pair else '')) from None


def _pair_apart(mech: Mechanism, length: float) -> str:
    """Two legs that cannot both be ``length`` long, in words ('' if every two can).

    Legs i and j at length L put their platform joints, |p_i - p_j| apart on
    the rigid platform, within 2 L + |b_i - b_j| and beyond |b_i - b_j| - 2 L
    of each other: a necessary condition of any pose (a 6-3's pair, p_i =
    p_j, is the fk's own 'cannot meet'; a 6-6's close pair is named here).
    """
    plat = mech.leg_platform_points
    for i in range(6):
        for j in range(i + 1, 6):
            joints = float(np.linalg.norm(plat[i] - plat[j]))
            bases = float(np.linalg.norm(mech.base_points[i] - mech.base_points[j]))
            if joints < bases - 2 * length or joints > bases + 2 * length:
                return ('legs %d and %d cannot both be %g m long: their base points are '
                        '%.4g m apart, their platform joints %.4g m'
                        % (i + 1, j + 1, length, bases, joints))
    return ''




class GravityPD:
    """Eq. (40) towards a setpoint (its rate as feed-forward), plus the forces
    that hold the mechanism against gravity at the pose the readings give
    (``PDGravityLaw.holding_forces``), saturated at ``max_force``: without
    them the platform would sag below its setpoint by load / kp (6 cm on the
    default machine's legs 3-6).

    Args:
        setup: the machine (``max_force``) and the gains (``kp``, ``kv``).
    """

    def __init__(self, setup: Setup) -> None:
        self.setup = setup
        self.kp = np.array(setup.gains.kp, float)
        self.kv = np.array(setup.gains.kv, float)
        self.max_force = float(setup.mechanism.max_force)
        self._gravity: PDGravityLaw | None = None
        self._last_holding = np.zeros(6)

    def holding(self, lengths: np.ndarray, rates: np.ndarray) -> np.ndarray:
        """The forces (6,) [N] that hold the mechanism against gravity at the
        pose of these readings; readings that no pose has (a lying sensor, the
        ``pose_box`` trip's) keep those of the last pose they gave (none yet:
        zero), so the safe action still acts."""
        if self._gravity is None:
            self._gravity = PDGravityLaw(self.setup.mechanism, self.setup.to_params())
        try:
            position, rotation, _ = self._gravity.estimator(lengths, rates)
        except ValueError:                  # NoAssemblyError
            return self._last_holding
        self._last_holding = self._gravity.holding_forces(position, rotation)
        return self._last_holding

    def __call__(self, lengths: np.ndarray, rates: np.ndarray, setpoint: np.ndarray,
                 setpoint_rate: np.ndarray) -> np.ndarray:
        """The forces (6,) [N] towards ``setpoint`` (6,) [m] at ``setpoint_rate``."""
        force = (self.kp * (setpoint - lengths) + self.kv * (setpoint_rate - rates)
                 + self.holding(lengths, rates))
        return np.clip(force, -self.max_force, self.max_force)


class Return:
    """The way back into operation after a reset (docs/supervisor.md): each
    leg's setpoint goes from where it is to the reference the controller
    follows, L(t) = r(t) + g (1 + cos(pi t / T)) / 2 with g = L(0) - r(0)
    the gap at the start, the gap's fastest leg peaking at ``speed``
    (pi |g| / (2 T)): a leg moves at most ``speed`` faster than the reference
    itself. Tracked by ``GravityPD``; ``SETTLE`` seconds on the reference
    after the profile, then over ``HANDOVER`` seconds the forces blend from
    the supervisor's to the controller's request; then the controller's go
    through alone.

    Args:
        start: (6,) the leg readings at the start [m]; start_ns: its stamp.
        reference: what the controller follows, or None (the setpoint stays
            at ``start``: only the hand-over).
        t0: the reference's time at the start [s]; speed: [m/s].
    """

    def __init__(self, start: np.ndarray, start_ns: int, reference: Reference | None,
                 t0: float, speed: float) -> None:
        self.reference, self.t0, self.start_ns = reference, t0, start_ns
        self._ref = None
        start = np.array(start, float)
        self.target = start if reference is None else self._sample(t0)[R_LEN].copy()
        self.gap = Descent(start - self.target, np.zeros(6), speed)
        self.done = False

    def _sample(self, t):
        self._ref = self.reference.sample(t, self._ref)
        return self._ref

    def setpoint(self, ns: int) -> tuple[np.ndarray, np.ndarray]:
        """(setpoint (6,) [m], its rate (6,) [m/s]) for sample ``ns``."""
        t = (ns - self.start_ns) * 1e-9
        gap, gap_rate = self.gap.at(t)
        if self.reference is None:
            return self.target, np.zeros(6)
        ref = self._sample(self.t0 + t)
        return ref[R_LEN] + gap, ref[R_RATE] + gap_rate

    def blend(self, ns: int) -> float:
        """The controller's share of the forces for sample ``ns``: 0 until the
        profile and the settling are over, then a cosine to 1 over HANDOVER."""
        tau = (ns - self.start_ns) * 1e-9 - self.gap.duration - SETTLE
        if tau <= 0:
            return 0.0
        if tau >= HANDOVER:
            self.done = True
            return 1.0
        return 0.5 * (1.0 - math.cos(math.pi * tau / HANDOVER))
