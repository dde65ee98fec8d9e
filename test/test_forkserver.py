"""The fork server ``rig`` starts its processes from (runtime/forkserver.py):
a fork must behave as ``python -m module`` would, and the server must have
loaded what the nodes import, or it saves nothing."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from stewart63_ros.paths import default_params_path
from stewart63_ros.runtime import forkserver
from stewart63_ros.tools.rig_process import MODULES

PARAMS = default_params_path()

pytestmark = pytest.mark.slow

CHILD = textwrap.dedent('''
    import os, sys, time
    def main():
        print('argv', sys.argv[1:], 'cwd', os.getcwd(), 'env', os.environ.get('FS_TEST'),
              flush=True)
        what = sys.argv[1]
        if what == 'return':
            return 4                  # as `sys.exit(main())` would
        if what == 'exit':
            sys.exit(3)
        if what == 'raise':
            raise ValueError('boom')
        if what == 'wait':
            print('waiting', flush=True)
            time.sleep(60)
    if __name__ == '__main__':
        sys.exit(main())
''')


@pytest.fixture
def server(tmp_path, monkeypatch):
    (tmp_path / 'fs_child.py').write_text(CHILD)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv('FS_TEST', 'from the request')
    started = forkserver.ForkServer()
    yield started
    started.close()
    assert started.proc.wait(30) == 0


def test_a_fork_exits_as_python_m_would(server, tmp_path):
    codes = {}
    for what in ('return', 'exit', 'raise', 'none'):
        log = tmp_path / ('%s.log' % what)
        proc = server.spawn('fs_child', [what], log)
        codes[what] = proc.wait(60)
        text = log.read_text()
        assert "argv ['%s'] cwd %s env from the request" % (what, tmp_path) in text, text
        if what == 'raise':
            assert 'ValueError: boom' in text and 'Traceback' in text, text
    assert codes == {'return': 4, 'exit': 3, 'raise': 1, 'none': 0}


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_a_signalled_fork_ends_as_python_m_would(server, tmp_path, sig):
    """SIGINT: KeyboardInterrupt, then killed by SIGINT (the rig counts that
    as stopped as asked); SIGTERM: killed. Each in its own process group."""
    log = tmp_path / 'wait.log'
    proc = server.spawn('fs_child', ['wait'], log)
    deadline = time.monotonic() + 60
    while 'waiting' not in log.read_text():
        assert time.monotonic() < deadline and proc.poll() is None, log.read_text()
        time.sleep(0.02)
    assert os.getpgid(proc.pid) == proc.pid     # setsid: a terminal's Ctrl-C is rig's
    with pytest.raises(subprocess.TimeoutExpired):
        proc.wait(0.1)
    proc.send_signal(sig)
    assert proc.wait(30) == -sig


def test_the_server_ends_once_closed_and_its_children_have_ended(server, tmp_path):
    proc = server.spawn('fs_child', ['wait'], tmp_path / 'wait.log')
    server.close()
    time.sleep(0.3)
    assert server.proc.poll() is None       # still reaping its child
    proc.terminate()
    assert proc.wait(30) == -signal.SIGTERM
    assert server.proc.wait(30) == 0


def test_the_server_preloads_every_core_module_a_node_imports():
    """What a node imports of the core beyond ``PRELOAD`` it loads itself in
    each process: each module listed here was missed. (One interpreter: the
    server's preload, then every node module rig forks.)"""
    nodes = [module for name, module in MODULES.items() if name not in ('record', 'view')]
    script = textwrap.dedent('''
        import importlib, json, sys
        from stewart63_ros.runtime import forkserver
        core = lambda: {m for m in sys.modules if m.startswith('stewart63_ros.core')}
        forkserver.preload()
        assert 'rclpy' not in sys.modules, 'rclpy in the server'
        preloaded = core()
        for module in sys.argv[1:]:
            importlib.import_module(module)
        print(json.dumps(sorted(core() - preloaded)))
    ''')
    done = subprocess.run([sys.executable, '-c', script] + nodes, capture_output=True,
                          text=True)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == []


def test_a_bad_switch_is_refused_and_zero_starts_python_m(monkeypatch):
    monkeypatch.setenv(forkserver.ENV_SWITCH, 'yes')
    with pytest.raises(ValueError, match='must be 0 or 1'):
        forkserver.fork_server_wanted()
    monkeypatch.setenv(forkserver.ENV_SWITCH, '0')
    assert forkserver.fork_server_wanted() is False
    monkeypatch.delenv(forkserver.ENV_SWITCH)
    assert forkserver.fork_server_wanted() is True


def test_rig_refuses_a_bad_switch_before_it_starts_anything(tmp_path):
    env = dict(os.environ, **{forkserver.ENV_SWITCH: 'yes'})
    done = subprocess.run([sys.executable, '-m', 'stewart63_ros.tools.rig', '--duration', '0.1',
                           '--log-dir', str(tmp_path / 'logs')], env=env, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 2, done
    assert 'STEWART63_FORK_SERVER must be 0 or 1' in done.stderr, done.stderr
    assert not (tmp_path / 'logs').exists()


def test_a_node_never_reads_half_of_the_rigs_parameter_file(tmp_path):
    """rig writes its overlay again for each process it starts, and a fork
    reads it at once: a reader must find the whole file every time (a
    controller read it truncated in 5-10 % of 1000 stress runs)."""
    import threading

    import yaml

    from stewart63_ros.tools.rig_process import Rig
    rig = Rig(PARAMS, duration=1.0, log_dir=tmp_path / 'rig')
    whole = yaml.safe_load(rig.overlay().read_text())
    done = threading.Event()

    def write():
        for _ in range(300):
            rig.overlay()
        done.set()

    writer = threading.Thread(target=write)
    writer.start()
    reads = 0
    try:
        while not done.is_set():
            assert yaml.safe_load((tmp_path / 'rig' / 'rig_params.yaml').read_text()) == whole
            reads += 1
    finally:
        writer.join()
    assert reads > 10
