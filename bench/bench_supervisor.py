"""The supervisor's cost: prints figures, asserts nothing.

- per sample, in-process (core/machine/supervisor.py): ``on_sample`` + ``on_request``
  of an untripped supervisor on a moving platform (forward kinematics for
  the pose box, the tracking check), and the safe action's forces once
  tripped (the descent: forward kinematics and the gravity model);
- the lockstep rig's throughput with the supervisor out and in
  (``rig --supervisor``), plant + controller, alternating runs in one sitting;
  with ``--bus``, the same over the field bus (``rig --bus canopen``: the
  bridge between the bus and the supervisor).

    bench_supervisor.py [--duration S] [--repeat N] [--bus] [--json]
"""
from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time

import numpy as np
from bench_loop import PAIR, private_domain

from stewart63_ros.core.machine.supervisor import run_supervised, supervisor_from_params
from stewart63_ros.core.plumbing.params import default_params_path, load_setup
from stewart63_ros.tools.rig_process import Rig


def per_sample_us(samples: int = 5000) -> dict:
    """Microseconds per sample of the core's checks and of the descent."""
    setup = load_setup(default_params_path())
    params = setup.to_params()
    sup = supervisor_from_params(setup, params, 1000.0)
    out = run_supervised(setup, sup, samples / 1000.0, 1000.0)     # a real trajectory
    lengths, forces = out['measured'], out['requests']
    rates = np.gradient(lengths, 1e-3, axis=0)
    timings = {}
    for name in ('checks', 'descent'):
        sup = supervisor_from_params(setup, params, 1000.0)
        sup.limits = sup.limits.__class__(**dict(sup.limits.__dict__, tracking_time=1e9,
                                                  leg_speed=0.0))
        if name == 'descent':
            sup.on_sample(0, lengths[0], rates[0])
            sup.trip_now('estop', 'bench')
        start = time.perf_counter()
        for k in range(1, len(lengths)):
            ns = k * 1_000_000
            sup.on_sample(ns, lengths[k], rates[k])
            if name == 'checks':
                sup.on_request(ns, forces[k])
            else:
                sup.safe_forces(ns)
        timings[name + '_us'] = (time.perf_counter() - start) / (len(lengths) - 1) * 1e6
    return timings


def rig_throughput(duration: float, repeat: int, bus: str | None = None) -> dict:
    """Lockstep samples per second, plant + controller, supervisor out and in
    (``bus``: 'canopen', over the field bus)."""
    results = {'out': [], 'in': []}
    with private_domain():
        for _ in range(repeat):
            for key in ('out', 'in'):
                summary = run_rig(duration, PAIR, key == 'in', bus)
                if summary:
                    results[key].append(summary['samples'] / summary['wall_time_s'])
    return {key: statistics.median(v) if v else None for key, v in results.items()} | {
        'runs': {key: [round(x) for x in v] for key, v in results.items()}}


def run_rig(duration, nodes, supervisor, bus=None):
    log_dir = tempfile.mkdtemp(prefix='bench_supervisor_')
    rig = Rig(default_params_path(), 'lockstep', duration, nodes=nodes, log_dir=log_dir,
              supervisor=supervisor, bus=bus)
    try:
        rig.start()
        ok = rig.wait(timeout=60 + 50 * duration)
    except RuntimeError as exc:
        print('run failed: %s; logs in %s' % (exc, log_dir))
        ok = False
    finally:
        rig.stop()
    summary = rig.summary()
    return summary if ok else None


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--duration', type=float, default=5.0)
    parser.add_argument('--repeat', type=int, default=3)
    parser.add_argument('--bus', action='store_true',
                        help='the rigs over the field bus (rig --bus canopen)')
    parser.add_argument('--json', action='store_true')
    args = parser.parse_args(argv)
    figures = per_sample_us()
    print('supervisor core per sample: checks %.1f us, descent %.1f us'
          % (figures['checks_us'], figures['descent_us']), flush=True)
    figures.update(rig_throughput(args.duration, args.repeat, 'canopen' if args.bus else None))
    print('lockstep plant+controller%s: %s samples/s without the supervisor, %s with it '
          '(runs: %s)' % (' over the bus' if args.bus else '', _round(figures['out']),
                          _round(figures['in']), figures['runs']))
    if args.json:
        print(json.dumps(figures))
    return 0


def _round(value):
    return 'failed' if value is None else '%.0f' % value


if __name__ == '__main__':
    raise SystemExit(main())
