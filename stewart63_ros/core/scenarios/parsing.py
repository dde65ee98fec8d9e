"""Scenario files read and checked: every key, with a "did you mean" for a
typo, a ``matrix:`` expanded into one scenario per combination
(docs/scenarios.md). What a scenario is: ``scenario``.
"""
from __future__ import annotations

import difflib
import itertools
import math
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from stewart63_ros.core.machine.faults import FaultError, parse_faults
from stewart63_ros.core.plumbing.node_parameters import BY_NAME
from stewart63_ros.core.scenarios.running import build_controller, build_plant, build_supervisor
from stewart63_ros.core.scenarios.scenario import (
    BUSES,
    EXPECT_KEYS,
    METRICS,
    RUN_MODES,
    SCENARIO_KEYS,
    SCENARIO_OWNED,
    TRIP_KEYS,
    TRIP_METRICS,
    WRENCH_KEYS,
    Expectation,
    Scenario,
    ScenarioError,
    WrenchInterval,
)


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
        from stewart63_ros.bagio import BagError
        from stewart63_ros.bagruns import reference_points_from_bag
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
