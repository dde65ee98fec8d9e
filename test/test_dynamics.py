"""The Newton-Euler dynamics against independent references.

References built here, from the model as documented (docs/interface.md) and not
from ``stewart63_ros.core.mechanics.dynamics``:

* kinetic and potential energy of platform, cylinders and pistons, written
  from the leg geometry (and, for the kinetic energy, a second time by finite
  differences of the centres of mass along the twist);
* energy conservation / the work-energy balance along free motion;
* Lagrange's equations in q = (t, theta), by numerical differentiation of the
  energies written here;
* the static virtual-work answer J^T F = -wrench for massless legs.

The energy balances and Lagrange's equations run on both geometries: the
paper's 6-3 and the packaged 6-6 (config/hexapod66.yaml, leg i at its own
platform joint p_i).
"""
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

from stewart63_ros.core.mechanics import kinematics as kin
from stewart63_ros.core.mechanics.dynamics import Dynamics

# A 6-3: legs 2k-1 and 2k meet at vertex p_k; a 6-6: leg i at p_i (docs/geometry.md).
VERTEX_OF_LEG = [0, 0, 1, 1, 2, 2]
HEXAPOD66 = Path(__file__).resolve().parents[1] / 'config' / 'hexapod66.yaml'


def platform_joints(mech):
    """(6, 3) the platform point of each leg, platform frame, from the file's rule."""
    points = np.asarray(mech.platform_points)
    return points[VERTEX_OF_LEG] if len(points) == 3 else points


# -- independent model ------------------------------------------------------------------
def rot_euler(theta):
    """R = Rz(theta_z) Ry(theta_y) Rx(theta_x), built from elementary rotations."""
    def axis(k, a):
        c, s = np.cos(a), np.sin(a)
        i, j = [(1, 2), (2, 0), (0, 1)][k]
        r = np.eye(3)
        r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
        return r
    return axis(2, theta[2]) @ axis(1, theta[1]) @ axis(0, theta[0])


def euler_rates_to_omega(theta):
    """E with omega = E dtheta: columns are the axes the three rates turn about,
    omega = dtz z + Rz(tz) dty y + Rz(tz) Ry(ty) dtx x."""
    rz = rot_euler([0, 0, theta[2]])
    rzy = rot_euler([0, theta[1], theta[2]])
    return np.column_stack([rzy[:, 0], rz[:, 1], [0.0, 0.0, 1.0]])


def legs_of(mech, t, rot, v, omega):
    """(S, L, s, Ldot, W) of every leg, eqs. 2-5, 13, 14."""
    q = platform_joints(mech) @ rot.T
    S = t + q - np.asarray(mech.base_points)
    L = np.linalg.norm(S, axis=1)
    s = S / L[:, None]
    S_dot = v + np.cross(omega, q)
    return S, L, s, np.einsum('ij,ij->i', s, S_dot), np.cross(s, S_dot) / L[:, None]


def kinetic_energy(mech, t, rot, v, omega):
    """Platform (COM offset, full inertia tensor) + cylinder rotating about b_i
    + piston sliding and rotating; both leg parts spin-free (angular velocity W)."""
    c = rot @ np.asarray(mech.platform_com)
    v_c = v + np.cross(omega, c)
    i_world = rot @ np.asarray(mech.platform_inertia) @ rot.T
    T = 0.5 * mech.platform_mass * v_c @ v_c + 0.5 * omega @ i_world @ omega
    _, L, s, L_dot, W = legs_of(mech, t, rot, v, omega)
    turn = np.cross(W, s)                                   # ds/dt
    v_lower = mech.leg_lower_com * turn
    v_upper = L_dot[:, None] * s + (L - mech.leg_upper_com)[:, None] * turn
    w2 = np.einsum('ij,ij->i', W, W)
    T += 0.5 * mech.leg_lower_mass * np.sum(v_lower * v_lower)
    T += 0.5 * mech.leg_upper_mass * np.sum(v_upper * v_upper)
    T += 0.5 * (mech.leg_lower_inertia[1] + mech.leg_upper_inertia[1]) * np.sum(w2)
    return T


def mass_points(mech, t, rot):
    """Masses and centres of mass: platform, 6 cylinders, 6 pistons."""
    S, L, s, _, _ = legs_of(mech, t, rot, np.zeros(3), np.zeros(3))
    base = np.asarray(mech.base_points)
    points = np.vstack([t + rot @ np.asarray(mech.platform_com),
                        base + mech.leg_lower_com * s,
                        base + (L - mech.leg_upper_com)[:, None] * s])
    masses = np.array([mech.platform_mass] + [mech.leg_lower_mass] * 6
                      + [mech.leg_upper_mass] * 6)
    return masses, points, s


def potential_energy(mech, t, rot):
    masses, points, _ = mass_points(mech, t, rot)
    return -np.sum(masses * (points @ np.asarray(mech.gravity)))


def kinetic_energy_fd(mech, t, rot, v, omega, h=1e-6):
    """Kinetic energy from central differences of the centres of mass (and of
    the leg directions) as the pose moves along the twist."""
    def at(e):
        return mass_points(mech, t + v * e, Rotation.from_rotvec(omega * e).as_matrix() @ rot)
    masses, _, s = at(0.0)
    _, p_plus, s_plus = at(h)
    _, p_minus, s_minus = at(-h)
    vel = (p_plus - p_minus) / (2 * h)
    W = np.cross(s, (s_plus - s_minus) / (2 * h))           # spin-free leg
    i_world = rot @ np.asarray(mech.platform_inertia) @ rot.T
    return (0.5 * np.sum(masses * np.einsum('ij,ij->i', vel, vel))
            + 0.5 * omega @ i_world @ omega
            + 0.5 * (mech.leg_lower_inertia[1] + mech.leg_upper_inertia[1]) * np.sum(W * W))


def dissipation(mech, t, rot, v, omega):
    _, _, _, L_dot, W = legs_of(mech, t, rot, v, omega)
    return mech.piston_damping * L_dot @ L_dot + mech.ujoint_damping * np.sum(W * W)


def unpack(y):
    return y[0:3], Rotation.from_quat(y[3:7]).as_matrix(), y[7:10], y[10:13]


def make_state(t, rot, v, omega):
    return np.concatenate([t, Rotation.from_matrix(rot).as_quat(), v, omega])


# -- fixtures -----------------------------------------------------------------------------
@pytest.fixture(scope='module')
def rich_mech(default_mech):
    """Everything that can be non-trivial is: COM offset, a non-diagonal
    inertia, leg COMs and inertias that differ, damping on."""
    return default_mech.replace(
        platform_com=[0.04, -0.03, 0.06],
        platform_inertia=[0.95, 1.10, 1.80, -0.06, 0.04, 0.09],
        leg_lower_com=0.42, leg_upper_com=0.28,
        leg_lower_inertia=[0.003, 0.17], leg_upper_inertia=[0.0007, 0.05],
        piston_damping=60.0, ujoint_damping=0.8)


@pytest.fixture(scope='module', params=['6-3', '6-6'])
def any_rich_mech(request, rich_mech):
    """``rich_mech``, and the same changes on the packaged 6-6."""
    if request.param == '6-3':
        return rich_mech
    from stewart63_ros.core.plumbing.params import load_mechanism
    mech = load_mechanism(HEXAPOD66).replace(
        platform_com=[0.04, -0.03, 0.06],
        platform_inertia=[1.35, 1.50, 2.70, -0.06, 0.04, 0.09],
        leg_lower_com=0.42, leg_upper_com=0.28,
        leg_lower_inertia=[0.003, 0.17], leg_upper_inertia=[0.0007, 0.05],
        piston_damping=60.0, ujoint_damping=0.8)
    assert mech.layout == '6-6'
    return mech


@pytest.fixture
def rng():
    return np.random.default_rng(7)


#: the packaged file's initial position [m]: the poses are drawn around it
START = (0.01, 0.01, 1.0)


def random_pose(rng, mech, spread=1.0):
    for _ in range(1000):
        t = np.asarray(START) + spread * rng.uniform([-0.3, -0.3, -0.25],
                                                     [0.3, 0.3, 0.3])
        theta = spread * rng.uniform(-0.4, 0.4, 3)
        rot = rot_euler(theta)
        L = legs_of(mech, t, rot, np.zeros(3), np.zeros(3))[1]
        if np.all((L > mech.leg_length_min) & (L < mech.leg_length_max)):
            return t, theta, rot
    raise AssertionError('no pose inside the stroke found')


def test_independent_kinetic_energies_agree(rich_mech, rng):
    """The two references of this file agree with each other (guards the references)."""
    for _ in range(10):
        t, _, rot = random_pose(rng, rich_mech)
        v, omega = rng.normal(0, 0.5, 3), rng.normal(0, 1, 3)
        T = kinetic_energy(rich_mech, t, rot, v, omega)
        assert T > 0
        np.testing.assert_allclose(kinetic_energy_fd(rich_mech, t, rot, v, omega), T, rtol=1e-8)


# -- energy ----------------------------------------------------------------------------------
def test_energy_function_matches_independent_energies(rich_mech, rng):
    dyn = Dynamics(rich_mech)
    for _ in range(10):
        t, _, rot = random_pose(rng, rich_mech)
        v, omega = rng.normal(0, 0.5, 3), rng.normal(0, 1, 3)
        y = make_state(t, rot, v, omega)
        kinetic, potential = dyn.energy(y)
        np.testing.assert_allclose(kinetic, kinetic_energy(rich_mech, t, rot, v, omega),
                                   rtol=1e-10)
        np.testing.assert_allclose(potential, potential_energy(rich_mech, t, rot), rtol=1e-10,
                                   atol=1e-9)
        np.testing.assert_allclose(dyn.dissipation(y), dissipation(rich_mech, t, rot, v, omega),
                                   rtol=1e-10)


def _free_motion(dyn, y0, duration, forces=None, wrench=None, samples=25):
    """Integrate with the work of forces, wrench and friction as extra states."""
    mech = dyn.mech
    forces = np.zeros(6) if forces is None else forces

    def rhs(_, z):
        y = z[:13]
        t, rot, v, omega = unpack(y)
        _, _, _, L_dot, _ = legs_of(mech, t, rot, v, omega)
        power_in = forces @ L_dot
        if wrench is not None:
            power_in += (rot @ wrench[0]) @ v + (rot @ wrench[1]) @ omega
        return np.concatenate([dyn.derivative(y, forces, wrench, with_endstops=False),
                               [power_in, dissipation(mech, t, rot, v, omega)]])
    times = np.linspace(0, duration, samples)
    sol = solve_ivp(rhs, (0, duration), np.concatenate([y0, [0.0, 0.0]]), method='DOP853',
                    rtol=1e-10, atol=1e-10, t_eval=times)
    assert sol.success, sol.message
    return sol.y.T


def _check_energies_along(dyn, states):
    """Every sampled state: Dynamics.energy equals the independent energies."""
    mech = dyn.mech
    total = []
    for z in states:
        t, rot, v, omega = unpack(z[:13])
        kinetic, potential = dyn.energy(z[:13])
        T_ref = kinetic_energy_fd(mech, t, rot, v, omega)
        np.testing.assert_allclose(kinetic, T_ref, rtol=1e-7)
        np.testing.assert_allclose(potential, potential_energy(mech, t, rot), rtol=1e-10,
                                   atol=1e-9)
        L = legs_of(mech, t, rot, v, omega)[1]
        assert np.all(L > 0.3), 'the motion left the sensible workspace'
        total.append(kinetic + potential)
    return np.array(total)


def test_energy_conserved_without_gravity(any_rich_mech, rng):
    mech = any_rich_mech.replace(gravity=[0.0, 0.0, 0.0], piston_damping=0.0, ujoint_damping=0.0)
    dyn = Dynamics(mech)
    t, _, rot = random_pose(rng, mech, spread=0.3)
    y0 = make_state(t, rot, rng.normal(0, 0.06, 3), rng.normal(0, 0.25, 3))
    states = _free_motion(dyn, y0, 3.0)
    energy = _check_energies_along(dyn, states)
    assert energy[0] > 0.05
    np.testing.assert_allclose(energy, energy[0], rtol=1e-8)
    # the legs really moved (and therefore exchanged energy with the platform)
    L0 = legs_of(mech, *unpack(states[0, :13]))[1]
    L1 = legs_of(mech, *unpack(states[-1, :13]))[1]
    assert np.max(np.abs(L1 - L0)) > 0.02


def test_energy_conserved_while_falling(any_rich_mech, rng):
    mech = any_rich_mech.replace(piston_damping=0.0, ujoint_damping=0.0)
    dyn = Dynamics(mech)
    t, _, rot = random_pose(rng, mech, spread=0.3)
    y0 = make_state(t, rot, rng.normal(0, 0.05, 3), rng.normal(0, 0.2, 3))
    states = _free_motion(dyn, y0, 0.4)
    energy = _check_energies_along(dyn, states)
    kinetic_end = dyn.energy(states[-1, :13])[0]
    assert kinetic_end > 10.0, 'the platform should have fallen'
    assert states[-1, 2] < states[0, 2] - 0.2
    np.testing.assert_allclose(energy - energy[0], 0.0, atol=1e-8 * kinetic_end)


def test_energy_lost_equals_integrated_dissipation(any_rich_mech, rng):
    dyn = Dynamics(any_rich_mech)
    t, _, rot = random_pose(rng, any_rich_mech, spread=0.3)
    y0 = make_state(t, rot, rng.normal(0, 0.1, 3), rng.normal(0, 0.4, 3))
    states = _free_motion(dyn, y0, 0.5)
    energy = _check_energies_along(dyn, states)
    lost = energy[0] - energy
    dissipated = states[:, 14]
    assert dissipated[-1] > 1.0, 'damping should matter in this run'
    np.testing.assert_allclose(lost, dissipated, rtol=0, atol=1e-6 * dissipated[-1])


def test_work_energy_balance_with_forces_and_wrench(any_rich_mech, rng):
    """dE/dt = F . dL/dt + (R F_ext) . v + (R M_ext) . omega - dissipation."""
    dyn = Dynamics(any_rich_mech)
    t, _, rot = random_pose(rng, any_rich_mech, spread=0.3)
    y0 = make_state(t, rot, rng.normal(0, 0.1, 3), rng.normal(0, 0.4, 3))
    forces = 50.0 + rng.uniform(-60, 60, 6)
    wrench = (rng.normal(0, 20, 3), rng.normal(0, 5, 3))
    states = _free_motion(dyn, y0, 0.5, forces=forces, wrench=wrench)
    energy = _check_energies_along(dyn, states)
    balance = states[:, 13] - states[:, 14]
    scale = np.max(np.abs(states[:, 13])) + states[-1, 14]
    assert np.max(np.abs(states[:, 13])) > 1.0
    np.testing.assert_allclose(energy - energy[0], balance, rtol=0, atol=1e-6 * scale)


# -- eq. (38): J ----------------------------------------------------------------------------------
def test_inertia_matrix_symmetric_positive_definite(rich_mech, rng):
    """J is SPD and is the kinetic-energy Hessian in twist coordinates."""
    dyn = Dynamics(rich_mech)
    for _ in range(30):
        t, _, rot = random_pose(rng, rich_mech)
        v, omega = rng.normal(0, 0.5, 3), rng.normal(0, 1, 3)
        J, eta, H = dyn.equation_terms(rot, t, v, omega)
        assert J.shape == (6, 6) and eta.shape == (6,) and H.shape == (6, 6)
        np.testing.assert_allclose(J, J.T, rtol=0, atol=1e-12 * np.abs(J).max())
        assert np.linalg.eigvalsh(J)[0] > 0
        np.testing.assert_allclose(H, kin.jacobian(rich_mech, rot, t).T, atol=1e-13)

        # T(x) = 1/2 x^T J x: polarisation of the independent kinetic energy
        def T(x):
            return kinetic_energy(rich_mech, t, rot, x[:3], x[3:])
        ref = np.empty((6, 6))
        for i in range(6):
            for j in range(6):
                ei, ej = np.eye(6)[i], np.eye(6)[j]
                ref[i, j] = T(ei + ej) - T(ei) - T(ej) if i != j else 2 * T(ei)
        np.testing.assert_allclose(J, ref, rtol=0, atol=1e-10 * np.abs(ref).max())


# -- a second formulation: Lagrange's equations in q = (t, theta) ------------------------------
def lagrange_accelerations(mech, q, qd, forces, wrench, h=1e-5):
    """qdd from d/dt dT/dqd - dT/dq + dV/dq = Q, by numerical differentiation."""
    def twist(qq, qqd):
        return qqd[:3], euler_rates_to_omega(qq[3:]) @ qqd[3:]

    def T(qq, qqd):
        return kinetic_energy(mech, qq[:3], rot_euler(qq[3:]), *twist(qq, qqd))

    def V(qq):
        return potential_energy(mech, qq[:3], rot_euler(qq[3:]))

    def lengths(qq):
        return legs_of(mech, qq[:3], rot_euler(qq[3:]), np.zeros(3), np.zeros(3))[1]

    def mass_matrix(qq):  # T is a quadratic form in qd: polarisation is exact
        m = np.empty((6, 6))
        for i in range(6):
            for j in range(6):
                ei, ej = np.eye(6)[i], np.eye(6)[j]
                m[i, j] = (T(qq, ei + ej) - T(qq, ei) - T(qq, ej)) if i != j else 2 * T(qq, ei)
        return m
    eye = np.eye(6)
    M = mass_matrix(q)
    # d/dt (dT/dqd) = M qdd + (dM/dt) qd, dM/dt along qd
    mdot_qd = (mass_matrix(q + h * qd) - mass_matrix(q - h * qd)) @ qd / (2 * h)
    dT_dq = np.array([(T(q + h * e, qd) - T(q - h * e, qd)) / (2 * h) for e in eye])
    dV_dq = np.array([(V(q + h * e) - V(q - h * e)) / (2 * h) for e in eye])
    dL_dq = np.column_stack([(lengths(q + h * e) - lengths(q - h * e)) / (2 * h) for e in eye])

    rot = rot_euler(q[3:])
    _, _, _, L_dot, W = legs_of(mech, q[:3], rot, *twist(q, qd))
    Q = dL_dq.T @ forces                                          # pistons
    for j in range(6):                                            # friction; rates are linear in qd
        _, _, _, L_dot_j, W_j = legs_of(mech, q[:3], rot, *twist(q, eye[j]))
        Q[j] -= mech.piston_damping * L_dot @ L_dot_j + mech.ujoint_damping * np.sum(W * W_j)
    E = euler_rates_to_omega(q[3:])                               # external wrench, power
    Q[:3] += rot @ wrench[0]                                      # F.v + M.omega
    Q[3:] += E.T @ (rot @ wrench[1])
    return np.linalg.solve(M, Q - dV_dq + dT_dq - mdot_qd)


def test_newton_euler_matches_lagrange(any_rich_mech, rng):
    dyn = Dynamics(any_rich_mech)
    h = 1e-6
    for _ in range(8):
        t, theta, rot = random_pose(rng, any_rich_mech)
        t_dot, theta_dot = rng.normal(0, 0.5, 3), rng.normal(0, 1.0, 3)
        forces = rng.uniform(-300, 600, 6)
        wrench = (rng.normal(0, 30, 3), rng.normal(0, 10, 3))
        q, qd = np.concatenate([t, theta]), np.concatenate([t_dot, theta_dot])
        qdd_ref = lagrange_accelerations(any_rich_mech, q, qd, forces, wrench)

        E = euler_rates_to_omega(theta)
        omega = E @ theta_dot
        accel, alpha = dyn.accelerations(rot, t, t_dot, omega, forces, wrench)
        # alpha = E thetadd + (dE/dt) thetad
        e_dot = (euler_rates_to_omega(theta + h * theta_dot)
                 - euler_rates_to_omega(theta - h * theta_dot)) / (2 * h)
        theta_dd = np.linalg.solve(E, alpha - e_dot @ theta_dot)
        qdd = np.concatenate([accel, theta_dd])
        np.testing.assert_allclose(qdd, qdd_ref, rtol=0, atol=1e-6 * np.abs(qdd_ref).max())

        # the state-vector derivative carries the same accelerations
        y = make_state(t, rot, t_dot, omega)
        dy = dyn.derivative(y, forces, wrench, with_endstops=False)
        np.testing.assert_allclose(dy[:3], t_dot, atol=1e-14)
        np.testing.assert_allclose(dy[7:10], accel, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(dy[10:13], alpha, rtol=1e-12, atol=1e-12)


# -- statics and inverse dynamics ------------------------------------------------------------------
def test_massless_legs_statics_is_jacobian_transpose(rich_mech, rng):
    tiny = 1e-9
    mech = rich_mech.replace(
        leg_lower_mass=tiny * rich_mech.leg_lower_mass,
        leg_upper_mass=tiny * rich_mech.leg_upper_mass,
        leg_lower_inertia=tiny * np.asarray(rich_mech.leg_lower_inertia),
        leg_upper_inertia=tiny * np.asarray(rich_mech.leg_upper_inertia))
    dyn = Dynamics(mech)
    zero = np.zeros(3)
    for _ in range(10):
        t, _, rot = random_pose(rng, mech)
        wrench = (rng.normal(0, 30, 3), rng.normal(0, 10, 3))
        F = dyn.inverse_dynamics(rot, t, zero, zero, zero, zero, wrench)
        weight = mech.platform_mass * np.asarray(mech.gravity)
        c = rot @ np.asarray(mech.platform_com)
        applied = np.concatenate([weight + rot @ wrench[0], np.cross(c, weight) + rot @ wrench[1]])
        # the legs' wrench on the platform, sum F_i [s_i; q_i x s_i], balances it
        F_ref = np.linalg.solve(kin.jacobian(mech, rot, t).T, -applied)
        np.testing.assert_allclose(F, F_ref, rtol=0, atol=1e-6 * np.abs(F_ref).max())
        # and holds the platform still
        a, alpha = dyn.accelerations(rot, t, zero, zero, F_ref, wrench)
        assert np.abs(np.concatenate([a, alpha])).max() < 1e-6


def test_inverse_dynamics_round_trip(rich_mech, rng):
    dyn = Dynamics(rich_mech)
    for _ in range(20):
        t, _, rot = random_pose(rng, rich_mech)
        v, omega = rng.normal(0, 0.5, 3), rng.normal(0, 1, 3)
        wrench = (rng.normal(0, 30, 3), rng.normal(0, 10, 3))
        forces = rng.uniform(-500, 800, 6)
        a, alpha = dyn.accelerations(rot, t, v, omega, forces, wrench)
        back = dyn.inverse_dynamics(rot, t, v, omega, a, alpha, wrench)
        np.testing.assert_allclose(back, forces, rtol=0, atol=1e-8 * np.abs(forces).max())
        a_want, alpha_want = rng.normal(0, 2, 3), rng.normal(0, 4, 3)
        F = dyn.inverse_dynamics(rot, t, v, omega, a_want, alpha_want)
        a2, alpha2 = dyn.accelerations(rot, t, v, omega, F)
        np.testing.assert_allclose(np.concatenate([a2, alpha2]),
                                   np.concatenate([a_want, alpha_want]), atol=1e-9)
