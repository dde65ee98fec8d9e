"""A source that starts again, and two sources on one topic.

- StampGate (no DDS): a new publisher after a pause, or stamps jumping back
  after a pause, start a new run (accepted, counted); out-of-order samples
  within a run and a second publisher interleaving are refused.
- Over DDS: a lockstep plant run twice (and a realtime one restarted) under
  one running controller is answered in full the second time; ``play`` of one
  bag twice into a running fk: the second replay is answered in full; two rigs
  in one domain under one namespace report the collision on /diagnostics
  within a second, naming the publishers, and their controllers withhold
  forces.
"""
from __future__ import annotations

import pytest

from stewart63_ros.runtime.checks import Rejected, StampGate

A, B = b'A' * 16, b'B' * 16


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def feed(gate, ns, source):
    ns = gate.check_ns(ns, source)
    gate.check_source(source)
    gate.accept(ns, source)
    return gate.new_run


def test_gate_new_publisher_after_a_pause_is_a_new_run():
    clock = Clock()
    gate = StampGate(0.5, clock)
    for k in range(10):
        clock.t += 0.001
        assert feed(gate, 10**9 + k * 10**6, A) == ''
    clock.t += 2.0                        # the plant ended; a new one starts from 0
    assert feed(gate, 0, B) == 'a new publisher'
    assert gate.restarts == 1
    clock.t += 0.001
    assert feed(gate, 10**6, B) == ''
    with pytest.raises(Rejected) as exc:  # within the new run: order still holds
        clock.t += 0.001
        gate.check_ns(0, B)
    assert exc.value.reason == 'stamp_from_past'
    assert gate.restarts == 1


def test_gate_same_publisher_jumping_back_after_a_pause_is_a_new_run():
    clock = Clock()
    gate = StampGate(0.5, clock)
    feed(gate, 5 * 10**9, A)
    clock.t += 0.1                        # no pause: refused
    with pytest.raises(Rejected) as exc:
        gate.check_ns(10**9, A)
    assert exc.value.reason == 'stamp_from_past'
    clock.t += 0.6                        # quiet for 0.7 s, then back to 1 s: a new run
    assert feed(gate, 10**9, None).startswith('stamps jumped back')
    assert gate.restarts == 1


def test_gate_without_restart_pause_refuses_every_older_stamp():
    clock = Clock()
    gate = StampGate(None, clock)
    feed(gate, 5 * 10**9, A)
    clock.t += 100.0
    with pytest.raises(Rejected):
        gate.check_ns(10**9, B)


def test_gate_second_publisher_interleaving_is_refused_and_counted():
    clock = Clock()
    gate = StampGate(0.5, clock)
    refused = 0
    for k in range(100):                  # two rigs: both send at 1 kHz
        clock.t += 0.0005
        source = A if k % 2 == 0 else B
        try:
            feed(gate, 10**9 + k * 10**6, source)
        except Rejected as exc:
            assert exc.reason == 'second_source'
            refused += 1
    assert refused == 50 and gate.interleaved == 50 and gate.other_source == B
    assert gate.restarts == 0 and gate.source == A


def test_gate_senders_two_publishers_alternating_in_runs_are_both_senders():
    """Two lockstep plants waiting a second for forces each: their samples
    alternate in runs (each one a 'new run'), not interleaved: still two senders."""
    clock = Clock()
    gate = StampGate(0.5, clock)
    feed(gate, 10**9, A)
    clock.t += 0.6
    feed(gate, 5 * 10**8, B)             # quiet for 0.6 s: a new run of B
    assert gate.senders(1.0) == {A, B}
    clock.t += 2.0                       # a killed plant, restarted seconds later
    feed(gate, 0, A)
    assert gate.senders(1.0) == {A}


def test_gate_bad_content_from_a_second_publisher_keeps_its_own_reason():
    """The source check comes after the content checks (see wire)."""
    import numpy as np

    from stewart63_ros.runtime import wire
    gate = StampGate(0.5)
    good = wire.JointStateTemplates(('effort',)).get('base')
    wire_ok = good.fill(1, 0, effort=np.ones(6))
    ns, *_ = wire.joint_state_sample(wire_ok, gate, ('effort',), source=A)
    gate.accept(ns, A)
    bad = good.fill(2, 0, effort=np.array([np.nan] + [1.0] * 5))
    with pytest.raises(Rejected) as exc:
        wire.joint_state_sample(bad, gate, ('effort',), source=B)
    assert exc.value.reason == 'non_finite'
    with pytest.raises(Rejected) as exc:
        wire.joint_state_sample(good.fill(2, 0, effort=np.ones(6)), gate, ('effort',), source=B)
    assert exc.value.reason == 'second_source'


# -- over DDS ------------------------------------------------------------------------
import json  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from ros_harness import PYTHON, wait_until  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
PARAMS = REPO / 'config' / 'stewart63.yaml'
ERROR = 2


def exe(name):
    path = Path(PYTHON).parent / name
    return [str(path)] if path.exists() else [PYTHON, '-m', {
        'plant': 'stewart63_ros.nodes.plant', 'controller': 'stewart63_ros.nodes.controller',
        'fk': 'stewart63_ros.nodes.fk_node', 'rig': 'stewart63_ros.tools.rig',
        'play': 'stewart63_ros.tools.play'}[name]]


def level_of(status) -> int:
    lvl = status.level
    return lvl[0] if isinstance(lvl, (bytes, bytearray)) else int(lvl)


class Diagnostics:
    """Every /diagnostics status seen by a probe node: (time, name, level, message, values)."""

    def __init__(self, ros):
        from diagnostic_msgs.msg import DiagnosticArray

        from stewart63_ros import topics as T
        self.ros = ros
        self.seen = []
        self.node = ros.node('diag_probe')
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self.on_diag,
                                      T.DIAGNOSTICS_QOS)

    def on_diag(self, msg):
        now = time.monotonic()
        for s in msg.status:
            self.seen.append((now, s.name, level_of(s), s.message,
                              {kv.key: kv.value for kv in s.values}))

    def last(self, name):
        found = [d for d in self.seen if d[1] == name]
        return found[-1] if found else None

    def value(self, name, key, default=0):
        last = self.last(name)
        return int(last[4].get(key, default)) if last else default

    def wait(self, predicate, timeout):
        return self.ros.spin_until(predicate, timeout)


def _text(proc):
    return proc.stdout() + proc.stderr()


@pytest.mark.parametrize('mode', ['lockstep', 'realtime'])
def test_restarted_plant_under_a_running_controller_is_answered_in_full(ros, tmp_path, mode):
    diags = Diagnostics(ros)
    ns = ['--ros-args', '-r', '__ns:=/rs', '-p', 'clock_mode:=%s' % mode]
    ctl = ros.spawn(exe('controller') + ns, name='controller')
    fk = ros.spawn(exe('fk') + ns, name='fk')
    for proc in (ctl, fk):
        assert wait_until(lambda p=proc: 'matched after' in _text(p) or p.returncode is not None,
                          120), proc.describe()
    duration = 0.3 if mode == 'lockstep' else 1.0
    summaries = []
    for run in (1, 2):
        path = tmp_path / ('plant_%d.json' % run)
        plant = ros.spawn(exe('plant') + ns + [
            '-p', 'duration:=%g' % duration, '-p', 'summary_file:=%s' % path,
            '-p', 'lengths_subscribers:=2'], name='plant%d' % run)
        assert plant.wait(150) == 0, plant.describe()
        summaries.append(json.loads(path.read_text()))
    first, second = summaries
    n = int(round(duration * 1000)) + 1
    assert first['samples'] == second['samples'] == n
    ok = diags.wait(lambda: diags.value('stewart63/rs/controller', 'source_restarts') >= 1
                    and diags.value('stewart63/rs/fk', 'source_restarts') >= 1, 5)
    assert ok, (diags.last('stewart63/rs/controller'), diags.last('stewart63/rs/fk'),
                ctl.describe())
    assert 'a new run of its source' in _text(ctl)
    if mode == 'lockstep':
        # answered in full: no force timed out, and the run is the same run again
        assert first['force_timeouts'] == 0 and second['force_timeouts'] == 0, summaries
        diff = np.max(np.abs(np.subtract(first['final_leg_lengths_m'],
                                         second['final_leg_lengths_m'])))
        assert diff <= 1e-12, diff
    # every sample the controller took, of both runs, was answered; none refused
    name = 'stewart63/rs/controller'
    assert diags.wait(lambda: diags.value(name, 'received/leg_lengths') >= 2 * n * (
        0.9 if mode == 'lockstep' else 0.3), 5), diags.last(name)
    last = diags.last(name)[4]
    assert int(last['rejected_total']) == 0, last
    assert int(last['published/leg_forces']) == int(last['received/leg_lengths']), last
    print('\n%s plant run twice under one controller: second run %d samples, %d answered, '
          'force timeouts %d, final error %.4f %% (first %.4f %%); controller counted %d '
          'source restarts' % (mode, second['samples'], second['loop_latency']['count'],
                               second['force_timeouts'], second['positioning_error_percent'],
                               first['positioning_error_percent'],
                               diags.value('stewart63/rs/controller', 'source_restarts')))


def test_play_of_one_bag_twice_into_a_running_fk_is_answered_in_full(ros, tmp_path):
    from geometry_msgs.msg import PoseStamped, TwistStamped

    from stewart63_ros import bagio
    from stewart63_ros import topics as T
    bag = tmp_path / 'bag'
    rig = ros.spawn(exe('rig') + ['--mode', 'lockstep', '--duration', '0.5', '--record',
                                  str(bag), '--log-dir', str(tmp_path / 'rig')], name='rig')
    assert rig.wait(180) == 0, rig.describe()
    n = sum(1 for _ in bagio.read_messages(bag, ['/leg_lengths']))
    assert n == 501
    diags = Diagnostics(ros)
    got = []
    probe = diags.node
    probe.create_subscription(PoseStamped, '/replay/platform_pose',
                              lambda m: got.append(m.header.stamp.sec * 10**9
                                                   + m.header.stamp.nanosec), T.RECORD_SUB)
    probe.create_subscription(TwistStamped, '/replay/platform_twist', lambda m: None,
                              T.RECORD_SUB)
    fk = ros.spawn(exe('fk') + ['--ros-args', '-r', '__ns:=/replay',
                                '-p', 'wait_for_subscribers:=1'], name='fk')
    assert ros.spin_until(lambda: 'matched after' in fk.stderr(), 120), fk.describe()
    counts = []
    for run in (1, 2):
        # At a tenth of the recorded pace. Samples a replay lost here came from
        # fk's queue overflowing while fk was starved of CPU (it was 100 deep;
        # now 1 s at 1 kHz). play starts once its publisher has matched fk's
        # subscription: from then on the reliable writer keeps each sample
        # for fk, also if fk's side of the match completes a moment later.
        before = len(got)
        play = ros.spawn(exe('play') + [str(bag), '--topics', 'leg_lengths', '--namespace',
                                        '/replay', '--rate', '0.1'], name='play%d' % run)
        ros.spin_until(lambda b=before: len(got) - b >= n, 90)
        assert play.wait(30) == 0, play.describe()
        ros.spin_until(lambda b=before: len(got) - b >= n, 5)
        counts.append(len(got) - before)
    first, second = got[:counts[0]], got[counts[0]:]
    assert diags.wait(lambda: diags.value('stewart63/replay/fk', 'source_restarts') >= 1, 5)
    # Without the restart handling the second replay is refused as a whole
    # (stamp_from_past). Here nothing is refused, and each replay is answered
    # in full: every sample of the bag, once.
    rejected = diags.value('stewart63/replay/fk', 'rejected_total')
    assert rejected == 0, diags.last('stewart63/replay/fk')
    expected = set(range(0, n * 1_000_000, 1_000_000))
    for run, poses in (('first', first), ('second', second)):
        assert len(poses) == n and set(poses) == expected, (
            '%s replay: %d poses of %d, missing stamps (ms) %s' % (
                run, len(poses), n, sorted(s // 1_000_000 for s in expected - set(poses))[:20]),
            counts, fk.describe())
    print('\nplay twice into one fk: %d + %d poses of %d, source restarts %d, rejected %d'
          % (counts[0], counts[1], n, diags.value('stewart63/replay/fk', 'source_restarts'),
             rejected))


def test_two_rigs_in_one_namespace_report_the_collision_and_withhold_forces(ros, tmp_path):
    from sensor_msgs.msg import JointState

    from stewart63_ros import topics as T
    diags = Diagnostics(ros)
    # A witness of the two sources: a reader of /leg_lengths, matched to both
    # plants once this domain's discovery has joined the two rigs. Each rig
    # waits only for its own nodes (it cannot name the other), so that join
    # comes when discovery brings it, seconds later on a loaded machine; the
    # report's delay is counted from it, not from the plants' start.
    witness = diags.node.create_subscription(JointState, '/leg_lengths', lambda _m: None,
                                             T.LATEST_SUB, raw=True)
    rigs = [ros.spawn(exe('rig') + ['--mode', 'realtime', '--log-dir', str(tmp_path / str(i))],
                      name='rig%d' % i) for i in (1, 2)]
    plant_logs = [tmp_path / str(i) / 'plant.log' for i in (1, 2)]

    def running(i):
        return plant_logs[i].exists() and 'realtime at' in plant_logs[i].read_text()
    assert ros.spin_until(lambda: running(0) and running(1) or any(
        r.returncode is not None for r in rigs), 240), [r.describe() for r in rigs]
    assert ros.spin_until(lambda: witness.get_publisher_count() >= 2, 30), (
        witness.get_publisher_count(), [r.describe() for r in rigs])
    both_running = time.monotonic()
    diags.node.destroy_subscription(witness)        # (2 kHz this test need not take)
    name = 'stewart63/controller'      # both rigs' controllers: one status name

    def collisions():
        return [d for d in diags.seen if d[1] == name and d[2] == ERROR
                and d[3].startswith('collision')]
    assert ros.spin_until(lambda: len(collisions()) >= 2, 10), diags.seen[-6:]
    first = collisions()[0]
    assert 'publishers send on /leg_lengths' in first[3] and 'forces withheld' in first[3]
    delay = first[0] - both_running
    # each controller's report names both plants, told apart by their gids
    # (a plant the graph did not know yet is named on a later report)
    assert ros.spin_until(lambda: any(d[3].count('/plant (gid') == 2 for d in collisions()),
                          5), collisions()[-1][3]
    # the controllers withhold forces: their published count stands still
    ros.spin_until(lambda: False, 2.5)
    late = [d for d in collisions() if d[0] > time.monotonic() - 2.0]
    published = {int(d[4].get('published/leg_forces', 0)) for d in late}
    withheld = max(int(d[4].get('forces_withheld', 0)) for d in late)
    assert withheld > 10, late[-1]
    assert len(published) <= 2, published     # one count per controller, standing still
    fk_errors = [d for d in diags.seen if d[1] == 'stewart63/fk' and d[2] == ERROR]
    assert fk_errors, diags.last('stewart63/fk')
    # the plants: forces from both controllers (ERROR) until they withhold them,
    # then two silent controllers matched (WARN)
    plant_flags = [d for d in diags.seen if d[1] == 'stewart63/plant' and (
        d[2] == ERROR or 'publishers matched on /leg_forces' in d[3])]
    assert plant_flags, diags.last('stewart63/plant')
    for r in rigs:
        ros.stop(r)
    print('\ntwo rigs, one namespace: first collision report %.2f s after both plants ran '
          'and a reader had matched both (negative: found before); %s; forces withheld %d, '
          'leg_forces '
          'published counts while colliding %s' % (delay, first[3][:160], withheld,
                                                    sorted(published)))
    assert delay <= 1.0, delay


def test_four_rigs_in_four_namespaces_each_equal_sim_sample_for_sample(setup, ros, tmp_path):
    """Four lockstep rigs in one domain (one process each: --compose, with its
    recorder), under /r1 .. /r4: each bag equals the offline sampled run, no
    cross-talk, no collision reported."""
    from stewart63_ros import bagio
    from stewart63_ros.core.controllers.simulate import run_sampled, sensor_reading
    from stewart63_ros.core.mechanics.dynamics import Dynamics
    from stewart63_ros.core.plumbing.params import load_mechanism
    duration, names = 0.3, ['r1', 'r2', 'r3', 'r4']
    rigs = {ns: ros.spawn(exe('rig') + [
        '--mode', 'lockstep', '--duration', str(duration), '--compose', '--namespace', '/' + ns,
        '--record', str(tmp_path / ns), '--log-dir', str(tmp_path / ('log_' + ns))], name=ns)
        for ns in names}
    for proc in rigs.values():
        assert proc.wait(300) == 0, proc.describe()
    mech = load_mechanism(PARAMS)
    ref = run_sampled(setup, duration, 1000.0)
    dyn = Dynamics(mech)
    expected = [sensor_reading(dyn, ref.states[k]) for k in range(len(ref.times))]
    n = len(expected)
    worst = {}
    for ns in names:
        samples = {}
        for topic, _, msg in bagio.read_messages(tmp_path / ns):
            if topic.endswith('/leg_lengths'):
                assert topic == '/%s/leg_lengths' % ns, topic   # no other rig's samples
                stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
                assert stamp not in samples, 'two samples stamped %d in /%s' % (stamp, ns)
                samples[stamp] = msg
        assert sorted(samples) == [k * 1_000_000 for k in range(n)], (ns, len(samples))
        dl = max(float(np.max(np.abs(np.asarray(samples[k * 1_000_000].position)
                                     - expected[k][0]))) for k in range(n))
        worst[ns] = dl
        assert dl <= 1e-9, (ns, dl)
        statuses = [s for _, _, m in bagio.read_messages(tmp_path / ns, ['/diagnostics'])
                    for s in m.status if s.name.startswith('stewart63/%s/' % ns)]
        assert statuses
        for s in statuses:
            values = {kv.key: kv.value for kv in s.values}
            assert values.get('collisions', '0') == '0', (ns, s.name, s.message)
            assert not s.message.startswith('collision'), (ns, s.name, s.message)
    print('\nfour lockstep rigs in one domain, /r1../r4: each %d samples, max |dL| vs sim %s'
          % (n, ', '.join('%s %.2g m' % kv for kv in worst.items())))
