"""Closed-loop speed over DDS: prints figures, asserts nothing.

- realtime at 1 kHz: latency from a leg_lengths stamp to the plant's receipt
  of the answering force (p50, p99, max) and missed cycles;
- lockstep: samples per second.
Each run: plant + controller + fk as separate processes on a private domain.
"""
import argparse
import os
import random
import tempfile
import time

from stewart63_ros.core.params import default_params_path
from stewart63_ros.tools.rig import Rig


def run(mode, duration, nodes):
    rig = Rig(default_params_path(), mode, duration, nodes=nodes,
              log_dir=tempfile.mkdtemp(prefix='bench_loop_'))
    start = time.monotonic()
    rig.start()
    ok = rig.wait(timeout=60 + 50 * duration)
    rig.stop()
    summary = rig.summary()
    if not ok or summary is None:
        print('%s run failed; logs in %s' % (mode, rig.log_dir))
        return None
    summary['total_wall_s'] = time.monotonic() - start
    return summary


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--duration', type=float, default=5.0)
    args = parser.parse_args()
    os.environ['ROS_DOMAIN_ID'] = str(random.randint(150, 230))
    for nodes in (('plant', 'controller'), ('plant', 'controller', 'fk')):
        s = run('realtime', args.duration, nodes)
        if s:
            lat = s['loop_latency']
            print('realtime 1 kHz, %-24s latency p50 %.3f ms, p99 %.3f ms, max %.3f ms; '
                  'missed %d of %d cycles (%.3f %%), late %d'
                  % ('+'.join(nodes) + ':', lat['p50_ms'], lat['p99_ms'], lat['max_ms'],
                     s['missed_cycles'], s['samples'], 100.0 * s['missed_cycles'] / s['samples'],
                     s['late_cycles']))
        s = run('lockstep', args.duration, nodes)
        if s:
            lat = s['loop_latency']
            print('lockstep,        %-24s %.0f samples/s (round trip p50 %.3f ms, p99 %.3f ms)'
                  % ('+'.join(nodes) + ':', s['samples'] / s['wall_time_s'], lat['p50_ms'],
                     lat['p99_ms']))


if __name__ == '__main__':
    main()
