"""`colcon build` of the package (README), in a temporary workspace.

The package files are copied into ``<tmp>/src/stewart63_ros``; build, install
and log directories are all under ``<tmp>``, so the checkout is left as it was.
colcon is the one in this venv (``colcon-core``, ``colcon-ros``), or on PATH.

Checks: colcon identifies the package as ``ros.ament_python`` (a
``package.xml`` that catkin_pkg rejects silently turns it into a plain Python
package, which ``ros2 run`` cannot find); the install has every executable in
``lib/stewart63_ros``, the package.xml, the ament index marker and the
parameter file in ``share``; each installed executable's ``--help`` works with
the install's Python path, and the installed package (not the checkout) is the
one imported.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow      # a colcon build in processes
PACKAGE = 'stewart63_ros'
EXECUTABLES = ('plant', 'controller', 'fk', 'record', 'play', 'rig', 'sim', 'plot', 'analyze',
               'sweep', 'supervisor')
PACKAGE_FILES = ('package.xml', 'setup.py', 'setup.cfg', 'README.md')
PACKAGE_DIRS = ('resource', 'stewart63_ros', 'config', 'launch')
PY = 'python%d.%d' % sys.version_info[:2]
BUILD_TIMEOUT = 300


def colcon_command():
    venv = Path(sys.executable).parent / 'colcon'
    if venv.exists():
        return [str(venv)]
    found = shutil.which('colcon')
    if found:
        return [found]
    pytest.skip('colcon is not installed (pip install colcon-core colcon-ros '
                'colcon-package-information)')


def run(cmd, cwd, timeout, env=None):
    return subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=timeout, stdin=subprocess.DEVNULL)


def describe(proc) -> str:
    return 'exit %s\n--- stdout ---\n%s\n--- stderr ---\n%s' % (
        proc.returncode, proc.stdout[-4000:], proc.stderr[-4000:])


@pytest.fixture(scope='module')
def workspace(tmp_path_factory):
    """A colcon workspace with the package copied in, built once."""
    colcon = colcon_command()
    before = {name: (REPO / name).exists() for name in ('build', 'install', 'log')}
    ws = tmp_path_factory.mktemp('colcon_ws')
    src = ws / 'src' / PACKAGE
    src.mkdir(parents=True)
    for name in PACKAGE_FILES:
        if (REPO / name).exists():
            shutil.copy2(REPO / name, src / name)
    ignore = shutil.ignore_patterns('__pycache__', '*.pyc', '*.egg-info')
    for name in PACKAGE_DIRS:
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, src / name, ignore=ignore)
    env = dict(os.environ)
    env.pop('PYTHONPATH', None)
    listing = run(colcon + ['--log-base', ws / 'log', 'list', '--base-paths', ws / 'src'],
                  ws, 120, env)
    info = run(colcon + ['--log-base', ws / 'log', 'info', '--base-paths', ws / 'src'],
               ws, 120, env)
    build = run(colcon + ['--log-base', ws / 'log', 'build', '--base-paths', ws / 'src',
                          '--build-base', ws / 'build', '--install-base', ws / 'install',
                          '--event-handlers', 'console_direct+'],
                ws, BUILD_TIMEOUT, env)
    after = {name: (REPO / name).exists() for name in ('build', 'install', 'log')}
    return {'ws': ws, 'list': listing, 'info': info, 'build': build,
            'prefix': ws / 'install' / PACKAGE, 'repo_before': before, 'repo_after': after}


def installed_env(workspace) -> dict:
    """What sourcing the install's setup script sets for this package: its
    site-packages first on PYTHONPATH (the venv stays the interpreter) and its
    prefix on AMENT_PREFIX_PATH."""
    prefix = workspace['prefix']
    env = dict(os.environ)
    site = prefix / 'lib' / PY / 'site-packages'
    env['PYTHONPATH'] = os.pathsep.join([str(site)] + [
        p for p in os.environ.get('PYTHONPATH', '').split(os.pathsep) if p])
    env['AMENT_PREFIX_PATH'] = os.pathsep.join([str(prefix)] + [
        p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p])
    env['PYTHONDONTWRITEBYTECODE'] = '1'
    env.pop('ROS_DOMAIN_ID', None)
    return env


def test_colcon_identifies_an_ament_python_package(workspace):
    listing, info = workspace['list'], workspace['info']
    assert listing.returncode == 0, describe(listing)
    lines = [line.split() for line in listing.stdout.splitlines() if line.strip()]
    assert [line[0] for line in lines] == [PACKAGE], listing.stdout
    assert lines[0][-1] == '(ros.ament_python)', (
        'colcon did not take package.xml (catkin_pkg rejected it?): ' + listing.stdout
        + listing.stderr)
    assert info.returncode == 0, describe(info)
    assert 'type: ros.ament_python' in info.stdout, info.stdout


def test_colcon_build_succeeds_outside_the_checkout(workspace):
    build = workspace['build']
    assert build.returncode == 0, describe(build)
    assert 'Finished <<< %s' % PACKAGE in build.stdout + build.stderr, describe(build)
    # Nothing appeared in the checkout (a `colcon build` there would leave these).
    for name, existed in workspace['repo_before'].items():
        if not existed:
            assert not workspace['repo_after'][name], '%s/ appeared in the checkout' % name


def test_install_layout(workspace):
    assert workspace['build'].returncode == 0, describe(workspace['build'])
    prefix = workspace['prefix']
    for exe in EXECUTABLES:
        path = prefix / 'lib' / PACKAGE / exe
        assert path.is_file(), 'missing %s' % path
        assert os.access(path, os.X_OK), '%s is not executable' % path
    share = prefix / 'share'
    assert (share / PACKAGE / 'package.xml').read_text() == (REPO / 'package.xml').read_text()
    assert (share / 'ament_index' / 'resource_index' / 'packages' / PACKAGE).is_file()
    for name in ('stewart63.yaml', 'hexapod66.yaml'):    # the packaged 6-3 and 6-6
        config = share / PACKAGE / 'config' / name
        assert config.read_text() == (REPO / 'config' / name).read_text()
    assert (prefix / 'lib' / PY / 'site-packages' / PACKAGE / '__init__.py').is_file()
    for launch in sorted((REPO / 'launch').glob('*.launch.py')):
        assert (share / PACKAGE / 'launch' / launch.name).is_file(), launch.name


def test_installed_package_is_the_one_imported(workspace):
    assert workspace['build'].returncode == 0, describe(workspace['build'])
    prefix = workspace['prefix']
    probe = ('import stewart63_ros, sys\n'
             'from ament_index_python.packages import get_package_prefix\n'
             'from stewart63_ros.core.plumbing.params import default_params_path, load_mechanism\n'
             'print(stewart63_ros.__file__)\n'
             'print(get_package_prefix("stewart63_ros"))\n'
             'print(default_params_path())\n'
             'load_mechanism(default_params_path())\n')
    proc = run([sys.executable, '-c', probe], workspace['ws'], 120, installed_env(workspace))
    assert proc.returncode == 0, describe(proc)
    module, pkg_prefix, params = proc.stdout.splitlines()[:3]
    assert Path(module).resolve().is_relative_to(prefix.resolve()), module
    assert Path(pkg_prefix).resolve() == prefix.resolve()
    assert Path(params).resolve() == (prefix / 'share' / PACKAGE / 'config' /
                                      'stewart63.yaml').resolve()


def test_installed_executables_print_help(workspace):
    """Like ``ros2 run stewart63_ros <exe> --help``: the executable from
    <prefix>/lib/stewart63_ros, run with the install's environment."""
    assert workspace['build'].returncode == 0, describe(workspace['build'])
    env = installed_env(workspace)
    libexec = workspace['prefix'] / 'lib' / PACKAGE
    procs = {}
    for exe in EXECUTABLES:     # in parallel: each pays for importing rclpy
        procs[exe] = subprocess.Popen([str(libexec / exe), '--help'], cwd=workspace['ws'],
                                      env=env, stdin=subprocess.DEVNULL,
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                      text=True)
    failures = []
    for exe, proc in procs.items():
        try:
            out, err = proc.communicate(timeout=180)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
            failures.append('%s --help timed out' % exe)
            continue
        if proc.returncode != 0 or not out.lstrip().startswith('usage: %s' % exe):
            failures.append('%s --help: exit %s\n%s\n%s' % (exe, proc.returncode, out[-1500:],
                                                           err[-1500:]))
    assert not failures, '\n\n'.join(failures)
