"""The runtime under the nodes, against small fakes: no DDS, no processes,
milliseconds a test (the rig tests check the same over DDS, in seconds).

- the hot loop (runtime/hotloop.py): side subscriptions, timers and executor
  turns between two 1 kHz messages, an outer loop's pace;
- the start-up barrier (runtime/startup.py): no first message before the
  subscribers matched, bounded by discovery_timeout;
- the lockstep window (runtime/lockstep.py, PeerWindow): the plant waits for a
  slow peer, drops a silent or vanished one;
- the flush at stop (runtime/stopping.py): done on the recorder's word, on the
  acknowledgements, or at the timeout;
- the source watch (runtime/sources.py): two publishers on one input, restarts;
- the handshake (runtime/handshake.py): its words and the plant's start-up keys.

The skip counter (runtime/checks.py) and the stamp gate have theirs in
test_load.py and test_sources.py.
"""
from __future__ import annotations

import contextlib
import time
from types import SimpleNamespace

import pytest
from test_sources import Clock, feed

from stewart63_ros import topics
from stewart63_ros.runtime import handshake, hotloop, lockstep, sources, startup, stopping
from stewart63_ros.runtime.checks import Rejected, StampGate
from stewart63_ros.runtime.launcher import STOP

MS = 1_000_000          # ns


# -- fakes --------------------------------------------------------------------------------
class Log:
    def __init__(self):
        self.lines = []

    def info(self, text):
        self.lines.append(('info', text))

    def warning(self, text):
        self.lines.append(('warning', text))

    def error(self, text):
        self.lines.append(('error', text))


class Health:
    def __init__(self):
        self.values = {}
        self.fault = ''
        self.warning = ''
        self.collision = ''
        self.source_warning = ''
        self.reports = 0
        self.status_name = 'stewart63/a/fk'
        self.pub = Pub('/diagnostics')

    def report(self):
        self.reports += 1


class Pub:
    """A publisher: how many subscriptions it matched, whether they acknowledged."""

    def __init__(self, topic, matched=0, acked=True):
        self.topic_name = topic
        self.matched = matched
        self.acked = acked
        self.destroyed = False
        self.msg_type = SimpleNamespace  # graph_subscriptions is faked below

    def get_subscription_count(self):
        if self.destroyed:
            raise RuntimeError('InvalidHandle')
        return self.matched

    def wait_for_all_acked(self, _timeout):
        if self.destroyed:
            raise RuntimeError('InvalidHandle')
        return self.acked


class Sub:
    def __init__(self, topic, callback=None, publishers=1):
        self.topic_name = topic
        self.callback = callback
        self.publishers = publishers
        self.queue = []

    def get_publisher_count(self):
        return self.publishers


class Node:
    """What the runtime modules use of a RigNode."""

    def __init__(self):
        self.health = Health()
        self.log = Log()
        self.subscriptions = []
        self.timers = []
        self.started = False
        self.closing = False
        self.data_publishers = []
        self.optional_publishers = set()
        self.created = time.monotonic()
        self.wait_for_subscribers = 1
        self.discovery_settle = 0.0
        self.discovery_timeout = 1.0
        self.spins = 0
        self.on_spin = None
        self.executor_ = SimpleNamespace(spin_once=self._spin_once)
        self.after_batch = None
        self.publishers = []

    def _spin_once(self, timeout_sec=0.0):
        self.spins += 1
        if self.on_spin is not None:
            self.on_spin()

    def get_logger(self):
        return self.log

    def get_fully_qualified_name(self):
        return '/a/fk'

    def create_subscription(self, _type, topic, callback, _qos, raw=False):
        sub = Sub(topic, callback)
        self.subscriptions.append(sub)
        return sub

    def create_timer(self, period, callback):
        self.timers.append((period, callback))

    def create_publisher(self, _type, topic, _qos):
        pub = Pub(topic)
        pub.sent = []
        pub.publish = lambda msg: pub.sent.append((msg.sec, msg.nanosec))
        self.publishers.append(pub)
        return pub

    def get_subscriptions_info_by_topic(self, _topic):
        return []

    def get_publishers_info_by_topic(self, _topic):
        return []

    def resolve_topic_name(self, topic):
        return '/a/' + topic


@pytest.fixture
def stop_flag():
    """STOP (the process's stop signals) as a test left it: restored after."""
    saved = STOP.requested, STOP.interruptible
    yield STOP
    STOP.requested, STOP.interruptible = saved


# -- the lockstep window ------------------------------------------------------------------
def window(peers=('/a/fk', '/a/record'), size=2, timeout=10.0):
    node = Node()
    return node, lockstep.PeerWindow(node, list(peers), size, MS, timeout)


def bounded(serve=lambda timeout: time.sleep(timeout), calls=1000):
    """``serve`` for PeerWindow.hold that fails the test past ``calls`` calls
    (a hold that never ends)."""
    count = [0]

    def wrapped(timeout):
        count[0] += 1
        assert count[0] <= calls, 'the plant still waits after %d calls' % calls
        serve(timeout)
    return wrapped


def progress(peer_window, peer, ns):
    sub = peer_window.subs[peer]
    sub.callback(SimpleNamespace(sec=ns // 10**9, nanosec=ns % 10**9))


def test_peer_window_lets_the_plant_run_a_window_ahead_of_the_slowest_peer():
    node, peers = window()
    assert [s.topic_name for s in node.subscriptions] == [
        '/a/fk/lockstep_progress', '/a/record/lockstep_progress']
    served = []
    assert peers.hold(1 * MS, served.append)        # samples 0 and 1: before any progress
    progress(peers, '/a/fk', 5 * MS)
    progress(peers, '/a/record', 3 * MS)
    assert peers.hold(5 * MS, served.append)        # the slowest (3) is 2 behind 5
    assert served == [] and peers.holds == 0

    def record_catches_up(_timeout):
        served.append(_timeout)
        progress(peers, '/a/record', 3 * MS + len(served) * MS)
    assert peers.hold(7 * MS, record_catches_up)    # waits until /a/record handled 5
    assert peers.progress['/a/record'] == 5 * MS
    assert len(served) == 2 and peers.holds == 1
    assert node.health.values['lockstep_held_samples'] == 1
    assert peers.dropped == {} and node.health.fault == ''


def test_peer_window_drops_a_peer_that_makes_no_progress():
    node, peers = window(timeout=0.005)
    progress(peers, '/a/record', 100 * MS)
    started = time.monotonic()
    assert peers.hold(10 * MS, bounded())
    assert time.monotonic() - started < 1.0
    assert list(peers.dropped) == ['/a/fk']
    assert 'lockstep_peer_timeout' in peers.dropped['/a/fk']
    assert '/a/fk' in node.health.fault and '/a/fk' in node.health.values[
        'lockstep_peers_dropped']
    assert node.log.lines[-1][0] == 'error'
    # no longer waited for: the next samples pass at once
    assert peers.active == ['/a/record']
    assert peers.hold(50 * MS, pytest.fail)


def test_peer_window_names_a_missing_publisher_and_drops_one_that_left():
    node, peers = window(timeout=60.0)
    peers.subs['/a/fk'].publishers = 0
    assert peers.missing_publishers() == [
        '/a/fk/lockstep_progress: no progress publisher matched yet (lockstep_peers)']
    progress(peers, '/a/record', 100 * MS)
    assert peers.hold(10 * MS, bounded(calls=5))    # no wait for the timeout
    assert 'left the ROS graph' in peers.dropped['/a/fk']


def test_peer_window_stops_waiting_on_a_stop(stop_flag):
    _, peers = window()

    def stop(_timeout):
        stop_flag.requested = True
    assert peers.hold(10 * MS, stop) is False


def fk_progress(clock=time.monotonic):
    """An fk as far as lockstep goes: its progress publisher, and ``serve(k)``,
    sample k handled whichever path took it (on_sample's ``note``)."""
    fk = Node()
    fk.progress = lockstep.ProgressPublisher(fk)
    fk.progress.clock = clock
    fk.after_batch = fk.progress.publish
    fk.serve = lambda k: fk.progress.note(k * MS)
    return fk, fk.progress.pub.sent


def test_peer_window_ends_the_run_only_once_every_peer_handled_the_last_sample():
    """The plant's exit ends a rig (rig stops the others): a peer still a
    window behind would be stopped with samples its reader acknowledged and
    it never handled (a late fk: 670 of 801 poses)."""
    node, peers = window(size=200)
    progress(peers, '/a/fk', 900 * MS)
    progress(peers, '/a/record', 1000 * MS)
    assert peers.hold(1000 * MS, pytest.fail)       # the last sample goes out at once

    def fk_catches_up(_timeout):
        progress(peers, '/a/fk', peers.progress['/a/fk'] + 25 * MS)
    assert peers.drain(1000 * MS, bounded(fk_catches_up))
    assert peers.progress['/a/fk'] == 1000 * MS and peers.dropped == {}


def test_fk_reports_the_samples_its_start_up_wait_served():
    """The stall of a loaded rig (fk dropped after lockstep_peer_timeout, the
    plant holding one sample): fk's executor turns in its start-up wait
    served all the plant may send (a window's worth) and said nothing; its
    hot loop then waits for a next sample the plant holds until it does."""
    fk, sent = fk_progress()
    fk.discovery_timeout = 5.0
    fk.data_publishers = [Pub('/a/platform_pose', 0)]
    fk.health.pub = Pub('/diagnostics', 1)
    gate = startup.StartupBarrier(fk, SimpleNamespace(matched={}, recorded={}))
    gate.MATCH_SETTLE = 0.0
    size = 3

    def turn():     # each turn serves one sample; fk's subscribers match at the last
        fk.serve(fk.spins - 1)
        if fk.spins == size:
            fk.data_publishers[0].matched = 1
    fk.on_spin = turn
    assert gate.wait() is True
    assert sent and sent[-1] == (0, (size - 1) * MS)     # samples 0..2 handled, and said
    plant, peers = window(peers=['/a/fk'], size=size - 1)
    for sec, nanosec in sent:           # the plant's progress subscription takes them
        peers.subs['/a/fk'].callback(SimpleNamespace(sec=sec, nanosec=nanosec))
    assert peers.hold(size * MS, pytest.fail)           # sample 3 goes out at once


def test_fk_hot_loop_reports_a_sample_an_executor_turn_served(loop_node, monkeypatch):
    node, hot, _ = loop_node
    fk, sent = fk_progress()
    node.after_batch = fk.after_batch
    node.wait_for_matches = lambda: True
    monkeypatch.setattr('rclpy.ok', lambda: True)
    polls = []

    def poll(_timeout):     # no sample comes: the plant holds for this one's report
        polls.append(_timeout)
        if len(polls) == 3:
            STOP.requested = True
        return False
    monkeypatch.setattr(hotloop, 'DirectTake', lambda _node, sub: SimpleNamespace(poll=poll))
    node.on_spin = lambda: node.spins == 1 and fk.serve(7)     # the turn takes sample 7
    node.run_on(hot, batch_period=0.005)
    assert node.spins == 1 and sent == [(0, 7 * MS)]


def test_progress_unchanged_is_said_again_every_resend_period():
    """A progress message lost, or sent before fk's writer had matched the
    plant's reader, is not the last word: the plant would hold for it."""
    now = [0.0]
    fk, sent = fk_progress(clock=lambda: now[0])
    fk.after_batch()
    assert sent == []                   # nothing handled: nothing to say
    fk.serve(4)
    fk.after_batch()
    fk.after_batch()
    assert sent == [(0, 4 * MS)]        # said once per change ...
    now[0] += 1.0                       # (RESEND_PERIOD: 0.1 s)
    fk.after_batch()
    assert sent == [(0, 4 * MS)] * 2    # ... and again while unchanged


# -- the flush at stop --------------------------------------------------------------------
def flushing(pubs, confirm_after=None):
    node = Node()
    node.data_publishers = pubs
    word = SimpleNamespace(confirmed=False, takes=0)

    def take_waiting():
        word.takes += 1
        if confirm_after is not None and word.takes >= confirm_after:
            word.confirmed = True
    word.take_waiting = take_waiting
    flush = stopping.Flush(node, word)
    flush.POLL = 0.001
    return flush, word


def test_flush_ends_when_every_subscriber_acknowledged():
    pub = Pub('leg_lengths', matched=1, acked=False)
    flush, _ = flushing([pub, Pub('leg_forces', matched=0, acked=False)])
    calls = []

    def recorder_in_this_thread():     # composed: the recorder takes its messages now
        calls.append(1)
        pub.acked = len(calls) >= 3
    flush.while_flushing = recorder_in_this_thread
    assert flush.flush(timeout=5.0) == 'acknowledged'
    assert len(calls) == 3


def test_flush_ends_on_the_recorders_confirmation():
    flush, word = flushing([Pub('leg_lengths', matched=1, acked=False)], confirm_after=2)
    assert flush.flush(timeout=5.0) == 'recorder'
    assert word.takes == 2


def test_flush_is_bounded_by_its_timeout_and_skips_destroyed_publishers():
    gone = Pub('platform_pose', matched=1, acked=False)
    gone.destroyed = True
    flush, _ = flushing([Pub('leg_lengths', matched=1, acked=False), gone])
    started = time.monotonic()
    assert flush.flush(timeout=0.02) == 'timeout'
    assert time.monotonic() - started < 1.0
    flush, _ = flushing([gone])
    assert flush.flush(timeout=5.0) == 'acknowledged'


# -- the start-up barrier -----------------------------------------------------------------
def barrier(matched=0):
    node = Node()
    node.data_publishers = [Pub('/a/platform_pose', matched), Pub('/a/markers', 0)]
    node.optional_publishers = {id(node.data_publishers[1])}
    node.health.pub = Pub('/diagnostics', 5)
    gate = startup.StartupBarrier(node, SimpleNamespace(matched={}, recorded={}))
    gate.MATCH_SETTLE = 0.0
    return node, gate


def test_startup_barrier_waits_for_the_subscribers_then_starts():
    node, gate = barrier()

    def recorder_matches():
        if node.spins == 3:
            node.data_publishers[0].matched = 1
    node.on_spin = recorder_matches
    assert gate.wait() is True
    assert node.started and node.spins == 3     # no first message before the match
    assert node.health.warning == ''
    assert node.log.lines[0][0] == 'info' and '/a/platform_pose: 0 of 1' in node.log.lines[0][1]


def test_a_node_takes_its_input_only_once_its_outputs_are_matched():
    """A node that answers samples subscribes to them as its wait ends
    (RigNode.subscribe_input), not before: samples served by its wait's
    executor turns were answered on writers a recorder had not matched. A
    second wait (run_on after the node's own) neither waits nor subscribes
    again."""
    node, gate = barrier()
    subscribed = []
    node.subscribe_input = lambda: subscribed.append((node.spins, node.started))

    def recorder_matches():
        if node.spins == 3:
            node.data_publishers[0].matched = 1
    node.on_spin = recorder_matches
    assert gate.wait() is True
    assert subscribed == [(3, True)]
    assert gate.wait() is True and subscribed == [(3, True)] and node.spins == 3


def test_a_lockstep_answer_to_a_new_source_waits_for_the_writers_side_of_the_match():
    """The controller's first answer to a plant went to a writer that had not
    discovered the plant's subscription yet (the plant's side had matched):
    sent to nobody, never repaired, the plant waiting 20 s for it. Now the
    first answer to each source waits until the graph shows the source's
    subscription and the writer has matched it; later answers do not wait."""
    node = Node()
    node.discovery_timeout = 5.0
    plant_gid = bytes(range(16))
    graph = {'subs': [], 'matched': 0, 'polls': 0}

    class Answers:
        topic_name = '/leg_forces'

        def get_subscription_count(self):
            graph['polls'] += 1
            if graph['polls'] == 5:     # discovery brings the plant's subscription
                graph['subs'] = [SimpleNamespace(node_namespace='/', node_name=n)
                                 for n in ('plant', 'record')]
            if graph['polls'] == 8:     # and the writer matches it
                graph['matched'] = 2
            return graph['matched']
    node.resolve_topic_name = lambda topic: '/' + topic.lstrip('/')
    node.get_publishers_info_by_topic = lambda topic: [
        SimpleNamespace(node_namespace='/', node_name='plant', endpoint_gid=list(plant_gid))]
    node.startup = SimpleNamespace(graph_subscriptions=lambda pub: graph['subs'])
    first = startup.FirstAnswer(node, Answers(), 'leg_lengths')
    assert first.missing(plant_gid) == '/leg_forces: the subscription of /plant'
    first.wait(plant_gid)
    assert graph['polls'] >= 8 and first.missing(plant_gid) == ''
    polls = graph['polls']
    first.wait(plant_gid)                       # the same source: no wait, no look
    assert graph['polls'] == polls
    assert node.log.lines[-1][0] == 'info' and 'waited' in node.log.lines[-1][1]


def test_startup_barrier_waits_for_what_else_is_missing():
    node, gate = barrier(matched=1)
    missing = ['a leg_forces publisher']
    node.on_spin = lambda: node.spins == 2 and missing.clear()
    assert gate.wait(lambda: missing) is True
    assert node.spins == 2


def test_startup_barrier_is_bounded_and_starts_anyway_with_a_warning():
    node, gate = barrier()
    node.discovery_timeout = 0.02
    started = time.monotonic()
    assert gate.wait() is False
    assert time.monotonic() - started < 1.0
    assert node.started
    assert node.health.warning == 'started before all subscribers matched'
    level, text = node.log.lines[-1]
    assert level == 'warning' and '/a/platform_pose: 0 of 1 subscriptions matched' in text


def test_startup_barrier_waits_for_a_recorder_to_name_the_node():
    node, gate = barrier(matched=1)
    pub = node.data_publishers[0]
    pub.msg_type = type('PoseStamped', (), {'__module__': 'geometry_msgs.msg._pose_stamped'})
    pub.qos_profile = topics.SETPOINT_QOS
    recorder = SimpleNamespace(topic_type='geometry_msgs/msg/PoseStamped', node_name='record',
                               node_namespace='/a', qos_profile=topics.SETPOINT_QOS)
    node.get_subscriptions_info_by_topic = lambda topic: (
        [recorder] if topic == pub.topic_name else [])
    gate.word.matched['/a/record'] = set()

    def recorder_says_matched():
        if node.spins == 2:
            gate.word.matched['/a/record'] = {'/a/fk', '/a/controller'}
    node.on_spin = recorder_says_matched
    assert gate.wait() is True
    assert node.spins == 2
    assert "/a/record to match /a/fk's publishers" in node.log.lines[0][1]


# -- the source watch ---------------------------------------------------------------------
def offer(gate, ns, source):
    """A sample through the gate as a node takes it; one refused (a second
    source) is dropped, as the node drops it."""
    with contextlib.suppress(Rejected):
        feed(gate, ns, source)


def watched(publishers=2):
    """(clock, gate, node, input subscription, SourceWatch) of one node's input."""
    clock = Clock()
    gate = StampGate(0.5, clock)
    node = Node()
    sub = Sub('/a/leg_lengths', publishers=publishers)
    return clock, gate, node, sub, sources.SourceWatch(node, sub, 'leg_lengths', gate)


def test_source_watch_reports_two_publishers_on_one_input_once_and_clears():
    clock, gate, node, sub, watch = watched()
    assert node.timers == [(watch.SOURCE_CHECK_PERIOD, watch.check)]
    node.started = True
    for k in range(5):
        clock.t += 0.001
        offer(gate, k * MS, b'A' * 16)
        offer(gate, k * MS + 1, b'B' * 16)
    watch.check()
    watch.check()
    h = node.health
    assert h.collision.startswith('collision: 2 publishers send on /a/leg_lengths')
    assert h.values['collisions'] == 1 and h.reports == 1   # once, not at every check
    assert [level for level, _ in node.log.lines] == ['error']
    # one source again: the collision ends after COLLISION_CLEAR_AFTER
    watch.COLLISION_CLEAR_AFTER = 0.0
    clock.t += 2.0
    offer(gate, 10 * MS, b'A' * 16)
    sub.publishers = 1
    watch.check()
    watch.check()
    assert h.collision == '' and h.values['collisions'] == 1
    assert 'collision over' in node.log.lines[-1][1]


def test_source_watch_counts_restarts_and_warns_of_a_silent_second_publisher():
    clock, gate, node, sub, watch = watched()
    offer(gate, 5 * MS, b'A' * 16)
    clock.t += 2.0                      # the plant restarted: its stamps begin again
    offer(gate, 0, b'A' * 16)
    watch.check()
    assert node.health.values['source_restarts'] == 1
    assert node.health.collision == ''
    assert node.health.source_warning.startswith('2 publishers matched on /a/leg_lengths, '
                                                 'one sends')


# -- the hot loop -------------------------------------------------------------------------
class LoopNode(hotloop.HotLoop, Node):
    pass


@pytest.fixture
def loop_node(monkeypatch, stop_flag):
    """A node with a hot subscription and a side one; ``take`` and the timers faked."""
    node = LoopNode()
    hot = Sub('/a/leg_lengths', callback=lambda msg: None)
    side = Sub('/a/leg_setpoint', callback=lambda msg: node.taken.append(msg))
    node.subscriptions = [hot, side]
    node.taken = []
    node.due_timers = []
    monkeypatch.setattr(hotloop, 'take', lambda sub: sub.queue.pop(0) if sub.queue else None)
    monkeypatch.setattr(hotloop, 'DirectTake', lambda _node, sub: ('direct', sub))

    def run_timer_if_ready(timer):
        if timer in node.due_timers:
            node.due_timers.remove(timer)
            timer.runs += 1
            return True
        return False
    monkeypatch.setattr(hotloop, 'run_timer_if_ready', run_timer_if_ready)
    # the collector's view of the heap is frozen at the start (a full
    # collection of a loaded process would take the test 0.7 s: recorded only)
    node.gc = []
    monkeypatch.setattr(hotloop, 'gc', SimpleNamespace(collect=lambda: node.gc.append('collect'),
                                                       freeze=lambda: node.gc.append('freeze')))
    yield node, hot, side


def timer(left_s):
    return SimpleNamespace(runs=0, time_until_next_call=lambda: int(left_s * 1e9))


def test_hot_loop_serves_side_subscriptions_timers_and_the_executor_between_messages(loop_node):
    node, hot, side = loop_node
    status = timer(0.05)
    node.timers = [status]
    assert node.start_hot_loop(hot) == ('direct', hot)
    assert node.gc == ['freeze']      # no 20-40 ms collection in the loop, none at start
    assert STOP.interruptible is False          # from here a stop is a flag the loop reads
    side.queue.append('setpoint')
    now = time.monotonic()
    wake = node.housekeeping(now)
    assert node.taken == ['setpoint']            # a command is served between two samples
    assert node.spins == 1                       # nothing due: the executor's turn
    assert now < wake <= now + 0.06              # the loop wakes for the timer's next call
    node.due_timers.append(status)
    node.housekeeping(wake + 0.001)
    assert status.runs == 1 and node.spins == 1  # a due timer instead of an executor turn
    later = time.monotonic() + node.EXECUTOR_PERIOD + 0.01
    node.housekeeping(later)
    assert node.spins == 2                       # parameter services: at least every 0.1 s


def test_hot_loop_puts_off_a_turn_when_short_of_time(loop_node):
    node, hot, _ = loop_node
    node.start_hot_loop(hot)
    now = time.monotonic()
    node.housekeeping(now)
    assert node.spins == 1
    node._next_turn = now + 0.001
    node.housekeeping(now + 0.002, turn_ok=False)
    assert node.spins == 1                       # put off ...
    node.housekeeping(now + 0.2, turn_ok=False)
    assert node.spins == 2                       # ... by 0.1 s at most


def test_hot_loop_driven_by_an_outer_loop_keeps_its_pace(loop_node):
    node, hot, side = loop_node
    outer = SimpleNamespace(side_period=0.01, started=[])
    outer.start = lambda own: outer.started.append(own) or 'outer poll'
    node.drive_by(outer)
    assert node.start_hot_loop(hot) == 'outer poll'
    assert outer.started == [('direct', hot)]
    now = time.monotonic()
    wake = node.housekeeping(now)
    assert wake <= now + 0.01
    side.queue.append('setpoint')
    assert node.housekeeping(now + 0.001) == wake and node.taken == []   # not yet
    node.housekeeping(wake)
    assert node.taken == ['setpoint']


def test_hot_loop_start_honours_a_stop_that_came_first(loop_node):
    node, hot, _ = loop_node
    STOP.requested = True
    with pytest.raises(KeyboardInterrupt):
        node.start_hot_loop(hot)


# -- the handshake ------------------------------------------------------------------------
def test_handshake_final_counts_read_a_nodes_last_status():
    assert handshake.final_counts({'final': 'true', 'final/leg_lengths': '1000',
                                   'final/leg_forces': '999', 'other': '3'}) == {
        'leg_lengths': 1000, 'leg_forces': 999}
    assert handshake.final_counts({'final/leg_lengths': '1000'}) is None


@pytest.mark.parametrize('nodes,record,mode,compose,want', [
    (('plant', 'controller', 'fk'), True, 'lockstep', False,
     {'lengths_subscribers': 3, 'lengths_peers': ['controller', 'fk'],
      'lockstep_peers': ['fk', 'record']}),
    (('plant', 'controller', 'fk'), True, 'lockstep', True,
     {'lengths_subscribers': 3, 'lengths_peers': ['controller', 'fk']}),
    (('plant', 'fk'), False, 'realtime', False,
     {'lengths_subscribers': 2, 'lengths_peers': ['controller', 'fk']}),
    (('plant', 'controller'), False, 'lockstep', False,
     {'lengths_subscribers': 1, 'lengths_peers': ['controller'], 'lockstep_peers': []}),
])
def test_handshake_the_plant_waits_for_every_reader_of_its_samples(nodes, record, mode,
                                                                    compose, want):
    assert handshake.plant_startup_parameters(nodes, record, mode, compose) == want


def test_handshake_recorder_waits_for_the_publishers_run_here():
    assert handshake.recorder_waits_for(('plant', 'controller', 'fk')) == [
        topics.LEG_FORCES, topics.PLATFORM_POSE]
    assert handshake.recorder_waits_for(('plant',)) == []


def diagnostics(name, **values):
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from rclpy.serialization import serialize_message
    msg = DiagnosticArray(status=[DiagnosticStatus(
        name=topics.STATUS_PREFIX + name,
        values=[KeyValue(key=k, value=v) for k, v in values.items()])])
    return serialize_message(msg)


def test_handshake_recorder_word_hears_matched_and_confirms_at_the_right_time():
    node = Node()
    word = handshake.RecorderWord(node)
    assert node.subscriptions == [word.sub] and word.sub.topic_name == topics.DIAGNOSTICS
    word.on_status(diagnostics('/a/record', matched_publishers='/a/fk,/a/controller'))
    assert word.matched == {'/a/record': {'/a/fk', '/a/controller'}}
    # a confirmation only counts while the node stops, and only its own
    word.on_status(diagnostics('/a/record', confirms='stewart63/a/fk'))
    node.started = True
    word.on_status(diagnostics('/a/record', confirms='stewart63/a/fk'))
    assert not word.confirmed
    node.closing = True
    word.on_status(diagnostics('/a/record', confirms='stewart63/a/controller'))
    assert not word.confirmed
    word.on_status(b'\x00\x01 not a status')
    word.on_status(diagnostics('/a/record', confirms='stewart63/a/controller,stewart63/a/fk'))
    assert word.confirmed
    # once started, what recorders matched no longer changes
    word.on_status(diagnostics('/a/other', matched_publishers='/a/fk'))
    assert list(word.matched) == ['/a/record']


# -- a publish the middleware refuses -------------------------------------------------------
class StatusNode:
    """What ``diagnostics.Health`` uses of a node: a logger, a name, publishers."""

    def __init__(self):
        self.log = Log()
        self.statuses = []

    def get_logger(self):
        log = self.log

        class Throttled:
            def warning(self, text, throttle_duration_sec=None):
                log.warning(text)
        return Throttled()

    def get_fully_qualified_name(self):
        return '/plant'

    def resolve_topic_name(self, topic):
        return topic if topic.startswith('/') else '/' + topic

    def create_publisher(self, _type, _topic, _qos):
        return SimpleNamespace(publish=self.statuses.append)


def test_a_refused_publish_is_counted_warned_of_and_not_among_the_final_counts():
    """A cut link makes Fast DDS refuse a sample (rclpy's RCLError, a
    RuntimeError): the node goes on, says so on /diagnostics, and its final
    counts hold only what went out, so a recorder does not wait for the rest."""
    from builtin_interfaces.msg import Time
    from diagnostic_msgs.msg import DiagnosticStatus

    from stewart63_ros.runtime.diagnostics import Health as RealHealth
    node = StatusNode()
    health = RealHealth(node, 'plant')
    refuse = [False]

    def publish_raw(_data):
        if refuse[0]:
            raise RuntimeError('Failed to publish: cannot publish data, at rmw_publish.cpp:120')
    send = health.sender(topics.LEG_LENGTHS, SimpleNamespace(handle=SimpleNamespace(
        publish_raw=publish_raw)))
    assert send(b'1') is True
    refuse[0] = True
    assert send(b'2') is False and send(b'3') is False
    refuse[0] = False
    assert send(b'4') is True
    assert health.published[topics.LEG_LENGTHS] == 2
    assert health.publish_failed[topics.LEG_LENGTHS] == 2
    # warned of once: the second refusal within a second is throttled (LogThrottle)
    warned = [text for _, text in node.log.lines if 'could not publish on' in text]
    assert len(warned) == 1 and '%s (1 so far)' % topics.LEG_LENGTHS in warned[0], warned
    health.report(Time(), final=True)
    status = node.statuses[-1].status[0]
    values = {kv.key: kv.value for kv in status.values}
    assert status.level == DiagnosticStatus.WARN
    assert 'could not publish 2 samples' in status.message
    assert values['publish_failed/' + topics.LEG_LENGTHS] == '2'
    assert values[handshake.FINAL_PREFIX + '/' + topics.LEG_LENGTHS.lstrip('/')] == '2'
    # The next period with no refusal is OK again.
    health.report(Time())
    assert node.statuses[-1].status[0].level == DiagnosticStatus.OK


@pytest.mark.parametrize('fast_path', [True, False], ids=['waitset', 'executor'])
def test_the_recorder_says_its_progress_on_either_path_and_while_nothing_comes(fast_path):
    """A lockstep plant waits for the recorder's word on how far the recorded
    leg_lengths got: the executor path (rclpy versions without the fast wait
    set) must say it too, and a turn with no message repeats it."""
    from stewart63_ros.recording.recorder import Recorder
    from stewart63_ros.recording.recorder_intake import Intake
    from stewart63_ros.runtime.lockstep import ProgressPublisher
    sent = []
    progress = ProgressPublisher.__new__(ProgressPublisher)
    progress.handled_ns, progress._sent_ns, progress._sent_at = -1, -1, -1e9
    progress.clock = time.monotonic
    progress._msg = SimpleNamespace(sec=0, nanosec=0)
    progress.pub = SimpleNamespace(publish=lambda msg: sent.append((msg.sec, msg.nanosec)))
    intake = Intake.__new__(Intake)
    intake.progress = progress
    intake.take_all = lambda: 0
    rec = Recorder.__new__(Recorder)
    rec.fast_path, rec.intake, rec.batch_period = fast_path, intake, 0.0
    rec.subs = SimpleNamespace(wait=lambda _timeout: None)
    rec._housekeeping = lambda: None

    def executor_turn(timeout_sec):     # a leg_lengths sample written meanwhile
        progress.note(7 * MS)
    rec._executor = SimpleNamespace(spin_once=executor_turn)
    if fast_path:
        rec.subs.wait = lambda _timeout: progress.note(7 * MS)
    rec.spin_once(0.0)
    assert sent == [(0, 7 * MS)]
    progress._sent_at -= ProgressPublisher.RESEND_PERIOD    # as if that long passed
    rec.spin_once(0.0)
    assert sent == [(0, 7 * MS)] * 2


def test_a_silent_force_source_is_dropped_after_the_peer_timeout_and_comes_back():
    """A controller hung without leaving the graph would pace a lockstep run
    at one sample per force_timeout (50 min for 3000 samples): after
    lockstep_peer_timeout of unanswered samples the plant stops waiting the
    full force_timeout, with an ERROR, until an answer comes again."""
    from stewart63_ros.runtime.lockstep import AnswerWatch
    clock = Clock()
    health = Health()
    log = Log()
    watch = AnswerWatch(health, log, timeout=10.0, clock=clock)
    assert watch.wait(1.0) == 1.0
    for _ in range(9):              # nine samples of 1 s without an answer
        clock.t += 1.0
        watch.missed(1.0)
        assert watch.wait(1.0) == 1.0 and health.fault == ''
    clock.t += 1.0
    watch.missed(1.0)               # the tenth: 10 s of silence
    assert watch.dropped and watch.wait(1.0) == AnswerWatch.DROPPED_WAIT
    assert health.fault.startswith('no force answer for 10.0 s (lockstep_peer_timeout)')
    assert health.values['force_source_drops'] == 1
    assert log.lines[-1][0] == 'error'
    watch.answered()
    assert not watch.dropped and watch.wait(1.0) == 1.0 and health.fault == ''
    # An answer in between starts the count again.
    for _ in range(2):
        for _ in range(5):
            clock.t += 1.0
            watch.missed(1.0)
        watch.answered()
    assert not watch.dropped and health.values['force_source_drops'] == 1
