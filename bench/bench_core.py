"""Speed of the physics core: prints figures, asserts nothing.

One dynamics evaluation (eq. 38 assembled and solved), one RK4 step, and the
wall time of the paper's 10 s scenario in each control mode.
"""
import time

import numpy as np

from stewart63_ros.core.control import PDController
from stewart63_ros.core.dynamics import Dynamics
from stewart63_ros.core.params import load_mechanism
from stewart63_ros.core.simulate import initial_state, run_continuous, run_sampled


def per_call(func, repeat=20000):
    func()
    best = float('inf')
    for _ in range(5):
        start = time.perf_counter()
        for _ in range(repeat // 5):
            func()
        best = min(best, (time.perf_counter() - start) / (repeat // 5))
    return best


def main():
    mech = load_mechanism()
    dyn = Dynamics(mech)
    law = PDController(mech)
    y = initial_state(mech)
    forces = np.full(6, 100.0)
    print('dynamics evaluation (derivative, Python call):  %7.2f us'
          % (per_call(lambda: dyn.derivative(y, forces)) * 1e6))
    print('dynamics + PD law (continuous RHS):              %7.2f us'
          % (per_call(lambda: dyn.derivative_with(y, law)) * 1e6))
    print('one RK4 step of 1 ms (4 evaluations, compiled):  %7.2f us'
          % (per_call(lambda: dyn.step(y, forces, 1e-3), 5000) * 1e6))
    for label, run in (('continuous (RK45, rtol 1e-8)', lambda: run_continuous(mech, 10.0, dyn=dyn)),
                       ('sampled 100 Hz (RK4, 1 ms)', lambda: run_sampled(mech, 10.0, 100.0, dyn=dyn)),
                       ('sampled 1 kHz (RK4, 1 ms)', lambda: run_sampled(mech, 10.0, 1000.0, dyn=dyn))):
        run()
        walls = []
        for _ in range(3):
            start = time.perf_counter()
            result = run()
            walls.append(time.perf_counter() - start)
        wall = min(walls)
        print('paper scenario 10 s, %-30s %7.3f s wall = %6.0fx real time, %d RHS evaluations'
              % (label + ':', wall, 10.0 / wall, result.rhs_evaluations))


if __name__ == '__main__':
    main()
