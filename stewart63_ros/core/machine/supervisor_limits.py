"""The supervisor's limits: the trip causes and their safe actions, the limits
checked against each other and the mechanism, and the rest pose (no ROS).

core/machine/supervisor.py is the supervisor; docs/supervisor.md the user's page.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from stewart63_ros.core.mechanics.kinematics import leg_lengths
from stewart63_ros.core.mechanics.rotation import rotation_from_euler
from stewart63_ros.core.plumbing.errors import ParameterError
from stewart63_ros.core.plumbing.node_parameters import read as read_declared

if TYPE_CHECKING:
    from stewart63_ros.core.mechanics.mechanism import Mechanism
    from stewart63_ros.core.mechanics.setup import Setup

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
    'singularity': (HOLD, 'the pose of the readings near a singularity (its Jacobian\'s '
                          'condition number above trip_condition), before the platform '
                          'crosses into another assembly mode'),
    'diagnostics_error': (DESCEND, 'an ERROR on /diagnostics from a node of the rig'),
    'user_request': (DESCEND, 'a trip asked for on the supervisor\'s trip_request topic'),
    'estop': (DESCEND, '~/estop'),
    'homing': (ZERO, 'the offsets the homing found could not be set on the drives'),
}

#: ``return_speed`` 0: this share of ``trip_leg_speed``, or this speed [m/s]
#: when that check is off (docs/supervisor.md, the return)
RETURN_SHARE, RETURN_SPEED = 0.4, 0.2

#: The supervisor's keys of core/plumbing/node_parameters.py that ``Limits`` reads.
LIMIT_KEYS = ('stroke_margin', 'trip_leg_speed', 'trip_force', 'trip_force_rate',
              'trip_tracking_error', 'trip_tracking_time', 'pose_box', 'trip_tilt',
              'stale_lengths_ms', 'stale_forces_ms', 'descent_speed', 'rest_clearance',
              'return_speed', 'trip_condition')


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
        return_speed [m/s]: the peak leg speed of the return after a reset.
        condition: the Jacobian condition number that trips (0: off).
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
    return_speed: float
    condition: float


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
    if not value['return_speed']:       # (the key's default: a margin under the limit)
        value['return_speed'] = RETURN_SHARE * value['trip_leg_speed'] or RETURN_SPEED
    if value['trip_leg_speed'] and value['return_speed'] >= value['trip_leg_speed']:
        raise ParameterError('return_speed', '%g m/s is not below trip_leg_speed (%g m/s): '
                             'the return after a reset would trip on its own speed'
                             % (value['return_speed'], value['trip_leg_speed']))
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
                  rest_clearance=value['rest_clearance'],
                  return_speed=value['return_speed'], condition=value['trip_condition'])


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


