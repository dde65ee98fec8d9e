"""The recorder node: raw subscriptions to the rig's topics, written into a bag.

``record`` (``stewart63_ros/tools/record.py``) is its command line; ``rig``
and the tests use the ``Recorder`` class in-process. See docs/bags.md.
"""
from __future__ import annotations

import collections
import importlib
import os
import struct
import sys
import threading
import time
from pathlib import Path

from stewart63_ros import topics as T
from stewart63_ros.bagio import NAMESPACE_KEY, BagError
from stewart63_ros.nodes import handshake
from stewart63_ros.nodes.rclpy_internals import WaitAny, take_with_info

READY_LINE = 'READY'
MATCHED_LINE = 'MATCHED'


def message_class(type_name: str):
    """``'sensor_msgs/msg/JointState'`` -> the rclpy message class."""
    parts = type_name.split('/')
    if len(parts) == 2:
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3:
        raise ValueError(f'bad message type name {type_name!r}')
    module = importlib.import_module(f'{parts[0]}.{parts[1]}')
    return getattr(module, parts[2])


def qos_to_rosbags(profile):
    """An rclpy QoSProfile (e.g. a discovered publisher's) as a rosbags ``Qos``."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    def enum(cls, value):
        name = getattr(value, 'name', None)
        if name in cls.__members__:
            return cls[name]
        try:
            return cls(int(value))
        except (TypeError, ValueError):
            return cls['UNKNOWN']

    def dur(d):
        ns = d.nanoseconds if hasattr(d, 'nanoseconds') else int(d)
        sec, nsec = divmod(int(ns), 1_000_000_000)
        return QosTime(sec, nsec)

    return Qos(enum(QosHistory, profile.history), int(profile.depth),
               enum(QosReliability, profile.reliability),
               enum(QosDurability, profile.durability),
               dur(profile.deadline), dur(profile.lifespan),
               enum(QosLiveliness, profile.liveliness),
               dur(profile.liveliness_lease_duration),
               bool(profile.avoid_ros_namespace_conventions))


#: An MCAP Message record's opcode and length, then its channel id, sequence
#: (0), log time and publish time: what rosbags' MCAP writer writes before a
#: message's bytes.
_MCAP_MESSAGE = struct.Struct('<BQHIQQ')
#: rosbags closes a chunk once it is larger than this many bytes.
_MCAP_CHUNK_SIZE = 2**20


class BatchWriter:
    """Appends messages to a rosbags MCAP ``Writer``, the bytes and the
    bookkeeping (counts, times, chunk index) exactly as ``Writer.write``
    does, without its per-message Python (a few microseconds a message; a
    recorded rig writes seven messages a sample).

    Uses the writer's storage objects, which are not rosbags' public API:
    where they are not as expected (another rosbags), ``write`` falls back
    to ``Writer.write`` for each message. ``test/test_bags.py`` compares the
    two byte for byte.
    """

    def __init__(self, writer):
        self.writer = writer
        self.direct = False
        try:
            from rosbags.rosbag2.writer import CompressionMode
            storage = writer.storage
            chunk = storage.chunk
            self.direct = (type(storage).__name__ == 'McapWriter'
                           and writer.compression_mode != CompressionMode.MESSAGE
                           and hasattr(chunk.bio, 'tell') and isinstance(chunk.msgs, dict)
                           and all(hasattr(obj, name) for obj, name in (
                               (chunk, 'message_start_time'), (chunk, 'message_end_time'),
                               (storage, 'message_start_time'), (storage, 'message_end_time'),
                               (storage, 'channel_stats'), (storage, 'close_chunk'),
                               (writer, 'counts'), (writer, 'min_timestamp'),
                               (writer, 'max_timestamp'), (writer, 'connections'))))
        except (AttributeError, ImportError):
            self.direct = False

    def write(self, conn, messages: list) -> None:
        """Write ``messages``, (timestamp ns, bytes) in order, on connection ``conn``."""
        writer = self.writer
        if not self.direct:
            for stamp, data in messages:
                writer.write(conn, stamp, data)
            return
        if writer.storage is None or conn not in writer.connections:
            from rosbags.rosbag2.errors import WriterError
            raise WriterError('not an open connection of the bag: %r' % (conn,))
        storage = writer.storage
        cid = conn.id
        pack = _MCAP_MESSAGE.pack
        chunk = storage.chunk
        bio, index = chunk.bio, chunk.msgs[cid]
        for stamp, data in messages:
            index.append((stamp, bio.tell()))
            bio.write(pack(0x05, 22 + len(data), cid, 0, stamp, stamp))
            bio.write(data)
            if stamp < chunk.message_start_time:
                chunk.message_start_time = stamp
            if stamp > chunk.message_end_time:
                chunk.message_end_time = stamp
            if bio.tell() > _MCAP_CHUNK_SIZE:
                storage.close_chunk()               # a new chunk
                chunk = storage.chunk
                bio, index = chunk.bio, chunk.msgs[cid]
        n = len(messages)
        if n:
            first, last = messages[0][0], messages[-1][0]
            low, high = min(first, last), max(first, last)
            if n > 2:
                low = min(stamp for stamp, _ in messages)
                high = max(stamp for stamp, _ in messages)
            storage.message_start_time = min(low, storage.message_start_time)
            storage.message_end_time = max(high, storage.message_end_time)
            storage.channel_stats[cid] += n
            writer.counts[cid] += n
            writer.min_timestamp = min(low, writer.min_timestamp)
            writer.max_timestamp = max(high, writer.max_timestamp)


def header_stamp_ns(data: bytes) -> int:
    """The ``header.stamp`` [ns] of a serialized message that starts with a
    std_msgs/Header (little-endian CDR: 4 bytes of encapsulation, then
    sec int32, nanosec uint32); -1 if it cannot be read."""
    if len(data) < 12 or data[1] != 1:
        return -1
    sec, nanosec = _STAMP.unpack_from(data, 4)
    return sec * 1_000_000_000 + nanosec


_STAMP = struct.Struct('<iI')


class Recorder:
    """Records topics into a new bag; usable in-process (tests, ``rig``) and by ``main``.

    ``open()`` checks the output path, creates the node and one raw subscription
    per topic whose type is known (every topic of the rig), then sets ``ready``:
    from then on nothing a matched publisher sends is lost. Topics of unknown
    type named in ``topics`` are subscribed once they appear in the ROS graph.

    ``batch_period`` [s]: after taking messages, the recording loop lets the
    next ones gather that long before it takes again: one wake-up per batch
    instead of one per message (measured: a third less CPU per rig sample,
    CPU the nodes being recorded need). The bag times are the middleware's
    reception times, unchanged by it.

    Use ``start()``/``stop()`` to record in a background thread, or ``run()``
    in the calling thread; ``close()`` (done by ``stop()``) writes the
    bag's index and ``metadata.yaml`` and returns the message count per topic.
    """

    def __init__(self, bag_dir, topics=None, *, namespace=None, context=None,
                 domain_id=None, ros_args=None, node_name='record',
                 flush_period=0.5, discovery_period=0.25, fast_path=True,
                 batch_period=0.005):
        self.path = Path(bag_dir)
        self.requested = list(topics) if topics else list(T.TOPIC_TYPES)
        self.namespace = namespace
        self.flush_period = float(flush_period)
        self.discovery_period = float(discovery_period)
        self.batch_period = float(batch_period)
        self.fast_path = fast_path
        self.ready = threading.Event()
        self.counts: dict[str, int] = {}
        self._context = context
        self._own_context = context is None
        self._domain_id = domain_id
        self._ros_args = ros_args
        self._node_name = node_name
        self._node = None
        self._writer = None
        self._subs: dict[str, object] = {}     # full topic -> Subscription
        # Latched command topics are subscribed twice (see _subscribe): the
        # second, volatile subscription per topic, and the last message
        # written per topic, to drop the copy that comes through both.
        self._volatile_subs: dict[str, object] = {}
        self._recent_commands: dict[str, collections.deque] = {}
        self._types: dict[str, str] = {}       # full topic -> type name
        self._pending: dict[str, str] = {}     # full topic -> requested name (type unknown)
        self._conns: dict[str, object] = {}    # full topic -> rosbags Connection
        self._last_stamp: dict[str, int] = {}  # full topic -> last bag timestamp written
        self._stop = threading.Event()
        self._thread = None
        self._guard = None
        self._waitset = None
        self._waitset_subs = None
        self._executor = None
        self._next_flush = 0.0
        self._next_discovery = 0.0
        self._closed = False
        self._lock = threading.Lock()
        self.error: BaseException | None = None
        # Confirming to a stopping node that the bag holds all it published
        # (RigNode.flush): the last message number per (topic, sending
        # participant), the last statuses still to be confirmed, where to say so.
        self._per_source: collections.Counter = collections.Counter()
        self._finals: dict[tuple, tuple] = {}   # (status, participant) -> (counts, since)
        self._status_pub = None
        self._status_name = ''
        self._matched_nodes: list[str] = []     # see _report
        self._own_status_gid = None     # its status publisher's, from the graph
        self._next_report = 0.0
        self._diag_topic = None
        #: messages of each topic that never reached the bag: gaps in each
        #: publisher's sequence numbers (a reader that could not keep up)
        self.lost: collections.Counter = collections.Counter()
        self._skips: dict = {}          # full topic -> checks.SkipCounter
        #: lockstep flow control (nodes/lockstep.py): how far the bag has got
        #: on leg_lengths, for a plant that lists this recorder in lockstep_peers
        self._progress = None
        self._lengths_topic = None

    # ----------------------------------------------------------------- setup
    def open(self):
        """Create the bag and the subscriptions; returns self with ``ready`` set."""
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.rosbag2.errors import WriterError

        if os.path.lexists(self.path):
            raise BagError(f'{self.path} exists already; record writes a new bag, '
                           'give a path that does not exist')
        import rclpy
        from rclpy.node import Node
        if self._context is None:
            from stewart63_ros.middleware import use_rig_profile
            use_rig_profile()
            self._context = rclpy.Context()
            rclpy.init(args=self._ros_args, context=self._context, domain_id=self._domain_id)
        try:
            self._node = Node(self._node_name, namespace=self.namespace or None,
                              context=self._context, start_parameter_services=False)
            writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
            writer.set_custom_data(NAMESPACE_KEY, self._node.get_namespace())
            try:
                writer.open()
            except WriterError as exc:
                raise BagError(str(exc)) from exc
            self._writer = writer
            self._batch = BatchWriter(writer)
            self._guard = self._node.create_guard_condition(lambda: None)
            for name in self.requested:
                full = self._node.resolve_topic_name(name)
                type_name = T.TOPIC_TYPES.get(name) or T.TOPIC_TYPES.get(T.relative_name(full))
                if type_name:
                    self._subscribe(full, type_name)
                else:
                    self._pending[full] = name
            # The recorder's own status (see _report), also when /diagnostics
            # is not recorded: starting nodes wait for what it says.
            from diagnostic_msgs.msg import DiagnosticArray
            diag = self._node.resolve_topic_name(T.DIAGNOSTICS)
            self._status_pub = self._node.create_publisher(DiagnosticArray, diag,
                                                           T.DIAGNOSTICS_QOS)
            self._status_name = T.status_name(self._node.get_fully_qualified_name())
            if diag in self._subs:
                self._diag_topic = diag
            from stewart63_ros.nodes.lockstep import ProgressPublisher
            self._progress = ProgressPublisher(self._node)
            lengths = self._node.resolve_topic_name(T.LEG_LENGTHS)
            self._lengths_topic = lengths if lengths in self._subs else None
            if self.fast_path:
                try:
                    self._build_waitset()
                except Exception:  # noqa: BLE001 - other rclpy versions: the executor path
                    self.fast_path = False
            if not self.fast_path:
                from rclpy.executors import SingleThreadedExecutor
                self._executor = SingleThreadedExecutor(context=self._context)
                self._executor.add_node(self._node)
            now = time.monotonic()
            self._next_flush = now + self.flush_period
            self._next_discovery = now
        except BaseException:
            self._teardown(abort=True)
            raise
        self.ready.set()
        return self

    def _subscribe(self, full, type_name, qos=None):
        """A raw subscription to ``full``; for a latched command topic also a
        volatile one: the TRANSIENT_LOCAL subscription receives the command a
        latched publisher sent before recording started, but matches no
        volatile publisher (``ros2 topic pub`` by default); the VOLATILE one
        matches both, and a latched sample that comes through both is
        written once (``_on_message``)."""
        from rclpy.qos import DurabilityPolicy, QoSProfile
        cls = message_class(type_name)
        qos = qos or T.recorder_qos(full)

        def make_callback(tag):
            # rclpy inspects the signature: give it exactly (msg, info)
            return lambda data, info: self._on_message(full, data, info, tag)
        sub = self._node.create_subscription(cls, full, make_callback('main'), qos, raw=True)
        old = self._subs.get(full)
        self._subs[full] = sub
        self._types[full] = type_name
        self.counts.setdefault(full, 0)
        if old is not None:
            self._node.destroy_subscription(old)
        if (T.relative_name(full) in T.LATCHED_TOPICS and full not in self._volatile_subs
                and qos.durability == DurabilityPolicy.TRANSIENT_LOCAL):
            volatile = QoSProfile(history=qos.history, depth=qos.depth,
                                  reliability=qos.reliability,
                                  durability=DurabilityPolicy.VOLATILE)
            self._volatile_subs[full] = self._node.create_subscription(
                cls, full, make_callback('volatile'), volatile, raw=True)
        self._waitset_subs = None

    def _build_waitset(self):
        subs = list(self._subs.values()) + list(self._volatile_subs.values())
        self._waitset = WaitAny(self._context, subs, [self._guard])
        self._waitset_subs = subs

    # -------------------------------------------------------------- recording
    def _on_message(self, topic, data, info, tag='main'):
        if topic == self._diag_topic and self._is_own_status(info):
            return      # the recorder's own status: about the recording, not of the rig
        if topic in self._volatile_subs:
            # A latched publisher's sample arrives through both subscriptions:
            # the copy through the other one, within a second, is not written.
            now = time.monotonic()
            recent = self._recent_commands.setdefault(topic, collections.deque(maxlen=32))
            for i, (other, seen, when) in enumerate(recent):
                if other != tag and seen == data and now - when < 1.0:
                    del recent[i]
                    return
            recent.append((tag, bytes(data), now))
        conn = self._conns.get(topic)
        if conn is None:
            conn = self._add_connection(topic)
        stamp = info.get('received_timestamp') if info else None
        stamp = int(stamp) if stamp else time.time_ns()
        # Reliable topics are delivered in order; a sample re-sent after a loss
        # carries a later reception time than the ones that followed it but is
        # only delivered before them. Its time in the bag is when it became
        # available in order, so each topic's bag times follow delivery order.
        last = self._last_stamp.get(topic, 0)
        if stamp <= last:
            stamp = last + 1
        self._last_stamp[topic] = stamp
        self._writer.write(conn, stamp, data)
        self.counts[topic] += 1
        gid = info.get('publisher_gid') if info else None
        if gid:
            self._count_gap(topic, bytes(gid['data']), info)
        if topic == self._lengths_topic:
            self._progress.note(header_stamp_ns(data))
        if gid:
            # The first 12 bytes of an endpoint's GID are its participant's
            # (its process's): a node's /diagnostics and data publishers share them.
            source = bytes(gid['data'][:12])
            # A writer numbers its messages 1, 2, ...: the last one's number is
            # how many it published, also for a recorder started after it.
            seq = info.get('publication_sequence_number')
            key = (topic, source)
            if seq:
                self._per_source[key] = max(self._per_source[key], int(seq))
            else:
                self._per_source[key] += 1
            if topic == self._diag_topic:
                self._note_final(data, source)

    #: s: how long a stopping node's last status waits for its messages
    FINAL_WAIT = 30.0

    def _note_final(self, data, source):
        """A node's last status (``final: true``) says how many messages it
        published per topic: confirm once the bag holds them (``_confirm``)."""
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.serialization import deserialize_message
        try:
            msg = deserialize_message(bytes(data), DiagnosticArray)
        except Exception:   # noqa: BLE001 - written as received; not ours to judge
            return
        for status in msg.status:
            if status.name == self._status_name:
                continue
            wanted = handshake.final_counts({kv.key: kv.value for kv in status.values})
            if wanted is None:
                continue
            self._finals[status.name, source] = (wanted, time.monotonic())

    def _confirm(self):
        """Say on /diagnostics (``confirms``: the statuses' names) which stopping
        nodes' messages the bag now holds, on the topics it records."""
        done = []
        now = time.monotonic()
        for key, (wanted, since) in list(self._finals.items()):
            name, source = key
            if all(self._per_source[topic, source] >= n for topic, n in wanted.items()
                   if topic in self._subs):
                done.append(name)
                del self._finals[key]
            elif now - since > self.FINAL_WAIT:
                del self._finals[key]
        if done:
            self._publish_status('holds every message of ' + ', '.join(done),
                                 **{handshake.CONFIRMS: ','.join(done)})

    def _publish_status(self, message, **keys):
        """One status of the recorder on /diagnostics: ``keys`` and the count
        recorded per topic."""
        if self._status_pub is None:
            return
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
        values = [KeyValue(key=k, value=v) for k, v in keys.items()]
        values += [KeyValue(key='recorded/' + topic, value=str(n))
                   for topic, n in sorted(self.counts.items())]
        values += [KeyValue(key='lost/' + topic, value=str(n))
                   for topic, n in sorted(self.lost.items())]
        level = DiagnosticStatus.OK
        if self.lost:
            level = DiagnosticStatus.WARN
            message = 'lost %d messages (%s); %s' % (
                sum(self.lost.values()), ', '.join(sorted(self.lost)), message)
        status = DiagnosticStatus(level=level, name=self._status_name,
                                  message=message, hardware_id='stewart63_ros', values=values)
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self._node.get_clock().now().to_msg()
        try:
            self._status_pub.publish(msg)
        except RuntimeError:    # rclpy's InvalidHandle: the node is going down
            pass

    def _add_connection(self, topic):
        from stewart63_ros.bagio import typestore
        try:
            infos = self._node.get_publishers_info_by_topic(topic)
        except RuntimeError:  # rclpy's RCLError, InvalidHandle: the node is going down
            infos = []
        others = [i for i in infos if not self._own(i)]
        # The recorder's own status publisher, when it is the only one known
        # (its first status on /diagnostics). The QoS is fixed here, in the MCAP
        # channel and in metadata.yaml alike: a reader pairs the two by it.
        qos = [qos_to_rosbags(i.qos_profile) for i in (others or infos)]
        conn = self._writer.add_connection(topic, self._types[topic], typestore=typestore(),
                                           offered_qos_profiles=qos)
        self._conns[topic] = conn
        return conn

    def _take_all(self):
        n = 0
        for topic, sub in list(self._subs.items()):
            volatile = self._volatile_subs.get(topic)
            if volatile is None and topic != self._diag_topic:
                n += self._take_topic(topic, sub)
                continue
            if volatile is None:        # /diagnostics: rare, and read (see _note_final)
                while True:
                    got = take_with_info(sub)
                    if got is None:
                        break
                    self._on_message(topic, got[0], got[1])
                    n += 1
                continue
            # A latched command topic: both subscriptions' messages in the
            # order they were received, so duplicates meet and the bag's
            # order is the publishers'.
            taken = []
            for tag, each in (('main', sub), ('volatile', volatile)):
                while True:
                    got = take_with_info(each)
                    if got is None:
                        break
                    taken.append((got[1].get('received_timestamp', 0), tag, got[0], got[1]))
            taken.sort(key=lambda item: (item[0], item[1]))
            for _, tag, data, info in taken:
                self._on_message(topic, data, info, tag)
                n += 1
        if self._finals:
            self._confirm()
        if n and self._progress is not None:
            self._progress.publish()
        return n

    def _take_topic(self, topic, sub) -> int:
        """Everything queued on ``sub`` (not a latched topic's), written as one
        batch: what ``_on_message`` does for each message, in one pass."""
        got = take_with_info(sub)
        if got is None:
            return 0
        conn = self._conns.get(topic)
        if conn is None:
            conn = self._add_connection(topic)
        last = self._last_stamp.get(topic, 0)
        per_source = self._per_source
        note_gap = self._skip_counter(topic).note
        batch = []
        while got is not None:
            info = got[1]
            stamp = info.get('received_timestamp') if info else None
            stamp = int(stamp) if stamp else time.time_ns()
            if stamp <= last:           # see _on_message
                stamp = last + 1
            last = stamp
            batch.append((stamp, got[0]))
            gid = info.get('publisher_gid') if info else None
            if gid:                     # the sender's count, as in _on_message
                full = bytes(gid['data'])
                gap = note_gap(full, info)
                if gap:
                    self._note_lost(topic, gap)
                key = (topic, full[:12])
                seq = info.get('publication_sequence_number')
                if seq:
                    per_source[key] = max(per_source[key], int(seq))
                else:
                    per_source[key] += 1
            got = take_with_info(sub)
        self._last_stamp[topic] = last
        self._batch.write(conn, batch)
        self.counts[topic] += len(batch)
        if topic == self._lengths_topic:
            self._progress.note(header_stamp_ns(batch[-1][1]))
        return len(batch)

    def _skip_counter(self, topic):
        """The checks.SkipCounter of ``topic``: gaps in each publisher's numbers."""
        counter = self._skips.get(topic)
        if counter is None:
            from stewart63_ros.nodes.checks import SkipCounter
            counter = self._skips[topic] = SkipCounter()
        return counter

    def _count_gap(self, topic, gid: bytes, info) -> None:
        """Count the messages of the publisher ``gid`` on ``topic`` that never
        reached the recorder."""
        gap = self._skip_counter(topic).note(gid, info)
        if gap:
            self._note_lost(topic, gap)

    def _note_lost(self, topic, gap: int) -> None:
        """``gap`` messages of ``topic`` never reached the recorder: counted, said."""
        if gap:
            self.lost[topic] += gap
            self._next_report = 0.0     # say so at once
            print('record: lost %d %s messages (%d so far): they never reached the recorder'
                  % (gap, topic, self.lost[topic]), file=sys.stderr, flush=True)

    def spin_once(self, timeout=0.1):
        """Wait up to ``timeout`` s for messages, write what arrived, do housekeeping."""
        if self.fast_path:
            if self._waitset_subs is None:
                self._build_waitset()
            self._waitset.wait(timeout)
            if self._take_all() and self.batch_period > 0 and not self._stop.is_set():
                # Let the next messages gather in the subscriptions' queues
                # (the middleware receives and acknowledges them meanwhile):
                # one wake-up and one pass over the topics for a batch,
                # instead of one per message, which would take CPU from the
                # nodes being recorded.
                time.sleep(min(self.batch_period, timeout))
        else:
            self._executor.spin_once(timeout_sec=timeout)
        self._housekeeping()

    def take_available(self) -> int:
        """Write what has arrived, without waiting; the periodic flush and
        discovery as ``spin_once``. For a loop that hosts the recorder with
        other nodes in one thread (the composed rig): the number written."""
        n = self._take_all()
        self._housekeeping()
        return n

    def _housekeeping(self):
        now = time.monotonic()
        if now >= self._next_discovery:
            self._next_discovery = now + self.discovery_period
            self._discover()
        self._report(now)
        if now >= self._next_flush:
            self._next_flush = now + self.flush_period
            self.flush()

    def flush(self):
        """Write the buffered messages to disk as a complete MCAP chunk, so they
        survive a hard kill of this process (see recover_bag)."""
        storage = getattr(self._writer, 'storage', None)
        if storage is None:
            return
        chunk = getattr(storage, 'chunk', None)
        if chunk is not None and hasattr(storage, 'close_chunk') and chunk.bio.tell():
            storage.close_chunk()
        bio = getattr(storage, 'bio', None)
        if bio is not None:
            bio.flush()

    def _discover(self):
        node = self._node
        if self._pending:
            for name, types in node.get_topic_names_and_types():
                if name in self._pending and types:
                    del self._pending[name]
                    self._subscribe(name, types[0])
        # node -> whether every one of its publishers on recorded topics is
        # matched by this recorder's subscriptions (see _report)
        complete: dict[str, bool] = {}
        for topic, sub in list(self._subs.items()):
            try:
                infos = node.get_publishers_info_by_topic(topic)
            except RuntimeError:  # rclpy's RCLError, InvalidHandle: the node is going down
                continue
            # The subscription's own count is the reader's side of each match
            # (its own status publisher's too); the graph shows a publisher no
            # earlier than the match begins.
            matched = self._publisher_count(topic) >= len(infos)
            infos = [i for i in infos if not self._own(i)]
            for info in infos:
                name = T.endpoint_node_name(info)
                complete[name] = complete.get(name, True) and matched
            if not infos:
                continue
            if topic not in self._conns:
                self._add_connection(topic)
            # A best-effort publisher (a sensor driver) does not match a reliable
            # subscription: follow rosbag2 and subscribe best effort then.
            from rclpy.qos import QoSProfile, ReliabilityPolicy
            if (sub.qos_profile.reliability == ReliabilityPolicy.RELIABLE and
                    any(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
                        for i in infos)):
                q = sub.qos_profile
                be = QoSProfile(history=q.history, depth=q.depth,
                                reliability=ReliabilityPolicy.BEST_EFFORT,
                                durability=q.durability)
                print(f'record: {topic} has a best-effort publisher; '
                      'subscribing best effort', file=sys.stderr, flush=True)
                self._subscribe(topic, self._types[topic], be)
        matched = sorted(name for name, ok in complete.items() if ok)
        if matched != self._matched_nodes:
            self._matched_nodes = matched
            self._next_report = 0.0     # say so at once

    #: s: how often the recorder publishes its status
    REPORT_PERIOD = 1.0

    def _report(self, now):
        """The recorder's status on /diagnostics, every ``REPORT_PERIOD`` and
        at once when it changes: ``matched_publishers`` names the nodes every
        one of whose publishers on the recorded topics the recorder has matched.

        A publisher counts the recorder as matched as soon as it has discovered
        the recorder's subscription; the recorder drops what comes before it
        has discovered the publisher in turn (a volatile reader starts at the
        first sample it sees announced). Nobody but the recorder sees its side,
        so it says it here, and a starting node waits for its own name before
        its first sample (RigNode.wait_for_matches): every sample from the first.
        """
        if now < self._next_report:
            return
        self._next_report = now + self.REPORT_PERIOD
        self._publish_status('recording %d topics to %s' % (len(self._subs), self.path),
                             **{handshake.MATCHED: ','.join(self._matched_nodes)})

    def _is_own_status(self, info) -> bool:
        """Whether a /diagnostics message (its ``info``) is the recorder's own
        status (not written to the bag: about the recording, not the rig)."""
        gid = info.get('publisher_gid') if info else None
        if not gid or self._status_pub is None:
            return False
        if self._own_status_gid is None:
            try:
                infos = self._node.get_publishers_info_by_topic(self._status_pub.topic_name)
            except RuntimeError:  # rclpy's RCLError, InvalidHandle: the node is going down
                return False
            own = [bytes(i.endpoint_gid) for i in infos if self._own(i)]
            if not own:
                return False
            self._own_status_gid = own[0]
        data = bytes(gid['data'])
        return data[:len(self._own_status_gid)] == self._own_status_gid

    def _own(self, info) -> bool:
        """Whether graph endpoint ``info`` is the recorder's own."""
        return (info.node_name == self._node.get_name()
                and info.node_namespace == self._node.get_namespace())

    @property
    def topics(self) -> list[str]:
        """The full names of the topics subscribed so far (more may come: a
        topic of unknown type is subscribed once the ROS graph shows it)."""
        return list(self._subs)

    def publisher_counts(self, topics=None):
        """Publishers the recorder's own subscriptions have matched, per
        subscribed topic (or per topic of ``topics``, relative names resolved
        in the recorder's namespace). A latched command topic counts those of
        its volatile subscription, which matches latched and volatile
        publishers alike (``_subscribe``).

        This is the reader's side of the match: a publisher can already count
        the recorder while the recorder does not know it yet, and what it
        sends then is lost to the recorder."""
        names = [self._node.resolve_topic_name(t) for t in topics] if topics else list(self._subs)
        return {t: self._publisher_count(t) for t in names}

    def _publisher_count(self, topic) -> int:
        sub = self._volatile_subs.get(topic) or self._subs.get(topic)
        return 0 if sub is None else sub.get_publisher_count()

    def matched(self, topics=None) -> bool:
        """True when every topic in ``topics`` (default: all subscribed) has a
        matched publisher. Relative names resolve in the recorder's namespace."""
        return all(n >= 1 for n in self.publisher_counts(topics).values())

    def wait_for_publishers(self, topics=None, timeout=30.0) -> bool:
        """Block until :meth:`matched` (bounded); spins if no thread is recording."""
        deadline = time.monotonic() + timeout
        while not self.matched(topics):
            if time.monotonic() >= deadline:
                return False
            if self._thread is None:
                self.spin_once(0.02)
            else:
                time.sleep(0.01)
        return True

    def run(self, duration=None, stop_event=None):
        """Record until ``stop()``, ``stop_event`` or ``duration`` seconds."""
        end = None if duration is None else time.monotonic() + duration
        while not self._stop.is_set() and not (stop_event and stop_event.is_set()):
            if end is not None and time.monotonic() >= end:
                break
            timeout = 0.1 if end is None else max(0.0, min(0.1, end - time.monotonic()))
            self.spin_once(timeout)

    def start(self):
        """Open if needed, then record in a background thread."""
        if self._node is None:
            self.open()

        def target():
            try:
                self.run()
            except BaseException as exc:  # noqa: BLE001 - reported by stop()
                self.error = exc
        self._thread = threading.Thread(target=target, name='recorder', daemon=True)
        self._thread.start()
        return self

    def request_stop(self):
        """Ask ``run()`` to return (safe from a signal handler or another thread)."""
        self._stop.set()
        guard = self._guard
        if guard is not None:
            try:
                guard.trigger()
            except RuntimeError:  # rclpy's InvalidHandle: already destroyed, run() has returned
                pass

    def stop(self, timeout=10.0):
        """Stop the recording thread and close the bag; returns counts per topic."""
        self.request_stop()
        if self._thread is not None:
            self._thread.join(timeout)
        if self.error is not None:
            raise self.error
        return self.close()

    def close(self):
        """Write what is still queued, the MCAP summary and metadata.yaml."""
        with self._lock:
            if self._closed:
                return dict(self.counts)
            self._closed = True
        try:
            if self._node is not None and self._writer is not None:
                try:
                    self._take_all()
                except Exception:  # noqa: BLE001 - the bag is closed whatever the last take met
                    pass
        finally:
            self._teardown(abort=False)
        return dict(self.counts)

    def _teardown(self, abort):
        writer, self._writer = self._writer, None
        try:
            if writer is not None:
                if abort:
                    writer.abort()
                else:
                    writer.close()
        finally:
            if self._executor is not None:
                self._executor.shutdown(timeout_sec=1.0)
                self._executor = None
            if self._node is not None:
                self._node.destroy_node()
                self._node = None
            if self._own_context and self._context is not None:
                self._context.try_shutdown()
                self._context = None

    def summary(self) -> str:
        total = sum(self.counts.values())
        parts = ', '.join(f'{t} {n}' for t, n in self.counts.items() if n or t in self._conns)
        text = f'record: {self.path}: {total} messages ({parts or "no topics"})'
        if self.lost:
            text += '; LOST (never reached the recorder): ' + ', '.join(
                f'{t} {n}' for t, n in sorted(self.lost.items()))
        return text
