"""Time `calibrate fit`'s core on 100 tracked poses (target < 10 s), and `plan`.

A machine built off the packaged drawing (points up to 5 mm, offsets up to
10 mm), 100 random feasible poses tracked with 0.1 mm / 0.1 mrad noise; the
fit (identifiability, the least-squares pass, the Huber pass, the
covariance) timed alone, median of a few repeats. One BLAS thread, as the
`calibrate` command runs (tools/calibrate.py). No assertion: it prints.
Run: .venv/bin/python bench/bench_calibration.py [--poses N] [--repeat R]
"""
import os

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from stewart63_ros.core.machine import calibration as cal  # noqa: E402
from stewart63_ros.core.machine import calibration_model as cal_model  # noqa: E402
from stewart63_ros.core.machine import calibration_plan as cp  # noqa: E402
from stewart63_ros.core.plumbing.params import load_setup  # noqa: E402


def measure(poses: int = 100, repeat: int = 5) -> dict:
    """{'calibrate_fit_100_s': median fit time [s], 'calibrate_plan_30_s': ...}."""
    setup = load_setup()
    mech = setup.mechanism
    rng = np.random.default_rng(0)
    theta = cal_model.parameter_vector(mech)
    theta[:27] += rng.uniform(-0.005, 0.005, 27)
    theta[27:] += rng.uniform(-0.01, 0.01, 6)
    positions, rotations = cp.candidate_poses(setup, poses, rng)
    true = cal_model.Measurements(positions, rotations, np.zeros((poses, 6)))
    readings = cal_model.predict_readings(theta, true)
    seen = Rotation.from_rotvec(rng.normal(0, 1e-4, (poses, 3))) * Rotation.from_matrix(rotations)
    meas = cal_model.measurements(positions + rng.normal(0, 1e-4, positions.shape), seen.as_quat(),
                            readings)
    cal.fit(mech, meas)         # imports and first calls
    fits = []
    for _ in range(repeat):
        start = time.perf_counter()
        result = cal.fit(mech, meas)
        fits.append(time.perf_counter() - start)
    start = time.perf_counter()
    cp.plan(setup, 30, seed=0)
    plan = time.perf_counter() - start
    return {'calibrate_fit_%d_s' % poses: float(np.median(fits)),
            'calibrate_fit_rms_after_m': result.rms_after,
            'calibrate_plan_30_s': plan}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--poses', type=int, default=100)
    parser.add_argument('--repeat', type=int, default=5)
    args = parser.parse_args()
    figures = measure(args.poses, args.repeat)
    print('calibrate fit, %d poses: median %.3f s (target < 10 s); reading RMS after %.3g m'
          % (args.poses, figures['calibrate_fit_%d_s' % args.poses],
             figures['calibrate_fit_rms_after_m']))
    print('calibrate plan, 30 poses from 1500 candidates: %.2f s' % figures['calibrate_plan_30_s'])


if __name__ == '__main__':
    main()
