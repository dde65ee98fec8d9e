"""Every node and ``rig`` stop cleanly on any number of SIGINT / SIGTERM.

A terminal's Ctrl-C under ``ros2 launch`` reaches each process twice (from
the terminal's process group and forwarded by launch), then launch sends
SIGTERM after its 5 s timeout. Here each of plant, controller, fk and record
(and a whole ``rig``, recording) gets SIGINT twice 50 ms apart, or SIGINT then
SIGTERM: exit 0, no traceback, within 5 s; the plant writes its summary; the
rig prints its summary and its bag holds every message the nodes published.
"""
from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import pytest
from ros_harness import PYTHON, wait_until

from stewart63_ros import bagio

REPO = Path(__file__).resolve().parents[1]
SEQUENCES = {'SIGINT-SIGINT': (signal.SIGINT, signal.SIGINT),
             'SIGINT-SIGTERM': (signal.SIGINT, signal.SIGTERM)}
STOP_WITHIN = 5.0       # s: launch's SIGTERM timeout


def exe(name):
    path = Path(PYTHON).parent / name
    return [str(path)] if path.exists() else [PYTHON, '-m', {
        'plant': 'stewart63_ros.nodes.plant', 'controller': 'stewart63_ros.nodes.controller',
        'fk': 'stewart63_ros.nodes.fk_node', 'record': 'stewart63_ros.tools.record',
        'rig': 'stewart63_ros.tools.rig'}[name]]


def _text(proc):
    return proc.stdout() + proc.stderr()


def send(proc, sequence):
    first, second = SEQUENCES[sequence]
    os.kill(proc.pid, first)
    time.sleep(0.05)
    if proc.returncode is None:
        os.kill(proc.pid, second)


@pytest.mark.parametrize('sequence', list(SEQUENCES))
def test_each_node_stops_cleanly_on_repeated_signals(ros, tmp_path, sequence):
    summary = tmp_path / 'plant_summary.json'
    ros_args = ['--ros-args', '-r', '__ns:=/stops']
    procs = {
        # realtime with nobody answering: the plant runs on its own
        'plant': ros.spawn(exe('plant') + ros_args + [
            '-p', 'clock_mode:=realtime', '-p', 'summary_file:=%s' % summary], name='plant'),
        'controller': ros.spawn(exe('controller') + ros_args, name='controller'),
        'fk': ros.spawn(exe('fk') + ros_args, name='fk'),
        'record': ros.spawn(exe('record') + [str(tmp_path / 'bag'), '--namespace', '/stops'],
                            name='record'),
    }
    ready = {'plant': 'realtime at', 'controller': 'matched after', 'fk': 'matched after',
             'record': 'READY'}
    for name, proc in procs.items():
        assert wait_until(lambda p=proc, n=name: ready[n] in _text(p) or p.returncode is not None,
                          120), proc.describe()
        assert proc.returncode is None, proc.describe()
    time.sleep(0.5)     # the plant in its loop, the others in theirs
    took, codes = {}, {}
    for name, proc in procs.items():
        t0 = time.monotonic()
        send(proc, sequence)
        codes[name] = proc.wait(STOP_WITHIN + 5)
        took[name] = time.monotonic() - t0
    for name, proc in procs.items():
        assert codes[name] == 0, proc.describe()
        assert took[name] < STOP_WITHIN, (name, took[name], proc.describe())
        assert 'Traceback' not in _text(proc), proc.describe()
        assert 'KeyboardInterrupt' not in _text(proc), proc.describe()
    # the plant's summary of the part it ran; the bag is complete and readable
    data = json.loads(summary.read_text())
    assert data['stopped_by_signal'] and data['samples'] > 100, data
    assert (tmp_path / 'bag' / 'metadata.yaml').exists()
    assert sum(1 for _ in bagio.read_messages(tmp_path / 'bag', ['/diagnostics'])) > 0
    print('\n%s: %s' % (sequence, ', '.join('%s exit %d in %.2f s' % (n, codes[n], took[n])
                                           for n in procs)))
    for proc in procs.values():     # each node's flush: confirmed by the recorder, or not
        print('  ' + ' | '.join(line for line in _text(proc).splitlines() if 'stopped (' in line))


@pytest.mark.parametrize('name', ['fk', 'record'])
def test_sigusr1_prints_where_a_process_is_and_it_runs_on(ros, tmp_path, name):
    """What ``rig`` (and the tests) send a process that ignored SIGINT before
    SIGTERM: its Python stacks go to its log, and it goes on running."""
    args = [str(tmp_path / 'bag'), '--namespace', '/usr1'] if name == 'record' else \
        ['--ros-args', '-r', '__ns:=/usr1']
    proc = ros.spawn(exe(name) + args, name=name)
    # fk: started its loop (no fixed settle: nothing to wait for here)
    ready = ('READY',) if name == 'record' else ('waiting', 'matched after')
    assert wait_until(lambda: any(r in _text(proc) for r in ready)
                      or proc.returncode is not None, 120), proc.describe()
    os.kill(proc.pid, signal.SIGUSR1)
    assert wait_until(lambda: 'most recent call first' in proc.stderr()
                      or proc.returncode is not None, 10), proc.describe()
    assert proc.returncode is None, proc.describe()
    assert 'File "' in proc.stderr(), proc.describe()
    os.kill(proc.pid, signal.SIGINT)
    assert proc.wait(STOP_WITHIN + 5) == 0, proc.describe()


def published_counts(bag) -> dict:
    """{topic: count} that the nodes say they published (their last status in the bag)."""
    last = {}
    for _, _, msg in bagio.read_messages(bag, ['/diagnostics']):
        for status in msg.status:
            last[status.name] = {kv.key[len('published/'):]: int(kv.value)
                                 for kv in status.values if kv.key.startswith('published/')}
    out = {}
    for counts in last.values():
        for topic, n in counts.items():
            if topic != '/diagnostics':
                out[topic] = out.get(topic, 0) + n
    return out


@pytest.mark.parametrize('sequence', list(SEQUENCES))
def test_rig_stops_cleanly_on_repeated_signals_and_loses_nothing(ros, tmp_path, sequence):
    log_dir, bag = tmp_path / 'logs', tmp_path / 'bag'
    proc = ros.spawn(exe('rig') + ['--mode', 'realtime', '--record', str(bag),
                                   '--log-dir', str(log_dir)], name='rig')
    plant_log = log_dir / 'plant.log'
    assert wait_until(lambda: proc.returncode is not None or (
        plant_log.exists() and 'realtime at' in plant_log.read_text()), 180), proc.describe()
    time.sleep(2.0)
    t0 = time.monotonic()
    send(proc, sequence)
    code = proc.wait(30)
    took = time.monotonic() - t0
    out = proc.stdout()
    assert code == 0, proc.describe()
    assert 'Traceback' not in _text(proc), proc.describe()
    for name in ('plant', 'controller', 'fk', 'record'):
        assert 'Traceback' not in (log_dir / ('%s.log' % name)).read_text(), name
    # the same summary as a timed run, for the part it ran
    assert 'stopped by SIGINT' in out, out
    for text in ('rig summary:', 'final positioning error', 'loop latency', 'missed cycles',
                 'controller: received', 'fk: received'):
        assert text in out, out
    published = published_counts(bag)
    for topic in ('leg_lengths', 'leg_forces', 'platform_pose'):
        n = sum(1 for _ in bagio.read_messages(bag, ['/' + topic]))
        assert published.get(topic) and n == published[topic], (topic, n, published)
    print('\nrig, %s: exit 0 in %.2f s (nodes flush, then the recorder); bag holds all %s'
          % (sequence, took, published))
    assert took < STOP_WITHIN, took


STUCK_NODE = '''
import sys, time
from stewart63_ros.runtime.launcher import run

class Stuck:
    """A node whose stop never ends (as one stuck inside the middleware)."""
    def __init__(self, options):
        print('RUNNING', flush=True)
    def run(self):
        while True:
            time.sleep(0.05)
    def close(self):
        time.sleep(60)
    def destroy_node(self):
        pass

sys.exit(run('stuck', 'a node that hangs when it stops', Stuck, ['stuck']))
'''


def test_a_node_that_hangs_while_stopping_exits_by_its_deadline_with_its_stacks(ros):
    """A stop always stops: 3.5 s after the first signal a process still
    running prints where every thread is and exits 1 (launcher.arm_stop_deadline)."""
    proc = ros.python('-c', STUCK_NODE, name='stuck')
    assert ros.wait_line(proc, 'RUNNING', 60), proc.describe()
    os.kill(proc.popen.pid, signal.SIGINT)
    sent = time.monotonic()
    code = proc.popen.wait(10)
    took = time.monotonic() - sent
    print('\nhung stop: exit %d after %.2f s' % (code, took))
    assert code == 1, proc.describe()
    assert 3.0 <= took <= 5.0, took
    assert 'in close' in proc.stderr(), proc.describe()      # its stack: where it hung


HUNG_TEARDOWN = '''
import ctypes, sys, time
from stewart63_ros.runtime.launcher import run

class HungTeardown:
    """A node that stops cleanly, then hangs in its teardown holding the GIL,
    as in the Fast DDS teardown deadlock (eProsima/Fast-DDS#6502)."""
    flushed = 'acknowledged after 0.001 s'
    def __init__(self, options):
        print('RUNNING', flush=True)
    def run(self):
        started = time.monotonic()
        while time.monotonic() - started < float(sys.argv[1]):
            time.sleep(0.05)
        return 3
    def close(self):
        pass
    def destroy_node(self):
        ctypes.PyDLL(None).sleep(30)    # native, the GIL held: no Python code runs

sys.exit(run('hung', 'a node whose teardown hangs', HungTeardown, ['hung']))
'''


@pytest.mark.parametrize('how', ['signal', 'own end'])
def test_a_node_whose_teardown_hangs_after_its_flush_exits_with_its_own_code(ros, how):
    """launcher.exit_natively_after: a node whose close is done ends with the
    exit code its run gave (0 when stopped by a signal, its own otherwise),
    TEARDOWN_BOUND after the close, however its teardown hangs; not with the
    stop deadline's 1."""
    from stewart63_ros.runtime.launcher import STOP_DEADLINE, TEARDOWN_BOUND
    proc = ros.python('-c', HUNG_TEARDOWN, '60' if how == 'signal' else '1.0', name='hung')
    assert ros.wait_line(proc, 'RUNNING', 60), proc.describe()
    sent = time.monotonic()
    if how == 'signal':
        os.kill(proc.popen.pid, signal.SIGINT)
    code = proc.popen.wait(30)
    took = time.monotonic() - sent
    print('\nhung teardown after %s: exit %d after %.2f s' % (how, code, took))
    assert code == (0 if how == 'signal' else 3), proc.describe()
    assert 'stopped (exit %d' % code in proc.stdout(), proc.describe()
    if how == 'signal':
        assert TEARDOWN_BOUND <= took < STOP_DEADLINE, took
