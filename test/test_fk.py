"""Forward kinematics (stewart63_ros.core.mechanics.fk) against independent references.

References: inverse kinematics (kinematics.leg_lengths), a brute-force
multi-start Newton on a different formulation (the nine vertex coordinates,
nine quadratic equations), numpy's SVD for the condition number, the
Jacobian's determinant for singular poses, and a trajectory integrated with
scipy from the dynamics.
"""
import json
import subprocess
import sys

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation

from stewart63_ros.core.mechanics import rotation as rotation_mod
from stewart63_ros.core.mechanics.dynamics import Dynamics
from stewart63_ros.core.mechanics.fk import (
    FKResult,
    FKTracker,
    ForwardKinematics,
    NoAssemblyError,
)
from stewart63_ros.core.mechanics.fk_modes import real_angles
from stewart63_ros.core.mechanics.fk_tracking import condition_number
from stewart63_ros.core.mechanics.kinematics import jacobian, leg_lengths, leg_rates
from stewart63_ros.core.mechanics.rotation import rotation_from_euler
from stewart63_ros.core.plumbing.params import load_mechanism
from stewart63_ros.tools import fk_solve

PAIR = np.array([0, 0, 1, 1, 2, 2])   # leg -> platform vertex
SIDES = [(0, 1), (1, 2), (2, 0)]


@pytest.fixture(scope='module')
def fk(default_setup):
    """The default machine's, its modes ordered by nearness to the task's start."""
    task = default_setup.task
    return ForwardKinematics(default_setup.mechanism,
                             start=(task.initial_position, task.initial_rotation))


def angle_between(ra, rb):
    """Rotation angle of ra^T rb [rad], from its sine and cosine (accurate when small)."""
    a = ra.T @ rb
    sin2 = np.linalg.norm([a[2, 1] - a[1, 2], a[0, 2] - a[2, 0], a[1, 0] - a[0, 1]])
    return np.arctan2(sin2, np.trace(a) - 1.0)


def random_workspace_poses(mech, rng, count):
    """Random poses within +-0.2 m in x, y, z in [0.85, 1.25], angles +-0.25 rad, inside the stroke.

    Returns (t, R, L) triples.
    """
    n = 4 * count
    t = np.c_[rng.uniform(-0.2, 0.2, (n, 2)), rng.uniform(0.85, 1.25, n)]
    rot = Rotation.from_euler('xyz', rng.uniform(-0.25, 0.25, (n, 3))).as_matrix()
    legs = np.einsum('nij,kj->nki', rot, mech.leg_platform_points) + t[:, None] - mech.base_points
    lengths = np.linalg.norm(legs, axis=2)
    inside = np.flatnonzero((lengths.min(1) >= mech.leg_length_min)
                            & (lengths.max(1) <= mech.leg_length_max))[:count]
    assert len(inside) == count
    return [(t[k], rot[k], lengths[k]) for k in inside]


def vertices(mode, mech):
    """Platform vertices in the base frame, (3, 3)."""
    return mode.position + mech.platform_points @ mode.rotation.T


def brute_force_vertices(base, plat, lengths, rng, starts=3000, iters=50):
    """Every vertex triple P with |P_k(i) - b_i| = L_i and |P_i - P_j| = |p_i - p_j|.

    Damped Newton on the nine quadratic equations in the nine vertex
    coordinates from many random starts in the box that holds every
    solution; converged solutions deduplicated. Returns the list and the
    fewest starts that reached any one solution (a measure of how safe the
    count is).
    """
    sides = np.array([np.linalg.norm(plat[i] - plat[j]) for i, j in SIDES])
    lo, hi = base.min(0) - lengths.max(), base.max(0) + lengths.max()
    x = rng.uniform(lo, hi, size=(starts, 3, 3))
    for _ in range(iters):
        f = np.empty((starts, 9))
        jac = np.zeros((starts, 9, 9))
        d = x[:, PAIR] - base
        f[:, :6] = np.einsum('nij,nij->ni', d, d) - lengths ** 2
        for i in range(6):
            jac[:, i, 3 * PAIR[i]:3 * PAIR[i] + 3] = 2 * d[:, i]
        for r, (i, j) in enumerate(SIDES):
            e = x[:, i] - x[:, j]
            f[:, 6 + r] = np.einsum('ni,ni->n', e, e) - sides[r] ** 2
            jac[:, 6 + r, 3 * i:3 * i + 3] = 2 * e
            jac[:, 6 + r, 3 * j:3 * j + 3] = -2 * e
        jac += 1e-14 * np.eye(9)     # keep singular starts from raising
        step = np.linalg.solve(jac, f[..., None])[..., 0]
        norm = np.linalg.norm(step, axis=1, keepdims=True)
        step *= np.minimum(1.0, 0.5 / np.maximum(norm, 1e-300))   # at most 0.5 m a step
        x = x - np.nan_to_num(step).reshape(-1, 3, 3)
    d = x[:, PAIR] - base
    err_legs = np.abs(np.linalg.norm(d, axis=2) - lengths).max(1)
    err_sides = np.abs(np.stack([np.linalg.norm(x[:, i] - x[:, j], axis=1)
                                 for i, j in SIDES], 1) - sides).max(1)
    good = x[(err_legs < 1e-10) & (err_sides < 1e-10)]
    found, hits = [], []
    for p in good:
        for k, q in enumerate(found):
            if np.abs(p - q).max() < 1e-6:
                hits[k] += 1
                break
        else:
            found.append(p)
            hits.append(1)
    return found, min(hits, default=0)


def random_mechanism(default, rng, coplanar):
    """A random 6-3 platform of ~1 m scale: base pairs around three azimuths, random triangle."""
    azimuth = np.sort(rng.uniform(0, 2 * np.pi, 3))
    base = []
    for k in range(3):
        for sign in (-1, 1):
            a = azimuth[k] + sign * rng.uniform(0.3, 0.8)
            z = 0.0 if coplanar else rng.uniform(-0.3, 0.3)
            base.append(rng.uniform(0.8, 1.4) * np.array([np.cos(a), np.sin(a), 0.0]) + [0, 0, z])
    plat = np.column_stack([rng.uniform(-0.6, 0.6, (3, 2)),
                            np.zeros(3) if coplanar else rng.uniform(-0.1, 0.1, 3)])
    return default.replace(base_points=np.array(base), platform_points=plat,
                           leg_length_min=0.01, leg_length_max=10.0)


# -- 1. FK(IK(pose)) -------------------------------------------------------------

def test_fk_of_ik_returns_the_pose(default_mech, fk):
    rng = np.random.default_rng(3)
    tracker = FKTracker(fk)
    worst_modes = worst_track = 0.0
    for t, rot, lengths in random_workspace_poses(default_mech, rng, 1000):
        modes = fk.all_modes(lengths)
        errors = [max(np.abs(m.position - t).max(), angle_between(m.rotation, rot)) for m in modes]
        worst_modes = max(worst_modes, errors[0])   # the true pose is the one nearest the start
        assert all(m.residual < 1e-12 for m in modes)
        # tracking from a nearby pose (as from the previous sample)
        tracker.reset(t + rng.uniform(-1e-3, 1e-3, 3),
                      Rotation.from_rotvec(rng.uniform(-1e-3, 1e-3, 3)).as_matrix() @ rot)
        found = tracker.solve(lengths)
        assert not found.fallback and not found.singular
        worst_track = max(worst_track, np.abs(found.position - t).max(),
                          angle_between(found.rotation, rot))
    assert worst_modes < 1e-9
    assert worst_track < 1e-9


def test_nearest_mode_to_the_initial_pose_is_the_setpoint_pose(default_setup, fk):
    """The paper's setpoint is a level pose ~7 cm above the start (config, docs/design.md)."""
    modes = fk.all_modes(default_setup.task.setpoint_lengths)
    assert len(modes) == 8                        # 8 real assembly modes here
    best = modes[0]
    assert abs(best.position[2] - 1.0737) < 1e-3 and np.abs(best.position[:2]).max() < 1e-3
    assert angle_between(best.rotation, np.eye(3)) < 1e-3
    np.testing.assert_allclose(leg_lengths(default_setup.mechanism, best.position, best.rotation),
                               default_setup.task.setpoint_lengths, atol=1e-14)


# -- 2. every assembly mode, against brute force ---------------------------------

@pytest.mark.parametrize('seed', range(8))
def test_modes_match_brute_force_on_random_mechanisms(default_mech, seed):
    rng = np.random.default_rng(100 + seed)
    mech = random_mechanism(default_mech, rng, coplanar=seed % 2 == 0)
    t = np.r_[rng.uniform(-0.2, 0.2, 2), rng.uniform(0.6, 1.2)]
    rot = Rotation.from_rotvec(rng.uniform(-0.5, 0.5, 3)).as_matrix()
    lengths = leg_lengths(mech, t, rot)
    modes = ForwardKinematics(mech).all_modes(lengths)
    brute, fewest_hits = brute_force_vertices(mech.base_points, mech.platform_points,
                                              lengths, rng)
    assert fewest_hits >= 5, 'brute force too thin to be a reference'
    ours = [vertices(m, mech) for m in modes]
    assert len(ours) == len(brute)
    for p in brute:
        assert min(np.abs(p - q).max() for q in ours) < 1e-9
    for m in modes:      # each is a genuine pose, to machine precision
        np.testing.assert_allclose(leg_lengths(mech, m.position, m.rotation), lengths,
                                   atol=1e-12)


def test_default_setpoint_modes_match_brute_force(default_setup, default_mech, fk):
    """A symmetric design: several modes share vertex 1 (a triple root in t1)."""
    lengths = np.asarray(default_setup.task.setpoint_lengths)
    brute, fewest_hits = brute_force_vertices(default_mech.base_points,
                                              default_mech.platform_points, lengths,
                                              np.random.default_rng(7))
    assert fewest_hits >= 5
    ours = [vertices(m, default_mech) for m in fk.all_modes(lengths)]
    assert len(ours) == len(brute) == 8
    for p in brute:
        assert min(np.abs(p - q).max() for q in ours) < 1e-9


def test_resultant_roots_keep_multiple_and_infinite_roots():
    """The root step on a polynomial with known roots: a double real root
    (two modes sharing vertex 1, as in the default design) comes out of the
    eigenvalues as a complex pair with a tiny imaginary part but must not be
    dropped; a vanishing leading coefficient is a root at t = infinity (phi = pi)."""
    real = [0.7, 0.7, -2.0, -2.0, 0.1, 3.0]
    complex_pairs = [0.3 + 1.1j, -1.0 + 0.5j, 2.0 + 3.0j, 0.5 + 0.2j, -0.4 + 2.0j]
    roots = real + complex_pairs + [np.conj(z) for z in complex_pairs]
    coeffs = np.poly(roots)[::-1].real            # 16 roots, lowest power first
    phis = real_angles(np.ascontiguousarray(coeffs))
    assert len(coeffs) == 17
    for t in (0.7, -2.0, 0.1, 3.0):
        assert np.min(np.abs(phis - 2 * np.arctan(t))) < 1e-4
    assert len(phis) <= len(real)                 # the complex roots are not taken
    phis = real_angles(np.r_[np.poly(roots[1:])[::-1].real, 0.0])    # degree 15
    assert np.min(np.abs(np.abs(phis) - np.pi)) < 1e-12


def test_mirror_images_come_in_pairs(default_mech, fk):
    rng = np.random.default_rng(5)
    cases = [(default_mech, fk, p[2]) for p in random_workspace_poses(default_mech, rng, 5)]
    for _ in range(3):
        mech = random_mechanism(default_mech, rng, coplanar=True)
        t = np.r_[rng.uniform(-0.2, 0.2, 2), rng.uniform(0.6, 1.2)]
        rot = Rotation.from_rotvec(rng.uniform(-0.5, 0.5, 3)).as_matrix()
        cases.append((mech, ForwardKinematics(mech), leg_lengths(mech, t, rot)))
    mirror = np.diag([1.0, 1.0, -1.0])        # base points in z = 0
    for mech, solver, lengths in cases:
        points = [vertices(m, mech) for m in solver.all_modes(lengths)]
        assert len(points) % 2 == 0
        for p in points:
            assert sum(np.abs(p @ mirror - q).max() < 1e-9 for q in points) == 1


# -- 3. no assembly --------------------------------------------------------------

@pytest.mark.parametrize('pair', range(3))
@pytest.mark.parametrize('kind', ['difference', 'sum'])
def test_a_pair_that_cannot_meet_is_named(default_setup, default_mech, fk, pair, kind):
    a, b = 2 * pair, 2 * pair + 1
    gap = np.linalg.norm(default_mech.base_points[b] - default_mech.base_points[a])
    lengths = np.array(default_setup.task.setpoint_lengths, dtype=float)
    if kind == 'difference':          # |La - Lb| > |ba - bb|
        lengths[a], lengths[b] = 0.1, 0.1 + gap * 1.01
    else:                             # La + Lb < |ba - bb|
        lengths[a] = lengths[b] = 0.49 * gap
    with pytest.raises(NoAssemblyError, match='legs %d and %d cannot meet' % (a + 1, b + 1)):
        fk.all_modes(lengths)
    with pytest.raises(NoAssemblyError, match='legs %d and %d' % (a + 1, b + 1)):
        FKTracker(fk).solve(lengths)


def test_lengths_without_assembly_raise_and_brute_force_agrees(default_mech, fk):
    # Every pair can meet (just), but its vertex is then pinned near the
    # middle of its base line, and those points are not a platform triangle.
    gaps = np.linalg.norm(default_mech.base_points[1::2] - default_mech.base_points[0::2], axis=1)
    lengths = np.repeat(gaps / 2 * 1.001, 2)
    fk.circles(lengths)            # no pair fails
    brute, _ = brute_force_vertices(default_mech.base_points, default_mech.platform_points,
                                    lengths, np.random.default_rng(11))
    assert brute == []
    with pytest.raises(NoAssemblyError, match='no assembly mode'):
        fk.all_modes(lengths)
    with pytest.raises(NoAssemblyError):
        FKTracker(fk).solve(lengths)


def test_bad_lengths(fk):
    with pytest.raises(ValueError, match='6 finite'):
        fk.all_modes([1.0] * 5)
    with pytest.raises(ValueError, match='6 finite'):
        fk.all_modes([1.6, 1.6, 1.6, 1.6, 1.6, np.nan])
    with pytest.raises(ValueError, match='6 finite'):
        FKTracker(fk).solve([1.6, np.nan, 1.6, 1.6, 1.6, 1.6])
    with pytest.raises(NoAssemblyError, match='leg_3'):
        FKTracker(fk).solve([1.6, 1.6, -1.0, 1.6, 1.6, 1.6])


# -- 4. singular poses -----------------------------------------------------------

def test_condition_number_matches_numpy():
    rng = np.random.default_rng(2)
    for scale in (1.0, 1e-3, 1e-6, 1e-9):
        a = rng.normal(size=(6, 6))
        u, s, vt = np.linalg.svd(a)
        s[-1] = scale * s[0]               # prescribed conditioning
        a = u @ np.diag(s) @ vt
        assert condition_number(a) == pytest.approx(np.linalg.cond(a), rel=1e-6)


def test_singular_pose_is_flagged_and_tracked_through(default_mech):
    """Turning the level platform about z crosses a singular pose (det J = 0,
    the classic one near 90 deg). The flag is on there and off away from it.
    A threshold of 100 (rather than the default 1e4) gives a flagged window
    wide enough to sample on both sides of the singularity."""
    threshold = 100.0
    fk = ForwardKinematics(default_mech, cond_threshold=threshold)
    t = np.array([0.0, 0.0, 1.07])

    def rot(psi):
        return rotation_from_euler([0.0, 0.0, psi])

    def det(psi):
        return np.linalg.det(jacobian(default_mech, rot(psi), t))
    psi_star = brentq(det, 1.2, 1.9, xtol=1e-14)
    singular = fk.all_modes(leg_lengths(default_mech, t, rot(psi_star)))
    assert singular[0].singular and singular[0].condition > 1e6
    assert np.abs(singular[0].position - t).max() < 1e-6

    tracker = FKTracker(fk, t, rot(1.2))
    psis = np.linspace(1.2, 1.95, 1501)
    flags = []
    for psi in psis:
        found = tracker.solve(leg_lengths(default_mech, t, rot(psi)))
        flags.append(found.singular)
        true_cond = np.linalg.cond(jacobian(default_mech, rot(psi), t))
        if abs(true_cond / threshold - 1) > 0.01:
            assert found.singular == (true_cond > threshold)
        if not found.singular:     # on the true branch on both sides
            assert np.abs(found.position - t).max() < 1e-9
            assert angle_between(found.rotation, rot(psi)) < 1e-9
    flagged = psis[np.array(flags)]
    assert flagged.min() < psi_star < flagged.max()
    assert flagged.max() - flagged.min() < 0.1          # near it only
    assert np.all(np.diff(np.flatnonzero(flags)) == 1)  # one window


def test_quaternion_matches_scipy():
    rng = np.random.default_rng(4)
    rots = Rotation.random(2000, random_state=rng)
    special = Rotation.from_rotvec([[np.pi, 0, 0], [0, np.pi, 0], [0, 0, np.pi],
                                    [np.pi / np.sqrt(2), np.pi / np.sqrt(2), 0], [0, 0, 0]])
    for rot in list(rots) + list(special):
        expected = rot.as_quat()
        expected = -expected if expected[3] < 0 else expected
        found = FKResult(np.zeros(3), rot.as_matrix(), 1.0, False, 0.0).quaternion
        if abs(expected[3]) < 1e-12:        # w = 0: q and -q are both right
            found = found * np.sign(found @ expected)
        np.testing.assert_allclose(found, expected, atol=1e-14)


# -- 5. tracking ---------------------------------------------------------------

def test_tracker_falls_back_to_the_nearest_mode_after_a_jump(default_mech, fk):
    tracker = FKTracker(fk)
    t = np.array([0.15, -0.1, 1.2])
    rot = rotation_from_euler([0.2, -0.1, 0.25])
    found = tracker.solve(leg_lengths(default_mech, t, rot))     # 0.2 m from the start
    assert found.fallback
    assert np.abs(found.position - t).max() < 1e-9 and angle_between(found.rotation, rot) < 1e-9
    again = tracker.solve(leg_lengths(default_mech, t + 1e-4, rot))
    assert not again.fallback


def test_twist_from_leg_rates(default_mech, fk):
    rng = np.random.default_rng(8)
    for t, rot, _ in random_workspace_poses(default_mech, rng, 50):
        v, w = rng.normal(size=3), rng.normal(size=3)
        rates = leg_rates(default_mech, t, rot, v, w)
        v2, w2 = fk.twist(t, rot, rates)
        np.testing.assert_allclose(np.r_[v2, w2], np.r_[v, w], atol=1e-12)


def paper_trajectory(setup, duration=10.0, rate=1000.0):
    """The paper's scenario (PD to the setpoint lengths, eq. 40), integrated by scipy."""
    dyn = Dynamics(setup.mechanism)

    def rhs(_, y):
        legs = dyn.legs(y)
        forces = np.clip(setup.gains.kp * (setup.task.setpoint_lengths - legs.L)
                         - setup.gains.kv * legs.Ldot,
                         -setup.mechanism.max_force, setup.mechanism.max_force)
        return dyn.derivative(y, forces)

    theta0 = np.asarray(setup.task.initial_orientation)
    y0 = np.r_[setup.task.initial_position, rotation_mod.quaternion_from_euler(theta0),
               setup.task.initial_velocity,
               rotation_mod.euler_rate_matrix(theta0) @ setup.task.initial_orientation_rate]
    sol = solve_ivp(rhs, (0.0, duration), y0, rtol=1e-8, atol=1e-10, dense_output=True)
    assert sol.success
    times = np.arange(int(round(duration * rate)) + 1) / rate
    return times, sol.sol(times).T


def test_tracking_follows_the_paper_scenario(default_setup, default_mech, fk):
    times, states = paper_trajectory(default_setup)
    t = states[:, 0:3]
    rot = Rotation.from_quat(states[:, 3:7]).as_matrix()     # normalises
    v, w = states[:, 7:10], states[:, 10:13]
    # inverse kinematics and leg rates (eqs. 2-5, 13), all samples at once
    q = np.einsum('nij,kj->nki', rot, default_mech.leg_platform_points)
    legs = q + t[:, None] - default_mech.base_points
    lengths = np.linalg.norm(legs, axis=2)
    rates = np.einsum('nki,nki->nk', legs / lengths[..., None],
                      np.cross(w[:, None], q) + v[:, None])
    tracker = FKTracker(fk)
    pos, rots, twists, iterations = [], [], [], []
    for k in range(len(times)):
        found = tracker.solve(lengths[k], rates[k])
        assert not found.fallback and not found.singular
        pos.append(found.position)
        rots.append(found.rotation)
        twists.append(np.r_[found.velocity, found.omega])
        iterations.append(found.iterations)
    assert len(times) == 10001
    assert np.abs(np.array(pos) - t).max() < 1e-9
    assert Rotation.from_matrix(np.array(rots) @ rot.transpose(0, 2, 1)).magnitude().max() < 1e-9
    assert np.abs(np.array(twists) - np.c_[v, w]).max() < 1e-9
    assert max(iterations) <= 4


# -- 6. the command line -------------------------------------------------------

def test_cli_prints_the_nearest_pose(default_setup, default_mech, capsys):
    setpoint = default_setup.task.setpoint_lengths
    assert fk_solve.main(['--solve'] + ['%.17g' % v for v in setpoint]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) >= {'position', 'theta', 'quaternion', 'condition_number'}
    rot = rotation_from_euler(out['theta'])
    np.testing.assert_allclose(leg_lengths(default_mech, out['position'], rot),
                               default_setup.task.setpoint_lengths, atol=1e-12)
    np.testing.assert_allclose(Rotation.from_quat(out['quaternion']).as_matrix(), rot, atol=1e-12)
    assert abs(out['position'][2] - 1.0737) < 1e-3
    assert out['condition_number'] == pytest.approx(
        np.linalg.cond(jacobian(default_mech, rot, out['position'])), rel=1e-9)


@pytest.mark.parametrize('name, count', [('stewart63.yaml', 8), ('hexapod66.yaml', 12)])
def test_cli_all_modes(default_params_file, capsys, name, count):
    """Both packaged geometries: the 6-3's 8 real modes (by its degree-16
    polynomial), the 6-6's 12 (by fk66's 40-path homotopy), each fitting the
    lengths."""
    path = default_params_file.parent / name
    argv = ['--solve', '1.9', '1.9', '1.6', '1.6', '1.6', '1.6', '--all', '--params', str(path)]
    assert fk_solve.main(argv) == 0
    out = json.loads(capsys.readouterr().out)
    assert out['count'] == len(out['modes']) == count
    mech = load_mechanism(path)
    for mode in out['modes']:
        np.testing.assert_allclose(leg_lengths(mech, mode['position'],
                                               rotation_from_euler(mode['theta'])),
                                   [1.9, 1.9, 1.6, 1.6, 1.6, 1.6], atol=1e-9)


def test_cli_no_assembly_exits_2_with_one_line(capsys):
    assert fk_solve.main(['--solve', '0.1', '3.2', '1.6', '1.6', '1.6', '1.6']) == 2
    captured = capsys.readouterr()
    assert captured.out == ''
    assert captured.err.count('\n') == 1 and 'legs 1 and 2' in captured.err


@pytest.mark.parametrize('argv', [['--solve', '1', '2', '3'],
                                  ['--solve', '1', '2', '3', '4', '5', 'x'],
                                  ['--solve', '1', '2', '3', '4', '5', 'nan'], []])
def test_cli_bad_arguments_are_argparse_errors(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        fk_solve.main(argv)
    assert exc.value.code == 2
    assert 'usage' in capsys.readouterr().err


def test_the_fk_executable_dispatches_to_the_solver_or_the_node(capsys):
    """``fk`` (tools/fk.py) runs the solver with --solve, else the node, whose
    --help lists the solver's options too (--strict included)."""
    from stewart63_ros.tools import fk
    with pytest.raises(SystemExit) as exc:
        fk.main(['fk', '--solve', '1.9', '1.9', '1.6', '1.6', '1.6', '1.6', '--strict'])
    assert exc.value.code == 0
    assert json.loads(capsys.readouterr().out)['position'][2] == pytest.approx(1.0737, abs=1e-3)
    with pytest.raises(SystemExit) as exc:
        fk.main(['fk', '--help'])
    assert exc.value.code == 0
    usage = capsys.readouterr().out
    for option in ('--solve', '--params', '--all', '--strict', '--ros-args'):
        assert option in usage, usage


@pytest.mark.slow      # a fresh interpreter
def test_cli_runs_as_a_module_without_ros():
    code = ('import sys, runpy; sys.argv = ["fk", "--solve", "1.9", "1.9", "1.6", "1.6", '
            '"1.6", "1.6"]\n'
            'try:\n    runpy.run_module("stewart63_ros.tools.fk", run_name="__main__")\n'
            'except SystemExit as e:\n    assert not e.code, e.code\n'
            'assert "rclpy" not in sys.modules\n')
    proc = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)['position'][2] == pytest.approx(1.0737, abs=1e-3)
