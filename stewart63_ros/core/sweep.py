"""Many runs of the paper's scenario with parameters drawn from ranges, in parallel.

A run is exactly what ``sim`` (continuous control, the default) does with one
parameter file: the plant's mechanism from the file's plant section, the
law from the controller's (``pd``: eq. (40) compiled inside the ODE, scipy's
RK45 compiled in ``dopri``; another law: ``laws.Controller`` through
``simulate.run_continuous``), output at 100 Hz. Each run varies some keys of
the file: a scalar (``platform_mass``) or one element of a list as written in
the file (``kp[2]``, ``base_points[4]``), drawn uniformly from [LO, HI] or on
a grid.

Per run (``METRICS``):

- ``final_error_percent``: max_i |L_i(T) - (L_i)_0| / (L_i)_0 x 100 at the
  last sample: ``sim``'s ``positioning_error_percent`` (the same arithmetic);
- ``max_force``: the largest |F_i| [N] over the output samples (100 Hz);
- ``settling_time_s``: the first output time after which every leg stays
  within 2 % of the largest leg travel, max_i |L_i(T) - L_i(0)|, of its final
  length L_i(T) (a step response's 2 % settling time, about the final value,
  which the PD law's gravity sag moves off the setpoint); NaN when the legs
  enter that band only in the last 10 % of the run (not settled);
- ``endstop_samples``: output samples with a leg outside its stroke;
- ``diverged``: 1 when the run did not finish: non-finite state, the
  integrator failed, the law raised, or the drawn parameters are invalid
  (``failure`` says which); its metrics are NaN.

Runs go to local processes (``concurrent.futures``, forked after the
kernels are loaded) or to a Dask cluster (``distributed``): chunks of runs,
each chunk one task.
"""
from __future__ import annotations

import concurrent.futures
import dataclasses
import math
import multiprocessing
import os
import re
import time
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from stewart63_ros.core._jit import njit
from stewart63_ros.core.dynamics import Dynamics, lengths_rates
from stewart63_ros.core.faults import FaultError, FaultModel, parse_faults
from stewart63_ros.core.laws import Controller, LawError, holding_gain_problem, law_class
from stewart63_ros.core.mechanism import MECHANISM_KEYS
from stewart63_ros.core.node_parameters import read as read_declared
from stewart63_ros.core.params import (
    ParameterError,
    known_keys,
    read_parameter_file,
    setup_from_params,
)
from stewart63_ros.core.setup import GAIN_KEYS, TASK_KEYS
from stewart63_ros.core.simulate import run_continuous, run_sampled

METRICS = ('final_error_percent', 'max_force', 'settling_time_s', 'endstop_samples',
           'diverged')
#: Output sample rate of a run [Hz] (``sim``'s default for continuous control).
OUTPUT_RATE = 100.0
#: Settling band: this fraction of the largest leg travel.
SETTLING_BAND = 0.02
#: A run settled only within this last fraction of its duration has not settled.
UNSETTLED_TAIL = 0.1
PERCENTILES = (0, 5, 25, 50, 75, 95, 100)

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


@njit
def leg_lengths_of_states(base: np.ndarray, plat: np.ndarray,
                          states: np.ndarray) -> np.ndarray:
    """Leg lengths of many states (eq. 5): the sensors' ``lengths_rates``. Compiled.

    Args:
        base, plat: (6, 3) b_i and each leg's vertex p_k(i) [m]
            (``Dynamics.base_points``, ``Dynamics.leg_points``).
        states: (N, 13) states, as the dynamics'.

    Returns:
        (N, 6) leg lengths [m].
    """
    out = np.empty((states.shape[0], 6))
    for k in range(states.shape[0]):
        out[k] = lengths_rates(base, plat, states[k])[0]
    return out


def settling_time(times: np.ndarray, lengths: np.ndarray, band: float = SETTLING_BAND,
                  tail: float = UNSETTLED_TAIL) -> float:
    """The 2 % settling time of leg lengths (see ``METRICS``).

    Args:
        times: (N,) output times [s], increasing.
        lengths: (N, 6) leg lengths at those times [m].
        band: the band, a fraction of the largest leg travel.
        tail: settling within this last fraction of the run counts as not settled.

    Returns:
        The settling time [s] (0.0 when no leg moves); NaN when not settled.
    """
    final = lengths[-1]
    travel = float(np.max(np.abs(final - lengths[0])))
    if travel == 0.0:
        return 0.0
    outside = np.any(np.abs(lengths - final) > band * travel, axis=1)
    if not outside.any():
        return float(times[0])
    last = int(np.flatnonzero(outside)[-1])
    settled = float(times[min(last + 1, len(times) - 1)])
    if settled > times[-1] - tail * (times[-1] - times[0]):
        return float('nan')
    return settled


def run_one(plan: SweepPlan, values: Iterable[float]) -> dict[str, Any]:
    """One run: the plant (and a law other than ``pd``) built with ``values``, simulated
    as ``sim`` does (continuous, or sampled with the run's faults).

    Args:
        plan: the sweep.
        values: (K,) one value per axis of ``plan.axes`` (the variations first).

    Returns:
        {metric: value for each of ``METRICS``, 'failure': str ('' when the
        run finished)}; a failed run has ``diverged`` 1 and NaN metrics.
    """
    row = {'final_error_percent': math.nan, 'max_force': math.nan,
           'settling_time_s': math.nan, 'endstop_samples': 0, 'diverged': 1, 'failure': ''}
    values = [float(v) for v in values]
    try:
        setup, controller = _build(plan, values[:len(plan.variations)])
    except ParameterError as exc:
        row['failure'] = 'invalid parameters: %s' % exc
        return row
    dyn = Dynamics(setup.mechanism)
    try:
        if plan.control == 'sampled':
            plant = apply_values(plan.plant_params, plan.variations, values)
            rate = plan.rate or read_declared(plant, 'sensor_rate')
            texts = run_faults(plan, values)
            try:
                model = FaultModel(parse_faults(texts), rate,
                                   read_declared(plant, 'sensor_seed')) if texts else None
            except FaultError as exc:       # a draw the fault syntax refuses (T1 <= T0)
                row['failure'] = 'invalid fault: %s' % exc
                return row
            result = run_sampled(setup, plan.duration, rate, dyn=dyn, controller=controller,
                                 faults=model)
        else:
            result = run_continuous(setup, plan.duration, output_rate=plan.output_rate,
                                    dyn=dyn, controller=controller)
    except LawError as exc:
        row['failure'] = 'the control law failed: %s' % exc
        return row
    except (RuntimeError, ValueError, ArithmeticError) as exc:
        row['failure'] = 'diverged: %s' % exc
        return row
    if not np.all(np.isfinite(result.states)):
        row['failure'] = 'diverged: non-finite state'
        return row
    errors = result.final_leg_error_percent(dyn, setup.task.setpoint_lengths)   # as sim's summary
    lengths = leg_lengths_of_states(dyn.base_points, dyn.leg_points, result.states)
    row.update(final_error_percent=float(errors.max()),
               max_force=float(np.max(np.abs(result.forces))),
               settling_time_s=settling_time(result.times, lengths),
               endstop_samples=int(result.endstop_samples), diverged=0)
    return row


def run_chunk(plan: SweepPlan,
              chunk: Iterable[tuple[int, Iterable[float]]]) -> list[dict[str, Any]]:
    """The runs of a chunk: the unit of work of a worker.

    Args:
        plan: the sweep.
        chunk: [(run index, values (K,)), ...] (``chunks_of``).

    Returns:
        ``run_one``'s rows, each with its 'run' index, in chunk order.
    """
    rows = []
    for index, values in chunk:
        row = run_one(plan, values)
        row['run'] = int(index)
        rows.append(row)
    return rows


def chunks_of(values: np.ndarray | Sequence[Sequence[float]],
              parts: int) -> list[list[tuple[int, tuple[float, ...]]]]:
    """Split the runs into about ``parts`` chunks of (index, values) pairs.

    Args:
        values: (N, K) the runs' values (``draw_values``).
        parts: how many chunks to aim for (at least one run per chunk).

    Returns:
        Chunks of equal size (the last smaller) of (run index, K floats), in
        run order.
    """
    items = [(i, tuple(float(v) for v in row)) for i, row in enumerate(values)]
    size = max(1, math.ceil(len(items) / max(1, parts)))
    return [items[k:k + size] for k in range(0, len(items), size)]


def warm_up(plan: SweepPlan, values: Iterable[float]) -> None:
    """Load (or compile) the kernels of a run in this process, before forking workers.

    Args:
        plan: the sweep (run for at most 0.05 s here).
        values: (K,) one run's values.
    """
    short = dataclasses.replace(plan, duration=min(plan.duration, 0.05))
    run_one(short, values)


def run_local(plan: SweepPlan, values: np.ndarray,
              workers: int | None = None) -> tuple[list[dict[str, Any]], int, float]:
    """All runs on this machine: ``workers`` processes (default: one per core),
    forked after ``warm_up`` so that none of them compiles.

    Args:
        plan: the sweep.
        values: (N, K) the runs' values.
        workers: how many processes (1: in this process).

    Returns:
        (``run_one`` rows with their 'run' index, in run order; workers used;
        wall time of the runs [s]).
    """
    workers = max(1, int(workers or os.cpu_count() or 1))
    chunks = chunks_of(values, workers * 8)
    warm_up(plan, values[0])
    start = time.perf_counter()
    if workers == 1 or len(values) == 1:
        rows = [row for chunk in chunks for row in run_chunk(plan, chunk)]
        return rows, 1, time.perf_counter() - start
    context = multiprocessing.get_context('fork')
    with concurrent.futures.ProcessPoolExecutor(max_workers=workers,
                                                mp_context=context) as pool:
        parts = pool.map(run_chunk, [plan] * len(chunks), chunks)
        rows = [row for part in parts for row in part]
    return sorted(rows, key=lambda r: r['run']), workers, time.perf_counter() - start


def check_scheduler_address(address: str) -> str:
    """A Dask scheduler's address as ``distributed`` parses it, checked before
    anything starts (``tcp://host:8786``; ``host:8786`` means tcp).

    Args:
        address: as given to ``--scheduler``.

    Returns:
        The address.

    Raises:
        SweepError: not an address with a host and a port (the reason).
        ImportError: ``distributed`` is not installed.
    """
    # lazy: optional: distributed costs 543 ms; only --scheduler
    from distributed.comm import parse_address
    from distributed.comm.addressing import parse_host_port
    try:
        scheme, location = parse_address(address)
        if scheme in ('tcp', 'tls', 'ws', 'wss'):
            parse_host_port(location)
    except (ValueError, TypeError) as exc:
        raise SweepError('--scheduler %s: not a scheduler address (expected tcp://HOST:PORT): '
                         '%s' % (address, exc)) from None
    return address


def _run_chunk_on_worker(plan: SweepPlan, chunk) -> tuple[str, list[dict[str, Any]]]:
    """``run_chunk`` on a Dask worker, with the worker's address (who ran it)."""
    # lazy: optional: distributed costs 543 ms; only --scheduler
    from distributed import get_worker
    return get_worker().address, run_chunk(plan, chunk)


def run_dask(plan: SweepPlan, values: np.ndarray, scheduler: str | None = None,
             local_workers: int | None = None) -> tuple[list[dict[str, Any]], int, float]:
    """All runs on a Dask cluster: the scheduler at ``scheduler`` (``tcp://host:8786``),
    or a ``distributed.LocalCluster`` of ``local_workers`` processes (one thread
    each) started for the sweep. Workers need this package importable (the
    same version). Every worker runs ``warm_up`` first (loads the kernels), then
    the clock starts.

    Args:
        plan: the sweep.
        values: (N, K) the runs' values.
        scheduler: the scheduler's address, or None for a local cluster.
        local_workers: the local cluster's processes (default 1).

    Returns:
        (``run_one`` rows with their 'run' index, in run order; the workers
        that delivered runs; wall time of the runs [s]). ``run_dask_report``
        also tells the workers lost meanwhile.

    Raises:
        ImportError: ``distributed`` is not installed.
    """
    report = run_dask_report(plan, values, scheduler, local_workers)
    return report['rows'], report['workers'], report['wall_time_s']


def run_dask_report(plan: SweepPlan, values: np.ndarray, scheduler: str | None = None,
                    local_workers: int | None = None) -> dict[str, Any]:
    """``run_dask``, with the workers as they were: those the sweep started
    with, those that delivered runs, those lost on the way (a worker killed
    mid-sweep: the scheduler gives its runs to the others, whose rows are
    the same).

    Args:
        plan, values, scheduler, local_workers: as ``run_dask``.

    Returns:
        {'rows': in run order, 'wall_time_s': float [s], 'workers': int (that
        delivered runs), 'workers_at_start': int, 'workers_lost': int (of
        those at the start, gone at the end)}.

    Raises:
        ImportError: ``distributed`` is not installed.
        SweepError: the cluster lost runs it could not do again (every
            worker gone, or a run's worker killed too often).
    """
    # lazy: optional: distributed costs 543 ms; only --scheduler
    from distributed import Client, LocalCluster
    cluster = None
    if scheduler is None:
        cluster = LocalCluster(n_workers=int(local_workers or 1), threads_per_worker=1,
                               processes=True, host='127.0.0.1', dashboard_address=None)
        client = Client(cluster)
    else:
        client = Client(scheduler, timeout='10s')
    try:
        at_start = set(client.scheduler_info()['workers'])
        chunks = chunks_of(values, max(1, len(at_start)) * 8)
        client.run(warm_up, plan, tuple(values[0]))
        start = time.perf_counter()
        # The plan goes with every task (a few kB), not scattered once: data
        # scattered to a worker that dies cannot be made again, a task can.
        futures = client.map(_run_chunk_on_worker, [plan] * len(chunks), chunks, pure=False)
        try:
            parts = client.gather(futures)
        except Exception as exc:  # noqa: BLE001 - KilledWorker, CancelledError, ...
            raise SweepError('the Dask cluster lost runs: %s: %s'
                             % (type(exc).__name__, str(exc).splitlines()[0] if str(exc)
                                else '')) from None
        wall = time.perf_counter() - start
        at_end = set(client.scheduler_info()['workers'])
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    rows = [row for _, part in parts for row in part]
    return {'rows': sorted(rows, key=lambda r: r['run']), 'wall_time_s': wall,
            'workers': len({address for address, _ in parts}),
            'workers_at_start': len(at_start), 'workers_lost': len(at_start - at_end)}


def run_sweep(plan: SweepPlan, values: np.ndarray | Sequence[Sequence[float]],
              workers: int | None = None, scheduler: str | None = None,
              dask_local: int | None = None) -> dict[str, Any]:
    """Every run, locally (``run_local``) or on Dask (``run_dask``).

    The wall time counts the runs only, after every worker has loaded the
    kernels (cluster start-up and compilation excluded).

    Args:
        plan: the sweep.
        values: (N, K) the runs' values (``draw_values``).
        workers: local processes (default: one per core).
        scheduler: a Dask scheduler's address; dask_local: processes of a
            local Dask cluster instead (either one selects Dask).

    Returns:
        {'rows': the rows in run order, each with its values under their
        columns (``axis_columns``), 'wall_time_s': float [s], 'workers': int
        (that delivered runs), 'workers_at_start': int, 'workers_lost': int
        (gone before the end: a Dask worker killed mid-sweep), 'engine':
        'processes' or 'dask ...'}.
    """
    values = np.asarray(values, dtype=float).reshape(len(values), len(plan.axes))
    if scheduler is None and dask_local is None:
        rows, used, wall = run_local(plan, values, workers)
        outcome = {'rows': rows, 'wall_time_s': wall, 'workers': used,
                   'workers_at_start': used, 'workers_lost': 0, 'engine': 'processes'}
    else:
        outcome = run_dask_report(plan, values, scheduler, dask_local)
        outcome['engine'] = 'dask %s' % (scheduler or 'LocalCluster')
    for row in outcome['rows']:
        row.update(axis_columns(plan, values[row['run']]))
    return outcome


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


def columns(plan: SweepPlan) -> list[str]:
    """Columns of runs.csv: run, each varied key (``param.<key>``), each fault
    pattern's drawn parts (``fault<n>.<field>``) and fault (``fault<n>``), the
    metrics, failure. No two share a name.

    Args:
        plan: the sweep.

    Returns:
        The column names in order.
    """
    faults = []
    for pattern in plan.faults:
        faults += [a.column for a in pattern.axes] + [pattern.column]
    return (['run'] + [v.column for v in plan.variations] + faults + list(METRICS)
            + ['failure'])


def summary(plan: SweepPlan,
            rows: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, float]]:
    """Percentiles (0, 5, 25, 50, 75, 95, 100), mean and count of every numeric
    column over the runs that finished; ``diverged``: how many did not.

    Args:
        plan: the sweep.
        rows: the runs' rows (``run_sweep``'s 'rows').

    Returns:
        {axis column or metric: {'count': int (finite values), 'p0' ... 'p100',
        'mean' (when count > 0)}, 'diverged': {'count': int}}, in the column's
        unit.
    """
    done = [r for r in rows if not r['diverged']]
    out: dict[str, dict[str, float]] = {}
    for key in [a.column for a in plan.axes] + list(METRICS[:-1]):
        data = np.array([r[key] for r in done], dtype=float)
        data = data[np.isfinite(data)]
        stats: dict[str, float] = {'count': int(data.size)}
        if data.size:
            stats.update({'p%d' % p: float(v) for p, v in zip(PERCENTILES,
                                                              np.percentile(data, PERCENTILES))})
            stats['mean'] = float(data.mean())
        out[key] = stats
    out['diverged'] = {'count': int(sum(r['diverged'] for r in rows))}
    return out


def write_run_parameters(params_path: str | os.PathLike, out_path: str | os.PathLike,
                         variations: Iterable[Variation], values: Iterable[float],
                         faults: Iterable[str] = ()) -> None:
    """Write the parameter file of one run: ``params_path`` with each varied key
    set in every section that has it (in the wildcard section ``/**`` when
    none has it), and the run's ``--fault`` s (its ``fault<n>`` columns) added
    to the plant's ``faults``, so that ``sim --params out_path`` reproduces the
    run (``--control sampled`` for a sampled sweep without faults).

    Args:
        params_path: the sweep's ROS 2 parameter file (read).
        out_path: the run's parameter file (written, YAML).
        variations: the varied parameters; values: (K,) the run's values.
        faults: the run's resolved fault strings (``fault<n>`` of runs.csv).
    """
    doc = yaml.safe_load(Path(params_path).read_text())
    sections = [s['ros__parameters'] for s in doc.values()
                if isinstance(s, dict) and isinstance(s.get('ros__parameters'), dict)]
    wildcard = next((doc[k]['ros__parameters'] for k in doc if str(k).strip() in ('/**', '**')),
                    sections[0])
    for var, value in zip(variations, values):
        holders = [s for s in sections if var.name in s] or [wildcard]
        for section in holders:
            section.update(apply_values(section, [var], [value]))
    faults = list(faults)
    if faults:
        plant = next((doc[k]['ros__parameters'] for k in doc if str(k).split('/')[-1] == 'plant'
                      and isinstance(doc[k], dict)), wildcard)
        plant['faults'] = _file_faults(plant) + faults
    Path(out_path).write_text(yaml.safe_dump(doc, sort_keys=False))
