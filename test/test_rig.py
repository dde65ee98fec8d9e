"""The rig over real DDS, nodes in separate processes.

- lockstep: the distributed loop (plant, controller, fk, record) reproduces
  the offline ``run_sampled(setup, D, 1000)`` sample for sample;
- realtime: the ``fk`` pose agrees with the plant's ground truth;
- the ``rig`` command: Ctrl-C / SIGTERM stops every child and exits 0; a node
  that dies makes the rig stop the others and exit non-zero.

Every test runs on its own ROS domain (``ros`` fixture), every wait is
bounded, every process started here is stopped by its pid. Figures (max
differences, counts, rates) are printed: run with ``-s`` to see them.
"""
from __future__ import annotations

import contextlib
import json
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest
from ros_harness import PYTHON, rig_env, run_to_end, wait_line, wait_until

from stewart63_ros import bagio
from stewart63_ros.bagio import header_stamp_ns as stamp_ns
from stewart63_ros.core.controllers.simulate import run_sampled, sensor_reading
from stewart63_ros.core.mechanics.dynamics import POS, Dynamics
from stewart63_ros.core.plumbing.params import load_mechanism
from stewart63_ros.tools.rig_process import Rig

REPO = Path(__file__).resolve().parents[1]
#: Node processes over DDS: `make test-fast` leaves this file out.
pytestmark = [pytest.mark.dds, pytest.mark.slow]
PARAMS = REPO / 'config' / 'stewart63.yaml'
RATE = 1000.0
LOCKSTEP_DURATION = 0.5      # simulated s: 501 samples
REALTIME_DURATION = 3.0      # s: 3001 samples
#: Bound on a whole rig run (start-up with discovery, the run, the stop).
RUN_TIMEOUT = 150.0
MODULES = ('stewart63_ros.nodes.plant', 'stewart63_ros.nodes.controller',
           'stewart63_ros.nodes.fk_node')


@pytest.fixture(scope='module')
def mech():
    return load_mechanism(PARAMS)


@pytest.fixture(scope='module')
def warm_kernels(setup, mech):
    """Compile the numba kernels here, once, into the on-disk cache, so the
    nodes (three processes) load them instead of each compiling for tens of
    seconds (on a fresh checkout or after the core changed)."""
    from stewart63_ros.core.mechanics.fk import FKTracker
    from stewart63_ros.core.mechanics.kinematics import leg_lengths
    from stewart63_ros.core.mechanics.rotation import rotation_from_euler
    tracker = FKTracker(mech)
    rot = rotation_from_euler(setup.task.initial_orientation)
    lengths = leg_lengths(mech, setup.task.initial_position, rot)
    tracker.solve(lengths, np.zeros(6))
    tracker.fk.all_modes(lengths)
    run_sampled(setup, 0.002, RATE)


def by_stamp(bag, topic) -> tuple[dict, int]:
    """{stamp_ns: message} of one topic, and the number of messages read."""
    out, count = {}, 0
    for _, _, msg in bagio.read_messages(bag, [topic]):
        out[stamp_ns(msg)] = msg
        count += 1
    return out, count


def run_rig(ros, monkeypatch, tmp_path, mode, duration):
    """A ``Rig`` (plant, controller, fk, record) run to its end; always stopped."""
    rig_env(ros, monkeypatch)
    bag = tmp_path / 'bag'
    rig = Rig(PARAMS, mode=mode, duration=duration, record=bag, log_dir=tmp_path / 'rig')
    wall = time.monotonic()
    ok, codes, logs = run_to_end(rig, RUN_TIMEOUT)
    wall = time.monotonic() - wall
    assert ok, 'the rig did not finish its run: %s\n%s' % (codes, logs)
    assert codes == {'record': 0, 'controller': 0, 'fk': 0, 'plant': 0}, logs
    summary = rig.summary()
    assert summary is not None, logs
    return bag, summary, wall, logs


def test_lockstep_rig_reproduces_offline_sampled_run(setup, ros, monkeypatch, tmp_path, mech,
                                                     warm_kernels):
    ref = run_sampled(setup, LOCKSTEP_DURATION, RATE)
    n = int(round(LOCKSTEP_DURATION * RATE)) + 1
    assert len(ref.times) == n

    bag, summary, wall, logs = run_rig(ros, monkeypatch, tmp_path, 'lockstep',
                                       LOCKSTEP_DURATION)
    assert summary['clock_mode'] == 'lockstep'
    assert summary['samples'] == n, summary
    assert summary['force_timeouts'] == 0, summary

    lengths, n_lengths = by_stamp(bag, 'leg_lengths')
    forces, n_forces = by_stamp(bag, 'leg_forces')
    truth, n_truth = by_stamp(bag, 'ground_truth/pose')
    assert n_lengths == n, 'bag has %d leg_lengths samples, expected %d' % (n_lengths, n)
    assert n_forces == n, 'bag has %d leg_forces, expected %d' % (n_forces, n)
    expected_stamps = [k * 1_000_000 for k in range(n)]   # k / 1000 s, exact in ns
    assert sorted(lengths) == expected_stamps
    assert sorted(forces) == expected_stamps

    dyn = Dynamics(mech)
    dl = dv = df = dp = 0.0
    for k in range(n):
        s = k * 1_000_000
        L, Ldot = sensor_reading(dyn, ref.states[k])
        msg = lengths[s]
        assert list(msg.name) == ['leg_%d' % i for i in range(1, 7)]
        dl = max(dl, float(np.max(np.abs(np.asarray(msg.position) - L))))
        dv = max(dv, float(np.max(np.abs(np.asarray(msg.velocity) - Ldot))))
        df = max(df, float(np.max(np.abs(np.asarray(forces[s].effort) - ref.forces[k]))))
        if s in truth:
            p = truth[s].pose.position
            dp = max(dp, float(np.max(np.abs(np.array([p.x, p.y, p.z]) - ref.states[k, POS]))))
    print('\nlockstep rig vs run_sampled over %d samples: max |dL| %.3g m, max |dLdot| %.3g m/s, '
          'max |dF| %.3g N, max |dt| (ground truth) %.3g m; %d ground-truth poses; '
          'plant loop %.1f samples/s (%.2f s wall), whole rig %.1f s wall'
          % (n, dl, dv, df, dp, n_truth, n / summary['wall_time_s'],
             summary['wall_time_s'], wall))
    assert dl <= 1e-9, 'leg lengths differ from the offline run by %g m' % dl
    assert dv <= 1e-9, 'leg rates differ from the offline run by %g m/s' % dv
    # F = Kp dL + Kv dLdot: a length difference of 1e-9 m is 4e-6 N.
    assert df <= 1e-5, 'forces differ from the offline run by %g N' % df
    assert n_truth == n and dp <= 1e-9
    counts = assert_every_published_message_is_in_the_bag(bag, summary)
    assert counts['/clock'] == n, counts


def test_played_leg_lengths_into_a_fresh_fk_reproduce_the_recorded_truth(
        ros, monkeypatch, tmp_path, mech, warm_kernels):
    """`play BAG --topics leg_lengths` stands in for the plant; a new
    fk process turns the recorded samples back into the recorded ground truth."""
    from geometry_msgs.msg import PoseStamped

    from stewart63_ros import topics as T
    bag, summary, _, _ = run_rig(ros, monkeypatch, tmp_path, 'lockstep', LOCKSTEP_DURATION)
    truth, n_truth = by_stamp(bag, 'ground_truth/pose')
    assert n_truth == summary['samples']

    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import TwistStamped
    got = {}
    probe = ros.node('probe')
    probe.create_subscription(PoseStamped, '/replay/platform_pose',
                              lambda m: got.__setitem__(stamp_ns(m), m), T.RECORD_SUB)
    probe.create_subscription(TwistStamped, '/replay/platform_twist', lambda m: None,
                              T.RECORD_SUB)
    probe.create_subscription(DiagnosticArray, '/diagnostics', lambda m: None,
                              T.DIAGNOSTICS_QOS)
    # fk starts taking samples only once its publishers have matched the probe,
    # and play starts only then: nothing is published before anyone listens.
    fk = ros.spawn([PYTHON, '-m', 'stewart63_ros.nodes.fk_node', '--ros-args',
                    '--params-file', str(PARAMS), '-r', '__ns:=/replay',
                    '-p', 'wait_for_subscribers:=1'], name='fk')
    assert ros.spin_until(lambda: 'matched after' in fk.stderr(), 60), fk.describe()
    play = ros.spawn([PYTHON, '-m', 'stewart63_ros.tools.play', str(bag), '--topics',
                      'leg_lengths', '--namespace', '/replay'], name='play')
    ros.spin_until(lambda: len(got) >= n_truth, 60)
    assert play.wait(30) == 0, play.describe()
    ros.spin_until(lambda: len(got) >= n_truth, 5)
    assert sorted(got) == sorted(truth), (len(got), n_truth, fk.describe())
    dpos = drot = 0.0
    for s, msg in got.items():
        t, f = truth[s].pose, msg.pose
        dpos = max(dpos, max(abs(f.position.x - t.position.x), abs(f.position.y - t.position.y),
                             abs(f.position.z - t.position.z)))
        drot = max(drot, quat_angle(
            [t.orientation.x, t.orientation.y, t.orientation.z, t.orientation.w],
            [f.orientation.x, f.orientation.y, f.orientation.z, f.orientation.w]))
    print('\nplay -> fresh fk: %d poses, max |dt| %.3g m, max angle %.3g rad vs recorded truth'
          % (len(got), dpos, drot))
    assert dpos <= 1e-6 and drot <= 1e-6, (dpos, drot)


def quat_angle(q1, q2) -> float:
    """Angle [rad] of the rotation between two unit quaternions (x, y, z, w),
    accurate near zero (atan2 of the relative rotation's parts)."""
    q1 = np.asarray(q1, float) / np.linalg.norm(q1)
    q2 = np.asarray(q2, float) / np.linalg.norm(q2)
    w = abs(float(np.dot(q1, q2)))
    # |vector part| of q1^-1 q2
    x1, y1, z1, w1 = q1
    x2, y2, z2, w2 = q2
    v = np.array([w1 * x2 - x1 * w2 - (y1 * z2 - z1 * y2),
                  w1 * y2 - y1 * w2 - (z1 * x2 - x1 * z2),
                  w1 * z2 - z1 * w2 - (x1 * y2 - y1 * x2)])
    return 2.0 * float(np.arctan2(np.linalg.norm(v), w))


def test_quat_angle_helper():
    from scipy.spatial.transform import Rotation
    a = Rotation.from_euler('xyz', [0.1, -0.2, 0.3])
    b = a * Rotation.from_rotvec([1e-8, -2e-8, 3e-8])
    assert abs(quat_angle(a.as_quat(), b.as_quat()) - np.sqrt(14) * 1e-8) < 1e-15
    assert abs(quat_angle(a.as_quat(), -a.as_quat())) < 1e-15


def test_realtime_fk_pose_matches_ground_truth(ros, monkeypatch, tmp_path, mech, warm_kernels):
    bag, summary, wall, logs = run_rig(ros, monkeypatch, tmp_path, 'realtime',
                                       REALTIME_DURATION)
    n = int(round(REALTIME_DURATION * RATE)) + 1
    assert summary['clock_mode'] == 'realtime'
    assert summary['samples'] == n, summary

    truth, n_truth = by_stamp(bag, 'ground_truth/pose')
    fk, n_fk = by_stamp(bag, 'platform_pose')
    lengths, n_lengths = by_stamp(bag, 'leg_lengths')
    common = sorted(set(truth) & set(fk))
    assert common, 'no platform_pose with the stamp of a ground_truth/pose sample:\n' + logs
    assert set(fk) <= set(lengths), 'a platform_pose with a stamp of no sample'

    dpos = drot = 0.0
    for s in common:
        t, f = truth[s].pose, fk[s].pose
        pt = np.array([t.position.x, t.position.y, t.position.z])
        pf = np.array([f.position.x, f.position.y, f.position.z])
        qt = [t.orientation.x, t.orientation.y, t.orientation.z, t.orientation.w]
        qf = [f.orientation.x, f.orientation.y, f.orientation.z, f.orientation.w]
        assert fk[s].header.frame_id == 'base'
        dpos = max(dpos, float(np.max(np.abs(pf - pt))))
        drot = max(drot, quat_angle(qt, qf))
    lat = summary['loop_latency']
    print('\nrealtime rig, %g s at %g Hz: %d samples published, %d leg_lengths / %d ground truth '
          '/ %d fk poses recorded, %d compared; fk vs truth max |dt| %.3g m, max angle %.3g rad; '
          'missed cycles %d, late cycles %d, force timeouts %d; latency p50 %s ms p99 %s ms '
          'max %s ms; whole rig %.1f s wall'
          % (REALTIME_DURATION, RATE, summary['samples'], n_lengths, n_truth, n_fk, len(common),
             dpos, drot, summary['missed_cycles'], summary['late_cycles'],
             summary['force_timeouts'], _fmt(lat.get('p50_ms')), _fmt(lat.get('p99_ms')),
             _fmt(lat.get('max_ms')), wall))
    z = [m.pose.position.z for m in truth.values()]
    context = ('(plant: missed cycles %d, late cycles %d, end-stop samples %d, '
               'final error %.3g %%; ground truth z from %.3f to %.3f m)'
               % (summary['missed_cycles'], summary['late_cycles'], summary['endstop_samples'],
                  summary['positioning_error_percent'], min(z), max(z)))
    assert dpos <= 1e-6, 'fk position off the ground truth by %g m %s' % (dpos, context)
    assert drot <= 1e-6, 'fk orientation off the ground truth by %g rad %s' % (drot, context)
    counts = assert_every_published_message_is_in_the_bag(bag, summary)
    print('published = recorded, per topic: %s' % counts)


def final_published_counts(bag) -> dict:
    """{(node status name, topic): count} from each node's last /diagnostics
    status in the bag: what the node says it published, sent at its exit."""
    last = {}
    for _, _, msg in bagio.read_messages(bag, ['/diagnostics']):
        for status in msg.status:
            last[status.name] = {kv.key[len('published/'):]: int(kv.value)
                                 for kv in status.values if kv.key.startswith('published/')}
    return {(name, topic): n for name, counts in last.items() for topic, n in counts.items()
            if topic != '/diagnostics'}    # a status cannot count itself


def message_stamp_ns(m) -> int:
    if hasattr(m, 'markers'):                   # MarkerArray: its markers' stamp
        m = m.markers[0]
    if hasattr(m, 'header'):
        return stamp_ns(m)
    return int(m.clock.sec) * 1_000_000_000 + int(m.clock.nanosec)


def assert_every_published_message_is_in_the_bag(bag, summary):
    """Per topic, the publisher's count equals the bag's, in stamp order."""
    counts = final_published_counts(bag)
    nodes = {name.rsplit('/', 1)[-1] for name, _ in counts}
    assert nodes == {'plant', 'controller', 'fk'}, counts
    topics_of = {}
    for (_name, topic), n in counts.items():
        topics_of.setdefault(topic, 0)
        topics_of[topic] += n
    for topic in ('leg_lengths', 'leg_forces', 'ground_truth/pose', 'ground_truth/twist',
                  'platform_pose', 'platform_twist'):
        assert topics_of.get(topic), (topic, counts)
    assert topics_of['leg_lengths'] == summary['samples']
    for topic, published in topics_of.items():
        stamps = [message_stamp_ns(m) for _, _, m in bagio.read_messages(bag, [topic])]
        assert len(stamps) == published, '%s: published %d, bag has %d' % (
            topic, published, len(stamps))
        assert all(a < b for a, b in zip(stamps, stamps[1:])), '%s out of order' % topic
    assert_every_status_is_in_the_bag(bag)
    return topics_of


def assert_every_status_is_in_the_bag(bag) -> dict:
    """Each node's statuses on /diagnostics are all in the bag: its last one
    counts those before it (``published//diagnostics``), so the bag holds
    that many plus the last one."""
    held, said = {}, {}
    for _, _, msg in bagio.read_messages(bag, ['/diagnostics']):
        for status in msg.status:
            held[status.name] = held.get(status.name, 0) + 1
            values = {kv.key: kv.value for kv in status.values}
            if values.get('final') == 'true':
                said[status.name] = int(values.get('published//diagnostics', 0)) + 1
    assert said, 'no final status in the bag: %s' % held
    for name, n in said.items():
        assert held[name] == n, '%s: published %d statuses, bag has %d' % (name, n, held[name])
    return said


def _fmt(value):
    return 'n/a' if value is None else '%.3f' % value


# --------------------------------------------------------------------------
# The `rig` command and its children


def rig_command():
    exe = Path(PYTHON).parent / 'rig'
    return [str(exe)] if exe.exists() else [PYTHON, '-m', 'stewart63_ros.tools.rig']


def children_of(pid: int) -> dict[int, str]:
    """{pid: command line} of the live children of ``pid`` (from /proc), and
    of a child that is rig's fork server (runtime/forkserver.py), its
    children too: the rig's nodes, forked from it."""
    out = direct_children(pid)
    for child, cmd in list(out.items()):
        if 'stewart63_ros.runtime.forkserver' in cmd.split():
            out.update(direct_children(child))
    return out


def direct_children(pid: int) -> dict[int, str]:
    """{child pid: command line} of the live children of ``pid`` (from /proc)."""
    out = {}
    for entry in Path('/proc').iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / 'stat').read_text()
            ppid = int(stat.rsplit(')', 1)[1].split()[1])
            if ppid != pid:
                continue
            cmd = (entry / 'cmdline').read_bytes().replace(b'\0', b' ').decode(errors='replace')
        except (OSError, ValueError, IndexError):
            continue
        out[int(entry.name)] = cmd
    return out


def ended(pid: int, cmdline: str) -> bool:
    """True once ``pid`` is gone (or a zombie, or reused by another program)."""
    try:
        stat = Path('/proc/%d/stat' % pid).read_text()
        cmd = Path('/proc/%d/cmdline' % pid).read_bytes().replace(b'\0', b' ').decode(
            errors='replace')
    except OSError:
        return True
    state = stat.rsplit(')', 1)[1].split()[0]
    return state in ('Z', 'X') or cmd != cmdline


def node_pids(children: dict[int, str]) -> dict[str, int]:
    found = {}
    for pid, cmd in children.items():
        for module in MODULES:
            if module in cmd.split():
                found[module.rsplit('.', 1)[1]] = pid
    return found


@contextlib.contextmanager
def rig_process(ros, tmp_path):
    """``rig --mode realtime`` (no duration) running, with the pids of its three
    nodes; its children are killed by pid at the end whatever happened."""
    log_dir = tmp_path / 'rig_logs'
    proc = ros.spawn(rig_command() + ['--mode', 'realtime', '--log-dir', str(log_dir)],
                     name='rig')
    children: dict[int, str] = {}
    try:
        assert wait_line(proc, 'rig: ', 90), proc.describe()
        assert wait_until(lambda: len(node_pids(children_of(proc.pid))) == 3, 10), (
            children_of(proc.pid), proc.describe())
        children = children_of(proc.pid)
        pids = node_pids(children)
        # The plant is past discovery and in its loop: stop the rig mid-run.
        plant_log = log_dir / 'plant.log'
        assert wait_until(lambda: plant_log.exists() and 'realtime at' in plant_log.read_text(),
                          60), proc.describe() + '\n' + read_log(plant_log)
        yield proc, pids, children, log_dir
    finally:
        ros.stop(proc)
        kill_leftovers(children)


def kill_leftovers(children: dict) -> None:
    """SIGKILL every child of a stopped rig that is still alive."""
    for pid, cmd in children.items():
        if not ended(pid, cmd):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)


def read_log(path) -> str:
    try:
        return Path(path).read_text(errors='replace')
    except OSError:
        return ''


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
def test_rig_signal_stops_every_child_and_exits_zero(ros, tmp_path, warm_kernels, sig):
    with rig_process(ros, tmp_path) as (proc, pids, children, log_dir):
        os.kill(proc.pid, sig)        # Ctrl-C in a terminal reaches only the rig's group
        code = proc.wait(45)
        assert code == 0, proc.describe()
        assert wait_until(lambda: all(ended(p, c) for p, c in children.items()), 10), (
            {p: c for p, c in children.items() if not ended(p, c)})
        assert 'stopped by %s' % sig.name in proc.stdout(), proc.describe()
        print('\nrig stopped by %s: exit %d; nodes %s ended' % (sig.name, code, pids))


def test_rig_exits_nonzero_when_a_node_dies(ros, tmp_path, warm_kernels):
    with rig_process(ros, tmp_path) as (proc, pids, children, log_dir):
        os.kill(pids['controller'], signal.SIGKILL)
        code = proc.wait(45)
        assert code is not None, 'rig still running after its controller died\n' + proc.describe()
        assert code != 0, proc.describe()
        assert wait_until(lambda: all(ended(p, c) for p, c in children.items()), 10), (
            {p: c for p, c in children.items() if not ended(p, c)})
        assert 'controller exited with -9' in proc.stderr(), proc.describe()
        summary = read_log(log_dir / 'plant_summary.json')
        print('\nrig after SIGKILL of its controller: exit %d; plant, fk ended; %s'
              % (code, 'plant summary written' if summary else 'no plant summary'))
        if summary:
            json.loads(summary)


def test_rig_sigterm_while_starting_stops_at_once(ros, tmp_path, warm_kernels):
    """SIGTERM while the rig still waits for its recorder to match the nodes
    (which may take minutes on a cold numba cache) stops it then, not after."""
    log_dir = tmp_path / 'rig_logs'
    proc = ros.spawn(rig_command() + ['--mode', 'lockstep', '--record', str(tmp_path / 'bag'),
                                      '--log-dir', str(log_dir)], name='rig')
    children: dict[int, str] = {}
    try:
        record_log = log_dir / 'record.log'
        assert wait_until(lambda: 'READY' in read_log(record_log).split(), 60), (
            proc.describe() + '\n' + read_log(record_log))
        assert wait_until(lambda: len(children_of(proc.pid)) >= 2, 10), children_of(proc.pid)
        children = children_of(proc.pid)
        os.kill(proc.pid, signal.SIGTERM)
        t0 = time.monotonic()
        code = proc.wait(30)
        took = time.monotonic() - t0
        assert code == 0, proc.describe()
        assert 'stopped by SIGTERM' in proc.stdout(), proc.describe()
        assert wait_until(lambda: all(ended(p, c) for p, c in children.items()), 10), (
            {p: c for p, c in children.items() if not ended(p, c)})
        print('\nrig stopped by SIGTERM during start-up in %.2f s: exit %d, %d children ended'
              % (took, code, len(children)))
    finally:
        ros.stop(proc)
        kill_leftovers(children)
