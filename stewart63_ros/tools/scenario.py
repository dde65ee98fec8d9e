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
import json
import math
import multiprocessing
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from stewart63_ros.paths import try_lock_domain
from stewart63_ros.tools.cli import announce_compile, quiet_on_closed_pipe

PROG = 'scenario'
#: Bound on a rig's start-up (loading or compiling the kernels, discovery) [s].
RIG_START_BOUND = 240.0


def _fail(message) -> int:
    print('%s: error: %s' % (PROG, message), file=sys.stderr)
    return 2


@dataclasses.dataclass
class Outcome:
    """What one scenario gave: its verdicts, or the reason its run failed."""
    scenario: Any
    verdicts: list
    error: str = ''
    wall_s: float = 0.0
    trace: Any = None

    @property
    def passed(self) -> bool:
        return not self.error and all(v.passed for v in self.verdicts)


# -- ROS domains for rig scenarios --------------------------------------------
def _domain_range() -> list[int]:
    text = os.environ.get('STEWART63_SCENARIO_DOMAINS', '1-100')
    match = re.fullmatch(r'\s*(\d+)\s*(?:-\s*(\d+))?\s*', text)
    if not match:
        raise ValueError('STEWART63_SCENARIO_DOMAINS: expected LO-HI or one id, got %r' % text)
    lo = int(match.group(1))
    hi = int(match.group(2) or lo)
    return list(range(lo, hi + 1))


@contextlib.contextmanager
def leased_domain(fixed: int | None = None, wait: float = 120.0):
    """A ROS domain id no other process on this machine holds while the block
    runs (``fixed``: that id, unleased: the caller vouches for it)."""
    if fixed is not None:
        yield fixed
        return
    ids = _domain_range()
    deadline = time.monotonic() + wait
    start = (os.getpid() * 7) % len(ids)
    while True:
        for k in range(len(ids)):
            domain = ids[(start + k) % len(ids)]
            fd = try_lock_domain(domain)
            if fd is None:
                continue
            try:
                yield domain
            finally:
                os.close(fd)
            return
        if time.monotonic() > deadline:
            raise RuntimeError('no free ROS domain id in %s' % ids)
        time.sleep(0.5)


# -- a rig scenario --------------------------------------------------------------
def write_parameter_file(scenario, path: Path) -> None:
    """The scenario's parameter file: its ``params_file`` with each override set in
    every section that has the key (the wildcard section when none has it)."""
    import yaml  # lazy: yaml costs 76 ms; --help answers without it
    doc = yaml.safe_load(Path(scenario.params_file).read_text())
    sections = [s['ros__parameters'] for s in doc.values()
                if isinstance(s, dict) and isinstance(s.get('ros__parameters'), dict)]
    wildcard = next((doc[k]['ros__parameters'] for k in doc if str(k).strip() in ('/**', '**')),
                    sections[0])
    for key, value in scenario.params.items():
        for section in [s for s in sections if key in s] or [wildcard]:
            section[key] = value
    path.write_text(yaml.safe_dump(doc, sort_keys=False))


def trace_from_rig(scenario, bag: Path, summary: dict, trips: list | None = None):
    """The ``Trace`` of a rig run from its bag (ground truth, leg_lengths,
    leg_forces), the plant's summary and the supervisor's trips (its summary's
    ``trips``: cause, sample, latency_samples, detail)."""
    # lazy: numpy and the core cost 692 ms; only a rig run needs them
    import numpy as np

    from stewart63_ros.bagio import header_stamp_ns, read_messages
    from stewart63_ros.core.analysis.sweep import leg_lengths_of_states
    from stewart63_ros.core.mechanics.dynamics import Dynamics
    from stewart63_ros.core.scenarios.running import (
        build_controller,
        build_plant,
        reference_lengths,
    )
    from stewart63_ros.core.scenarios.scenario import Trace, TripRecord
    lengths_msgs, poses, forces = {}, {}, {}
    for topic, _, msg in read_messages(bag, ['leg_lengths', 'leg_forces', 'ground_truth/pose']):
        stamp = header_stamp_ns(msg)
        if topic.endswith('ground_truth/pose'):
            p, q = msg.pose.position, msg.pose.orientation
            poses[stamp] = (p.x, p.y, p.z, q.x, q.y, q.z, q.w)
        elif topic.endswith('leg_lengths'):
            lengths_msgs[stamp] = np.asarray(msg.position, float)
        else:
            forces[stamp] = np.asarray(msg.effort, float)
    stamps = sorted(s for s in lengths_msgs if s in poses)
    if not stamps:
        raise RuntimeError('the bag %s has no sample with both leg_lengths and '
                           'ground_truth/pose' % bag)
    plant = build_plant(scenario)
    mech = plant.mechanism
    dyn = Dynamics(mech)
    states = np.zeros((len(stamps), 13))
    states[:, :7] = [poses[s] for s in stamps]
    lengths = leg_lengths_of_states(dyn.base_points, dyn.leg_points, states)
    held = np.zeros(6)          # the plant holds zero until the first answer
    rows = np.empty((len(stamps), 6))
    withheld = np.zeros(len(stamps), bool)
    for k, s in enumerate(stamps):
        if s in forces:
            held = forces[s]
        elif np.all(np.isfinite(lengths_msgs[s])):
            withheld[k] = True
        rows[k] = held
    # Sample k's stamp is k periods after the first: k / rate, as sim's times.
    rate = float(summary.get('rate_hz') or 0.0)
    times = (np.array(stamps, dtype=np.int64) - stamps[0]) * 1e-9
    if rate > 0:
        times = np.round(times * rate) / rate
    _, reference = build_controller(scenario)
    expected = int(summary.get('samples', len(stamps)))
    lost = sum(int(v) for v in (summary.get('skipped') or {}).values())
    lost += max(0, expected - len(lengths_msgs))
    missed = int(summary.get('missed_cycles', 0)) + int(summary.get('force_timeouts', 0))
    if rate <= 0:
        rate = float(plant.setting('sensor_rate'))
    records = tuple(TripRecord(t['cause'], int(t['sample']), t.get('latency_samples'),
                               t.get('detail', '')) for t in trips or ())
    return Trace(times, lengths, reference_lengths(scenario, reference, times), rows, withheld,
                 (mech.leg_length_min, mech.leg_length_max), missed, lost,
                 rate, records)


def _stop_group(proc: subprocess.Popen) -> None:
    """SIGINT to the rig's process group (it stops its nodes), then SIGKILL."""
    for sig, wait in ((signal.SIGINT, 20.0), (signal.SIGKILL, 5.0)):
        if proc.poll() is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, sig)
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(wait)


def rig_reference(reference: str, workdir: Path) -> str:
    """The reference CSV ``rig --reference`` takes: the scenario's, or a topic
    file's poses written as one (a trajectory with velocities is refused when
    the scenario is read)."""
    if not os.path.isdir(reference):
        return reference
    # lazy: bagio costs 197 ms; only a rig run needs it
    from stewart63_ros.bagruns import reference_points_from_bag
    from stewart63_ros.core.controllers.reference_files import write_reference_csv
    points = reference_points_from_bag(reference)
    path = workdir / 'reference.csv'
    write_reference_csv(path, points['times'], points['poses'])
    return str(path)


def run_rig(scenario, workdir: Path, domain: int | None = None):
    """Run a scenario with ``rig --mode lockstep|realtime`` on a leased ROS domain.

    ``domain``: run on that id instead of a leased one. Returns its
    ``Trace``; RuntimeError when the rig fails (its log's tail)."""
    params = workdir / 'params.yaml'
    write_parameter_file(scenario, params)
    bag, logs = workdir / 'bag', workdir / 'logs'
    cmd = [sys.executable, '-m', 'stewart63_ros.tools.rig', '--params', str(params),
           '--mode', scenario.run, '--duration', repr(scenario.duration),
           '--record', str(bag), '--log-dir', str(logs),
           # no fk: the verdicts read the plant's ground truth, not its pose
           '--nodes', 'plant,controller']
    if scenario.control_law:
        cmd += ['--control-law', scenario.control_law]
    if scenario.reference:
        cmd += ['--reference', rig_reference(scenario.reference, workdir)]
    for fault in scenario.faults:
        cmd += ['--fault', fault]
    if scenario.supervised:
        cmd += ['--supervisor']
    if scenario.bus:
        cmd += ['--bus', scenario.bus]
    bound = RIG_START_BOUND + 60.0 * scenario.duration
    with leased_domain(domain) as domain:
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1',
                   ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
        env.pop('ROS_LOCALHOST_ONLY', None)
        with open(workdir / 'rig.log', 'w') as log:
            proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env,
                                    start_new_session=True)
            try:
                code = proc.wait(bound)
            except subprocess.TimeoutExpired:
                code = None
            finally:
                _stop_group(proc)
    tail = ' | '.join((workdir / 'rig.log').read_text().strip().splitlines()[-3:])
    if code is None:
        raise RuntimeError('the rig did not finish within %.0f s: %s' % (bound, tail))
    summary_path = logs / 'plant_summary.json'
    if code != 0 or not summary_path.exists():
        raise RuntimeError('the rig failed (exit %s): %s' % (code, tail))
    trips = None
    if scenario.supervised:
        supervisor = logs / 'supervisor_summary.json'
        if not supervisor.exists():
            raise RuntimeError('the rig wrote no supervisor summary: %s' % tail)
        trips = json.loads(supervisor.read_text()).get('trips') or []
    return trace_from_rig(scenario, bag, json.loads(summary_path.read_text()), trips)


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


# -- outputs --------------------------------------------------------------------
def failure_message(outcome: Outcome) -> str:
    """One line: which bounds failed and by how much (or why the run failed)."""
    if outcome.error:
        return 'the run failed: %s' % outcome.error
    return '; '.join(v.text() for v in outcome.verdicts if not v.passed)


def write_junit(outcomes: Sequence[Outcome], path: Path, suite: str = 'scenarios') -> None:
    """JUnit XML (the schema Jenkins, GitLab and GitHub's test reporters read):
    one ``testsuite`` per scenario file, one ``testcase`` per scenario; a
    failed expectation is a ``failure`` naming the bound, the measured value and
    by how much; a run that failed is an ``error``."""
    root = ET.Element('testsuites', name=suite)
    by_file: dict[str, list[Outcome]] = {}
    for o in outcomes:
        by_file.setdefault(o.scenario.source or suite, []).append(o)
    totals = [0, 0, 0, 0.0]
    for source, items in by_file.items():
        failures = sum(1 for o in items if not o.error and not o.passed)
        errors = sum(1 for o in items if o.error)
        wall = sum(o.wall_s for o in items)
        element = ET.SubElement(root, 'testsuite', name=Path(source).stem, tests=str(len(items)),
                                failures=str(failures), errors=str(errors), skipped='0',
                                time='%.3f' % wall,
                                timestamp=time.strftime('%Y-%m-%dT%H:%M:%S'),
                                hostname=os.uname().nodename)
        for o in items:
            case = ET.SubElement(element, 'testcase', name=o.scenario.name,
                                 classname='scenario.%s.%s' % (Path(source).stem, o.scenario.run),
                                 time='%.3f' % o.wall_s)
            if o.error:
                ET.SubElement(case, 'error', message=failure_message(o),
                              type='RunFailed').text = o.error
            elif not o.passed:
                ET.SubElement(case, 'failure', message=failure_message(o),
                              type='ExpectationFailed').text = '\n'.join(
                                  v.text() for v in o.verdicts if not v.passed)
            ET.SubElement(case, 'system-out').text = '\n'.join(v.text() for v in o.verdicts)
        totals = [totals[0] + len(items), totals[1] + failures, totals[2] + errors,
                  totals[3] + wall]
    root.set('tests', str(totals[0]))
    root.set('failures', str(totals[1]))
    root.set('errors', str(totals[2]))
    root.set('time', '%.3f' % totals[3])
    ET.indent(root)
    path.parent.mkdir(parents=True, exist_ok=True)
    ET.ElementTree(root).write(path, encoding='utf-8', xml_declaration=True)


def _slug(name: str) -> str:
    return re.sub(r'[^A-Za-z0-9_.=,-]+', '_', name).strip('_') or 'scenario'


#: Metrics drawn on the leg-error axes (in mm) or the force axes (N), with a bound line.
_ERROR_AXES = {'tracking_error_max_m': 1e3, 'tracking_error_rms_m': 1e3}


def draw_outcome(outcome: Outcome, path: Path) -> Path:
    """The scenario's figure: the largest leg error and the largest |F| against
    time; each expectation's window a band along the top (red when it failed), a failed
    bound drawn as a dashed line where it has the axes' unit, and the time it
    failed as a vertical line."""
    import matplotlib  # lazy: matplotlib costs 425 ms; only --plot needs it
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt  # lazy: pyplot costs 794 ms; only --plot needs it
    import numpy as np  # lazy: numpy costs 50 ms; --help answers without it
    trace = outcome.trace
    fig, (ax_e, ax_f) = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    t = trace.times
    ax_e.plot(t, 1e3 * np.abs(trace.lengths - trace.reference).max(axis=1), color='#4c72b0',
              lw=1)
    ax_e.set_ylabel('max |L - L_ref| [mm]')
    ax_e.set_yscale('symlog', linthresh=1e-3)
    ax_f.plot(t, np.abs(trace.forces).max(axis=1), color='#55a868', lw=1)
    ax_f.set_ylabel('max |F| [N]')
    ax_f.set_xlabel('t [s]')
    # Each expectation's window: a band of its own along the top of its axes.
    bands = {ax_e: 0, ax_f: 0}
    for v in outcome.verdicts:
        exp = v.expectation
        ax = ax_f if exp.metric == 'max_force' else ax_e
        color = '#c0392b' if not v.passed else '#999999'
        top = 1.0 - 0.05 * bands[ax]
        bands[ax] += 1
        ax.axvspan(*v.window, ymin=top - 0.04, ymax=top, color=color, alpha=0.6, lw=0)
        if not v.passed:
            if exp.metric == 'max_force':
                ax.axhline(exp.limit, color=color, ls='--', lw=1, label='%s %s %g N' % (
                    exp.metric, exp.kind, exp.limit))
            elif exp.metric in _ERROR_AXES:
                ax.axhline(exp.limit * _ERROR_AXES[exp.metric], color=color, ls='--', lw=1,
                           label='%s %s %g m' % (exp.metric, exp.kind, exp.limit))
            if v.at_s is not None:
                ax.axvline(v.at_s, color=color, lw=1,
                           label='%s fails at %.3f s' % (exp.metric, v.at_s))
    for trip in trace.trips[:1]:        # the latched trip (later ones are not drawn)
        for ax in (ax_e, ax_f):
            ax.axvline(trip.sample / trace.rate, color='#8e44ad', ls=':', lw=1.2,
                       label='supervisor trip: %s' % trip.cause if ax is ax_e else None)
    for ax in (ax_e, ax_f):
        ax.grid(True, alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7, loc='upper right')
    fig.suptitle('%s (%s): %s' % (outcome.scenario.name, outcome.scenario.run,
                                  'pass' if outcome.passed else 'FAIL'), fontsize=10)
    # Fixed margins: tight_layout drew the figure twice, a third of its cost
    # (0.26 s of CPU a figure with it, 0.17 s without; the suite draws dozens).
    fig.subplots_adjust(left=0.1, right=0.97, top=0.92, bottom=0.1, hspace=0.1)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _draw(item: tuple) -> Path:
    return draw_outcome(*item)


def draw_all(drawings: Sequence[tuple], jobs: int = 1) -> None:
    """Draw (outcome, path) figures, on ``jobs`` forked processes when > 1:
    a figure costs about 0.3 s of matplotlib, the package's suite has 30."""
    if jobs <= 1 or len(drawings) < 2:
        for item in drawings:
            _draw(item)
        return
    import matplotlib  # lazy: matplotlib costs 425 ms; only figures need it
    matplotlib.use('Agg')
    # lazy: pyplot costs 794 ms: loaded once here, before the fork, not once per process
    import matplotlib.pyplot  # noqa: F401
    context = multiprocessing.get_context('fork')
    with concurrent.futures.ProcessPoolExecutor(max_workers=jobs, mp_context=context) as pool:
        list(pool.map(_draw, drawings, chunksize=max(1, len(drawings) // (4 * jobs))))


def write_report(outcomes: Sequence[Outcome], out: Path, figures: bool = True,
                 jobs: int = 1) -> Path:
    """DIR/report.md: a table of scenarios, then per scenario its verdicts and
    figure (drawn on ``jobs`` processes)."""
    out.mkdir(parents=True, exist_ok=True)
    drawings = []
    passed = sum(o.passed for o in outcomes)
    lines = ['# Scenario report', '',
             '%d of %d scenarios pass.' % (passed, len(outcomes)), '',
             '| scenario | run | result | wall [s] |', '|---|---|---|---|']
    for o in outcomes:
        lines.append('| %s | %s | %s | %.2f |' % (o.scenario.name, o.scenario.run,
                                                  'pass' if o.passed else
                                                  ('**error**' if o.error else '**FAIL**'),
                                                  o.wall_s))
    for o in outcomes:
        lines += ['', '## %s' % o.scenario.name, '']
        if o.scenario.description:
            lines += [o.scenario.description.strip(), '']
        if o.error:
            lines += ['The run failed: %s' % o.error, '']
        lines += ['| metric | bound | measured | window [s] | verdict |', '|---|---|---|---|---|']
        for v in o.verdicts:
            exp = v.expectation
            verdict = 'pass' if v.passed else '**FAIL**' + (
                ' at %.4f s' % v.at_s if v.at_s is not None else '')
            if v.why:
                verdict += ': ' + v.why
            lines.append('| %s | %s | %s | %g-%g | %s |' % (
                exp.metric, v.bound_text(), v.measured_text(), *v.window, verdict))
        if figures and o.trace is not None:
            fig_dir = out / 'figures'
            fig_dir.mkdir(exist_ok=True)
            name = '%s.png' % _slug(o.scenario.name)
            drawings.append((o, fig_dir / name))
            lines += ['', '![%s](figures/%s)' % (o.scenario.name, name)]
    draw_all(drawings, jobs)
    path = out / 'report.md'
    path.write_text('\n'.join(lines) + '\n')
    return path


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
        _domain_range()
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
