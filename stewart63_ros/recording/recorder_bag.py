"""The recorder's bag: a rosbags MCAP writer, one connection per topic, and
the fast batch writes the recording loop makes (see recording/recorder.py).
"""
from __future__ import annotations

import os
import struct
from pathlib import Path

from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.errors import WriterError
from rosbags.rosbag2.writer import CompressionMode

from stewart63_ros.bagio import NAMESPACE_KEY, BagError, typestore
from stewart63_ros.core.plumbing.stamps import ns_of


def qos_to_rosbags(profile):
    """An rclpy QoSProfile (e.g. a discovered publisher's) as a rosbags ``Qos``."""

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
    return ns_of(sec, nanosec)


_STAMP = struct.Struct('<iI')


class BagOut:
    """The bag being written: its writer, one connection per topic, and per
    topic the count and the last time written.

    ``counts`` (full topic -> messages written) is the recorder's public
    count; a topic is in it, at 0, from its subscription on.
    """

    def __init__(self, path):
        self.path = Path(path)
        self.writer = None
        self.batch = None       # BatchWriter of ``writer``
        self.counts: dict[str, int] = {}
        self.conns: dict[str, object] = {}      # full topic -> rosbags Connection
        #: full topic -> the last bag time [ns] written (see Intake.write)
        self.last_stamp: dict[str, int] = {}

    def check_new(self) -> None:
        """BagError if the path exists: a recording never writes over a bag."""
        if os.path.lexists(self.path):
            raise BagError(f'{self.path} exists already; record writes a new bag, '
                           'give a path that does not exist')

    def open(self, namespace: str) -> None:
        """Create the bag (MCAP storage), saying the recorded rig's ``namespace``."""
        writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        writer.set_custom_data(NAMESPACE_KEY, namespace)
        try:
            writer.open()
        except WriterError as exc:
            raise BagError(str(exc)) from exc
        self.writer = writer
        self.batch = BatchWriter(writer)

    @property
    def is_open(self) -> bool:
        return self.writer is not None

    def add_connection(self, topic, type_name, offered_qos):
        """The connection of ``topic``, with the QoS its publishers offer (rclpy
        profiles). The QoS is fixed here, in the MCAP channel and in
        metadata.yaml alike: a reader pairs the two by it."""
        conn = self.writer.add_connection(topic, type_name, typestore=typestore(),
                                          offered_qos_profiles=[qos_to_rosbags(q)
                                                                for q in offered_qos])
        self.conns[topic] = conn
        return conn

    def flush(self):
        """Write the buffered messages to disk as a complete MCAP chunk, so they
        survive a hard kill of this process (see recover_bag)."""
        storage = getattr(self.writer, 'storage', None)
        if storage is None:
            return
        chunk = getattr(storage, 'chunk', None)
        if chunk is not None and hasattr(storage, 'close_chunk') and chunk.bio.tell():
            storage.close_chunk()
        bio = getattr(storage, 'bio', None)
        if bio is not None:
            bio.flush()

    def close(self, abort=False) -> None:
        """Write the MCAP summary and metadata.yaml (``abort``: drop the bag)."""
        writer, self.writer = self.writer, None
        if writer is None:
            return
        if abort:
            writer.abort()
        else:
            writer.close()

    def summary(self, lost) -> str:
        """One line: the messages written per topic, and ``lost`` ones."""
        total = sum(self.counts.values())
        parts = ', '.join(f'{t} {n}' for t, n in self.counts.items() if n or t in self.conns)
        text = f'record: {self.path}: {total} messages ({parts or "no topics"})'
        if lost:
            text += '; LOST (never reached the recorder): ' + ', '.join(
                f'{t} {n}' for t, n in sorted(lost.items()))
        return text
