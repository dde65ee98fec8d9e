"""The modes of our linear model against MuJoCo's linearization of the same mechanism.

MuJoCo (``stewart63_ros.mujoco_model``) models the platform as 25 bodies:
the free platform and, per leg, a cylinder on a universal joint and a
piston on a slide, tied to the platform by equality constraints: 24 degrees
of freedom, 18 constraints. ``mujoco.mjd_transitionFD`` differentiates one
of its steps: a 48 x 48 discrete transition matrix, whose eigenvalues z give
continuous ones by log(z) / dt. Its 36 constraint eigenvalues (|z| = 0.75,
the stabilisation over two steps) lie far from the 12 of the mechanism
(|z| > 0.98 at a 0.2 ms step), which are picked by that alone; then they are matched to ours.

``mjd_transitionFD`` does not take MuJoCo's RK4, so the step is
semi-implicit Euler: the eigenvalues converge at first order in the
timestep (measured: largest relative gap 2.3e-3, 1.2e-3, 5.8e-4 at 0.4,
0.2, 0.1 ms open loop; 7.8e-3, 3.9e-3 at 0.2, 0.1 ms closed loop), and
Richardson's extrapolation of the last two leaves 8e-5 open loop and 4e-5
closed loop, about the compliance MuJoCo's soft constraints keep (impedance
0.9999).

Open loop: the model with kp = kv = 0 (its pd actuators idle) and our
holding forces applied to the slides (``qfrc_applied``); closed loop: eq.
(40) as MuJoCo's actuators with ctrl = our references u0. MuJoCo's
accelerations at that state check our holding forces too.
"""
from __future__ import annotations

import os

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

if os.environ.get('STEWART63_REQUIRE_MUJOCO'):
    import mujoco
else:
    mujoco = pytest.importorskip('mujoco', reason='MuJoCo is the optional [bench] extra')

from stewart63_ros.core.analysis import linear, modal  # noqa: E402
from stewart63_ros.mujoco_model import MujocoPlatform, Settings  # noqa: E402

TIMESTEPS = (2e-4, 1e-4)


def mujoco_eigenvalues(setup, model, timestep):
    """The 12 slowest continuous eigenvalues of MuJoCo's linearization at our
    equilibrium, and the largest |z| of the rest; the platform's acceleration
    there [m/s^2, rad/s^2]."""
    eq = model.equilibrium
    at_rest = dict(initial_position=eq.position, initial_orientation=eq.theta,
                   initial_velocity=[0.0] * 3, initial_orientation_rate=[0.0] * 3)
    if not model.closed_loop:
        at_rest.update(kp=[0.0] * 6, kv=[0.0] * 6)
    platform = MujocoPlatform(setup.replace(**at_rest),
                              Settings(timestep=timestep, integrator='Euler'))
    m, d = platform.model, platform.data
    if model.closed_loop:
        d.ctrl[platform._pd] = model.u0
    else:
        d.qfrc_applied[platform._slide_dof] = model.u0
    mujoco.mj_forward(m, d)
    platform_acc = float(np.abs(d.qacc[:6]).max())
    transition = np.zeros((2 * m.nv + m.na, 2 * m.nv + m.na))
    mujoco.mjd_transitionFD(m, d, 1e-7, True, transition, None, None, None)
    z = np.linalg.eigvals(transition)
    order = np.argsort(-np.abs(z))
    slow = np.log(z[order[:12]].astype(complex)) / timestep
    return slow, float(np.abs(z[order[12]])), platform_acc


def matched(ours, theirs):
    """``theirs`` reordered to pair with ``ours`` (least total distance)."""
    rows, cols = linear_sum_assignment(np.abs(ours[:, None] - theirs[None, :]))
    return theirs[cols[np.argsort(rows)]]


@pytest.mark.parametrize('law', [None, 'pd'])
def test_modes_agree_with_mujocos_linearization(default_setup, law):
    model = linear.linearize(default_setup, law)
    values, vectors = np.linalg.eig(model.A)
    gaps, estimates = [], []
    for dt in TIMESTEPS:
        theirs, next_z, platform_acc = mujoco_eigenvalues(default_setup, model, dt)
        assert np.all(np.abs(np.exp(theirs * dt)) > 0.95) and next_z < 0.9, next_z
        # Our holding forces (or references) hold MuJoCo's platform too (measured
        # 7.4e-4 m/s^2, 7.5e-5 g: what its soft constraints give way).
        assert platform_acc < 2e-3, platform_acc
        theirs = matched(values, theirs)
        estimates.append(theirs)
        gaps.append(np.max(np.abs(theirs - values) / np.abs(values)))
    # First order in MuJoCo's step, towards our eigenvalues ...
    assert 1.7 < gaps[0] / gaps[1] < 2.3, gaps
    # ... and its extrapolation to a zero step lands on them.
    extrapolated = 2 * estimates[1] - estimates[0]
    assert np.max(np.abs(extrapolated - values) / np.abs(values)) < 3e-4
    # The natural frequencies and damping ratios of the six modes.
    for i, j in modal.pair_eigenvalues(values, vectors):
        ours = modal.pair_figures(values[i], values[j])
        theirs = modal.pair_figures(extrapolated[i], extrapolated[j])
        assert theirs[0] == pytest.approx(ours[0], rel=3e-4)
        assert theirs[1] == pytest.approx(ours[1], rel=3e-4)
        assert theirs[2] == ours[2]
