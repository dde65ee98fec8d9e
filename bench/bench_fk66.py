"""Forward kinematics of a 6-6 (core/mechanics/fk66.py): all assembly modes, and tracking.

Prints the time of ``all_modes`` (40 homotopy paths, median over poses and
repeats, CPU time of this process and wall time: the machine may be shared) and
of tracking (Newton from the last pose) per sample, on a semi-regular hexapod
and on a random non-planar 6-6. Targets: all modes <= 50 ms,
tracking <= 20 us a sample.

    python bench/bench_fk66.py [--repeats N]
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np
from scipy.spatial.transform import Rotation

from stewart63_ros.core.mechanics.fk66 import FKTracker66, ForwardKinematics66, _StartSystem


def semi_regular():
    ang_b = [k * 2 * np.pi / 3 + s * np.radians(6) for k in range(3) for s in (-1, 1)]
    ang_p = [k * 2 * np.pi / 3 - np.pi / 3 + s * np.radians(5) for k in range(3) for s in (1, -1)]
    base = np.c_[0.5 * np.cos(ang_b), 0.5 * np.sin(ang_b), np.zeros(6)]
    plat = np.c_[0.3 * np.cos(ang_p), 0.3 * np.sin(ang_p), np.zeros(6)]
    return base, np.roll(plat, -1, axis=0)


def random_general(seed=3):
    rng = np.random.default_rng(seed)
    return rng.uniform(-0.5, 0.5, (6, 3)), rng.uniform(-0.3, 0.3, (6, 3))


def bench_all_modes(fk, repeats, rng):
    cpu, wall, counts, reruns = [], [], [], 0
    for _ in range(repeats):
        t = np.array([*rng.uniform(-0.05, 0.05, 2), rng.uniform(0.35, 0.55)])
        rot = Rotation.from_euler('xyz', rng.uniform(-0.3, 0.3, 3)).as_matrix()
        lengths = fk.lengths(t, rot)
        c0, w0 = time.process_time(), time.perf_counter()
        modes = fk.all_modes(lengths)
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
        counts.append(len(modes))
        reruns += fk.reruns
    return np.array(cpu) * 1e3, np.array(wall) * 1e3, counts, reruns


def bench_tracking(fk, samples):
    t0, r0 = np.array([0.0, 0.0, 0.45]), np.eye(3)
    s = np.arange(samples) * 1e-3
    ts = np.c_[0.03 * np.sin(2 * s), 0.02 * np.sin(3 * s), 0.45 + 0.03 * np.sin(s)]
    rots = Rotation.from_euler('xyz', np.c_[0.1 * np.sin(2 * s), 0.05 * np.sin(s),
                                            0.2 * np.sin(0.5 * s)]).as_matrix()
    lengths = [fk.lengths(t, r) for t, r in zip(ts, rots)]
    tracker = FKTracker66(fk, t0, r0)
    tracker.solve(lengths[0])       # compile outside the timing
    tracker.reset(t0, r0)
    c0, w0 = time.process_time(), time.perf_counter()
    worst = 0.0
    for t, length in zip(ts, lengths):
        worst = max(worst, np.abs(tracker.solve(length).position - t).max())
    return ((time.process_time() - c0) / samples * 1e6,
            (time.perf_counter() - w0) / samples * 1e6, worst)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--repeats', type=int, default=40, help='poses per geometry')
    parser.add_argument('--samples', type=int, default=5000, help='tracking samples')
    args = parser.parse_args()
    c0 = time.process_time()
    _StartSystem.get()
    print('load %.2f (1 min) on %d cpus' % (os.getloadavg()[0], os.cpu_count()))
    print('start system (128 total-degree paths, once per process): %.0f ms cpu'
          % ((time.process_time() - c0) * 1e3))
    rng = np.random.default_rng(1)
    for name, geometry in (('semi-regular hexapod', semi_regular()),
                           ('random non-planar 6-6', random_general())):
        fk = ForwardKinematics66(*geometry)
        fk.all_modes(fk.lengths([0, 0, 0.45], np.eye(3)))      # compile
        cpu, wall, counts, reruns = bench_all_modes(fk, args.repeats, rng)
        print('%s: all modes %.1f ms cpu median (p90 %.1f, max %.1f), %.1f ms wall median; '
              'real modes %d..%d, re-runs %d of %d (target <= 50 ms)'
              % (name, np.median(cpu), np.percentile(cpu, 90), cpu.max(), np.median(wall),
                 min(counts), max(counts), reruns, args.repeats))
        us_cpu, us_wall, worst = bench_tracking(fk, args.samples)
        print('%s: tracking %.1f us/sample cpu, %.1f wall, max |t error| %.1e m '
              '(target <= 20 us)' % (name, us_cpu, us_wall, worst))


if __name__ == '__main__':
    main()
