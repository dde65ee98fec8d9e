"""The floor under the lockstep figures: what DDS and the compiled kernels
cost per sample with none of the nodes' own code. Prints figures, asserts nothing.

- ``composed_dds_us``: one composed-rig sample's traffic in one process and
  nothing else: leg_lengths published to two subscriptions (controller, fk)
  and taken by both, leg_forces published and taken by the plant,
  platform_pose and platform_twist published; the rig's QoS profiles and
  serialized templates (runtime/wire.py), raw takes as the nodes do them.
- ``composed_dds_kernels_us``: the same with the sample's compiled work in
  between (leg lengths and rates, eq. 40, one dynamics step, tracking FK
  with its twist and quaternion) on real numbers: a composed sample with no
  parsing, checks, counters, timers or diagnostics. 10 000 samples/s is 100 µs.
- ``composed_dds_kernels_read_us``: the same, each taken message also read
  into numbers by the nodes' fast path (``wire.read_joint_state``), and the
  numbers read are the ones worked on: the least a node can do with a message.
- ``kernels_alone_us``: that work alone, in a tight loop (the caches warm).
- ``xproc_publish_cpu_us`` / ``xproc_take_cpu_us``: a message between
  processes as in the separate-process rig at 1 kHz: one publisher, two
  subscriber processes that wait for each message (they sleep between
  messages, as the nodes do). CPU time of one publish in the publisher's
  thread, and of one wait-and-take in a subscriber's main thread;
  ``sleep_wake_cpu_us``: a 0.5 ms sleep's CPU cost alone, for scale.

Each figure is the median over ``--repeat`` rounds taken in turn.

    bench_floor.py [--samples N] [--repeat R] [--json]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import rclpy
from geometry_msgs.msg import PoseStamped, TwistStamped
from sensor_msgs.msg import JointState

from stewart63_ros import topics
from stewart63_ros.core.controllers.laws import Controller
from stewart63_ros.core.controllers.simulate import initial_state, substeps_for
from stewart63_ros.core.mechanics.dynamics import Dynamics
from stewart63_ros.core.mechanics.fk import FKTracker
from stewart63_ros.core.plumbing.params import load_setup
from stewart63_ros.runtime import wire
from stewart63_ros.runtime.rclpy_internals import WaitAny, raw_publisher, take, take_with_info

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import bench_loop  # noqa: E402

#: s: the longest any wait here blocks (discovery, a subscriber's run)
WAIT = 30.0


class ComposedFloor:
    """Three nodes in this process with the composed rig's topics."""

    def __init__(self):
        self.take_with_info = take_with_info
        self.nodes = [rclpy.create_node(n) for n in ('floor_plant', 'floor_controller', 'floor_fk')]
        plant, ctl, fk = self.nodes
        pubs = (plant.create_publisher(JointState, 'floor/leg_lengths', topics.STREAM_PUB),
                ctl.create_publisher(JointState, 'floor/leg_forces', topics.STREAM_PUB),
                fk.create_publisher(PoseStamped, 'floor/platform_pose', topics.STREAM_PUB),
                fk.create_publisher(TwistStamped, 'floor/platform_twist', topics.STREAM_PUB))

        def ignore(_):
            pass
        self.subs = (ctl.create_subscription(JointState, 'floor/leg_lengths', ignore,
                                             topics.LATEST_SUB, raw=True),
                     fk.create_subscription(JointState, 'floor/leg_lengths', ignore,
                                            topics.EVERY_SUB, raw=True),
                     plant.create_subscription(JointState, 'floor/leg_forces', ignore,
                                               topics.LATEST_SUB, raw=True))
        deadline = time.monotonic() + WAIT
        while (pubs[0].get_subscription_count() < 2 or pubs[1].get_subscription_count() < 1
               or any(s.get_publisher_count() < 1 for s in self.subs)):
            if time.monotonic() > deadline:
                raise RuntimeError('the floor nodes did not match within %g s' % WAIT)
            time.sleep(0.01)
        self.send = [raw_publisher(p) for p in pubs]
        self.templates = (wire.JointStateTemplates().get('base'),
                          wire.JointStateTemplates(('effort',)).get('base'),
                          wire.pose_template(), wire.twist_template())
        self.setup = setup = load_setup()
        self.mech = mech = setup.mechanism
        self.dyn = Dynamics(mech)
        self.y0 = initial_state(setup.task)
        self.substeps = substeps_for(1e-3)
        self.control = Controller(setup)
        self.tracker = FKTracker(mech, setup.task.initial_position, setup.task.initial_rotation)
        self.np = np
        self.read_joint_state = wire.read_joint_state

    def run(self, n: int, work: bool, read: bool = False) -> float:
        """µs per sample over ``n`` samples (``read``: read what is taken)."""
        np = self.np
        send_lengths, send_forces, send_pose, send_twist = self.send
        lengths_tpl, forces_tpl, pose_tpl, twist_tpl = self.templates
        sub_ctl, sub_fk, sub_plant = self.subs
        dyn, control, tracker, substeps = self.dyn, self.control, self.tracker, self.substeps
        y = self.y0.copy()
        tracker.reset(self.setup.task.initial_position, np.eye(3))
        zero3, zero6, unit_quat = np.zeros(3), np.zeros(6), np.array([0.0, 0.0, 0.0, 1.0])

        read_joint_state, take_with_info = self.read_joint_state, self.take_with_info

        def take(sub, fields=('position', 'velocity')):
            taken = take_with_info(sub)
            if taken is None:
                raise RuntimeError('%s: nothing to take' % sub.topic_name)
            if read:
                return read_joint_state(taken[0], fields)[3]
            return None
        start = time.perf_counter()
        for k in range(n):
            lengths, rates = dyn.lengths_and_rates(y) if work else (zero6, zero6)
            send_lengths(lengths_tpl.fill(0, k, position=lengths, velocity=rates))
            got = take(sub_ctl)
            if read:
                lengths, rates = got['position'], got['velocity']
            force = control.forces(k * 1e-3, lengths, rates) if work else zero6
            send_forces(forces_tpl.fill(0, k, effort=force))
            got = take(sub_plant, ('effort',))
            if read:
                force = got['effort']
            if work:
                y = dyn.step(y, force, 1e-3, substeps)
            got = take(sub_fk)
            if read:
                lengths, rates = got['position'], got['velocity']
            if work:
                result = tracker.solve(lengths, rates)
                pose = (result.position, result.quaternion)
                twist = (result.velocity, result.omega)
            else:
                pose, twist = (zero3, unit_quat), (zero3, zero3)
            send_pose(pose_tpl.fill(0, k, position=pose[0], orientation=pose[1]))
            send_twist(twist_tpl.fill(0, k, linear=twist[0], angular=twist[1]))
        return 1e6 * (time.perf_counter() - start) / n

    def kernels_alone(self, n: int) -> float:
        dyn, control, tracker = self.dyn, self.control, self.tracker
        y = self.y0.copy()
        tracker.reset(self.setup.task.initial_position, self.np.eye(3))
        start = time.perf_counter()
        for k in range(n):
            lengths, rates = dyn.lengths_and_rates(y)
            force = control.forces(k * 1e-3, lengths, rates)
            y = dyn.step(y, force, 1e-3, self.substeps)
            result = tracker.solve(lengths, rates)
            result.quaternion     # noqa: B018 - computed as fk publishes it
        return 1e6 * (time.perf_counter() - start) / n

    def close(self):
        for node in self.nodes:
            node.destroy_node()


# -- between processes -----------------------------------------------------------
_TOPIC = 'floor/xproc'


def _subscriber(n: int) -> None:
    """Child: take ``n`` messages, each after waiting for it; print its CPU per message."""
    rclpy.init()
    node = rclpy.create_node('floor_sub_%d' % os.getpid())
    sub = node.create_subscription(JointState, _TOPIC, lambda _: None, topics.EVERY_SUB,
                                   raw=True)
    waiter = WaitAny(node.context, [sub])
    got, cpu_start = 0, None
    deadline = time.monotonic() + WAIT + n * 2e-3
    while got < n and time.monotonic() < deadline:
        waiter.wait(0.5)
        while take(sub) is not None:
            if cpu_start is None:
                cpu_start = time.thread_time()     # from the first message on
            got += 1
    cpu = time.thread_time() - cpu_start if cpu_start is not None else 0.0
    print(json.dumps({'got': got, 'cpu_us': 1e6 * cpu / max(got - 1, 1)}), flush=True)
    node.destroy_node()
    rclpy.shutdown()


def cross_process(n: int, readers: int = 2) -> dict:
    """Publisher here, ``readers`` subscriber processes; CPU per publish and per take."""
    procs = [subprocess.Popen([sys.executable, __file__, '--subscriber', str(n)],
                              stdout=subprocess.PIPE, text=True) for _ in range(readers)]
    node = rclpy.create_node('floor_pub')
    try:
        pub = node.create_publisher(JointState, _TOPIC, topics.STREAM_PUB)
        deadline = time.monotonic() + WAIT
        while pub.get_subscription_count() < readers:
            if time.monotonic() > deadline:
                raise RuntimeError('the subscriber processes did not match within %g s' % WAIT)
            time.sleep(0.01)
        # Our side matched; theirs may still be completing (see RigNode): a
        # short pause, then the first messages are not counted by them anyway.
        time.sleep(1.0)
        send = raw_publisher(pub)
        tpl = wire.JointStateTemplates().get('base')
        six = np.ones(6)
        cpu = 0.0
        clock = time.thread_time
        for k in range(n):
            data = tpl.fill(0, k, position=six, velocity=six)
            before = clock()
            send(data)
            cpu += clock() - before
            time.sleep(5e-4)       # the readers go back to sleep, as at 1 kHz
        takes = []
        for proc in procs:
            out, _ = proc.communicate(timeout=WAIT)
            takes.append(json.loads(out.strip().splitlines()[-1]))
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        node.destroy_node()
    lost = sum(n - t['got'] for t in takes)
    return {'xproc_publish_cpu_us': 1e6 * cpu / n,
            'xproc_take_cpu_us': statistics.median(t['cpu_us'] for t in takes),
            'xproc_lost': lost}


def sleep_wake_cpu(n: int) -> float:
    start = time.thread_time()
    for _ in range(n):
        time.sleep(5e-4)
    return 1e6 * (time.thread_time() - start) / n


def measure(samples: int = 20000, repeat: int = 3, quiet: bool = False) -> dict:
    rounds = {k: [] for k in ('composed_dds_us', 'composed_dds_kernels_us',
                              'composed_dds_kernels_read_us', 'kernels_alone_us',
                              'xproc_publish_cpu_us', 'xproc_take_cpu_us', 'sleep_wake_cpu_us')}
    lost = 0
    with bench_loop.private_domain():
        rclpy.init()
        try:
            floor = ComposedFloor()
            floor.run(1000, True, read=True)     # kernels loaded, templates warm
            for _ in range(repeat):
                rounds['composed_dds_us'].append(floor.run(samples, False))
                rounds['composed_dds_kernels_us'].append(floor.run(samples, True))
                rounds['composed_dds_kernels_read_us'].append(
                    floor.run(samples, True, read=True))
                rounds['kernels_alone_us'].append(floor.kernels_alone(samples))
                x = cross_process(max(1000, samples // 4))
                lost += x.pop('xproc_lost')
                for key, value in x.items():
                    rounds[key].append(value)
                rounds['sleep_wake_cpu_us'].append(sleep_wake_cpu(2000))
                if not quiet:
                    print('round: ' + ', '.join('%s %.1f' % (k, v[-1])
                                                for k, v in rounds.items()), flush=True)
            floor.close()
        finally:
            rclpy.try_shutdown()
    result = {k: statistics.median(v) for k, v in rounds.items()}
    result['xproc_lost'] = lost
    result['floor_rounds'] = repeat
    return result


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--samples', type=int, default=20000)
    parser.add_argument('--repeat', type=int, default=3)
    parser.add_argument('--json', action='store_true', help='print the figures as JSON')
    parser.add_argument('--subscriber', type=int, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.subscriber:
        _subscriber(args.subscriber)
        return
    result = measure(args.samples, args.repeat, quiet=args.json)
    if args.json:
        print(json.dumps(result, indent=1))
        return
    per_s = 1e6 / result['composed_dds_kernels_us']
    print('composed sample, DDS traffic only:          %6.1f us' % result['composed_dds_us'])
    print('composed sample, DDS + compiled kernels:    %6.1f us (%.0f samples/s, no node code)'
          % (result['composed_dds_kernels_us'], per_s))
    print('the same, each message read into numbers: %6.1f us (%.0f samples/s)'
          % (result['composed_dds_kernels_read_us'], 1e6 / result['composed_dds_kernels_read_us']))
    print('the kernels alone, tight loop:              %6.1f us' % result['kernels_alone_us'])
    print('between processes, CPU per publish (2 idle readers): %6.1f us'
          % result['xproc_publish_cpu_us'])
    print('between processes, CPU per wait + take:              %6.1f us'
          % result['xproc_take_cpu_us'])
    print('a 0.5 ms sleep, CPU:                                 %6.1f us'
          % result['sleep_wake_cpu_us'])
    if result['xproc_lost']:
        print('(%d messages between processes were not received)' % result['xproc_lost'])


if __name__ == '__main__':
    main()
