"""Our core and MuJoCo on the paper's 10 s scenario, side by side: prints figures.

Both integrate the same mechanism (built from the same parameter file) with
continuous PD control. Accuracy is the largest leg-length error over the
100 Hz samples against our core at rtol 1e-11 (which MuJoCo converges to,
test/test_mujoco.py). MuJoCo runs RK4 (its Euler and implicitfast
integrators are first order: 2e-4 and 5e-4 m at a 2 ms step) at the largest
timestep that divides the 10 ms output period and keeps its error under
1e-6 m; that run's wall time is ``mujoco_paper_10s_s``.

Run: .venv/bin/python bench/bench_mujoco.py [--repeat N] [--params FILE]
(``--params config/hexapod66.yaml``: the packaged 6-6, each leg at its own
platform joint in both engines)
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from stewart63_ros.core.controllers.simulate import run_continuous
from stewart63_ros.core.mechanics.dynamics import Dynamics
from stewart63_ros.core.plumbing.params import load_setup
from stewart63_ros.mujoco_model import MujocoPlatform, Settings

DURATION = 10.0
TOLERANCE = 1e-6                                  # m, on leg lengths
TIMESTEPS = (1e-2, 5e-3, 2.5e-3, 2e-3, 1e-3, 5e-4)


def _lengths(dyn, states):
    return np.array([dyn.lengths_and_rates(y)[0] for y in states])


def _median_wall(func, repeat):
    walls = []
    for _ in range(repeat):
        start = time.perf_counter()
        func()
        walls.append(time.perf_counter() - start)
    return statistics.median(walls)


def measure(repeat: int = 5, verbose: bool = True, params=None) -> dict:
    setup = load_setup(params)
    mech = setup.mechanism
    dyn = Dynamics(mech)
    reference = _lengths(dyn, run_continuous(setup, DURATION, dyn=dyn, rtol=1e-11,
                                             atol=1e-13).states)
    ours_error = float(np.abs(_lengths(dyn, run_continuous(setup, DURATION, dyn=dyn).states)
                              - reference).max())
    ours_wall = _median_wall(lambda: run_continuous(setup, DURATION, dyn=dyn), repeat)
    chosen = None
    rows = []
    for dt in TIMESTEPS:
        platform = MujocoPlatform(setup, Settings(timestep=dt))
        _, lengths, _, _, violation = platform.run(DURATION)
        error = float(np.abs(lengths - reference).max())
        wall = _median_wall(lambda p=platform: p.run(DURATION), repeat)
        rows.append((dt, error, violation, wall))
        if error <= TOLERANCE and chosen is None:
            chosen = (dt, error, wall)
    if verbose:
        print('paper scenario on the %s, %g s simulated, continuous PD; error = max '
              '|L - L_ref| [m]' % (mech.layout, DURATION))
        print('%-30s %10s %12s %10s %9s' % ('engine', 'step', 'error', 'wall s', 'x realtime'))
        import mujoco  # lazy: optional (the bench extra): mujoco costs 240 ms
        print('%-30s %10s %12.2e %10.4f %9.0f' % ('ours (RK45, rtol 1e-8)', 'adaptive',
                                                 ours_error, ours_wall, DURATION / ours_wall))
        for dt, error, _violation, wall in rows:
            print('%-30s %8.2g s %12.2e %10.4f %9.0f%s'
                  % ('MuJoCo %s RK4' % mujoco.__version__,
                     dt, error, wall, DURATION / wall,
                     '   <- largest step within %g m' % TOLERANCE
                     if chosen and dt == chosen[0] else ''))
    if chosen is None:
        raise RuntimeError('no MuJoCo timestep reached %g m' % TOLERANCE)
    return {'mujoco_paper_10s_s': chosen[2], 'mujoco_timestep_s': chosen[0],
            'mujoco_error_m': chosen[1], 'sim_paper_10s_error_m': ours_error,
            'sim_paper_10s_s_vs_mujoco': ours_wall}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--repeat', type=int, default=5)
    parser.add_argument('--params', default=None, help='parameter file (default: the 6-3)')
    args = parser.parse_args()
    measure(args.repeat, params=args.params)


if __name__ == '__main__':
    main()
