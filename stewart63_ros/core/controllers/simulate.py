"""Integration of the closed loop: the paper's scenario offline (section VI).

Two control modes:
- ``continuous``: eq. (40) evaluated inside the ODE, adaptive RK45 as the
  paper's ode45: scipy's RK45 compiled (``dopri``), or scipy ``solve_ivp``
  itself as the independent reference;
- ``sampled``: eq. (40) sampled at ``rate`` Hz and held (zero-order hold),
  fixed-step RK4 between samples, exactly as the plant node runs it, so a
  lockstep rig reproduces it sample for sample. The loop is compiled; it
  calls the plant's own RK4 kernel, so its arithmetic is the plant's. With
  faults (core/machine/faults.py) the loop runs in Python, sample by sample as the
  plant node does (``run_faulted``).
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from scipy.integrate import solve_ivp

from stewart63_ros.core.controllers.control import PDGains, pd_law
from stewart63_ros.core.controllers.laws import Controller, PDController
from stewart63_ros.core.machine.faults import FaultModel, parse_faults
from stewart63_ros.core.mechanics import dopri
from stewart63_ros.core.mechanics.dynamics import (
    NO_GAINS,
    NO_WRENCH,
    OMEGA,
    POS,
    QUAT,
    STATE_SIZE,
    VEL,
    Dynamics,
    derivative_pd,
    lengths_rates,
    rk4,
)
from stewart63_ros.core.mechanics.rotation import (
    euler_from_quaternion,
    euler_rate_matrix,
    quaternion_from_euler,
)
from stewart63_ros.core.plumbing._jit import njit
from stewart63_ros.core.plumbing.trajectory import COLUMNS

if TYPE_CHECKING:
    from stewart63_ros.core.mechanics.setup import Setup, Task

#: Longest RK4 step of the sampled/plant integrator [s]. 1 ms keeps the
#: end-stop spring (about 700 rad/s) well inside RK4's stability region.
MAX_STEP = 1.0e-3


def initial_state(task: Task) -> np.ndarray:
    """The state at t = 0 from t_0, dt_0/dt, theta_0, dtheta_0/dt of the parameters.

    Args:
        task: the run's task (its ``initial_*`` values; ``Setup.task``).

    Returns:
        (13,) t, quaternion (x, y, z, w), v, omega (base frame), as in the dynamics.
    """
    y = np.empty(STATE_SIZE)
    y[POS] = task.initial_position
    y[QUAT] = quaternion_from_euler(task.initial_orientation)
    y[VEL] = task.initial_velocity
    y[OMEGA] = euler_rate_matrix(task.initial_orientation) @ task.initial_orientation_rate
    return y


def substeps_for(period: float) -> int:
    """RK4 steps per control period so that none exceeds MAX_STEP.

    Args:
        period: the control period [s].

    Returns:
        The number of RK4 steps, at least 1.
    """
    return max(1, int(math.ceil(period / MAX_STEP - 1e-9)))


def sensor_reading(dyn: Dynamics, y: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """What ideal linear sensors measure: L_i and dL_i/dt, eqs. (5), (13).

    Args:
        dyn: the model; y: the state (13,).

    Returns:
        (L (6,) [m], dL/dt (6,) [m/s]).
    """
    return dyn.lengths_and_rates(y)


@dataclasses.dataclass
class Result:
    """Samples of a run: times (N,) [s], states (N, 13), forces (N, 6) [N] applied
    from each time; how many samples had a leg outside its stroke, and how many
    right-hand-side evaluations the integration took."""
    times: np.ndarray
    states: np.ndarray
    forces: np.ndarray
    endstop_samples: int = 0     # samples with some leg outside its stroke
    rhs_evaluations: int = 0
    #: with faults: the forces the pistons applied (``forces`` holds the
    #: controller's commands, as the rig's leg_forces do), what the sensors
    #: reported (N, 12: L1..L6, Ldot1..Ldot6, as leg_lengths carries them),
    #: and what each fault did (``FaultModel.summary``)
    applied: np.ndarray | None = None
    measured: np.ndarray | None = None
    faults: list | None = None

    def table(self, dyn: Dynamics) -> np.ndarray:
        """Rows of the trajectory CSV (docs/interface.md).

        Args:
            dyn: the model (for the leg lengths and rates of each state).

        Returns:
            (N, 31) in the order of ``trajectory.COLUMNS``.
        """
        rows = np.empty((len(self.times), len(COLUMNS)))
        rows[:, 0] = self.times
        rows[:, 1:4] = self.states[:, POS]
        rows[:, 4:7] = euler_from_quaternion(self.states[:, QUAT])
        rows[:, 7:10] = self.states[:, VEL]
        rows[:, 10:13] = self.states[:, OMEGA]
        for k, y in enumerate(self.states):
            rows[k, 13:19], rows[k, 19:25] = sensor_reading(dyn, y)
        rows[:, 25:31] = self.forces
        return rows

    def final_leg_error_percent(self, dyn: Dynamics, setpoint: ArrayLike) -> np.ndarray:
        """|L_i - (L_i)_0| / (L_i)_0 in % at the last sample, per leg.

        Args:
            dyn: the model; setpoint: (L_i)_0 (6,) [m].

        Returns:
            (6,) [%].
        """
        lengths, _ = sensor_reading(dyn, self.states[-1])
        return 100.0 * np.abs(lengths - setpoint) / np.asarray(setpoint)


def _outside_stroke(mech, lengths) -> bool:
    return bool(np.any(lengths < mech.leg_length_min) or np.any(lengths > mech.leg_length_max))


@njit
def _outside(lengths, lmin, lmax):
    for i in range(lengths.size):
        if lengths[i] < lmin or lengths[i] > lmax:
            return True
    return False


@njit
def _sampled_pd(const, base, plat, inertia_body, y0, wrench, setpoint, kp, kv, max_force,
                lmin, lmax, n, dt, steps):
    """The loop of ``run_sampled``: sensors, eq. (40), ``rk4`` held over each period.

    The same kernels (``lengths_rates``, ``pd_law``, ``rk4``) with the same
    arguments as ``Dynamics.step`` and the plant node, so the same numbers."""
    states = np.empty((n + 1, y0.size))
    forces = np.empty((n + 1, 6))
    contact = 0
    y = y0.copy()
    for k in range(n + 1):
        lengths, rates = lengths_rates(base, plat, y)
        if _outside(lengths, lmin, lmax):
            contact += 1
        states[k] = y
        forces[k] = pd_law(lengths, rates, setpoint, kp, kv, max_force)
        if k < n:
            y = rk4(const, base, plat, inertia_body, y, forces[k], wrench, dt, steps)
    return states, forces, contact


@njit
def _pd_samples(base, plat, states, setpoint, kp, kv, max_force, lmin, lmax):
    """Per output sample: the PD forces of eq. (40) from L, dL/dt (the sensors'
    ``lengths_rates``), and how many samples had a leg outside the stroke."""
    n = states.shape[0]
    forces = np.empty((n, 6))
    contact = 0
    for k in range(n):
        lengths, rates = lengths_rates(base, plat, states[k])
        if _outside(lengths, lmin, lmax):
            contact += 1
        forces[k] = pd_law(lengths, rates, setpoint, kp, kv, max_force)
    return forces, contact


def _fixed_pd(setup: Setup, controller: Controller | None) -> PDGains | None:
    """Eq. (40) towards fixed lengths, which the compiled loops evaluate themselves:
    the setup's own (no controller), or the controller's ``pd_gains()``; None
    for any other law (the loops call the controller per sample)."""
    if controller is None:
        return PDGains(setup.task.setpoint_lengths, setup.gains.kp, setup.gains.kv,
                       float(setup.mechanism.max_force))
    return controller.pd_gains()


def run_sampled(setup: Setup, duration: float, rate: float,
                controller: Controller | None = None, y0: ArrayLike | None = None,
                dyn: Dynamics | None = None, loop: str = 'compiled',
                faults: FaultModel | Iterable[str] | None = None,
                wrench: ArrayLike | None = None) -> Result:
    """Eq. (40) sampled at ``rate`` Hz with zero-order hold; RK4 in between.

    Sample k at t_k = k / rate: measure L, dL/dt; F_k = the controller's
    forces; hold F_k over [t_k, t_k+1). This is the loop the plant and
    controller nodes close over DDS. ``loop='compiled'`` runs eq. (40)
    towards fixed lengths (no controller, or one whose ``pd_gains()`` says
    so) in one compiled call (the same kernels as ``Dynamics.step``, hence
    the same numbers to the bit); otherwise, or with ``loop='python'``,
    ``Dynamics.step`` runs per sample, as the plant node does, and the
    controller's ``forces(t, lengths, rates)`` answers each sample.

    Args:
        setup: the machine, gains and task (``params.load_setup``).
        duration: simulated time [s]; rate: the control and sample rate [Hz].
        controller: a ``laws.Controller``; None: ``laws.PDController(setup)``.
        y0: the initial state (13,); default ``initial_state(setup.task)``.
        dyn: the model to use (default: a new ``Dynamics(setup.mechanism)``).
        loop: ``'compiled'`` or ``'python'``.
        faults: a ``FaultModel``, or a list of fault strings: the faulted
            loop (``run_faulted``); None: none.
        wrench: (N, 6) the external wrench (F_ext, M_ext) [N, N m], platform
            frame, at its origin, held over each sample's period (a scenario's
            schedule, ``scenario.wrench_samples``); None: none.

    Returns:
        One row per sample, N = duration * rate + 1: times (N,) [s], states
        (N, 13), forces (N, 6) [N] held from each time.

    Raises:
        ValueError: an unknown ``loop``, a ``wrench`` not (N, 6).
        FaultError: a bad fault string.
        LawError: the controller's law failed.
    """
    if loop not in ('compiled', 'python'):
        raise ValueError("loop must be 'compiled' or 'python', not %r" % (loop,))
    mech = setup.mechanism
    dyn = dyn or Dynamics(mech)
    period = 1.0 / rate
    steps = substeps_for(period)
    n = int(round(duration * rate))
    wrenches = _wrench_rows(wrench, n)
    if faults is not None:
        return run_faulted(setup, duration, rate, faults, controller, y0, dyn, wrench)
    y = initial_state(setup.task) if y0 is None else np.array(y0, float)
    pd = _fixed_pd(setup, controller)
    if loop == 'compiled' and pd is not None:
        states, forces, contact = _sampled_pd_segments(mech, dyn, pd, y, wrenches,
                                                       n, period / steps, steps)
        return Result(np.arange(n + 1) * period, states, forces, int(contact), 4 * steps * n)
    controller = controller or PDController(setup)
    states = np.empty((n + 1, STATE_SIZE))
    forces = np.empty((n + 1, 6))
    contact = 0
    for k in range(n + 1):
        lengths, rates = sensor_reading(dyn, y)
        contact += _outside_stroke(mech, lengths)
        states[k] = y
        forces[k] = controller.forces(k * period, lengths, rates)
        if k < n:
            y = dyn.step(y, forces[k], period, steps, _wrench_at(wrenches, k))
    return Result(np.arange(n + 1) * period, states, forces, contact, 4 * steps * n)


def _wrench_rows(wrench, n):
    """The per-sample wrench (n + 1, 6), checked; None stays None."""
    if wrench is None:
        return None
    rows = np.asarray(wrench, dtype=float)
    if rows.shape != (n + 1, 6) or not np.all(np.isfinite(rows)):
        raise ValueError('wrench must be (%d, 6) finite numbers, got shape %s'
                         % (n + 1, rows.shape))
    return rows


def _wrench_at(wrenches, k):
    """Sample k's wrench as Dynamics.step takes it (None: none)."""
    return None if wrenches is None else (wrenches[k, :3], wrenches[k, 3:])


def _sampled_pd_segments(mech, dyn, pd, y, wrenches, n, dt, steps):
    """``_sampled_pd`` over the runs of samples with one wrench each, chained:
    a segment starts from the state the previous one ended at, so the result
    is the one call's with the wrench changing between samples."""
    bounds = [0, n]
    if wrenches is not None:
        changes = np.flatnonzero(np.any(np.diff(wrenches[:n], axis=0) != 0.0, axis=1)) + 1
        bounds = [0, *changes.tolist(), n]
    args = (pd.setpoint, pd.kp, pd.kv, float(pd.max_force),
            float(mech.leg_length_min), float(mech.leg_length_max))
    states, forces, contact = [], [], 0
    for a, b in zip(bounds, bounds[1:]):
        w = NO_WRENCH if wrenches is None else np.ascontiguousarray(wrenches[a])
        s, f, c = _sampled_pd(*dyn.kernel_args(), y, w, *args, b - a, dt, steps)
        if states:      # the first sample is the last one of the segment before
            c -= _outside(dyn.lengths_and_rates(s[0])[0], args[4], args[5])
            s, f = s[1:], f[1:]
        states.append(s)
        forces.append(f)
        contact += c
        y = s[-1].copy() if len(s) else y
    return np.concatenate(states), np.concatenate(forces), contact


def run_faulted(setup: Setup, duration: float, rate: float,
                faults: FaultModel | Iterable[str] | None,
                controller: Controller | None = None, y0: ArrayLike | None = None,
                dyn: Dynamics | None = None, wrench: ArrayLike | None = None) -> Result:
    """``run_sampled`` with sensor and actuator faults, as the lockstep plant runs it.

    Sample k: the faults begin k; the sensors read L, dL/dt; ``faults.sense``
    makes what ``leg_lengths`` would carry; the controller answers it (a
    sample with a dropped-out leg gets no answer, as the controller node
    refuses it: the force of the previous sample holds); ``faults.actuate``
    gives the applied forces, held over the period.

    Args:
        setup, duration, rate, controller, y0, dyn, wrench: as ``run_sampled``.
        faults: a ``FaultModel`` (used as it is: a fresh one for a fresh
            run) or fault strings (a model at ``rate``, seed 0; None: none).

    Returns:
        A Result, N = duration * rate + 1 rows: ``forces`` (N, 6) [N] the
        controller's commands, ``applied`` (N, 6) [N] what the pistons
        applied, ``measured`` (N, 12) what the sensors reported (L_1..L_6
        [m], dL_1/dt..dL_6/dt [m/s]), ``faults`` each fault's summary.

    Raises:
        FaultError: a bad fault string.
        ValueError: a ``wrench`` not (N, 6).
    """
    if not isinstance(faults, FaultModel):
        faults = FaultModel(parse_faults(faults), rate)
    mech = setup.mechanism
    dyn = dyn or Dynamics(mech)
    controller = controller or PDController(setup)
    period = 1.0 / rate
    steps = substeps_for(period)
    n = int(round(duration * rate))
    wrenches = _wrench_rows(wrench, n)
    y = initial_state(setup.task) if y0 is None else np.array(y0, float)
    states = np.empty((n + 1, STATE_SIZE))
    forces = np.empty((n + 1, 6))
    applied = np.empty((n + 1, 6))
    measured = np.empty((n + 1, 12))
    held = np.zeros(6)          # the plant holds zero until the first answer
    contact = 0
    for k in range(n + 1):
        faults.begin(k)
        lengths, rates = sensor_reading(dyn, y)
        contact += _outside_stroke(mech, lengths)
        states[k] = y
        lengths, rates, complete = faults.sense(lengths, rates)
        measured[k, :6], measured[k, 6:] = lengths, rates
        if complete:
            held = controller.forces(k * period, lengths, rates)
        forces[k] = held
        applied[k] = faults.actuate(held)
        if k < n:
            y = dyn.step(y, applied[k], period, steps, _wrench_at(wrenches, k))
    return Result(np.arange(n + 1) * period, states, forces, contact, 4 * steps * n,
                  applied=applied, measured=measured, faults=faults.summary())


def run_continuous(setup: Setup, duration: float, output_rate: float = 100.0,
                   controller: Controller | None = None, y0: ArrayLike | None = None,
                   rtol: float = 1e-8, atol: float = 1e-10,
                   dyn: Dynamics | None = None, integrator: str = 'compiled',
                   max_steps: int = dopri.MAX_STEPS) -> Result:
    """Eq. (40) inside the ODE, adaptive RK45 (the paper's ode45), output at ``output_rate``.

    ``integrator='compiled'`` (default) runs scipy's RK45 compiled
    (``dopri.solve_pd``: same steps, same dense output, ~4x faster);
    ``'scipy'`` calls ``scipy.integrate.solve_ivp`` (the reference).
    A controller whose ``pd_gains()`` is None (any law but eq. (40) towards
    fixed lengths) runs inside scipy's ``solve_ivp``.

    Args:
        setup: the machine, gains and task (``params.load_setup``).
        duration: simulated time [s]; output_rate: rows per second [Hz].
        controller: a ``laws.Controller``; None: eq. (40) with the setup's
            setpoint and gains and the mechanism's saturation.
        y0: the initial state (13,); default ``initial_state(setup.task)``.
        rtol, atol: the integrator's tolerances.
        dyn: the model to use (default: a new ``Dynamics(setup.mechanism)``).
        integrator: ``'compiled'`` or ``'scipy'``.
        max_steps: bounds the compiled integrator's step attempts.

    Returns:
        One row per output time, N = duration * output_rate + 1.

    Raises:
        ValueError: an unknown ``integrator``, or a non-finite initial state.
        RuntimeError: the integration failed.
    """
    if integrator not in ('compiled', 'scipy'):
        raise ValueError("integrator must be 'compiled' or 'scipy', not %r" % (integrator,))
    mech = setup.mechanism
    dyn = dyn or Dynamics(mech)
    pd = _fixed_pd(setup, controller)
    if pd is None:
        return _continuous_law(setup, dyn, duration, output_rate, controller, y0, rtol, atol)

    # One compiled call per evaluation: dynamics and eq. (40) from the same L, dL/dt.
    args = dyn.kernel_args()
    gains = pd.rows()
    zero, max_force = np.zeros(6), float(pd.max_force)

    y = initial_state(setup.task) if y0 is None else np.array(y0, float)
    n = int(round(duration * output_rate))
    t_eval = np.arange(n + 1) / output_rate
    if integrator == 'compiled':
        states, info = dopri.solve_pd(dyn, y, t_eval, forces=zero, gains=gains,
                                      max_force=max_force, rtol=rtol, atol=atol,
                                      max_steps=max_steps)
        times, nfev = t_eval, info['nfev']
    else:
        def rhs(_t, y):
            return derivative_pd(*args, y, zero, NO_WRENCH, True, gains, max_force)

        # solve_ivp would loop forever on a NaN first step size (NaN derivative at t0).
        if np.all(np.isfinite(y)) and not np.all(np.isfinite(rhs(0.0, y))):
            raise RuntimeError('integration failed: %s at the initial state'
                               % dopri.STATUS_MESSAGES[dopri.NON_FINITE])
        sol = solve_ivp(rhs, (0.0, t_eval[-1]), y, method='RK45', t_eval=t_eval,
                        rtol=rtol, atol=atol)
        if not sol.success:
            raise RuntimeError('integration failed: %s' % sol.message)
        states, times, nfev = sol.y.T.copy(), sol.t, sol.nfev
    states[:, QUAT] /= np.linalg.norm(states[:, QUAT], axis=1)[:, None]
    forces, contact = _pd_samples(dyn.base_points, dyn.leg_points, states, pd.setpoint,
                                  pd.kp, pd.kv, max_force,
                                  float(mech.leg_length_min), float(mech.leg_length_max))
    return Result(times, states, forces, int(contact), int(nfev))


def _continuous_law(setup, dyn, duration, output_rate, controller, y0, rtol, atol) -> Result:
    """A law other than plain eq. (40) inside the ODE: scipy's RK45 (``solve_ivp``)
    on dy/dt = f(y, law(t, L(y), dL/dt(y))). A law with a pose estimate tracks it
    from evaluation to evaluation (Newton from the previous one). The forces
    reported at the output times are the law evaluated again there."""
    args = dyn.kernel_args()
    base, plat = dyn.base_points, dyn.leg_points

    def law(t, y):
        lengths, rates = lengths_rates(base, plat, y)
        return controller.forces(t, lengths, rates)

    def rhs(t, y):
        return derivative_pd(*args, y, law(t, y), NO_WRENCH, True, NO_GAINS, 0.0)

    y = initial_state(setup.task) if y0 is None else np.array(y0, float)
    n = int(round(duration * output_rate))
    t_eval = np.arange(n + 1) / output_rate
    sol = solve_ivp(rhs, (0.0, t_eval[-1]), y, method='RK45', t_eval=t_eval, rtol=rtol,
                    atol=atol)
    if not sol.success:
        raise RuntimeError('integration failed: %s' % sol.message)
    states = sol.y.T.copy()
    states[:, QUAT] /= np.linalg.norm(states[:, QUAT], axis=1)[:, None]
    forces = np.empty((len(states), 6))
    contact = 0
    for k, yk in enumerate(states):
        lengths, rates = lengths_rates(base, plat, yk)
        contact += _outside_stroke(setup.mechanism, lengths)
        forces[k] = controller.forces(sol.t[k], lengths, rates)
    return Result(sol.t, states, forces, int(contact), int(sol.nfev))
