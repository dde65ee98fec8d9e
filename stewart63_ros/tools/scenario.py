"""`scenario`: run scenario files and give each expectation a verdict (docs/scenarios.md).

    scenario run FILE... [--junit F] [--out DIR] [--jobs N | --scheduler ADDRESS]
             [--domain ID] [--no-figures]

Runs every scenario of the files (``run: sim`` in process, ``lockstep`` and
``realtime`` by starting ``rig`` with a bag and a summary in a temporary
folder, each on a ROS domain of its own), prints one line per expectation
(the measured value beside the bound; a failure says by how much and when),
and writes DIR/report.md with one figure per scenario (DIR/figures/), and
with --junit a JUnit XML file that CI servers read (one test case per
scenario). Exit status: 0 every expectation holds, 1 one fails (or a run
fails), 2 bad input (a bad file: one line naming its key).

Rig scenarios lease their ROS domain ids from the same lock files as the
package's tests (one id per run; ``STEWART63_SCENARIO_DOMAINS=LO-HI``
restricts the range, default 1-100).
"""
from __future__ import annotations

import argparse
import concurrent.futures
import contextlib
import dataclasses
import math
import multiprocessing
import os
import sys
import tempfile
import time
from collections.abc import Iterable, Sequence
from pathlib import Path

from stewart63_ros.tools.cli import announce_compile, quiet_on_closed_pipe
from stewart63_ros.tools.scenario_report import (
    Outcome,
    write_junit,
    write_report,
)
from stewart63_ros.tools.scenario_rig import domain_range, run_rig

PROG = 'scenario'


def _fail(message) -> int:
    print('%s: error: %s' % (PROG, message), file=sys.stderr)
    return 2


# -- running --------------------------------------------------------------------
def run_one(scenario, keep_trace: bool = True, domain: int | None = None) -> Outcome:
    """One scenario, its verdicts (a run that fails: every verdict fails, with the reason)."""
    # lazy: core.controllers.laws costs 926 ms (numba); --help answers
    from stewart63_ros.core.controllers.laws import LawError
    from stewart63_ros.core.scenarios.running import run_sim
    from stewart63_ros.core.scenarios.scenario import ScenarioError
    from stewart63_ros.core.scenarios.verdicts import evaluate, failed_run_verdicts
    start = time.perf_counter()
    try:
        if scenario.run == 'sim':
            trace = run_sim(scenario)
        else:
            with tempfile.TemporaryDirectory(prefix='scenario_') as tmp:
                trace = run_rig(scenario, Path(tmp), domain)
    except (RuntimeError, ScenarioError, LawError, ValueError, ArithmeticError, OSError) as exc:
        return Outcome(scenario, failed_run_verdicts(scenario.expect, scenario.duration),
                       str(exc), time.perf_counter() - start)
    verdicts = evaluate(trace, scenario.expect)
    return Outcome(scenario, verdicts, '', time.perf_counter() - start,
                   trace if keep_trace else None)


def run_chunk(scenarios: Sequence, keep_trace: bool = True) -> list[Outcome]:
    """The scenarios of one task, in order."""
    return [run_one(s, keep_trace) for s in scenarios]


def warm_up(scenarios: Sequence) -> None:
    """Load (or compile) the kernels the sim scenarios use, before forking workers."""
    # lazy: core.scenarios.scenario costs 129 ms; --help answers without it
    from stewart63_ros.core.scenarios.running import run_sim
    seen = set()
    for s in scenarios:
        key = (s.run, s.control_law, bool(s.faults), bool(s.wrench), bool(s.reference))
        if s.run == 'sim' and key not in seen:
            seen.add(key)
            with contextlib.suppress(Exception):
                run_sim(dataclasses.replace(s, duration=min(s.duration, 0.01)))


def _chunks(items: Sequence, parts: int) -> list[list]:
    size = max(1, math.ceil(len(items) / max(1, parts)))
    return [list(items[k:k + size]) for k in range(0, len(items), size)]


def run_all(scenarios: Sequence, jobs: int = 1, scheduler: str | None = None,
            keep_traces: bool = True, domain: int | None = None) -> list[Outcome]:
    """Every scenario: in this process (``jobs`` 1), on ``jobs`` forked local
    processes, or on the Dask cluster at ``scheduler``; outcomes in input order.

    Rig scenarios run one per task (each starts its own rig on its own domain);
    sim scenarios in chunks, after the kernels are loaded in every worker. With
    a fixed ``domain`` the rig scenarios run one after the other, here."""
    warm_up(scenarios)
    rigs = [i for i, s in enumerate(scenarios) if s.run != 'sim']
    serial = []
    if domain is not None:
        serial, rigs = rigs, []
    sims = [i for i, s in enumerate(scenarios) if s.run == 'sim']
    workers = max(1, jobs)
    tasks = [[i] for i in rigs] + _chunks(sims, workers * 4)
    out: list[Outcome | None] = [None] * len(scenarios)
    if scheduler is not None:
        from distributed import Client  # lazy: optional: distributed costs 543 ms; only --dask
        client = Client(scheduler, timeout='10s')
        try:
            client.run(warm_up, list(scenarios))
            futures = client.map(run_chunk, [[scenarios[i] for i in t] for t in tasks],
                                 keep_trace=keep_traces, pure=False)
            results = client.gather(futures)
        finally:
            client.close()
    elif workers == 1 or len(scenarios) == 1:
        results = [run_chunk([scenarios[i] for i in t], keep_traces) for t in tasks]
    else:
        context = multiprocessing.get_context('fork')
        with concurrent.futures.ProcessPoolExecutor(max_workers=workers,
                                                    mp_context=context) as pool:
            results = list(pool.map(run_chunk, [[scenarios[i] for i in t] for t in tasks],
                                    [keep_traces] * len(tasks)))
    for task, outcomes in zip(tasks, results):
        for i, outcome in zip(task, outcomes):
            out[i] = outcome
    for i in serial:
        out[i] = run_one(scenarios[i], keep_traces, domain)
    return [o for o in out if o is not None]


def load_files(paths: Iterable[str]) -> list:
    """Every scenario of the files, in order (ScenarioError for a bad file; two
    scenarios of one name refused)."""
    # lazy: core.scenarios.scenario costs 129 ms; --help answers without it
    from stewart63_ros.core.scenarios.parsing import load_scenarios
    from stewart63_ros.core.scenarios.scenario import ScenarioError
    out = []
    for path in paths:
        out.extend(load_scenarios(path))
    seen: dict[str, str] = {}
    for s in out:
        if s.name in seen and seen[s.name] != s.source:
            raise ScenarioError('%s: scenario %r is also in %s' % (s.source, s.name, seen[s.name]))
        seen[s.name] = s.source
    return out


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split('\n\n')[0])
    sub = parser.add_subparsers(dest='command', required=True)
    run = sub.add_parser('run', help='run scenario files, give verdicts, write the report')
    run.add_argument('files', nargs='+', metavar='FILE', help='scenario files (YAML)')
    run.add_argument('--junit', metavar='F', default=None, help='write JUnit XML here')
    run.add_argument('--out', metavar='DIR', default='out/scenarios',
                     help='the report and its figures (out/scenarios)')
    engine = run.add_mutually_exclusive_group()
    engine.add_argument('--jobs', type=int, default=1, metavar='N',
                        help='run on N local processes (1: in this process)')
    engine.add_argument('--scheduler', default=None, metavar='ADDRESS',
                        help='run on the Dask cluster of this scheduler (tcp://host:8786)')
    run.add_argument('--domain', type=int, default=None, metavar='ID',
                     help='run the rig scenarios on this ROS domain id, one after the other '
                     '(default: each on a leased free id, in parallel)')
    run.add_argument('--no-figures', action='store_true', help='a report without figures')
    return parser


@quiet_on_closed_pipe
def main(argv=None) -> int:
    # The summary's wall time is what the user waited: from the process's
    # start when run as the command (it said 3.7 s of runs for a 23 s wait),
    # from here when called in a process that was running before.
    begun = time.perf_counter() - (process_age() if argv is None else 0.0)
    args = build_parser().parse_args(argv)
    # lazy: core.scenarios.scenario costs 129 ms; --help answers without it
    from stewart63_ros.core.scenarios.scenario import ScenarioError
    if args.jobs < 1:
        return _fail('--jobs must be at least 1, got %d' % args.jobs)
    if args.domain is not None and not 0 <= args.domain <= 232:
        return _fail('--domain must be a ROS domain id from 0 to 232, got %d' % args.domain)
    try:
        domain_range()
        scenarios = load_files(args.files)
    except (ScenarioError, ValueError) as exc:
        return _fail(exc)
    if args.scheduler:
        try:
            # lazy: optional: distributed costs 543 ms; only --dask
            import distributed  # noqa: F401
        except ImportError:
            return _fail('--scheduler needs Dask: pip install dask distributed')
    announce_compile(PROG)
    start = time.perf_counter()
    try:
        outcomes = run_all(scenarios, args.jobs, args.scheduler,
                           keep_traces=not args.no_figures, domain=args.domain)
    except OSError as exc:
        return _fail('Dask scheduler %s: %s' % (args.scheduler, exc))
    runs = time.perf_counter() - start
    for o in outcomes:
        print('%s %s (%s, %.2f s)' % ('PASS' if o.passed else 'FAIL', o.scenario.name,
                                      o.scenario.run, o.wall_s))
        if o.error:
            print('    the run failed: %s' % o.error)
        for v in o.verdicts:
            print('    %s' % v.text())
    report_start = time.perf_counter()
    report = write_report(outcomes, Path(args.out), figures=not args.no_figures,
                          jobs=args.jobs)
    written = [str(report)]
    if args.junit:
        write_junit(outcomes, Path(args.junit))
        written.append(args.junit)
    end = time.perf_counter()
    failed = sum(not o.passed for o in outcomes)
    print('%s: %d scenarios, %d passed, %d failed; %.2f s wall in all: start-up and files '
          '%.2f s, runs %.2f s, report%s %.2f s; written: %s' % (
              PROG, len(outcomes), len(outcomes) - failed, failed, end - begun,
              start - begun, runs, '' if args.no_figures else ' and figures',
              end - report_start, ', '.join(written)))
    return 1 if failed else 0


def process_age() -> float:
    """Seconds since this process started (Linux: /proc), 0 where unknown:
    the interpreter's start and the imports before ``main`` are time the user
    waited too."""
    try:
        with open('/proc/self/stat') as stat, open('/proc/uptime') as uptime:
            ticks = int(stat.read().rsplit(')', 1)[1].split()[19])     # field 22, starttime
            return max(0.0, float(uptime.read().split()[0]) - ticks / os.sysconf('SC_CLK_TCK'))
    except (OSError, ValueError, IndexError):
        return 0.0


if __name__ == '__main__':
    sys.exit(main())
