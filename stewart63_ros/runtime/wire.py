"""The 1 kHz messages as bytes: read and written without rosidl Python objects.

A rosidl message object costs tens of microseconds per sample on the hot
paths (every field goes through a checked Python property, the C
typesupport converts the object to and from C, and it serializes), on a
loop whose whole budget is one millisecond. The nodes therefore subscribe
to ``leg_lengths`` / ``leg_forces`` with ``raw=True`` and publish pre-built
serialized messages (``Publisher.publish(bytes)``); the bytes on the wire
are the same CDR the middleware would have produced.

- Writing: a ``Template`` is a message serialized once by rclpy itself with
  sentinel values; filling it in overwrites the stamp and the numbers in
  place, so the layout (alignment, padding, strings) is rclpy's own.
- Reading: ``read_joint_state`` accepts only the common, valid case (plain
  little-endian CDR, names empty or exactly leg_1..leg_6, the wanted fields
  six finite numbers) and returns None for anything else; the caller then
  deserializes the message the ordinary way and runs its usual checks, so
  every rejection (reason, count, report) is exactly what it was.
"""
from __future__ import annotations

import operator
import re
import struct

import numpy as np
from geometry_msgs.msg import PoseStamped, TwistStamped
from rclpy.serialization import deserialize_message, serialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState

from stewart63_ros.core.plumbing.params import LEG_NAMES
from stewart63_ros.core.plumbing.stamps import ns_of
from stewart63_ros.runtime.checks import Rejected, StampGate, leg_vector

#: Plain CDR, little endian (the 4-byte encapsulation header).
CDR_LE = b'\x00\x01\x00\x00'
_STAMP = struct.Struct('<iI')
_U32 = struct.Struct('<I')
_HEAD = struct.Struct('<iII')     # stamp sec, nanosec; frame_id length
_LEG_NAMES_B = [name.encode() for name in LEG_NAMES]
_JOINT_FIELDS = ('position', 'velocity', 'effort')


class Template:
    """One serialized message with its stamp and float64 fields writable in place.

    ``fields`` maps a name to a path setter: ``lambda msg, values: ...`` that
    puts the sentinel ``values`` (a list of floats) into a message. The
    sentinels are found again in the serialized bytes, which gives the
    offsets; a message type whose header stamp is not at the start of the
    payload (all used here have it there) would be refused.
    """

    def __init__(self, msg, fields: dict, sizes: dict, end=None):
        self.msg_type = type(msg)
        offsets = {}
        for i, (name, setter) in enumerate(fields.items()):
            sentinel = [_sentinel(i, j) for j in range(sizes[name])]
            setter(msg, sentinel)
            offsets[name] = sentinel
        header = getattr(msg, 'header', None)
        stamp = header.stamp if header is not None else msg.clock
        stamp.sec, stamp.nanosec = 0x12345678, 0x0FEDCBA9
        data = serialize_message(msg)
        if data[:4] != CDR_LE or data.find(_STAMP.pack(0x12345678, 0x0FEDCBA9)) != 4:
            raise RuntimeError('unexpected serialization of %s' % self.msg_type.__name__)
        # serialize_message returns a buffer of the estimated size, up to 8
        # bytes longer than the message with sequences in it; on the wire the
        # payload is the exact size, and strict readers (rosbags, recording)
        # refuse any other.
        self.buf = bytearray(data[:end(data)] if end is not None else data)
        self.views = {}
        for name, sentinel in offsets.items():
            packed = struct.pack('<%dd' % len(sentinel), *sentinel)
            at = self.buf.find(packed)
            if at < 0 or self.buf.find(packed, at + 1) >= 0:
                raise RuntimeError('cannot locate %s in %s' % (name, self.msg_type.__name__))
            self.views[name] = np.frombuffer(self.buf, dtype='<f8', count=len(sentinel),
                                             offset=at)

    def fill(self, sec: int, nanosec: int, **values) -> bytes:
        """The serialized message with this stamp and these field values."""
        _STAMP.pack_into(self.buf, 4, sec, nanosec)
        for name, value in values.items():
            self.views[name][:] = value
        return bytes(self.buf)


def _sentinel(i: int, j: int) -> float:
    # Distinct, unmistakable doubles (no other bytes of a small message match them).
    return -1.234567890123e-300 * (1 + i * 16 + j)


class FrameTemplates:
    """A template per frame_id (str or UTF-8 bytes) made by ``make(frame_id_str)``."""

    def __init__(self, make):
        self.make = make
        self._by_frame = {}

    def get(self, frame_id) -> Template:
        tpl = self._by_frame.get(frame_id)
        if tpl is None:
            text = frame_id.decode('utf-8') if isinstance(frame_id, bytes) else frame_id
            tpl = self.make(text)
            if len(self._by_frame) > 16:     # frame ids are few; never grow without bound
                self._by_frame.clear()
            self._by_frame[frame_id] = tpl
        return tpl


def joint_state_template(frame_id: str = 'base', fields=('position', 'velocity')) -> Template:
    """JointState with names leg_1..leg_6 and the six-number ``fields``."""
    msg = JointState(name=list(LEG_NAMES))
    msg.header.frame_id = frame_id
    return Template(msg, {f: _setter(f) for f in fields}, {f: 6 for f in fields},
                    end=joint_state_end)


class JointStateTemplates(FrameTemplates):
    """Serialized JointState (names leg_1..leg_6) per frame_id, for one set of fields."""

    def __init__(self, fields=('position', 'velocity')):
        fields = tuple(fields)
        super().__init__(lambda frame_id: joint_state_template(frame_id, fields))


def _setter(field):
    def put(msg, values):
        setattr(msg, field, values)
    return put


def pose_template(frame_id: str = 'base') -> Template:
    """PoseStamped: fields 'position' (x, y, z) and 'orientation' (x, y, z, w)."""
    msg = PoseStamped()
    msg.header.frame_id = frame_id

    def position(m, v):
        m.pose.position.x, m.pose.position.y, m.pose.position.z = v

    def orientation(m, v):
        o = m.pose.orientation
        o.x, o.y, o.z, o.w = v
    return Template(msg, {'position': position, 'orientation': orientation},
                    {'position': 3, 'orientation': 4})


def twist_template(frame_id: str = 'base') -> Template:
    """TwistStamped: fields 'linear' and 'angular' (x, y, z each)."""
    msg = TwistStamped()
    msg.header.frame_id = frame_id

    def linear(m, v):
        m.twist.linear.x, m.twist.linear.y, m.twist.linear.z = v

    def angular(m, v):
        m.twist.angular.x, m.twist.angular.y, m.twist.angular.z = v
    return Template(msg, {'linear': linear, 'angular': angular}, {'linear': 3, 'angular': 3})


def clock_template() -> Template:
    return Template(Clock(), {}, {})


# -- reading -------------------------------------------------------------------
#: names leg_1..leg_6 as CDR: each string is its length (6), 5 letters and a
#: NUL, then 2 bytes of padding (any content) up to the next 4-byte boundary.
_LEG_NAMES_RE = re.compile(b''.join(re.escape(_U32.pack(6) + name + b'\x00') + b'..'
                                    for name in _LEG_NAMES_B), re.DOTALL)
_F64x6 = struct.Struct('<6d')


def read_joint_state(data: bytes, want: tuple, optional: tuple = ()):
    """Fast path for a serialized JointState: (sec, nanosec, frame_id,
    {field: array of 6}) or None when the message is anything but the plain
    valid case (the caller then deserializes and checks it as usual).

    ``want``: fields that must hold six finite numbers; ``optional``: fields
    that may also be empty (then absent from the result). Fields in neither
    are skipped whatever they hold. Names must be empty or leg_1..leg_6.

    A stream repeats one layout (frame id, names, sizes): the layout of the
    last message read is kept per size as one ``struct`` format, and a
    message whose every byte outside the numbers, the stamp and the padding
    equals that layout's is read with a single unpack (a few microseconds
    less per message than walking it); any other goes the long way.
    """
    key = (len(data), want, optional)
    layout = _LAYOUTS.get(key)
    if layout is not None:
        got = layout.read(data)
        if got is not None:
            return got
    return _read_joint_state_walk(data, want, optional, key)


class _Layout:
    """One JointState layout as a struct format: the stamp, the numbers of the
    fields read, the constant bytes between them (compared) and the padding
    (skipped, whatever it holds)."""

    def __init__(self, parts: list, frame_id: str):
        # parts: ('const', bytes) | ('pad', n) | ('field', name) in message order,
        # after the 4-byte encapsulation header and the stamp.
        fmt, expected, fields, items = ['4xiI'], [], [], 2
        run = b''
        for kind, value in parts + [('end', None)]:
            if kind == 'const':
                run += value
                continue
            if run:
                fmt.append('%ds' % len(run))
                expected.append(run)
                items += 1
                run = b''
            if kind == 'pad' and value:
                fmt.append('%dx' % value)
            elif kind == 'field':
                fmt.append('6d')
                fields.append((value, items))
                items += 6
        self.struct = struct.Struct('<' + ''.join(fmt))
        index = [i for i in range(2, items) if not any(at <= i < at + 6 for _, at in fields)]
        self.expected = tuple(expected)
        self.constants = operator.itemgetter(*index) if len(index) > 1 else (
            lambda items, i=index[0]: (items[i],))
        self.fields = fields            # (name, index of its first number)
        self.frame_id = frame_id

    def read(self, data):
        try:
            items = self.struct.unpack_from(data)
        except struct.error:
            return None
        if self.constants(items) != self.expected:
            return None
        values = {}
        for name, at in self.fields:
            numbers = items[at:at + 6]
            total = sum(numbers)
            if total - total != 0.0:        # not all finite: the long way decides
                return None
            values[name] = np.array(numbers)
        return items[0], items[1], self.frame_id, values


#: (size, want, optional) -> the _Layout of the last message of that size read
_LAYOUTS: dict = {}


def _read_joint_state_walk(data, want, optional, key):
    """read_joint_state the long way; remembers the layout of a message it reads."""
    try:
        if data[:4] != CDR_LE:
            return None
        size = len(data)
        sec, nanosec, length = _HEAD.unpack_from(data, 4)
        end = 16 + length
        if length < 1 or end > size or data[end - 1] != 0:
            return None
        frame_id = data[16:end - 1]
        if b'\x00' in frame_id:
            return None
        frame_id = frame_id.decode('utf-8')
        # The layout as it is walked (see _Layout).
        parts = [('const', bytes(data[12:end]))]
        o = end + (-end & 3)          # 4-byte alignment (the payload starts at 4)
        parts.append(('pad', o - end))
        count = _U32.unpack_from(data, o)[0]
        parts.append(('const', _U32.pack(count)))
        o += 4
        if count == 6:
            if _LEG_NAMES_RE.match(data, o) is None:
                return None
            for name in _LEG_NAMES_B:
                parts += [('const', _U32.pack(len(name) + 1) + name + b'\x00'), ('pad', 2)]
            o += 72
        elif count != 0:
            return None
        values = {}
        for field in _JOINT_FIELDS:
            pad = -o & 3
            o += pad
            count = _U32.unpack_from(data, o)[0]
            parts += [('pad', pad), ('const', _U32.pack(count))]
            o += 4
            if count:
                pad = -(o - 4) & 7     # 8-byte alignment relative to the payload
                o += pad
                parts.append(('pad', pad))
            if field in want or field in optional:
                if count == 6:
                    numbers = _F64x6.unpack_from(data, o)
                    total = sum(numbers)      # inf or nan unless all six are finite
                    if total - total != 0.0:  # (or the sum overflows: the slow path decides)
                        return None
                    values[field] = np.array(numbers)
                    parts.append(('field', field))
                elif count or field in want:
                    return None
            elif count:
                parts.append(('pad', 8 * count))
            o += 8 * count
            if o > size:
                return None
        if len(_LAYOUTS) > 64:          # sizes are few; never grow without bound
            _LAYOUTS.clear()
        _LAYOUTS[key] = _Layout(parts, frame_id)
        return sec, nanosec, frame_id, values
    except (struct.error, IndexError, ValueError):   # UnicodeDecodeError is a ValueError
        return None


def joint_state_end(data: bytes) -> int:
    """Where a serialized JointState ends (its exact size)."""
    length = _U32.unpack_from(data, 12)[0]
    o = 16 + length
    o += -o & 3
    names = _U32.unpack_from(data, o)[0]
    o += 4
    for _ in range(names):
        o += -o & 3
        o += 4 + _U32.unpack_from(data, o)[0]
    for _ in _JOINT_FIELDS:
        o += -o & 3
        count = _U32.unpack_from(data, o)[0]
        o += 4
        if count:
            o += -(o - 4) & 7
        o += 8 * count
    return o


def deserialize(data: bytes, msg_type):
    """The message object, or None if the bytes are not one."""
    try:
        return deserialize_message(data, msg_type)
    except Exception:  # noqa: BLE001 - any undecodable input is rejected by the caller
        return None


def joint_state_sample(data: bytes, gate, want: tuple, optional: tuple = (), source=None):
    """A serialized leg JointState, checked: (stamp ns, sec, nanosec, frame_id,
    {field: array of 6}), or Rejected exactly as for a message object:
    the stamp against ``gate`` first (not accepted here; ``source``: the
    sending publisher, see StampGate), then the fields in
    order with ``leg_vector``; an ``optional`` field may be empty (absent).
    A sample refused for its content alone says its stamp (``Rejected.stamp_ns``)."""
    fast = read_joint_state(data, want, optional)
    if fast is not None:
        sec, nanosec, frame_id, values = fast
        ns = gate.check_ns(ns_of(sec, nanosec), source)
        gate.check_source(source)
        return ns, sec, nanosec, frame_id, values
    msg = deserialize(data, JointState)
    if msg is None:
        raise Rejected('undecodable', 'not a serialized sensor_msgs/JointState')
    stamp = msg.header.stamp
    ns = gate.check(stamp, source)
    values = {}
    try:
        for field in want:
            values[field] = leg_vector(msg.name, getattr(msg, field), field)
        for field in optional:
            if len(getattr(msg, field)):
                values[field] = leg_vector(msg.name, getattr(msg, field), field)
    except Rejected as exc:
        if not gate.second:
            exc.stamp_ns = ns       # a sample of the run, in order: only its content refused
        raise
    gate.check_source(source)
    return ns, stamp.sec, stamp.nanosec, msg.header.frame_id, values


def warm_up(want: tuple, optional: tuple = (), frame_id: str = 'base') -> None:
    """Run the reading path once on a sample (its first call costs about a
    millisecond: the first sample of a realtime run would be late)."""
    sample = JointStateTemplates(want + optional).get(frame_id).fill(
        0, 0, **{field: np.ones(6) for field in want + optional})
    joint_state_sample(sample, StampGate(), want, optional)
