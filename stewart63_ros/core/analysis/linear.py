"""The mechanism linearized about an equilibrium (``equilibrium``): the state
space model, open loop or closed through a control law.

The linear model is about x0: dx/dt = A dx + B du, dy = C dx + D du with
dx = x - x0 (x0's rotation entries are R0's rotation vector, recorded for
information: a perturbation is applied as exp([dphi]x) R0, never added to it).

- Open loop (``law=None``): inputs u = the six piston forces F_i [N]
  (positive extends the leg), outputs y = the six leg lengths L_i [m] (eq. 5).
- Closed loop (a control law, e.g. ``pd`` = eq. (40)): inputs u = the six
  leg-length references (L_i)_ref [m]; u0 is the reference that makes the law
  give exactly u0_forces at the equilibrium (for ``pd``: L0 + u0_forces / Kp,
  the gravity sag; for ``pd_gravity`` and ``computed_torque``: L0).

A and B come from central differences of the compiled right-hand side
(``dynamics.derivative_pd``: eq. 38 assembled and solved) in the chart above;
the rotation rows use phi' = J_l(phi)^-1 omega (the inverse left Jacobian of
SO(3)). C is the Jacobian of eq. (5) by the same differences (rows
[s_i, q_i x s_i], eq. 13). The ``pd`` law is folded in analytically,
F = Kp (L_ref - L) - Kv dL/dt, i.e. dF = Kp du - Kp C dx - Kv [0, J] dx;
any other law is differenced through ``laws.Controller`` exactly as the
controller node runs it.

The state x and the chart are ``equilibrium``'s.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from stewart63_ros.core.analysis.equilibrium import (
    DEFAULT_MAX_CONDITION,
    AnalysisError,
    Equilibrium,
    chart_derivative,
    chart_outputs,
    equilibrium,
)
from stewart63_ros.core.controllers.laws import (
    HOLDING_GAIN_LAWS,
    Controller,
    LawError,
    holding_gain_problem,
    make_law,
)
from stewart63_ros.core.controllers.reference import Reference
from stewart63_ros.core.mechanics.dynamics import Dynamics
from stewart63_ros.core.mechanics.mechanism import Mechanism
from stewart63_ros.core.mechanics.setup import Setup
from stewart63_ros.core.plumbing.legs import LEG_NAMES

#: Names of the 12 states, the pose coordinates and their units.
STATE_NAMES = ('x', 'y', 'z', 'phi_x', 'phi_y', 'phi_z',
               'v_x', 'v_y', 'v_z', 'omega_x', 'omega_y', 'omega_z')
STATE_MEANINGS = (
    'platform position x [m], base frame', 'platform position y [m], base frame',
    'platform position z [m], base frame',
    'rotation vector x [rad]: R = exp([phi]x) R0, base frame',
    'rotation vector y [rad]: R = exp([phi]x) R0, base frame',
    'rotation vector z [rad]: R = exp([phi]x) R0, base frame',
    'velocity x [m/s], base frame', 'velocity y [m/s], base frame',
    'velocity z [m/s], base frame',
    'angular velocity x [rad/s], base frame', 'angular velocity y [rad/s], base frame',
    'angular velocity z [rad/s], base frame')
POSE_NAMES = ('x', 'y', 'z', 'theta_x', 'theta_y', 'theta_z')

#: Central-difference steps: states (m, rad, m/s, rad/s), forces [N], references [m].
STATE_STEP = 1e-6
FORCE_STEP = 1e-2
REFERENCE_STEP = 1e-6



def _central(func, n: int, step: float) -> np.ndarray:
    """(m, n) d func / d z at z = 0 by central differences, func: (n,) -> (m,)."""
    columns = []
    for k in range(n):
        e = np.zeros(n)
        e[k] = step
        columns.append((func(e) - func(-e)) / (2.0 * step))
    return np.column_stack(columns)


# -- the linear model --------------------------------------------------------------------------
@dataclasses.dataclass
class LinearModel:
    """dx/dt = A dx + B du, dy = C dx + D du about (x0, u0).

    Attributes:
        A: (12, 12); B: (12, 6); C: (6, 12); D: (6, 6).
        x0: (12,) equilibrium state (position, R0's rotation vector, zero twist).
        u0: (6,) equilibrium input: holding forces [N] (open loop) or the
            leg-length references [m] that hold the pose (closed loop).
        y0: (6,) leg lengths at the equilibrium [m].
        equilibrium: the ``Equilibrium``.
        law: the control law's name, or None for the open loop.
    """
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    x0: np.ndarray
    u0: np.ndarray
    y0: np.ndarray
    equilibrium: Equilibrium
    law: str | None = None

    @property
    def closed_loop(self) -> bool:
        """True under a control law (inputs: leg-length references), False open loop."""
        return self.law is not None

    def input_meanings(self) -> list[str]:
        """What each of the six inputs is, with its unit, in leg order.

        Returns:
            Six strings: piston forces F_i [N] (open loop) or leg-length
            references (L_i)_ref [m] (closed loop).
        """
        if self.closed_loop:
            return ['leg-length reference (L_%d)_ref [m] of the %s law' % (i + 1, self.law)
                    for i in range(6)]
        return ['piston force F_%d [N], positive extends the leg' % (i + 1) for i in range(6)]

    def describe(self) -> dict:
        """Everything of the model as plain JSON types, with what each row and column means."""
        eq = self.equilibrium
        return {
            'loop': 'closed' if self.closed_loop else 'open',
            'control_law': self.law,
            'A': self.A.tolist(), 'B': self.B.tolist(), 'C': self.C.tolist(),
            'D': self.D.tolist(), 'x0': self.x0.tolist(), 'u0': self.u0.tolist(),
            'y0': self.y0.tolist(),
            'states': [{'name': n, 'meaning': m} for n, m in zip(STATE_NAMES, STATE_MEANINGS)],
            'inputs': [{'name': n, 'meaning': m} for n, m in zip(LEG_NAMES,
                                                                  self.input_meanings())],
            'outputs': [{'name': n, 'meaning': 'leg length L_%d [m], eq. (5)' % (i + 1)}
                        for i, n in enumerate(LEG_NAMES)],
            'equations': 'd(x - x0)/dt = A (x - x0) + B (u - u0); y - y0 = C (x - x0) + '
                         'D (u - u0); rotation: R = exp([phi - phi0]x) R0',
            'pose': eq.pose.tolist(),
            'pose_names': list(POSE_NAMES),
            'rotation': eq.rotation.tolist(),
            'holding_forces': eq.forces.tolist(),
            'condition_number': eq.condition,
        }


def open_loop(mech: Mechanism, eq: Equilibrium, dyn: Dynamics | None = None) -> LinearModel:
    """The plant alone about ``eq``: inputs the six piston forces, outputs the leg lengths.

    Args:
        mech: the plant's mechanism.
        eq: the equilibrium x0 (u0: its holding forces).
        dyn: the model (default: a new ``Dynamics(mech)``).

    Returns:
        The open-loop ``LinearModel``: A (12, 12), B (12, 6) per newton,
        C (6, 12), D = 0 (6, 6), u0 (6,) [N], y0 (6,) [m].
    """
    dyn = dyn or Dynamics(mech)
    u0 = eq.forces
    zero = np.zeros(12)
    A = _central(lambda d: chart_derivative(dyn, eq, d, u0), 12, STATE_STEP)
    B = _central(lambda d: chart_derivative(dyn, eq, zero, u0 + d), 6, FORCE_STEP)
    C = _central(lambda d: chart_outputs(dyn, eq, d)[0], 12, STATE_STEP)
    return LinearModel(A, B, C, np.zeros((6, 6)), eq.state12(), u0.copy(), eq.lengths.copy(),
                       eq)


def _law_controller(setup, params, law, eq: Equilibrium, references):
    ref = Reference.constant_lengths(setup.mechanism, references,
                                     near=(eq.position, eq.rotation))
    return Controller(setup, params, law=law, reference=ref)


def law_jacobians(dyn: Dynamics, eq: Equilibrium, law: str, references: ArrayLike,
                  controller: Setup, params: Mapping[str, Any] | None = None,
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Forces of a law (through ``laws.Controller``, as the controller node runs it)
    and their derivatives at the equilibrium, by central differences.

    Args:
        dyn: the plant's model.
        eq: the equilibrium x0.
        law: the law's name (``pd``, ``pd_gravity``, ``computed_torque``,
            ``package.module:Class``).
        references: (6,) the leg-length references about which to differentiate [m].
        controller: the controller's setup (machine, gains, task).
        params: the controller's parameters (over its setup's), or None.

    Returns:
        (forces (6,) [N], K_x (6, 12) = dF/dx, K_r (6, 6) = dF/d(reference)
        [N/m]); K_x's columns in the chart's units (N/m, N/rad, N s/m, N s/rad).

    Raises:
        AnalysisError: the law raised (``LawError``) at the pose.
    """
    references = np.asarray(references, dtype=float)

    def forces_of(controller, dx):
        lengths, rates = chart_outputs(dyn, eq, dx)
        return np.array(controller(lengths, rates, 0.0), dtype=float)

    try:
        at_ref = _law_controller(controller, params, law, eq, references)
        zero = np.zeros(12)
        forces = forces_of(at_ref, zero)          # also settles a law's pose estimate
        K_x = _central(lambda d: forces_of(at_ref, d), 12, STATE_STEP)

        def by_reference(d):
            return forces_of(_law_controller(controller, params, law, eq, references + d),
                             zero)

        K_r = _central(by_reference, 6, REFERENCE_STEP)
    except LawError as exc:
        raise AnalysisError('the control law failed at the pose: %s' % exc) from None
    return forces, K_x, K_r


def _pd_gains(mech, params, law_name='pd'):
    law = make_law(law_name, mech, dict(params or {}))
    return np.asarray(law.kp, float), np.asarray(law.kv, float)


def holding_references(dyn: Dynamics, eq: Equilibrium, law: str, controller: Setup,
                       params: Mapping[str, Any] | None = None,
                       iterations: int = 20) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The leg-length references u0 for which the law gives the holding forces at
    rest at the pose, with the law's Jacobians there.

    Newton on F(x0, r) = F_hold from r = L0 (for ``pd`` the first step is exact:
    r = L0 + F_hold / Kp; for laws that hold the pose by themselves r = L0).

    Args:
        dyn: the plant's model.
        eq: the equilibrium x0 (its holding forces are the target).
        law: the law's name, as ``law_jacobians``.
        controller: the controller's setup (machine, gains, task).
        params: the controller's parameters, or None.
        iterations: the most Newton steps.

    Returns:
        (u0 (6,) [m], K_x (6, 12), K_r (6, 6) [N/m]), as ``law_jacobians`` at u0.

    Raises:
        AnalysisError: the law's forces do not depend on the references, or
            Newton does not converge (the law cannot hold the pose).
    """
    r = eq.lengths.copy()
    tol = 1e-9 * max(1.0, float(np.max(np.abs(eq.forces))))
    for _ in range(iterations):
        forces, K_x, K_r = law_jacobians(dyn, eq, law, r, controller, params)
        miss = forces - eq.forces
        if np.max(np.abs(miss)) <= tol:
            return r, K_x, K_r
        try:
            step = np.linalg.solve(K_r, miss)
        except np.linalg.LinAlgError:
            step = None
        if step is None or not np.all(np.isfinite(step)) or np.linalg.cond(K_r) > 1e12:
            raise AnalysisError('the %s law cannot hold the pose: its forces do not depend '
                                'on the leg-length references (a gain of zero?)' % law)
        r = r - step
    raise AnalysisError('the %s law cannot hold the pose: no leg-length reference gives '
                        'the holding forces (off by %.3g N)' % (law, np.max(np.abs(miss))))


def closed_loop(setup: Setup, eq: Equilibrium, law: str,
                params: Mapping[str, Any] | None = None, dyn: Dynamics | None = None,
                controller: Setup | None = None,
                numeric: bool = False) -> LinearModel:
    """The plant under a control law about ``eq``: inputs the six leg-length references.

    ``pd`` (eq. 40) is folded in analytically unless ``numeric``; any other law
    (``pd_gravity``, ``computed_torque``, ``package.module:Class``) is
    differenced through ``laws.Controller``.

    Args:
        setup: the plant's setup (its machine).
        eq: the equilibrium x0.
        law: the law's name.
        params: the controller's parameter dictionary (gains), over the
            controller setup's own; None for those alone.
        dyn: the plant's model (default: a new ``Dynamics(setup.mechanism)``).
        controller: the controller's setup (default ``setup``).
        numeric: difference ``pd`` through ``laws.Controller`` too.

    Returns:
        The closed-loop ``LinearModel``: A (12, 12), B (12, 6) per metre of
        reference, C (6, 12), D = 0 (6, 6), u0 (6,) the references [m].

    Raises:
        AnalysisError: the law cannot hold the pose (a zero gain, no
            convergence) or fails there.
    """
    mech = setup.mechanism
    dyn = dyn or Dynamics(mech)
    plant = open_loop(mech, eq, dyn)
    controller = controller or setup
    params = dict(controller.to_params(), **(params or {}))
    if law in HOLDING_GAIN_LAWS:
        problem = holding_gain_problem(law, _pd_gains(controller.mechanism, params, law)[0])
        if problem:
            raise AnalysisError(problem)
    if law == 'pd' and not numeric:
        kp, kv = _pd_gains(controller.mechanism, params)
        u0 = eq.lengths + eq.forces / kp
        jac = plant.C[:, 0:6]
        rate_rows = np.hstack([np.zeros((6, 6)), jac])      # dL/dt = J [v; omega] (eq. 13)
        K_x = -kp[:, None] * plant.C - kv[:, None] * rate_rows
        K_r = np.diag(kp)
    else:
        u0, K_x, K_r = holding_references(dyn, eq, law, controller, params)
    A = plant.A + plant.B @ K_x
    B = plant.B @ K_r
    return LinearModel(A, B, plant.C.copy(), np.zeros((6, 6)), plant.x0, u0, plant.y0, eq, law)


def linearize(setup: Setup, law: str | None = None, pose: ArrayLike | None = None,
              params: Mapping[str, Any] | None = None, max_condition: float = DEFAULT_MAX_CONDITION,
              controller: Setup | None = None) -> LinearModel:
    """The linear model about the equilibrium at ``pose`` (default: the setpoint's).

    Args:
        setup: the plant's setup (machine; task: the setpoint's pose).
        law: None for the open loop, else a law name (``pd``, ``pd_gravity``,
            ``computed_torque``, ``package.module:Class``).
        pose: (6,) x, y, z [m], theta_x, theta_y, theta_z [rad], or None.
        params: the controller's parameter dictionary (gains, law parameters).
        max_condition: refuse poses whose Jacobian condition number exceeds this.
        controller: the controller's setup (default ``setup``).

    Returns:
        The ``LinearModel``.

    Raises:
        AnalysisError: an unusable pose or law; ParameterError: an unknown law.
    """
    dyn = Dynamics(setup.mechanism)
    eq = equilibrium(setup, pose, max_condition, dyn)
    if law is None:
        return open_loop(setup.mechanism, eq, dyn)
    return closed_loop(setup, eq, law, params, dyn, controller)
