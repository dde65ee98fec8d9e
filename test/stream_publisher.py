"""A stand-in for the rig's publishers, for bag tests and benchmarks.

    python test/stream_publisher.py --count N --rate HZ [--topics ...]
        [--wait-subscribers K] [--wait-timeout S] [--namespace NS]

Publishes sample k = 0..N-1 on each stream topic (QoS of stewart63_ros.topics)
at HZ, with contents given by :func:`expected` so a test can rebuild exactly
what was sent. ``leg_setpoint`` (latched) is published once, before anything
else. Waits (bounded) until every publisher has K matched subscribers, prints
``MATCHED``, publishes, prints ``DONE <n>``, waits for every reliable
subscriber to acknowledge, prints ``ACKED`` and exits.
"""
from __future__ import annotations

import argparse
import sys
import time

STREAMS = ('leg_lengths', 'leg_forces', 'ground_truth/pose', 'ground_truth/twist')
T0_NS = 1_000_000_000          # stamp of sample 0
LEGS = [f'leg_{i}' for i in range(1, 7)]


def stamp_ns(k: int, rate: float) -> int:
    return T0_NS + int(round(k * 1e9 / rate))


def expected(topic: str, k: int, rate: float = 1000.0) -> dict:
    """Field values of sample ``k`` on ``topic`` (plain Python, no ROS types)."""
    s = stamp_ns(k, rate)
    t = (s - T0_NS) * 1e-9
    stamp = (s // 1_000_000_000, s % 1_000_000_000)
    if topic == 'leg_lengths':
        return {'stamp': stamp, 'frame_id': 'base', 'name': LEGS,
                'position': [1.6 + 0.001 * i + 1e-6 * k for i in range(6)],
                'velocity': [0.01 * i - 1e-5 * k for i in range(6)], 'effort': []}
    if topic == 'leg_forces':
        return {'stamp': stamp, 'frame_id': 'base', 'name': LEGS, 'position': [],
                'velocity': [], 'effort': [100.0 * i + 0.5 * k for i in range(6)]}
    if topic == 'leg_setpoint':
        return {'stamp': (0, 0), 'frame_id': 'base', 'name': LEGS,
                'position': [1.9, 1.9, 1.6, 1.6, 1.6, 1.6], 'velocity': [], 'effort': []}
    if topic == 'ground_truth/pose':
        import math
        a = 0.001 * k
        return {'stamp': stamp, 'frame_id': 'base', 'position': [0.01, 0.01 + 1e-5 * k, 1.0 + t],
                'orientation': [math.sin(a / 2), 0.0, 0.0, math.cos(a / 2)]}
    if topic == 'ground_truth/twist':
        return {'stamp': stamp, 'frame_id': 'base', 'linear': [0.0, 1e-2, 1.0],
                'angular': [1.0, 0.0, 1e-3 * k]}
    raise KeyError(topic)


def build(topic: str, k: int, rate: float):
    from geometry_msgs.msg import PoseStamped, TwistStamped
    from sensor_msgs.msg import JointState
    e = expected(topic, k, rate)
    if topic in ('leg_lengths', 'leg_forces', 'leg_setpoint'):
        m = JointState()
        m.name = e['name']
        m.position, m.velocity, m.effort = e['position'], e['velocity'], e['effort']
    elif topic == 'ground_truth/pose':
        m = PoseStamped()
        p, q = m.pose.position, m.pose.orientation
        p.x, p.y, p.z = e['position']
        q.x, q.y, q.z, q.w = e['orientation']
    else:
        m = TwistStamped()
        m.twist.linear.x, m.twist.linear.y, m.twist.linear.z = e['linear']
        m.twist.angular.x, m.twist.angular.y, m.twist.angular.z = e['angular']
    m.header.stamp.sec, m.header.stamp.nanosec = e['stamp']
    m.header.frame_id = e['frame_id']
    return m


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument('--count', type=int, default=1000)
    p.add_argument('--rate', type=float, default=1000.0)
    p.add_argument('--topics', nargs='+', default=list(STREAMS))
    p.add_argument('--setpoint', action='store_true', help='publish a latched leg_setpoint first')
    p.add_argument('--wait-subscribers', type=int, default=1)
    p.add_argument('--wait-timeout', type=float, default=20.0)
    p.add_argument('--namespace', default=None)
    p.add_argument('--depth', type=int, default=None,
                   help='publisher history depth (default: the topics module\'s)')
    p.add_argument('--keep-all', action='store_true', help='KEEP_ALL publisher history')
    a = p.parse_args(argv)

    import rclpy
    from rclpy.node import Node

    from stewart63_ros import topics as T
    from stewart63_ros.recording.recorder import message_class

    rclpy.init()
    node = Node('stream_publisher', namespace=a.namespace)
    try:
        if a.setpoint:
            sp = node.create_publisher(message_class(T.TOPIC_TYPES['leg_setpoint']),
                                       'leg_setpoint', T.publisher_qos('leg_setpoint'))
            sp.publish(build('leg_setpoint', 0, a.rate))
        def qos(t):
            q = T.publisher_qos(t)
            if a.depth or a.keep_all:
                from rclpy.qos import HistoryPolicy, QoSProfile
                q = QoSProfile(history=HistoryPolicy.KEEP_ALL if a.keep_all else q.history,
                               depth=a.depth or q.depth, reliability=q.reliability,
                               durability=q.durability)
            return q
        pubs = [node.create_publisher(message_class(T.TOPIC_TYPES[t]), t, qos(t))
                for t in a.topics]
        if a.wait_subscribers > 0:
            if not T.wait_for_subscribers(pubs, a.wait_subscribers, a.wait_timeout):
                print('NOT MATCHED', flush=True)
                return 3
        print('MATCHED', flush=True)
        msgs = [[build(t, k, a.rate) for t in a.topics] for k in range(a.count)]
        start = time.monotonic() + 0.01
        late = 0
        for k in range(a.count):
            due = start + k / a.rate
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            elif delay < -0.002:
                late += 1
            for pub, msg in zip(pubs, msgs[k]):
                pub.publish(msg)
        took = time.monotonic() - start
        print(f'DONE {a.count} in {took:.3f} s (late by >2 ms: {late})', flush=True)
        from rclpy.duration import Duration
        acked = all(pub.wait_for_all_acked(Duration(seconds=10)) for pub in pubs)
        print('ACKED' if acked else 'NOT ACKED', flush=True)
        return 0
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    sys.exit(main())
