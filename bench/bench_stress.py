"""Many short lockstep rigs, side by side: does every one exit 0? Prints figures, asserts nothing.

Runs ``--runs`` N rigs (``rig --mode lockstep --duration S``: plant,
controller, fk as separate processes) in ``--streams`` K parallel streams,
each stream on a ROS domain of its own, one rig after another. Per run it
notes the exit code, the start-up, run and stop from the rig's summary, and
whether any process of that rig was still running after the rig exited (its
children are found by the rig's parameter file on their command line; one
found is reported, then killed). At the end: the count of each exit code,
the medians and worst cases, the processes left running, and the logs of
every run that did not exit 0 (kept in ``--keep-dir``; the others' are
deleted).

    bench_stress.py [--runs N] [--streams K] [--duration S] [--max-wall S]
                    [--tree DIR] [--keep-dir DIR] [--json]

The target: 1000 runs, every one exit 0, nothing left running.
"""
from __future__ import annotations

import argparse
import collections
import json
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_loop import lease_domain  # noqa: E402

SUMMARY = re.compile(r'in ([\d.]+) s wall .*start-up'
                     r' ([\d.]+) s, stop ([\d.]+) s, ([\d.]+) s in all')
#: s: the bound on one rig run (a hung one is killed and counted as such)
RUN_TIMEOUT = 180.0


def left_running(marker: str) -> list[int]:
    """Pids of live processes whose command line holds ``marker`` (a run's log folder)."""
    found = []
    for entry in Path('/proc').iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            cmdline = (entry / 'cmdline').read_bytes().replace(b'\0', b' ').decode()
        except OSError:
            continue
        if marker in cmdline:
            found.append(int(entry.name))
    return found


def one_run(k: int, duration: float, work: Path, env: dict) -> dict:
    logs = work / ('run%05d' % k)
    argv = [sys.executable, '-m', 'stewart63_ros.tools.rig', '--mode', 'lockstep',
            '--duration', '%g' % duration, '--log-dir', str(logs)]
    started = time.monotonic()
    try:
        # cwd: not a checkout (``python -m`` puts the cwd first on the path)
        out = subprocess.run(argv, capture_output=True, text=True, timeout=RUN_TIMEOUT,
                             env=env, cwd=work)
        code, text = out.returncode, out.stdout + out.stderr
    except subprocess.TimeoutExpired as exc:
        code, text = 'timeout', '%s%s' % (exc.stdout or '', exc.stderr or '')
    result = {'run': k, 'code': code, 'command_s': time.monotonic() - started,
              'logs': str(logs)}
    found = SUMMARY.search(text)
    if found:
        result.update(run_s=float(found.group(1)), startup_s=float(found.group(2)),
                      stop_s=float(found.group(3)))
    leftovers = left_running(str(logs) + '/')
    if leftovers:
        result['left_running'] = leftovers
        for pid in leftovers:
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
    if code != 0 or leftovers or not found:
        (logs / 'rig_output.txt').parent.mkdir(parents=True, exist_ok=True)
        (logs / 'rig_output.txt').write_text(text)
        result['tail'] = text[-400:]
    return result


def stream(runs: list[int], duration: float, work: Path, tree: str | None, results: list,
           keep: Path, lock: threading.Lock, quiet: bool, until: float) -> None:
    domain, fd = lease_domain()
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    root = Path(tree).resolve() if tree else HERE.parent
    env['PYTHONPATH'] = str(root) + os.pathsep + env.get('PYTHONPATH', '')
    try:
        for k in runs:
            if time.monotonic() >= until:
                return      # --max-wall: no new run
            result = one_run(k, duration, work, env)
            logs = Path(result['logs'])
            if 'tail' in result:
                target = keep / logs.name
                shutil.rmtree(target, ignore_errors=True)
                shutil.move(str(logs), str(target))
                result['logs'] = str(target)
            else:
                shutil.rmtree(logs, ignore_errors=True)
            with lock:
                results.append(result)
                if not quiet:
                    done = len(results)
                    if 'tail' in result or done % 10 == 0:
                        codes = collections.Counter(r['code'] for r in results)
                        print('%d runs: exit codes %s%s' % (
                            done, dict(codes), '; run %d: exit %s, logs %s' % (
                                k, result['code'], result['logs']) if 'tail' in result
                            else ''), flush=True)
    finally:
        os.close(fd)


def spread(values: list[float]) -> dict:
    values = sorted(values)
    if not values:
        return {}
    return {'median': statistics.median(values),
            'p90': values[min(len(values) - 1, int(0.9 * len(values)))], 'max': values[-1]}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--runs', type=int, default=200)
    parser.add_argument('--streams', type=int, default=2)
    parser.add_argument('--duration', type=float, default=1.0,
                        help='simulated seconds of each rig run')
    parser.add_argument('--max-wall', type=float, metavar='S',
                        help='start no new run after S seconds (default: run them all)')
    parser.add_argument('--tree', help='run the rig of this checkout (default: this one)')
    parser.add_argument('--keep-dir', default=str(Path(tempfile.gettempdir())
                                                  / 'bench_stress_failed'),
                        help='where the logs of the runs that did not exit 0 are kept')
    parser.add_argument('--json', action='store_true', help='print the figures as JSON')
    args = parser.parse_args(argv)
    if args.runs < 1 or args.streams < 1:
        parser.error('--runs and --streams must be at least 1')
    keep = Path(args.keep_dir)
    keep.mkdir(parents=True, exist_ok=True)
    results: list[dict] = []
    lock = threading.Lock()
    load_before = os.getloadavg()
    started = time.monotonic()
    with tempfile.TemporaryDirectory(prefix='bench_stress_') as tmp:
        threads = [threading.Thread(target=stream, args=(
            list(range(s, args.runs, args.streams)), args.duration, Path(tmp), args.tree,
            results, keep, lock, args.json,
            started + args.max_wall if args.max_wall else float('inf')))
            for s in range(args.streams)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    wall = time.monotonic() - started
    codes = collections.Counter(str(r['code']) for r in results)
    figures = {'runs': len(results), 'streams': args.streams, 'duration_s': args.duration,
               'wall_s': wall, 'exit_codes': dict(codes),
               'left_running': sum(len(r.get('left_running', ())) for r in results),
               'no_summary': sum('startup_s' not in r for r in results),
               'load_average_before': load_before, 'load_average_after': os.getloadavg()}
    for key in ('startup_s', 'run_s', 'stop_s', 'command_s'):
        figures[key] = spread([r[key] for r in results if key in r])
    figures['failed'] = [{k: r[k] for k in ('run', 'code', 'logs', 'tail') if k in r}
                         for r in results if 'tail' in r]
    if args.json:
        print(json.dumps(figures, indent=1))
        return
    print('%d lockstep rigs of %g s in %d streams, %.0f s wall' % (
        figures['runs'], args.duration, args.streams, wall))
    print('exit codes: %s' % ', '.join('%s: %d' % item for item in sorted(codes.items())))
    print('processes left running after their rig: %d; runs without a summary: %d' % (
        figures['left_running'], figures['no_summary']))
    for key, name in (('startup_s', 'start-up'), ('run_s', 'run'), ('stop_s', 'stop'),
                      ('command_s', 'command')):
        s = figures[key]
        if s:
            print('%-9s median %.2f s, p90 %.2f s, max %.2f s' % (
                name, s['median'], s['p90'], s['max']))
    for failed in figures['failed']:
        print('run %d: exit %s, logs in %s' % (failed['run'], failed['code'], failed['logs']))
    print('load average %s before, %s after' % (
        ' '.join('%.1f' % x for x in load_before),
        ' '.join('%.1f' % x for x in figures['load_average_after'])))


if __name__ == '__main__':
    main()
