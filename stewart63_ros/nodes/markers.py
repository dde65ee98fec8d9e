"""``markers``: the rig as a ``visualization_msgs/MarkerArray`` for RViz2 and Foxglove.

A ``MarkerPublisher`` lives in the ``fk`` node, which already has the newest
measured leg lengths and the pose estimated from them at every sample. The
sample path only stores references to them (no work); a timer of the node,
at ``marker_rate`` Hz (default 30, 0 turns markers off), draws the newest
state once (``core.mechanics.markers.Scene``) and publishes it. It publishes only when a
new sample came since the last array, so marker stamps (the sample's stamp)
strictly increase, in simulated or recorded time alike.

Forces for the colours come from ``leg_forces`` (the newest one, taken as
bytes and read only when drawn); the ghost is the setpoint: the
``setpoint_lengths`` parameter, then the newest ``pose_setpoint`` or
``leg_setpoint`` (turned into a pose by forward kinematics, the assembly
mode nearest the platform), a setpoint outside the stroke ignored, as the
controller refuses it. Where ``tf2_msgs`` is importable (a ROS install) the
same timer broadcasts the ``base`` -> ``platform`` transform on ``/tf``.
"""
from __future__ import annotations

import copy

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, PoseStamped, TransformStamped
from rclpy.serialization import serialize_message
from sensor_msgs.msg import JointState
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from stewart63_ros import topics
from stewart63_ros.core.mechanics import markers as shapes_mod
from stewart63_ros.core.mechanics.fk import NoAssemblyError
from stewart63_ros.core.mechanics.kinematics import leg_lengths
from stewart63_ros.core.mechanics.rotation import quaternion_from_rotation, rotation_from_quaternion
from stewart63_ros.runtime import wire
from stewart63_ros.runtime.commands import CommandInput

FRAME = 'base'
PLATFORM_FRAME = 'platform'

_KIND = {}


def _kinds():
    if not _KIND:
        _KIND.update({shapes_mod.CYLINDER: Marker.CYLINDER, shapes_mod.SPHERE: Marker.SPHERE,
                      shapes_mod.SPHERE_LIST: Marker.SPHERE_LIST,
                      shapes_mod.TRIANGLE_LIST: Marker.TRIANGLE_LIST,
                      shapes_mod.LINE_LIST: Marker.LINE_LIST})
    return _KIND


class MarkerArrayBuilder:
    """Shapes -> one MarkerArray, its Marker objects made once and refilled."""

    def __init__(self, frame_id: str = FRAME):
        self.frame_id = frame_id
        self.msg = None

    def build(self, shape_list, sec: int, nanosec: int):
        kinds = _kinds()
        if self.msg is None or len(self.msg.markers) != len(shape_list):
            self.msg = MarkerArray(markers=[Marker() for _ in shape_list])
        for marker, shape in zip(self.msg.markers, shape_list):
            marker.header.frame_id = self.frame_id
            marker.header.stamp = Time(sec=int(sec), nanosec=int(nanosec))
            marker.ns = shape.ns
            marker.id = shape.id
            marker.type = kinds[shape.kind]
            marker.action = Marker.ADD
            r, g, b, a = (float(c) for c in shape.color)
            marker.color = ColorRGBA(r=r, g=g, b=b, a=a)
            marker.scale.x, marker.scale.y, marker.scale.z = (float(v) for v in shape.scale)
            pose = marker.pose
            if shape.position is not None and shape.kind in (shapes_mod.CYLINDER,
                                                              shapes_mod.SPHERE):
                pose.position.x, pose.position.y, pose.position.z = (
                    float(v) for v in shape.position)
                q = shape.orientation
                pose.orientation.x, pose.orientation.y = float(q[0]), float(q[1])
                pose.orientation.z, pose.orientation.w = float(q[2]), float(q[3])
                marker.points = []
            else:
                pose.orientation.w = 1.0
                marker.points = [Point(x=float(p[0]), y=float(p[1]), z=float(p[2]))
                                 for p in shape.points]
        return self.msg


class MarkerTemplate:
    """The serialized MarkerArray of a scene, refilled in place per frame.

    Like the 1 kHz messages (runtime/wire.py): the array is built and
    serialized once by rclpy with distinct sentinels in every number that
    changes (``core.mechanics.markers.flatten`` order: poses, scales, points as
    float64, colours as float32, each marker's stamp); the sentinels found in
    the bytes give the offsets, and a frame is numpy stores into them. A
    rosidl MarkerArray of 24 markers costs milliseconds to fill and
    serialize in Python; this costs tens of microseconds.

    The serializer leaves its alignment padding (up to 7 bytes) uninitialised,
    so it holds whatever the buffer held before, often an earlier template
    with the same sentinels: a lone 4-byte sentinel matched padding in 7 % of
    templates. So each field is found as a whole group of at least 16 bytes
    (a pose, a scale, a point list, a colour, a stamp with its frame id),
    whose first 9 bytes or more can only be real data, at its CDR alignment,
    exactly once.
    """

    def __init__(self, shape_list, frame_id: str = FRAME):
        n8, n4 = (len(v) for v in shapes_mod.flatten(shape_list))
        s8 = 1.0e9 + 0.123456789 + np.arange(n8) * 0.5           # exact, distinct
        s4 = (1000.0 + np.arange(n4) * 0.25).astype(np.float32)
        shapes, self.m8, groups8 = _with_numbers(shape_list, s8, s4)
        msg = MarkerArrayBuilder(frame_id).build(shapes, 0, 0)
        for k, marker in enumerate(msg.markers):
            marker.header.stamp = Time(sec=0x12340000 + k, nanosec=0x0FEDCBA9)
        self.buf = bytearray(serialize_message(msg))
        # CDR aligns to the payload, which starts after the 4-byte header.
        self.f8 = np.frombuffer(self.buf, dtype='<f8', offset=4,
                                count=(len(self.buf) - 4) // 8)
        self.f4 = np.frombuffer(self.buf, dtype='<f4', offset=4,
                                count=(len(self.buf) - 4) // 4)
        self.u4 = np.frombuffer(self.buf, dtype='<u4', offset=4,
                                count=(len(self.buf) - 4) // 4)
        self.i8 = np.empty(n8, dtype=int)
        for group in groups8:
            self.i8[group] = self._find(s8[group].astype('<f8').tobytes(), 8, len(group))
        self.i8 = self.i8[self.m8]
        self.i4 = np.concatenate([self._find(s4[b:b + 4].astype('<f4').tobytes(), 4, 4)
                                  for b in range(0, n4, 4)])
        frame = frame_id.encode()
        frame_bytes = np.array([len(frame) + 1], '<u4').tobytes() + frame + b'\0'
        self.sec = np.array([
            self._find(np.array([0x12340000 + k, 0x0FEDCBA9], '<u4').tobytes() + frame_bytes,
                       4, 1)[0] for k in range(len(msg.markers))])
        self.nanosec = self.sec + 1

    def _find(self, packed: bytes, size: int, count: int) -> np.ndarray:
        """Indices (in units of ``size`` from the payload) of the ``count``
        numbers that open the one aligned occurrence of ``packed``."""
        hits = []
        pos = self.buf.find(packed)
        while pos >= 0:
            if (pos - 4) % size == 0:
                hits.append(pos)
            pos = self.buf.find(packed, pos + 1)
        if len(hits) != 1:
            raise RuntimeError('unexpected MarkerArray serialization: a field found %d times'
                               % len(hits))
        return (hits[0] - 4) // size + np.arange(count)

    def fill(self, sec: int, nanosec: int, f8, f4) -> bytes:
        self.f8[self.i8] = f8[self.m8]
        self.f4[self.i4] = f4
        self.u4[self.sec] = sec & 0xFFFFFFFF
        self.u4[self.nanosec] = nanosec
        return bytes(self.buf)


def _with_numbers(shape_list, f8, f4):
    """Copies of the shapes carrying the numbers f8, f4 (``flatten`` order);
    the mask of the f8 entries a marker holds (a list kind's pose is the
    identity, fixed: not in the mask); and the index arrays of the f8 fields
    that lie contiguous in the serialized message (pose, scale, points)."""
    out, groups, a, b = [], [], 0, 0
    used = np.ones(len(f8), dtype=bool)
    for shape in shape_list:
        shape = copy.copy(shape)
        if shape.kind in (shapes_mod.CYLINDER, shapes_mod.SPHERE):
            shape.position, shape.orientation = f8[a:a + 3], f8[a + 3:a + 7]
            groups.append(np.arange(a, a + 7))
        else:
            used[a:a + 7] = False
        shape.scale = tuple(f8[a + 7:a + 10])
        groups.append(np.arange(a + 7, a + 10))
        a += 10
        if shape.kind not in (shapes_mod.CYLINDER, shapes_mod.SPHERE):
            n = shape.points.size
            shape.points = f8[a:a + n].reshape(-1, 3)
            if n:
                groups.append(np.arange(a, a + n))
            a += n
        shape.color = tuple(float(c) for c in f4[b:b + 4])
        b += 4
        out.append(shape)
    return out, used, groups


class MarkerPublisher:
    """The ``markers`` timer of a node that sees every sample (see module doc)."""

    def __init__(self, node, setup, rate: float, fk=None):
        self.node = node
        self.mech = mech = setup.mechanism
        self.fk = fk
        self.scene = shapes_mod.Scene(mech)
        self.template = MarkerTemplate(self.scene.shapes(setup.task.initial_position, np.eye(3)))
        # A data publisher of the node: the subscriptions the graph shows are
        # waited for before the first sample like the 1 kHz topics' (a recorder
        # started first gets every array); flushed at the end.
        self.pub = node.publisher(MarkerArray, topics.MARKERS, topics.MARKERS_QOS,
                                  required=False)
        self.tf_pub = self._tf_publisher(node)
        self.sample = None            # (sec, nanosec, lengths, position, rotation)
        self.drawn = None             # the sample last drawn
        self.forces_data = None
        self.ghost = None
        self.published = 0
        self.set_ghost_lengths(np.asarray(setup.task.setpoint_lengths, dtype=float))
        # The newest force only: taken as bytes, read when drawn.
        node.create_subscription(JointState, topics.LEG_FORCES, self.on_forces,
                                 topics.LATEST_SUB, raw=True)
        # The setpoints as the controller takes them: volatile and latched publishers.
        self.commands = [
            CommandInput(node, PoseStamped, topics.POSE_SETPOINT, self.on_pose_setpoint),
            CommandInput(node, JointState, topics.LEG_SETPOINT, self.on_leg_setpoint)]
        self.timer = node.create_timer(1.0 / rate, self.publish)

    @staticmethod
    def _tf_publisher(node):
        try:
            # lazy: optional: tf2_msgs comes with a ROS install, not the wheels
            from tf2_msgs.msg import TFMessage
        except ImportError:        # the Python wheels have no tf2_msgs: markers only
            return None
        return node.create_publisher(TFMessage, '/tf', 10)

    # -- inputs (cheap: they only store) ---------------------------------------
    def on_sample(self, sec, nanosec, lengths, position, rotation):
        self.sample = (sec, nanosec, lengths, position, rotation)

    def on_forces(self, data):
        self.forces_data = data

    def in_stroke(self, lengths) -> bool:
        return bool(np.all((lengths >= self.mech.leg_length_min)
                           & (lengths <= self.mech.leg_length_max)))

    def set_ghost_lengths(self, lengths):
        if lengths is None or self.fk is None or not self.in_stroke(lengths):
            return
        ref = (self.ghost if self.ghost is not None else
               (self.sample[3], self.sample[4]) if self.sample is not None else
               self.fk.reference)
        try:
            result = self.fk.nearest(lengths, *ref)
        except NoAssemblyError:
            return
        self.ghost = (np.asarray(result.position), np.asarray(result.rotation))

    def on_pose_setpoint(self, msg):
        p, q = msg.pose.position, msg.pose.orientation
        position = np.array([p.x, p.y, p.z])
        quat = np.array([q.x, q.y, q.z, q.w])
        norm = np.linalg.norm(quat)
        if not (np.all(np.isfinite(position)) and np.isfinite(norm) and 0.9 < norm < 1.1):
            return
        rot = rotation_from_quaternion(quat / norm)
        if self.in_stroke(leg_lengths(self.mech, position, rot)):
            self.ghost = (position, rot)

    def on_leg_setpoint(self, msg):
        values = np.asarray(msg.position, dtype=float)
        if values.shape == (6,) and np.all(np.isfinite(values)):
            self.set_ghost_lengths(values)

    # -- the timer ---------------------------------------------------------------
    def forces(self):
        data = self.forces_data
        if data is None:
            return None
        fast = wire.read_joint_state(data, ('effort',))
        if fast is not None:
            return fast[3]['effort']
        msg = wire.deserialize(data, JointState)    # None if malformed: drawn grey
        if msg is None or len(msg.effort) != 6:
            return None
        return np.asarray(msg.effort, dtype=float)

    def publish(self):
        sample = self.sample
        if sample is None or sample is self.drawn:
            return
        self.drawn = sample
        sec, nanosec, lengths, position, rotation = sample
        f8, f4 = self.scene.flat(position, rotation, lengths, self.forces(), self.ghost)
        self.pub.publish(self.template.fill(sec, nanosec, f8, f4))
        self.published += 1
        if self.tf_pub is not None:
            self.tf_pub.publish(self._transform(sec, nanosec, position, rotation))

    def _transform(self, sec, nanosec, position, rotation):
        # lazy: optional: tf2_msgs comes with a ROS install, not the wheels
        from tf2_msgs.msg import TFMessage

        tf = TransformStamped()
        tf.header.frame_id = FRAME
        tf.header.stamp.sec, tf.header.stamp.nanosec = int(sec), int(nanosec)
        tf.child_frame_id = PLATFORM_FRAME
        tr = tf.transform
        tr.translation.x, tr.translation.y, tr.translation.z = (float(v) for v in position)
        q = quaternion_from_rotation(rotation)
        tr.rotation.x, tr.rotation.y, tr.rotation.z, tr.rotation.w = (float(v) for v in q)
        return TFMessage(transforms=[tf])
