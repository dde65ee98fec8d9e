"""Speed of the analysis: a 1000-run sweep and `analyze modes`. Prints figures, asserts nothing.

- ``sweep_1000_runs_s``: 1000 runs of the paper's 10 s scenario (continuous
  eq. (40), as `sim`) with platform_mass and kp[2] drawn from ranges, on one
  worker process per core, after the kernels are loaded (``sweep.run_sweep``'s
  wall time, as `sweep` prints it); median of ``repeat`` sweeps;
- ``analyze_modes_s``: the work of `analyze modes` on the default mechanism
  (equilibrium by forward kinematics, closed-loop linearization, eigenvalues),
  median of ``repeat`` calls in this process;
- ``analyze_modes_command_s``: the whole command, `analyze modes --json` in a
  new Python process (start-up and loading the kernels included).

Run: .venv/bin/python bench/bench_analysis.py [--repeat N]
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

import numpy as np

from stewart63_ros.core.analysis import linear, modal, sweep, sweep_plan
from stewart63_ros.core.plumbing.params import load_setup
from stewart63_ros.paths import default_params_path


def measure(repeat: int = 3, runs: int = 1000) -> dict:
    """{'sweep_1000_runs_s', 'analyze_modes_s', 'analyze_modes_command_s'}."""
    plan = sweep_plan.make_plan(default_params_path(),
                                [sweep_plan.parse_vary('platform_mass=10:20'),
                                 sweep_plan.parse_vary('kp[2]=3000:5000')])
    values = sweep_plan.draw_values(plan.variations, runs, seed=1)
    walls = []
    for _ in range(repeat):
        outcome = sweep.run_sweep(plan, values)
        walls.append(outcome['wall_time_s'])
        print('sweep: %d runs of the 10 s scenario in %.3f s wall (%d workers, %.0f runs/s, '
              '%d diverged)' % (runs, walls[-1], outcome['workers'], runs / walls[-1],
                                sum(r['diverged'] for r in outcome['rows'])), flush=True)
    setup = load_setup()
    modal.modes(linear.linearize(setup, 'pd'))            # load the kernels
    modes_walls = []
    for _ in range(max(5, repeat)):
        start = time.perf_counter()
        modal.modes(linear.linearize(setup, 'pd'))
        modes_walls.append(time.perf_counter() - start)
    command_walls = []
    for _ in range(repeat):
        start = time.perf_counter()
        subprocess.run([sys.executable, '-m', 'stewart63_ros.tools.analyze', 'modes', '--json'],
                       check=True, capture_output=True, env=dict(os.environ))
        command_walls.append(time.perf_counter() - start)
    out = {'sweep_1000_runs_s': float(np.median(walls)),
           'analyze_modes_s': float(np.median(modes_walls)),
           'analyze_modes_command_s': float(np.median(command_walls))}
    print('analyze modes: %.4f s of work (median of %d), %.2f s as a command (new process, '
          'median of %d)' % (out['analyze_modes_s'], len(modes_walls),
                             out['analyze_modes_command_s'], repeat), flush=True)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--repeat', type=int, default=3)
    args = parser.parse_args(argv)
    print(measure(repeat=args.repeat))
    return 0


if __name__ == '__main__':
    sys.exit(main())
