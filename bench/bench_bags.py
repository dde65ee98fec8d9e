"""Benchmark of record and play over real DDS (separate processes, own domain).

    .venv/bin/python bench/bench_bags.py [--rates 1000 2000 4000] [--seconds 5]
                                         [--topics 4] [--executor] [--play-seconds 5]

1. Recording throughput: test/stream_publisher.py publishes on N stream topics
   at each rate (samples/s per topic) while ``record`` records; reported: total
   messages/s offered, recorded, lost, and the recorder's CPU use. "No loss"
   means the bag holds every message published.
2. Play timing: the leg_lengths of the last bag are replayed by ``play`` into a
   subscriber in this process; the error between the reception times and the
   bag's timestamps (common offset removed) is reported as p50/p99/max.
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
from sensor_msgs.msg import JointState

from stewart63_ros import topics as T

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'test'))

from ros_harness import PYTHON, RosTest, lease_domain_id, stop, wait_line  # noqa: E402

from stewart63_ros import bagio  # noqa: E402

PUBLISHER = str(ROOT / 'test' / 'stream_publisher.py')
STREAMS = ['leg_lengths', 'leg_forces', 'ground_truth/pose', 'ground_truth/twist']


def cpu_seconds(pid: int) -> float:
    try:
        fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')
    except (OSError, IndexError, ValueError):
        return float('nan')


def record_run(rt: RosTest, tmp: Path, rate: float, seconds: float, topics: list[str],
               executor: bool, pub_args=()) -> dict:
    bag = tmp / f'bag-{int(rate)}-{len(topics)}{"-exec" if executor else ""}'
    count = int(rate * seconds)
    cmd = [PYTHON, '-m', 'stewart63_ros.tools.record', str(bag), '--topics', *topics]
    if executor:
        cmd.append('--executor')
    rec = rt.spawn(cmd, name='record')
    if not wait_line(rec, 'READY', 30):
        raise RuntimeError(rec.describe())
    cpu0 = cpu_seconds(rec.pid)
    pub = rt.spawn([PYTHON, PUBLISHER, '--count', str(count), '--rate', str(rate),
                    '--topics', *topics, *pub_args], name='publisher')
    if pub.wait(seconds * 3 + 60) is None:
        stop(pub)
    cpu1 = cpu_seconds(rec.pid)
    out = pub.stdout()
    took = float(out.split(' in ')[1].split()[0]) if 'DONE' in out else float('nan')
    stop(rec)
    counts = {t.lstrip('/'): n for t, (_, n) in bagio.bag_info(bag)['topics'].items()}
    recorded = sum(counts.get(t, 0) for t in topics)
    offered = count * len(topics)
    return {'bag': bag, 'rate': rate, 'offered': offered, 'recorded': recorded,
            'lost': offered - recorded, 'msg_per_s': offered / took if took else float('nan'),
            'publish_s': took, 'cpu_pct': 100 * (cpu1 - cpu0) / took if took else float('nan'),
            'acked': 'ACKED' in out and 'NOT ACKED' not in out}


def play_timing(rt: RosTest, bag: Path, seconds_max: float) -> dict:
    want = [s for _, _, s, _ in bagio.read_raw(bag, ['leg_lengths'])]
    node = rt.node('bench_probe')
    got = []
    node.create_subscription(JointState, 'leg_lengths',
                             lambda m, i: got.append(i['received_timestamp']),
                             T.RECORD_SUB, raw=True)
    play = rt.spawn([PYTHON, '-m', 'stewart63_ros.tools.play', str(bag), '--topics',
                     'leg_lengths'], name='play')
    duration = (want[-1] - want[0]) * 1e-9
    rt.spin_until(lambda: len(got) >= len(want) or play.returncode is not None,
                  duration + 30)
    rt.spin_until(lambda: len(got) >= len(want), 3)
    play.wait(10)
    n = min(len(got), len(want))
    rx = np.array(got[:n], dtype=np.int64)
    tb = np.array(want[:n], dtype=np.int64)
    err = ((rx - rx[0]) - (tb - tb[0])) * 1e-6
    err -= np.median(err)
    a = np.abs(err)
    return {'n': n, 'expected': len(want), 'p50': np.percentile(a, 50),
            'p99': np.percentile(a, 99), 'max': a.max(), 'duration': duration}


def measure(rates=(1000, 2000, 4000, 8000), seconds: float = 3.0, repeat: int = 3,
            verbose: bool = True) -> dict:
    """{'record_msgs_per_s'}: the highest rate (all four stream topics) that
    ``record`` took with nothing lost, median over ``repeat`` sweeps of ``rates``
    (samples/s per topic); 0 when even the lowest lost messages."""
    lease = lease_domain_id()
    tmp = Path(tempfile.mkdtemp(prefix='bench_bags-'))
    rt = RosTest(lease, tmp / 'logs')
    best = []
    try:
        for sweep in range(repeat):
            top = 0.0
            for rate in rates:
                r = record_run(rt, tmp / f'sweep{sweep}', rate, seconds, STREAMS, False)
                if verbose:
                    print('record: %d topics x %5.0f/s = %6.0f msg/s offered, %d lost'
                          % (len(STREAMS), rate, r['msg_per_s'], r['lost']), flush=True)
                if r['lost']:
                    break
                top = r['msg_per_s']
            best.append(top)
    finally:
        rt.cleanup()
        shutil.rmtree(tmp, ignore_errors=True)
    return {'record_msgs_per_s': float(np.median(best))}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--rates', type=float, nargs='+', default=[1000, 2000, 4000],
                   help='samples/s per topic')
    p.add_argument('--seconds', type=float, default=5.0)
    p.add_argument('--topics', type=int, default=4, choices=range(1, 5))
    p.add_argument('--executor', action='store_true', help='record with --executor')
    p.add_argument('--no-play', action='store_true')
    p.add_argument('--load', type=int, default=0,
                   help='run N busy-loop processes meanwhile (a loaded machine)')
    p.add_argument('--pub-depth', type=int, help='publisher history depth (default 1000)')
    p.add_argument('--keep-all', action='store_true', help='KEEP_ALL publisher history')
    a = p.parse_args(argv)
    pub_args = ((['--depth', str(a.pub_depth)] if a.pub_depth else [])
                + (['--keep-all'] if a.keep_all else []))

    topics = STREAMS[:a.topics]
    lease = lease_domain_id()
    tmp = Path(tempfile.mkdtemp(prefix='bench_bags-'))
    rt = RosTest(lease, tmp / 'logs')
    print(f'domain {lease.domain_id}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}, '
          f'topics {topics}, recorder {"executor" if a.executor else "wait-set loop"}, '
          f'publisher {" ".join(pub_args) or "STREAM_PUB"}, {a.load} busy loops')
    try:
        for _ in range(a.load):
            rt.spawn([PYTHON, '-c', 'while True: pass'], name='load')
        print(f'{"rate/topic":>10} {"offered msg/s":>14} {"offered":>8} {"recorded":>9} '
              f'{"lost":>5} {"rec CPU %":>9}')
        last = None
        for rate in a.rates:
            r = record_run(rt, tmp, rate, a.seconds, topics, a.executor, pub_args)
            print(f'{rate:>10.0f} {r["msg_per_s"]:>14.0f} {r["offered"]:>8} '
                  f'{r["recorded"]:>9} {r["lost"]:>5} {r["cpu_pct"]:>9.1f}'
                  + ('' if r['acked'] else '  (publisher not acked)'), flush=True)
            if rate == 1000 or last is None:
                last = r
        if not a.no_play and last is not None:
            t = play_timing(rt, last['bag'], a.seconds)
            print(f'play leg_lengths ({t["n"]}/{t["expected"]} msgs over {t["duration"]:.1f} s): '
                  f'timing error vs bag timestamps p50 {t["p50"]:.3f} ms, '
                  f'p99 {t["p99"]:.3f} ms, max {t["max"]:.3f} ms')
    finally:
        rt.cleanup()
    return 0


if __name__ == '__main__':
    sys.exit(main())
