"""Integration of the closed loop: the paper's scenario offline (section VI).

Two control modes:
- ``continuous``: eq. (40) evaluated inside the ODE, adaptive RK45 as the
  paper's ode45 (scipy ``solve_ivp``);
- ``sampled``: eq. (40) sampled at ``rate`` Hz and held (zero-order hold),
  fixed-step RK4 between samples, exactly as the plant node runs it, so a
  lockstep rig reproduces it sample for sample.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy.integrate import solve_ivp

from stewart63_ros.core.control import PDController
from stewart63_ros.core.dynamics import OMEGA, POS, QUAT, STATE_SIZE, VEL, Dynamics
from stewart63_ros.core.rotation import (euler_from_quaternion, euler_rate_matrix,
                                         quaternion_from_euler)

#: Longest RK4 step of the sampled/plant integrator [s]. 1 ms keeps the
#: end-stop spring (about 700 rad/s) well inside RK4's stability region.
MAX_STEP = 1.0e-3


def initial_state(mech) -> np.ndarray:
    """The 13-state at t = 0 from t_0, dt_0/dt, theta_0, dtheta_0/dt of the parameters."""
    y = np.empty(STATE_SIZE)
    y[POS] = mech.initial_position
    y[QUAT] = quaternion_from_euler(mech.initial_orientation)
    y[VEL] = mech.initial_velocity
    y[OMEGA] = euler_rate_matrix(mech.initial_orientation) @ mech.initial_orientation_rate
    return y


def substeps_for(period: float) -> int:
    """RK4 steps per control period so that none exceeds MAX_STEP."""
    return max(1, int(math.ceil(period / MAX_STEP - 1e-9)))


def sensor_reading(dyn: Dynamics, y) -> tuple[np.ndarray, np.ndarray]:
    """What ideal linear sensors measure: L_i and dL_i/dt, eqs. (5), (13)."""
    return dyn.lengths_and_rates(y)


@dataclasses.dataclass
class Result:
    """Samples of a run: times (N,), states (N, 13), forces (N, 6) applied from each time."""
    times: np.ndarray
    states: np.ndarray
    forces: np.ndarray
    endstop_samples: int = 0     # samples with some leg outside its stroke
    rhs_evaluations: int = 0

    def table(self, dyn: Dynamics) -> np.ndarray:
        """Rows of the trajectory CSV (CONTRACT section 5)."""
        rows = np.empty((len(self.times), 31))
        rows[:, 0] = self.times
        rows[:, 1:4] = self.states[:, POS]
        rows[:, 4:7] = euler_from_quaternion(self.states[:, QUAT])
        rows[:, 7:10] = self.states[:, VEL]
        rows[:, 10:13] = self.states[:, OMEGA]
        for k, y in enumerate(self.states):
            rows[k, 13:19], rows[k, 19:25] = sensor_reading(dyn, y)
        rows[:, 25:31] = self.forces
        return rows

    def final_leg_error_percent(self, dyn: Dynamics, setpoint) -> np.ndarray:
        """|L_i - (L_i)_0| / (L_i)_0 in % at the last sample, per leg."""
        lengths, _ = sensor_reading(dyn, self.states[-1])
        return 100.0 * np.abs(lengths - setpoint) / np.asarray(setpoint)


def _outside_stroke(mech, lengths) -> bool:
    return bool(np.any(lengths < mech.leg_length_min) or np.any(lengths > mech.leg_length_max))


def run_sampled(mech, duration: float, rate: float, controller=None, y0=None,
                dyn: Dynamics | None = None) -> Result:
    """Eq. (40) sampled at ``rate`` Hz with zero-order hold; RK4 in between.

    Sample k at t_k = k / rate: measure L, dL/dt; F_k = PD; hold F_k over
    [t_k, t_k+1). This is the loop the plant and controller nodes close over DDS.
    """
    dyn = dyn or Dynamics(mech)
    controller = controller or PDController(mech)
    period = 1.0 / rate
    steps = substeps_for(period)
    n = int(round(duration * rate))
    states = np.empty((n + 1, STATE_SIZE))
    forces = np.empty((n + 1, 6))
    y = initial_state(mech) if y0 is None else np.array(y0, float)
    contact = 0
    for k in range(n + 1):
        lengths, rates = sensor_reading(dyn, y)
        contact += _outside_stroke(mech, lengths)
        states[k] = y
        forces[k] = controller(lengths, rates)
        if k < n:
            y = dyn.step(y, forces[k], period, steps)
    return Result(np.arange(n + 1) * period, states, forces, contact, 4 * steps * n)


def run_continuous(mech, duration: float, output_rate: float = 100.0, controller=None,
                   y0=None, rtol: float = 1e-8, atol: float = 1e-10,
                   dyn: Dynamics | None = None) -> Result:
    """Eq. (40) inside the ODE, adaptive RK45 (the paper's ode45), output at ``output_rate``."""
    dyn = dyn or Dynamics(mech)
    controller = controller or PDController(mech)

    # One compiled call per evaluation: dynamics and eq. (40) from the same L, dL/dt.
    from stewart63_ros.core.dynamics import _derivative_pd, _NO_WRENCH
    args = dyn._args() + ()
    gains = np.vstack([controller.setpoint, controller.kp, controller.kv])
    zero, max_force = np.zeros(6), controller.max_force

    def rhs(_t, y):
        return _derivative_pd(*args, y, zero, _NO_WRENCH, True, gains, max_force)

    y = initial_state(mech) if y0 is None else np.array(y0, float)
    n = int(round(duration * output_rate))
    t_eval = np.arange(n + 1) / output_rate
    sol = solve_ivp(rhs, (0.0, t_eval[-1]), y, method='RK45', t_eval=t_eval,
                    rtol=rtol, atol=atol)
    if not sol.success:
        raise RuntimeError('integration failed: %s' % sol.message)
    states = sol.y.T.copy()
    states[:, QUAT] /= np.linalg.norm(states[:, QUAT], axis=1)[:, None]
    forces = np.empty((len(states), 6))
    contact = 0
    for k, yk in enumerate(states):
        lengths, rates = sensor_reading(dyn, yk)
        contact += _outside_stroke(mech, lengths)
        forces[k] = controller(lengths, rates)
    return Result(sol.t, states, forces, contact, sol.nfev)
