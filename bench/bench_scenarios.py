"""Time `scenario run`: 100 sim scenarios of 10 s, and 10 lockstep rig scenarios.

The sim figure: the paper's scenario as a matrix of 100 values of
``platform_mass`` (eq. 40 sampled at 1 kHz, the compiled loop), five
expectations each, on local worker processes after the kernels are loaded
(``tools.scenario.run_all``, as ``scenario run --jobs N``); target < 10 s
wall. Also the CPU time of one such scenario, run serially (a loaded
machine stretches the wall time, not this), and with the supervisor in the
loop (a ``no_trip`` expectation: ``core.machine.supervisor.run_supervised``). The rig figure: 10
lockstep
scenarios (the paper's, ``--rig-duration`` s each), each starting `rig` on
its own leased ROS domain, ``--rig-jobs`` at a time (``--domain``: one
after the other on that id). Prints wall times and scenarios per second; never asserts.
Run: .venv/bin/python bench/bench_scenarios.py [--runs 100] [--jobs 2]
     [--rig-runs 10] [--rig-duration 2] [--rig-jobs 2] [--no-rig] [--domain ID]
"""
import argparse
import dataclasses
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from stewart63_ros.core.scenarios.parsing import load_scenarios
from stewart63_ros.core.scenarios.scenario import Expectation
from stewart63_ros.tools.scenario import run_all

EXPECT = """    expect:
      final_error_percent: {max: 2.0}
      max_force: {max: 3000.0}
      settling_time_s: {max: 5.0}
      overshoot_percent: {max: 10.0}
      endstop_samples: {max: 0}
"""


def scenario_file(folder: Path, runs: int, run: str, duration: float) -> Path:
    masses = ', '.join('%.4f' % m for m in np.linspace(10.0, 20.0, runs))
    path = folder / ('%s.yaml' % run)
    path.write_text('scenarios:\n  - name: bench\n    run: %s\n    duration: %g\n'
                    '    matrix: {params.platform_mass: [%s]}\n%s' % (run, duration, masses,
                                                                     EXPECT))
    return path


def measure(runs=100, jobs=2, rig_runs=10, rig_duration=2.0, rig_jobs=2, domain=None):
    """{'scenario_sim_100_s': wall, 'scenario_sim_cpu_ms', 'scenario_sim_supervised_cpu_ms',
    'scenario_lockstep_10_s': wall (only with rig_runs)}."""
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        sims = load_scenarios(scenario_file(Path(tmp), runs, 'sim', 10.0))
        run_all(sims[:jobs], jobs=1, keep_traces=False)        # load the kernels here
        start = time.perf_counter()
        outcomes = run_all(sims, jobs=jobs, keep_traces=False)
        wall = time.perf_counter() - start
        passed = sum(o.passed for o in outcomes)
        print('%d sim scenarios of 10 s (%d passed), %d workers: %.2f s wall, %.0f scenarios/s; '
              'median wall per scenario in its worker %.0f ms'
              % (len(sims), passed, jobs, wall, len(sims) / wall,
                 1e3 * float(np.median([o.wall_s for o in outcomes]))))
        out['scenario_sim_%d_s' % runs] = wall
        # CPU time per scenario in this process: what a loaded machine does not change
        cpu = time.process_time()
        run_all(sims[:10], jobs=1, keep_traces=False)
        cpu = (time.process_time() - cpu) / 10
        print('CPU per scenario (serial, 10 of them): %.1f ms; %d of them on %d idle cores: '
              '%.2f s' % (1e3 * cpu, len(sims), jobs, cpu * len(sims) / jobs))
        out['scenario_sim_cpu_ms'] = 1e3 * cpu
        # With the supervisor in the loop (a trip expectation): run_supervised,
        # a Python loop per sample, not the compiled one
        no_trip = Expectation('no_trip', 'max', 0.0)
        supervised = [dataclasses.replace(s, expect=s.expect + (no_trip,)) for s in sims[:3]]
        cpu = time.process_time()
        run_all(supervised, jobs=1, keep_traces=False)
        cpu = (time.process_time() - cpu) / len(supervised)
        print('CPU per scenario with the supervisor in the loop (serial, %d of them): %.0f ms'
              % (len(supervised), 1e3 * cpu))
        out['scenario_sim_supervised_cpu_ms'] = 1e3 * cpu
        if rig_runs:
            rigs = load_scenarios(scenario_file(Path(tmp), rig_runs, 'lockstep', rig_duration))
            start = time.perf_counter()
            outcomes = run_all(rigs, jobs=rig_jobs, keep_traces=False, domain=domain)
            wall = time.perf_counter() - start
            each = [o.wall_s for o in outcomes]
            print('%d lockstep scenarios of %g s (%d passed, %d failed runs), %s: %.1f s wall; '
                  'per scenario median %.1f s (start-up included)'
                  % (len(rigs), rig_duration, sum(o.passed for o in outcomes),
                     sum(bool(o.error) for o in outcomes),
                     'one at a time on domain %d' % domain if domain is not None
                     else '%d at a time' % rig_jobs, wall, float(np.median(each))))
            for o in outcomes:
                if o.error:
                    print('  %s: %s' % (o.scenario.name, o.error))
            out['scenario_lockstep_%d_s' % rig_runs] = wall
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--runs', type=int, default=100)
    parser.add_argument('--jobs', type=int, default=os.cpu_count() or 1)
    parser.add_argument('--rig-runs', type=int, default=10)
    parser.add_argument('--rig-duration', type=float, default=2.0)
    parser.add_argument('--rig-jobs', type=int, default=2)
    parser.add_argument('--no-rig', action='store_true')
    parser.add_argument('--domain', type=int, default=None,
                        help='run the rig scenarios on this ROS domain, one at a time')
    args = parser.parse_args()
    measure(args.runs, args.jobs, 0 if args.no_rig else args.rig_runs, args.rig_duration,
            args.rig_jobs, args.domain)


if __name__ == '__main__':
    main()
