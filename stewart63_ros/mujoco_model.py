"""The same mechanism, a 6-3 or a 6-6, as a MuJoCo model, built from the same parameter file.

A second, independent engine for ``make bench``: it solves the
closed chains with constraints instead of our reduced Newton-Euler model, so
agreement between the two checks both, and its speed is what a team reaching
for MuJoCo would get. MuJoCo is an optional extra (``pip install
stewart63_ros[bench]``), never a run-time dependency: nothing else imports
this module.

The model (docs/interface.md, "Frames and conventions"), mapped onto MuJoCo elements:

- platform: a free body; frame = the platform frame, inertial at
  ``platform_com`` with ``fullinertia`` = ``platform_inertia`` (same element
  order as the parameter file);
- leg i: a cylinder body at b_i on a universal joint (two hinges, the first
  fixed in the base and perpendicular to the initial leg, the second
  perpendicular to both), and a piston body on a slide along the leg; the
  slide's coordinate *is* L_i (``ref`` = initial length);
- the piston tips are tied to the platform joints by ``connect`` equality
  constraints (``Mechanism.leg_platform_points``: legs 2k-1, 2k at p_k of a
  6-3, leg i at p_i of a 6-6), with tight solver settings;
- C_p: damping of the slide joint (exactly -C_p dL/dt);
- C_u: the moment -C_u W_i with W_i the leg's angular velocity *across* the
  leg (eq. 14). Plain damping on the two hinges would also damp the spin a
  U-joint leg picks up (measured), so the moment is two velocity-feedback
  actuators with a site transmission on the cylinder, about its two
  transverse axes;
- eq. (40): one affine actuator per slide, force = Kp (ctrl - L) - Kv dL/dt,
  ctrl = (L_i)_0, clamped to +-max_force. Evaluated inside every integrator
  stage, i.e. continuous control as in the paper's ode45;
- the model is spin-free by assumption, so the legs' axial inertias do not
  enter it; MuJoCo needs a positive one, so they are set to ``AXIAL_INERTIA``
  (negligible next to the transverse ones).

End stops are not modelled here (the paper's scenario stays inside the
stroke).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from stewart63_ros.core.mechanics.rotation import (
    euler_rate_matrix,
    quaternion_from_rotation,
    rotation_from_euler,
    rotation_from_quaternion,
)
from stewart63_ros.core.mechanics.setup import Setup, Task

#: Axial moment of inertia of each leg part in the MuJoCo model [kg m^2].
AXIAL_INERTIA = 1e-9


def _fmt(values) -> str:
    return ' '.join('%.17g' % v for v in np.ravel(values))


def _quat_wxyz(rot) -> np.ndarray:
    x, y, z, w = quaternion_from_rotation(rot)
    return np.array([w, x, y, z])


def _leg_frame(s: np.ndarray) -> np.ndarray:
    """Columns: x along the leg, y = first U-joint axis (horizontal, across the leg), z."""
    y = np.cross([0.0, 0.0, 1.0], s)
    if np.linalg.norm(y) < 1e-6:           # a vertical leg: any horizontal axis will do
        y = np.array([0.0, 1.0, 0.0])
    y /= np.linalg.norm(y)
    return np.column_stack([s, y, np.cross(s, y)])


@dataclasses.dataclass
class Settings:
    """Integrator and constraint settings of the MuJoCo model."""
    timestep: float = 1e-3
    integrator: str = 'RK4'
    # Equality constraints as hard as MuJoCo allows: impedance d -> 1, and
    # the shortest reference time constant it accepts (two steps, critically
    # damped) to pull back the drift.
    solimp: tuple = (0.9999, 0.9999, 0.001, 0.5, 2)
    iterations: int = 100
    tolerance: float = 1e-14


def initial_pose(task: Task):
    """t_0, R_0, v_0 and omega_0 (base frame) of the paper's scenario (``Setup.task``)."""
    rot = rotation_from_euler(task.initial_orientation)
    omega = euler_rate_matrix(task.initial_orientation) @ task.initial_orientation_rate
    return (np.asarray(task.initial_position, float), rot,
            np.asarray(task.initial_velocity, float), omega)


def build_xml(setup: Setup, settings: Settings | None = None) -> str:
    """MJCF of the mechanism at its initial pose, eq. (40) with the setup's
    gains (see the module docstring)."""
    st = settings or Settings()
    mech, gains = setup.mechanism, setup.gains
    t0, rot0, _, _ = initial_pose(setup.task)
    joints = np.asarray(mech.leg_platform_points, float)
    base = np.asarray(mech.base_points, float)
    inertia = np.asarray(mech.platform_inertia, float)
    full = [inertia[0, 0], inertia[1, 1], inertia[2, 2],
            inertia[0, 1], inertia[0, 2], inertia[1, 2]]
    it_d, it_u = mech.leg_lower_inertia[1], mech.leg_upper_inertia[1]
    legs, equalities, actuators = [], [], []
    for i in range(6):
        S = t0 + rot0 @ joints[i] - base[i]
        length = np.linalg.norm(S)
        frame = _leg_frame(S / length)
        n = i + 1
        legs.append(f'''
    <body name="cylinder_{n}" pos="{_fmt(base[i])}" quat="{_fmt(_quat_wxyz(frame))}">
      <joint name="ujoint_a_{n}" type="hinge" axis="0 1 0"/>
      <joint name="ujoint_b_{n}" type="hinge" axis="0 0 1"/>
      <inertial pos="{mech.leg_lower_com:.17g} 0 0" mass="{mech.leg_lower_mass:.17g}"
                diaginertia="{AXIAL_INERTIA:.17g} {it_d:.17g} {it_d:.17g}"/>
      <site name="ujoint_{n}"/>
      <body name="piston_{n}" pos="{length:.17g} 0 0">
        <joint name="slide_{n}" type="slide" axis="1 0 0" ref="{length:.17g}"
               damping="{mech.piston_damping:.17g}"/>
        <inertial pos="{-mech.leg_upper_com:.17g} 0 0" mass="{mech.leg_upper_mass:.17g}"
                  diaginertia="{AXIAL_INERTIA:.17g} {it_u:.17g} {it_u:.17g}"/>
      </body>
    </body>''')
        equalities.append(f'<connect body1="piston_{n}" body2="platform" anchor="0 0 0"/>')
        actuators.append(
            f'<general name="pd_{n}" joint="slide_{n}" gainprm="{gains.kp[i]:.17g}" '
            f'biastype="affine" '
            f'biasprm="0 {-gains.kp[i]:.17g} {-gains.kv[i]:.17g}" forcelimited="true" '
            f'forcerange="{-mech.max_force:.17g} {mech.max_force:.17g}"/>')
        for axis, gear in (('a', '0 0 0 0 1 0'), ('b', '0 0 0 0 0 1')):
            actuators.append(
                f'<general name="cu_{axis}_{n}" site="ujoint_{n}" gear="{gear}" gainprm="0" '
                f'biastype="affine" biasprm="0 0 {-mech.ujoint_damping:.17g}"/>')
    nl = '\n    '
    return f'''<mujoco model="stewart63">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{st.timestep:.17g}" integrator="{st.integrator}" gravity="{_fmt(mech.gravity)}"
          solver="Newton" iterations="{st.iterations}" tolerance="{st.tolerance:.17g}"
          ls_tolerance="1e-10" jacobian="dense">
    <flag contact="disable"/>
  </option>
  <default>
    <equality solref="{2 * st.timestep:.17g} 1" solimp="{_fmt(st.solimp)}"/>
    <joint armature="0" frictionloss="0"/>
  </default>
  <worldbody>
    <body name="platform" pos="{_fmt(t0)}" quat="{_fmt(_quat_wxyz(rot0))}">
      <freejoint name="platform"/>
      <inertial pos="{_fmt(mech.platform_com)}" mass="{mech.platform_mass:.17g}"
                fullinertia="{_fmt(full)}"/>
    </body>{''.join(legs)}
  </worldbody>
  <equality>
    {nl.join(equalities)}
  </equality>
  <actuator>
    {nl.join(actuators)}
  </actuator>
</mujoco>
'''


class MujocoPlatform:
    """The MuJoCo model with the scenario's initial state and eq. (40) set up."""

    def __init__(self, setup: Setup, settings: Settings | None = None):
        import mujoco  # lazy: optional (the bench extra): mujoco costs 240 ms
        self.mujoco = mujoco
        self.setup = setup
        self.mech = setup.mechanism
        self.settings = settings or Settings()
        self.model = mujoco.MjModel.from_xml_string(build_xml(setup, self.settings))
        self.data = mujoco.MjData(self.model)
        m = self.model
        self._slide_qpos = np.array([m.jnt_qposadr[m.joint(f'slide_{i}').id] for i in range(1, 7)])
        self._slide_dof = np.array([m.jnt_dofadr[m.joint(f'slide_{i}').id] for i in range(1, 7)])
        self._pd = np.array([m.actuator(f'pd_{i}').id for i in range(1, 7)])
        self.reset()

    def reset(self):
        """The paper's initial state: platform pose and twist, legs moving with it."""
        m, d, mj = self.model, self.data, self.mujoco
        mj.mj_resetData(m, d)
        t0, rot0, v0, omega0 = initial_pose(self.setup.task)
        # Free joint: linear velocity in the world frame, angular in the body frame.
        d.qvel[0:3] = v0
        d.qvel[3:6] = rot0.T @ omega0
        # Each leg follows its vertex: dL/dt along the slide, the transverse
        # angular velocity W = s x dS/dt / L (eq. 14) on the two hinges, which
        # at the reference pose are the leg frame's y and z axes.
        base = np.asarray(self.mech.base_points, float)
        for i in range(6):
            q = rot0 @ self.mech.leg_platform_points[i]
            S = t0 + q - base[i]
            length = np.linalg.norm(S)
            s = S / length
            Sdot = v0 + np.cross(omega0, q)
            frame = _leg_frame(s)
            W = np.cross(s, Sdot) / length
            dof = m.jnt_dofadr[m.joint(f'ujoint_a_{i + 1}').id]
            d.qvel[dof] = W @ frame[:, 1]
            d.qvel[dof + 1] = W @ frame[:, 2]
            d.qvel[self._slide_dof[i]] = s @ Sdot
        d.ctrl[self._pd] = self.setup.task.setpoint_lengths
        mj.mj_forward(m, d)

    def run(self, duration: float, output_rate: float = 100.0):
        """Integrate from the initial state; sample at ``output_rate``.

        Returns times (N,), leg lengths L_i from the platform pose (eq. 5;
        not the slides, which differ by the constraint violation) (N, 6),
        positions (N, 3), quaternions (x, y, z, w) (N, 4), and the largest
        distance between a piston tip and its vertex at the samples [m].
        The loop only copies arrays, so its wall time is MuJoCo's.
        """
        self.reset()
        m, d = self.model, self.data
        step, kinematics = self.mujoco.mj_step, self.mujoco.mj_kinematics
        per_sample = int(round(1.0 / (output_rate * m.opt.timestep)))
        if abs(per_sample * m.opt.timestep * output_rate - 1.0) > 1e-9:
            raise ValueError('timestep %g does not divide the output period' % m.opt.timestep)
        n = int(round(duration * output_rate))
        pistons = [m.body(f'piston_{i}').id for i in range(1, 7)]
        poses = np.empty((n + 1, 7))
        tips = np.empty((n + 1, 6, 3))
        for k in range(n + 1):
            if k:
                step(m, d, per_sample)
                kinematics(m, d)        # mj_step leaves xpos at the state before the step
            poses[k] = d.qpos[0:7]
            tips[k] = d.xpos[pistons]
        positions = poses[:, 0:3]
        quats = poses[:, [4, 5, 6, 3]]                       # (w, x, y, z) -> (x, y, z, w)
        rots = rotation_from_quaternion(quats)
        vertices = positions[:, None, :] + np.einsum('nab,lb->nla', rots,
                                                     self.mech.leg_platform_points)
        lengths = np.linalg.norm(vertices - np.asarray(self.mech.base_points), axis=2)
        violation = float(np.linalg.norm(tips - vertices, axis=2).max())
        return np.arange(n + 1) / output_rate, lengths, positions, quats, violation
