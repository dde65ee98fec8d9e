"""Time the control laws per sample, as the controller node runs them.

For each law (pd towards a setpoint, pd on a reference motion, pd_gravity,
computed_torque, the user-law example), the call the node makes on every
leg_lengths sample: ``Controller.forces(t, lengths, rates)`` (reference
sample, law, checks, saturation), along a smooth 1 kHz path of leg lengths
and rates. Target: computed_torque <= 50 us per sample.
Prints medians and 90th percentiles; never asserts. ``measure()`` returns
{'law_<name>_us': median} for bench/bench_all.py.
Run: .venv/bin/python bench/bench_laws.py [--params FILE] [--count N]
"""
import argparse
import time

import numpy as np

from stewart63_ros.core.controllers.laws import Controller
from stewart63_ros.core.controllers.reference import Reference
from stewart63_ros.core.controllers.simulate import run_sampled
from stewart63_ros.core.mechanics.dynamics import Dynamics
from stewart63_ros.core.plumbing.params import load_setup

CASES = (('pd_setpoint', 'pd', False), ('pd_reference', 'pd', True),
         ('pd_gravity', 'pd_gravity', True), ('computed_torque', 'computed_torque', True),
         ('user_example', 'stewart63_ros.examples.my_law:LegPD', True))
TARGETS = {'computed_torque': 50.0}


def path(setup, n):
    mech = setup.mechanism
    """(times, lengths, rates, reference) along a smooth motion about the start pose."""
    t = np.arange(0.0, n / 1000.0 + 2.0, 0.01)
    centre = np.concatenate([setup.task.initial_position, setup.task.initial_orientation])
    poses = centre + np.outer(np.minimum(t, 1.0), [0.02, 0.01, 0.03, 0.02, 0.01, 0.03]) \
        * np.sin(2 * np.pi * 0.5 * t)[:, None]
    reference = Reference.from_poses(mech, t, poses)
    run = run_sampled(setup, n / 1000.0, 1000.0,
                      controller=Controller(setup, law='computed_torque', reference=reference))
    dyn = Dynamics(mech)
    samples = [dyn.lengths_and_rates(y) for y in run.states[:n]]
    return run.times[:n], [s[0] for s in samples], [s[1] for s in samples], reference


def measure(params=None, count=5000, verbose=True):
    setup = load_setup(params)
    times, lengths, rates, reference = path(setup, count)
    out = {}
    for name, law, with_reference in CASES:
        ctl = Controller(setup, law=law, reference=reference if with_reference else None)
        ctl.forces(0.0, lengths[0], rates[0])       # load the kernels
        us = np.empty(count)
        for k in range(count):
            start = time.perf_counter()
            ctl.forces(times[k], lengths[k], rates[k])
            us[k] = time.perf_counter() - start
        us *= 1e6
        out['law_%s_us' % name] = float(np.median(us))
        if verbose:
            target = TARGETS.get(name)
            print('%-20s median %7.1f us   p90 %7.1f us%s' % (
                name, np.median(us), np.percentile(us, 90),
                '   (target <= %g us)' % target if target else ''))
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--params', default=None)
    parser.add_argument('--count', type=int, default=5000)
    args = parser.parse_args()
    measure(args.params, args.count)


if __name__ == '__main__':
    main()
