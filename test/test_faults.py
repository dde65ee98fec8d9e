"""Faults while a realtime rig runs, each with the behaviour docs/hosts.md states.

The rig's nodes run here as separate processes (not under ``rig``, which
stops everything when a node dies) in one namespace, with a recorder:

- the controller hangs (SIGSTOP) for 1 s and comes back (SIGCONT): the plant
  counts the missed cycles, control resumes;
- the controller is killed (SIGKILL) and started again: the plant misses
  cycles meanwhile, then takes the new controller's forces (a new source,
  counted); the bag shows a gap in ``leg_forces`` and none in ``leg_lengths``;
- fk is killed and started again: a gap in ``platform_pose`` only;
- the plant is killed and started again: the controller's watchdog trips and
  recovers on the new plant's samples (a new source, counted); the bag shows
  a gap in ``leg_lengths``.
Nobody else exits; everything stops with exit 0 at the end.
"""
from __future__ import annotations

import os
import signal
from pathlib import Path

from ros_harness import PYTHON, wait_until

from stewart63_ros import bagio

NS = '/faults'
ERROR = 2


def exe(name):
    path = Path(PYTHON).parent / name
    return [str(path)] if path.exists() else [PYTHON, '-m', {
        'plant': 'stewart63_ros.nodes.plant', 'controller': 'stewart63_ros.nodes.controller',
        'fk': 'stewart63_ros.nodes.fk_node', 'record': 'stewart63_ros.tools.record'}[name]]


def _text(proc):
    return proc.stdout() + proc.stderr()


def gaps(stamps, at_least_ns):
    """(start, length) of every gap between consecutive stamps longer than ``at_least_ns``."""
    stamps = sorted(stamps)
    return [(a, b - a) for a, b in zip(stamps, stamps[1:]) if b - a > at_least_ns]


def test_hang_kill_and_restart_of_nodes_in_a_realtime_rig(ros, tmp_path):
    from test_sources import Diagnostics
    diags = Diagnostics(ros)
    args = ['--ros-args', '-r', '__ns:=%s' % NS, '-p', 'clock_mode:=realtime']
    record = ros.spawn(exe('record') + [str(tmp_path / 'bag'), '--namespace', NS],
                       name='record')
    assert wait_until(lambda: 'READY' in record.stdout(), 60), record.describe()
    procs = {}

    def spawn(name, *extra):
        procs[name] = ros.spawn(exe(name) + args + list(extra), name=name)

    def ready(name):
        proc = procs[name]
        said = 'realtime at' if name == 'plant' else 'matched after'
        # or its start-up wait ran out (discovery_timeout): the bag then
        # shows what that cost, with the logs (below), not a 120 s wait here
        assert wait_until(lambda: said in _text(proc) or 'starting anyway' in _text(proc)
                          or proc.returncode is not None, 120), proc.describe()
        assert proc.returncode is None, proc.describe()

    def start(name, *extra):
        spawn(name, *extra)
        ready(name)
    # controller and fk start side by side (each waits only for the recorder)
    spawn('controller')
    spawn('fk')
    ready('controller')
    ready('fk')
    start('plant', '-p', 'lengths_subscribers:=3')
    plant_name, ctl_name = 'stewart63%s/plant' % NS, 'stewart63%s/controller' % NS

    def missed():
        return diags.value(plant_name, 'missed_cycles')

    def settle(seconds):
        diags.wait(lambda: False, seconds)

    settle(2.0)
    events = []
    # 1. the controller hangs for a second
    before = missed()
    os.kill(procs['controller'].pid, signal.SIGSTOP)
    settle(1.0)
    os.kill(procs['controller'].pid, signal.SIGCONT)
    settle(2.5)
    events.append(('controller SIGSTOP 1 s', missed() - before))
    assert missed() - before >= 500, events
    # 2. the controller killed and started again
    before = missed()
    restarts = diags.value(plant_name, 'source_restarts')
    procs['controller'].popen.kill()
    procs['controller'].wait(5)
    settle(1.0)
    start('controller')
    assert diags.wait(lambda: diags.value(plant_name, 'source_restarts') > restarts, 30), \
        diags.last(plant_name)
    settle(1.5)
    events.append(('controller SIGKILL + restart', missed() - before))
    # 3. fk killed and started again
    procs['fk'].popen.kill()
    procs['fk'].wait(5)
    settle(1.0)
    start('fk')
    settle(1.5)
    # 4. the plant killed and started again
    ctl_restarts = diags.value(ctl_name, 'source_restarts')
    procs['plant'].popen.kill()
    procs['plant'].wait(5)
    assert diags.wait(lambda: any(d[1] == ctl_name and d[2] == ERROR and 'watchdog' in d[3]
                                  for d in diags.seen[-20:]), 5), diags.last(ctl_name)
    start('plant', '-p', 'lengths_subscribers:=3')
    # bounded by the restarted plant's own wait for its subscribers
    # (discovery_timeout, 20 s), not by a guess of how long that takes
    assert diags.wait(lambda: diags.value(ctl_name, 'source_restarts') > ctl_restarts, 30), \
        diags.last(ctl_name)
    # The watchdog recovered: a report without its ERROR (a later one may
    # again name a starved moment of a loaded machine: that is not this)
    assert diags.wait(lambda: diags.last(ctl_name)[2] != ERROR, 10), diags.last(ctl_name)
    settle(1.0)
    # everybody else ran on; now stop them all cleanly
    for name in ('plant', 'controller', 'fk'):
        assert procs[name].returncode is None, procs[name].describe()
    for proc in list(procs.values()) + [record]:
        os.kill(proc.pid, signal.SIGINT)
        assert proc.wait(10) == 0, proc.describe()
        assert 'Traceback' not in _text(proc), proc.describe()
    # what the bag shows
    stamps = {}
    for topic, _, msg in bagio.read_messages(tmp_path / 'bag'):
        if hasattr(msg, 'header') and topic.startswith(NS + '/'):
            stamps.setdefault(topic[len(NS) + 1:], []).append(
                msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec)
    found = {topic: gaps(stamps.get(topic, []), 300_000_000)
             for topic in ('leg_lengths', 'leg_forces', 'platform_pose')}
    # What the bag holds of each topic (count, first and last stamp from the
    # first sample), what the recorder said, and what fk said: a topic the
    # recorder lost, or a restarted node that published nothing, shows here.
    first = min((min(v) for v in stamps.values() if v), default=0)
    held = {t: (len(v), '%.2f-%.2f s' % ((min(v) - first) * 1e-9, (max(v) - first) * 1e-9))
            for t, v in stamps.items() if v}
    why = (found, held, 'record: ' + _text(record)[-1500:],
           'fk: ' + _text(procs['fk'])[-1500:], events)
    # (whole, in the captured output: pytest cuts an assertion's message
    # short, and what the recorder and the plant said is at its end)
    print('\nthe bag and the nodes: %r\nplant: %s' % (why, _text(procs['plant'])[-1500:]))
    # the hang and the kill of the controller: two gaps in the forces; fk's
    # restart: one in the poses; the plant's restart: one in everything
    assert len(found['leg_forces']) >= 2, why
    assert len(found['platform_pose']) >= 2, why
    assert len(found['leg_lengths']) == 1, why
    print('\nfaults in a realtime rig: %s; gaps > 0.3 s in the bag: %s' % (
        ', '.join('%s: %d missed cycles' % e for e in events),
        {t: ['%.2f s' % (g[1] * 1e-9) for g in v] for t, v in found.items()}))
