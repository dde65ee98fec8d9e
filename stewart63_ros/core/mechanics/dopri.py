"""scipy's RK45 (Dormand-Prince 5(4)) compiled with numba, for the continuous closed loop.

``scipy.integrate.solve_ivp(method='RK45')`` spends most of its time in
Python bookkeeping around each step (stage combinations with small numpy
calls, the error norm, step-size control, the wrapper of the right-hand
side): about 8 us per right-hand-side evaluation, while the evaluation itself
(``dynamics.derivative_pd``, compiled) costs under 0.5 us. The paper's 10 s
scenario takes about 2200 evaluations: ~25 ms in scipy. This module runs the
same algorithm in one compiled call that evaluates ``derivative_pd`` compiled
to compiled, so the run costs little more than the evaluations (~2.5 ms).

It is scipy's ``RK45`` step for step, not a look-alike:

- the Butcher tableau, error weights and dense-output matrix are read from
  ``scipy.integrate.RK45`` (``A``, ``B``, ``C``, ``E``, ``P``) at import time
  and handed to the kernel as arrays (never copied by hand);
- the error norm is the RMS of err / scale with
  scale = atol + max(|y|, |y_new|) * rtol;
- step-size control: factor SAFETY * norm^(-1/5) limited to
  [MIN_FACTOR, MAX_FACTOR] = [0.2, 10], no growth on the step right after a
  rejection, minimum step 10 ulp(t), the last step clipped to the end time;
- the initial step is ``scipy.integrate._ivp.common.select_initial_step``;
- output at ``t_eval`` through scipy's dense output of each step,
  y_old + h Q [x, x^2, x^3, x^4] with Q = K^T P and x = (t - t_old) / h;
- ``nfev`` counts as scipy's: one evaluation at t0, one in the initial step
  selection, six per step attempt.

The small matrix products go through np.dot (BLAS), as in scipy: where the
BLAS that numba calls (scipy's) and numpy's give the same bits, as with the
OpenBLAS wheels, the result is solve_ivp's to the bit (same steps, same
evaluations, same output). Elsewhere only the summation order differs, which
moves the result by about what one ulp changed in y0 does (< 1e-9 of the
state's scale here). ``solve_ivp`` stays the independent reference
(``simulate.run_continuous(integrator='scipy')``).

Unlike scipy, the kernel never loops forever: a non-finite state or
derivative fails at once, and the number of step attempts is bounded.
"""
from __future__ import annotations

import warnings

import numpy as np
from numpy.typing import ArrayLike
from scipy.integrate import RK45 as _RK45

from stewart63_ros.core.mechanics.dynamics import (
    NO_GAINS,
    STATE_SIZE,
    Dynamics,
    derivative_pd,
    wrench6,
)
from stewart63_ros.core.plumbing._jit import njit

#: scipy's step-control constants (scipy.integrate's RK solvers keep them in a
#: private module; test_integrators checks these equal them).
SAFETY, MIN_FACTOR, MAX_FACTOR = 0.9, 0.2, 10.0

#: Dormand-Prince 5(4) tableau and dense output, from scipy at import time.
TABLEAU_A = np.ascontiguousarray(_RK45.A, dtype=float)
TABLEAU_B = np.ascontiguousarray(_RK45.B, dtype=float)
TABLEAU_C = np.ascontiguousarray(_RK45.C, dtype=float)
TABLEAU_E = np.ascontiguousarray(_RK45.E, dtype=float)
TABLEAU_P = np.ascontiguousarray(_RK45.P, dtype=float)
N_STAGES = int(_RK45.n_stages)
#: Order of the error estimator (4): the step-size factor goes as norm^(-1/5).
ERROR_ORDER = int(_RK45.error_estimator_order)

#: Default bound on step attempts (accepted + rejected); the paper's 10 s
#: scenario takes about 365 at rtol 1e-8.
MAX_STEPS = 100_000

# Status codes returned by the kernel.
SUCCESS, TOO_SMALL_STEP, TOO_MANY_STEPS, NON_FINITE = 0, 1, 2, 3
STATUS_MESSAGES = {
    TOO_SMALL_STEP: 'required step size is less than spacing between numbers',
    TOO_MANY_STEPS: 'more than max_steps = %d step attempts',
    NON_FINITE: 'non-finite state or derivative (NaN or inf)',
}


@njit
def _norm(x):
    """scipy's ``common.norm``: np.linalg.norm(x) / x.size ** 0.5 (BLAS ddot, as numpy)."""
    return np.sqrt(np.dot(x, x)) / x.size ** 0.5


@njit
def _all_finite(x):
    for i in range(x.size):
        if not np.isfinite(x[i]):
            return False
    return True


@njit
def _dopri45_pd(const, base, plat, inertia_body, y0, forces, wrench, endstops, pd, max_force,
                t0, t_bound, t_eval, rtol, atol, max_step, max_steps,
                A, B, C, E, P, n_stages, error_order, safety, min_factor, max_factor):
    """scipy's RK45 on dy/dt = ``derivative_pd(..., y, forces, wrench, endstops, pd, max_force)``.

    Integrates from ``t0`` to ``t_bound`` (> t0) and returns
    (states at ``t_eval`` (sorted, within [t0, t_bound]) as (len(t_eval), n),
    rhs evaluations, accepted steps, rejected steps, status). On failure
    (status != 0) the rows not reached are NaN. The right-hand side is
    autonomous (time never enters ``derivative_pd``), so ``C`` is unused.

    Each vector expression is scipy's, in scipy's order; the small matrix
    products go through np.dot (BLAS, as numpy does), so that on a machine
    where numpy's and scipy's BLAS share their kernels the arithmetic is
    scipy's to the last bit.
    """
    n = y0.size
    m = t_eval.size
    ys = np.full((m, n), np.nan)
    exponent = -1.0 / (error_order + 1)
    nfev = 0
    accepted = 0
    rejected = 0
    if not _all_finite(y0):
        return ys, nfev, accepted, rejected, 3
    y = y0.copy()
    t = t0
    f = derivative_pd(const, base, plat, inertia_body, y, forces, wrench, endstops, pd,
                       max_force)
    nfev += 1
    if not _all_finite(f):
        return ys, nfev, accepted, rejected, 3
    i_out = 0
    interval = abs(t_bound - t0)
    if interval == 0.0:
        while i_out < m and t_eval[i_out] <= t:
            ys[i_out] = y
            i_out += 1
        return ys, nfev, accepted, rejected, 0

    # common.select_initial_step (Hairer, Norsett, Wanner II.4)
    scale = atol + np.abs(y) * rtol
    d0 = _norm(y / scale)
    d1 = _norm(f / scale)
    if d0 < 1e-5 or d1 < 1e-5:
        h0 = 1e-6
    else:
        h0 = 0.01 * d0 / d1
    h0 = min(h0, interval)
    y1 = y + h0 * f
    f1 = derivative_pd(const, base, plat, inertia_body, y1, forces, wrench, endstops, pd,
                        max_force)
    nfev += 1
    d2 = _norm((f1 - f) / scale) / h0
    if d1 <= 1e-15 and d2 <= 1e-15:
        h1 = max(1e-6, h0 * 1e-3)
    else:
        h1 = (0.01 / max(d1, d2)) ** (1.0 / (error_order + 1))
    h_abs = min(min(100 * h0, h1), min(interval, max_step))
    if not np.isfinite(h_abs):
        return ys, nfev, accepted, rejected, 3

    K = np.empty((n_stages + 1, n))
    order = P.shape[1]
    attempts = 0
    while t < t_bound:
        # RungeKutta._step_impl
        min_step = 10.0 * abs(np.nextafter(t, np.inf) - t)
        if h_abs > max_step:
            h_abs = max_step
        elif h_abs < min_step:
            h_abs = min_step
        step_rejected = False
        nonfinite = False
        while True:
            if h_abs < min_step:
                return ys, nfev, accepted, rejected, 3 if nonfinite else 1
            if attempts >= max_steps:
                return ys, nfev, accepted, rejected, 2
            attempts += 1
            t_new = t + h_abs
            if t_new > t_bound:
                t_new = t_bound
            h = t_new - t
            h_abs = abs(h)
            # rk_step
            K[0] = f
            for s in range(1, n_stages):
                dy = np.dot(K[:s].T, A[s, :s]) * h
                K[s] = derivative_pd(const, base, plat, inertia_body, y + dy, forces, wrench,
                                      endstops, pd, max_force)
            y_new = y + h * np.dot(K[:n_stages].T, B)
            f_new = derivative_pd(const, base, plat, inertia_body, y_new, forces, wrench,
                                   endstops, pd, max_force)
            K[n_stages] = f_new
            nfev += n_stages
            scale = atol + np.maximum(np.abs(y), np.abs(y_new)) * rtol
            error_norm = _norm(np.dot(K.T, E) * h / scale)
            if error_norm < 1.0:
                if error_norm == 0.0:
                    factor = max_factor
                else:
                    factor = safety * error_norm ** exponent
                    if factor > max_factor:
                        factor = max_factor
                if step_rejected and factor > 1.0:
                    factor = 1.0
                h_abs *= factor
                break
            # rejected; like Python's max(MIN_FACTOR, x), a NaN norm gives MIN_FACTOR
            nonfinite = not np.isfinite(error_norm)
            factor = safety * error_norm ** exponent
            if not factor > min_factor:
                factor = min_factor
            h_abs *= factor
            step_rejected = True
            rejected += 1
        accepted += 1
        # solve_ivp: the t_eval points in (t, t_new] from this step's dense output,
        # RkDenseOutput: y_old + h Q p, Q = K^T P, p = cumprod([x] * 4)
        j = i_out
        while j < m and t_eval[j] <= t_new:
            j += 1
        if j > i_out:
            Q = np.dot(K.T, P)
            if j - i_out == 1:   # numpy's dot of a (4, 1) column is a matrix-vector product
                x = (t_eval[i_out] - t) / h
                p = np.empty(order)
                p[0] = x
                for c in range(1, order):
                    p[c] = p[c - 1] * x
                ys[i_out] = h * np.dot(Q, p) + y
            else:
                p2 = np.empty((order, j - i_out))
                for k in range(j - i_out):
                    x = (t_eval[i_out + k] - t) / h
                    p2[0, k] = x
                    for c in range(1, order):
                        p2[c, k] = p2[c - 1, k] * x
                yk = h * np.dot(Q, p2)
                for k in range(j - i_out):
                    ys[i_out + k] = yk[:, k] + y
            i_out = j
        t = t_new
        y = y_new
        f = f_new
        if not np.isfinite(h_abs):
            return ys, nfev, accepted, rejected, 3
    return ys, nfev, accepted, rejected, 0


def solve_pd(dyn: Dynamics, y0: ArrayLike, t_eval: ArrayLike, forces: ArrayLike | None = None,
             wrench: tuple[ArrayLike, ArrayLike] | None = None,
             gains: ArrayLike | None = None, max_force: float = 0.0, endstops: bool = True,
             rtol: float = 1e-8, atol: float = 1e-10, max_step: float = np.inf,
             max_steps: int = MAX_STEPS) -> tuple[np.ndarray, dict[str, int]]:
    """Integrate the dynamics of ``dyn`` from t_eval[0] to t_eval[-1]: scipy's RK45, compiled.

    dy/dt is ``derivative_pd``: piston forces ``forces`` (held) plus, with
    ``gains`` = [setpoint; kp; kv] (3, 6), the PD law of eq. (40) evaluated
    inside the ODE.

    Args:
        dyn: the model (``Dynamics``).
        y0: the initial state (13,), at t_eval[0].
        t_eval: (T,) output times [s], T >= 2, non-decreasing.
        forces: (6,) piston forces [N], held (default zeros).
        wrench: (F_ext [N], M_ext [N m]), each (3,), platform frame, at its
            origin; None for none.
        gains: (3, 6) [setpoint [m]; kp [N/m]; kv [N s/m]] for eq. (40) inside
            the ODE, or None for none.
        max_force: the PD law's saturation [N].
        endstops: whether the end stops act.
        rtol, atol: scipy's tolerances (rtol below 100 eps is raised to it,
            with a warning, as scipy does).
        max_step: the longest step [s].
        max_steps: the most step attempts.

    Returns:
        (states (T, 13) at ``t_eval``, quaternions as integrated (not
        normalised); {'nfev', 'accepted', 'rejected'}: right-hand-side
        evaluations and steps).

    Raises:
        ValueError: a non-finite or misshapen initial state, a bad ``t_eval``,
            or non-positive tolerances.
        RuntimeError: the integration failed (as scipy's ``sol.success``
            False) or took more than ``max_steps`` step attempts.
    """
    y0 = np.array(y0, dtype=float)
    if y0.shape != (STATE_SIZE,):
        raise ValueError('initial state must have %d components, got shape %s'
                         % (STATE_SIZE, y0.shape))
    if not np.all(np.isfinite(y0)):
        raise ValueError('initial state is not finite (components %s are NaN or inf)'
                         % np.flatnonzero(~np.isfinite(y0)).tolist())
    t_eval = np.ascontiguousarray(t_eval, dtype=float)
    if (t_eval.ndim != 1 or t_eval.size < 2 or not np.all(np.isfinite(t_eval))
            or np.any(np.diff(t_eval) < 0) or t_eval[-1] < t_eval[0]):
        raise ValueError('t_eval must be a finite increasing time vector of two or more samples')
    forces = np.zeros(6) if forces is None else np.ascontiguousarray(forces, dtype=float)
    pd = NO_GAINS if gains is None else np.ascontiguousarray(gains, dtype=float)
    rtol, atol, max_step = float(rtol), float(atol), float(max_step)
    if not (rtol > 0 and atol >= 0 and max_step > 0):
        raise ValueError('rtol and max_step must be positive and atol non-negative')
    if rtol < 100 * np.finfo(float).eps:   # as scipy's validate_tol
        warnings.warn('rtol %g is too small; using %g' % (rtol, 100 * np.finfo(float).eps),
                      stacklevel=2)
        rtol = 100 * np.finfo(float).eps
    ys, nfev, accepted, rejected, status = _dopri45_pd(
        *dyn.kernel_args(), y0, forces, wrench6(wrench), bool(endstops), pd, float(max_force),
        float(t_eval[0]), float(t_eval[-1]), t_eval, rtol, atol, max_step, int(max_steps),
        TABLEAU_A, TABLEAU_B, TABLEAU_C, TABLEAU_E, TABLEAU_P, N_STAGES, ERROR_ORDER,
        SAFETY, MIN_FACTOR, MAX_FACTOR)
    if status != SUCCESS:
        done = int(np.sum(np.all(np.isfinite(ys), axis=1)))
        message = STATUS_MESSAGES[status]
        if status == TOO_MANY_STEPS:
            message = message % max_steps
        raise RuntimeError('integration failed: %s (%d of %d output samples reached, '
                           '%d step attempts, %d rhs evaluations)'
                           % (message, done, len(t_eval), accepted + rejected, nfev))
    return ys, {'nfev': int(nfev), 'accepted': int(accepted), 'rejected': int(rejected)}
