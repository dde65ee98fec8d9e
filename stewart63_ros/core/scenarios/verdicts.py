"""A run's samples (a ``Trace``) judged against its expectations: each metric
of ``scenario.METRICS`` measured over its window, the supervisor's trips
against ``trip`` and ``no_trip``.
"""
from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

from stewart63_ros.core.scenarios.scenario import (
    TRACKING_FROM,
    TRIP_METRICS,
    Expectation,
    ScenarioError,
    Trace,
    Verdict,
)


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
