"""The composed rig: plant, controller, fk (and the recorder) as nodes of one process.

- lockstep: equals the offline ``run_sampled`` sample for sample, and the
  separate-process rig; with the recorder in the process every message the
  nodes published is in the bag;
- ``rig --compose``: Ctrl-C / SIGTERM stop it cleanly, exit 0; a node that
  raises ends the process (and the rig) non-zero with its traceback in the log.

Every test runs on its own ROS domain (``ros`` fixture) with bounded waits.
"""
from __future__ import annotations

import contextlib
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest
from ros_harness import PYTHON, rig_env, run_to_end, wait_line, wait_until
from test_rig import (
    assert_every_published_message_is_in_the_bag,
    by_stamp,
    children_of,
    ended,
    kill_leftovers,
    read_log,
    rig_command,
    warm_kernels,  # noqa: F401 (a fixture)
)

from stewart63_ros.core.controllers.simulate import run_sampled, sensor_reading
from stewart63_ros.core.mechanics.dynamics import POS, Dynamics
from stewart63_ros.core.plumbing.params import load_mechanism
from stewart63_ros.tools.rig_process import Rig

REPO = Path(__file__).resolve().parents[1]
PARAMS = REPO / 'config' / 'stewart63.yaml'
RATE = 1000.0
DURATION = 0.5              # simulated s: 501 samples
RUN_TIMEOUT = 150.0
#: The numba kernels compiled once, into the cache the nodes load.
pytestmark = [pytest.mark.usefixtures('warm_kernels'), pytest.mark.dds, pytest.mark.slow]


@pytest.fixture(scope='module')
def mech():
    return load_mechanism(PARAMS)


def run(tmp_path, name, compose, record=True, duration=DURATION, extra_params=None):
    """One lockstep rig run to its end: (bag, summary, exit codes, logs)."""
    log_dir = tmp_path / name
    bag = tmp_path / (name + '_bag') if record else None
    rig = Rig(PARAMS, mode='lockstep', duration=duration, record=bag, log_dir=log_dir,
              compose=compose, extra_params=extra_params)
    ok, codes, logs = run_to_end(rig, RUN_TIMEOUT)
    return bag, rig.summary(), ok, codes, logs


def test_composed_lockstep_equals_offline_run_and_separate_rig_and_records_everything(setup,
        ros, monkeypatch, tmp_path, mech):
    rig_env(ros, monkeypatch)
    n = int(round(DURATION * RATE)) + 1
    bag, summary, ok, codes, logs = run(tmp_path, 'composed', compose=True)
    assert ok and codes == {'composed': 0}, (codes, logs)
    assert summary['samples'] == n and summary['force_timeouts'] == 0, summary
    ref = run_sampled(setup, DURATION, RATE)
    dyn = Dynamics(mech)
    lengths, n_lengths = by_stamp(bag, 'leg_lengths')
    forces, _ = by_stamp(bag, 'leg_forces')
    truth, _ = by_stamp(bag, 'ground_truth/pose')
    assert sorted(lengths) == [k * 1_000_000 for k in range(n)]
    dl = dv = df = dp = 0.0
    for k in range(n):
        s = k * 1_000_000
        L, Ldot = sensor_reading(dyn, ref.states[k])
        dl = max(dl, float(np.max(np.abs(np.asarray(lengths[s].position) - L))))
        dv = max(dv, float(np.max(np.abs(np.asarray(lengths[s].velocity) - Ldot))))
        df = max(df, float(np.max(np.abs(np.asarray(forces[s].effort) - ref.forces[k]))))
        p = truth[s].pose.position
        dp = max(dp, float(np.max(np.abs(np.array([p.x, p.y, p.z]) - ref.states[k, POS]))))
    counts = assert_every_published_message_is_in_the_bag(bag, summary)
    assert counts['/clock'] == n, counts

    # The same scenario with the nodes in separate processes.
    sbag, ssummary, sok, scodes, slogs = run(tmp_path, 'separate', compose=False)
    assert sok and set(scodes.values()) == {0}, (scodes, slogs)
    slengths, _ = by_stamp(sbag, 'leg_lengths')
    sforces, _ = by_stamp(sbag, 'leg_forces')
    assert sorted(slengths) == sorted(lengths)
    ds = max(max(float(np.max(np.abs(np.asarray(lengths[s].position)
                                     - np.asarray(slengths[s].position)))),
                 float(np.max(np.abs(np.asarray(forces[s].effort)
                                     - np.asarray(sforces[s].effort)))))
             for s in lengths)
    print('\ncomposed lockstep vs run_sampled over %d samples: max |dL| %.3g m, |dLdot| %.3g m/s, '
          '|dF| %.3g N, ground truth |dt| %.3g m; vs the separate-process rig: max |d| %.3g; '
          'bag = published %s; plant loop %.0f samples/s composed, %.0f separate (both '
          'recording)' % (n, dl, dv, df, dp, ds, counts, n / summary['wall_time_s'],
                          n / ssummary['wall_time_s']))
    assert dl <= 1e-9 and dv <= 1e-9 and dp <= 1e-9, (dl, dv, dp)
    assert df <= 1e-5, df
    assert ds <= 1e-9, 'composed and separate rigs differ by %g' % ds


def node_children(pid: int) -> dict[int, str]:
    """rig's processes but its fork server."""
    return {p: c for p, c in children_of(pid).items() if 'runtime.forkserver' not in c}


@contextlib.contextmanager
def composed_rig(ros, tmp_path):
    """``rig --compose --mode realtime`` (no duration), its composed node running."""
    log_dir = tmp_path / 'rig_logs'
    proc = ros.spawn(rig_command() + ['--compose', '--mode', 'realtime',
                                      '--log-dir', str(log_dir)], name='rig')
    children: dict[int, str] = {}
    try:
        assert wait_line(proc, 'rig: ', 90), proc.describe()
        # one process for every node, forked from rig's fork server
        assert wait_until(lambda: len(node_children(proc.pid)) == 1, 10), children_of(proc.pid)
        children = children_of(proc.pid)
        log = log_dir / 'composed.log'
        assert wait_until(lambda: 'realtime at' in read_log(log), 90), (
            proc.describe() + read_log(log))
        yield proc, children, log
    finally:
        ros.stop(proc)
        kill_leftovers(children)


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
def test_composed_rig_signal_stops_cleanly(ros, tmp_path, sig):
    with composed_rig(ros, tmp_path) as (proc, children, log):
        time.sleep(0.5)                # mid-run
        os.kill(proc.pid, sig)
        code = proc.wait(45)
        assert code == 0, proc.describe()
        assert 'stopped by %s' % sig.name in proc.stdout(), proc.describe()
        assert wait_until(lambda: all(ended(p, c) for p, c in children.items()), 10)
        text = read_log(log)
        assert 'composed: stopped (exit 0' in text, text[-2000:]
        assert 'Traceback' not in text, text[-3000:]
        print('\ncomposed rig stopped by %s: exit %d' % (sig.name, code))


#: Runs the composed executable with fk's callback made to raise at its 100th sample.
FAILING_FK = '''
import sys
from stewart63_ros.nodes import composed, fk_node
calls = []
original = fk_node.FKNode.on_sample
def on_sample(self, data, info):
    calls.append(1)
    if len(calls) == 100:
        raise ZeroDivisionError('injected fault in fk at sample 100')
    return original(self, data, info)
fk_node.FKNode.on_sample = on_sample
composed.main(['composed', '--ros-args', '--params-file', sys.argv[1],
               '-p', 'clock_mode:=lockstep', '-p', 'duration:=2.0',
               '-p', 'lengths_subscribers:=2'])
'''


def test_a_node_that_raises_ends_the_composed_process_nonzero_with_its_traceback(
        ros, tmp_path):
    proc = ros.spawn([PYTHON, '-c', FAILING_FK, str(PARAMS)], name='composed')
    code = proc.wait(90)
    out = proc.stdout() + proc.stderr()
    assert code not in (0, None), proc.describe()
    assert 'Traceback' in out and 'ZeroDivisionError: injected fault in fk' in out, out[-3000:]
    assert 'composed: stopped' in out, out[-3000:]     # the other nodes were closed
    print('\ncomposed process with a raising fk: exit %d, traceback in its log' % code)


def test_a_node_that_raises_takes_the_composed_rig_down(ros, monkeypatch, tmp_path):
    """The plant cannot write its summary (a folder that does not exist): its
    run raises; the rig reports the composed process's failure and exits 1."""
    rig_env(ros, monkeypatch)
    _, _, ok, codes, logs = run(tmp_path, 'broken', compose=True, record=False, duration=0.1,
                                extra_params={'plant': {
                                    'summary_file': str(tmp_path / 'missing' / 's.json')}})
    assert not ok and codes['composed'] not in (0, None), (codes, logs)
    assert 'Traceback' in logs and 'FileNotFoundError' in logs, logs
