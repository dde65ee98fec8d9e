"""The recorder's intake: what its subscriptions received, taken and written
into the bag, each message through one path (``Intake.write``).

On the hot path of a lockstep rig (thousands of messages a second): the
wait-set loop takes a topic's whole queue and writes it as one batch.
"""
from __future__ import annotations

import time

from stewart63_ros.recording.recorder_bag import header_stamp_ns
from stewart63_ros.runtime.rclpy_internals import take_with_info


class Intake:
    """Takes what the recorder's subscriptions (``subs``, RecordedTopics) hold
    and writes it into ``bag`` (BagOut), counting for ``status``
    (RecorderStatus) and ``losses`` (LossCount).

    Two topics are read as they are written: ``diag_topic`` (/diagnostics,
    if recorded: the nodes' last statuses, RecorderStatus.note_final) and
    ``lengths_topic`` (leg_lengths, if recorded: ``progress``, lockstep flow
    control, runtime/lockstep.py: how far the bag has got, for a plant that
    lists this recorder in lockstep_peers).
    """

    def __init__(self, bag, subs, status, losses, progress, diag_topic, lengths_topic):
        self.bag = bag
        self.subs = subs
        self.status = status
        self.losses = losses
        self.progress = progress
        self.diag_topic = diag_topic
        self.lengths_topic = lengths_topic

    def add_connection(self, topic):
        """The bag's connection of ``topic``, with its publishers' QoS."""
        return self.bag.add_connection(topic, self.subs.types[topic],
                                       self.subs.offered_qos(topic))

    def write(self, topic, got, sub=None) -> int:
        """The one path of every message into the bag: ``got``, a (data, info)
        pair as taken, then (if ``sub`` is given) everything else ``sub``
        holds, in order: stamped, written as one batch and counted per topic,
        per sender (``RecorderStatus.per_source``, for the handshake) and per
        gap in a sender's numbers (``losses``). Returns how many were written.

        The wait-set loop hands a topic's whole queue here at once, thousands
        of messages a second: the loop makes no call and no allocation it
        can do without.
        """
        bag = self.bag
        last = bag.last_stamp.get(topic, 0)
        per_source = self.status.per_source
        note_gap = self.losses.counter(topic).note
        batch = []
        append = batch.append
        while got is not None:
            data, info = got
            stamp = info.get('received_timestamp') if info else None
            stamp = int(stamp) if stamp else time.time_ns()
            # Reliable topics are delivered in order; a sample re-sent after a
            # loss carries a later reception time than the ones that followed
            # it but is only delivered before them. Its time in the bag is
            # when it became available in order, so each topic's bag times
            # follow delivery order.
            if stamp <= last:
                stamp = last + 1
            last = stamp
            append((stamp, data))
            gid = info.get('publisher_gid') if info else None
            if gid:
                full = bytes(gid['data'])
                gap = note_gap(full, info)
                if gap:
                    self.losses.note(topic, gap)
                # The first 12 bytes of an endpoint's GID are its participant's
                # (its process's): a node's /diagnostics and data publishers
                # share them. A writer numbers its messages 1, 2, ...: the last
                # one's number is how many it published, also for a recorder
                # started after it.
                key = (topic, full[:12])
                seq = info.get('publication_sequence_number')
                if seq:
                    per_source[key] = max(per_source[key], int(seq))
                else:
                    per_source[key] += 1
            got = take_with_info(sub) if sub is not None else None
        if not batch:
            return 0
        bag.last_stamp[topic] = last
        conn = bag.conns.get(topic)
        if conn is None:
            conn = self.add_connection(topic)
        bag.batch.write(conn, batch)
        bag.counts[topic] += len(batch)
        if topic == self.lengths_topic:
            self.progress.note(header_stamp_ns(batch[-1][1]))
        return len(batch)

    def on_message(self, topic, data, info, tag='main'):
        """One message, as the executor hands it (and the wait-set loop the
        rare topics': /diagnostics, the latched commands), through ``write``.
        ``tag``: which of a latched topic's subscriptions it came through."""
        if topic == self.diag_topic and self.status.is_own(info):
            return      # the recorder's own status: about the recording, not of the rig
        copies = self.subs.copies.get(topic)
        if copies is not None and not copies.first(tag, bytes(data)):
            return      # a latched sample's copy through the other subscription
        self.write(topic, (data, info))
        if topic == self.diag_topic:
            gid = info.get('publisher_gid') if info else None
            if gid:
                self.status.note_final(data, bytes(gid['data'][:12]))

    def take_all(self) -> int:
        """Write what the subscriptions hold; the number written."""
        n = 0
        subs = self.subs
        for topic, sub in list(subs.subs.items()):
            volatile = subs.volatile.get(topic)
            if volatile is None and topic != self.diag_topic:
                got = take_with_info(sub)
                if got is not None:     # (most turns find most topics empty)
                    n += self.write(topic, got, sub)
                continue
            if volatile is None:        # /diagnostics: rare, and read (see on_message)
                while (got := take_with_info(sub)) is not None:
                    self.on_message(topic, got[0], got[1])
                    n += 1
                continue
            # A latched command topic: both subscriptions' messages in the
            # order they were received, so copies meet and the bag's order
            # is the publishers'.
            taken = []
            for tag, each in (('main', sub), ('volatile', volatile)):
                while (got := take_with_info(each)) is not None:
                    taken.append((got[1].get('received_timestamp', 0), tag, got[0], got[1]))
            taken.sort(key=lambda item: (item[0], item[1]))
            for _, tag, data, info in taken:
                self.on_message(topic, data, info, tag)
                n += 1
        if self.status.finals:
            self.status.confirm()
        if n:
            self.say_progress()
        return n

    def say_progress(self) -> None:
        """Tell a lockstep plant how far the recorded ``leg_lengths`` got
        (``ProgressPublisher.publish``: only when it changed, or to repeat it)."""
        if self.progress is not None:
            self.progress.publish()
