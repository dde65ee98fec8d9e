"""Shared fixtures. Keep this small: helpers that only one test file needs live there.

pytest puts this folder on ``sys.path`` (rootdir conftest, prepend import
mode), so test modules import ``ros_harness`` and ``stream_publisher`` directly.
"""
from pathlib import Path

import pytest
from ros_harness import ros  # noqa: F401  (the DDS fixture: a domain id, child processes)

REPO = Path(__file__).resolve().parents[1]


def pytest_collection_modifyitems(items):
    """Every test on DDS (it uses the ``ros`` fixture, directly or through
    another fixture) is marked ``dds`` and ``slow``: ``make test-fast`` leaves
    it out. Tests that spawn processes without DDS carry ``slow`` themselves.

    The slow tests run first, in file order: with ``-n 2`` the quick ones then
    fill the workers' last minutes, instead of a long rig test starting when
    the other worker has nothing left (the suite's wall time)."""
    for item in items:
        if 'ros' in item.fixturenames:
            item.add_marker(pytest.mark.dds)
            item.add_marker(pytest.mark.slow)
    items.sort(key=lambda item: item.get_closest_marker('slow') is None)


@pytest.fixture(scope='session', autouse=True)
def one_fork_server_per_worker():
    """The rigs a test starts in its own process fork from one server per
    worker (runtime/forkserver.py): the core is loaded once, not once a rig."""
    from stewart63_ros.runtime.forkserver import share_servers
    share_servers()


@pytest.fixture(scope='session')
def default_params_file() -> Path:
    """The packaged parameter file, read from the checkout."""
    return REPO / 'config' / 'stewart63.yaml'


@pytest.fixture(scope='session')
def default_mech(default_params_file):
    """The default mechanism (validated)."""
    from stewart63_ros.core.plumbing.params import load_mechanism
    return load_mechanism(default_params_file)


@pytest.fixture(scope='session')
def default_setup(default_params_file):
    """The default setup (validated): machine, gains, task, settings."""
    from stewart63_ros.core.plumbing.params import load_setup
    return load_setup(default_params_file)


@pytest.fixture(scope='module')
def setup(default_setup):
    """The default setup by its short name (a test file may define its own)."""
    return default_setup


@pytest.fixture(scope='module')
def mech(default_mech):
    """The default mechanism by its short name (a test file may define its own)."""
    return default_mech


@pytest.fixture(scope='module')
def dyn(mech):
    """The dynamics of ``mech`` (eq. 38), one per test module."""
    from stewart63_ros.core.mechanics.dynamics import Dynamics
    return Dynamics(mech)
