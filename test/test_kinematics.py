"""Kinematics against independent references.

Every quantity of ``stewart63_ros.core.mechanics.kinematics`` (and the orientation
conventions of ``rotation``) is checked against something computed here from
first principles: leg vectors from the documented formula, rates and the
Jacobian from central finite differences of the pose moved along a twist,
accelerations from second differences along a trajectory of constant
(accel, alpha). Nothing is compared with saved output of the code.
"""
import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

from stewart63_ros.core.mechanics import kinematics as kin
from stewart63_ros.core.mechanics import rotation as rotmod

# Legs 2k-1 and 2k meet at vertex p_k (docs/interface.md).
VERTEX_OF_LEG = [0, 0, 1, 1, 2, 2]


# -- independent references -----------------------------------------------------
def rot_x(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def rot_euler(theta):
    """R = Rz(theta_z) Ry(theta_y) Rx(theta_x) (docs/interface.md)."""
    return rot_z(theta[2]) @ rot_y(theta[1]) @ rot_x(theta[0])


def leg_vectors(mech, t, rot):
    """S_i = t + R p_k - b_i, from the raw parameter arrays."""
    p = np.asarray(mech.platform_points)[VERTEX_OF_LEG]
    return np.asarray(t) + p @ rot.T - np.asarray(mech.base_points)


def moved(t, rot, v, omega, h):
    """The pose after time h along the constant twist (v, omega), base frame."""
    return t + v * h, Rotation.from_rotvec(omega * h).as_matrix() @ rot


def central(f, h):
    return (f(h) - f(-h)) / (2 * h)


#: the packaged file's initial position [m]: the poses are drawn around it
START = (0.01, 0.01, 1.0)


def random_pose(rng, mech):
    """A pose inside the stroke, around the initial pose."""
    for _ in range(1000):
        t = np.asarray(START) + rng.uniform(-0.15, 0.15, 3)
        theta = rng.uniform(-0.3, 0.3, 3)
        rot = rot_euler(theta)
        lengths = np.linalg.norm(leg_vectors(mech, t, rot), axis=1)
        if np.all((lengths > mech.leg_length_min) & (lengths < mech.leg_length_max)):
            return t, theta, rot
    raise AssertionError('no pose inside the stroke found')


def random_twist(rng):
    return rng.normal(0, 0.3, 3), rng.normal(0, 0.6, 3)


@pytest.fixture
def rng():
    return np.random.default_rng(20240602)


# -- rotation conventions --------------------------------------------------------
def test_rotation_convention_and_quaternions(rng):
    for _ in range(20):
        theta = rng.uniform(-1.2, 1.2, 3)
        ref = rot_euler(theta)
        np.testing.assert_allclose(rotmod.rotation_from_euler(theta), ref, atol=1e-14)
        quat = rotmod.quaternion_from_euler(theta)
        assert quat.shape == (4,)
        # scalar last: (x, y, z, w); the axis part is sin(angle/2) * axis
        rv = Rotation.from_matrix(ref).as_rotvec()
        angle = np.linalg.norm(rv)
        np.testing.assert_allclose(abs(quat[3]), np.cos(angle / 2), atol=1e-12)
        np.testing.assert_allclose(np.sign(quat[3]) * quat[:3], np.sin(angle / 2) * rv / angle,
                                   atol=1e-12)
        np.testing.assert_allclose(rotmod.matrix_from_quaternion(quat), ref, atol=1e-14)
        np.testing.assert_allclose(rotmod.euler_from_quaternion(quat), theta, atol=1e-12)
        np.testing.assert_allclose(rotmod.euler_from_matrix(ref), theta, atol=1e-12)


def test_euler_rate_matrix_against_finite_differences(rng):
    """omega = E(theta) dtheta/dt, with [omega]x = dR/dt R^T (base frame)."""
    h = 1e-6
    for _ in range(20):
        theta = rng.uniform(-1.2, 1.2, 3)
        dtheta = rng.normal(0, 1, 3)
        rdot = central(lambda e: rot_euler(theta + e * dtheta), h)
        w_hat = rdot @ rot_euler(theta).T
        np.testing.assert_allclose(w_hat, -w_hat.T, atol=1e-9)
        omega = np.array([w_hat[2, 1], w_hat[0, 2], w_hat[1, 0]])
        np.testing.assert_allclose(rotmod.euler_rate_matrix(theta) @ dtheta, omega, atol=1e-8)


def test_quaternion_rate_against_finite_differences(rng):
    h = 1e-6
    for _ in range(20):
        rot = Rotation.from_rotvec(rng.normal(0, 1, 3))
        omega = rng.normal(0, 1, 3)
        quat = rot.as_quat()

        def q_at(e):
            q = (Rotation.from_rotvec(omega * e) * rot).as_quat()
            return q if q @ quat > 0 else -q
        np.testing.assert_allclose(rotmod.quaternion_rate(quat, omega), central(q_at, h),
                                   atol=1e-9)


# -- inverse kinematics ------------------------------------------------------------
def test_inverse_kinematics_matches_contract_formula(default_mech, rng):
    mech = default_mech
    for _ in range(20):
        t, _, rot = random_pose(rng, mech)
        S = leg_vectors(mech, t, rot)
        L = np.linalg.norm(S, axis=1)
        np.testing.assert_allclose(kin.leg_lengths(mech, t, rot), L, rtol=1e-13)
        np.testing.assert_allclose(kin.leg_vectors(mech, t, rot), S, atol=1e-13)
        legs = kin.LegState(mech, t, rot)
        np.testing.assert_allclose(legs.S, S, atol=1e-13)
        np.testing.assert_allclose(legs.L, L, rtol=1e-13)
        np.testing.assert_allclose(legs.s, S / L[:, None], atol=1e-13)
        p = np.asarray(mech.platform_points)[VERTEX_OF_LEG]
        np.testing.assert_allclose(legs.q, p @ rot.T, atol=1e-13)


def test_initial_pose_of_default_file_is_inside_stroke(setup, default_mech):
    mech = default_mech
    L = np.linalg.norm(leg_vectors(mech, setup.task.initial_position,
                                   rot_euler(setup.task.initial_orientation)), axis=1)
    assert np.all(L > mech.leg_length_min) and np.all(L < mech.leg_length_max)


# -- rates and Jacobian --------------------------------------------------------------
def test_leg_rates_against_finite_differences(default_mech, rng):
    """Sdot, Ldot and W = s x dS/dt / L against central differences of the pose."""
    mech, h = default_mech, 1e-5
    for _ in range(20):
        t, _, rot = random_pose(rng, mech)
        v, omega = random_twist(rng)
        legs = kin.LegState(mech, t, rot, v, omega)

        def S_at(e):
            return leg_vectors(mech, *moved(t, rot, v, omega, e))

        def unit_at(e):
            S = S_at(e)
            return S / np.linalg.norm(S, axis=1)[:, None]
        S_dot = central(S_at, h)
        L_dot = central(lambda e: np.linalg.norm(S_at(e), axis=1), h)
        s = unit_at(0.0)
        s_dot = central(unit_at, h)

        np.testing.assert_allclose(legs.Sdot, S_dot, atol=1e-8)
        np.testing.assert_allclose(legs.Ldot, L_dot, atol=1e-8)
        np.testing.assert_allclose(kin.leg_rates(mech, t, rot, v, omega), L_dot, atol=1e-8)
        # A spin-free leg: its angular velocity is perpendicular to it and turns s.
        np.testing.assert_allclose(np.einsum('ij,ij->i', legs.W, s), 0, atol=1e-12)
        np.testing.assert_allclose(np.cross(legs.W, s), s_dot, atol=1e-8)
        np.testing.assert_allclose(legs.W, np.cross(s, s_dot), atol=1e-8)


def test_jacobian_against_finite_differences(default_mech, rng):
    """Column j of the Jacobian = dL/dh for the unit twist e_j; J twist = Ldot."""
    mech, h = default_mech, 1e-5
    for _ in range(10):
        t, _, rot = random_pose(rng, mech)
        fd = np.empty((6, 6))
        for j in range(6):
            twist = np.eye(6)[j]
            fd[:, j] = central(lambda e: np.linalg.norm(
                leg_vectors(mech, *moved(t, rot, twist[:3], twist[3:], e)), axis=1), h)
        jac = kin.jacobian(mech, rot, t)
        assert jac.shape == (6, 6)
        np.testing.assert_allclose(jac, fd, atol=1e-8)
        np.testing.assert_allclose(kin.jacobian(mech, rot, legs=kin.LegState(mech, t, rot)),
                                   fd, atol=1e-8)
        v, omega = random_twist(rng)
        np.testing.assert_allclose(jac @ np.concatenate([v, omega]),
                                   kin.LegState(mech, t, rot, v, omega).Ldot, atol=1e-12)


# -- accelerations ----------------------------------------------------------------------
def rotation_along(rot0, omega0, alpha, h):
    """R(h) for dR/dt = [omega0 + alpha t]x R, R(0) = rot0.

    Magnus expansion: Omega = omega0 h + alpha h^2/2 + (alpha x omega0) h^3/12 + O(h^5)
    (the commutator [w(t1), w(t2)] = (t1 - t2) alpha x omega0 gives the cubic term).
    """
    magnus = omega0 * h + alpha * h ** 2 / 2 + np.cross(alpha, omega0) * h ** 3 / 12
    return Rotation.from_rotvec(magnus).as_matrix() @ rot0


def test_magnus_rotation_reference_is_accurate(rng):
    """The reference trajectory above, against a tight numerical integration."""
    rot0 = Rotation.from_rotvec(rng.normal(0, 1, 3)).as_matrix()
    omega0, alpha = rng.normal(0, 1, 3), rng.normal(0, 3, 3)

    def rhs(time, y):
        w = omega0 + alpha * time
        wx = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        return (wx @ y.reshape(3, 3)).ravel()
    for h in (2e-3, -2e-3):
        sol = solve_ivp(rhs, (0, h), rot0.ravel(), method='DOP853', rtol=1e-13, atol=1e-15)
        np.testing.assert_allclose(rotation_along(rot0, omega0, alpha, h),
                                   sol.y[:, -1].reshape(3, 3), atol=1e-13)


def test_leg_accelerations_against_second_differences(default_mech, rng):
    """a_P = d2S/dt2, ddL = d2L/dt2, A = dW/dt along t(h) = t + v h + a h^2/2,
    omega(h) = omega + alpha h (constant accel and alpha, base frame)."""
    mech, h = default_mech, 2e-4
    for _ in range(10):
        t0, _, rot0 = random_pose(rng, mech)
        v0, omega0 = random_twist(rng)
        accel, alpha = rng.normal(0, 1.5, 3), rng.normal(0, 3, 3)

        def state(e):
            return (t0 + v0 * e + accel * e ** 2 / 2, rotation_along(rot0, omega0, alpha, e),
                    v0 + accel * e, omega0 + alpha * e)

        def S_at(e):
            t, rot, _, _ = state(e)
            return leg_vectors(mech, t, rot)

        def W_at(e):  # eq. 14 with dS/dt = v + omega x R p, computed here
            t, rot, v, omega = state(e)
            S = leg_vectors(mech, t, rot)
            p = np.asarray(mech.platform_points)[VERTEX_OF_LEG]
            S_dot = v + np.cross(omega, p @ rot.T)
            L = np.linalg.norm(S, axis=1)[:, None]
            return np.cross(S / L, S_dot) / L

        def second(f):
            return (f(h) - 2 * f(0.0) + f(-h)) / h ** 2
        S_ddot = second(S_at)
        L_ddot = second(lambda e: np.linalg.norm(S_at(e), axis=1))
        W_dot = central(W_at, h)

        legs = kin.LegState(mech, t0, rot0, v0, omega0)
        a_p, ddl, ang = kin.leg_accelerations(legs, accel, alpha, omega0)
        np.testing.assert_allclose(a_p, S_ddot, atol=2e-6)
        np.testing.assert_allclose(ddl, L_ddot, atol=2e-6)
        np.testing.assert_allclose(ang, W_dot, atol=2e-6)
        # eq. (15) reassembles the tip acceleration from the leg's own motion
        S = legs.S
        rebuilt = (ddl[:, None] * legs.s + 2 * np.cross(legs.W, legs.Ldot[:, None] * legs.s)
                   + np.cross(ang, S) + np.cross(legs.W, np.cross(legs.W, S)))
        np.testing.assert_allclose(rebuilt, S_ddot, atol=2e-6)
