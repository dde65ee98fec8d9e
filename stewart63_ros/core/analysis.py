"""The mechanism linearized about an equilibrium: state space, modes, frequency responses.

Equilibrium: the platform at rest at a pose (t0, R0), held against gravity
by the piston forces u0 that solve eq. (38) with zero velocity and
acceleration, H u0 = eta(q, 0) (platform and both parts of every leg; the
``inverse_dynamics_forces`` kernel). The default pose is the forward
kinematics of the parameter file's ``setpoint_lengths`` (the assembly mode
nearest the initial pose).

State (12): x = (t, phi, v, omega): platform position [m], a small rotation
vector phi [rad] with R = exp([phi]x) R0 (base frame, left perturbation),
velocity [m/s] and angular velocity [rad/s], both in the base frame. The
linear model is about x0: dx/dt = A dx + B du, dy = C dx + D du with
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

Modes: the eigenvalues of A in pairs (complex conjugates, or two real ones
matched by the shape of their eigenvectors); a pair (l1, l2) has natural
frequency sqrt(l1 l2) / 2 pi and damping ratio -(l1 + l2) / (2 sqrt(l1 l2)),
which holds for an underdamped pair (zeta < 1) and an overdamped one
(zeta > 1) alike. A pair with l1 l2 < 0 (one eigenvalue positive: a negative
stiffness, the platform falls away from the pose) gets sqrt(|l1 l2|) and is
marked unstable.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from stewart63_ros.core.dynamics import (
    NO_GAINS,
    NO_WRENCH,
    STATE_SIZE,
    Dynamics,
    derivative_pd,
    inverse_dynamics_forces,
    lengths_rates,
)
from stewart63_ros.core.fk import ForwardKinematics
from stewart63_ros.core.laws import (
    HOLDING_GAIN_LAWS,
    Controller,
    LawError,
    holding_gain_problem,
    make_law,
)
from stewart63_ros.core.legs import LEG_NAMES
from stewart63_ros.core.mechanism import Mechanism
from stewart63_ros.core.reference import Reference
from stewart63_ros.core.rotation import (
    euler_from_matrix,
    euler_rate_matrix,
    quaternion_from_rotation,
    quaternion_of_rotvec_times,
    rotation_from_euler,
    rotvec_between,
    rotvec_from_rotation,
)
from stewart63_ros.core.setup import Setup

#: A pose whose Jacobian (rows [s_i, q_i x s_i], metres) has a 2-norm
#: condition number above this is refused as near-singular (``--max-condition``).
#: Over the default workspace it stays between 3 and 6; fk flags 1e4, where
#: its pose estimate is no longer trusted. At 100 a leg-length error moves the
#: pose by up to 100 times as much: no model for a controller to design on.
DEFAULT_MAX_CONDITION = 100.0

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


class AnalysisError(ValueError):
    """A pose or law the analysis cannot use; the message names the problem."""


# -- the equilibrium ---------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Equilibrium:
    """The platform at rest at a pose, held by ``forces``.

    Attributes:
        position: t0 (3,) [m], base frame.
        rotation: R0 (3, 3), platform to base.
        forces: the six holding piston forces u0 (6,) [N], eq. (38) with zero twist.
        lengths: the six leg lengths L0 (6,) [m] (eq. 5).
        condition: 2-norm condition number of the Jacobian at the pose.
    """
    position: np.ndarray
    rotation: np.ndarray
    forces: np.ndarray
    lengths: np.ndarray
    condition: float

    @property
    def theta(self) -> np.ndarray:
        """(3,) Euler angles theta_x, theta_y, theta_z [rad] (R = Rz Ry Rx)."""
        return euler_from_matrix(self.rotation)

    @property
    def pose(self) -> np.ndarray:
        """(6,) x, y, z [m], theta_x, theta_y, theta_z [rad]."""
        return np.concatenate([self.position, self.theta])

    def state13(self) -> np.ndarray:
        """(13,) the dynamics' state: position, quaternion (x, y, z, w), zero twist."""
        y = np.zeros(STATE_SIZE)
        y[0:3] = self.position
        y[3:7] = quaternion_from_rotation(self.rotation)
        return y

    def state12(self) -> np.ndarray:
        """(12,) x0: position, R0's rotation vector (for information), zero twist."""
        x = np.zeros(12)
        x[0:3] = self.position
        x[3:6] = rotvec_from_rotation(self.rotation)
        return x


def setpoint_pose(setup: Setup) -> tuple[np.ndarray, np.ndarray]:
    """The setpoint's pose: the forward kinematics of ``setpoint_lengths``, the
    assembly mode nearest the initial pose.

    Args:
        setup: the machine and the task (``setpoint_lengths``, the initial pose).

    Returns:
        (position t (3,) [m], rotation R (3, 3), platform to base).

    Raises:
        AnalysisError: the setpoint lengths close no platform.
    """
    try:
        task = setup.task
        mode = ForwardKinematics(setup.mechanism, start=(
            task.initial_position, task.initial_rotation)).all_modes(task.setpoint_lengths)[0]
    except ValueError as exc:
        raise AnalysisError('setpoint_lengths: no pose: %s' % exc) from None
    return mode.position, mode.rotation


def pose_lengths_condition(mech: Mechanism, position: ArrayLike,
                           rotation: ArrayLike) -> tuple[np.ndarray, float]:
    """Leg lengths (6,) [m] (eq. 5) and the Jacobian's condition number at a pose.

    Args:
        mech: the mechanism.
        position: t (3,) [m], base frame.
        rotation: R (3, 3), platform to base.

    Returns:
        (lengths (6,) [m], 2-norm condition number of the Jacobian (rows
        [s_i, q_i x s_i], metres)).
    """
    fk = ForwardKinematics(mech)
    lengths, _ = lengths_rates(fk.base, fk.legp, _state13(position, rotation))
    return lengths, fk.condition(position, rotation)


def check_pose(mech: Mechanism, position: ArrayLike, rotation: ArrayLike,
               max_condition: float = DEFAULT_MAX_CONDITION) -> tuple[np.ndarray, float]:
    """Leg lengths and condition number of a pose the analysis can use.

    Args:
        mech: the mechanism (its stroke ``leg_length_min``, ``leg_length_max``).
        position: t (3,) [m], base frame.
        rotation: R (3, 3), platform to base.
        max_condition: the largest Jacobian condition number accepted.

    Returns:
        (lengths (6,) [m], condition number), as ``pose_lengths_condition``.

    Raises:
        AnalysisError: a leg outside the stroke [leg_length_min, leg_length_max],
            or the condition number above ``max_condition`` (near a singularity).
    """
    lengths, condition = pose_lengths_condition(mech, position, rotation)
    bad = np.flatnonzero((lengths < mech.leg_length_min) | (lengths > mech.leg_length_max))
    if bad.size:
        i = int(bad[0])
        raise AnalysisError('pose outside the stroke: leg_%d length %.4f m is outside '
                            '[leg_length_min %g, leg_length_max %g]'
                            % (i + 1, lengths[i], mech.leg_length_min, mech.leg_length_max))
    if not condition <= max_condition:
        raise AnalysisError('singular pose: the Jacobian\'s condition number %.4g exceeds '
                            '%g (--max-condition)' % (condition, max_condition))
    return lengths, float(condition)


def holding_forces(dyn: Dynamics, position: ArrayLike, rotation: ArrayLike) -> np.ndarray:
    """The piston forces that hold platform and legs still at a pose against
    gravity: H F = eta(q, 0), eq. (38) with zero twist and acceleration.

    Args:
        dyn: the model.
        position: t (3,) [m], base frame.
        rotation: R (3, 3), platform to base.

    Returns:
        (6,) piston forces [N], positive extends (NaN where H is singular).
    """
    zero = np.zeros(3)
    return inverse_dynamics_forces(*dyn.kernel_args(), np.asarray(rotation, float),
                                   np.asarray(position, float), zero, zero, np.zeros(6))


def equilibrium(setup: Setup, pose: ArrayLike | None = None,
                max_condition: float = DEFAULT_MAX_CONDITION,
                dyn: Dynamics | None = None) -> Equilibrium:
    """The equilibrium at ``pose``; default the setpoint's pose (``setpoint_pose``).

    Args:
        setup: the machine and the task (the setpoint's pose).
        pose: (6,) x, y, z [m], theta_x, theta_y, theta_z [rad] (R = Rz Ry Rx),
            or None for the setpoint's pose.
        max_condition: the largest Jacobian condition number accepted.
        dyn: the model (default: a new ``Dynamics(mech)``).

    Returns:
        The ``Equilibrium``: pose, holding forces (6,) [N], lengths (6,) [m].

    Raises:
        AnalysisError: a pose that is not six finite numbers, or one outside
            the stroke, near-singular, or needing a holding force beyond
            ``max_force``; the setpoint lengths close no platform.
    """
    mech = setup.mechanism
    if pose is None:
        position, rotation = setpoint_pose(setup)
    else:
        pose = np.asarray(pose, dtype=float)
        if pose.shape != (6,) or not np.all(np.isfinite(pose)):
            raise AnalysisError('pose: expected six finite numbers x y z theta_x theta_y '
                                'theta_z, got %r' % (pose.tolist(),))
        position, rotation = pose[:3].copy(), rotation_from_euler(pose[3:])
    lengths, condition = check_pose(mech, position, rotation, max_condition)
    forces = holding_forces(dyn or Dynamics(mech), position, rotation)
    worst = int(np.argmax(np.abs(forces)))
    if not abs(forces[worst]) <= mech.max_force:
        raise AnalysisError('holding the pose needs %.1f N on leg_%d, beyond max_force %g N'
                            % (forces[worst], worst + 1, mech.max_force))
    return Equilibrium(np.asarray(position, float), np.asarray(rotation, float), forces,
                       lengths, condition)


# -- the chart: 12-state <-> the dynamics' 13-state ------------------------------------------
def _state13(position, rotation, velocity=(0.0, 0.0, 0.0), omega=(0.0, 0.0, 0.0)):
    y = np.empty(STATE_SIZE)
    y[0:3] = position
    y[3:7] = quaternion_from_rotation(np.asarray(rotation, float))
    y[7:10] = velocity
    y[10:13] = omega
    return y


def state13_from_chart(dx: ArrayLike, eq: Equilibrium) -> np.ndarray:
    """The dynamics' state at x0 + dx: position t0 + dx[0:3], rotation
    exp([dx[3:6]]x) R0, velocity dx[6:9], angular velocity dx[9:12].

    Args:
        dx: (12,) the chart's state about ``eq`` [m, rad, m/s, rad/s].
        eq: the equilibrium x0.

    Returns:
        (13,) position [m], quaternion (x, y, z, w), velocity [m/s], angular
        velocity [rad/s], base frame.
    """
    dx = np.asarray(dx, dtype=float)
    y = np.empty(STATE_SIZE)
    y[0:3] = eq.position + dx[0:3]
    y[3:7] = quaternion_of_rotvec_times(dx[3:6], eq.rotation)
    y[7:13] = dx[6:12]
    return y


def chart_from_state13(y: ArrayLike, eq: Equilibrium) -> np.ndarray:
    """The chart's dx of the dynamics' states: the inverse of ``state13_from_chart``,
    phi = log(R R0^T).

    Args:
        y: (13,) a state, or (N, 13) states, as the dynamics' (quaternion x, y, z, w).
        eq: the equilibrium x0.

    Returns:
        (12,) dx, or (N, 12) for (N, 13) [m, rad, m/s, rad/s].
    """
    y = np.asarray(y, dtype=float)
    single = y.ndim == 1
    y = np.atleast_2d(y)
    dx = np.empty((len(y), 12))
    dx[:, 0:3] = y[:, 0:3] - eq.position
    dx[:, 3:6] = rotvec_between(y[:, 3:7], eq.rotation)
    dx[:, 6:12] = y[:, 7:13]
    return dx[0] if single else dx


def left_jacobian_inverse(phi: ArrayLike) -> np.ndarray:
    """J_l(phi)^-1 of SO(3): phi' = J_l^-1 omega when R = exp([phi]x) R0 and
    omega is R's base-frame angular velocity (Barfoot, State Estimation for
    Robotics, eq. 7.77): 1 - [phi]/2 + (1/a^2 - (1 + cos a)/(2 a sin a)) [phi]^2.

    Args:
        phi: (3,) rotation vector [rad] (a series below |phi| = 1e-4).

    Returns:
        (3, 3) J_l(phi)^-1.
    """
    phi = np.asarray(phi, dtype=float)
    a = float(np.linalg.norm(phi))
    k = np.array([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]])
    c = 1.0 / 12.0 + a * a / 720.0 if a < 1e-4 else (
        1.0 / a ** 2 - (1.0 + np.cos(a)) / (2.0 * a * np.sin(a)))
    return np.eye(3) - 0.5 * k + c * (k @ k)


def chart_derivative(dyn: Dynamics, eq: Equilibrium, dx: np.ndarray,
                     forces: ArrayLike) -> np.ndarray:
    """d(dx)/dt of the nonlinear model under piston forces, no end stops (the pose
    lies inside the stroke): eq. (38) through ``derivative_pd``.

    Args:
        dyn: the model.
        eq: the equilibrium x0.
        dx: (12,) the chart's state about ``eq`` [m, rad, m/s, rad/s].
        forces: (6,) piston forces [N], held.

    Returns:
        (12,) d(dx)/dt [m/s, rad/s, m/s^2, rad/s^2].
    """
    y = state13_from_chart(dx, eq)
    dy = derivative_pd(*dyn.kernel_args(), y, np.asarray(forces, float), NO_WRENCH, False,
                       NO_GAINS, 0.0)
    out = np.empty(12)
    out[0:3] = dx[6:9]
    out[3:6] = left_jacobian_inverse(dx[3:6]) @ dx[9:12]
    out[6:12] = dy[7:13]
    return out


def chart_outputs(dyn: Dynamics, eq: Equilibrium,
                  dx: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Leg lengths and rates at x0 + dx (eqs. 5, 13): what the sensors measure.

    Args:
        dyn: the model.
        eq: the equilibrium x0.
        dx: (12,) the chart's state about ``eq`` [m, rad, m/s, rad/s].

    Returns:
        (lengths (6,) [m], rates (6,) [m/s]).
    """
    return lengths_rates(dyn.base_points, dyn.leg_points, state13_from_chart(dx, eq))


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


# -- modes ------------------------------------------------------------------------------------
@dataclasses.dataclass
class Modes:
    """The six modes of a linear model, slowest first.

    Attributes:
        frequencies_hz: (6,) sqrt(|l1 l2|) / 2 pi [Hz].
        damping_ratios: (6,) -(l1 + l2) / (2 sqrt(|l1 l2|)).
        mode_shapes: (6, 6) one row per mode, in pose coordinates (x, y, z [m],
            theta_x, theta_y, theta_z [rad]), largest component +1.
        eigenvalues: (6, 2) complex, each mode's pair [1/s].
        stable: (6,) False where the pair has a positive real part.
        pose: (6,) the equilibrium pose.
    """
    frequencies_hz: np.ndarray
    damping_ratios: np.ndarray
    mode_shapes: np.ndarray
    eigenvalues: np.ndarray
    stable: np.ndarray
    pose: np.ndarray

    def to_json(self) -> dict:
        """The modes as plain JSON types.

        Returns:
            {'frequencies_hz', 'damping_ratios', 'mode_shapes', 'pose': lists as
            the attributes, 'stable': six bools, 'eigenvalues': (6, 2) pairs
            [real, imag] [1/s]}.
        """
        return {
            'frequencies_hz': self.frequencies_hz.tolist(),
            'damping_ratios': self.damping_ratios.tolist(),
            'mode_shapes': self.mode_shapes.tolist(),
            'pose': self.pose.tolist(),
            'stable': [bool(s) for s in self.stable],
            'eigenvalues': [[[float(v.real), float(v.imag)] for v in pair]
                            for pair in self.eigenvalues],
        }


def pair_eigenvalues(values: ArrayLike, vectors: np.ndarray) -> list[tuple[int, int]]:
    """Index pairs of the eigenvalues of a second-order system (12 -> 6 pairs).

    Complex conjugates pair with each other. The real eigenvalues left over
    are matched greedily by the shape of their eigenvectors' position parts
    (the largest |cos| of the angle between them first): the two real roots
    of one overdamped (or divergent) mode move the same coordinates.

    Args:
        values: (2n,) eigenvalues [1/s], complex; vectors: (2n, 2n) eigenvectors
            as columns (``np.linalg.eig``), positions in their first n rows.

    Returns:
        n pairs (i, j) of indices into ``values``: the complex pairs first.

    Raises:
        AnalysisError: an odd number of real eigenvalues.
    """
    values = np.asarray(values)
    n = len(values)
    scale = max(1.0, float(np.max(np.abs(values))))
    is_real = np.abs(values.imag) <= 1e-9 * scale
    pairs, used = [], set()
    for i in np.flatnonzero(~is_real & (values.imag > 0)):
        rest = [j for j in np.flatnonzero(~is_real & (values.imag < 0)) if j not in used]
        j = min(rest, key=lambda k: abs(values[k] - np.conj(values[i])))
        pairs.append((int(i), int(j)))
        used.add(j)
    reals = [int(i) for i in np.flatnonzero(is_real)]
    shapes = np.real(vectors[: n // 2, :])
    shapes = shapes / np.maximum(np.linalg.norm(shapes, axis=0), 1e-300)
    while len(reals) >= 2:
        best = max(((a, b) for k, a in enumerate(reals) for b in reals[k + 1:]),
                   key=lambda ab: abs(shapes[:, ab[0]] @ shapes[:, ab[1]]))
        pairs.append(best)
        reals = [k for k in reals if k not in best]
    if reals:
        raise AnalysisError('an odd number of real eigenvalues: not a second-order system')
    return pairs


def pair_figures(l1: complex, l2: complex) -> tuple[float, float, bool]:
    """Natural frequency, damping ratio and stability of an eigenvalue pair.

    Args:
        l1, l2: the pair [1/s] (complex conjugates, or two real roots).

    Returns:
        (sqrt(|l1 l2|) / 2 pi [Hz], -(l1 + l2) / (2 sqrt(|l1 l2|)) (inf for a
        zero frequency), both real parts negative).
    """
    product = (l1 * l2).real
    omega = np.sqrt(abs(product))
    zeta = -(l1 + l2).real / (2.0 * omega) if omega > 0 else np.inf
    stable = bool(max(l1.real, l2.real) < 0)
    return float(omega / (2.0 * np.pi)), float(zeta), stable


def modes(model: LinearModel) -> Modes:
    """The six modes of ``model`` (see the module docstring), slowest first.

    A mode's shape is the position part of the eigenvector of its eigenvalue
    with the larger real part (the slower, or the growing, root), rotation
    converted to Euler-angle increments (d theta = E(theta0)^-1 d phi), made
    real (the phase of its largest component removed) and scaled to +1 there.

    Args:
        model: the linear model (A (12, 12): a second-order system).

    Returns:
        The ``Modes``, six, slowest first.

    Raises:
        AnalysisError: the eigenvalues do not pair (``pair_eigenvalues``).
    """
    values, vectors = np.linalg.eig(model.A)
    e_inv = np.linalg.inv(euler_rate_matrix(model.equilibrium.theta))
    rows = []
    for i, j in pair_eigenvalues(values, vectors):
        lead = i if values[i].real >= values[j].real else j
        shape = vectors[:6, lead].astype(complex)
        shape[3:6] = e_inv @ shape[3:6]
        big = int(np.argmax(np.abs(shape)))
        shape = np.real(shape * np.exp(-1j * np.angle(shape[big])))
        shape = shape / shape[big]
        freq, zeta, stable = pair_figures(values[i], values[j])
        pair = sorted((values[i], values[j]), key=lambda v: (v.real, v.imag))
        rows.append((freq, zeta, shape, pair, stable))
    rows.sort(key=lambda row: row[0])
    return Modes(np.array([r[0] for r in rows]), np.array([r[1] for r in rows]),
                 np.array([r[2] for r in rows]), np.array([r[3] for r in rows]),
                 np.array([r[4] for r in rows]), model.equilibrium.pose)


# -- frequency responses ----------------------------------------------------------------------
def frequency_response(model: LinearModel, frequencies_hz: ArrayLike) -> np.ndarray:
    """G(j 2 pi f) = C (j 2 pi f I - A)^-1 B + D at each frequency.

    Args:
        model: the linear model.
        frequencies_hz: (F,) [Hz].

    Returns:
        (F, 6, 6) complex, [f, output, input]: output units per input unit
        (m/N open loop, m/m closed loop).
    """
    f = np.asarray(frequencies_hz, dtype=float)
    s = 2j * np.pi * f
    n = model.A.shape[0]
    pencil = s[:, None, None] * np.eye(n)[None] - model.A[None]
    rhs = np.broadcast_to(model.B, (len(f),) + model.B.shape)
    return model.C[None] @ np.linalg.solve(pencil, rhs) + model.D[None]


def frequency_table(frequencies_hz: ArrayLike,
                    response: np.ndarray) -> list[tuple[float, str, str, float, float]]:
    """``frequency_response``'s result as rows, by input, then output, then frequency.

    Args:
        frequencies_hz: (F,) [Hz].
        response: (F, 6, 6) complex, [f, output, input] (``frequency_response``).

    Returns:
        36 F rows (f [Hz], input leg name, output leg name, magnitude (output
        units per input unit), phase [deg]); the phase is unwrapped along
        frequency (continuous).
    """
    f = np.asarray(frequencies_hz, dtype=float)
    rows = []
    for i in range(response.shape[2]):
        for o in range(response.shape[1]):
            g = response[:, o, i]
            phase = np.degrees(np.unwrap(np.angle(g)))
            for k in range(len(f)):
                rows.append((float(f[k]), LEG_NAMES[i], LEG_NAMES[o], float(abs(g[k])),
                             float(phase[k])))
    return rows


def strongest_couplings(response: np.ndarray, count: int = 3) -> list[tuple[int, int]]:
    """The off-diagonal responses with the largest peak magnitude over frequency; of
    responses whose peaks agree to 1e-6 (legs that mirror each other) only the first.

    Args:
        response: (F, 6, 6) complex, [f, output, input] (``frequency_response``).
        count: how many to return (fewer when fewer are distinct).

    Returns:
        Up to ``count`` (output, input) 0-based leg indices, strongest first.
    """
    peak = np.max(np.abs(response), axis=0)
    chosen, seen = [], []
    for flat in np.argsort(peak, axis=None)[::-1]:
        o, i = np.unravel_index(flat, peak.shape)
        if o == i or any(abs(peak[o, i] - p) <= 1e-6 * p for p in seen):
            continue
        chosen.append((int(o), int(i)))
        seen.append(peak[o, i])
        if len(chosen) == count:
            break
    return chosen
