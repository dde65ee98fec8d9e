"""pytest plugin: a lab's own tests run scenarios (docs/scenarios.md).

Installed with the package (entry point ``pytest11``), so in a lab's
repository, with this package installed, a test file needs no import:

    def test_my_controller(run_scenarios):
        run_scenarios('scenarios/my_law.yaml')          # fails with the verdicts

    def test_built_in_python(run_scenarios):
        outcomes = run_scenarios({'name': 'mine', 'duration': 5.0,
                                  'control_law': 'my_lab.laws:Mine',
                                  'expect': {'final_error_percent': {'max': 1.0}}},
                                 check=False)
        assert outcomes[0].verdicts[0].value < 0.5

``run_scenarios(source, jobs=1, check=True)``: ``source`` a scenario file, a
list of files, a scenario as a dict (``matrix:`` allowed) or a list of
dicts (paths relative to the test's directory). It returns the outcomes
(``scenario``, ``verdicts`` with ``value``, ``passed``, ``at_s``; ``error``)
and, with ``check``, fails the test with every failed verdict's line.
``--scenario-junit F`` writes the outcomes of the session's calls as JUnit
XML too (as ``scenario run --junit``).
"""
from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import pytest


def pytest_addoption(parser: Any) -> None:
    """``--scenario-junit F``: the scenarios the session ran, as JUnit XML."""
    group = parser.getgroup('stewart63_ros scenarios')
    group.addoption('--scenario-junit', default=None, metavar='F',
                    help='write the scenarios run_scenarios ran as JUnit XML')


def load(source: Any, base: str | os.PathLike) -> list:
    """The scenarios of ``source`` (file(s) or dict(s)), checked.

    Args:
        source: a path, a dict, or a list of either.
        base: the folder relative paths start from.

    Returns:
        The ``Scenario`` objects, matrices expanded.

    Raises:
        ScenarioError: a bad scenario (its key named).
    """
    # lazy: core.scenarios costs 129 ms; pytest loads this plugin always
    from stewart63_ros.core.scenarios.parsing import load_scenarios, scenarios_from_dict
    items = source if isinstance(source, (list, tuple)) else [source]
    out = []
    for item in items:
        if isinstance(item, Mapping):
            out.extend(scenarios_from_dict(item, base))
        else:
            path = Path(item)
            out.extend(load_scenarios(path if path.is_absolute() else Path(base) / path))
    return out


_SESSION_OUTCOMES: list = []


@pytest.fixture
def run_scenarios(request: Any) -> Callable[..., list]:
    """A function that runs scenarios and, by default, fails the test on a failed verdict."""
    # lazy: tools.scenario costs 139 ms; pytest loads this plugin always
    from stewart63_ros.core.scenarios.scenario import ScenarioError
    from stewart63_ros.tools.scenario import run_all
    from stewart63_ros.tools.scenario_report import failure_message
    base = Path(str(request.node.fspath)).parent

    def run(source: Any, jobs: int = 1, check: bool = True) -> Sequence:
        try:
            scenarios = load(source, base)
        except ScenarioError as exc:
            pytest.fail('bad scenario: %s' % exc, pytrace=False)
        outcomes = run_all(scenarios, jobs, keep_traces=False)
        _SESSION_OUTCOMES.extend(outcomes)
        failed = [o for o in outcomes if not o.passed]
        if check and failed:
            pytest.fail('\n'.join('%s: %s' % (o.scenario.name, failure_message(o))
                                  for o in failed), pytrace=False)
        return outcomes
    return run


def pytest_sessionfinish(session: Any) -> None:
    """Write ``--scenario-junit`` when asked."""
    path = session.config.getoption('--scenario-junit', default=None)
    if path and _SESSION_OUTCOMES:
        # lazy: tools.scenario costs 139 ms; pytest loads this plugin always
        from stewart63_ros.tools.scenario_report import write_junit
        write_junit(_SESSION_OUTCOMES, Path(path))
