"""Scenario files: runs with expectations and their verdicts (docs/scenarios.md).

A scenario file (YAML) holds ``scenarios:``, a list of runs, each with the
expectations its result must meet. This module says what a scenario is: its
keys, the metrics, a run's samples (a ``Trace``) and a ``Verdict``. The jobs
are beside it: ``parsing`` reads and checks a file (every key, with a "did
you mean" for a typo) and expands a ``matrix:``; ``running`` runs a ``sim``
scenario in this process (``run_sim``: the sampled loop of
``simulate.run_sampled`` at the plant's ``sensor_rate``, the loop the
lockstep rig closes over DDS sample for sample); ``verdicts`` turns a
``Trace`` into verdicts (``evaluate``). Running on the rig is the
``scenario`` tool's (it starts ``rig``); it builds a ``Trace`` from the
recorded bag and the plant's summary.

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
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

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
