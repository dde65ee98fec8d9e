"""What ``scenario run`` leaves: each scenario's ``Outcome``, a failure's one
line, the JUnit XML that CI servers read, and DIR/report.md with one figure
per scenario.
"""
from __future__ import annotations

import concurrent.futures
import dataclasses
import multiprocessing
import os
import re
import time
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from pathlib import Path
from typing import Any


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
