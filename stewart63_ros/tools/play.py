"""``play``: replay a rosbag2 directory onto its topics.

    play BAG [--rate R] [--loop] [--topics T ...] [--start-offset S]
             [--clock [HZ]] [--namespace NS] [--wait-subscribers N] [--wait-timeout S]

Messages are published as the CDR bytes stored in the bag (no decoding), at
the times given by the bag's timestamps (their reception times when recorded),
scaled by 1/R. Each topic is published with the QoS of stewart63_ros.topics,
so a replayed ``leg_lengths`` can stand in for the plant or a sensor driver.
Before the first message, play waits (bounded) until every topic it publishes
has a matched subscriber. See docs/bags.md.
"""
from __future__ import annotations

import argparse
import collections
import queue
import sys
import threading
import time

import rclpy
from rclpy.duration import Duration
from rosgraph_msgs.msg import Clock

from stewart63_ros import topics as T
from stewart63_ros.bagio import (
    ABSOLUTE_TOPICS,
    BagError,
    bag_namespace,
    open_reader,
    read_raw,
    resolve_bag_topics,
)
from stewart63_ros.middleware import use_rig_profile
from stewart63_ros.runtime.launcher import StopSignals
from stewart63_ros.runtime.ros_args import rclpy_args, split_ros_args
from stewart63_ros.tools.cli import quiet_on_closed_pipe


def _rebase(topic: str, rec_ns: str, namespace: str | None) -> str:
    """Where a bag topic is published: unchanged without ``namespace``; else the
    topic's name relative to the recording namespace, under ``namespace``
    (``/clock``, ``/diagnostics`` and topics recorded outside the rig's
    namespace keep their names)."""
    if not namespace or topic in ABSOLUTE_TOPICS:
        return topic
    rec = rec_ns.rstrip('/')
    if rec:
        if not topic.startswith(rec + '/'):
            return topic
        rel = topic[len(rec) + 1:]
    else:
        rel = topic.lstrip('/')
    ns = namespace.strip('/')
    return f'/{ns}/{rel}' if ns else f'/{rel}'


class Player:
    """Replays a bag; usable in-process (tests) and by ``main``.

    ``open()`` reads the bag's topics and creates one publisher per topic;
    ``wait_for_subscribers()`` waits (bounded) for matches; ``run()`` publishes
    with the bag's timing and returns the number of messages published per
    (output) topic; ``close()`` waits for reliable subscribers to acknowledge
    what was sent, then destroys the node.
    """

    def __init__(self, bag_dir, *, topics=None, rate=1.0, loop=False, start_offset=0.0,
                 clock_hz=None, namespace=None, context=None, domain_id=None, ros_args=None,
                 node_name='play'):
        if rate <= 0:
            raise ValueError('rate must be positive')
        if start_offset < 0:
            raise ValueError('start offset must not be negative')
        self.bag_dir = bag_dir
        self.requested = list(topics) if topics else None
        self.rate = float(rate)
        self.loop = bool(loop)
        self.start_offset = float(start_offset)
        self.clock_hz = clock_hz
        self.namespace = namespace
        self._context = context
        self._own_context = context is None
        self._domain_id = domain_id
        self._ros_args = ros_args
        self._node_name = node_name
        self._node = None
        self._pubs: dict[str, object] = {}     # bag topic -> publisher
        self._out: dict[str, str] = {}         # bag topic -> published name
        self._clock_pub = None
        self._stop = threading.Event()
        self.counts: dict[str, int] = {}
        # s each message went out after its due time (the last 100000)
        self.lateness = collections.deque(maxlen=100_000)
        self.start_ns = 0
        self.end_ns = 0

    def open(self):
        reader = open_reader(self.bag_dir)
        try:
            names = resolve_bag_topics(reader, self.requested)
            types = {c.topic: c.msgtype for c in reader.connections}
            rec_ns = bag_namespace(reader)
            self.start_ns, self.end_ns = reader.start_time, reader.end_time
        finally:
            reader.close()
        if self.clock_hz and '/clock' in names:
            names.remove('/clock')  # we publish /clock ourselves
        self.topics = names

        # lazy: rclpy.node costs 334 ms; --help answers without it
        from rclpy.node import Node

        from stewart63_ros.recording.recorder import message_class
        classes = {}
        for name in names:
            try:
                classes[name] = message_class(types[name])
            except (ImportError, AttributeError, ValueError) as exc:
                raise BagError(f'cannot publish {name}: message type {types[name]} '
                               f'is not available here ({exc})') from exc
        if self._context is None:
            use_rig_profile()
            self._context = rclpy.Context()
            rclpy.init(args=self._ros_args, context=self._context, domain_id=self._domain_id)
        self._node = Node(self._node_name, namespace=self.namespace or None,
                          context=self._context, start_parameter_services=False)
        ns = self.namespace or (self._node.get_namespace()
                                if self._node.get_namespace() != '/' else None)
        for name in names:
            out = _rebase(name, rec_ns, ns)
            self._out[name] = out
            self._pubs[name] = self._node.create_publisher(classes[name], out,
                                                           T.publisher_qos(out))
            self.counts[out] = 0
        if self.clock_hz:
            self._clock_pub = self._node.create_publisher(Clock, '/clock', T.STREAM_PUB)
        return self

    def subscriber_counts(self) -> dict[str, int]:
        return {self._out[t]: p.get_subscription_count() for t, p in self._pubs.items()}

    def wait_for_subscribers(self, count=1, timeout=10.0) -> bool:
        """Wait until each topic has ``count`` matched subscribers (bounded)."""
        if count <= 0:
            return True
        deadline = time.monotonic() + timeout
        while not self._stop.is_set():
            if all(p.get_subscription_count() >= count for p in self._pubs.values()):
                return True
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.01)
        return False

    def request_stop(self):
        self._stop.set()

    def _sleep_until(self, due: float) -> bool:
        """Sleep until monotonic time ``due``; False if asked to stop."""
        while True:
            if self._stop.is_set():
                return False
            delay = due - time.monotonic()
            if delay <= 0:
                return True
            self._stop.wait(min(delay, 0.1))

    def _prefetch(self, first_ns):
        """Read the bag in a background thread, ahead of the publishing loop, so
        that decoding a chunk never stalls the schedule. Yields items as read_raw."""
        q = queue.Queue(maxsize=self.PREFETCH)
        end = object()
        failure = []

        def reader():
            try:
                for item in read_raw(self.bag_dir, self.topics, start_ns=first_ns):
                    while not self._stop.is_set():
                        try:
                            q.put(item, timeout=0.1)
                            break
                        except queue.Full:
                            continue
                    if self._stop.is_set():
                        return
            except BaseException as exc:  # noqa: BLE001 - re-raised in the publishing thread
                failure.append(exc)
            finally:
                while True:
                    try:
                        q.put(end, timeout=0.1)
                        break
                    except queue.Full:
                        if self._stop.is_set():
                            break
        th = threading.Thread(target=reader, name='play-reader', daemon=True)
        th.start()
        try:
            while not self._stop.is_set():
                try:
                    item = q.get(timeout=0.1)
                except queue.Empty:
                    continue
                if item is end:
                    break
                yield item
            if failure:
                raise failure[0]
        finally:
            th.join(1.0)

    #: messages read ahead of the schedule
    PREFETCH = 20_000

    def run(self) -> dict[str, int]:
        """Publish the bag (again and again with ``loop``) until done or stopped."""
        first_ns = self.start_ns + int(self.start_offset * 1e9)
        clock_period = 1.0 / self.clock_hz if self.clock_hz else None
        old_switch = sys.getswitchinterval()
        sys.setswitchinterval(min(old_switch, 0.0005))  # the reader thread yields the GIL soon
        try:
            while not self._stop.is_set():
                items = self._prefetch(first_ns)
                sent = 0
                wall0 = None
                for topic, _, stamp, data in items:
                    if wall0 is None:   # the clock starts once the first message is read
                        wall0 = time.monotonic() - (stamp - first_ns) * 1e-9 / self.rate
                        next_clock = wall0 if clock_period else float('inf')
                    due = wall0 + (stamp - first_ns) * 1e-9 / self.rate
                    while next_clock <= due:
                        if not self._sleep_until(next_clock):
                            break
                        self._publish_clock(Clock, first_ns, wall0)
                        next_clock += clock_period
                    if not self._sleep_until(due):
                        break
                    self._pubs[topic].publish(data)
                    self.lateness.append(time.monotonic() - due)
                    self.counts[self._out[topic]] += 1
                    sent += 1
                items.close()
                if not self.loop or sent == 0:
                    break
        finally:
            sys.setswitchinterval(old_switch)
        return dict(self.counts)

    def _publish_clock(self, Clock, first_ns, wall0):
        bag_ns = first_ns + int((time.monotonic() - wall0) * self.rate * 1e9)
        msg = Clock()
        msg.clock.sec, msg.clock.nanosec = divmod(bag_ns, 1_000_000_000)
        self._clock_pub.publish(msg)

    def close(self, ack_timeout=5.0):
        """Wait (bounded) until reliable subscribers have everything, then tear down."""
        if self._node is not None:
            deadline = time.monotonic() + ack_timeout
            for pub in self._pubs.values():
                left = max(0.0, deadline - time.monotonic())
                try:
                    pub.wait_for_all_acked(Duration(seconds=left))
                except RuntimeError:  # rclpy's RCLError: the context is going down
                    pass
            self._node.destroy_node()
            self._node = None
        if self._own_context and self._context is not None:
            self._context.try_shutdown()
            self._context = None

    def summary(self) -> str:
        total = sum(self.counts.values())
        parts = ', '.join(f'{t} {n}' for t, n in self.counts.items())
        return f'play: {self.bag_dir}: published {total} messages ({parts})'


def _parser():
    p = argparse.ArgumentParser(
        prog='play',
        description='Replay a rosbag2 directory onto its topics with the recorded timing. '
                    'Ctrl-C stops.',
        epilog='ROS arguments go after --ros-args. Relative --topics names resolve under the '
               'namespace the bag was recorded in.')
    p.add_argument('bag', metavar='BAG', help='bag directory')
    p.add_argument('--rate', type=float, default=1.0, metavar='R',
                   help='playback speed factor (default 1)')
    p.add_argument('--loop', action='store_true', help='start again at the end')
    p.add_argument('--topics', nargs='+', metavar='T', help='topics to play (default: all)')
    p.add_argument('--start-offset', type=float, default=0.0, metavar='S',
                   help='skip the first S seconds of the bag')
    p.add_argument('--clock', nargs='?', type=float, const=100.0, default=None, metavar='HZ',
                   help='publish /clock with the bag time at HZ (default 100)')
    p.add_argument('--namespace', metavar='NS',
                   help='publish the rig\'s topics under NS instead of the recorded namespace')
    p.add_argument('--wait-subscribers', type=int, default=1, metavar='N',
                   help='before the first message, wait until each topic has N matched '
                        'subscribers (default 1; 0: do not wait)')
    p.add_argument('--wait-timeout', type=float, default=10.0, metavar='S',
                   help='wait at most S s for subscribers, then play anyway (default 10)')
    return p


@quiet_on_closed_pipe
def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    argv, ros = split_ros_args(argv)
    ros_args = rclpy_args('play', ros)
    args = _parser().parse_args(argv)
    if args.rate <= 0:
        _parser().error('--rate must be positive')
    if args.start_offset < 0:
        _parser().error('--start-offset must not be negative')
    if args.clock is not None and args.clock <= 0:
        _parser().error('--clock HZ must be positive')

    player = Player(args.bag, topics=args.topics, rate=args.rate, loop=args.loop,
                    start_offset=args.start_offset, clock_hz=args.clock,
                    namespace=args.namespace, ros_args=ros_args)

    signals = StopSignals(player.request_stop, deadline=False, interrupt=False).install()
    try:
        player.open()
        if args.wait_subscribers > 0:
            if not player.wait_for_subscribers(args.wait_subscribers, args.wait_timeout):
                missing = [t for t, n in player.subscriber_counts().items()
                           if n < args.wait_subscribers]
                if missing:
                    print(f'play: warning: after {args.wait_timeout:g} s still fewer than '
                          f'{args.wait_subscribers} subscribers on {", ".join(missing)}; '
                          'playing anyway', file=sys.stderr, flush=True)
        print('PLAYING', flush=True)
        player.run()
        player.close()
        print(player.summary(), flush=True)
        return 0
    except BagError as exc:
        print(f'play: error: {exc}', file=sys.stderr)
        return 2
    finally:
        try:
            player.close(ack_timeout=1.0)
        except Exception:  # noqa: BLE001 - the outcome is already decided; tear-down is best effort
            pass
        signals.restore()       # main may run inside another program (a test)


if __name__ == '__main__':
    sys.exit(main())
