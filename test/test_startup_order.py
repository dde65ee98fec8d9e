"""What ``rig`` tells its plant to wait for before the first sample
(runtime/startup.py), checked through the rig's own parameter file."""
from __future__ import annotations

import yaml

from stewart63_ros.runtime.handshake import plant_startup_parameters, recorder_waits_for
from stewart63_ros.tools.rig_process import Rig


def test_a_recording_lockstep_rig_holds_its_plant_for_fk_and_the_recorder():
    params = plant_startup_parameters(('plant', 'controller', 'fk'), True, 'lockstep', False)
    assert params == {'lengths_subscribers': 3, 'lengths_peers': ['controller', 'fk'],
                      'lockstep_peers': ['fk', 'record']}


def test_composed_and_realtime_rigs_have_no_lockstep_peers():
    for mode, compose in (('lockstep', True), ('realtime', False)):
        params = plant_startup_parameters(('plant', 'controller', 'fk'), True, mode, compose)
        assert 'lockstep_peers' not in params


def test_a_plant_whose_controller_runs_elsewhere_waits_for_it_too():
    params = plant_startup_parameters(('plant',), False, 'lockstep', False)
    assert params['lengths_subscribers'] == 1 and params['lengths_peers'] == ['controller']
    assert params['lockstep_peers'] == []
    assert recorder_waits_for(('plant',)) == []
    assert recorder_waits_for(('controller', 'fk')) == ['leg_forces', 'platform_pose']


def test_the_rigs_parameter_file_carries_them_to_the_plant(tmp_path):
    from stewart63_ros.paths import default_params_path
    rig = Rig(default_params_path(), record=tmp_path / 'bag', log_dir=tmp_path / 'logs')
    doc = yaml.safe_load(rig.overlay().read_text())
    plant = doc['/**/plant']['ros__parameters']
    assert plant['lockstep_peers'] == ['fk', 'record'] and plant['lengths_subscribers'] == 3
    assert doc['/**']['ros__parameters']['wait_for_subscribers'] == 1


READER = r'''
import sys, time
import rclpy
from sensor_msgs.msg import JointState
from stewart63_ros import topics
rclpy.init()
node = rclpy.create_node('late_reader')
got = []
node.create_subscription(JointState, 'race', lambda m: got.append(m.header.frame_id),
                         topics.EVERY_SUB)
print('SUBSCRIBED', flush=True)
deadline = time.monotonic() + 30
while time.monotonic() < deadline and 'last' not in got:
    rclpy.spin_once(node, timeout_sec=0.05)
print('GOT ' + ','.join(got), flush=True)
'''


def test_a_reader_that_matches_after_the_first_message_still_gets_it(ros):
    """The race the fixed settles (``discovery_settle``, a match's 1 s) were
    kept for: a publisher counts a subscription as matched as soon as it has
    discovered it, and sends its first message at once, possibly before
    the reader has discovered the publisher in turn. With the rig's QoS and
    its Fast DDS profile (heartbeat 50 ms) the writer then repairs it: every
    reader gets every message from the first, so the start-up waits for
    matches, not for a clock. (The recorder still says it has matched,
    ``matched_publishers``: its bag must hold every message from the first
    even if a publisher's first messages outrun its side of the match.)"""
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Header

    from stewart63_ros import topics
    from stewart63_ros.middleware import use_rig_profile
    assert use_rig_profile()        # this process's writer too (set before its participant)
    node = ros.node('race_writer')
    pub = node.create_publisher(JointState, 'race', topics.STREAM_PUB)
    burst = 50
    for trial in range(2):
        readers = [ros.python('-c', READER, name='reader%d_%d' % (trial, k)) for k in range(3)]
        assert ros.spin_until(lambda: pub.get_subscription_count() >= 3, 60), \
            [r.describe() for r in readers]
        # at once: the readers' side of the match may not be complete yet
        for k in range(burst):
            pub.publish(JointState(header=Header(frame_id='first' if k == 0 else str(k))))
        pub.publish(JointState(header=Header(frame_id='last')))
        for reader in readers:
            assert reader.wait(60) == 0, reader.describe()
            got = reader.stdout().split('GOT ')[-1].split()[0].split(',')
            assert got[0] == 'first' and len(got) == burst + 1, (got[:3], len(got))
        assert ros.spin_until(lambda: pub.get_subscription_count() == 0, 30)


NOTING_RECORDER = r'''
import sys, time
from stewart63_ros.runtime import recorders
path = recorders.announce('/rig7/record', 77)
print('NOTED', flush=True)
time.sleep(60)
'''


def test_a_recorder_running_here_is_known_on_its_domain_until_it_ends(tmp_path, monkeypatch):
    """runtime/recorders.py: what a starting node learns before discovery
    shows a recorder started before it (a live process, its domain, this
    network namespace); a recorder killed without withdrawing its note is
    not waited for, and its note goes."""
    import subprocess
    import sys

    from stewart63_ros.runtime import recorders
    monkeypatch.setenv('XDG_RUNTIME_DIR', str(tmp_path))
    proc = subprocess.Popen([sys.executable, '-c', NOTING_RECORDER], stdout=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout.readline().strip() == 'NOTED'
        assert recorders.running(77) == ['/rig7/record']
        assert recorders.running(78) == []
        own = recorders.announce('/me/record', 77)       # this process's own: not waited for
        assert recorders.running(77) == ['/rig7/record']
        recorders.withdraw(own)
    finally:
        proc.kill()
        proc.wait(10)
    assert recorders.running(77) == []
    assert list(recorders.notes_dir().iterdir()) == []


class _Pub:
    def __init__(self, topic):
        self.topic_name = topic


class _Info:
    def __init__(self, node):
        self.node_namespace, _, self.node_name = node.rpartition('/')
        self.node_namespace = self.node_namespace or '/'


def test_a_node_waits_for_each_recorder_on_every_topic_it_records():
    """StartupBarrier.recorders_missing: a recorder noted running here is
    waited for before discovery shows it; then on each of the node's topics
    it records (its status's ``recorded/`` keys) the graph must show its
    subscription, so that the writer's own count holds it, and it must name
    the node on each of them (``matched_publishers/<topic>``: its side of
    the match; a recorder that named it matched from a partial graph lost
    410 lockstep forces at -n 2)."""
    from stewart63_ros.runtime.handshake import RecorderWord
    from stewart63_ros.runtime.startup import StartupBarrier

    class Node:
        def get_fully_qualified_name(self):
            return '/fk'
    word = RecorderWord.__new__(RecorderWord)
    word.matched, word.recorded, word.matched_on = {}, {}, {}
    barrier = StartupBarrier(Node(), word)
    pubs = [_Pub('/platform_pose'), _Pub('/diagnostics')]
    graph = {'/platform_pose': [], '/diagnostics': []}
    barrier.graph_subscriptions = lambda pub: [_Info(n) for n in graph[pub.topic_name]]
    noted = ['/record']
    assert barrier.recorders_missing(pubs, noted) == [
        '/record (recording on this machine) to say what it records']
    word.matched['/record'] = {''}
    word.recorded['/record'] = {'/platform_pose', '/diagnostics', '/leg_lengths'}
    assert barrier.recorders_missing(pubs, noted) == [
        '/diagnostics: the subscription of /record', '/platform_pose: the subscription of /record',
        '/record to match /fk on /diagnostics, /platform_pose']
    graph['/platform_pose'] = ['/record']
    graph['/diagnostics'] = ['/record', '/plant']
    # its graph showed fk's status publisher only: named on that alone, not enough
    word.matched['/record'] = {'/plant', '/fk'}
    word.matched_on['/record'] = {'/diagnostics': {'/plant', '/fk'}}
    assert barrier.recorders_missing(pubs, noted) == ['/record to match /fk on /platform_pose']
    word.matched_on['/record']['/platform_pose'] = {'/fk'}
    assert barrier.recorders_missing(pubs, noted) == []
    # one the graph shows but that has not spoken is no recorder (a viewer)
    graph['/platform_pose'] = ['/record', '/view']
    assert barrier.recorders_missing(pubs, []) == []
