"""Forward kinematics of the 6-6 (core/mechanics/fk66.py): every assembly mode, checked
against the true pose, the lengths, and a brute-force search that shares
nothing with the homotopy but the leg equations."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stewart63_ros.core.mechanics.fk import NoAssemblyError
from stewart63_ros.core.mechanics.fk66 import GENERIC_MODES, FKTracker66, ForwardKinematics66
from stewart63_ros.core.mechanics.fk_tracking import _newton, _pose_distance


def semi_regular(base_radius=0.5, plat_radius=0.3, base_gap_deg=12.0, plat_gap_deg=10.0):
    """A lab hexapod: joints in three close pairs on each side, each base
    pair's legs going to two different platform pairs (the usual zig-zag)."""
    base_gap, plat_gap = np.radians(base_gap_deg), np.radians(plat_gap_deg)
    ang_b = [k * 2 * np.pi / 3 + s * base_gap / 2 for k in range(3) for s in (-1, 1)]
    ang_p = [k * 2 * np.pi / 3 - np.pi / 3 + s * plat_gap / 2 for k in range(3) for s in (1, -1)]
    base = np.c_[base_radius * np.cos(ang_b), base_radius * np.sin(ang_b), np.zeros(6)]
    plat = np.c_[plat_radius * np.cos(ang_p), plat_radius * np.sin(ang_p), np.zeros(6)]
    return base, np.roll(plat, -1, axis=0)


def general(seed):
    """Six random points on each side, neither set planar."""
    rng = np.random.default_rng(seed)
    return rng.uniform(-0.5, 0.5, (6, 3)), rng.uniform(-0.3, 0.3, (6, 3))


def pose(position, euler):
    return np.array(position, float), Rotation.from_euler('xyz', euler).as_matrix()


POSES = [pose([0.0, 0.0, 0.45], [0.0, 0.0, 0.0]),
         pose([0.03, -0.02, 0.42], [0.08, -0.05, 0.15]),
         pose([-0.06, 0.04, 0.5], [-0.15, 0.1, -0.3])]


def contains(modes, position, rotation, size):
    return any(_pose_distance(m.position, m.rotation, position, rotation, size) < 1e-8
               for m in modes)


def brute_force(fk, lengths, starts, seed=1):
    """Distinct poses Newton reaches from `starts` random poses (a check only:
    it can miss modes, but any mode it finds is real and must be among ours)."""
    rng = np.random.default_rng(seed)
    reach = lengths.max() + np.linalg.norm(fk.base, axis=1).max()
    rots = Rotation.random(starts, random_state=seed).as_matrix()
    found = []
    for k in range(starts):
        t0 = rng.uniform(-reach, reach, 3)
        t, rot, _, ok, res = _newton(fk.base, fk.legp, lengths, t0, np.ascontiguousarray(rots[k]),
                                     60, 1e-12)
        if ok and res < 1e-9 and not any(
                _pose_distance(t, rot, t2, r2, fk.size) < 1e-6 for t2, r2 in found):
            found.append((t, rot))
    return found


@pytest.mark.parametrize('k', range(len(POSES)))
def test_semi_regular_true_pose_is_a_mode_and_every_mode_fits_the_lengths(k):
    fk = ForwardKinematics66(*semi_regular())
    position, rotation = POSES[k]
    lengths = fk.lengths(position, rotation)
    modes = fk.all_modes(lengths, reference=(position, rotation))
    # (a) the pose the lengths came from is a mode, and the nearest one to it
    assert contains(modes, position, rotation, fk.size)
    assert np.allclose(modes[0].position, position, atol=1e-9)
    assert np.allclose(modes[0].rotation, rotation, atol=1e-9)
    # (b) every mode reproduces the lengths, is a rotation, and is distinct
    for m in modes:
        assert np.abs(fk.lengths(m.position, m.rotation) - lengths).max() < 1e-9
        assert np.allclose(m.rotation @ m.rotation.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(m.rotation) > 0
        assert m.condition >= 1.0 and m.singular == (m.condition > fk.cond_threshold)
    for i in range(len(modes)):
        for j in range(i):
            assert _pose_distance(modes[i].position, modes[i].rotation, modes[j].position,
                                  modes[j].rotation, fk.size) > 1e-6
    # planar base and platform: each mode's mirror image through the base plane is one too
    mirror = np.diag([1.0, 1.0, -1.0])
    for m in modes:
        assert contains(modes, mirror @ m.position, mirror @ m.rotation @ mirror, fk.size)
    assert len(modes) % 2 == 0 and len(modes) <= GENERIC_MODES


@pytest.mark.parametrize('geometry, position, euler', [
    ('semi_regular', [0.04, 0.02, 0.40], [0.2, -0.1, 0.25]),
    ('general_3', [0.05, -0.03, 0.55], [0.1, 0.2, -0.15]),
    ('general_7', [-0.02, 0.06, 0.45], [-0.2, 0.05, 0.3]),
])
def test_brute_force_finds_no_mode_the_homotopy_missed(geometry, position, euler):
    base, plat = semi_regular() if geometry == 'semi_regular' else general(
        int(geometry.split('_')[1]))
    fk = ForwardKinematics66(base, plat)
    position, rotation = pose(position, euler)
    lengths = fk.lengths(position, rotation)
    modes = fk.all_modes(lengths)
    found = brute_force(fk, lengths, 20000)
    missed = [t for t, rot in found if not contains(modes, t, rot, fk.size)]
    assert not missed, 'brute force found %d modes the homotopy missed: %s' % (
        len(missed), missed)
    assert contains(modes, position, rotation, fk.size)
    assert len(found) >= 2      # the search did find something to compare


def test_a_path_lost_midway_is_tracked_again_round_the_near_miss():
    """Found by a sweep: on this geometry the straight parameter line passes so
    near the degenerate set e = 0 that one path stops at t = 0.243; that path
    carries the eighth of eight real modes. The re-run through a complex
    midpoint must bring it back (the brute force finds 8)."""
    fk = ForwardKinematics66(*general(297))
    lengths = fk.lengths(*pose([0.040853038306200365, 0.02365456328821397, 0.5585143958414169],
                               [0.13720098802496206, 0.23100506266908533, 0.27415975238756823]))
    modes = fk.all_modes(lengths)
    assert fk.reruns >= 1
    assert len(modes) == 8
    assert all(contains(modes, t, rot, fk.size) for t, rot in brute_force(fk, lengths, 4000))


def test_generic_geometry_gives_forty_regular_complex_solutions():
    """The count: random complex-generic data has exactly 40 solutions (Raghavan;
    Lazard; Ronga & Vust); for a random real geometry every path must end on a
    distinct regular point, none lost."""
    fk = ForwardKinematics66(*general(11))
    lengths = fk.lengths(*pose([0.02, 0.01, 0.5], [0.1, -0.2, 0.3]))
    ends, done = fk.complex_solutions(lengths)
    assert done.all() and ends.shape == (GENERIC_MODES, 8)
    for i in range(GENERIC_MODES):
        for j in range(i):
            a, b = ends[i] / ends[i][0], ends[j] / ends[j][0]
            assert np.linalg.norm(a - b) > 1e-6


def test_unreachable_lengths_and_bad_input_are_refused():
    fk = ForwardKinematics66(*semi_regular())
    with pytest.raises(NoAssemblyError, match='no real'):
        fk.all_modes([0.01, 0.01, 0.01, 0.01, 0.01, 0.01])   # shorter than any gap
    with pytest.raises(NoAssemblyError, match='leg_2'):
        fk.all_modes([0.4, -0.4, 0.4, 0.4, 0.4, 0.4])
    with pytest.raises(ValueError, match='6 finite'):
        fk.all_modes([0.4] * 5)
    base, plat = semi_regular()
    plat[3] = plat[2]
    with pytest.raises(ValueError, match='legs 3 and 4 share a joint'):
        ForwardKinematics66(base, plat)


def test_tracker_follows_a_moving_6_6_with_core_fk_kernels():
    fk = ForwardKinematics66(*semi_regular())
    position, rotation = POSES[0]
    tracker = FKTracker66(fk, position, rotation)
    worst = 0.0
    for k in range(1, 400):
        s = k / 1000.0
        t = np.array([0.03 * np.sin(2 * s), 0.02 * np.sin(3 * s), 0.45 + 0.03 * np.sin(s)])
        rot = Rotation.from_euler('xyz', [0.1 * np.sin(2 * s), 0.05 * s, 0.2 * s]).as_matrix()
        result = tracker.solve(fk.lengths(t, rot), rates=np.zeros(6))
        assert np.allclose(result.velocity, 0.0) and np.allclose(result.omega, 0.0)
        assert not result.fallback and not result.singular and result.iterations <= 4
        worst = max(worst, np.abs(result.position - t).max(), np.abs(result.rotation - rot).max())
    assert worst < 1e-9


@pytest.mark.slow
def test_sweep_of_geometries_and_poses_against_brute_force():
    """60 solves, semi-regular and random 6-6 alternately, at random poses: the
    true pose is always a mode, the brute force never finds one more, and the
    real count is even (non-real solutions come in conjugate pairs)."""
    rng = np.random.default_rng(2026)
    for k in range(60):
        fk = ForwardKinematics66(*(semi_regular() if k % 2 else general(500 + k)))
        position, rotation = pose([*rng.uniform(-0.05, 0.05, 2), rng.uniform(0.3, 0.6)],
                                  rng.uniform(-0.3, 0.3, 3))
        lengths = fk.lengths(position, rotation)
        modes = fk.all_modes(lengths)
        assert contains(modes, position, rotation, fk.size), k
        assert len(modes) % 2 == 0, k
        found = brute_force(fk, lengths, 5000, seed=k)
        assert all(contains(modes, t, rot, fk.size) for t, rot in found), k


def test_at_and_near_a_singular_pose():
    """A 90-degree twist about the vertical is singular for this hexapod (cond J ~
    1e16): there the mode nearest the truth is flagged singular and fits the
    lengths, though the lengths no longer pin the pose; 1e-3 rad away the true
    pose is found exactly."""
    fk = ForwardKinematics66(*semi_regular())
    at = pose([0.0, 0.0, 0.45], [0.0, 0.0, np.pi / 2])
    lengths = fk.lengths(*at)
    modes = fk.all_modes(lengths, reference=at)
    assert modes[0].singular
    assert _pose_distance(modes[0].position, modes[0].rotation, *at, fk.size) < 1e-5
    assert all(np.abs(fk.lengths(m.position, m.rotation) - lengths).max() < 1e-9 for m in modes)
    near = pose([0.0, 0.0, 0.45], [0.0, 0.0, np.pi / 2 + 1e-3])
    assert contains(fk.all_modes(fk.lengths(*near)), *near, fk.size)
