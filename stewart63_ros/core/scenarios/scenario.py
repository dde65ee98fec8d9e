"""Scenario files: runs with expectations and their verdicts (docs/scenarios.md).

A scenario file (YAML) holds ``scenarios:``, a list of runs, each with the
expectations its result must meet. This module reads and checks a file (every
key, with a "did you mean" for a typo), expands a ``matrix:`` into one
scenario per combination, runs a ``sim`` scenario in this process
(``run_sim``: the sampled loop of ``simulate.run_sampled`` at the plant's
``sensor_rate``, the loop the lockstep rig closes over DDS sample for
sample), and turns a run's samples (a ``Trace``) into verdicts
(``evaluate``). Running on the rig is the ``scenario`` tool's (it starts
``rig``); it builds a ``Trace`` from the recorded bag and the plant's summary.

Metrics (``METRICS``), each over the window [``from``, ``to``] of the run
(default: the whole run; the tracking errors from ``TRACKING_FROM``), the
error e_i(t) = |L_i(t) - L_ref,i(t)| of the true leg lengths against the
reference's (the setpoint (L_i)_0 without a reference):

- ``final_error_percent``: max_i e_i / L_ref,i x 100 at the window's last
  sample (without a window: ``sim``'s ``positioning_error_percent``);
- ``tracking_error_rms_m``: sqrt(mean over samples and legs of e_i^2);
- ``tracking_error_max_m``: max over samples and legs of e_i;
- ``settling_time_s``: the 2 % settling time of the legs in the window
  (``sweep.settling_time``; not settled: NaN, which fails any bound);
- ``overshoot_percent``: how far a leg went past its final length in the
  direction it moved, max_i max_t s_i (L_i(t) - L_i(T)) / travel x 100, with
  s_i the sign of L_i(T) - L_i(t0) and travel the largest |L_i(T) - L_i(t0)|;
- ``max_force``: the largest |F_i| the controller commanded [N];
- ``endstop_samples``: samples with a leg outside its stroke;
- ``withheld_samples``: samples with a complete reading the controller did
  not answer because its law raised (a fault detector's trip, README
  "Control laws"); on the rig: complete ``leg_lengths`` samples without a
  ``leg_forces`` answer;
- ``missed_cycles``: the plant's missed cycles plus its force timeouts (the
  whole run: no window); ``lost_messages``: samples that readers skipped plus
  ``leg_lengths`` samples missing from the bag (the whole run). Both only
  mean something on the rig: in ``sim`` nothing is sent, so they are 0 by
  construction.

Supervisor trips (``TRIP_METRICS``): a scenario with one runs with the
supervisor between controller and plant (``sim``: ``supervisor.run_supervised``,
the core the ``supervisor`` node runs; on the rig: ``rig --supervisor``), its
limits from ``params``:

- ``trip``: the first trip has ``cause`` and comes within ``within`` samples
  of ``after`` (a time [s], default the start of the scenario's earliest
  fault); the value is its sample minus ``after``'s (negative: it tripped
  before), with the cause and the sample beside it;
- ``no_trip``: the number of trips is 0.
"""
from __future__ import annotations

import dataclasses
import difflib
import functools
import itertools
import math
import os
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from stewart63_ros.core.machine.faults import FaultError, FaultModel, parse_faults
from stewart63_ros.core.plumbing.errors import ParameterError
from stewart63_ros.core.plumbing.node_parameters import BY_NAME
from stewart63_ros.core.plumbing.node_parameters import read as read_declared

#: Where a scenario runs.
RUN_MODES = ('sim', 'lockstep', 'realtime')
#: The keys of a scenario.
SCENARIO_KEYS = ('name', 'description', 'run', 'duration', 'params_file', 'params',
                 'control_law', 'reference', 'faults', 'wrench', 'expect', 'matrix', 'bus')
#: The field buses a rig scenario can run over (``rig --bus``).
BUSES = ('canopen',)
#: The keys of an expectation.
EXPECT_KEYS = ('max', 'min', 'from', 'to')
#: The keys of a wrench interval.
WRENCH_KEYS = ('from', 'to', 'force', 'torque')
#: metric -> (unit, whether it takes a window, what it is).
METRICS: dict[str, tuple[str, bool, str]] = {
    'final_error_percent': ('%', True, 'largest leg error at the window end, % of L_ref'),
    'tracking_error_rms_m': ('m', True, 'RMS leg-length error over the window'),
    'tracking_error_max_m': ('m', True, 'largest leg-length error over the window'),
    'settling_time_s': ('s', True, '2 % settling time of the legs'),
    'overshoot_percent': ('%', True, 'overshoot past the final leg length, % of travel'),
    'max_force': ('N', True, 'largest commanded |F_i|'),
    'endstop_samples': ('', True, 'samples with a leg outside its stroke'),
    'withheld_samples': ('', True, 'samples the controller did not answer (law raised)'),
    'missed_cycles': ('', False, 'missed cycles and force timeouts (rig; 0 in sim)'),
    'lost_messages': ('', False, 'skipped or unrecorded samples (rig; 0 in sim)'),
    'trip': ('samples', False, 'the supervisor trips with this cause within N samples of '
             'the fault\'s start or a time'),
    'no_trip': ('trips', False, 'the supervisor does not trip'),
}
#: The supervisor's expectations: a scenario with one runs with the supervisor.
TRIP_METRICS = ('trip', 'no_trip')
#: The keys of a ``trip`` expectation.
TRIP_KEYS = ('cause', 'within', 'after')
#: The tracking errors count from this time by default [s], as ``sim`` and the
#: rig's summary print them.
TRACKING_FROM = 1.0
#: Parameter keys the scenario sets through its own keys.
SCENARIO_OWNED = {'control_law': 'control_law', 'faults': 'faults',
                  'reference_file': 'reference', 'duration': 'duration',
                  'clock_mode': 'run', 'summary_file': None}


class ScenarioError(ValueError):
    """A scenario file that cannot run: the message names the file and the key."""


@dataclasses.dataclass(frozen=True)
class Expectation:
    """One bound on one metric: ``kind`` 'max' (value <= limit) or 'min'
    (value >= limit), over [t_from, t_to] [s] (None: the run's start or end)."""
    metric: str
    kind: str
    limit: float
    t_from: float | None = None
    t_to: float | None = None
    #: ``trip``: the cause expected, and what ``t_from`` is (``the fault X at T s``)
    cause: str | None = None
    after_what: str = ''


@dataclasses.dataclass(frozen=True)
class WrenchInterval:
    """An external wrench on the platform (platform frame, at its origin) over
    the samples with t_from <= t < t_to [s]: force (3,) [N], torque (3,) [N m]."""
    t_from: float
    t_to: float
    force: tuple[float, float, float]
    torque: tuple[float, float, float]


@dataclasses.dataclass(frozen=True)
class Scenario:
    """One run and its expectations, checked (``load_scenarios``)."""
    name: str
    run: str
    duration: float
    params_file: str
    params: Mapping[str, Any]
    control_law: str | None
    reference: str | None
    faults: tuple[str, ...]
    wrench: tuple[WrenchInterval, ...]
    expect: tuple[Expectation, ...]
    source: str = ''
    description: str = ''
    #: the field bus the rig runs over (``rig --bus``; docs/bus.md), '' for none
    bus: str = ''

    @property
    def supervised(self) -> bool:
        """It runs with the supervisor: it expects a trip or none."""
        return any(e.metric in TRIP_METRICS for e in self.expect)


@dataclasses.dataclass(frozen=True)
class TripRecord:
    """A supervisor's trip: its cause, the sample (index from 0) on which the
    limit was crossed, the samples until the first safe force, its words."""
    cause: str
    sample: int
    latency_samples: int | None
    detail: str = ''


@dataclasses.dataclass
class Trace:
    """The samples of a run that the metrics read.

    Attributes:
        times: (N,) sample times [s] from 0.
        lengths: (N, 6) true leg lengths [m].
        reference: (N, 6) the reference's leg lengths [m] at those times.
        forces: (N, 6) the controller's commands [N] (held where it did not answer).
        withheld: (N,) bool, a complete sample the controller did not answer.
        stroke: (leg_length_min, leg_length_max) [m].
        missed_cycles, lost_messages: whole-run counts (0 in sim).
        rate: the sample rate [Hz].
        trips: the supervisor's trips, in order (a run without it: none).
    """
    times: np.ndarray
    lengths: np.ndarray
    reference: np.ndarray
    forces: np.ndarray
    withheld: np.ndarray
    stroke: tuple[float, float]
    missed_cycles: int = 0
    lost_messages: int = 0
    rate: float = 1000.0
    trips: tuple[TripRecord, ...] = ()


@dataclasses.dataclass
class Verdict:
    """An expectation's outcome: the measured value beside the bound, and the
    time it failed (a windowed metric), or None."""
    expectation: Expectation
    value: float
    passed: bool
    at_s: float | None
    window: tuple[float, float]
    #: the trip expectations' measured trip: ``tracking_error at sample 3162 (t = 3.162 s)``
    measured: str = ''
    #: why a trip expectation failed, beside its value
    why: str = ''

    def bound_text(self) -> str:
        """The bound: ``<= 3000 N``, ``tracking_error within 200 samples of t = 3 s``."""
        exp = self.expectation
        if exp.metric == 'trip':
            return '%s within %d samples of %s' % (exp.cause, exp.limit, exp.after_what)
        if exp.metric == 'no_trip':
            return 'none expected'
        unit = METRICS[exp.metric][0]
        return '%s %s%s' % ('<=' if exp.kind == 'max' else '>=', _num(exp.limit),
                            ' ' + unit if unit else '')

    def measured_text(self) -> str:
        """The measured value: ``3120.5``, ``tracking_error at sample 3162 (t = 3.162 s),
        +162 samples``."""
        exp = self.expectation
        if exp.metric == 'trip':
            if not self.measured:
                return 'no trip'
            return '%s, %+d samples' % (self.measured, self.value)
        if exp.metric == 'no_trip':
            trips = '%d trip%s' % (self.value, '' if self.value == 1 else 's')
            return trips + (': ' + self.measured if self.measured else '')
        return _num(self.value)

    def text(self) -> str:
        """One line: ``max_force = 3120.5 N <= 3000 N: FAIL by 120.5 N at t = 0.012 s``."""
        exp = self.expectation
        if exp.metric in TRIP_METRICS:
            line = '%s = %s (%s)' % (exp.metric, self.measured_text(), self.bound_text())
            if self.passed:
                return line + ': pass'
            line += ': FAIL' + (' (%s)' % self.why if self.why else '')
            return line + (' at t = %.4f s' % self.at_s if self.at_s is not None else '')
        unit = METRICS[exp.metric][0]
        unit = ' ' + unit if unit else ''
        op = '<=' if exp.kind == 'max' else '>='
        line = '%s = %s%s (%s %s%s, window %g-%g s)' % (
            exp.metric, _num(self.value), unit, op, _num(exp.limit), unit, *self.window)
        if self.passed:
            return line + ': pass'
        if math.isnan(self.value):
            line += ': FAIL (no value: %s)' % (
                'not settled' if exp.metric == 'settling_time_s' else 'the run failed')
        else:
            line += ': FAIL by %s%s' % (_num(abs(self.value - exp.limit)), unit)
        if self.at_s is not None:
            line += ' at t = %.4f s' % self.at_s
        return line


def _num(value: float) -> str:
    return '%.6g' % value


# -- reading a file ------------------------------------------------------------
class _UniqueKeyLoader(yaml.SafeLoader):
    """YAML's safe loader, refusing a key given twice in one mapping (plain
    YAML keeps the last one silently)."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            if key in seen:
                raise ScenarioError('line %d: %s: given twice in one mapping (for two '
                                    'windows of a metric, give a list of bounds)'
                                    % (key_node.start_mark.line + 1, key))
            seen.add(key)
        return super().construct_mapping(node, deep)


def _hint(key: str, known: Iterable[str]) -> str:
    close = difflib.get_close_matches(str(key), list(known), n=1, cutoff=0.6)
    return ' (did you mean %s?)' % close[0] if close else ' (known: %s)' % ', '.join(known)


def _number(where: str, value: Any, positive: bool = False, nonnegative: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ScenarioError('%s: expected a number, got %r' % (where, value))
    value = float(value)
    if not math.isfinite(value):
        raise ScenarioError('%s: expected a finite number, got %r' % (where, value))
    if positive and value <= 0:
        raise ScenarioError('%s: must be > 0, got %g' % (where, value))
    if nonnegative and value < 0:
        raise ScenarioError('%s: must be >= 0, got %g' % (where, value))
    return value


def _vector3(where: str, value: Any) -> tuple[float, float, float]:
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise ScenarioError('%s: expected three numbers, got %r' % (where, value))
    x, y, z = (_number('%s[%d]' % (where, i), v) for i, v in enumerate(value))
    return x, y, z


def _mapping(where: str, value: Any) -> Mapping:
    if not isinstance(value, Mapping):
        raise ScenarioError('%s: expected a mapping (key: value), got %r' % (where, value))
    return value


def _unknown(where: str, doc: Mapping, known: Sequence[str]) -> None:
    for key in doc:
        if key not in known:
            raise ScenarioError('%s.%s: unknown key%s' % (where, key, _hint(key, known)))


def parse_expectations(where: str, doc: Any, duration: float,
                       faults: Sequence[str] = ()) -> tuple[Expectation, ...]:
    """The ``expect:`` mapping of a scenario, checked.

    Args:
        where: the scenario's place in its file, for messages.
        doc: {metric: {max|min: B, from: T0, to: T1}}, or {metric: [such
            a mapping, ...]} for several windows of one metric; ``trip:
            {cause: C, within: N, after: T}``; ``no_trip: true``.
        duration: the run's duration [s] (a window must lie inside it).
        faults: the scenario's fault strings (a trip counts from the earliest
            start by default).

    Returns:
        One ``Expectation`` per bound (a metric may have both max and min).

    Raises:
        ScenarioError: an unknown metric, key or trip cause, a bad number, a
            window outside the run, a window on a whole-run metric.
    """
    out = []
    for metric, spec in _mapping(where + '.expect', doc or {}).items():
        at = '%s.expect.%s' % (where, metric)
        if metric in TRIP_METRICS:
            out.append(_trip_expectation(metric, spec, at, duration, faults))
            continue
        if metric not in METRICS:
            raise ScenarioError('%s: unknown metric%s' % (at, _hint(metric, METRICS)))
        specs = spec if isinstance(spec, list) else [spec]
        for k, one in enumerate(specs):
            out.extend(_expectations(metric, one, '%s[%d]' % (at, k) if len(specs) > 1 else at,
                                     duration))
    return tuple(out)


def _trip_expectation(metric: str, spec: Any, at: str, duration: float,
                      faults: Sequence[str]) -> Expectation:
    if metric == 'no_trip':
        if spec is not True:
            raise ScenarioError('%s: expected true (no trip over the whole run), got %r'
                                % (at, spec))
        return Expectation('no_trip', 'max', 0.0)
    # lazy: core.machine.supervisor costs 1050 ms (numba); scenario --help, pytest
    from stewart63_ros.core.machine.supervisor import CAUSES
    spec = _mapping(at, spec)
    _unknown(at, spec, TRIP_KEYS)
    cause = spec.get('cause')
    if cause is None:
        raise ScenarioError('%s.cause: a trip expectation names its cause (%s)'
                            % (at, ', '.join(CAUSES)))
    if cause not in CAUSES:
        raise ScenarioError('%s.cause: unknown trip cause %r%s' % (at, cause, _hint(cause, CAUSES)))
    if 'within' not in spec:
        raise ScenarioError('%s.within: a trip expectation needs within: N (samples)' % at)
    within = _number(at + '.within', spec['within'], nonnegative=True)
    if within != int(within):
        raise ScenarioError('%s.within: a whole number of samples, got %g' % (at, within))
    after = spec.get('after', 'fault')
    if after == 'fault':
        started = sorted(parse_faults(list(faults)), key=lambda f: f.start)
        if not started:
            raise ScenarioError('%s.after: the scenario has no fault to count from: give '
                                'after: T (a time [s])' % at)
        t_after, what = started[0].start, 'the fault %s' % started[0].text
    else:
        t_after = _number(at + '.after', after, nonnegative=True)
        what = 't = %g s' % t_after
    if t_after >= duration:
        raise ScenarioError('%s.after: %g s is at or after the end of the run (%g s)'
                            % (at, t_after, duration))
    return Expectation('trip', 'max', within, t_after, None, str(cause), what)


def _expectations(metric: str, spec: Any, at: str, duration: float) -> list[Expectation]:
    out = []
    spec = _mapping(at, spec)
    _unknown(at, spec, EXPECT_KEYS)
    bounds = [k for k in ('max', 'min') if k in spec]
    if not bounds:
        raise ScenarioError('%s: needs a bound, max: B or min: B' % at)
    t_from = spec.get('from')
    t_to = spec.get('to')
    windowed = t_from is not None or t_to is not None
    if windowed and not METRICS[metric][1]:
        raise ScenarioError('%s: counts the whole run, a window (from/to) cannot apply'
                            % at)
    if t_from is not None:
        t_from = _number(at + '.from', t_from, nonnegative=True)
    if t_to is not None:
        t_to = _number(at + '.to', t_to, nonnegative=True)
    lo = t_from or 0.0
    hi = duration if t_to is None else t_to
    if not lo < hi or hi > duration + 1e-9:
        raise ScenarioError('%s: the window %g-%g s must lie inside the run (0-%g s) and '
                            'end after it starts' % (at, lo, hi, duration))
    for kind in bounds:
        limit = _number('%s.%s' % (at, kind), spec[kind])
        out.append(Expectation(metric, kind, limit, t_from, t_to))
    return out


def parse_wrench(where: str, doc: Any, duration: float) -> tuple[WrenchInterval, ...]:
    """The ``wrench:`` list of a scenario, checked.

    Args:
        where: the scenario's place, for messages.
        doc: [{from: T0, to: T1, force: [fx, fy, fz], torque: [mx, my, mz]}, ...]
            (platform frame, at its origin; ``to`` default: the end;
            ``force`` or ``torque`` default zero).
        duration: the run's duration [s].

    Returns:
        The intervals, in order.

    Raises:
        ScenarioError: a bad key, number or interval; intervals that overlap.
    """
    if doc is None:
        return ()
    if not isinstance(doc, list):
        raise ScenarioError('%s.wrench: expected a list of {from, to, force, torque}' % where)
    out = []
    for i, item in enumerate(doc):
        at = '%s.wrench[%d]' % (where, i)
        item = _mapping(at, item)
        _unknown(at, item, WRENCH_KEYS)
        t_from = _number(at + '.from', item.get('from', 0.0), nonnegative=True)
        t_to = _number(at + '.to', item.get('to', duration), nonnegative=True)
        if not t_from < t_to:
            raise ScenarioError('%s: from %g must be before to %g' % (at, t_from, t_to))
        if t_from >= duration:
            raise ScenarioError('%s: from %g s is at or after the end of the run (%g s): '
                                'it would never act' % (at, t_from, duration))
        if 'force' not in item and 'torque' not in item:
            raise ScenarioError('%s: needs force: [fx, fy, fz] or torque: [mx, my, mz]' % at)
        force = _vector3(at + '.force', item.get('force', [0, 0, 0]))
        torque = _vector3(at + '.torque', item.get('torque', [0, 0, 0]))
        out.append(WrenchInterval(t_from, t_to, force, torque))
    out.sort(key=lambda w: w.t_from)
    for a, b in zip(out, out[1:]):
        if b.t_from < a.t_to:
            raise ScenarioError('%s.wrench: intervals %g-%g s and %g-%g s overlap'
                                % (where, a.t_from, a.t_to, b.t_from, b.t_to))
    return tuple(out)


#: Supervisor keys ``sim`` runs with (``run_supervised``) besides its limits
#: (``supervisor.LIMIT_KEYS``); ``request_timeout`` (wall clock) and
#: ``trip_on_diagnostics`` act on the rig only.
SIM_HOMING_KEYS = ('homing', 'homing_direction', 'homing_speed', 'homing_force')


def _check_params(where: str, params: Mapping, law: str | None, run: str,
                  supervised: bool = False) -> dict:
    # lazy: core.plumbing.params costs 715 ms (numba); scenario --help, pytest
    from stewart63_ros.core.plumbing.params import known_keys
    known = sorted(known_keys({'control_law': law} if law else None))
    out = {}
    for key, value in params.items():
        at = '%s.params.%s' % (where, key)
        if key in SCENARIO_OWNED:
            own = SCENARIO_OWNED[key]
            raise ScenarioError('%s: set by the scenario%s' % (
                at, ' (use its %s: key)' % own if own else ' runner'))
        if key not in known:
            raise ScenarioError('%s: unknown parameter%s' % (at, _hint(key, known)))
        declared = BY_NAME.get(key)
        if declared is not None and declared.nodes == ('supervisor',):
            if not supervised:
                raise ScenarioError('%s: read by the supervisor, which runs only in a scenario '
                                    'that expects a trip or no_trip' % at)
            # lazy: core.machine.supervisor costs 1050 ms (numba); scenario --help, pytest
            from stewart63_ros.core.machine.supervisor import LIMIT_KEYS
            if run == 'sim' and key not in LIMIT_KEYS + SIM_HOMING_KEYS:
                raise ScenarioError('%s: the supervisor node\'s only, not sim\'s: it takes '
                                    'effect in run: lockstep or realtime' % at)
        elif run == 'sim' and declared is not None and 'sim' not in declared.nodes:
            raise ScenarioError('%s: read by the %s node only, not by sim: it takes effect '
                                'in run: lockstep or realtime' % (at, '/'.join(declared.nodes)))
        out[str(key)] = value
    return out


def _resolve(base: Path, path: str) -> str:
    p = Path(os.path.expanduser(str(path)))
    return str(p if p.is_absolute() else (base / p))


def parse_scenario(doc: Any, where: str, base: Path, source: str = '') -> Scenario:
    """One scenario (no ``matrix:`` left), checked; the parameter values too
    (the mechanism they give), the law, the reference and the faults.

    Args:
        doc: the scenario's mapping.
        where: its place in its file (``file: scenarios[2] (name)``), for messages.
        base: the folder relative paths (params_file, reference) start from.
        source: the file it came from.

    Returns:
        The ``Scenario``.

    Raises:
        ScenarioError: anything that would keep it from running as written.
    """
    doc = _mapping(where, doc)
    _unknown(where, doc, SCENARIO_KEYS)
    name = doc.get('name')
    if not isinstance(name, str) or not name.strip():
        raise ScenarioError('%s.name: every scenario needs a name' % where)
    run = doc.get('run', 'sim')
    if run not in RUN_MODES:
        raise ScenarioError('%s.run: %r is not one of %s%s' % (
            where, run, ', '.join(RUN_MODES), _hint(run, RUN_MODES) if isinstance(run, str)
            else ''))
    duration = _number(where + '.duration', doc.get('duration', 10.0), positive=True)
    law = doc.get('control_law')
    if law is not None and not isinstance(law, str):
        raise ScenarioError('%s.control_law: expected a name, got %r' % (where, law))
    supervised = isinstance(doc.get('expect'), Mapping) and any(
        k in TRIP_METRICS for k in doc['expect'])
    params = _check_params(where, _mapping(where + '.params', doc.get('params') or {}), law, run,
                           supervised)
    # lazy: core.plumbing.params costs 715 ms (numba); scenario --help, pytest
    from stewart63_ros.core.plumbing.params import default_params_path
    params_file = (_resolve(base, doc['params_file']) if doc.get('params_file')
                   else str(default_params_path()))
    reference = _resolve(base, doc['reference']) if doc.get('reference') else None
    faults = doc.get('faults') or []
    if isinstance(faults, str):
        faults = [faults]
    if not isinstance(faults, list) or not all(isinstance(f, str) for f in faults):
        raise ScenarioError('%s.faults: expected a list of fault strings' % where)
    try:
        parse_faults(faults)
    except FaultError as exc:
        raise ScenarioError('%s.faults: %s' % (where, exc)) from None
    bus = doc.get('bus') or ''
    if bus not in ('',) + BUSES:
        raise ScenarioError('%s.bus: %r is not one of %s%s' % (
            where, bus, ', '.join(BUSES), _hint(bus, BUSES) if isinstance(bus, str) else ''))
    if bus and run == 'sim':
        raise ScenarioError('%s.bus: a scenario runs over the bus on the rig: run: lockstep or '
                            'realtime, not sim' % where)
    on_bus = [f for f in faults if f.strip().startswith('bus_')]
    if on_bus and not bus:
        raise ScenarioError('%s.faults: %s acts on the field bus: it needs bus: canopen (and '
                            'run: lockstep or realtime)' % (where, on_bus[0]))
    wrench = parse_wrench(where, doc.get('wrench'), duration)
    if wrench and run != 'sim':
        raise ScenarioError('%s.wrench: a wrench schedule runs in sim only (the rig takes '
                            'external_wrench from its topic, not on a schedule)' % where)
    if 'expect' not in doc:
        raise ScenarioError('%s.expect: a scenario needs at least one expectation' % where)
    expect = parse_expectations(where, doc.get('expect'), duration, faults)
    if not expect:
        raise ScenarioError('%s.expect: a scenario needs at least one expectation' % where)
    if reference is not None and run != 'sim' and os.path.isdir(reference):
        # lazy: bagio costs 197 ms; only a reference from a bag needs it
        from stewart63_ros.bagio import BagError, reference_points_from_bag
        try:
            with_rates = reference_points_from_bag(reference)['rates'] is not None
        except BagError as exc:
            raise ScenarioError('%s.reference: %s' % (where, exc)) from None
        if with_rates:
            raise ScenarioError('%s.reference: a trajectory with velocities runs in sim only '
                                '(the rig takes its reference as a CSV of poses)' % where)
    description = doc.get('description') or ''
    scenario = Scenario(name.strip(), run, duration, params_file, params, law, reference,
                        tuple(faults), wrench, expect, source, str(description), bus)
    try:
        build_plant(scenario)
        build_controller(scenario)
        if scenario.supervised:
            build_supervisor(scenario)
    except ScenarioError as exc:
        raise ScenarioError('%s: %s' % (where, exc)) from None
    return scenario


def _matrix_label(value: Any) -> str:
    if isinstance(value, float):
        return '%g' % value
    if isinstance(value, (list, tuple)):
        return ','.join(_matrix_label(v) for v in value)
    return str(value)


def expand_matrix(doc: Mapping, where: str) -> list[tuple[str, dict]]:
    """A scenario with ``matrix:`` as one scenario per combination of its values.

    ``matrix: {KEY: [v1, v2, ...], ...}`` with KEY a scenario key
    (``control_law``, ``duration``, ``faults``, ...) or ``params.NAME``; each
    combination sets its keys and is named ``name[KEY=v,...]`` (the last part
    of a dotted key).

    Args:
        doc: the scenario's mapping.
        where: its place in its file.

    Returns:
        [(place, scenario mapping without ``matrix``)], first key slowest.

    Raises:
        ScenarioError: a bad key or an empty list of values.
    """
    matrix = doc.get('matrix')
    if matrix is None:
        return [(where, dict(doc))]
    matrix = _mapping(where + '.matrix', matrix)
    keys, values = [], []
    for key, vals in matrix.items():
        at = '%s.matrix.%s' % (where, key)
        head, _, tail = str(key).partition('.')
        if head not in SCENARIO_KEYS or head in ('name', 'matrix', 'expect') or (
                head == 'params') != bool(tail):
            choices = [k for k in SCENARIO_KEYS if k not in ('name', 'matrix', 'expect')]
            raise ScenarioError('%s: not a scenario key or params.NAME%s'
                                % (at, _hint(key, choices + ['params.NAME'])))
        if not isinstance(vals, list) or not vals:
            raise ScenarioError('%s: expected a non-empty list of values' % at)
        keys.append(str(key))
        values.append(vals)
    out = []
    for combo in itertools.product(*values):
        item = {k: v for k, v in doc.items() if k != 'matrix'}
        item['params'] = dict(item.get('params') or {})
        labels = []
        for key, value in zip(keys, combo):
            head, _, tail = key.partition('.')
            if tail:
                item['params'][tail] = value
            else:
                item[head] = value
            labels.append('%s=%s' % (tail or head, _matrix_label(value)))
        item['name'] = '%s[%s]' % (doc.get('name'), ','.join(labels))
        out.append(('%s (%s)' % (where, item['name']), item))
    return out


def load_scenarios(path: str | os.PathLike) -> list[Scenario]:
    """Every scenario of a file, checked, matrices expanded.

    Args:
        path: the YAML file (``scenarios:`` a list of scenarios).

    Returns:
        The scenarios in file order.

    Raises:
        ScenarioError: one line naming the file and the first bad key.
    """
    path = Path(path)
    try:
        doc = yaml.load(path.read_text(), Loader=_UniqueKeyLoader)  # noqa: S506 - a SafeLoader
    except ScenarioError as exc:
        raise ScenarioError('%s: %s' % (path, exc)) from None
    except OSError as exc:
        raise ScenarioError('%s: cannot read (%s)' % (path, exc.strerror)) from None
    except yaml.YAMLError as exc:
        raise ScenarioError('%s: not valid YAML: %s' % (
            path, str(exc).replace('\n', ' '))) from None
    if not isinstance(doc, Mapping) or 'scenarios' not in doc:
        keys = list(doc) if isinstance(doc, Mapping) else []
        hint = _hint(keys[0], ['scenarios']) if keys else ''
        raise ScenarioError('%s: expected a top-level "scenarios:" list%s' % (path, hint))
    _unknown(str(path), doc, ('scenarios',))
    items = doc['scenarios']
    if not isinstance(items, list) or not items:
        raise ScenarioError('%s.scenarios: expected a non-empty list of scenarios' % path)
    out: list[Scenario] = []
    for i, item in enumerate(items):
        where = '%s: scenarios[%d]' % (path, i)
        if isinstance(item, Mapping) and isinstance(item.get('name'), str) and (
                'matrix' not in item):
            where += ' (%s)' % item['name']
        item = _mapping(where, item)
        for place, single in expand_matrix(item, where):
            out.append(parse_scenario(single, place, path.parent, str(path)))
    names = [s.name for s in out]
    for name in names:
        if names.count(name) > 1:
            raise ScenarioError('%s: two scenarios named %r' % (path, name))
    return out


# -- building a run ------------------------------------------------------------
@functools.lru_cache(maxsize=32)
def _file_section(path: str, node: str, mtime_ns: int) -> Mapping[str, Any]:
    """A node's parameters of a file, read once per version of the file (YAML
    parsing would otherwise cost more than a 10 s run)."""
    # lazy: core.plumbing.params costs 715 ms (numba); scenario --help, pytest
    from stewart63_ros.core.plumbing.params import read_parameter_file
    return read_parameter_file(path, node)


def node_parameters(scenario: Scenario, node: str) -> dict:
    """The parameters a node of the scenario reads: its file's, then the overrides.

    Args:
        scenario: the scenario.
        node: 'plant' or 'controller'.

    Returns:
        {key: value}.

    Raises:
        ScenarioError: the parameter file cannot be read.
    """
    try:
        params = dict(_file_section(scenario.params_file, node,
                                    os.stat(scenario.params_file).st_mtime_ns))
    except OSError as exc:
        raise ScenarioError('params_file: cannot read %s (%s)'
                            % (scenario.params_file, exc.strerror)) from None
    except ParameterError as exc:
        raise ScenarioError('params_file: %s' % exc) from None
    params.update(scenario.params)
    if scenario.control_law is not None:
        params['control_law'] = scenario.control_law
    return params


def build_plant(scenario: Scenario) -> Any:
    """The plant's setup of the scenario (its machine, initial state, settings).

    Args:
        scenario: the scenario.

    Returns:
        The ``Setup``.

    Raises:
        ScenarioError: a parameter value the validation refuses (its key named).
    """
    # lazy: core.plumbing.params costs 715 ms (numba); scenario --help, pytest
    from stewart63_ros.core.plumbing.params import setup_from_params
    try:
        return setup_from_params(node_parameters(scenario, 'plant'))
    except ParameterError as exc:
        raise ScenarioError('params: %s' % exc) from None


def build_controller(scenario: Scenario) -> tuple[Any, Any]:
    """(controller, reference) of the scenario: a ``laws.Controller`` with its law
    and reference (None: the setpoint).

    Args:
        scenario: the scenario.

    Returns:
        (``Controller``, ``Reference`` or None).

    Raises:
        ScenarioError: the law cannot be built, the reference is refused.
    """
    # lazy: core.controllers.laws costs 926 ms (numba); scenario --help, pytest
    from stewart63_ros.core.controllers.laws import Controller
    from stewart63_ros.core.controllers.reference import ReferenceError, load_reference
    from stewart63_ros.core.plumbing.params import setup_from_params
    params = node_parameters(scenario, 'controller')
    try:
        setup = setup_from_params(params)
        reference = None
        if scenario.reference is not None:
            limits = (read_declared(params, 'max_leg_speed'),
                      read_declared(params, 'max_leg_acceleration'))
            if os.path.isdir(scenario.reference):
                # a topic file: read with the package's bag I/O (rosbags, no ROS)
                # lazy: bagio costs 197 ms; only a reference from a bag needs it
                from stewart63_ros.bagio import reference_from_bag
                reference = reference_from_bag(setup.mechanism, scenario.reference, *limits)
            else:
                reference = load_reference(setup.mechanism, scenario.reference, *limits)
        return Controller(setup, params, reference=reference), reference
    except ParameterError as exc:
        raise ScenarioError('params: %s' % exc) from None
    except ReferenceError as exc:
        raise ScenarioError('reference: %s' % exc) from None


def wrench_samples(wrench: Sequence[WrenchInterval], times: np.ndarray) -> np.ndarray | None:
    """The wrench held over each sample period (None: no wrench at all).

    Args:
        wrench: the schedule; times: (N,) the sample times [s].

    Returns:
        (N, 6) [N, N m] (platform frame), or None for an empty schedule.
    """
    if not wrench:
        return None
    out = np.zeros((len(times), 6))
    for w in wrench:
        inside = (times >= w.t_from - 1e-9) & (times < w.t_to - 1e-9)
        out[inside, :3] = w.force
        out[inside, 3:] = w.torque
    return out


class _Withholding:
    """A controller that, like the controller node, answers nothing when its
    law raises: the previous forces hold, and the sample is marked. It has
    the ``laws.Controller`` interface ``simulate`` drives (no fast path)."""

    def __init__(self, controller: Any, rate: float) -> None:
        self.controller = controller
        self.rate = rate
        self.held = np.zeros(6)
        self.withheld: list[int] = []

    def pd_gains(self) -> None:
        """No compiled fast path: every sample goes through ``forces``."""
        return None

    def forces(self, t: float, lengths: np.ndarray, rates: np.ndarray) -> np.ndarray:
        """The law's forces, or the previous ones when the law raises."""
        # lazy: core.controllers.laws costs 926 ms (numba); scenario --help, pytest
        from stewart63_ros.core.controllers.laws import LawError
        try:
            self.held = self.controller.forces(t, lengths, rates)
        except LawError:
            self.withheld.append(int(round(t * self.rate)))
        return self.held


def run_sim(scenario: Scenario) -> Trace:
    """Run a scenario in this process: ``run_sampled`` at the plant's
    ``sensor_rate`` (the lockstep rig's loop), faults as the plant injects them
    (seed ``sensor_seed``), the wrench schedule held per sample; a law that
    raises has its sample withheld (the previous forces hold), as the
    controller node does.

    Args:
        scenario: a scenario (any ``run``: this is how ``sim`` runs it).

    Returns:
        The run's ``Trace``.

    Raises:
        ScenarioError: the parameters, law or reference are refused.
        RuntimeError: the simulation diverged (non-finite state).
    """
    # lazy: the core's kernels cost 692 ms (numba); scenario --help, pytest
    from stewart63_ros.core.controllers.laws import PDLaw
    from stewart63_ros.core.controllers.simulate import run_sampled
    from stewart63_ros.core.mechanics.dynamics import Dynamics
    plant = build_plant(scenario)
    mech = plant.mechanism
    controller, reference = build_controller(scenario)
    rate = float(plant.setting('sensor_rate'))
    n = int(round(scenario.duration * rate))
    times = np.arange(n + 1) / rate
    wrenches = wrench_samples(scenario.wrench, times)
    faults = None
    plant_faults = list(plant.settings.get('faults') or []) + list(scenario.faults)
    if plant_faults:
        faults = FaultModel(parse_faults(plant_faults), rate, plant.setting('sensor_seed'))
    dyn = Dynamics(mech)
    if scenario.supervised:
        return _run_supervised(scenario, plant, dyn, controller, reference, rate, faults, wrenches)
    if reference is None and type(controller.law) is PDLaw and faults is None:
        # eq. (40) towards the setpoint: the compiled loop (controller.pd_gains())
        law: Any = controller
    else:
        law = _Withholding(controller, rate)
    result = run_sampled(plant, scenario.duration, rate, controller=law, dyn=dyn,
                         faults=faults, wrench=wrenches)
    if not np.all(np.isfinite(result.states)):
        raise RuntimeError('the simulation diverged (non-finite state)')
    # lazy: core.analysis.sweep costs 692 ms (numba, scipy.optimize)
    from stewart63_ros.core.analysis.sweep import leg_lengths_of_states
    lengths = leg_lengths_of_states(dyn.base_points, dyn.leg_points, result.states)
    withheld = np.zeros(len(times), bool)
    if isinstance(law, _Withholding):
        withheld[[k for k in law.withheld if k < len(times)]] = True
    return Trace(times, lengths, reference_lengths(scenario, reference, times),
                 result.forces, withheld, (mech.leg_length_min, mech.leg_length_max), rate=rate)


class _LawCalls:
    """The controller, noting the samples on which its law raised (the
    supervisor trips on them: ``run_supervised``)."""

    def __init__(self, controller: Any, rate: float) -> None:
        self.controller = controller
        self.rate = rate
        self.raised: list[int] = []

    def forces(self, t: float, lengths: np.ndarray, rates: np.ndarray) -> np.ndarray:
        """The law's forces; a LawError noted, then passed on."""
        # lazy: core.controllers.laws costs 926 ms (numba); scenario --help, pytest
        from stewart63_ros.core.controllers.laws import LawError
        try:
            return self.controller.forces(t, lengths, rates)
        except LawError:
            self.raised.append(int(round(t * self.rate)))
            raise


def build_supervisor(scenario: Scenario, reference: Any = None) -> Any:
    """The supervisor of a scenario that expects a trip (or none): the
    ``supervisor`` node's parameters (the file's, then the overrides), the
    reference the controller follows (None: its setpoint).

    Args:
        scenario: the scenario.
        reference: the controller's ``Reference`` (a CSV's or a topic file's), or None.

    Returns:
        A fresh ``core.machine.supervisor.Supervisor`` at the plant's ``sensor_rate``.

    Raises:
        ScenarioError: a limit out of range or contradicting another (its key named).
    """
    # lazy: core.plumbing.params costs 715 ms (numba); scenario --help, pytest
    from stewart63_ros.core.machine.supervisor import supervisor_from_params
    from stewart63_ros.core.plumbing.params import setup_from_params
    params = node_parameters(scenario, 'supervisor')
    params['reference_file'] = ''       # the scenario's reference is handed over below
    rate = float(read_declared(node_parameters(scenario, 'plant'), 'sensor_rate'))
    try:
        supervisor = supervisor_from_params(setup_from_params(params), params, rate)
    except ParameterError as exc:
        raise ScenarioError('params: %s' % exc) from None
    if reference is not None:
        supervisor.reference = reference
    return supervisor


def _run_supervised(scenario: Scenario, plant: Any, dyn: Any, controller: Any, reference: Any,
                    rate: float, faults: Any, wrenches: np.ndarray | None) -> Trace:
    """``run_sim`` with the supervisor between controller and plant:
    ``core.machine.supervisor.run_supervised``, the loop ``rig --supervisor`` runs."""
    # lazy: core.machine.supervisor costs 1050 ms (numba); scenario --help, pytest
    from stewart63_ros.core.machine.supervisor import run_supervised
    supervisor = build_supervisor(scenario, reference)
    law = _LawCalls(controller, rate)
    mech = plant.mechanism
    out = run_supervised(plant, supervisor, scenario.duration, rate, faults=faults,
                         controller=law, wrench=wrenches)
    if not np.all(np.isfinite(out['states'])):
        raise RuntimeError('the simulation diverged (non-finite state)')
    times = np.arange(len(out['lengths'])) / rate
    withheld = np.zeros(len(times), bool)
    withheld[[k for k in law.raised if k < len(times)]] = True

    def index(ns: int) -> int:
        return int(round(ns * 1e-9 * rate))
    trips = tuple(TripRecord(t.cause, index(t.sample_ns),
                             None if t.safe_ns is None else index(t.safe_ns) - index(t.sample_ns),
                             t.detail) for t in supervisor.trips)
    return Trace(times, out['lengths'], reference_lengths(scenario, reference, times),
                 out['forces'], withheld, (mech.leg_length_min, mech.leg_length_max),
                 rate=rate, trips=trips)


def build_controller_setup(scenario: Scenario) -> Any:
    """The controller's setup (its setpoint and gains) of the scenario.

    Args:
        scenario: the scenario.

    Returns:
        The ``Setup`` from the controller's parameters.

    Raises:
        ScenarioError: a parameter value the validation refuses.
    """
    # lazy: core.plumbing.params costs 715 ms (numba); scenario --help, pytest
    from stewart63_ros.core.plumbing.params import setup_from_params
    try:
        return setup_from_params(node_parameters(scenario, 'controller'))
    except ParameterError as exc:
        raise ScenarioError('params: %s' % exc) from None


def reference_lengths(scenario: Scenario, reference: Any, times: np.ndarray) -> np.ndarray:
    """The reference's leg lengths at ``times`` (the controller's setpoint
    without a reference).

    Args:
        scenario: the scenario; reference: its ``Reference`` or None.
        times: (N,) [s] from the run's first sample.

    Returns:
        (N, 6) [m].
    """
    if reference is None:
        setup = build_controller_setup(scenario)
        return np.tile(np.asarray(setup.task.setpoint_lengths, float), (len(times), 1))
    from stewart63_ros.core.controllers.reference import (
        R_LEN,  # lazy: core.controllers.reference costs 570 ms (numba)
    )
    return reference.sample_many(times)[:, R_LEN]


# -- verdicts -------------------------------------------------------------------
def _window(trace: Trace, exp: Expectation, default_from: float = 0.0) -> np.ndarray:
    t = trace.times
    lo = default_from if exp.t_from is None else exp.t_from
    hi = t[-1] if exp.t_to is None else exp.t_to
    return (t >= lo - 1e-9) & (t <= hi + 1e-9)


def _first_over(times: np.ndarray, series: np.ndarray, exp: Expectation) -> float | None:
    """The first time a per-sample series breaks a max bound (None for a min bound)."""
    if exp.kind != 'max':
        return None
    over = np.flatnonzero(~(series <= exp.limit))
    return float(times[over[0]]) if over.size else None


def _count_at(times: np.ndarray, flags: np.ndarray, exp: Expectation) -> float | None:
    """For a count with a max bound: the time of the sample that broke it."""
    if exp.kind != 'max':
        return None
    hits = np.flatnonzero(flags)
    k = int(math.floor(exp.limit))
    return float(times[hits[k]]) if 0 <= k < hits.size else None


def measure(trace: Trace, exp: Expectation) -> tuple[float, float | None, tuple[float, float]]:
    """An expectation's metric on a run.

    Args:
        trace: the run's samples.
        exp: the expectation (its metric and window).

    Returns:
        (value (NaN: none, e.g. not settled), the time the bound broke or
        None, the window (from, to) [s] actually used).
    """
    metric = exp.metric
    if metric in TRIP_METRICS:
        verdict = trip_verdict(trace, exp)
        return verdict.value, verdict.at_s, verdict.window
    default_from = TRACKING_FROM if metric.startswith('tracking_') else 0.0
    inside = _window(trace, exp, default_from)
    if not inside.any():
        inside[-1] = True
    t = trace.times[inside]
    window = (float(t[0]), float(t[-1]))
    lengths = trace.lengths[inside]
    error = np.abs(lengths - trace.reference[inside])
    per_sample = error.max(axis=1)
    if metric == 'final_error_percent':
        value = float(np.max(100.0 * error[-1] / trace.reference[inside][-1]))
        return value, (window[1] if not _passes(value, exp) else None), window
    if metric == 'tracking_error_rms_m':
        value = float(np.sqrt(np.mean(error ** 2)))
        return value, (window[1] if not _passes(value, exp) else None), window
    if metric == 'tracking_error_max_m':
        return float(per_sample.max()), _first_over(t, per_sample, exp), window
    if metric == 'settling_time_s':
        # lazy: core.analysis.sweep costs 692 ms (numba, scipy.optimize)
        from stewart63_ros.core.analysis.sweep import settling_time
        value = settling_time(t, lengths)
        return value, (None if _passes(value, exp) else
                       (window[1] if math.isnan(value) else value)), window
    if metric == 'overshoot_percent':
        moved = lengths[-1] - lengths[0]
        travel = float(np.max(np.abs(moved)))
        if travel == 0.0:
            return 0.0, None, window
        past = np.sign(moved) * (lengths - lengths[-1]) / travel * 100.0
        series = np.maximum(past.max(axis=1), 0.0)
        return float(series.max()), _first_over(t, series, exp), window
    if metric == 'max_force':
        series = np.abs(trace.forces[inside]).max(axis=1)
        return float(series.max()), _first_over(t, series, exp), window
    if metric == 'endstop_samples':
        lmin, lmax = trace.stroke
        flags = np.any((lengths < lmin) | (lengths > lmax), axis=1)
        return float(flags.sum()), _count_at(t, flags, exp), window
    if metric == 'withheld_samples':
        flags = trace.withheld[inside]
        return float(flags.sum()), _count_at(t, flags, exp), window
    if metric == 'missed_cycles':
        return float(trace.missed_cycles), None, window
    if metric == 'lost_messages':
        return float(trace.lost_messages), None, window
    raise ScenarioError('unknown metric %s' % metric)


def trip_verdict(trace: Trace, exp: Expectation) -> Verdict:
    """A ``trip`` or ``no_trip`` expectation's verdict: the run's first trip
    (its cause, sample, the samples until the safe force) beside the bound.

    Args:
        trace: the run's samples and trips.
        exp: a ``trip`` or ``no_trip`` expectation.

    Returns:
        The ``Verdict``: for ``trip``, the value is the trip's sample minus
        ``after``'s (NaN: no trip), failing on another cause, a trip before
        ``after`` or later than ``within``, or none, at the trip's time (none:
        the deadline); for ``no_trip``, the number of trips, failing at the first.
    """
    rate = trace.rate
    end = float(trace.times[-1])
    first = trace.trips[0] if trace.trips else None
    measured = ''
    if first is not None:
        measured = '%s at sample %d (t = %.4f s%s)' % (
            first.cause, first.sample, first.sample / rate,
            '' if first.latency_samples is None else
            '; safe force after %d samples' % first.latency_samples)
    if exp.metric == 'no_trip':
        count = len(trace.trips)
        return Verdict(exp, float(count), count == 0,
                       None if first is None else first.sample / rate, (0.0, end), measured)
    start = int(round((exp.t_from or 0.0) * rate))
    window = (start / rate, min((start + exp.limit) / rate, end))
    if first is None:
        return Verdict(exp, math.nan, False, window[1], window, '', 'no trip')
    value = float(first.sample - start)
    why = ''
    if first.cause != exp.cause:
        why = 'the cause is %s, not %s' % (first.cause, exp.cause)
    elif value < 0:
        why = 'it tripped %d samples before %s' % (-value, exp.after_what)
    elif value > exp.limit:
        why = 'late by %d samples' % (value - exp.limit)
    return Verdict(exp, value, not why, first.sample / rate if why else None, window,
                   measured, why)


def _passes(value: float, exp: Expectation) -> bool:
    if math.isnan(value):
        return False
    return value <= exp.limit if exp.kind == 'max' else value >= exp.limit


def evaluate(trace: Trace, expectations: Iterable[Expectation]) -> list[Verdict]:
    """Every expectation's verdict on a run.

    Args:
        trace: the run's samples.
        expectations: the scenario's expectations.

    Returns:
        One ``Verdict`` per expectation, in order.
    """
    out = []
    for exp in expectations:
        if exp.metric in TRIP_METRICS:
            out.append(trip_verdict(trace, exp))
            continue
        value, at, window = measure(trace, exp)
        passed = _passes(value, exp)
        out.append(Verdict(exp, value, passed, None if passed else at, window))
    return out


def failed_run_verdicts(expectations: Iterable[Expectation], duration: float) -> list[Verdict]:
    """Verdicts of a run that did not finish: every expectation fails, no value.

    Args:
        expectations: the scenario's expectations; duration: its length [s].

    Returns:
        One failing ``Verdict`` (value NaN) per expectation.
    """
    return [Verdict(exp, math.nan, False, None, (exp.t_from or 0.0, exp.t_to or duration))
            for exp in expectations]


def scenario_from_dict(doc: Mapping[str, Any], base: str | os.PathLike = '.') -> Scenario:
    """A scenario built in Python (as one entry of a file's ``scenarios:``).

    Args:
        doc: the scenario's keys, as in a file (``matrix`` not allowed here:
            use ``scenarios_from_dict``).
        base: the folder relative paths start from.

    Returns:
        The checked ``Scenario``.

    Raises:
        ScenarioError: as ``load_scenarios``.
    """
    if 'matrix' in doc:
        raise ScenarioError('matrix: expands to several scenarios, use scenarios_from_dict')
    return parse_scenario(doc, '<python>', Path(base), '<python>')


def scenarios_from_dict(doc: Mapping[str, Any], base: str | os.PathLike = '.') -> list[Scenario]:
    """Scenarios built in Python, a ``matrix:`` expanded.

    Args:
        doc: one scenario's keys, as in a file.
        base: the folder relative paths start from.

    Returns:
        The checked scenarios.

    Raises:
        ScenarioError: as ``load_scenarios``.
    """
    return [parse_scenario(single, place, Path(base), '<python>')
            for place, single in expand_matrix(_mapping('<python>', doc), '<python>')]


#: A function that runs a scenario on the rig and returns its ``Trace``
#: (the ``scenario`` tool provides it; the core knows no DDS).
RigRunner = Callable[[Scenario, str], Trace]
