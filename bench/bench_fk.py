"""Time the forward kinematics: one tracking solve and one all-modes solve.

Targets: tracking < 20 us; all modes < 1 ms for the 6-3 (its degree-16
polynomial), < 50 ms for a 6-6 (40 homotopy paths, core/mechanics/fk66.py;
``--params config/hexapod66.yaml``), through the same entry points.
Prints medians over many calls (and the 90th percentile, since a shared
machine is noisy). ``measure()`` returns the figures for bench/bench_all.py.
Run: .venv/bin/python bench/bench_fk.py [--params FILE] [--count N]
"""
import argparse
import time

import numpy as np

from stewart63_ros.core.mechanics.fk import FKTracker, ForwardKinematics
from stewart63_ros.core.mechanics.kinematics import leg_lengths
from stewart63_ros.core.mechanics.rotation import rotation_from_euler
from stewart63_ros.core.plumbing.params import load_setup


def timings(func, count):
    out = np.empty(count)
    for k in range(count):
        start = time.perf_counter()
        func(k)
        out[k] = time.perf_counter() - start
    return out * 1e6


def report(name, us, target):
    print('%-36s median %8.1f us   p90 %8.1f us   (target < %g us)'
          % (name, np.median(us), np.percentile(us, 90), target))


def smooth_path(mech, start, n):
    """Leg lengths and rates along a smooth 1 kHz path around the start pose:
    what the fk node sees, and the start pose."""
    s = np.arange(n) / 1000.0
    positions = np.asarray(start) + 0.05 * np.c_[
        np.sin(2 * s), np.sin(3 * s), 0.5 * np.sin(1.3 * s)]
    thetas = 0.1 * np.c_[np.sin(1.7 * s), np.sin(2.3 * s), np.sin(0.9 * s)]
    rots = [rotation_from_euler(th) for th in thetas]
    lengths = [leg_lengths(mech, t, r) for t, r in zip(positions, rots)]
    rates = np.gradient(np.array(lengths), 1e-3, axis=0)
    return lengths, rates, positions[0], rots[0]


def measure(params=None, count=5000, verbose=True, all_modes_count=1000):
    """{'fk_track_us', 'fk_all_modes_us'}: medians per call, as the fk node calls them
    (pose + twist + quaternion; every assembly mode, on at most ``all_modes_count``
    samples: a 6-6's take ~30 ms each)."""
    setup = load_setup(params)
    mech, task = setup.mechanism, setup.task
    fk = ForwardKinematics(mech, start=(task.initial_position, task.initial_rotation))
    lengths, rates, pos0, rot0 = smooth_path(mech, task.initial_position, count)

    start = time.perf_counter()
    fk.all_modes(task.setpoint_lengths)
    FKTracker(fk).solve(lengths[0])
    if verbose:
        print('first call (numba cache load or compile): %.2f s' % (time.perf_counter() - start))

    tracker = FKTracker(fk, pos0, rot0)
    pose_us = timings(lambda k: tracker.solve(lengths[k]), count)
    tracker = FKTracker(fk, pos0, rot0)
    twist_us = timings(lambda k: tracker.solve(lengths[k], rates[k]), count)
    tracker = FKTracker(fk, pos0, rot0)
    node_us = timings(lambda k: tracker.solve(lengths[k], rates[k]).quaternion, count)
    m = min(count, all_modes_count)
    all_us = timings(lambda k: fk.all_modes(lengths[k]), m)
    if verbose:
        report('tracking solve (pose)', pose_us, 20)
        report('tracking solve (pose + twist)', twist_us, 20)
        report('  + quaternion (as the fk node)', node_us, 20)
        modes = int(np.median([len(fk.all_modes(lengths[k]))
                               for k in range(0, m, max(1, m // 10))]))
        report('all-modes solve (%s, %d modes)' % (mech.layout, modes), all_us,
               1000 if mech.layout == '6-3' else 50000)
    return {'fk_track_us': float(np.median(node_us)),
            'fk_all_modes_us': float(np.median(all_us))}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--params', default=None)
    parser.add_argument('--count', type=int, default=5000)
    parser.add_argument('--all-modes-count', type=int, default=1000,
                        help='all-modes solves timed at most (a 6-6: ~30 ms each)')
    args = parser.parse_args()
    measure(args.params, args.count, all_modes_count=args.all_modes_count)


if __name__ == '__main__':
    main()
