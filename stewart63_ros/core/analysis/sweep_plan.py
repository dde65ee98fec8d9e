"""A sweep's plan: which keys vary and how (``--vary``, ``--fault``), checked
against what a run reads, and the values drawn per run (uniform or a grid).

A varied key is a scalar (``platform_mass``) or one element of a list as
written in the parameter file (``kp[2]``, ``base_points[4]``), drawn
uniformly from [LO, HI] or on a grid; a ``--fault`` pattern draws its leg,
value and times (``U(lo,hi)``, ``{a..b}``, ``{a,b,...}``). ``make_plan``
checks every varied key (known, read by the run, numeric) and builds the
first run once, so that a sweep that cannot run fails before the first
worker starts. The runs are ``sweep``'s; the columns and the summary
``sweep_report``'s.
"""
from __future__ import annotations

import dataclasses
import math
import os
import re
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from stewart63_ros.core.controllers.laws import Controller, holding_gain_problem, law_class
from stewart63_ros.core.machine.faults import FaultError, parse_faults
from stewart63_ros.core.mechanics.mechanism import MECHANISM_KEYS
from stewart63_ros.core.mechanics.setup import GAIN_KEYS, TASK_KEYS
from stewart63_ros.core.plumbing.node_parameters import read as read_declared
from stewart63_ros.core.plumbing.params import (
    ParameterError,
    known_keys,
    read_parameter_file,
    setup_from_params,
)

#: Output sample rate of a run [Hz] (``sim``'s default for continuous control).
OUTPUT_RATE = 100.0

_VARY = re.compile(r'^\s*([A-Za-z_][A-Za-z0-9_]*)(?:\[(\d+)\])?\s*=\s*([^:]+):([^:]+)$')
#: The prefix of a varied key's column in runs.csv (``param.max_force``).
PARAM_PREFIX = 'param.'
#: A drawn part of a ``--fault``: U(lo,hi), {a..b} or {a,b,...}.
_DRAWN = re.compile(r'U\(([^(),]*),([^(),]*)\)|\{(-?\d+)\.\.(-?\d+)\}|\{([^{}]*)\}')
#: Keys a run reads only under sampled control / with faults (``readable_keys``).
SAMPLED_KEYS = ('sensor_rate',)
FAULT_KEYS = ('sensor_seed',)


class SweepError(ValueError):
    """A sweep that cannot run; the message names the problem."""


@dataclasses.dataclass(frozen=True)
class Variation:
    """One varied parameter: ``name`` or element ``index`` of it, over [low, high].
    Its column in runs.csv is ``param.<key>`` (``column``): never a metric's name."""
    key: str
    name: str
    index: int | None
    low: float
    high: float

    @property
    def column(self) -> str:
        """The run table's column: ``param.`` and the key (``param.kp[2]``)."""
        return PARAM_PREFIX + self.key


@dataclasses.dataclass(frozen=True)
class FaultAxis:
    """One drawn part of a ``--fault`` pattern: ``U(low,high)`` (uniform; ``choices``
    empty) or ``{a..b}`` / ``{a,b,c}`` (one of ``choices``, each drawn as likely).

    Attributes:
        column: its column in runs.csv, ``fault<n>.<field>`` (field: kind, leg,
            value, start_s or end_s: where it stands in KIND:LEG[:VALUE][@T0[-T1]]).
        low, high: the range (of the choices' values for a choice).
        choices: ((text, value), ...) for a choice; () for a uniform draw.
    """
    column: str
    low: float
    high: float
    choices: tuple = ()

    def text(self, value: float) -> str:
        """How ``value`` is written into the fault string."""
        for text, number in self.choices:
            if number == value:
                return text
        return repr(float(value))


@dataclasses.dataclass(frozen=True)
class FaultPattern:
    """A ``--fault`` as given: a fault string with drawn parts (docs/analysis.md).

    Attributes:
        text: as given, e.g. ``actuator_dead:leg_{1..6}@U(1,5)``.
        column: ``fault<n>``: the run's fault, as ``sim --fault`` takes it.
        pieces: the literal text between the drawn parts (one more than ``axes``).
        axes: the drawn parts (``FaultAxis``), in order.
    """
    text: str
    column: str
    pieces: tuple
    axes: tuple

    def resolve(self, values: Sequence[float]) -> str:
        """The fault string of one run: each drawn part replaced by its value.

        Args:
            values: one value per axis, in order.

        Returns:
            A fault string for ``faults.parse_fault``.
        """
        out = [self.pieces[0]]
        for axis, value, piece in zip(self.axes, values, self.pieces[1:]):
            out += [axis.text(value), piece]
        return ''.join(out)


@dataclasses.dataclass(frozen=True)
class SweepPlan:
    """Everything a worker needs for the runs (plain data: it is pickled to workers).

    Attributes:
        plant_params: the parameter file as the plant reads it (flat dict).
        controller_params: as the controller reads it.
        law: the control law's name (``pd``: the compiled eq. (40)).
        duration: simulated time per run [s].
        variations: the varied parameters, in column order.
        output_rate: output samples per second [Hz] (continuous control).
        faults: the ``FaultPattern`` s of ``--fault`` (the plant's ``faults`` of
            the file are in ``plant_params``; both act in every run).
        control: ``continuous`` (eq. (40) inside the ODE, as the paper) or
            ``sampled`` (sampled and held, as the rig; always with faults).
        rate: the sampled control's rate [Hz]; None: the plant's
            ``sensor_rate`` (as varied).
    """
    plant_params: dict
    controller_params: dict
    law: str
    duration: float
    variations: tuple
    output_rate: float = OUTPUT_RATE
    faults: tuple = ()
    control: str = 'continuous'
    rate: float | None = None

    @property
    def axes(self) -> tuple:
        """Everything drawn per run, in column order: the variations, then the
        drawn parts of each fault pattern."""
        return tuple(self.variations) + tuple(a for f in self.faults for a in f.axes)


def parse_vary(text: str) -> Variation:
    """``KEY=LO:HI`` or ``KEY[i]=LO:HI`` -> ``Variation`` (a ``--vary`` option).

    Args:
        text: the option's value; LO and HI in the key's unit.

    Returns:
        The ``Variation``.

    Raises:
        SweepError: malformed, LO or HI not finite numbers, or LO above HI.
    """
    match = _VARY.match(text)
    if not match:
        raise SweepError('--vary %s: expected KEY=LO:HI or KEY[i]=LO:HI' % text)
    name, index, low, high = match.groups()
    try:
        low, high = float(low), float(high)
    except ValueError:
        raise SweepError('--vary %s: LO and HI must be numbers' % text) from None
    if not (math.isfinite(low) and math.isfinite(high)):
        raise SweepError('--vary %s: LO and HI must be finite' % text)
    if low > high:
        raise SweepError('--vary %s: LO %g is above HI %g' % (text, low, high))
    key = name if index is None else '%s[%s]' % (name, int(index))
    return Variation(key, name, None if index is None else int(index), low, high)


def _field_of(prefix: str) -> str:
    """Which field of KIND:LEG[:VALUE][@T0[-T1]] a drawn part after ``prefix`` is."""
    head, at, timing = _DRAWN.sub('X', prefix).partition('@')
    if at:
        return 'end_s' if '-' in timing else 'start_s'
    return ('kind', 'leg', 'value')[min(head.count(':'), 2)]


def _number_text(text: str, pattern: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise SweepError('--fault %s: %r is not a number' % (pattern, text.strip())) from None
    if not math.isfinite(value):
        raise SweepError('--fault %s: %r is not finite' % (pattern, text.strip()))
    return value


def parse_fault_pattern(text: str, number: int = 1) -> FaultPattern:
    """A ``--fault`` option -> ``FaultPattern``.

    The fault syntax of ``sim --fault`` (``KIND:LEG[:VALUE][@T_START[-T_END]]``,
    docs/faults.md), where any number may be drawn per run: ``U(lo,hi)``
    uniformly from [lo, hi], ``{a..b}`` one integer from a to b, ``{a,b,c}`` one
    of the numbers listed, e.g. ``actuator_dead:leg_{1..6}@U(1,5)``: a random
    leg dies at a random time from 1 to 5 s. Without drawn parts, the same
    fault acts in every run.

    Args:
        text: the option's value.
        number: n, its place among the ``--fault`` options (columns ``fault<n>...``).

    Returns:
        The pattern (``resolve`` gives one run's fault string).

    Raises:
        SweepError: empty, a malformed drawn part, lo above hi, two drawn parts
            in one field.
    """
    text = str(text).strip()
    if not text:
        raise SweepError('--fault: empty (expected KIND:LEG[:VALUE][@T_START[-T_END]])')
    column = 'fault%d' % number
    pieces, axes, last = [], [], 0
    for match in _DRAWN.finditer(text):
        pieces.append(text[last:match.start()])
        last = match.end()
        name = '%s.%s' % (column, _field_of(text[:match.start()]))
        if any(a.column == name for a in axes):
            raise SweepError('--fault %s: two drawn parts in %s' % (text, name))
        u_low, u_high, first, stop, listed = match.groups()
        if u_low is not None:
            low, high = _number_text(u_low, text), _number_text(u_high, text)
            if low > high:
                raise SweepError('--fault %s: U(%g,%g): %g is above %g' % (text, low, high,
                                                                          low, high))
            axes.append(FaultAxis(name, low, high))
            continue
        if first is not None:
            if int(first) > int(stop):
                raise SweepError('--fault %s: {%s..%s}: %s is above %s'
                                 % (text, first, stop, first, stop))
            choices = tuple((str(v), float(v)) for v in range(int(first), int(stop) + 1))
        else:
            items = [item.strip() for item in listed.split(',')]
            if not all(items):
                raise SweepError('--fault %s: {%s}: expected numbers a,b,...' % (text, listed))
            choices = tuple((item, _number_text(item, text)) for item in items)
        values = [v for _, v in choices]
        axes.append(FaultAxis(name, min(values), max(values), choices))
    pieces.append(text[last:])
    return FaultPattern(text, column, tuple(pieces), tuple(axes))


def _axis_ends(axis) -> list[float]:
    """The values of an axis checked before a sweep: both ends, or every choice."""
    choices = getattr(axis, 'choices', ())
    return [v for _, v in choices] if choices else [axis.low, axis.high]


def readable_keys(law: str, control: str = 'continuous', rate: float | None = None,
                  faults: bool = False) -> set[str]:
    """The keys a sweep's runs read: only these can be varied.

    Args:
        law: the control law (its ``parameters`` are read besides the model's keys).
        control: ``continuous`` or ``sampled``.
        rate: the sampled control's rate given (then ``sensor_rate`` is not read).
        faults: whether the runs have faults (``sensor_seed``: their noise).

    Returns:
        The machine's keys (``Mechanism``; its sensors' zero offsets aside:
        a run simulates true readings), the gains and the task (``Setup``),
        the law's, and ``sensor_rate`` / ``sensor_seed`` where they take effect.
    """
    keys = (MECHANISM_KEYS - {'leg_length_offset'}) | GAIN_KEYS | TASK_KEYS
    if law != 'pd':
        keys |= set(getattr(law_class(law), 'parameters', ()) or ())
    if control == 'sampled' and rate is None:
        keys |= set(SAMPLED_KEYS)
    if faults:
        keys |= set(FAULT_KEYS)
    return keys


def _check_readable(var: Variation, readable: set[str], control: str, rate) -> None:
    if var.name in readable:
        return
    if var.name == 'faults':
        why = 'faults are swept with --fault (e.g. actuator_dead:leg_{1..6}@U(1,5))'
    elif var.name in SAMPLED_KEYS:
        why = ('%s is read only under --control sampled without --rate (it is the '
               'control rate there)' % var.name) if control == 'continuous' or rate is None \
            else '--rate %g sets the control rate' % rate
    elif var.name in FAULT_KEYS:
        why = '%s seeds the noise of faults, and the runs have none' % var.name
    else:
        why = 'the runs do not read %s' % var.name
    raise SweepError('--vary %s: %s; keys that can be varied: %s'
                     % (var.key, why, ', '.join(sorted(readable))))


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def apply_values(params: dict, variations: Iterable[Variation],
                 values: Iterable[float]) -> dict:
    """A copy of ``params`` with each variation set to its value (lists copied).

    Args:
        params: a flat parameter dictionary (not changed).
        variations: the varied parameters.
        values: one value per variation, in their order (a list element's
            list is written back flat, as floats).

    Returns:
        The new dictionary.
    """
    out = dict(params)
    for var, value in zip(variations, values):
        if var.index is None:
            out[var.name] = float(value)
        else:
            current = np.asarray(out[var.name], dtype=float).ravel().tolist()
            current[var.index] = float(value)
            out[var.name] = current
    return out


def _check_key(var: Variation, plant: dict, controller: dict) -> None:
    present = [p for p in (plant, controller) if var.name in p]
    if not present:
        if var.name in known_keys(controller) and var.index is None:
            return            # a known key the file leaves at its default
        raise SweepError('--vary %s: unknown parameter %s (not in the parameter file)'
                         % (var.key, var.name))
    value = present[0][var.name]
    if var.index is None:
        if isinstance(value, (list, tuple)):
            raise SweepError('--vary %s: %s is a list of %d: vary one element, e.g. %s[0]'
                             % (var.key, var.name, len(value), var.name))
        if not _is_number(value):
            raise SweepError('--vary %s: %s is %r, not a number' % (var.key, var.name, value))
    else:
        if not isinstance(value, (list, tuple)):
            raise SweepError('--vary %s: %s is not a list' % (var.key, var.name))
        if var.index >= len(value):
            raise SweepError('--vary %s: %s has %d elements (index 0 to %d)'
                             % (var.key, var.name, len(value), len(value) - 1))
        if not _is_number(value[var.index]):
            raise SweepError('--vary %s: %s[%d] is %r, not a number'
                             % (var.key, var.name, var.index, value[var.index]))


def _build(plan: SweepPlan, values):
    """(plant setup, controller or None) of one run; ParameterError if invalid
    (a gain of zero under a law it leaves unable to hold the pose too)."""
    plant = setup_from_params(apply_values(plan.plant_params, plan.variations, values))
    if plan.law == 'pd':
        problem = holding_gain_problem(plan.law, plant.gains.kp)
        if problem:
            raise ParameterError('kp', problem)
        return plant, None
    ctrl_params = apply_values(plan.controller_params, plan.variations, values)
    ctrl = setup_from_params(ctrl_params)
    problem = holding_gain_problem(plan.law, ctrl.gains.kp)
    if problem:
        raise ParameterError('kp', problem)
    return plant, Controller(ctrl, ctrl_params, law=plan.law)


def _file_faults(plant_params: Mapping[str, Any]) -> list[str]:
    listed = plant_params.get('faults') or []
    return [listed] if isinstance(listed, str) else list(listed)


def run_faults(plan: SweepPlan, values: Sequence[float]) -> list[str]:
    """The fault strings of one run: the plant's ``faults`` of the file, then
    each ``--fault`` pattern resolved with the run's drawn values.

    Args:
        plan: the sweep.
        values: the run's values, one per axis of ``plan.axes``.

    Returns:
        The faults, as ``sim --fault`` takes them.
    """
    drawn = list(values)[len(plan.variations):]
    out = _file_faults(plan.plant_params)
    for pattern in plan.faults:
        count = len(pattern.axes)
        out.append(pattern.resolve(drawn[:count]))
        drawn = drawn[count:]
    return out


def make_plan(params_path: str | os.PathLike, variations: Iterable[Variation],
              law: str | None = None, duration: float = 10.0,
              faults: Iterable[FaultPattern] = (), control: str | None = None,
              rate: float | None = None) -> SweepPlan:
    """Read the parameter file, check every variation at both ends of its range
    and every fault pattern at the ends of each drawn part.

    Args:
        params_path: the ROS 2 parameter file.
        variations: ``Variation`` s (``parse_vary``).
        law: the control law (default: the controller's ``control_law``, else pd).
        duration: simulated time per run [s].
        faults: ``FaultPattern`` s (``parse_fault_pattern``).
        control: ``continuous`` or ``sampled`` (default: sampled when the runs
            have faults, from ``faults`` or the file's plant ``faults``, else
            continuous; as ``sim``).
        rate: sampled: the control rate [Hz] (default: the plant's
            ``sensor_rate``); continuous: the output rate (default ``OUTPUT_RATE``).

    Returns:
        The ``SweepPlan``.

    Raises:
        SweepError: a key varied twice, an unknown key, a key the runs do not
            read, a list varied whole, an index out of range, a range end the
            parameter validation refuses (its message; a gain of zero
            included), a fault the fault syntax refuses, faults under
            continuous control, a rate that is not a positive number.
        ParameterError: the file itself is invalid.
    """
    plant = read_parameter_file(params_path, 'plant')
    controller = read_parameter_file(params_path, 'controller')
    law = law or read_declared(controller, 'control_law')
    faults = tuple(faults)
    try:
        file_faults = parse_faults(_file_faults(plant))
    except FaultError as exc:
        raise ParameterError('faults', str(exc)) from None
    faulted = bool(faults or file_faults)
    if control not in (None, 'continuous', 'sampled'):
        raise SweepError('--control must be continuous or sampled, got %r' % (control,))
    if faulted and control == 'continuous':
        raise SweepError('faults act on the sensor samples: use --control sampled (the '
                         'default with faults)')
    control = control or ('sampled' if faulted else 'continuous')
    if rate is not None and not (math.isfinite(rate) and rate > 0):
        raise SweepError('--rate must be a positive number of Hz, got %g' % rate)
    plan = SweepPlan(plant, controller, law, float(duration), tuple(variations),
                     output_rate=OUTPUT_RATE if control == 'sampled' or rate is None
                     else float(rate),
                     faults=faults, control=control,
                     rate=float(rate) if control == 'sampled' and rate is not None else None)
    readable = readable_keys(law, control, plan.rate, faulted)
    keys = [v.key for v in plan.variations]
    for var in plan.variations:
        if keys.count(var.key) > 1:
            raise SweepError('--vary %s: given twice' % var.key)
        if var.name in known_keys(controller):      # a typo is named as unknown below
            _check_readable(var, readable, control, plan.rate)
        _check_key(var, plant, controller)
        _check_readable(var, readable, control, plan.rate)
    _build(dataclasses.replace(plan, variations=()), [])    # the file itself (ParameterError)
    for var in plan.variations:
        for end in (var.low, var.high):
            try:
                _build(dataclasses.replace(plan, variations=(var,)), [end])
                if var.name in SAMPLED_KEYS:
                    read_declared(apply_values(plant, [var], [end]), var.name)
            except ParameterError as exc:
                raise SweepError('--vary %s=%g:%g: %g is outside the valid range: %s'
                                 % (var.key, var.low, var.high, end, exc)) from None
    for pattern in faults:
        lows = [a.low if not a.choices else a.choices[0][1] for a in pattern.axes]
        for k, axis in enumerate(pattern.axes):
            for end in _axis_ends(axis):
                text = pattern.resolve(lows[:k] + [end] + lows[k + 1:])
                try:
                    parse_faults([text])
                except FaultError as exc:
                    raise SweepError('--fault %s: %s' % (pattern.text, exc)) from None
        if not pattern.axes:
            try:
                parse_faults([pattern.text])
            except FaultError as exc:
                raise SweepError('--fault %s' % exc) from None
    return plan


def draw_values(variations: Sequence[Variation], runs: int, seed: int | None = None,
                grid: bool = False) -> np.ndarray:
    """The parameter values of the runs, drawn from each variation's [low, high].

    Args:
        variations: the K drawn axes (``SweepPlan.axes``: ``Variation`` s, and
            ``FaultAxis`` es, whose choices are drawn each as likely).
        runs: N, how many runs (>= 1).
        seed: the seed of numpy's ``default_rng`` for the uniform draws.
        grid: instead of draws, every choice of each choice axis and n evenly
            spaced values of each other axis, n = round((runs / choices)^(1/K'))
            (K' such axes), every combination (first axis slowest).

    Returns:
        (N, K) values in the axes' units, one row per run ((runs, 0) without
        axes).

    Raises:
        SweepError: ``runs`` below 1.
    """
    if runs < 1:
        raise SweepError('--runs must be at least 1, got %d' % runs)
    k = len(variations)
    if k == 0:
        return np.zeros((runs, 0))
    low = np.array([v.low for v in variations])
    high = np.array([v.high for v in variations])
    choices = [np.array([c for _, c in getattr(v, 'choices', ())]) for v in variations]
    if grid:
        fixed = int(np.prod([len(c) for c in choices if len(c)]))
        ranged = sum(1 for c in choices if not len(c))
        n = max(1, int(round((runs / fixed) ** (1.0 / ranged)))) if ranged else 1
        axes = [c if len(c) else (np.linspace(lo, hi, n) if n > 1 else np.array([lo]))
                for c, lo, hi in zip(choices, low, high)]
        return np.stack(np.meshgrid(*axes, indexing='ij'), axis=-1).reshape(-1, k)
    rng = np.random.default_rng(seed)
    draws = rng.random((runs, k))
    out = low + (high - low) * draws
    for j, options in enumerate(choices):
        if len(options):
            out[:, j] = options[np.minimum((draws[:, j] * len(options)).astype(int),
                                           len(options) - 1)]
    return out


def axis_columns(plan: SweepPlan, values: Sequence[float]) -> dict[str, Any]:
    """A run's values under their columns: each axis's value, each ``--fault``'s
    resolved fault string (``fault<n>``).

    Args:
        plan: the sweep.
        values: the run's values, one per axis of ``plan.axes``.

    Returns:
        {column: value}.
    """
    out: dict[str, Any] = {axis.column: float(v) for axis, v in zip(plan.axes, values)}
    drawn = [float(v) for v in values][len(plan.variations):]
    for pattern in plan.faults:
        count = len(pattern.axes)
        out[pattern.column] = pattern.resolve(drawn[:count])
        drawn = drawn[count:]
    return out
