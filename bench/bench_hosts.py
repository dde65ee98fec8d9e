"""A rig split across two hosts beside one host: prints figures, asserts nothing.

Two network namespaces joined by a veth pair stand for the platform's
computer (``rig --nodes plant``) and a workstation (``rig --nodes
controller,fk``), DDS over UDPv4 only between them (test/netns.py, needs
root). In turn, ``--repeat`` times: the whole rig on one host, then split
across the link, each in lockstep (samples per second of the plant loop)
and realtime at 1 kHz (sample -> force latency p50 / p99, missed cycles).
Medians and the spread (min..max) per figure.

    bench_hosts.py [--duration S] [--repeat N]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / 'test'))

import bench_loop  # noqa: E402
from bench_loop import spread  # noqa: E402
from netns import TwoHosts, dds_env  # noqa: E402

RIG = [sys.executable, '-m', 'stewart63_ros.tools.rig']


def _summary(log_dir: Path) -> dict:
    return json.loads((log_dir / 'plant_summary.json').read_text())


def one_host(mode: str, duration: float, tmp: Path) -> dict:
    log = tmp / 'one'
    subprocess.run(RIG + ['--mode', mode, '--duration', str(duration), '--log-dir', str(log)],
                   check=True, capture_output=True, timeout=300)
    return _summary(log)


def two_hosts(hosts: TwoHosts, mode: str, duration: float, tmp: Path) -> dict:
    env = dds_env(os.environ)
    a_log, b_log = tmp / 'a', tmp / 'b'
    b = subprocess.Popen(hosts.exec_prefix(hosts.b) + RIG + [
        '--nodes', 'controller,fk', '--mode', mode, '--log-dir', str(b_log)],
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        subprocess.run(hosts.exec_prefix(hosts.a) + RIG + [
            '--nodes', 'plant', '--mode', mode, '--duration', str(duration),
            '--log-dir', str(a_log)], env=env, check=True, capture_output=True, timeout=300)
    finally:
        b.send_signal(2)
        try:
            b.wait(30)
        except subprocess.TimeoutExpired:
            b.kill()
            b.wait()
    return _summary(a_log)


def figures(mode: str, s: dict) -> dict:
    lat = s['loop_latency']
    if mode == 'lockstep':
        return {'samples_per_s': s['samples'] / s['wall_time_s']}
    return {'p50_us': lat['p50_ms'] * 1e3, 'p99_us': lat['p99_ms'] * 1e3,
            'missed_percent': 100.0 * s['missed_cycles'] / s['samples']}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--duration', type=float, default=5.0, help='simulated s per run')
    parser.add_argument('--repeat', type=int, default=3, help='runs of each kind')
    args = parser.parse_args()
    reason = TwoHosts.available()
    if reason:
        print('bench_hosts: %s' % reason, file=sys.stderr)
        return 2
    domain, fd = bench_loop.lease_domain()
    os.environ['ROS_DOMAIN_ID'] = str(domain)
    os.environ.pop('ROS_AUTOMATIC_DISCOVERY_RANGE', None)
    runs = {}
    hosts = TwoHosts().open()
    try:
        for k in range(args.repeat):
            for mode in ('lockstep', 'realtime'):
                for where in ('one host', 'two hosts'):
                    with tempfile.TemporaryDirectory(prefix='bench_hosts_') as tmp:
                        try:
                            s = (one_host(mode, args.duration, Path(tmp)) if where == 'one host'
                                 else two_hosts(hosts, mode, args.duration, Path(tmp)))
                        except (subprocess.SubprocessError, OSError) as exc:
                            print('%s, %s, run %d failed: %s' % (mode, where, k + 1, exc))
                            continue
                    f = figures(mode, s)
                    runs.setdefault((mode, where), []).append(f)
                    print('%-8s %-9s run %d: %s' % (mode, where, k + 1, ', '.join(
                        '%s %.3g' % kv for kv in f.items())), flush=True)
    finally:
        hosts.close()
        os.close(fd)
    print('\n%g s runs, median (min..max) of %d; two hosts: a veth link, UDPv4 only'
          % (args.duration, args.repeat))
    for where in ('one host', 'two hosts'):
        ls = runs.get(('lockstep', where), [])
        rt = runs.get(('realtime', where), [])
        print('  %-9s lockstep %s samples/s; realtime p50 %s us, p99 %s us, missed %s %%'
              % (where, spread([r['samples_per_s'] for r in ls]),
                 spread([r['p50_us'] for r in rt]), spread([r['p99_us'] for r in rt]),
                 spread([r['missed_percent'] for r in rt], '%.2f')))
    return 0


if __name__ == '__main__':
    sys.exit(main())
