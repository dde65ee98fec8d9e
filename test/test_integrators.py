"""The compiled integrators of the closed loop against independent references.

- continuous control: the compiled RK45 (``dopri``) against scipy's
  ``solve_ivp`` itself, and against a tight-tolerance scipy run;
- sampled control: the compiled loop of ``run_sampled`` against the plant
  node's way of stepping (``Dynamics.step`` per sample), to the bit;
- bad inputs fail with a clear error, never an endless loop.
"""
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from stewart63_ros.core.controllers.laws import PDController
from stewart63_ros.core.controllers.simulate import (
    initial_state,
    run_continuous,
    run_sampled,
    sensor_reading,
    substeps_for,
)
from stewart63_ros.core.mechanics.dynamics import QUAT, Dynamics
from stewart63_ros.core.plumbing.params import load_mechanism, load_setup

RTOL, ATOL = 1e-8, 1e-10
DURATION, OUTPUT_RATE = 10.0, 100.0      # the paper's scenario
#: A setpoint beyond the stroke [1.2, 2.3] m: the legs ride on their end stops.
PAST_STROKE = [2.5] * 6


@pytest.fixture(scope='module')
def mech():
    return load_mechanism()


@pytest.fixture(scope='module')
def dyn(mech):
    return Dynamics(mech)


def scipy_reference(dyn, law, y0, t_eval, rtol, atol):
    """solve_ivp RK45 on the public dynamics + PD right-hand side; quaternions normalised."""
    gains = law.pd_gains()
    sol = solve_ivp(lambda _t, y: dyn.derivative_with(y, gains), (t_eval[0], t_eval[-1]), y0,
                    method='RK45', t_eval=t_eval, rtol=rtol, atol=atol)
    assert sol.success, sol.message
    states = sol.y.T.copy()
    states[:, QUAT] /= np.linalg.norm(states[:, QUAT], axis=1)[:, None]
    return states, sol.nfev


def blas_agrees_with_numpy():
    """Whether compiled np.dot (scipy's BLAS) gives numpy's bits on RK45-sized products.

    The compiled RK45 does scipy's arithmetic through np.dot, so where this
    holds it must reproduce solve_ivp to the bit."""
    try:
        import numba
    except ImportError:      # the kernels then run as plain numpy
        return True

    @numba.njit
    def products(K, a, P):
        return np.dot(K[:5].T, a[:5]), np.dot(K.T, a), np.dot(K.T, P), np.dot(K[0], K[0])

    rng = np.random.default_rng(7)
    K = rng.standard_normal((7, 13)) * 10.0 ** rng.uniform(-6, 6, (7, 13))
    a, P = rng.standard_normal(7), rng.standard_normal((7, 4))
    expected = (np.dot(K[:5].T, a[:5]), np.dot(K.T, a), np.dot(K.T, P), np.dot(K[0], K[0]))
    return all(np.array_equal(x, y) for x, y in zip(products(K, a, P), expected))


def test_compiled_rk45_reproduces_scipy_solve_ivp(setup, mech, dyn):
    t_eval = np.arange(int(DURATION * OUTPUT_RATE) + 1) / OUTPUT_RATE
    ref, ref_nfev = scipy_reference(dyn, PDController(setup), initial_state(setup.task), t_eval,
                                    RTOL, ATOL)
    result = run_continuous(setup, DURATION, OUTPUT_RATE, dyn=dyn, rtol=RTOL, atol=ATOL)
    np.testing.assert_array_equal(result.times, t_eval)
    diff = np.abs(result.states - ref).max()
    exact = blas_agrees_with_numpy()
    print('\ncompiled RK45 vs solve_ivp: max |dy| %.3g, %d vs %d rhs evaluations (BLAS %s)'
          % (diff, result.rhs_evaluations, ref_nfev, 'identical' if exact else 'differs'))
    if exact:
        assert diff == 0.0
        assert result.rhs_evaluations == ref_nfev
    else:
        # Another summation order in the small products shifts the steps a little:
        # as much as one ulp changed in y0 moves solve_ivp's own result (up to
        # 8e-10 of the state's scale, 4 % in evaluations on this scenario).
        assert diff <= 2e-9 * np.abs(ref).max(), diff
        assert abs(result.rhs_evaluations - ref_nfev) <= 0.1 * ref_nfev


def test_compiled_rk45_meets_its_tolerance(setup, mech, dyn):
    t_eval = np.arange(int(DURATION * OUTPUT_RATE) + 1) / OUTPUT_RATE
    tight, _ = scipy_reference(dyn, PDController(setup), initial_state(setup.task), t_eval,
                               1e-11, 1e-13)
    result = run_continuous(setup, DURATION, OUTPUT_RATE, dyn=dyn, rtol=RTOL, atol=ATOL)
    err = np.abs(result.states - tight)
    peak = np.abs(tight).max(axis=0)
    print('\ncompiled RK45 (rtol %g) vs rtol 1e-11: max error / peak of each state %.3g'
          % (RTOL, (err / peak).max()))
    assert np.all(err <= RTOL * peak + ATOL)


def test_continuous_output_forces_and_end_stop_samples(setup, mech, dyn):
    """Forces are eq. (40) at each output state; end-stop samples are counted."""
    law = PDController(setup, setpoint=PAST_STROKE)
    result = run_continuous(setup, 2.0, OUTPUT_RATE, controller=law, dyn=dyn)
    contact = 0
    for y, force in zip(result.states, result.forces):
        lengths, rates = sensor_reading(dyn, y)
        contact += bool(np.any(lengths < mech.leg_length_min)
                        or np.any(lengths > mech.leg_length_max))
        np.testing.assert_allclose(force, law(lengths, rates), rtol=0, atol=1e-9)
    assert contact > 0
    assert result.endstop_samples == contact
    reference = run_continuous(setup, 2.0, OUTPUT_RATE, controller=law, dyn=dyn,
                               integrator='scipy')
    assert abs(reference.endstop_samples - contact) <= 1


@pytest.mark.parametrize('rate, setpoint', [(1000.0, None), (100.0, None),
                                            (1000.0, PAST_STROKE)])
def test_sampled_loop_is_the_plant_to_the_bit(setup, mech, dyn, rate, setpoint):
    """run_sampled computes what the plant node computes: Dynamics.step per sample."""
    duration = 2.0
    law = PDController(setup, setpoint=setpoint)
    result = run_sampled(setup, duration, rate, controller=law, dyn=dyn)
    period = 1.0 / rate
    substeps = substeps_for(period)
    y = initial_state(setup.task)
    contact = 0
    for k in range(int(round(duration * rate)) + 1):
        lengths, rates = dyn.lengths_and_rates(y)
        contact += bool(np.any(lengths < mech.leg_length_min)
                        or np.any(lengths > mech.leg_length_max))
        force = law(lengths, rates)
        assert np.array_equal(result.states[k], y), 'state differs at sample %d' % k
        assert np.array_equal(result.forces[k], force), 'force differs at sample %d' % k
        y = dyn.step(y, force, period, substeps)
    assert result.endstop_samples == contact
    assert (contact > 0) == (setpoint is not None)


@pytest.mark.parametrize('integrator', ['compiled', 'scipy'])
def test_non_finite_initial_state_is_refused(setup, mech, integrator):
    y0 = initial_state(setup.task)
    y0[0] = np.nan
    with pytest.raises(ValueError, match='finite'):
        run_continuous(setup, 1.0, y0=y0, integrator=integrator)
    y0 = initial_state(setup.task)
    y0[7] = 1e200   # finite, but its derivative is not
    with pytest.raises(RuntimeError, match='non-finite'):
        run_continuous(setup, 1.0, y0=y0, integrator=integrator)


def test_non_finite_derivative_mid_run_and_step_bound_fail_cleanly():
    # An infinitely stiff end stop: the derivative turns infinite when a leg
    # reaches its stroke limit, some way into the run.
    setup = load_setup(overrides={'endstop_stiffness': float('inf')})
    law = PDController(setup, setpoint=PAST_STROKE)
    with pytest.raises(RuntimeError, match='non-finite|max_steps'):
        run_continuous(setup, 2.0, controller=law, max_steps=20000)
    # The bound on step attempts holds on a sound problem too.
    with pytest.raises(RuntimeError, match='max_steps = 50 '):
        run_continuous(load_setup(), DURATION, max_steps=50)


def test_the_step_control_constants_are_scipys():
    """dopri's step control matches solve_ivp's only with scipy's constants."""
    from scipy.integrate._ivp import rk

    from stewart63_ros.core.mechanics import dopri
    assert (dopri.SAFETY, dopri.MIN_FACTOR, dopri.MAX_FACTOR) == \
        (rk.SAFETY, rk.MIN_FACTOR, rk.MAX_FACTOR)
