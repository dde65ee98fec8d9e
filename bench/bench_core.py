"""Speed of the physics core: prints figures, asserts nothing.

One dynamics evaluation (eq. 38 assembled and solved), one RK4 step, and the
wall time of the paper's 10 s scenario in each control mode: the compiled
integrators (scipy's RK45 compiled, the compiled sampled loop) with, for
comparison, scipy's solve_ivp and the sampled loop in Python.
``measure()`` returns the figures for bench/bench_all.py.
"""
import time

import numpy as np

from stewart63_ros.core.controllers.laws import PDController
from stewart63_ros.core.controllers.simulate import initial_state, run_continuous, run_sampled
from stewart63_ros.core.mechanics.dynamics import Dynamics
from stewart63_ros.core.plumbing.params import load_setup


def per_call(func, repeat=20000):
    func()
    best = float('inf')
    for _ in range(5):
        start = time.perf_counter()
        for _ in range(repeat // 5):
            func()
        best = min(best, (time.perf_counter() - start) / (repeat // 5))
    return best


def measure(repeat=7, verbose=True):
    """{'dynamics_eval_us', 'sim_paper_10s_s'}: one dynamics evaluation (Python
    call, best of 5 batches) and the paper's 10 s scenario, continuous control
    (median of ``repeat`` runs); prints the comparison lines too."""
    setup = load_setup()
    mech = setup.mechanism
    dyn = Dynamics(mech)
    gains = PDController(setup).pd_gains()
    y = initial_state(setup.task)
    forces = np.full(6, 100.0)
    eval_us = per_call(lambda: dyn.derivative(y, forces)) * 1e6
    print('dynamics evaluation (derivative, Python call):  %7.2f us' % eval_us)
    print('dynamics + PD law (continuous RHS):              %7.2f us'
          % (per_call(lambda: dyn.derivative_with(y, gains)) * 1e6))
    print('one RK4 step of 1 ms (4 evaluations, compiled):  %7.2f us'
          % (per_call(lambda: dyn.step(y, forces, 1e-3), 5000) * 1e6))
    scenarios = (
        ('continuous (RK45 compiled, rtol 1e-8)', lambda: run_continuous(setup, 10.0, dyn=dyn)),
        ('continuous (scipy solve_ivp RK45)',
         lambda: run_continuous(setup, 10.0, dyn=dyn, integrator='scipy')),
        ('sampled 100 Hz (RK4 1 ms, compiled loop)',
         lambda: run_sampled(setup, 10.0, 100.0, dyn=dyn)),
        ('sampled 100 Hz (Python loop)',
         lambda: run_sampled(setup, 10.0, 100.0, dyn=dyn, loop='python')),
        ('sampled 1 kHz (RK4 1 ms, compiled loop)',
         lambda: run_sampled(setup, 10.0, 1000.0, dyn=dyn)),
        ('sampled 1 kHz (Python loop)',
         lambda: run_sampled(setup, 10.0, 1000.0, dyn=dyn, loop='python')))
    walls_of = {}
    for label, run in scenarios:
        run()
        walls = []
        for _ in range(repeat):
            start = time.perf_counter()
            result = run()
            walls.append(time.perf_counter() - start)
        wall = walls_of[label] = float(np.median(walls))
        print('paper scenario 10 s, %-42s %7.4f s wall (median of %d) = %6.0fx real time, '
              '%d RHS evaluations (%.2f us each, all included)'
              % (label + ':', wall, repeat, 10.0 / wall, result.rhs_evaluations,
                 wall / result.rhs_evaluations * 1e6), flush=True)
    return {'dynamics_eval_us': eval_us, 'sim_paper_10s_s': walls_of[scenarios[0][0]]}


def main():
    measure()


if __name__ == '__main__':
    main()
