"""Compile every numba kernel once and store it in numba's cache.

`make` runs this after installing, so that the first node processes (which
load the kernels from the cache in a fraction of a second) do not each spend
tens of seconds compiling them at once.

It first drops the cached kernels: numba checks only the timestamp of the
file that defines a kernel, so a kernel that inlines one from another file
(dopri's RK45 calls the dynamics) would otherwise keep the old physics after
an edit of that other file.
"""
import os
import time
from pathlib import Path

import numpy as np


def clear_cache() -> int:
    """Delete numba's cached kernels of this package (``__pycache__/*.nbi``, ``*.nbc``).

    Returns:
        How many files were deleted.
    """
    package = Path(__file__).resolve().parents[1]
    stale = [p for pattern in ('*.nbi', '*.nbc') for p in package.rglob('__pycache__/' + pattern)]
    for path in stale:
        path.unlink(missing_ok=True)
    return len(stale)


#: What a program prints when it is about to compile the kernels.
COMPILE_NOTICE = ('compiling the numba kernels (first start after an install or a change '
                  'of stewart63_ros/core: up to a few minutes); later starts load them '
                  'from the cache')


def kernel_cache_cold() -> bool:
    """True when some module's compiled kernels are not in numba's cache (or
    are older than the module): the first call will compile, for a minute or
    more. A cheap look at the cache index files, without importing numba's
    internals; where the cache lives elsewhere than beside the modules or in
    NUMBA_CACHE_DIR it errs on "cold"."""
    core = Path(__file__).resolve().parent
    places = [core]
    if os.environ.get('NUMBA_CACHE_DIR'):
        places.append(Path(os.environ['NUMBA_CACHE_DIR']))
    for source in sorted(core.rglob('*.py')):
        if '\n@njit' not in source.read_text():    # no compiled kernel here
            continue
        index = [p for place in places if place.is_dir()
                 for p in place.rglob(source.stem + '.*.nbi')]
        if not index or max(p.stat().st_mtime for p in index) < source.stat().st_mtime:
            return True
    return False


def main() -> None:
    """Compile every kernel into numba's cache: ``python -m stewart63_ros.core.precompile``.

    Clears the cache (``clear_cache``), then calls each compiled path once on
    the default mechanism (dynamics, PD law, forward kinematics, the sampled
    and continuous loops, the control laws and reference, the analysis, the
    workspace grid and the sweep's leg lengths) and prints the time taken.
    """
    start = time.perf_counter()
    clear_cache()
    # lazy: the kernels cost 692 ms; cli imports this for the notice
    from stewart63_ros.core.controllers.laws import PDController
    from stewart63_ros.core.controllers.simulate import initial_state, run_continuous, run_sampled
    from stewart63_ros.core.mechanics.dynamics import Dynamics
    from stewart63_ros.core.mechanics.fk import FKTracker
    from stewart63_ros.core.plumbing.params import load_setup
    setup = load_setup()
    mech, task = setup.mechanism, setup.task
    dyn = Dynamics(mech)
    law = PDController(setup)
    y = initial_state(task)
    dyn.derivative(y, np.zeros(6))
    dyn.derivative_with(y, law.pd_gains())
    dyn.step(y, np.zeros(6), 1e-3)
    lengths, rates = dyn.lengths_and_rates(y)
    law(lengths, rates)
    law.forces(0.0, lengths, rates)
    tracker = FKTracker(mech)
    tracker.solve(lengths, rates)
    tracker.fk.all_modes(lengths)
    # lazy: the kernels cost 692 ms; cli imports this for the notice
    from stewart63_ros.core.mechanics.assembly import jacobian_determinant
    jacobian_determinant(*dyn.kernel_args()[1:3], y)
    # The compiled closed loops: scipy's RK45 (dopri), its output samples, the sampled loop.
    run_continuous(setup, 0.02, dyn=dyn)
    run_sampled(setup, 0.002, 1000.0, dyn=dyn)
    # The control laws and the reference motions.
    # lazy: the kernels cost 692 ms; cli imports this for the notice
    from stewart63_ros.core.controllers.laws import LAWS, Controller
    from stewart63_ros.core.controllers.reference import Reference
    ref = Reference.from_poses(mech, [0.0, 0.5, 1.0], np.zeros((3, 6)) + np.concatenate(
        [task.initial_position, task.initial_orientation]))
    ref.check(1.0, 1.0)
    for name in LAWS:
        Controller(setup, law=name, reference=ref)(lengths, rates, 0.25)
    # The analysis: holding forces, the workspace grid, a sweep run's leg lengths.
    # lazy: the kernels cost 692 ms; cli imports this for the notice
    from stewart63_ros.core.analysis.equilibrium import holding_forces
    from stewart63_ros.core.analysis.sweep import leg_lengths_of_states
    from stewart63_ros.core.analysis.workspace import workspace_map
    holding_forces(dyn, task.initial_position, np.eye(3))
    workspace_map(mech, np.eye(3), 1.0)
    leg_lengths_of_states(dyn.base_points, dyn.leg_points, y[None, :])
    # The general 6-6's forward kinematics (every mode by homotopy; tracking) on a
    # small semi-regular hexapod: joints in three close pairs on each side.
    # lazy: the kernels cost 692 ms; cli imports this for the notice
    from stewart63_ros.core.mechanics.fk66 import FKTracker66, ForwardKinematics66
    angles = np.radians([k * 120 + s * 6 for k in range(3) for s in (-1, 1)])
    base66 = np.c_[0.5 * np.cos(angles), 0.5 * np.sin(angles), np.zeros(6)]
    plat66 = np.roll(np.c_[0.3 * np.cos(angles - np.pi / 3), 0.3 * np.sin(angles - np.pi / 3),
                           np.zeros(6)], -1, axis=0)
    fk66 = ForwardKinematics66(base66, plat66)
    up = np.array([0.0, 0.0, 0.4])
    lengths66 = fk66.lengths(up, np.eye(3))
    fk66.all_modes(lengths66)
    FKTracker66(fk66, up, np.eye(3)).solve(lengths66)
    print('numba kernels ready (%.1f s)' % (time.perf_counter() - start))


if __name__ == '__main__':
    main()
