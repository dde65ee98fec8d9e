"""Soak: a realtime rig with recording for a long run; prints figures, asserts nothing.

    bench_soak.py [--duration S] [--sample-period S] [--out DIR] [--json FILE]
                  [--realtime-priority P]

Runs ``rig --mode realtime --record`` (plant, controller, fk, record as
separate processes, 1 kHz) for ``--duration`` seconds (default 600) on a
private domain, and while it runs reads the memory (VmRSS, from /proc) of
``rig`` and each of its processes every ``--sample-period`` seconds. After
the run it prints, per process, the memory at start and end and its growth
per hour (a least-squares slope over the second half of the run, after the
warm-up, extrapolated to an hour); from the plant's /diagnostics in the bag,
the missed cycles in each minute; and per topic the count each node says it
published beside the count in the bag (they must be equal).
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from stewart63_ros import bagio

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_loop import lease_domain  # noqa: E402

MODULES = {'stewart63_ros.nodes.plant': 'plant', 'stewart63_ros.nodes.controller': 'controller',
           'stewart63_ros.nodes.fk_node': 'fk', 'stewart63_ros.tools.record': 'record'}


def rss_kb(pid: int) -> int | None:
    try:
        for line in Path('/proc/%d/status' % pid).read_text().splitlines():
            if line.startswith('VmRSS:'):
                return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return None


def children(pid: int) -> dict[str, int]:
    """{node name: pid} of the rig's live children (from /proc)."""
    out = {}
    for entry in Path('/proc').iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / 'stat').read_text()
            if int(stat.rsplit(')', 1)[1].split()[1]) != pid:
                continue
            cmd = (entry / 'cmdline').read_bytes().split(b'\0')
        except (OSError, ValueError, IndexError):
            continue
        for arg in cmd:
            name = MODULES.get(arg.decode(errors='replace'))
            if name:
                out[name] = int(entry.name)
    return out


def _read(path) -> str:
    try:
        return Path(path).read_text(errors='replace')
    except OSError:
        return ''


def growth_per_hour(samples) -> float:
    """MB per hour: slope of RSS over the second half of the samples."""
    if len(samples) < 4:
        return float('nan')
    t = np.array([s[0] for s in samples[len(samples) // 2:]])
    m = np.array([s[1] for s in samples[len(samples) // 2:]]) / 1024.0
    if t[-1] - t[0] <= 0:
        return float('nan')
    return float(np.polyfit(t, m, 1)[0] * 3600.0)


def from_bag(bag) -> dict:
    """Missed cycles per minute (plant) and published-vs-bag counts per topic."""
    missed = []         # (sim time s, missed cycles so far)
    last = {}
    for _, _, msg in bagio.read_messages(bag, ['/diagnostics']):
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            last[status.name] = values
            if status.name.endswith('/plant') and 'missed_cycles' in values:
                missed.append((float(values.get('sim_time_s', 0)),
                               int(values['missed_cycles'])))
    per_minute = []
    for minute in range(int(missed[-1][0] // 60) + 1 if missed else 0):
        inside = [m for t, m in missed if t <= (minute + 1) * 60]
        before = [m for t, m in missed if t <= minute * 60]
        per_minute.append((inside[-1] if inside else 0) - (before[-1] if before else 0))
    published = {}
    for values in last.values():
        for key, value in values.items():
            if key.startswith('published/') and key != 'published//diagnostics':
                topic = key[len('published/'):]
                published[topic] = published.get(topic, 0) + int(value)
    in_bag = {}
    for topic, _, _, _ in bagio.read_raw(bag):
        in_bag[topic] = in_bag.get(topic, 0) + 1
    counts = {}
    for topic, n in sorted(published.items()):
        full = topic if topic.startswith('/') else '/' + topic
        counts[full] = {'published': n, 'bag': in_bag.get(full, 0)}
    return {'missed_per_minute': per_minute, 'counts': counts,
            'missed_total': missed[-1][1] if missed else None}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--duration', type=float, default=600.0, help='seconds (default 600)')
    parser.add_argument('--sample-period', type=float, default=5.0,
                        help='memory sampling period [s] (default 5)')
    parser.add_argument('--out', help='directory for the bag and logs (default: a temp dir)')
    parser.add_argument('--json', help='also write the figures to this file')
    parser.add_argument('--realtime-priority', type=int, default=0, metavar='P')
    args = parser.parse_args(argv)
    out = Path(args.out or tempfile.mkdtemp(prefix='bench_soak_'))
    out.mkdir(parents=True, exist_ok=True)
    bag, logs = out / 'bag', out / 'logs'
    domain, _lock = lease_domain()
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1')
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    exe = Path(sys.executable).parent / 'rig'
    cmd = ([str(exe)] if exe.exists() else [sys.executable, '-m', 'stewart63_ros.tools.rig'])
    cmd += ['--mode', 'realtime', '--duration', '%g' % args.duration, '--record', str(bag),
            '--log-dir', str(logs), '--realtime-priority', str(args.realtime_priority)]
    print('soak: %s (domain %d), %g s' % (' '.join(cmd), domain, args.duration), flush=True)
    rig = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                           text=True, start_new_session=True)
    memory: dict[str, list] = {}
    start = None
    try:
        while rig.poll() is None:
            procs = dict(children(rig.pid), rig=rig.pid)
            if start is None and 'realtime at' in _read(logs / 'plant.log'):
                start = time.monotonic()      # the run begins: memory from here
            now = time.monotonic() - (start or time.monotonic())
            for name, pid in procs.items():
                kb = rss_kb(pid)
                if kb is not None and start is not None:
                    memory.setdefault(name, []).append((now, kb))
            time.sleep(args.sample_period if start is not None else 0.2)
    except KeyboardInterrupt:
        os.kill(rig.pid, signal.SIGINT)
    rig_out = rig.communicate()[0]
    print(rig_out, end='')
    if rig.returncode != 0:
        print('soak: rig exited %d (logs in %s)' % (rig.returncode, logs))
    figures = {'duration_s': args.duration, 'rig_exit': rig.returncode, 'memory': {}}
    print('\nmemory (VmRSS), sampled every %g s:' % args.sample_period)
    print('  %-10s %10s %10s %14s' % ('process', 'start MB', 'end MB', 'growth MB/h'))
    for name, samples in sorted(memory.items()):
        grow = growth_per_hour(samples)
        figures['memory'][name] = {'start_mb': samples[0][1] / 1024,
                                   'end_mb': samples[-1][1] / 1024,
                                   'growth_mb_per_h': grow, 'samples': len(samples)}
        print('  %-10s %10.1f %10.1f %14.2f' % (name, samples[0][1] / 1024,
                                                 samples[-1][1] / 1024, grow))
    try:
        bag_figures = from_bag(bag)
    except Exception as exc:  # noqa: BLE001 - a benchmark reports what it could not read
        print('soak: cannot read the bag: %s' % exc)
        bag_figures = {}
    figures.update(bag_figures)
    if bag_figures:
        print('\nmissed cycles per minute: %s (total %s)'
              % (bag_figures['missed_per_minute'], bag_figures['missed_total']))
        print('published vs in the bag:')
        for topic, c in bag_figures['counts'].items():
            print('  %-22s %9d %9d %s' % (topic, c['published'], c['bag'],
                                          'ok' if c['published'] == c['bag'] else 'DIFFERENT'))
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=1))
    return 0


if __name__ == '__main__':
    sys.exit(main())
