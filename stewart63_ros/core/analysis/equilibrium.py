"""The equilibrium a linear model is taken about, and the state chart around it.

Equilibrium: the platform at rest at a pose (t0, R0), held against gravity
by the piston forces u0 that solve eq. (38) with zero velocity and
acceleration, H u0 = eta(q, 0) (platform and both parts of every leg; the
``inverse_dynamics_forces`` kernel). The default pose is the forward
kinematics of the parameter file's ``setpoint_lengths`` (the assembly mode
nearest the initial pose).

State (12): x = (t, phi, v, omega): platform position [m], a small rotation
vector phi [rad] with R = exp([phi]x) R0 (base frame, left perturbation),
velocity [m/s] and angular velocity [rad/s], both in the base frame.

The linear model in this chart is ``linear``'s; its modes and frequency
responses ``modal``'s.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from numpy.typing import ArrayLike

from stewart63_ros.core.mechanics.dynamics import (
    NO_GAINS,
    NO_WRENCH,
    STATE_SIZE,
    Dynamics,
    derivative_pd,
    inverse_dynamics_forces,
    lengths_rates,
)
from stewart63_ros.core.mechanics.fk import ForwardKinematics
from stewart63_ros.core.mechanics.mechanism import Mechanism
from stewart63_ros.core.mechanics.rotation import (
    euler_from_matrix,
    quaternion_from_rotation,
    quaternion_of_rotvec_times,
    rotation_from_euler,
    rotvec_between,
    rotvec_from_rotation,
)
from stewart63_ros.core.mechanics.setup import Setup

#: A pose whose Jacobian (rows [s_i, q_i x s_i], metres) has a 2-norm
#: condition number above this is refused as near-singular (``--max-condition``).
#: Over the default workspace it stays between 3 and 6; fk flags 1e4, where
#: its pose estimate is no longer trusted. At 100 a leg-length error moves the
#: pose by up to 100 times as much: no model for a controller to design on.
DEFAULT_MAX_CONDITION = 100.0


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
