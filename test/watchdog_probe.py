"""Run by test_control_dds: a controller whose process was stalled past its
watchdog while a sample waited in its queue. Prints one JSON line."""
from __future__ import annotations

import json
import sys
import time

import rclpy
from rclpy.node import Node
from sensor_msgs.msg import JointState

from stewart63_ros import topics
from stewart63_ros.core.params import load_mechanism
from stewart63_ros.nodes.controller import ControllerNode
from stewart63_ros.nodes.parameters import set_arguments
from stewart63_ros.nodes.rclpy_internals import WaitAny


def main() -> int:
    set_arguments([sys.argv[0], '--ros-args', '-p', 'watchdog_timeout:=0.5'])
    rclpy.init()
    controller = ControllerNode(None)
    sensor = Node('probe_sensor')
    pub = sensor.create_publisher(JointState, topics.LEG_LENGTHS, topics.STREAM_PUB)
    deadline = time.monotonic() + 20
    while pub.get_subscription_count() < 1 and time.monotonic() < deadline:
        time.sleep(0.01)
    mech = load_mechanism()
    lengths = [float(x) for x in mech.setpoint_lengths]

    def send(k: int) -> None:
        msg = JointState(name=['leg_%d' % i for i in range(1, 7)], position=lengths,
                         velocity=[0.0] * 6)
        msg.header.stamp.sec, msg.header.stamp.nanosec = 1, k * 1_000_000
        msg.header.frame_id = 'base'
        pub.publish(msg)

    waiting = WaitAny(controller.context, [controller.sub_samples])
    # A first sample, handled: the watchdog is armed from here.
    send(1)
    waiting.wait(10.0)
    controller.read_queued()
    first = controller.last_sample_wall is not None
    # The process "stalls": a second sample arrives and waits in the queue
    # while the clock runs past the watchdog's timeout.
    send(2)
    waiting.wait(10.0)
    controller.last_sample_wall = time.monotonic() - 1.0
    controller.watchdog()
    print(json.dumps({'first_handled': first, 'tripped': controller.tripped,
                      'fault': controller.health.fault,
                      'received': controller.health.received[topics.LEG_LENGTHS]}))
    controller.destroy_node()
    sensor.destroy_node()
    rclpy.shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
