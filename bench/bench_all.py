"""`make bench`: every speed figure of the rig in one run, next to MuJoCo's.

Prints a table and writes bench/results.json. Each figure is a median over
repeated runs taken by this one command; the machine's name, CPU and core
count go with them. Figures, never assertions: a slow machine is not a bug.

Run: .venv/bin/python bench/bench_all.py [--quick] [--out bench/results.json]
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from stewart63_ros.tools.rig import control_params

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import bench_analysis  # noqa: E402
import bench_bags  # noqa: E402
import bench_bus  # noqa: E402
import bench_core  # noqa: E402
import bench_fk  # noqa: E402
import bench_laws  # noqa: E402
import bench_loop  # noqa: E402
import bench_mujoco  # noqa: E402
import bench_scenarios  # noqa: E402

#: key -> (unit, target on this machine, "<" or ">", what it is)
FIGURES = {
    'dynamics_eval_us': ('us', None, '<', 'one dynamics evaluation, eq. (38) assembled and solved'),
    'sim_paper_10s_s': ('s', 0.01, '<', "paper's 10 s scenario, our core (>= 1000x real time)"),
    'mujoco_paper_10s_s': ('s', None, '<', 'the same in MuJoCo, at the step it needs for 1e-6 m'),
    'fk_track_us': ('us', 20.0, '<', 'FK tracking solve, pose + twist (fk node)'),
    'fk_all_modes_us': ('us', 1000.0, '<', 'FK, every assembly mode'),
    'mujoco66_paper_10s_s': ('s', None, '<', 'the packaged 6-6 (config/hexapod66.yaml) in '
                             'MuJoCo, at the step it needs for 1e-6 m'),
    'sim66_paper_10s_s_vs_mujoco': ('s', None, '<', '  the same, our core (RK45, rtol 1e-8)'),
    'fk66_track_us': ('us', 20.0, '<', 'FK tracking solve on the 6-6, pose + twist (fk node)'),
    'fk66_all_modes_us': ('us', 50000.0, '<', '  the 6-6, every assembly mode (40 paths)'),
    'lockstep66_samples_per_s': ('1/s', None, '>', '  the 6-6, lockstep rig throughput'),
    'loop_latency_p50_us': ('us', 1000.0, '<',
                            'realtime 1 kHz rig: sample stamp -> force received'),
    'loop_latency_p99_us': ('us', 1000.0, '<', '  the same, 99th percentile'),
    'loop_missed_fraction': ('', 0.001, '<', '  cycles whose force came after the next sample'),
    'lockstep_samples_per_s': ('1/s', 5000.0, '>', 'lockstep rig throughput'),
    'machine_wake_late_fraction': ('', None, '<', '1 kHz sleep loop alone: wake-ups > 0.5 ms late'),
    'loop_missed_over_machine_late': ('', None, '<',
                                      '  loop_missed_fraction / machine_wake_late_fraction'),
    'lockstep_record_samples_per_s': ('1/s', 2000.0, '>', 'lockstep rig, recording everything'),
    'lockstep_composed_samples_per_s': ('1/s', 10000.0, '>',
                                        'lockstep, nodes composed in one process'),
    'lockstep_composed_record_samples_per_s': ('1/s', 5000.0, '>',
                                               '  the same, recording everything'),
    'loop_composed_p99_us': ('us', 500.0, '<', 'realtime 1 kHz, composed: latency p99'),
    'loop_composed_missed_fraction': ('', 0.001, '<', '  the same, missed cycles'),
    'record_msgs_per_s': ('1/s', None, '>', 'recording throughput with nothing lost'),
    'law_pd_setpoint_us': ('us', None, '<', 'controller per sample: pd towards a setpoint'),
    'law_pd_gravity_us': ('us', None, '<', '  pd_gravity on a reference motion'),
    'law_computed_torque_us': ('us', 50.0, '<', '  computed_torque on a reference motion'),
    'ct_loop_latency_p99_us': ('us', 1000.0, '<',
                               'realtime 1 kHz rig with computed_torque: latency p99'),
    'ct_loop_missed_fraction': ('', 0.001, '<', '  the same, missed cycles'),
    'sweep_1000_runs_s': ('s', 10.0, '<', "sweep: 1000 runs of the paper's 10 s scenario"),
    'analyze_modes_s': ('s', None, '<', 'analyze modes: linearize about the setpoint, modes'),
    'scenario_sim_100_s': ('s', 10.0, '<', 'scenario run: 100 sim scenarios of 10 s, every core'),
    'scenario_sim_cpu_ms': ('ms', None, '<', '  CPU per sim scenario of 10 s'),
    'scenario_sim_supervised_cpu_ms': ('ms', None, '<', '  the same with the supervisor in '
                                       'the loop'),
    'scenario_lockstep_10_s': ('s', None, '<', '10 lockstep rig scenarios of 2 s '
                               '(--scenario-rig)'),
    'bus_rt_separate_missed_fraction': ('', 0.001, '<', 'realtime 1 kHz over the bus, separate '
                                        'processes: bridge cycles missed'),
    'bus_rt_separate_tpdo_missed_fraction': ('', 0.001, '<', '  the same, TPDOs missed '
                                             '(the worst leg)'),
    'bus_rt_separate_sync_rpdo_p50_us': ('us', None, '<', '  the same, SYNC -> torque RPDO p50'),
    'bus_rt_separate_sync_rpdo_p99_us': ('us', 1000.0, '<', '  the same, p99'),
    'bus_rt_composed_missed_fraction': ('', 0.001, '<', 'realtime 1 kHz over the bus, composed '
                                        'and supervised: bridge cycles missed'),
    'bus_rt_composed_tpdo_missed_fraction': ('', 0.001, '<', '  the same, TPDOs missed '
                                             '(the worst leg)'),
    'bus_rt_composed_sync_rpdo_p50_us': ('us', None, '<', '  the same, SYNC -> torque RPDO p50'),
    'bus_rt_composed_sync_rpdo_p99_us': ('us', 1000.0, '<', '  the same, p99'),
    'bus_load_planned_percent': ('%', 100.0, '<', 'bus load planned (the busiest bus)'),
    'bus_load_measured_percent': ('%', None, '<', "  measured, on the bridge's /diagnostics"),
}
#: Figures only some runs measure (a flag), not missing without it.
OPTIONAL = {'scenario_lockstep_10_s'}
#: Figures a run may lack without a failure: a realtime run that missed every
#: RPDO has no SYNC -> RPDO figure, and the measured load needs the bridge to
#: report one.
MAY_LACK = {'bus_rt_separate_sync_rpdo_p50_us', 'bus_rt_separate_sync_rpdo_p99_us',
            'bus_rt_composed_sync_rpdo_p50_us', 'bus_rt_composed_sync_rpdo_p99_us',
            'bus_load_measured_percent'}


def hexapod66(repeat, count, duration, runs) -> dict:
    """bench_mujoco, bench_fk and the lockstep rig on config/hexapod66.yaml ('66' keys)."""
    params = HERE.parent / 'config' / 'hexapod66.yaml'
    out = bench_mujoco.measure(repeat=repeat, params=params)
    fk = bench_fk.measure(params, count=count, all_modes_count=40)
    loop = bench_loop.measure_lockstep(params, duration=duration, repeat=runs)
    return {'mujoco66_paper_10s_s': out['mujoco_paper_10s_s'],
            'sim66_paper_10s_s_vs_mujoco': out['sim_paper_10s_s_vs_mujoco'],
            'fk66_track_us': fk['fk_track_us'], 'fk66_all_modes_us': fk['fk_all_modes_us'],
            'lockstep66_samples_per_s': loop['lockstep_samples_per_s']}


def computed_torque_loop(duration, repeat) -> dict:
    """bench_loop.measure with the controller running computed_torque ('ct_' keys)."""
    bench_loop.EXTRA_PARAMS.update(control_params('computed_torque'))
    try:
        return {'ct_' + k: v for k, v in bench_loop.measure(duration=duration,
                                                            repeat=repeat).items()
                if k.startswith('loop_')}
    finally:
        bench_loop.EXTRA_PARAMS.clear()


def machine() -> dict:
    cpu = platform.processor()
    try:
        for line in Path('/proc/cpuinfo').read_text().splitlines():
            if line.startswith('model name'):
                cpu = line.split(':', 1)[1].strip()
                break
    except OSError:
        pass
    return {'name': platform.node(), 'cpu': cpu, 'cores': os.cpu_count(),
            'python': platform.python_version(), 'system': platform.platform()}


def wake_jitter(seconds: float = 5.0, late_us: float = 500.0) -> dict:
    """The machine's own floor for a 1 kHz loop: one process that only sleeps
    to each millisecond deadline (a cyclictest in Python). A rig cycle needs
    three such wake-ups (plant, controller, plant), so the rig's missed
    fraction cannot go below what this shows."""
    n, period = int(seconds * 1000), 1e-3
    late = np.empty(n)
    start = time.monotonic()
    for k in range(n):
        deadline = start + (k + 1) * period
        while True:
            now = time.monotonic()
            if now >= deadline:
                break
            ahead = deadline - now
            time.sleep(ahead - 50e-6 if ahead > 60e-6 else 0)
        late[k] = time.monotonic() - deadline
    out = {'machine_wake_late_fraction': float(np.mean(late > late_us * 1e-6)),
           'machine_wake_p999_us': float(np.percentile(late, 99.9) * 1e6)}
    print('1 kHz sleep loop, nothing else running: wake-up lateness p50 %.0f us, p99 %.0f us, '
          'p99.9 %.0f us, max %.0f us; %.3f %% later than %.0f us'
          % (np.percentile(late, 50) * 1e6, np.percentile(late, 99) * 1e6,
             out['machine_wake_p999_us'], late.max() * 1e6,
             100 * out['machine_wake_late_fraction'], late_us), flush=True)
    return out


def verdict(key, value) -> str:
    _, target, sense, _ = FIGURES[key]
    if target is None or value is None:
        return ''
    ok = value < target if sense == '<' else value > target
    return '%s target %s %g' % ('meets' if ok else 'MISSES', sense, target)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--quick', action='store_true',
                        help='fewer repeats and shorter runs (a smoke test of the script)')
    parser.add_argument('--out', default=str(HERE / 'results.json'))
    parser.add_argument('--scenario-rig', action='store_true',
                        help='also 10 lockstep rig scenarios (about a minute)')
    args = parser.parse_args(argv)
    repeat = 2 if args.quick else 5
    host = machine()
    print('machine %s: %s, %d cores, Python %s' % (host['name'], host['cpu'], host['cores'],
                                                  host['python']), flush=True)
    started = time.time()
    results: dict = {}
    sections = [
        ('physics core', lambda: bench_core.measure(repeat=repeat)),
        ('MuJoCo side by side', lambda: bench_mujoco.measure(repeat=repeat)),
        ('forward kinematics', lambda: bench_fk.measure(count=2000 if args.quick else 5000)),
        ('the packaged 6-6: MuJoCo side by side, forward kinematics, lockstep rig',
         lambda: hexapod66(repeat, 2000 if args.quick else 5000,
                           2.0 if args.quick else 5.0, 1 if args.quick else 3)),
        ('control laws, per sample as the controller runs them',
         lambda: bench_laws.measure(count=2000 if args.quick else 5000)),
        ('analysis: a 1000-run sweep, analyze modes',
         lambda: bench_analysis.measure(repeat=1 if args.quick else 3)),
        ('machine floor: 1 kHz wake-up jitter', lambda: wake_jitter(2.0 if args.quick else 5.0)),
        ('rig over DDS', lambda: bench_loop.measure(duration=2.0 if args.quick else 5.0,
                                                     repeat=1 if args.quick else 3)),
        ('rig over DDS, plant and controller SCHED_FIFO 10 (root only)',
         lambda: {'rt_priority_' + k: v for k, v in bench_loop.measure(
             duration=2.0 if args.quick else 5.0, repeat=1 if args.quick else 3,
             realtime_priority=10).items() if k.startswith('loop_')}
         if os.geteuid() == 0 else {}),
        ('rig over DDS, controller running computed_torque',
         lambda: computed_torque_loop(2.0 if args.quick else 5.0, 1 if args.quick else 3)),
        ('composed rig, and the rig recording',
         lambda: bench_loop.measure_variants(duration=2.0 if args.quick else 5.0,
                                             repeat=1 if args.quick else 3)),
        ('field bus: realtime 1 kHz, separate, and composed with the supervisor',
         lambda: bench_bus.measure(duration=2.0 if args.quick else 5.0,
                                   repeat=1 if args.quick else 3)),
        ('recording', lambda: bench_bags.measure(seconds=2.0 if args.quick else 3.0,
                                                 repeat=1 if args.quick else 3)),
        ('scenarios: scenario run in sim (and on the lockstep rig with --scenario-rig)',
         lambda: bench_scenarios.measure(runs=100,
                                         jobs=os.cpu_count() or 1,
                                         rig_runs=10 if args.scenario_rig else 0)),
    ]
    for title, run in sections:
        print('\n== %s' % title, flush=True)
        try:
            results.update(run())
        except Exception as exc:  # noqa: BLE001 - one failed section must not hide the others
            print('%s failed: %s: %s' % (title, type(exc).__name__, exc), flush=True)

    missed, floor = results.get('loop_missed_fraction'), results.get('machine_wake_late_fraction')
    if missed is not None and floor is not None:
        # The separate-process realtime rig against the machine's own floor,
        # both measured in this run (None: the floor was 0 in this run).
        results['loop_missed_over_machine_late'] = missed / floor if floor else None
    print('\n%-24s %14s  %-8s %s' % ('figure', 'median', '', 'what'))
    for key, (unit, _, _, what) in FIGURES.items():
        value = results.get(key)
        shown = 'n/a' if value is None else ('%.4g' % value)
        print('%-24s %14s %-4s %-60s %s' % (key, shown, unit, what, verdict(key, value)))
    if results.get('sim_paper_10s_s') and results.get('mujoco_paper_10s_s'):
        print('our core is %.1fx faster than MuJoCo at <= 1e-6 m on the paper scenario'
              % (results['mujoco_paper_10s_s'] / results['sim_paper_10s_s']))
    if results.get('sim66_paper_10s_s_vs_mujoco') and results.get('mujoco66_paper_10s_s'):
        print('on the packaged 6-6: %.1fx faster than MuJoCo at <= 1e-6 m'
              % (results['mujoco66_paper_10s_s'] / results['sim66_paper_10s_s_vs_mujoco']))
    if 'rt_priority_loop_missed_fraction' in results:
        print('with realtime_priority 10: p99 %.0f us, missed fraction %.4f'
              % (results['rt_priority_loop_latency_p99_us'],
                 results['rt_priority_loop_missed_fraction']))
    out = {'machine': host, 'date': datetime.datetime.now().isoformat(timespec='seconds'),
           'repeats': repeat, 'quick': args.quick, 'wall_s': round(time.time() - started, 1),
           **results}
    Path(args.out).write_text(json.dumps(out, indent=1) + '\n')
    print('written: %s' % args.out)
    missing = [k for k in FIGURES if k not in results and k not in MAY_LACK
               and (k not in OPTIONAL or args.scenario_rig)]
    return 1 if missing else 0


if __name__ == '__main__':
    sys.exit(main())
