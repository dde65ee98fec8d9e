"""record / play / bagio over real DDS, in separate processes (docs/bags.md).

One recording (module fixture) feeds most checks: a publisher process sends
N samples at 1 kHz on four stream topics plus a latched setpoint, while
``record`` runs as its own process. Every wait is bounded, every process is
stopped by the harness, every test runs on its own ROS domain.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import stream_publisher as SP
from mcap.reader import make_reader
from ros_harness import PYTHON, RosTest, lease_domain_id, stop, wait_line, wait_matched, wait_until

from stewart63_ros import bagio, bagrepair, bagruns
from stewart63_ros.bagio import BagError
from stewart63_ros.core.plumbing.trajectory import COLUMNS

HERE = Path(__file__).resolve().parent
#: Node processes over DDS: `make test-fast` leaves this file out.
pytestmark = [pytest.mark.dds, pytest.mark.slow]
PUBLISHER = str(HERE / 'stream_publisher.py')
N = 2000
RATE = 1000.0
STREAMS = list(SP.STREAMS)


def cli(tool):
    return [PYTHON, '-m', f'stewart63_ros.tools.{tool}']


def sha(path: Path) -> dict:
    out = {}
    for p in sorted(Path(path).rglob('*')) if Path(path).is_dir() else [Path(path)]:
        if p.is_file():
            out[str(p)] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def record_and_publish(rt: RosTest, bag: Path, count: int, extra_record=(), extra_pub=(),
                       flush_period=None):
    """Start record, wait for READY, run the publisher to ACKED; returns (rec, pub)."""
    cmd = cli('record') + [str(bag), *extra_record]
    if flush_period is not None:
        cmd += ['--flush-period', str(flush_period)]
    rec = rt.spawn(cmd, name='record')
    assert wait_line(rec, 'READY', 30), rec.describe()
    pub = rt.python(PUBLISHER, '--count', str(count), '--rate', str(RATE), *extra_pub,
                    name='publisher')
    assert pub.wait(count / RATE + 60) == 0, pub.describe()
    out = pub.stdout()
    assert 'MATCHED' in out and 'ACKED' in out and 'NOT ACKED' not in out, pub.describe()
    return rec, pub


@pytest.fixture(scope='module')
def recorded(tmp_path_factory):
    """A bag recorded by a ``record`` process from a publisher process."""
    tmp = tmp_path_factory.mktemp('recorded')
    rt = RosTest(lease_domain_id(), tmp / 'logs')
    try:
        bag = tmp / 'bag'
        ready = tmp / 'ready'
        rec, pub = record_and_publish(
            rt, bag, N, extra_pub=['--setpoint'],
            extra_record=['--wait-for-publishers', *STREAMS, '--ready-file', str(ready)])
        assert wait_line(rec, 'MATCHED', 5), rec.describe()
        assert ready.read_text().strip() == 'ready'
        rc = stop(rec)                      # SIGINT, like Ctrl-C
        assert rc == 0, rec.describe()
        yield {'bag': bag, 'rec': rec, 'pub': pub, 'tmp': tmp}
    finally:
        rt.cleanup()


# ------------------------------------------------------------------ harness


def test_harness_stop_escalates_and_kills_the_group(ros):
    """stop() gets rid of a process that ignores SIGINT and SIGTERM, and of its children."""
    code = ('import os, signal, subprocess, sys, time\n'
            'signal.signal(signal.SIGINT, signal.SIG_IGN)\n'
            'signal.signal(signal.SIGTERM, signal.SIG_IGN)\n'
            'c = subprocess.Popen(["sleep", "60"])\n'
            'print(c.pid, flush=True)\n'
            'time.sleep(60)\n')
    proc = ros.python('-c', code, name='stubborn')
    assert wait_until(lambda: proc.stdout().strip().isdigit(), 20), proc.describe()
    child = int(proc.stdout().strip())
    t0 = time.monotonic()
    rc = stop(proc, sigint_wait=0.5, sigterm_wait=0.5, sigkill_wait=5)
    assert rc == -signal.SIGKILL
    assert time.monotonic() - t0 < 8
    assert wait_until(lambda: not Path(f'/proc/{child}').exists()
                      or 'Z' in Path(f'/proc/{child}/stat').read_text().split()[2], 5)


def test_harness_domains_are_distinct():
    leases = [lease_domain_id() for _ in range(5)]
    try:
        assert len({x.domain_id for x in leases}) == 5
        assert all(1 <= x.domain_id <= 100 for x in leases)
    finally:
        for x in leases:
            x.release()


# ------------------------------------------------------------------ record


def test_record_ready_matched_and_summary(recorded):
    out = recorded['rec'].stdout().splitlines()
    assert out[0] == 'READY' and out[1] == 'MATCHED'
    summary = out[-1]
    assert summary.startswith('record: ') and f'/leg_lengths {N}' in summary, summary


def test_record_counts_and_order(recorded):
    """Every published sample is in the bag, once, in order; the latched setpoint too."""
    stamps = {t: [] for t in STREAMS + ['leg_setpoint']}
    for topic, _, msg in bagio.read_messages(recorded['bag']):
        stamps[topic.lstrip('/')].append(bagio.header_stamp_ns(msg))
    for t in STREAMS:
        assert stamps[t] == [SP.stamp_ns(k, RATE) for k in range(N)], t
    assert stamps['leg_setpoint'] == [0]


def _check_fields(topic, k, get):
    e = SP.expected(topic, k, RATE)
    if topic in ('leg_lengths', 'leg_forces', 'leg_setpoint'):
        assert list(get('name')) == e['name']
        for f in ('position', 'velocity', 'effort'):
            assert np.array_equal(np.asarray(get(f), float), np.asarray(e[f], float)), (topic, k, f)
    elif topic == 'ground_truth/pose':
        p, q = get('pose').position, get('pose').orientation
        assert [p.x, p.y, p.z] == e['position']
        assert [q.x, q.y, q.z, q.w] == e['orientation']
    else:
        v, w = get('twist').linear, get('twist').angular
        assert [v.x, v.y, v.z] == e['linear'] and [w.x, w.y, w.z] == e['angular']
    assert get('header').frame_id == e['frame_id']
    assert (get('header').stamp.sec, get('header').stamp.nanosec) == e['stamp']


def test_bag_read_by_rosbags(recorded):
    seen = {t: 0 for t in STREAMS + ['leg_setpoint']}
    for topic, _, msg in bagio.read_messages(recorded['bag']):
        t = topic.lstrip('/')
        _check_fields(t, seen[t], lambda f: getattr(msg, f))
        seen[t] += 1
    assert seen == {**{t: N for t in STREAMS}, 'leg_setpoint': 1}


def test_bag_read_by_mcap_reader(recorded):
    """The MCAP file read independently of rosbags: mcap + mcap_ros2's decoder."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    files = list(recorded['bag'].glob('*.mcap'))
    assert len(files) == 1
    seen = {t: 0 for t in STREAMS + ['leg_setpoint']}
    with files[0].open('rb') as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == 4 * N + 1
        for _schema, channel, message, msg in reader.iter_decoded_messages():
            t = channel.topic.lstrip('/')
            assert message.log_time > 0
            _check_fields(t, seen[t], lambda f: getattr(msg, f))
            seen[t] += 1
    assert seen == {**{t: N for t in STREAMS}, 'leg_setpoint': 1}


def test_metadata_lists_topics_and_offered_qos(recorded):
    from ruamel.yaml import YAML
    meta = YAML(typ='safe').load((recorded['bag'] / 'metadata.yaml').read_text())
    info = meta['rosbag2_bagfile_information']
    assert info['version'] == 9 and info['storage_identifier'] == 'mcap'
    assert info['message_count'] == 4 * N + 1
    assert info['custom_data'][bagio.NAMESPACE_KEY] == '/'
    topics = {x['topic_metadata']['name']: x for x in info['topics_with_message_count']}
    assert set(topics) == {'/' + t for t in STREAMS} | {'/leg_setpoint'}
    for name, x in topics.items():
        md = x['topic_metadata']
        assert x['message_count'] == (1 if name == '/leg_setpoint' else N)
        assert md['type_description_hash'].startswith('RIHS01_')
        qos = md['offered_qos_profiles']
        assert len(qos) == 1 and qos[0]['reliability'] == 'reliable', (name, qos)
        assert qos[0]['durability'] == ('transient_local' if name == '/leg_setpoint'
                                        else 'volatile')


def test_trajectory_from_bag(recorded):
    cols = bagruns.trajectory_from_bag(recorded['bag'])
    assert list(cols) == list(COLUMNS)
    k = np.arange(N)
    assert all(len(v) == N for v in cols.values())
    assert np.allclose(cols['t'], k / RATE)
    assert np.allclose(cols['x'], 0.01) and np.allclose(cols['y'], 0.01 + 1e-5 * k)
    assert np.allclose(cols['theta_x'], 0.001 * k) and np.allclose(cols['theta_y'], 0)
    assert np.allclose(cols['vz'], 1.0) and np.allclose(cols['wz'], 1e-3 * k)
    for i in range(6):
        assert np.allclose(cols[f'L{i + 1}'], 1.6 + 0.001 * i + 1e-6 * k)
        assert np.allclose(cols[f'Ldot{i + 1}'], 0.01 * i - 1e-5 * k)
        assert np.allclose(cols[f'F{i + 1}'], 100.0 * i + 0.5 * k)
    held = bagruns.trajectory_from_bag(recorded['bag'], hold_forces=True)
    assert all(np.array_equal(held[c], cols[c]) for c in cols)   # nothing to hold here


def test_record_stops_cleanly_on_sigterm(ros, tmp_path):
    bag = tmp_path / 'bag'
    rec, _ = record_and_publish(ros, bag, 300, extra_pub=['--topics', 'leg_lengths'])
    os.killpg(rec.pid, signal.SIGTERM)
    assert rec.wait(15) == 0, rec.describe()
    assert bagio.bag_info(bag)['topics']['/leg_lengths'] == ('sensor_msgs/msg/JointState', 300)


def test_hard_kill_then_recover(ros, tmp_path):
    """SIGKILL leaves an MCAP without summary and no metadata.yaml; everything
    flushed before the kill comes back with ``record --recover``."""
    bag = tmp_path / 'bag'
    rec, _ = record_and_publish(ros, bag, 1000, flush_period=0.2)
    # everything is on disk once the file has stopped growing for a while
    mcap = bag / 'bag.mcap'
    sizes = []

    def settled():
        sizes.append(mcap.stat().st_size if mcap.exists() else -1)
        return len(sizes) > 8 and sizes[-1] > 0 and len(set(sizes[-8:])) == 1
    assert wait_until(settled, 20, period=0.1)
    os.killpg(rec.pid, signal.SIGKILL)
    assert rec.wait(10) == -signal.SIGKILL
    assert not (bag / 'metadata.yaml').exists()
    with pytest.raises(BagError, match='record --recover'):
        list(bagio.read_messages(bag))
    fix = ros.spawn(cli('record') + ['--recover', str(bag)], name='recover')
    assert fix.wait(60) == 0, fix.describe()
    assert 'recovered' in fix.stdout()
    info = bagio.bag_info(bag)
    assert {t: n for t, (_, n) in info['topics'].items()} == {'/' + t: 1000 for t in STREAMS}
    assert (bag / 'bag.mcap.orig').exists()
    stamps = [bagio.header_stamp_ns(m) for _, _, m in bagio.read_messages(bag, ['leg_lengths'])]
    assert stamps == [SP.stamp_ns(k, RATE) for k in range(1000)]
    from ruamel.yaml import YAML
    meta = YAML(typ='safe').load((bag / 'metadata.yaml').read_text())
    for x in meta['rosbag2_bagfile_information']['topics_with_message_count']:
        assert x['topic_metadata']['offered_qos_profiles'], x
    # a second recovery would overwrite the kept original: refused
    with pytest.raises(BagError, match='exists already'):
        bagrepair.recover_bag(bag)


# ------------------------------------------------------------------ play


def test_play_reproduces_messages_and_timing(recorded, ros):
    """``play --topics leg_lengths`` stands in for the plant: a subscriber gets
    the recorded bytes, in order, with the recorded timing."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import JointState

    from stewart63_ros import topics as T
    bag = recorded['bag']
    want = [(stamp, data) for _, _, stamp, data in bagio.read_raw(bag, ['leg_lengths'])]
    node = ros.node('probe')
    got, clock = [], []
    node.create_subscription(JointState, 'leg_lengths',
                             lambda m, i: got.append((i['received_timestamp'], m)),
                             T.RECORD_SUB, raw=True)
    node.create_subscription(Clock, '/clock', lambda m: clock.append(
        m.clock.sec * 10**9 + m.clock.nanosec),
        QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
    play = ros.spawn(cli('play') + [str(bag), '--topics', 'leg_lengths', '--clock', '50'],
                     name='play')
    assert ros.spin_until(lambda: len(got) >= N or play.returncode is not None,
                          timeout=N / RATE + 40), play.describe()
    ros.spin_until(lambda: len(got) >= N, timeout=5)
    assert play.wait(20) == 0, play.describe()
    assert play.stdout().splitlines()[0] == 'PLAYING'
    assert [d for _, d in got] == [d for _, d in want]
    rx = np.array([r for r, _ in got], dtype=np.int64)
    tb = np.array([s for s, _ in want], dtype=np.int64)
    err = ((rx - rx[0]) - (tb - tb[0])) * 1e-6          # ms
    err -= np.median(err)
    p50, p99, mx = np.percentile(np.abs(err), 50), np.percentile(np.abs(err), 99), \
        np.abs(err).max()
    print(f'\nplay timing error vs bag timestamps over {N} msgs at 1 kHz: '
          f'p50 {p50:.3f} ms, p99 {p99:.3f} ms, max {mx:.3f} ms')
    # Loose bounds: the machine may be shared (CI, other checkouts). Playing
    # without timing (a burst) or at a wrong rate would be off by ~1000 ms.
    assert p50 < 5.0 and mx < 250.0, (p50, p99, mx)
    span_rx, span_bag = (rx[-1] - rx[0]) * 1e-9, (tb[-1] - tb[0]) * 1e-9
    assert abs(span_rx - span_bag) < 0.05 * span_bag + 0.05, (span_rx, span_bag)
    # /clock: bag time, increasing, within the bag
    info = bagio.bag_info(bag)
    assert len(clock) >= 10
    assert all(b >= a for a, b in zip(clock, clock[1:]))
    assert info['start_ns'] <= clock[0] and clock[-1] <= info['end_ns'] + 10**8


# ------------------------------------------------------------------ in-process API


def _publish_when_matched(node, topic, n, cls=None):
    from sensor_msgs.msg import JointState

    from stewart63_ros import topics as T
    cls = cls or JointState
    pub = node.create_publisher(cls, topic, T.publisher_qos(topic))
    assert wait_matched(pub, 1, 15)
    for k in range(n):
        m = cls()
        if cls is JointState:
            m.header.stamp.nanosec = k
            m.position = [float(k)] * 6
        else:
            m.data = f'm{k}'
        pub.publish(m)
    return pub


@pytest.mark.parametrize('fast_path', [True, False], ids=['waitset', 'executor'])
def test_recorder_class_in_namespace_then_player(ros, tmp_path, fast_path):
    from sensor_msgs.msg import JointState

    from stewart63_ros import topics as T
    from stewart63_ros.recording.recorder import Recorder
    from stewart63_ros.tools.play import Player
    bag = tmp_path / 'nsbag'
    rec = Recorder(bag, namespace='rig2', domain_id=ros.domain_id, fast_path=fast_path).start()
    try:
        assert rec.ready.is_set() and rec.fast_path == fast_path
        node = ros.node('src', namespace='rig2')
        _publish_when_matched(node, 'leg_lengths', 300)
        assert rec.wait_for_publishers(['leg_lengths'], 10)
        assert wait_until(lambda: rec.counts.get('/rig2/leg_lengths') == 300, 15), rec.counts
    finally:
        counts = rec.stop()
    assert counts['/rig2/leg_lengths'] == 300
    info = bagio.bag_info(bag)
    assert info['namespace'] == '/rig2' and list(info['topics']) == ['/rig2/leg_lengths']
    # relative names resolve under the recorded namespace; --namespace re-roots
    assert [bagio.header_stamp_ns(m) for _, _, m in bagio.read_messages(bag, ['leg_lengths'])] \
        == list(range(300))

    got = []
    probe = ros.node('probe')
    probe.create_subscription(JointState, '/rig3/leg_lengths', got.append, T.RECORD_SUB)
    player = Player(bag, topics=['leg_lengths'], namespace='rig3', rate=4.0,
                    domain_id=ros.domain_id).open()
    try:
        assert player.wait_for_subscribers(1, 15)
        th = threading.Thread(target=player.run)
        th.start()
        ros.spin_until(lambda: len(got) >= 300, 20)
        th.join(10)
    finally:
        player.request_stop()
        player.close()
    assert [m.header.stamp.nanosec for m in got] == list(range(300))


def test_player_start_offset_and_loop(recorded, ros):
    from sensor_msgs.msg import JointState

    from stewart63_ros import topics as T
    from stewart63_ros.tools.play import Player
    bag = recorded['bag']
    start = bagio.bag_info(bag)['start_ns']
    raw = [(ts, d) for _, _, ts, d in bagio.read_raw(bag, ['leg_lengths'])]
    got = []
    probe = ros.node('probe')
    probe.create_subscription(JointState, 'leg_lengths', got.append, T.RECORD_SUB, raw=True)

    def play(offset_before_end, **kw):
        """Play the last ``offset_before_end`` s of the bag; returns what should come."""
        offset = (raw[-1][0] - start) * 1e-9 - offset_before_end
        want = [d for ts, d in raw if ts >= start + int(offset * 1e9)]
        got.clear()
        # the test's own context: same participant, no discovery delay
        player = Player(bag, topics=['leg_lengths'], context=ros.rc.context,
                        start_offset=offset, **kw).open()
        assert player.wait_for_subscribers(1, 15)
        th = threading.Thread(target=player.run)
        th.start()
        return player, th, want

    player, th, want = play(0.4, rate=2.0)
    try:
        ros.spin_until(lambda: not th.is_alive() and len(got) >= len(want), 30)
    finally:
        player.request_stop()
        th.join(5)
        player.close(ack_timeout=1.0)
    assert 100 < len(want) < N and got == want

    player, th, want = play(0.2, loop=True)
    try:
        ros.spin_until(lambda: len(got) >= 2 * len(want) + 5, 30)
    finally:
        player.request_stop()
        th.join(5)
        player.close(ack_timeout=1.0)
    n = len(want)
    assert len(got) >= 2 * n + 5 and got[:n] == want and got[n:2 * n] == want


def test_recorder_discovers_late_topic_of_unknown_type(ros, tmp_path):
    """A topic outside the rig's (type unknown in advance) is subscribed once
    its publisher appears, after the recorder started."""
    from std_msgs.msg import String

    from stewart63_ros.recording.recorder import Recorder
    bag = tmp_path / 'late'
    rec = Recorder(bag, ['leg_lengths', 'extra'], domain_id=ros.domain_id,
                   discovery_period=0.1).start()
    try:
        time.sleep(0.3)
        node = ros.node('late')
        pub = node.create_publisher(String, 'extra', 10)
        assert wait_until(lambda: '/extra' in rec.publisher_counts(), 15)
        _publish_when_matched(node, 'extra', 20, String)
        assert wait_until(lambda: rec.counts.get('/extra') == 20, 15), rec.counts
        node.destroy_publisher(pub)
    finally:
        rec.stop()
    msgs = [m.data for _, _, m in bagio.read_messages(bag, ['extra'])]
    assert msgs == [f'm{k}' for k in range(20)]


def test_a_message_before_its_publisher_is_known_still_reads_back(ros, tmp_path):
    """A first message can arrive before the recorder's graph shows who sent
    it (the reader's match comes first). The topic's QoS in the MCAP channel
    and in metadata.yaml must then still agree: a reader pairs the two by it,
    and finds none of the topic's messages where they differ."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from rclpy.serialization import serialize_message

    from stewart63_ros import topics as T
    from stewart63_ros.recording.recorder import Recorder
    bag = tmp_path / 'early'
    rec = Recorder(bag, ['leg_setpoint'], domain_id=ros.domain_id).open()
    try:
        first = serialize_message(DiagnosticArray(status=[DiagnosticStatus(name='early')]))
        rec._subscribe('/early', 'diagnostic_msgs/msg/DiagnosticArray')
        rec._on_message('/early', first, None)          # as taken from the middleware
        node = ros.node('late_in_the_graph')
        pub = node.create_publisher(DiagnosticArray, '/early', T.DIAGNOSTICS_QOS)
        assert wait_until(lambda: rec.publisher_counts(['/early'])['/early'] >= 1
                          and pub.get_subscription_count() >= 1, 15)
        pub.publish(DiagnosticArray(status=[DiagnosticStatus(name='later')]))
        assert wait_until(lambda: (rec.spin_once(0.05), rec.counts['/early'] >= 2)[1], 15), \
            rec.counts
    finally:
        rec.close()
    names = [s.name for _, _, m in bagio.read_messages(bag, ['/early']) for s in m.status]
    assert names == ['early', 'later'], names


def test_commands_from_volatile_and_latched_publishers_are_recorded_once_each(ros, tmp_path):
    """``ros2 topic pub`` publishes volatile: a latched-only subscription would
    never match it. The recorder takes every command, once, from either kind."""
    from geometry_msgs.msg import PoseStamped
    from rclpy.qos import DurabilityPolicy, QoSProfile

    from stewart63_ros import topics as T
    from stewart63_ros.recording.recorder import Recorder
    bag = tmp_path / 'commands'
    rec = Recorder(bag, ['pose_setpoint'], domain_id=ros.domain_id).start()
    try:
        node = ros.node('commander')
        volatile = node.create_publisher(
            PoseStamped, 'pose_setpoint',
            QoSProfile(depth=10, durability=DurabilityPolicy.VOLATILE))
        latched = node.create_publisher(PoseStamped, 'pose_setpoint', T.SETPOINT_QOS)
        # Both sides of each match: a sample sent while only the publisher
        # knows the recorder is lost to it (a volatile reader's late match).
        assert wait_until(lambda: volatile.get_subscription_count() >= 1
                          and latched.get_subscription_count() >= 2
                          and rec.publisher_counts(['pose_setpoint'])['/pose_setpoint'] >= 2,
                          15), rec.publisher_counts()
        for k, pub in enumerate((volatile, latched, volatile, latched)):
            msg = PoseStamped()
            msg.header.stamp.sec = k
            msg.pose.orientation.w = 1.0
            pub.publish(msg)
        assert wait_until(lambda: rec.counts.get('/pose_setpoint') == 4, 15), rec.counts
        time.sleep(0.5)          # a duplicate would come within this
    finally:
        rec.stop()
    stamps = [bagio.header_stamp_ns(m) for _, _, m in bagio.read_messages(bag, ['pose_setpoint'])]
    assert stamps == [k * 1_000_000_000 for k in range(4)]


# ------------------------------------------------------------------ bad input


def _bad_copies(src: Path, tmp: Path) -> dict[str, Path]:
    out = {}
    for kind in ('truncated', 'corrupt', 'badyaml', 'nomcap'):
        dst = tmp / kind
        shutil.copytree(src, dst)
        out[kind] = dst
    mcap = lambda d: next(d.glob('*.mcap'))  # noqa: E731
    f = mcap(out['truncated'])
    os.truncate(f, f.stat().st_size // 2)
    # Overwrite the middle of the largest chunk: message records. (The message
    # index records between chunks are redundant for every reader we know of,
    # so damage there is harmless, and a blind offset sometimes hit them.)
    f = mcap(out['corrupt'])
    with f.open('rb') as fh:
        chunk = max(make_reader(fh).get_summary().chunk_indexes, key=lambda c: c.chunk_length)
    with f.open('r+b') as fh:
        fh.seek(chunk.chunk_start_offset + chunk.chunk_length // 2 - 2048)
        fh.write(b'\xff' * 4096)
    (out['badyaml'] / 'metadata.yaml').write_text('rosbag2_bagfile_information: [[[\n')
    mcap(out['nomcap']).unlink()
    notbag = tmp / 'notbag'
    notbag.mkdir()
    (notbag / 'x.txt').write_text('hello')
    out['notbag'] = notbag
    plain = tmp / 'plain.csv'
    plain.write_text('t,x\n0,1\n')
    out['file'] = plain
    out['missing'] = tmp / 'does-not-exist'
    return out


def test_bad_inputs_give_one_line_errors_and_touch_nothing(recorded, ros, tmp_path):
    bad = _bad_copies(recorded['bag'], tmp_path)
    before = {k: sha(p) for k, p in bad.items() if p.exists()}
    for path in bad.values():
        with pytest.raises(BagError):
            list(bagio.read_messages(path))
        with pytest.raises(BagError):
            bagruns.trajectory_from_bag(path)
    procs = {kind: ros.spawn(cli('play') + [str(path), '--wait-subscribers', '0'],
                             name=f'play-{kind}') for kind, path in bad.items()}
    # a topic the bag does not have
    with pytest.raises(BagError, match='not in the bag'):
        list(bagio.read_messages(recorded['bag'], ['nope']))
    procs['topic'] = ros.spawn(cli('play') + [str(recorded['bag']), '--topics', 'nope'],
                               name='play-topic')
    # record never writes into an existing path (directory or file)
    existing = tmp_path / 'existing'
    existing.mkdir()
    (existing / 'keep.txt').write_text('keep')
    procs['rec-dir'] = ros.spawn(cli('record') + [str(existing)], name='rec-dir')
    procs['rec-file'] = ros.spawn(cli('record') + [str(bad['file'])], name='rec-file')
    procs['recover-notbag'] = ros.spawn(cli('record') + ['--recover', str(bad['notbag'])],
                                        name='recover-notbag')
    for kind, proc in procs.items():
        assert proc.wait(60) == 2, proc.describe()   # an input error
        err = [line for line in proc.stderr().splitlines() if line.strip()]
        assert len(err) == 1 and ': error: ' in err[0], (kind, proc.describe())
    assert 'exists already' in procs['rec-dir'].stderr()
    assert 'not in the bag' in procs['topic'].stderr()
    assert sorted(p.name for p in existing.iterdir()) == ['keep.txt']
    assert {k: sha(p) for k, p in bad.items() if p.exists()} == before


def test_what_never_reached_the_recorder_is_counted_and_reported(ros, tmp_path, monkeypatch):
    """A recorder that cannot keep up (here: its queue cut to 10 messages, and
    not taking while 100 arrive) loses messages; the loss is counted per
    topic from the publisher's sequence numbers, said on /diagnostics (WARN)
    and in its closing line, and the bag's metadata counts what it holds."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from rclpy.duration import Duration
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState

    from stewart63_ros import topics as T
    from stewart63_ros.recording.recorder import Recorder
    monkeypatch.setattr(T, 'RECORD_SUB', QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                                                    reliability=ReliabilityPolicy.RELIABLE))
    bag = tmp_path / 'lossy'
    rec = Recorder(bag, ['leg_lengths'], domain_id=ros.domain_id).open()
    statuses = []
    try:
        node = ros.node('fast_sender')
        pub = node.create_publisher(JointState, 'leg_lengths', T.STREAM_PUB)
        node.create_subscription(DiagnosticArray, '/diagnostics',
                                 lambda m: statuses.extend(m.status), T.DIAGNOSTICS_QOS)
        assert wait_until(lambda: rec.matched(['leg_lengths'])
                          and pub.get_subscription_count() >= 1, 15)

        def sample(k):
            msg = JointState(name=['leg_%d' % i for i in range(1, 7)], position=[1.5] * 6)
            msg.header.stamp.sec = k
            return msg
        pub.publish(sample(0))
        assert wait_until(lambda: (rec.spin_once(0.05), rec.counts['/leg_lengths'] == 1)[1], 15)
        for k in range(1, 101):
            pub.publish(sample(k))
        assert pub.wait_for_all_acked(Duration(seconds=15))    # delivered, queue overflowed
        rec.take_available()
        assert rec.counts['/leg_lengths'] == 11, rec.counts
        assert rec.lost == {'/leg_lengths': 90}, rec.lost
        assert ros.spin_until(lambda: rec.take_available() is not None and any(
            s.level == DiagnosticStatus.WARN
            and any(kv.key == 'lost//leg_lengths' and kv.value == '90' for kv in s.values)
            for s in statuses), 15), statuses[-1:]
        assert 'LOST (never reached the recorder): /leg_lengths 90' in rec.summary()
    finally:
        rec.close()
    assert bagio.bag_info(bag)['topics']['/leg_lengths'][1] == 11
