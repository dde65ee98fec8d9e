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

The plan (what varies, checked, and the values drawn) is ``sweep_plan``'s;
runs.csv's columns and summary.json are ``sweep_report``'s.
"""
from __future__ import annotations

import concurrent.futures
import dataclasses
import math
import multiprocessing
import os
import time
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from stewart63_ros.core.analysis.sweep_plan import (
    SweepError,
    SweepPlan,
    _build,
    apply_values,
    axis_columns,
    run_faults,
)
from stewart63_ros.core.controllers.laws import LawError
from stewart63_ros.core.controllers.simulate import run_continuous, run_sampled
from stewart63_ros.core.machine.faults import FaultError, FaultModel, parse_faults
from stewart63_ros.core.mechanics.dynamics import Dynamics, lengths_rates
from stewart63_ros.core.plumbing._jit import njit
from stewart63_ros.core.plumbing.node_parameters import read as read_declared
from stewart63_ros.core.plumbing.params import ParameterError

#: Settling band: this fraction of the largest leg travel.
SETTLING_BAND = 0.02
#: A run settled only within this last fraction of its duration has not settled.
UNSETTLED_TAIL = 0.1


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
