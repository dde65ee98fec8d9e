"""Closed-loop speed over DDS: prints figures, asserts nothing.

- realtime at 1 kHz: latency from a leg_lengths stamp to the plant's receipt
  of the answering force (p50, p99, max) and missed cycles (the answer came
  after the next sample);
- lockstep: samples per second.
Each run: plant + controller (+ fk) as separate processes on a private domain;
``--variants``: the composed rig (one process) and recording.

    bench_loop.py [--duration S] [--repeat N] [--nodes full|both] [--realtime-priority P]
                  [--json] [--variants]

``measure(duration, repeat)`` returns the medians over ``repeat`` runs of the
full rig (plant + controller + fk) as a dict, for bench/bench_all.py.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import statistics
import tempfile
import time

from stewart63_ros.core.plumbing.params import default_params_path
from stewart63_ros.paths import try_lock_domain
from stewart63_ros.tools.rig import control_params
from stewart63_ros.tools.rig_process import Rig

FULL = ('plant', 'controller', 'fk')
PAIR = ('plant', 'controller')


def lease_domain() -> tuple[int, int]:
    """(domain id, lock fd): a domain no other live holder of the lock uses."""
    start = os.getpid() % 100
    for k in range(100):
        domain = 1 + (start + k) % 100
        fd = try_lock_domain(domain)
        if fd is not None:
            return domain, fd
    raise RuntimeError('no free ROS domain id on this machine')


@contextlib.contextmanager
def private_domain():
    """Inside: a leased domain id and loopback discovery for the processes
    started (ROS_DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE); both restored after."""
    domain, fd = lease_domain()
    saved = {k: os.environ.get(k) for k in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE')}
    os.environ['ROS_DOMAIN_ID'] = str(domain)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    try:
        yield domain
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
        os.close(fd)


#: Node parameters of every run (``--control-law``: the controller's law).
EXTRA_PARAMS = {}


def run(mode, duration, nodes, realtime_priority=0, compose=False, record=False, params=None):
    """One rig run; the plant's summary (plus total_wall_s), or None if it failed.
    ``compose``: the nodes in one process (``rig --compose``); ``record``:
    recording every topic into a bag in a temporary folder; ``params``: the
    parameter file (default: the packaged 6-3)."""
    extra = {'realtime_priority': realtime_priority} if realtime_priority else {}
    if EXTRA_PARAMS:
        extra['extra_params'] = EXTRA_PARAMS
    log_dir = tempfile.mkdtemp(prefix='bench_loop_')
    bag = os.path.join(log_dir, 'bag') if record else None
    rig = Rig(params or default_params_path(), mode, duration, nodes=nodes, log_dir=log_dir,
              record=bag, compose=compose, **extra)
    start = time.monotonic()
    try:
        rig.start()
        ok = rig.wait(timeout=60 + 50 * duration)
    except RuntimeError as exc:
        print('%s run failed: %s; logs in %s' % (mode, exc, rig.log_dir))
        ok = False
    finally:
        rig.stop()
    summary = rig.summary()
    if not ok or summary is None:
        print('%s run failed; logs in %s' % (mode, rig.log_dir))
        return None
    summary['total_wall_s'] = time.monotonic() - start
    if bag:
        shutil.rmtree(bag, ignore_errors=True)
    return summary


def realtime_figures(s) -> dict:
    lat = s['loop_latency']
    return {'p50_us': lat['p50_ms'] * 1e3, 'p99_us': lat['p99_ms'] * 1e3,
            'max_us': lat['max_ms'] * 1e3, 'missed': s['missed_cycles'],
            'late': s['late_cycles'], 'samples': s['samples'],
            'missed_fraction': s['missed_cycles'] / s['samples']}


def lockstep_figures(s) -> dict:
    lat = s['loop_latency']
    return {'samples_per_s': s['samples'] / s['wall_time_s'], 'p50_us': lat['p50_ms'] * 1e3,
            'p99_us': lat['p99_ms'] * 1e3, 'timeouts': s['force_timeouts']}


def print_realtime(nodes, f):
    print('realtime 1 kHz, %-24s latency p50 %.3f ms, p99 %.3f ms, max %.3f ms; '
          'missed %d of %d cycles (%.3f %%), late %d'
          % ('+'.join(nodes) + ':', f['p50_us'] / 1e3, f['p99_us'] / 1e3, f['max_us'] / 1e3,
             f['missed'], f['samples'], 100.0 * f['missed_fraction'], f['late']), flush=True)


def print_lockstep(nodes, f):
    print('lockstep,        %-24s %.0f samples/s (round trip p50 %.3f ms, p99 %.3f ms)'
          % ('+'.join(nodes) + ':', f['samples_per_s'], f['p50_us'] / 1e3, f['p99_us'] / 1e3),
          flush=True)


def _median(runs, key):
    values = [r[key] for r in runs]
    return statistics.median(values) if values else None


def collect(duration, repeat, node_sets=(FULL,), quiet=False, realtime_priority=0) -> dict:
    """Runs realtime then lockstep, ``repeat`` times, for every node set;
    {nodes: {'realtime': [figures...], 'lockstep': [figures...]}}."""
    out = {nodes: {'realtime': [], 'lockstep': []} for nodes in node_sets}
    with private_domain():
        for _ in range(repeat):
            for nodes in node_sets:
                s = run('realtime', duration, nodes, realtime_priority)
                if s:
                    out[nodes]['realtime'].append(realtime_figures(s))
                    if not quiet:
                        print_realtime(nodes, out[nodes]['realtime'][-1])
                s = run('lockstep', duration, nodes)    # (FIFO: no faster there)
                if s:
                    out[nodes]['lockstep'].append(lockstep_figures(s))
                    if not quiet:
                        print_lockstep(nodes, out[nodes]['lockstep'][-1])
    return out


def medians(runs: dict) -> dict:
    rt, ls = runs['realtime'], runs['lockstep']
    return {'loop_latency_p50_us': _median(rt, 'p50_us'),
            'loop_latency_p99_us': _median(rt, 'p99_us'),
            'loop_latency_max_us': _median(rt, 'max_us'),
            'loop_missed_fraction': _median(rt, 'missed_fraction'),
            'lockstep_samples_per_s': _median(ls, 'samples_per_s'),
            'lockstep_round_trip_p50_us': _median(ls, 'p50_us'),
            'loop_runs': len(rt), 'lockstep_runs': len(ls)}


def measure(duration: float = 5.0, repeat: int = 3, realtime_priority: int = 0) -> dict:
    """Medians over ``repeat`` runs of the full rig (plant + controller + fk):
    loop_latency_p50_us, loop_latency_p99_us, loop_missed_fraction (realtime,
    1 kHz) and lockstep_samples_per_s (plus a few more figures).
    ``realtime_priority``: for the realtime runs, see ``rig --realtime-priority``
    (0: normal scheduling)."""
    result = medians(collect(duration, repeat, realtime_priority=realtime_priority)[FULL])
    result['loop_realtime_priority'] = realtime_priority
    print('rig over DDS%s, median of %d: realtime p50 %s us, p99 %s us, missed %s; '
          'lockstep %s samples/s' % (
              ' (SCHED_FIFO %d)' % realtime_priority if realtime_priority else '',
              result['loop_runs'], _fmt(result['loop_latency_p50_us']),
              _fmt(result['loop_latency_p99_us']), _fmt(result['loop_missed_fraction'], '%.4f'),
              _fmt(result['lockstep_samples_per_s'], '%.0f')), flush=True)
    return result


def measure_lockstep(params, duration: float = 5.0, repeat: int = 3) -> dict:
    """lockstep_samples_per_s of the full rig on another parameter file (the
    packaged 6-6: bench_all.py), median of ``repeat`` runs."""
    runs = []
    with private_domain():
        for _ in range(repeat):
            s = run('lockstep', duration, FULL, params=params)
            if s:
                runs.append(lockstep_figures(s))
                print_lockstep(FULL, runs[-1])
    return {'lockstep_samples_per_s': _median(runs, 'samples_per_s')}


def measure_variants(duration: float = 5.0, repeat: int = 3) -> dict:
    """Medians over ``repeat`` runs of each variant of the full rig, taken
    in turn (so a busy spell of the machine hits them alike):

    - ``lockstep_composed_samples_per_s``: ``rig --compose`` (one process);
    - ``lockstep_composed_record_samples_per_s``: the same with ``--record``;
    - ``lockstep_record_samples_per_s``: separate processes with ``--record``;
    - ``loop_composed_p50_us``, ``loop_composed_p99_us``,
      ``loop_composed_missed_fraction``: ``rig --compose --mode realtime``.

    Samples per second are the plant loop's (start-up excluded)."""
    runs = {'composed': [], 'composed_record': [], 'record': [], 'composed_rt': []}
    with private_domain():
        for _ in range(repeat):
            for key, mode, compose, record in (('composed', 'lockstep', True, False),
                                               ('composed_record', 'lockstep', True, True),
                                               ('record', 'lockstep', False, True),
                                               ('composed_rt', 'realtime', True, False)):
                s = run(mode, duration, FULL, compose=compose, record=record)
                if not s:
                    continue
                label = ('composed' if compose else 'separate') + (' + record' if record
                                                                   else '')
                if mode == 'lockstep':
                    runs[key].append(lockstep_figures(s))
                    print_lockstep((label,), runs[key][-1])
                else:
                    runs[key].append(realtime_figures(s))
                    print_realtime((label,), runs[key][-1])
    return {'lockstep_composed_samples_per_s': _median(runs['composed'], 'samples_per_s'),
            'lockstep_composed_record_samples_per_s': _median(runs['composed_record'],
                                                              'samples_per_s'),
            'lockstep_record_samples_per_s': _median(runs['record'], 'samples_per_s'),
            'loop_composed_p50_us': _median(runs['composed_rt'], 'p50_us'),
            'loop_composed_p99_us': _median(runs['composed_rt'], 'p99_us'),
            'loop_composed_missed_fraction': _median(runs['composed_rt'], 'missed_fraction')}


def spread(values, form='%.0f') -> str:
    """'median (min..max)' of ``values``, 'n/a' if there are none."""
    if not values:
        return 'n/a'
    return (form + ' (' + form + '..' + form + ')') % (statistics.median(values), min(values),
                                                     max(values))


def _fmt(value, form='%.0f'):
    return 'n/a' if value is None else form % value


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--duration', type=float, default=5.0, help='simulated s per run')
    parser.add_argument('--repeat', type=int, default=1, help='runs of each kind (medians)')
    parser.add_argument('--nodes', choices=('full', 'both'), default='both',
                        help='full: plant+controller+fk only; both: also plant+controller')
    parser.add_argument('--realtime-priority', type=int, default=0, metavar='P',
                        help='realtime runs: plant and controller SCHED_FIFO at priority P, '
                        'fk P-1 (rig --realtime-priority; needs root); default 0: normal '
                        'scheduling')
    parser.add_argument('--variants', action='store_true',
                        help='instead: the composed rig (lockstep, with and without '
                        'recording; realtime) and the separate rig with recording')
    parser.add_argument('--control-law', metavar='NAME', default=None,
                        help="the controller's law (rig --control-law), e.g. computed_torque "
                        'to compare its loop figures with pd (the default)')
    parser.add_argument('--json', action='store_true',
                        help='end with one line: JSON of the medians per node set')
    args = parser.parse_args()
    if args.control_law:
        EXTRA_PARAMS.update(control_params(args.control_law))
    if args.variants:
        result = measure_variants(args.duration, args.repeat)
        print(json.dumps(result, indent=1))
        return
    node_sets = (FULL,) if args.nodes == 'full' else (PAIR, FULL)
    runs = collect(args.duration, args.repeat, node_sets,
                   realtime_priority=args.realtime_priority)
    result = {}
    for nodes in node_sets:
        m = medians(runs[nodes])
        result['+'.join(nodes)] = m
        if args.repeat > 1:
            print('median of %d, %-22s realtime p50 %s us, p99 %s us, max %s us, missed %s %%; '
                  'lockstep %s samples/s' % (
                      m['loop_runs'], '+'.join(nodes) + ':', _fmt(m['loop_latency_p50_us']),
                      _fmt(m['loop_latency_p99_us']), _fmt(m['loop_latency_max_us']),
                      _fmt(None if m['loop_missed_fraction'] is None
                           else 100 * m['loop_missed_fraction'], '%.3f'),
                      _fmt(m['lockstep_samples_per_s'])))
    if args.json:
        print('BENCH_LOOP_JSON ' + json.dumps(result))


if __name__ == '__main__':
    main()
