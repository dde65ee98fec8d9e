"""Run by test_control_dds: a controller's watchdog in one staged scenario.
Prints one JSON line.

    watchdog_probe.py stall              a process stalled past its watchdog
                                         while a sample waited in its queue
    watchdog_probe.py dropout MODE       a sensor dropout (a leg NaN) that lasts
                                         longer than the watchdog, clock_mode MODE
"""
from __future__ import annotations

import json
import sys
import time

import rclpy
from rclpy.node import Node
from sensor_msgs.msg import JointState

from stewart63_ros import topics
from stewart63_ros.core.plumbing.params import load_setup
from stewart63_ros.nodes.controller import ControllerNode
from stewart63_ros.runtime.parameters import set_arguments
from stewart63_ros.runtime.rclpy_internals import WaitAny

#: s, the controller's watchdog_timeout here
TIMEOUT = 0.5


def main(argv) -> int:
    scenario = argv[1]
    mode = argv[2] if len(argv) > 2 else 'realtime'
    set_arguments([argv[0], '--ros-args', '-p', 'watchdog_timeout:=%g' % TIMEOUT,
                   '-p', 'clock_mode:=%s' % mode])
    rclpy.init()
    controller = ControllerNode(None)
    controller.subscribe_input()        # (its start-up wait, which makes it, is not run here)
    sensor = Node('probe_sensor')
    pub = sensor.create_publisher(JointState, topics.LEG_LENGTHS, topics.STREAM_PUB)
    # as a plant's: the reader of the answers (a lockstep controller's first one waits for it)
    sensor.create_subscription(JointState, topics.LEG_FORCES, lambda _msg: None,
                               topics.LATEST_SUB)
    deadline = time.monotonic() + 20
    while pub.get_subscription_count() < 1 and time.monotonic() < deadline:
        time.sleep(0.01)
    setup = load_setup()
    lengths = [float(x) for x in setup.task.setpoint_lengths]

    def send(k: int, dropped_leg: int | None = None) -> None:
        position, velocity = list(lengths), [0.0] * 6
        if dropped_leg is not None:
            position[dropped_leg] = velocity[dropped_leg] = float('nan')
        msg = JointState(name=['leg_%d' % i for i in range(1, 7)], position=position,
                         velocity=velocity)
        msg.header.stamp.sec, msg.header.stamp.nanosec = 1, k * 1_000_000
        msg.header.frame_id = 'base'
        pub.publish(msg)

    waiting = WaitAny(controller.context, [controller.sub_samples])
    # A first sample, handled: the watchdog is armed from here.
    send(1)
    waiting.wait(10.0)
    controller.read_queued()
    first = controller.last_sample_wall is not None
    if scenario == 'stall':
        # The process "stalls": a second sample arrives and waits in the queue
        # while the clock runs past the watchdog's timeout.
        send(2)
        waiting.wait(10.0)
        controller.last_sample_wall = time.monotonic() - 1.0
        controller.watchdog()
    else:
        # Leg 5 drops out for twice the watchdog's timeout: a NaN sample every
        # 10 ms, each handled, the watchdog judging after each.
        k = 2
        end = time.monotonic() + 2 * TIMEOUT
        while time.monotonic() < end:
            send(k, dropped_leg=4)
            waiting.wait(1.0)
            controller.read_queued()
            controller.watchdog()
            k += 1
            time.sleep(0.01)
    print(json.dumps({'first_handled': first, 'tripped': controller.tripped,
                      'fault': controller.health.fault,
                      'received': controller.health.received[topics.LEG_LENGTHS],
                      'rejected': dict(controller.health.rejected)}))
    controller.destroy_node()
    sensor.destroy_node()
    rclpy.shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv))
