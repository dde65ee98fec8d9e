"""Lockstep flow control: no reader of the rig falls behind the plant.

In lockstep the controller's answer paces the plant, sample by sample. The
other readers of ``leg_lengths`` (fk, a recorder) are not in that loop: on a
busy machine one of them can fall a thousand samples behind, and the
middleware then drops what its queue or the writer's history no longer
holds. So each of those *lockstep peers* says how far it has got, and the
plant publishes sample k only once every peer has handled sample
k - ``lockstep_window``: a slow peer slows the run, it never loses a sample.

The protocol (docs/interface.md, "Lockstep flow control"):

- a peer publishes on ``~/lockstep_progress`` (``builtin_interfaces/Time``,
  reliable, depth 1) the stamp of the newest ``leg_lengths`` sample it has
  handled (fk: posed and published, or refused, as a dropout's NaN sample
  is; the recorder: written), at most once
  per batch of samples, and again every ``ProgressPublisher.RESEND_PERIOD``
  while it is unchanged (fk: from its start-up wait on, whichever path
  served the sample; see HotLoop.run_on);
- the plant's parameter ``lockstep_peers`` names the peers (``rig`` sets fk
  and its recorder); before its first sample the plant waits until each
  one's progress publisher is matched;
- a peer whose progress publisher leaves the graph, or that has made no
  progress for ``lockstep_peer_timeout`` seconds while the plant waits for
  it, is dropped from the window with an error on /diagnostics: a dead peer
  never stalls a run for good.
"""
from __future__ import annotations

import time

from builtin_interfaces.msg import Time
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from stewart63_ros.core.plumbing.stamps import stamp_ns
from stewart63_ros.runtime.launcher import STOP

#: A peer's progress topic, private to the peer's node: ``/<ns>/<node>/lockstep_progress``.
PROGRESS_TOPIC = 'lockstep_progress'


def progress_qos():
    """Reliable, volatile, depth 1: only the newest progress matters."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


class ProgressPublisher:
    """A peer's side: ``note(ns)`` per sample handled, ``publish()`` per batch
    and between batches (it sends only what is new, or due again)."""

    #: s: an unchanged progress is sent again this often (while ``publish``
    #: is called): the plant holds for the one message that says a sample was
    #: handled, and a message lost, or sent before this writer had matched
    #: the plant's reader, must not hold it until ``lockstep_peer_timeout``.
    RESEND_PERIOD = 0.1

    def __init__(self, node):
        self._msg = Time()
        self.pub = node.create_publisher(Time, '~/' + PROGRESS_TOPIC, progress_qos())
        self.clock = time.monotonic      # (a test's fake clock)
        self.handled_ns = -1
        self._sent_ns = -1
        self._sent_at = 0.0

    def note(self, ns: int) -> None:
        """The sample stamped ``ns`` [ns] has been handled (samples come in
        order; a reset plant starts its stamps again, and so does this). A
        stamp that could not be read (negative) changes nothing."""
        if ns >= 0:
            self.handled_ns = ns

    def publish(self) -> None:
        """Say how far this node has got, if that changed since it last said
        or it said so ``RESEND_PERIOD`` ago."""
        if self.handled_ns < 0:
            return
        now = self.clock()
        if self.handled_ns == self._sent_ns and now - self._sent_at < self.RESEND_PERIOD:
            return
        self._sent_ns, self._sent_at = self.handled_ns, now
        self._msg.sec, self._msg.nanosec = divmod(self.handled_ns, 1_000_000_000)
        try:
            self.pub.publish(self._msg)
        except RuntimeError:     # rclpy's InvalidHandle: the node is going down
            pass


class PeerWindow:
    """The plant's side: which peers it waits for, and how far each has got.

    Args:
        node: the plant (a RigNode); the progress subscriptions are its side
            subscriptions, taken in its housekeeping.
        peers: full node names of the peers.
        window: samples the plant may run ahead of the slowest peer.
        period_ns: the sample period [ns].
        timeout: s without progress, while the plant waits, after which a
            peer is dropped.
    """

    def __init__(self, node, peers: list[str], window: int, period_ns: int, timeout: float):
        self.node = node
        self.window = int(window)
        self.period_ns = int(period_ns)
        self.timeout = float(timeout)
        self.progress: dict[str, int] = {}      # peer -> stamp [ns] handled
        self.last_advance: dict[str, float] = {}
        self.dropped: dict[str, str] = {}       # peer -> why
        self.subs = {}
        self.held_s = 0.0                       # wall time spent waiting for peers
        self.holds = 0                          # samples that waited
        self.window_ns = self.window * self.period_ns
        #: the slowest active peer's progress [ns]: one compare per sample
        self.slowest = -1
        for peer in peers:
            topic = '%s/%s' % (peer.rstrip('/'), PROGRESS_TOPIC)
            self.progress[peer] = -1
            self.subs[peer] = node.create_subscription(
                Time, topic, lambda msg, peer=peer: self._on_progress(peer, msg),
                progress_qos())

    @property
    def active(self) -> list[str]:
        return [p for p in self.subs if p not in self.dropped]

    def _on_progress(self, peer: str, msg) -> None:
        ns = stamp_ns(msg)
        if ns != self.progress.get(peer):
            self.progress[peer] = ns
            self.last_advance[peer] = time.monotonic()
            self._update_slowest()

    def _update_slowest(self) -> None:
        active = self.active
        self.slowest = min(self.progress[p] for p in active) if active else 1 << 62

    def missing_publishers(self) -> list[str]:
        """Before the first sample: the peers whose progress is not matched yet."""
        return ['%s: no progress publisher matched yet (lockstep_peers)' % sub.topic_name
                for peer, sub in self.subs.items() if sub.get_publisher_count() < 1]

    def behind(self, ns: int) -> list[str]:
        """The active peers that have not handled sample ``ns - window`` yet."""
        floor = ns - self.window_ns
        return [p for p in self.active if self.progress[p] < floor]

    def drop(self, peer: str, why: str) -> None:
        self.dropped[peer] = why
        self._update_slowest()
        health = self.node.health
        health.values['lockstep_peers_dropped'] = ', '.join(
            '%s (%s)' % item for item in self.dropped.items())
        health.fault = 'lockstep peer %s dropped: %s; its samples are no longer held for it' % (
            peer, why)
        self.node.get_logger().error(health.fault)

    def hold(self, ns: int, serve) -> bool:
        """Before publishing sample ``ns``: wait until no active peer is more
        than the window behind. ``serve(timeout)`` waits for and takes
        messages (the plant's housekeeping and its force input) up to
        ``timeout`` s. Returns False if a stop was requested meanwhile."""
        if ns - self.window_ns <= self.slowest:     # the usual case, per sample
            return True
        late = self.behind(ns)
        if not late:
            return True
        self.holds += 1
        started = time.monotonic()
        for peer in late:       # the timeout counts from now or its next progress
            self.last_advance[peer] = started
        while late:
            if STOP.requested:
                return False
            now = time.monotonic()
            for peer in late:
                if self.subs[peer].get_publisher_count() < 1:
                    self.drop(peer, 'its progress publisher left the ROS graph')
                elif now - self.last_advance[peer] > self.timeout:
                    self.drop(peer, 'no progress for %.1f s (lockstep_peer_timeout)'
                              % (now - self.last_advance[peer]))
            serve(0.001)
            late = self.behind(ns)
        waited = time.monotonic() - started
        self.held_s += waited
        health = self.node.health
        health.values['lockstep_held_s'] = '%.3f' % self.held_s
        health.values['lockstep_held_samples'] = self.holds
        return True


    def drain(self, last_ns: int, serve) -> bool:
        """After the run's last sample (stamp ``last_ns``): wait until every
        active peer has handled it. The plant's exit is what ends the rig
        (``rig`` then stops the other nodes), and a peer may still be a
        window behind: samples acknowledged by its reader but not yet
        handled would be lost with it (a late fk lost 130 of 801 poses).
        Same timeout and drop as ``hold``; False if a stop was requested."""
        return self.hold(last_ns + self.window_ns, serve)


class AnswerWatch:
    """The plant's watch on the source of its forces (the controller, or a
    supervisor) in lockstep.

    Each sample waits up to ``force_timeout`` for its answer, so a source
    that went silent without leaving (a hung process) would pace the run at
    one sample per ``force_timeout``: 50 minutes for a 3000-sample run.
    After ``timeout`` s (``lockstep_peer_timeout``) of samples with no answer
    the source is dropped, as a silent lockstep peer is: ERROR on
    /diagnostics, and each sample then waits only ``DROPPED_WAIT`` s. The
    first answer brings it back, and the fault clears.
    """

    #: how long a sample waits for an answer while the source is dropped [s]
    DROPPED_WAIT = 0.05

    def __init__(self, health, logger, timeout: float, clock=time.monotonic):
        self.health = health
        self.logger = logger
        self.timeout = float(timeout)
        self.clock = clock
        self.silent_since = None    # when the first unanswered wait began
        self.dropped = False
        self.drops = 0

    def wait(self, force_timeout: float) -> float:
        """How long the next sample waits for its answer [s]."""
        return min(force_timeout, self.DROPPED_WAIT) if self.dropped else force_timeout

    def answered(self) -> None:
        """The sample's answer came."""
        self.silent_since = None
        if self.dropped:
            self.dropped = False
            if self.health.fault.startswith('no force answer'):
                self.health.fault = ''
            self.logger.warning('forces answer again: waiting for them again')

    def missed(self, waited: float) -> None:
        """The sample's answer did not come within ``waited`` s."""
        now = self.clock()
        if self.silent_since is None:
            self.silent_since = now - waited
        silent = now - self.silent_since
        if not self.dropped and silent >= self.timeout:
            self.dropped = True
            self.drops += 1
            self.health.values['force_source_drops'] = self.drops
            self.health.fault = ('no force answer for %.1f s (lockstep_peer_timeout): '
                                 'stepping on with the held force, waiting %.2f s a sample'
                                 % (silent, self.DROPPED_WAIT))
            self.logger.error(self.health.fault)
