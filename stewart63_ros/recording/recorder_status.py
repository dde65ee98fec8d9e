"""What the recorder says: its status on /diagnostics, its side of the
handshake with the rig's nodes (runtime/handshake.py), and the messages that
never reached it (see recording/recorder.py).
"""
from __future__ import annotations

import collections
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.serialization import deserialize_message

from stewart63_ros.recording.recorder_topics import own_endpoint
from stewart63_ros.runtime import handshake
from stewart63_ros.runtime.diagnostics import StatusPublisher


class LossCount:
    """Messages of each topic that never reached the bag: gaps in each
    publisher's sequence numbers (a reader that could not keep up).

    ``lost``: full topic -> messages lost; ``on_loss()`` is called on each
    loss (the status says so at once).
    """

    def __init__(self):
        self.lost: collections.Counter = collections.Counter()
        self.on_loss = None
        self._skips: dict = {}          # full topic -> checks.SkipCounter

    def counter(self, topic):
        """The checks.SkipCounter of ``topic``: gaps in each publisher's numbers."""
        counter = self._skips.get(topic)
        if counter is None:
            # lazy: runtime.checks costs 1462 ms (numba); record starts without
            from stewart63_ros.runtime.checks import SkipCounter
            counter = self._skips[topic] = SkipCounter()
        return counter

    def note(self, topic, gap: int) -> None:
        """``gap`` messages of ``topic`` never reached the recorder: counted, said."""
        if gap:
            self.lost[topic] += gap
            if self.on_loss is not None:
                self.on_loss()
            print('record: lost %d %s messages (%d so far): they never reached the recorder'
                  % (gap, topic, self.lost[topic]), file=sys.stderr, flush=True)


class RecorderStatus:
    """The recorder's status on /diagnostics, and its side of the handshake.

    - ``matched_publishers`` (``report``): the nodes every one of whose
      publishers on the recorded topics the recorder has matched. A publisher
      counts the recorder as matched as soon as it has discovered the
      recorder's subscription; the recorder drops what comes before it has
      discovered the publisher in turn (a volatile reader starts at the first
      sample it sees announced). Nobody but the recorder sees its side, so it
      says it here, and a starting node waits for its own name before its
      first sample (RigNode.wait_for_matches): every sample from the first.
    - ``confirms`` (``confirm``): the stopping nodes whose messages the bag
      now holds, as their last status counted them (``note_final``).

    Every status also gives the count recorded per topic (``counts``), and
    the count lost (``losses``), then with level WARN.
    """

    #: s: how often the recorder publishes its status
    REPORT_PERIOD = 1.0
    #: s: how long a stopping node's last status waits for its messages
    FINAL_WAIT = 30.0

    def __init__(self, node, path, counts: dict, losses: LossCount, subscribed: dict):
        self.node = node
        self.path = path
        self.counts = counts
        self.losses = losses
        self.subscribed = subscribed     # full topic -> its subscription
        self.out = StatusPublisher(node)
        #: the last message number per (topic, sending participant): how many
        #: each process published, also for a recorder started after it
        self.per_source: collections.Counter = collections.Counter()
        #: the last statuses of stopping nodes still to confirm:
        #: (status name, participant) -> (counts wanted per topic, since when)
        self.finals: dict[tuple, tuple] = {}
        self._matched_nodes: list[str] = []
        self._matched_on: dict[str, list[str]] = {}
        self._next_report = 0.0
        self._own_gid = None        # its status publisher's, from the graph
        losses.on_loss = self.report_soon

    def report_soon(self) -> None:
        """Publish the status at the next ``report``, not a period later."""
        self._next_report = 0.0

    def matched(self, nodes: list[str], on_topics=None) -> None:
        """The nodes the recorder has matched every publisher of, now
        (sorted), and per topic the nodes whose publishers on it it has
        matched (``matched_publishers/<topic>``)."""
        on_topics = dict(on_topics or {})
        if nodes != self._matched_nodes or on_topics != self._matched_on:
            self._matched_nodes = nodes
            self._matched_on = on_topics
            self.report_soon()

    def report(self, now: float) -> None:
        """The status, every ``REPORT_PERIOD`` and at once when it changes."""
        if now < self._next_report:
            return
        self._next_report = now + self.REPORT_PERIOD
        per_topic = {handshake.MATCHED_ON_PREFIX + topic: ','.join(nodes)
                     for topic, nodes in sorted(self._matched_on.items())}
        self.publish('recording %d topics to %s' % (len(self.subscribed), self.path),
                     **{handshake.MATCHED: ','.join(self._matched_nodes)}, **per_topic)

    def note_final(self, data, source) -> None:
        """A /diagnostics message (``data``, serialized) from the participant
        ``source``: a node's last status (``final: true``) says how many
        messages it published per topic: confirm once the bag holds them."""
        try:
            msg = deserialize_message(bytes(data), DiagnosticArray)
        except Exception:   # noqa: BLE001 - written as received; not ours to judge
            return
        for status in msg.status:
            if status.name == self.out.name:
                continue
            wanted = handshake.final_counts({kv.key: kv.value for kv in status.values})
            if wanted is None:
                continue
            self.finals[status.name, source] = (wanted, time.monotonic())

    def confirm(self) -> None:
        """Say on /diagnostics (``confirms``: the statuses' names) which stopping
        nodes' messages the bag now holds, on the topics it records."""
        done = []
        now = time.monotonic()
        for key, (wanted, since) in list(self.finals.items()):
            name, source = key
            if all(self.per_source[topic, source] >= n for topic, n in wanted.items()
                   if topic in self.subscribed):
                done.append(name)
                del self.finals[key]
            elif now - since > self.FINAL_WAIT:
                del self.finals[key]
        if done:
            self.publish('holds every message of ' + ', '.join(done),
                         **{handshake.CONFIRMS: ','.join(done)})

    def publish(self, message, **keys) -> None:
        """One status of the recorder: ``keys``, the count recorded and lost
        per topic; WARN once messages were lost."""
        lost = self.losses.lost
        values = [KeyValue(key=k, value=v) for k, v in keys.items()]
        values += [KeyValue(key=handshake.RECORDED_PREFIX + topic, value=str(n))
                   for topic, n in sorted(self.counts.items())]
        values += [KeyValue(key='lost/' + topic, value=str(n))
                   for topic, n in sorted(lost.items())]
        level = DiagnosticStatus.OK
        if lost:
            level = DiagnosticStatus.WARN
            message = 'lost %d messages (%s); %s' % (
                sum(lost.values()), ', '.join(sorted(lost)), message)
        try:
            self.out.publish(level, message, values)
        except RuntimeError:    # rclpy's InvalidHandle: the node is going down
            pass

    def is_own(self, info) -> bool:
        """Whether a /diagnostics message (its ``info``) is the recorder's own
        status (not written to the bag: about the recording, not the rig)."""
        gid = info.get('publisher_gid') if info else None
        if not gid:
            return False
        if self._own_gid is None:
            try:
                infos = self.node.get_publishers_info_by_topic(self.out.pub.topic_name)
            except RuntimeError:  # rclpy's RCLError, InvalidHandle: the node is going down
                return False
            own = [bytes(i.endpoint_gid) for i in infos if own_endpoint(self.node, i)]
            if not own:
                return False
            self._own_gid = own[0]
        data = bytes(gid['data'])
        return data[:len(self._own_gid)] == self._own_gid
