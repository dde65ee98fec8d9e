"""Start-up and stop of the rig against the machine's floor. Prints figures, asserts nothing.

- the floor (``floor_s``): three bare rclpy processes started together, each
  with one reliable publisher and a subscription to each of the other two,
  until each has heard both others (the last one's time from the launch);
- per rig variant, ``rig --mode lockstep --duration S`` with nothing, or
  ``--compose``, ``--supervisor``, ``--bus canopen``, ``--record``: its
  start-up (the rig's summary: from starting its processes to the plant's
  first sample), its stop (from the run's end to the rig's exit), and the
  command's whole wall time (its own option checks included).

The floor and the variants are taken in turn, ``--repeat`` rounds in one
sitting (the machine's load moves): each figure is the median of its rounds,
and each start-up is also given as a multiple of the floor's median.
``--tree DIR`` (repeatable) runs the rig of that checkout (its
``stewart63_ros`` first on the path) instead of this one's; two of them,
e.g. the main branch and this one, are taken in turn in each round: a before
/ after in one sitting.

    bench_startup.py [--repeat R] [--duration S] [--variants plain,compose,...]
                     [--tree DIR]... [--json]
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_loop import private_domain  # noqa: E402

#: rig options of each variant (all in lockstep)
VARIANTS = {'plain': [], 'compose': ['--compose'], 'supervisor': ['--supervisor'],
            'bus': ['--bus', 'canopen'], 'record': ['--record']}
#: s: the bound on one floor round or one rig run
TIMEOUT = 180.0

FLOOR_CHILD = r'''
import os, select, sys, time
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import String
me, others = sys.argv[1], sys.argv[2:]
rclpy.init()
node = rclpy.create_node('floor_' + me)
qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
pub = node.create_publisher(String, 'floor_startup/' + me, qos)
heard = set()
for other in others:
    node.create_subscription(String, 'floor_startup/' + other,
                             lambda msg, o=other: heard.add(o), qos)
said = False
deadline = time.monotonic() + 60
while time.monotonic() < deadline:
    pub.publish(String(data=me))     # until the others have heard it too
    rclpy.spin_once(node, timeout_sec=0.005)
    if not said and len(heard) == len(others):
        print('HEARD %.6f' % time.time(), flush=True)
        said = True
    # on, publishing, until the parent closes stdin (the others have heard it)
    if said and select.select([sys.stdin], [], [], 0)[0] and sys.stdin.readline() == '':
        break
os._exit(0)     # no teardown: the next round must not share the cores with it
'''


def floor_once() -> float:
    """s from launching three bare rclpy processes to the last one hearing both others."""
    names = ['a', 'b', 'c']
    started = time.time()
    procs = [subprocess.Popen([sys.executable, '-c', FLOOR_CHILD, n] + [o for o in names
                                                                      if o != n],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
             for n in names]
    heard = []
    try:
        for proc in procs:
            line = proc.stdout.readline()
            if not line.startswith('HEARD'):
                raise RuntimeError('a floor process said %r' % line)
            heard.append(float(line.split()[1]))
    finally:
        for proc in procs:
            proc.stdin.close()      # each leaves its loop once the others are done
        for proc in procs:
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    return max(heard) - started


SUMMARY = re.compile(r'in ([\d.]+) s wall .*start-up'
                     r' ([\d.]+) s, stop ([\d.]+) s, ([\d.]+) s in all')


def rig_once(variant: str, duration: float, work: Path, env: dict) -> dict:
    """One ``rig`` run of ``variant``: its exit code and figures [s]."""
    logs = work / ('%s-%d' % (variant, time.monotonic_ns()))
    argv = [sys.executable, '-m', 'stewart63_ros.tools.rig', '--mode', 'lockstep',
            '--duration', '%g' % duration, '--log-dir', str(logs)]
    options = list(VARIANTS[variant])
    if options == ['--record']:
        options = ['--record', str(logs) + '.bag']
    started = time.monotonic()
    # cwd: not a checkout (``python -m`` puts the cwd first on the path)
    out = subprocess.run(argv + options, capture_output=True, text=True, timeout=TIMEOUT,
                         env=env, cwd=work)
    wall = time.monotonic() - started
    found = SUMMARY.search(out.stdout)
    result = {'code': out.returncode, 'command_s': wall}
    if found:
        result.update(run_s=float(found.group(1)), startup_s=float(found.group(2)),
                      stop_s=float(found.group(3)))
    else:
        result['error'] = (out.stdout + out.stderr)[-600:]
    shutil.rmtree(logs, ignore_errors=True)
    shutil.rmtree(str(logs) + '.bag', ignore_errors=True)
    shutil.rmtree(str(logs) + '.bag.logs', ignore_errors=True)
    return result


def tree_env(tree: str | None) -> dict:
    """The environment that runs the rig of checkout ``tree`` (None: this one)."""
    env = dict(os.environ)
    root = Path(tree).resolve() if tree else HERE.parent
    env['PYTHONPATH'] = str(root) + os.pathsep + env.get('PYTHONPATH', '')
    return env


def measure(repeat: int, duration: float, variants: list[str], trees: list,
            quiet: bool = False) -> dict:
    """``variants`` of each of ``trees`` (None: this checkout), labelled
    ``variant`` (one tree) or ``variant@tree``."""
    trees = trees or [None]
    runs = [(v, t, v if len(trees) == 1 else '%s@%s' % (v, t)) for t in trees for v in variants]
    rounds: dict[str, list] = {'floor': []}
    rounds.update({label: [] for _, _, label in runs})
    with private_domain(), tempfile.TemporaryDirectory(prefix='bench_startup_') as tmp:
        for k in range(repeat):
            rounds['floor'].append(floor_once())
            for variant, tree, label in runs:
                rounds[label].append(rig_once(variant, duration, Path(tmp), tree_env(tree)))
            labels = [label for _, _, label in runs]
            if not quiet:
                print('round %d: floor %.2f s; %s' % (k + 1, rounds['floor'][-1], '; '.join(
                    '%s %s' % (v, 'start-up %.2f s, stop %.2f s' % (
                        rounds[v][-1]['startup_s'], rounds[v][-1]['stop_s'])
                        if 'startup_s' in rounds[v][-1] else 'FAILED (exit %d)'
                        % rounds[v][-1]['code']) for v in labels)), flush=True)
    floor = statistics.median(rounds['floor'])
    result = {'floor_s': floor, 'floor_rounds_s': rounds['floor'], 'rounds': repeat,
              'load_average': os.getloadavg()}
    for _, _, label in runs:
        done = rounds[label]
        good = [r for r in done if 'startup_s' in r]
        figures = {'exit_codes': [r['code'] for r in done]}
        if good:
            for key in ('startup_s', 'stop_s', 'run_s', 'command_s'):
                figures[key] = statistics.median(r[key] for r in good)
            figures['startup_over_floor'] = figures['startup_s'] / floor
        figures['errors'] = [r['error'] for r in done if 'error' in r]
        result[label] = figures
    result['labels'] = [label for _, _, label in runs]
    return result


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--repeat', type=int, default=5)
    parser.add_argument('--duration', type=float, default=1.0,
                        help='simulated seconds of each rig run')
    parser.add_argument('--variants', default=','.join(VARIANTS),
                        help='comma-separated, of %s' % ','.join(VARIANTS))
    parser.add_argument('--tree', action='append', default=[],
                        help='run the rig of this checkout (default: this one); repeatable')
    parser.add_argument('--json', action='store_true', help='print the figures as JSON')
    args = parser.parse_args(argv)
    variants = [v for v in args.variants.split(',') if v]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        parser.error('unknown variants %s (of %s)' % (unknown, ','.join(VARIANTS)))
    before = os.getloadavg()
    result = measure(args.repeat, args.duration, variants, args.tree, quiet=args.json)
    result['load_average_before'] = before
    if args.json:
        print(json.dumps(result, indent=1))
        return
    print('floor: three bare rclpy processes until each hears both others: %.2f s '
          '(median of %d: %s)' % (result['floor_s'], args.repeat,
                                  ', '.join('%.2f' % f for f in result['floor_rounds_s'])))
    print('%-24s %9s %9s %7s %8s %10s  exits' % ('rig', 'start-up', 'x floor', 'stop',
                                                 'run', 'command'))
    for variant in result['labels']:
        f = result[variant]
        if 'startup_s' not in f:
            print('%-24s FAILED every run: %s' % (variant, f['errors'][:1]))
            continue
        print('%-24s %8.2fs %8.1fx %6.2fs %7.2fs %9.2fs  %s' % (
            variant, f['startup_s'], f['startup_over_floor'], f['stop_s'], f['run_s'],
            f['command_s'], ' '.join(map(str, f['exit_codes']))))
    print('load average %s before, %s after' % (
        ' '.join('%.1f' % x for x in before),
        ' '.join('%.1f' % x for x in result['load_average'])))


if __name__ == '__main__':
    main()
