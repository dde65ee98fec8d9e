"""Every parameter a node reads besides the model, declared once.

Why this long: it is the one table of every key (its declarations, each a
few lines of unit, range and doc); split, a reader would look in several places
for one key, which is what this module exists to prevent.

A declaration (``Declared``) holds what a user needs to know of a key: the
nodes that read it, its default, unit, range, whether it may change while the
node runs, one line of doc, and the check that turns a value as given into
the value used (or raises ``ParameterError`` with the reason). From these
declarations, and nowhere else, come:

- the keys each node reads (``NODE_KEYS``; with the model's keys, ``MODEL``,
  every key an executable knows: a key outside both is reported as unknown);
- the value a node, ``sim`` or the core uses: ``read(params, name)``,
  defaulted and checked;
- the table "Node-specific keys" of docs/interface.md: ``markdown_table()``
  (test/test_parameter_table.py keeps the page equal to it;
  ``python test/test_parameter_table.py --write`` rewrites it);
- what ``ros2 param describe`` shows of each key on each node
  (``describe``: description with unit, range, read-only; runtime/parameters.py
  makes the ParameterDescriptor of it) and the value's ROS type (``ros_value``).

The model's keys (geometry, masses, gains, initial state) are checked together
where they are held (core/mechanics/setup.py: the machine's in ``mechanism.validated``,
the gains and the task in ``setup``); their unit, words and range are declared
here too (``MODEL``, which writes the page's model table:
``model_markdown_table()``). Which part of a run's ``Setup`` holds a key
(mechanism, gains, task or settings) is the rule of core/mechanics/setup.py.

A node that reads a new parameter: declare it here (it is then known,
checked and documented), and read it with ``read`` (``RigNode.param``).
"""
from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from stewart63_ros.core.machine.faults import FaultError, parse_faults
from stewart63_ros.core.plumbing.errors import ParameterError
from stewart63_ros.core.plumbing.node_names import ALL_NODES

#: The nodes that read the file's keys (``node_names.ALL_NODES``); 'sim'
#: stands for the offline executables that read a node's keys (``sim``,
#: ``analyze``, ``sweep``).
NODES = ALL_NODES
#: A key every node reads.
ALL = NODES
#: The nodes that sample the plant for the rig: the plant, or the bridge to
#: the field bus when the plant stands on it as the legs' drives (docs/bus.md).
SAMPLERS = ('plant', 'canopen_bridge')


# -- checks: each takes (name, value as given) and returns the value used ----
def _number(name: str, value: Any) -> float:
    if isinstance(value, bool):
        raise ParameterError(name, 'expected a number, got %r' % (value,))
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ParameterError(name, 'expected a number, got %r' % (value,)) from None


def positive(name: str, value: Any) -> float:
    """A finite number > 0."""
    number = _number(name, value)
    if not number > 0 or number == math.inf:
        raise ParameterError(name, 'must be a positive finite number, got %r' % (value,))
    return number


def nonnegative(name: str, value: Any) -> float:
    """A finite number >= 0."""
    number = _number(name, value)
    if not (number >= 0 and math.isfinite(number)):
        raise ParameterError(name, 'must be a finite number >= 0, got %r' % (value,))
    return number


#: The inclusive range ``ros2 param describe`` shows for a check (``ros_range``):
#: rcl's ranges include both ends, so "> 0" is "from the smallest positive
#: double"; an open end is infinity (the check's own words say "finite").
positive.ros_range = (math.ulp(0.0), math.inf)
nonnegative.ros_range = (0.0, math.inf)


def nonnegative_or_infinite(name: str, value: Any) -> float:
    """A number >= 0, infinity allowed (an infinitely stiff end stop)."""
    number = _number(name, value)
    if not number >= 0:
        raise ParameterError(name, 'must be a number >= 0, got %r' % (value,))
    return number


nonnegative_or_infinite.ros_range = (0.0, math.inf)


def integer(low: int | None = None, high: int | None = None, what: str = '') -> Callable:
    """A check for an integer from ``low`` to ``high`` (None: unbounded).
    A float with an integral value (YAML's ``2.0``) counts as that integer."""
    def check(name: str, value: Any) -> int:
        ok = not isinstance(value, bool) and (
            isinstance(value, int) or (isinstance(value, float) and value.is_integer()))
        if ok:
            value = int(value)
        if not ok or (low is not None and value < low) or (high is not None and value > high):
            bounds = ('from %d to %d' % (low, high) if high is not None
                      else '>= %d' % low if low is not None else '')
            raise ParameterError(name, 'must be an integer%s %s, got %r'
                                 % (' ' + what if what else '', bounds, value))
        return value
    check.range_text = ('integer %d–%d' % (low, high) if high is not None
                        else 'integer ≥ %d' % low if low is not None else 'integer')
    if low is not None or high is not None:
        check.ros_range = (-2**63 if low is None else low, 2**63 - 1 if high is None else high)
    return check


def number_from(low: float, high: float, what: str) -> Callable:
    """A check for a number from ``low`` to ``high``."""
    def check(name: str, value: Any) -> float:
        number = _number(name, value)
        if not low <= number <= high:
            raise ParameterError(name, 'must be %s from %g to %g, got %r'
                                 % (what, low, high, value))
        return number
    check.ros_range = (float(low), float(high))
    return check


def one_of(*choices: str) -> Callable:
    """A check for one of the strings ``choices``."""
    def check(name: str, value: Any) -> str:
        if value not in choices:
            raise ParameterError(name, 'must be %s, got %r' % (
                ' or '.join(repr(c) for c in choices), value))
        return value
    check.range_text = ', '.join('`%s`' % c for c in choices)
    return check


def boolean(name: str, value: Any) -> bool:
    """true or false."""
    if not isinstance(value, bool):
        raise ParameterError(name, 'must be true or false, got %r' % (value,))
    return value


def text(name: str, value: Any) -> str:
    """A string (a path); None or empty: none."""
    if value is None:
        return ''
    if not isinstance(value, str):
        raise ParameterError(name, 'expected a string, got %r' % (value,))
    return value


def node_names(name: str, value: Any) -> list[str]:
    """A list of node names (resolved against the node's namespace by the node)."""
    if isinstance(value, str) or not isinstance(value, (list, tuple)) or not all(
            isinstance(v, str) and v.strip('/') for v in value):
        raise ParameterError(name, 'expected a list of node names, got %r' % (value,))
    return list(value)


def gain_vector(name: str, value: Any) -> np.ndarray:
    """Six finite non-negative gains, or ParameterError with the reason.

    Args:
        name: the parameter's name, for the error.
        value: the value as given (a sequence of six numbers).

    Returns:
        (6,) float array.
    """
    arr = six_lengths(name, value)
    if np.any(arr < 0):
        raise ParameterError(name, 'gains must be >= 0, got %s' % arr.tolist())
    return arr


def pose_box(name: str, value: Any) -> np.ndarray | None:
    """[] (no box) or six finite numbers: x, y, z minimum, then maximum [m]."""
    if value is None or (isinstance(value, (list, tuple)) and len(value) == 0):
        return None
    arr = six_lengths(name, value)
    if not np.all(arr[:3] < arr[3:]):
        raise ParameterError(name, 'each minimum (x, y, z) must be below its maximum, got %s'
                             % arr.tolist())
    return arr


def faults(name: str, value: Any) -> list:
    """A list of fault strings (core/machine/faults.py), parsed."""
    try:
        return parse_faults(value)
    except FaultError as exc:
        raise ParameterError(name, str(exc)) from None


def six_lengths(name: str, value: Any) -> np.ndarray:
    """Six finite numbers [m] (of either sign)."""
    try:
        arr = np.array(value, dtype=float).ravel()
    except (TypeError, ValueError):
        raise ParameterError(name, 'expected 6 numbers, got %r' % (value,)) from None
    if arr.size != 6:
        raise ParameterError(name, 'expected 6 numbers, got %d' % arr.size)
    if not np.all(np.isfinite(arr)):
        raise ParameterError(name, 'NaN or Inf in %s' % arr.tolist())
    return arr


def text_list(name: str, value: Any) -> list[str]:
    """A list of non-empty strings (an empty list: none)."""
    if isinstance(value, str) or not isinstance(value, (list, tuple)) or not all(
            isinstance(v, str) and v for v in value):
        raise ParameterError(name, 'expected a list of non-empty strings, got %r' % (value,))
    return list(value)


def law_name(name: str, value: Any) -> str:
    """A law's name (whether it exists is checked when the law is made)."""
    if not isinstance(value, str) or not value:
        raise ParameterError(name, 'expected a law name, got %r' % (value,))
    return value


# -- the declarations ---------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Declared:
    """One parameter: who reads it, its default, unit, range, and its check.

    Attributes:
        name: the key.
        nodes: the nodes that read it (``ALL`` for every node; 'sim' for the
            offline executables).
        default: the value when the key is missing, or a function of the
            other parameters that gives it.
        unit: the unit, '' for none.
        range: the range column's words; '' for the check's own.
        doc: one line for the interface page.
        check: (name, value) -> the value used, or ParameterError.
        runtime: the node lets it change while it runs (``ros2 param set``).
        default_text: the default column's words, when not ``default`` itself.
    """
    name: str
    nodes: tuple[str, ...]
    default: Any
    unit: str
    range: str
    doc: str
    check: Callable[[str, Any], Any]
    runtime: bool = False
    default_text: str = ''


def _watchdog_default(params: Mapping[str, Any]) -> float:
    # Lockstep pauses are the plant's choice, not a failure: longer default.
    return 2.0 if read(params, 'clock_mode') == 'lockstep' else 0.1


#: fk flags a pose whose 6x6 Jacobian (rows [s_i, q_i x s_i], in metres) has a
#: 2-norm condition number above this. Over 5000 random poses of the default
#: workspace it stays between 3 and 6; at a singular pose it is infinite. At
#: 100, a length error dL can move the estimate by ~100 dL: not to be trusted.
DEFAULT_COND_THRESHOLD = 1.0e4
#: computed_torque's default stiffness [1/s²] and damping [1/s] per task axis:
#: 50 rad/s (8 Hz), critically damped.
DEFAULT_CT_KP = 2500.0
DEFAULT_CT_KD = 100.0
#: The end stops' spring [N/m] and damper [N s/m] past the stroke.
DEFAULT_ENDSTOP_STIFFNESS = 2.0e6
DEFAULT_ENDSTOP_DAMPING = 5.0e3


_NAMES_RANGE = 'list of names, relative to the plant\'s namespace unless they start with `/`'

DECLARED: tuple[Declared, ...] = (
    Declared('sensor_rate', (*SAMPLERS, 'supervisor', 'sim'), 1000.0, 'Hz', '', 'sample rate of '
             '`leg_lengths`, and the physics step (also `sim --control sampled`)', positive),
    Declared('clock_mode', (*SAMPLERS, 'controller', 'fk', 'supervisor'), 'realtime', '', '',
             'see [Clock modes](#clock-modes-plant-parameter-clock_mode); the controller takes its '
             'watchdog default from it, fk its lockstep progress', one_of('realtime', 'lockstep')),
    Declared('duration', SAMPLERS, 0.0, 's (simulated)', '', 'end the run after this '
             'long; 0: run until stopped', nonnegative),
    Declared('force_timeout', SAMPLERS, 1.0, 's', '', 'lockstep: how long to wait for the '
             'force answering a sample before stepping on with the held one', positive),
    Declared('summary_file', ALL, '', 'path', '', 'write a JSON summary at the end of the '
             'run: the plant\'s ([Plant summary file](#plant-summary-file)), the '
             'controller\'s and fk\'s (below that table); `rig` sets it for each node in its '
             'log directory', text, default_text='"" (none)'),
    Declared('lengths_subscribers', SAMPLERS, 0, 'count', '', 'matched `leg_lengths` '
             'subscriptions to wait for before the first sample (`rig` sets controller + fk '
             '+ recorder)', integer(0)),
    Declared('lengths_peers', SAMPLERS, [], 'node names', _NAMES_RANGE, 'nodes whose '
             '`leg_lengths` subscription the ROS graph must show (and the plant have '
             'matched) before the first sample; `rig` sets its controller and fk. A count '
             'alone would be filled by a recorder started first while fk is still loading',
             node_names, default_text='[] (none)'),
    Declared('lockstep_peers', SAMPLERS, [], 'node names', _NAMES_RANGE, 'lockstep: the '
             'readers of `leg_lengths` the plant never runs more than `lockstep_window` '
             'samples ahead of ([flow control](#lockstep-flow-control-and-what-is-counted-'
             'as-lost)); `rig` sets its fk and its recorder', node_names,
             default_text='[] (none)'),
    Declared('lockstep_window', SAMPLERS, 200, 'samples', '', 'how far the plant may run '
             'ahead of its slowest lockstep peer (below the publishers\' 1000-sample '
             'history, so a sample a peer missed can still be re-sent)',
             integer(1, 900, 'number of samples')),
    Declared('lockstep_peer_timeout', SAMPLERS, 10.0, 's (wall clock)', '', 'a lockstep '
             'peer that has not advanced for this long while the plant waits for it is '
             'dropped (ERROR on `/diagnostics`); so is the source of the forces (the '
             'controller or a supervisor) after this long of samples without an answer: '
             'the plant then waits 0.05 s a sample, until an answer comes again', positive),
    Declared('sensor_noise', ('plant',), 0.0, 'm', '', 'Gaussian standard deviation '
             'added to L', nonnegative),
    Declared('sensor_rate_noise', ('plant',), 0.0, 'm/s', '', 'Gaussian standard '
             'deviation added to dL/dt', nonnegative),
    Declared('sensor_resolution', ('plant',), 0.0, 'm', '', 'quantisation step of L '
             '(0: none)', nonnegative),
    Declared('sensor_delay', ('plant',), 0, 'samples', '', 'transport delay of the '
             'sensor', integer(0)),
    Declared('sensor_seed', ('plant', 'sim'), 0, '', '', 'seed of the noise generator (and '
             'of the faults\' noise)', integer()),
    Declared('endstop_stiffness', ('plant', 'supervisor', 'sim'), DEFAULT_ENDSTOP_STIFFNESS,
             'N/m', '≥ 0 (inf: rigid)', 'end-stop spring past `leg_length_min` / `leg_length_max` '
             '([conventions](#frames-and-conventions))', nonnegative_or_infinite),
    Declared('endstop_damping', ('plant', 'sim'), DEFAULT_ENDSTOP_DAMPING, 'N s/m', '≥ 0',
             'end-stop damper', nonnegative_or_infinite),
    Declared('faults', ('plant', 'sim'), [], 'fault strings', '`kind:leg[:value][@from[-to]]` '
             '([faults.md](faults.md))', 'sensor and actuator faults injected on purpose',
             faults, runtime=True, default_text='[] (none)'),
    Declared('step_count', ('plant',), 1, 'samples', 'integer ≥ 1', 'lockstep: samples one '
             '`~/step` lets through before the plant pauses again ([faults.md](faults.md))',
             integer(1, 10**9, '(samples per ~/step)'), runtime=True),
    Declared('control_law', ('controller', 'sim'), 'pd', '', '`pd`, `pd_gravity`, '
             '`computed_torque`, `package.module:Class`', 'the control law ([Control '
             'laws](#control-laws))', law_name, runtime=True),
    Declared('ct_kp', ('controller', 'sim'), [DEFAULT_CT_KP] * 6, '1/s²', '6 numbers ≥ 0',
             '`computed_torque` stiffness per task axis x, y, z, rx, ry, rz', gain_vector,
             runtime=True, default_text='2500 ×6'),
    Declared('ct_kd', ('controller', 'sim'), [DEFAULT_CT_KD] * 6, '1/s', '6 numbers ≥ 0',
             '`computed_torque` damping per task axis', gain_vector, runtime=True,
             default_text='100 ×6'),
    Declared('max_leg_speed', ('controller', 'sim'), 0.0, 'm/s', '', 'refuse a reference '
             'motion that moves a leg faster (naming time and leg); 0: off', nonnegative),
    Declared('max_leg_acceleration', ('controller', 'sim'), 0.0, 'm/s²', '', 'refuse a '
             'reference motion that accelerates a leg more; 0: off', nonnegative),
    Declared('reference_file', ('controller', 'plant', 'supervisor'), '', 'path', 'a [Reference '
             'CSV](#reference-csv)', 'controller: follow it from the first sample (`rig '
             '--reference` sets it); plant: report the true tracking error in its summary',
             text, default_text='"" (none)'),
    Declared('watchdog_timeout', ('controller',), _watchdog_default, 's (wall clock)', '',
             'no valid sample for this long after the first one (in lockstep, a sample '
             'refused for a dropped-out leg counts: the plant goes on): forces withheld, '
             'ERROR on `/diagnostics`, until samples return; after the plant of its namespace said '
             'its run ended (`run: ended` on `/diagnostics`), an INFO line instead', positive,
             default_text='0.1 (2 in lockstep)'),
    Declared('singularity_threshold', ('fk',), DEFAULT_COND_THRESHOLD, '', '', 'Jacobian '
             'condition number above which a pose is not published (reported instead)',
             positive),
    Declared('marker_rate', ('fk',), 30.0, 'Hz', '0–200', 'rate of `markers` (a timer '
             'drawing the newest sample; only when a new sample came); 0: no markers',
             number_from(0, 200, 'a number of Hz (0: no markers)')),
    Declared('wait_for_subscribers', ALL, 0, 'count', '', 'before its first message, wait '
             'until every data publisher of the node has this many matched subscriptions '
             '(`rig --record` sets 1)', integer(0)),
    Declared('discovery_timeout', ALL, 20.0, 's', '', 'bound on those waits (and on the '
             'wait for every subscription the graph shows, see [Executables](#executables))',
             positive),
    Declared('discovery_settle', ALL, 0.0, 's', '0 ≤ value ≤ `discovery_timeout`', 'time '
             'from the node\'s start given to discovery to show a subscriber already running '
             'that the run does not name (a recorder started on its own), before the first '
             'message. 0: none; the node waits only for what the run names '
             '(`wait_for_subscribers`, the peers, a recorder\'s acknowledged match). A DDS '
             'participant re-announces itself every 3 s: 4 s outlasts one lost exchange',
             nonnegative),
    Declared('strict_parameters', ALL, False, '', '', 'true: an unknown key in what the '
             'node reads stops it (exit status 2) instead of a warning', boolean),
    Declared('realtime_priority', ALL, 0, '', '', 'not 0: the node\'s threads run '
             'SCHED_FIFO at this priority (needs root or `CAP_SYS_NICE`; refused: a warning '
             'and normal scheduling)', integer(0, 99, '(0: normal scheduling)')),
    Declared('use_sim_time', ALL, False, '', '', 'rclpy\'s own: the node\'s clock follows '
             '`/clock` (the plant publishes it in lockstep)', boolean),
    # Calibration (docs/calibration.md).
    Declared('leg_length_offset', ('plant', 'controller', 'fk', 'supervisor'), [0.0] * 6, 'm',
             '6 numbers', 'each length sensor\'s zero offset: reading = true length + '
             'offset. The plant adds it to the lengths it publishes; controller, fk and '
             'supervisor subtract it from every reading; `calibrate fit` identifies it '
             '([calibration.md](calibration.md))', six_lengths, default_text='0 ×6'),
    Declared('tracker_rate', ('plant',), 0.0, 'Hz', '0 or a divisor of `sensor_rate`',
             'a simulated tracker: publish the true pose with noise on `tracker/pose` at '
             'this rate; 0: no tracker ([calibration.md](calibration.md))', nonnegative),
    Declared('tracker_position_noise', ('plant',), 1.0e-4, 'm', '', 'the simulated '
             'tracker\'s Gaussian position noise per axis', nonnegative),
    Declared('tracker_orientation_noise', ('plant',), 1.0e-4, 'rad', '', 'the simulated '
             'tracker\'s Gaussian angle noise per axis (a rotation vector, base frame)',
             nonnegative),
    # -- the supervisor (core/machine/supervisor.py, docs/supervisor.md) --
    Declared('stroke_margin', ('supervisor',), 0.05, 'm', '≥ 0, < half the stroke', 'the '
             'soft stroke: this far inside `leg_length_min` and `leg_length_max`; a leg '
             'reading outside it trips (descent)', nonnegative, runtime=True),
    Declared('trip_leg_speed', ('supervisor',), 0.5, 'm/s', '≥ 0, > `descent_speed`', 'a '
             'leg rate reading faster trips (descent); 0: off', nonnegative, runtime=True),
    Declared('trip_force', ('supervisor',), 0.0, 'N', '', 'a requested force above this '
             'trips (hold); 0: the model\'s `max_force`', nonnegative, runtime=True),
    # Off by default: a PD law's request jumps by kp x the step at a setpoint
    # step, up to the whole force range (the packaged run's first request:
    # 234 N from zero, 0.23 MN/s at 1 kHz; its largest change after: 6.5 kN/s).
    Declared('trip_force_rate', ('supervisor',), 0.0, 'N/s', '≥ 0, < 2 `trip_force` × '
             '`sensor_rate`', 'a requested force changing faster from one sample to the next '
             'trips (hold); 0: off (the default: a PD law\'s request may jump by the whole '
             'force range at a setpoint step)', nonnegative, runtime=True),
    Declared('trip_tracking_error', ('supervisor',), 0.05, 'm', '', 'a leg farther than this '
             'from its reference (`reference_file`, else `setpoint_lengths`) for '
             '`trip_tracking_time` trips (descent); 0: off', nonnegative, runtime=True),
    Declared('trip_tracking_time', ('supervisor',), 1.0, 's (samples)', '', 'how long the '
             'tracking error must stay over `trip_tracking_error`', nonnegative, runtime=True),
    Declared('pose_box', ('supervisor',), [-0.3, -0.3, 0.5, 0.3, 0.3, 1.6], 'm', '[] or 6 '
             'numbers, min < max, the rest pose inside', 'x, y, z minimum then maximum of the '
             'platform\'s position (its forward kinematics from the readings); outside trips '
             '(descent); []: off',
             pose_box, runtime=True),
    Declared('trip_tilt', ('supervisor',), 0.35, 'rad', '', 'the platform\'s z axis tilted '
             'more than this from the base\'s trips (descent); 0: off', nonnegative,
             runtime=True),
    Declared('stale_lengths_ms', ('supervisor',), 20.0, 'ms (samples)', '> 0', 'no valid '
             '`leg_lengths` reading (NaN or missing) for longer trips (zero force)', positive,
             runtime=True),
    Declared('stale_forces_ms', ('supervisor',), 50.0, 'ms (samples)', '> 0', 'no request '
             'from the controller for longer trips (hold)', positive, runtime=True),
    Declared('request_timeout', ('supervisor',), 0.8, 's (wall clock)', '> 0, below the '
             'plant\'s `force_timeout`', 'lockstep: the longest the supervisor waits for the '
             'controller\'s request answering a sample before it answers without one (a '
             'first compute on a loaded machine has taken over 0.25 s; 0.2 s below the '
             'plant\'s 1 s leaves the hop to the plant its time)',
             positive),
    Declared('descent_speed', ('supervisor',), 0.05, 'm/s', '> 0, < `trip_leg_speed`', 'peak '
             'leg speed of the descent to the rest pose', positive, runtime=True),
    Declared('return_speed', ('supervisor',), 0.0, 'm/s', '≥ 0, < `trip_leg_speed`', 'peak '
             'leg speed of the return after a reset: the setpoint goes from where the legs are '
             'to the reference on a cosine profile, then the controller takes over; 0: 40 % '
             'of `trip_leg_speed` (0.2 m/s with the packaged 0.5 m/s; 0.2 m/s if that is off)',
             nonnegative, runtime=True),
    Declared('return_at_start', ('supervisor',), False, '', '', 'the run starts with the '
             'return a reset makes: from where the legs are to the reference at `return_speed`, '
             'then the controller\'s forces (a realtime rig whose first forces come late '
             'overshoots its first motion past `trip_leg_speed`)', boolean),
    Declared('trip_condition', ('supervisor',), 100.0, '', '≥ 0', 'the Jacobian condition '
             'number of the pose the readings give above which the platform is near a '
             'singularity, where it could cross into another assembly mode: trips (hold); '
             '0: off', nonnegative, runtime=True),
    Declared('rest_clearance', ('supervisor',), 0.05, 'm', '≥ 0', 'the rest pose (level, '
             'over the initial x, y) has its shortest leg this far above the soft lower '
             'limit', nonnegative, runtime=True),
    Declared('trip_on_diagnostics', ('supervisor',), True, '', '', 'an ERROR on '
             '`/diagnostics` from a node of the rig\'s namespace trips (descent)', boolean,
             runtime=True),
    Declared('force_stale_ms', SAMPLERS, 0.0, 'ms (samples)', '≥ 0', 'fail safe: a held '
             'force older than this (in sample time: the stamp it answers) is not applied, '
             'zero instead (the bridge: zero torque to the drives); 0: held for ever (`rig '
             '--supervisor` sets the supervisor\'s `stale_forces_ms`)', nonnegative),
    Declared('answer_every_sample', SAMPLERS, False, '', '', 'lockstep: wait for the answer '
             'to a sample with a missing reading too (the supervisor answers every sample; '
             '`rig --supervisor` sets it)', boolean),
    Declared('homing', ('supervisor',), False, '', '', 'home the legs\' incremental sensors '
             'against their end stops before the controller\'s forces go through '
             '([supervisor.md](supervisor.md#homing))', boolean),
    Declared('homing_direction', ('supervisor',), 'extend', '', '', 'the end stops homing '
             'drives the legs to: `extend` (upper) or `retract` (lower); refused at start-up '
             'when no pose has every leg at those stops', one_of('extend', 'retract')),
    Declared('homing_speed', ('supervisor',), 0.05, 'm/s', '> 0, < `trip_leg_speed`', 'leg '
             'speed of the homing, towards the stops and back', positive),
    Declared('homing_force', ('supervisor',), 200.0, 'N', '> 0', 'a leg that stalls while '
             'pushing this much more than its share of the load is at its stop', positive),
    Declared('homing_offset', ('plant',), [0.0] * 6, 'm', '6 numbers', 'the hidden zero of '
             'each leg\'s incremental sensor: added to its reading until a homing sets '
             '`homed_offset` (the simulated encoder has no absolute zero)', six_lengths,
             default_text='0 ×6'),
    Declared('homed_offset', SAMPLERS, [0.0] * 6, 'm', '6 numbers', 'the zero a homing '
             'found and set on the drives: subtracted from each reading (the supervisor '
             'sets it; the bridge writes it to each drive\'s home offset 0x607C by SDO)',
             six_lengths, runtime=True, default_text='0 ×6'),
    Declared('homed_offset_node', ('supervisor',), 'plant', '', '', 'the node whose '
             '`homed_offset` a homing sets: `plant` (its sensors) or `canopen_bridge` (the '
             'drives on the bus; `rig --bus canopen` sets it)',
             one_of('plant', 'canopen_bridge')),
    # -- the field bus (docs/bus.md) --
    Declared('io', ('plant',), 'dds', '', '', '`dds`: the plant publishes `leg_lengths` and '
             'takes `leg_forces` itself; `canopen`: it stands on the field bus as the six '
             'legs\' CiA 402 drives instead, and `canopen_bridge` links the bus to the topics '
             '([bus.md](bus.md))', one_of('dds', 'canopen')),
    Declared('bus_config', SAMPLERS, '', 'path', 'a [device config]'
             '(bus.md#the-device-config)', 'the legs\' drives on the bus: buses, node ids, EDS, '
             'scaling, actuator', text, default_text='"" (the packaged config/canopen.yaml)'),
    Declared('bus_interface', SAMPLERS, '', '', 'a python-can interface '
             '(`s63hub`, `socketcan`, ...)', 'the interface of every bus, instead of the '
             'config file\'s', text, default_text='"" (the config file\'s)'),
    Declared('bus_channels', SAMPLERS, [], 'channel names', 'one per bus '
             'of the config', 'the channel of each bus, instead of the config file\'s (`rig '
             '--bus canopen` gives its own, so two rigs on one machine never meet)', text_list,
             default_text='[] (the config file\'s)'),
    Declared('bus_bitrate', ('canopen_bridge',), 0, 'bit/s', '≥ 0', 'the bitrate of every '
             'bus, instead of the config file\'s; the bridge refuses a load over 100 %',
             integer(0, 10**7, 'a bitrate in bit/s (0: the config file\'s)'),
             default_text='0 (the config file\'s)'),
    Declared('bus_timeout', ('canopen_bridge',), 1.0, 's (wall clock)', '', 'lockstep: after '
             'a SYNC, how long to wait for a drive\'s TPDO before naming it missing (a drive '
             'already silent is waited for 2 ms after the others: a pulled cable costs this '
             'once)', positive),
    Declared('tpdo_missing_error_ms', ('canopen_bridge',), 20.0, 'ms (in SYNCs)', '0.1-10000',
             'realtime: a drive\'s TPDO missing this long in a row, counted in the SYNCs sent '
             '(20 ms: 4 at 200 Hz, 20 at 1 kHz; skipped ones do not count), is a bus fault '
             '(ERROR, torque withheld); shorter is a late message (WARN, counted), as the '
             'supervisor\'s `stale_lengths_ms` judges the missing readings. Lockstep: every '
             'miss (after `bus_timeout`) is a fault',
             number_from(0.1, 10000.0, 'a time in ms')),
    Declared('boot_timeout', ('canopen_bridge',), 30.0, 's', '', 'at start-up, how long to '
             'wait for every drive\'s boot-up; one still missing is named on '
             '`/diagnostics` and brought up when it boots', positive),
)

BY_NAME: dict[str, Declared] = {d.name: d for d in DECLARED}

#: The keys each node reads (besides the model's); 'sim' the offline tools'.
NODE_KEYS: dict[str, frozenset[str]] = {
    node: frozenset(d.name for d in DECLARED if node in d.nodes)
    for node in (*NODES, 'sim')}


# -- the model's keys ----------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class ModelKey:
    """One key of the model (a field of the ``Mechanism``, the ``Gains`` or the
    ``Task`` of core/mechanics/setup.py, checked there): what the interface page and
    ``ros2 param describe`` say of it. Every node reads every model key.

    Attributes:
        name: the key (the field's name).
        size: 1 for a number, n for a list of n numbers.
        other_size: another list length the key takes (``platform_points``:
            9 for a 6-3, 18 for a 6-6); 0 for none.
        unit: the unit of each number.
        packaged: the packaged file's value, in words.
        doc: meaning and checks, one line.
        bound: 'positive' (> 0) or 'nonnegative' (≥ 0) for a number with
            that range; '' for none.
        runtime: the nodes that let it change at run time.
    """
    name: str
    size: int
    unit: str
    packaged: str
    doc: str
    bound: str = ''
    runtime: tuple[str, ...] = ()
    other_size: int = 0

    @property
    def sizes_text(self) -> str:
        """'9 or 18' for a key of two lengths, '6' for one."""
        return '%d or %d' % (self.size, self.other_size) if self.other_size else str(self.size)


MODEL: tuple[ModelKey, ...] = (
    ModelKey('base_points', 18, 'm', 'see the file', 'b_1 … b_6, base frame; no two '
             'coincide; not all on one line'),
    ModelKey('platform_points', 9, 'm', '0.5 m circle at 0°, 120°, 240°', '9 numbers, a 6-3: '
             'p_1 … p_3, legs 2k−1 and 2k meet at p_k; or 18, a 6-6: p_1 … p_6, leg i at p_i; '
             'platform frame; no two coincide, not all on one line', other_size=18),
    ModelKey('platform_mass', 1, 'kg', '15.0', 'the platform\'s mass; > 0', 'positive'),
    ModelKey('platform_com', 3, 'm', '[0, 0, 0]', 'platform frame'),
    ModelKey('platform_inertia', 6, 'kg m²', '[0.95, 0.95, 1.875, 0, 0, 0]', 'Ixx, Iyy, Izz, '
             'Ixy, Ixz, Iyz: the matrix elements about the centre of mass, platform frame '
             '(Ixy = −Σ m·x·y, as `geometry_msgs/Inertia` and MuJoCo\'s `fullinertia`); '
             'positive definite, principal moments obey the triangle inequality'),
    ModelKey('leg_lower_mass', 1, 'kg', '2.0', 'm_d, the cylinder; > 0', 'positive'),
    ModelKey('leg_upper_mass', 1, 'kg', '1.0', 'm_u, the piston; > 0', 'positive'),
    ModelKey('leg_lower_com', 1, 'm', '0.35', 'cylinder\'s centre of mass from b_i along the '
             'leg; 0 ≤ value ≤ `leg_length_max`', 'nonnegative'),
    ModelKey('leg_upper_com', 1, 'm', '0.35', 'piston\'s centre of mass from the platform '
             'vertex towards the base; 0 ≤ value ≤ `leg_length_max`', 'nonnegative'),
    ModelKey('leg_lower_inertia', 2, 'kg m²', '[0.0016, 0.11]', 'axial, transverse moment '
             'about the cylinder\'s own centre of mass; axial ≥ 0, transverse > 0, axial ≤ '
             '2·transverse'),
    ModelKey('leg_upper_inertia', 2, 'kg m²', '[0.0003, 0.04]', 'the same for the piston'),
    ModelKey('piston_damping', 1, 'N s/m', '50.0', 'C_p, viscous, between cylinder and '
             'piston; ≥ 0', 'nonnegative'),
    ModelKey('ujoint_damping', 1, 'N m s/rad', '0.5', 'C_u, viscous, at the universal joint, '
             'on the leg\'s angular velocity; ≥ 0', 'nonnegative'),
    ModelKey('gravity', 3, 'm/s²', '[0, 0, −9.81] (also when missing)', 'base frame'),
    ModelKey('leg_length_min', 1, 'm', '1.2', 'stroke: > 0', 'positive'),
    ModelKey('leg_length_max', 1, 'm', '2.3', 'stroke: > `leg_length_min`', 'positive'),
    ModelKey('max_force', 1, 'N', '3000.0', 'piston force saturation; > 0', 'positive'),
    ModelKey('kp', 6, 'N/m', '4000 each', 'PD gains per leg, eq. (40); ≥ 0; the '
             'controller\'s can be changed at run time (`ros2 param set /controller kp ...`)',
             runtime=('controller',)),
    ModelKey('kv', 6, 'N s/m', '300 each', '≥ 0; changeable at run time, as `kp`',
             runtime=('controller',)),
    ModelKey('setpoint_lengths', 6, 'm', '[1.9, 1.9, 1.6, 1.6, 1.6, 1.6]', '(L_i)_0; > 0'),
    ModelKey('initial_position', 3, 'm', '[0.01, 0.01, 1.0]', 't_0, base frame; every leg '
             'within the stroke; not a singular pose (Jacobian condition number ≤ 10⁴)'),
    ModelKey('initial_velocity', 3, 'm/s', '[0.01, 0.01, 0.01]', 'dt_0/dt'),
    ModelKey('initial_orientation', 3, 'rad', '[0.01, 0.01, 0.01]', 'θ_0 (see '
             '[conventions](#frames-and-conventions))'),
    ModelKey('initial_orientation_rate', 3, 'rad/s', '[0.001, 0.001, 0.001]', 'dθ_0/dt'),
)

MODEL_BY_NAME: dict[str, ModelKey] = {m.name: m for m in MODEL}


# -- what `ros2 param describe` shows -------------------------------------------
@dataclasses.dataclass(frozen=True)
class Description:
    """One key as a node declares it to ROS (runtime/parameters.py makes the
    rcl_interfaces ``ParameterDescriptor`` of it; this module knows no ROS).

    Attributes:
        name: the key.
        type: 'double', 'integer', 'bool', 'string', 'double_array' or 'string_array'.
        description: meaning and unit, plain text.
        constraints: the range and checks in words (``additional_constraints``).
        read_only: fixed at start-up on this node: ``ros2 param set`` is refused.
        dynamic_typing: True for the number lists changeable at run time, so
            that ``[4000, 4000, ...]`` (integers, as YAML reads them) is
            taken as today; their check turns them into floats.
        range: inclusive (from, to) of a number, or None. Never on a list:
            rcl checks ranges of single numbers only, so a list's range is
            in ``constraints``, and its check refuses what is out of it.
    """
    name: str
    type: str
    description: str
    constraints: str
    read_only: bool
    dynamic_typing: bool
    range: tuple | None


_LINK = re.compile(r'\[([^\]]+)\]\([^)]*\)')


def _plain(text: str) -> str:
    """Markdown to plain text: links to their words, no backticks."""
    return _LINK.sub(r'\1', text).replace('`', '')


def _declared_type(d: Declared) -> str:
    value = default(d.name)
    if isinstance(value, bool):
        return 'bool'
    if isinstance(value, int):
        return 'integer'
    if isinstance(value, float):
        return 'double'
    if isinstance(value, str):
        return 'string'
    return 'double_array' if value and isinstance(value[0], float) else 'string_array'


def node_keys(node: str) -> list[str]:
    """Every key ``node`` reads and declares: the model's, then its own.

    Args:
        node: 'plant', 'controller' or 'fk'.

    Returns:
        The keys in the interface page's order (``use_sim_time`` too: rclpy declares it).
    """
    return [m.name for m in MODEL] + [d.name for d in DECLARED if node in d.nodes or
                                      d.nodes == ALL]


def describe(name: str, node: str) -> Description:
    """What ``ros2 param describe`` shows of key ``name`` on ``node``.

    Args:
        name: a model key or a declared one.
        node: 'plant', 'controller' or 'fk'.

    Returns:
        The Description, from the key's one declaration.

    Raises:
        KeyError: ``name`` is neither.
    """
    model = MODEL_BY_NAME.get(name)
    if model is not None:
        array = model.size > 1
        bound = {'positive': positive, 'nonnegative': nonnegative}.get(model.bound)
        return Description(
            name, 'double_array' if array else 'double',
            '%s [%s]' % (_plain(model.doc), model.unit),
            '%s numbers' % model.sizes_text if array else {'positive': '> 0', 'nonnegative': '≥ 0'}
            .get(model.bound, ''), node not in model.runtime, array and node in model.runtime,
            getattr(bound, 'ros_range', None))
    d = BY_NAME[name]
    kind = _declared_type(d)
    unit = ' [%s]' % d.unit if d.unit else ''
    return Description(name, kind, _plain(d.doc) + unit, _plain(_range_text(d)),
                       not d.runtime, kind == 'double_array' and d.runtime,
                       getattr(d.check, 'ros_range', None) if kind in ('double', 'integer')
                       else None)


def ros_value(name: str, value: Any, node: str) -> Any:
    """A value of key ``name`` that passed its check, as ROS holds it: of
    the type ``describe`` gives (``1000`` as ``1000.0`` for a double, a
    single fault string as a list of one).

    Args:
        name: a model key or a declared one.
        value: the value as given (or the default).
        node: the node that declares it.

    Returns:
        The value in its ROS type (unchanged where no conversion applies).
    """
    kind = describe(name, node).type
    if kind == 'double' and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if kind == 'integer' and isinstance(value, float) and value.is_integer():
        return int(value)
    if kind == 'double_array' and isinstance(value, (list, tuple)):
        return [float(v) if isinstance(v, int) and not isinstance(v, bool) else v
                for v in value]
    if kind == 'string_array' and isinstance(value, str):
        return [value]
    if kind == 'string' and value is None:
        return ''
    return value


def default(name: str, params: Mapping[str, Any] | None = None) -> Any:
    """The default of ``name`` (given the other ``params``, for a default
    that depends on them)."""
    value = BY_NAME[name].default
    return value(params or {}) if callable(value) else value


def read(params: Mapping[str, Any], name: str) -> Any:
    """The value of the declared key ``name`` a node uses: the given one, or
    its default, checked.

    Args:
        params: the node's parameters ({key: value}).
        name: a declared key.

    Returns:
        The checked value (e.g. a float for a ``positive`` key).

    Raises:
        ParameterError: the value does not pass the key's check.
        KeyError: ``name`` is not declared (a programming error).
    """
    value = params.get(name)
    if value is None:                   # missing, or YAML's ~
        value = default(name, params)
    return BY_NAME[name].check(name, value)


# -- the interface page's table -----------------------------------------------
def _code(value: Any) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, str):
        return '`%s`' % value
    if isinstance(value, float):
        return ('%g' % value).replace('e+0', 'e').replace('e+', 'e')
    return str(value)


def _range_text(declared: Declared) -> str:
    if declared.range:
        return declared.range
    check = declared.check
    return getattr(check, 'range_text', None) or {
        positive: '> 0', nonnegative: '≥ 0', boolean: 'true, false', text: ''}.get(check, '')


def markdown_table(packaged: Mapping[str, Any] | None = None) -> str:
    """docs/interface.md's table "Node-specific keys", from the declarations.

    Args:
        packaged: the packaged file's keys (all sections): a default the file
            overrides says so.

    Returns:
        The markdown table, one row per key, ending in a newline.
    """
    rows = ['| key | read by | unit | default | range | changeable at run time | meaning |',
            '|---|---|---|---|---|---|---|']
    for d in DECLARED:
        nodes = 'all' if d.nodes == ALL else ', '.join(
            '`sim`' if n == 'sim' else n for n in d.nodes)
        shown = d.default_text or _code(d.default)
        if packaged and d.name in packaged and not callable(d.default) \
                and packaged[d.name] != d.default:
            shown += ' (the packaged file sets %s)' % _code(packaged[d.name])
        rows.append('| `%s` | %s | %s | %s | %s | %s | %s |' % (
            d.name, nodes, d.unit, shown, _range_text(d), 'yes' if d.runtime else '', d.doc))
    return '\n'.join(rows) + '\n'



def model_markdown_table() -> str:
    """docs/interface.md's table "The model (shared keys)", from ``MODEL``.

    Returns:
        The markdown table, one row per model key, ending in a newline.
    """
    rows = ['| key | type, unit | packaged value | range and checks |', '|---|---|---|---|']
    for m in MODEL:
        kind = 'double' if m.size == 1 else 'double[%s]' % m.sizes_text
        rows.append('| `%s` | %s [%s] | %s | %s |' % (m.name, kind, m.unit, m.packaged, m.doc))
    return '\n'.join(rows) + '\n'
