"""The recorder's subscriptions: one raw subscription per recorded topic, a
second one per latched topic, and what the ROS graph shows of their
publishers (see recording/recorder.py).
"""
from __future__ import annotations

import importlib
import sys

from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from stewart63_ros import topics as T
from stewart63_ros.runtime.commands import LatchedCopies
from stewart63_ros.runtime.rclpy_internals import WaitAny


def message_class(type_name: str):
    """``'sensor_msgs/msg/JointState'`` -> the rclpy message class."""
    parts = type_name.split('/')
    if len(parts) == 2:
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3:
        raise ValueError(f'bad message type name {type_name!r}')
    module = importlib.import_module(f'{parts[0]}.{parts[1]}')
    return getattr(module, parts[2])


def own_endpoint(node, info) -> bool:
    """Whether graph endpoint ``info`` is ``node``'s own."""
    return info.node_name == node.get_name() and info.node_namespace == node.get_namespace()


class RecordedTopics:
    """The recorder's raw subscriptions, by full topic name.

    ``on_message(topic, data, info, tag)`` receives what the executor hands a
    subscription (the recorder's executor path); ``tag`` says which of a
    latched topic's two subscriptions it came through. ``counts`` (the bag's
    count per topic) gets each subscribed topic, at 0.
    """

    def __init__(self, node, on_message, counts: dict):
        self.node = node
        self.on_message = on_message
        self.counts = counts
        self.subs: dict[str, object] = {}       # full topic -> Subscription
        # Latched topics are subscribed twice (see subscribe): the second,
        # volatile subscription per topic, and the copies to drop.
        self.volatile: dict[str, object] = {}
        self.copies: dict[str, LatchedCopies] = {}
        self.types: dict[str, str] = {}         # full topic -> type name
        self.pending: dict[str, str] = {}       # full topic -> requested name (type unknown)
        #: wakes ``wait`` when triggered (Recorder.request_stop)
        self.guard = node.create_guard_condition(lambda: None)
        self._waitset = None
        self.matched_on: dict[str, list[str]] = {}     # see discover

    def request(self, name: str) -> None:
        """Subscribe the topic ``name`` (relative names in the node's
        namespace) if its type is known, else once the graph shows it."""
        full = self.node.resolve_topic_name(name)
        type_name = T.TOPIC_TYPES.get(name) or T.TOPIC_TYPES.get(T.relative_name(full))
        if type_name:
            self.subscribe(full, type_name)
        else:
            self.pending[full] = name

    def subscribe(self, full, type_name, qos=None):
        """A raw subscription to ``full``; for a latched command topic also a
        volatile one: the TRANSIENT_LOCAL subscription receives the command a
        latched publisher sent before recording started, but matches no
        volatile publisher (``ros2 topic pub`` by default); the VOLATILE one
        matches both, and a latched sample that comes through both is
        written once (``copies``, used by Intake.on_message)."""
        cls = message_class(type_name)
        qos = qos or T.recorder_qos(full)
        on_message = self.on_message

        def make_callback(tag):
            # rclpy inspects the signature: give it exactly (msg, info)
            return lambda data, info: on_message(full, data, info, tag)
        node = self.node
        sub = node.create_subscription(cls, full, make_callback('main'), qos, raw=True)
        old = self.subs.get(full)
        self.subs[full] = sub
        self.types[full] = type_name
        self.counts.setdefault(full, 0)
        if old is not None:
            node.destroy_subscription(old)
        if (T.relative_name(full) in T.LATCHED_TOPICS and full not in self.volatile
                and qos.durability == DurabilityPolicy.TRANSIENT_LOCAL):
            volatile = QoSProfile(history=qos.history, depth=qos.depth,
                                  reliability=qos.reliability,
                                  durability=DurabilityPolicy.VOLATILE)
            self.volatile[full] = node.create_subscription(
                cls, full, make_callback('volatile'), volatile, raw=True)
            self.copies[full] = LatchedCopies()
        self._waitset = None

    def build_waitset(self) -> None:
        """The wait set of every subscription and ``guard`` (raises where
        this rclpy lacks what rclpy_internals.WaitAny uses)."""
        self._waitset = WaitAny(self.node.context, list(self.subs.values())
                                + list(self.volatile.values()), [self.guard])

    def wait(self, timeout: float) -> None:
        """Block until a subscription has a message or ``guard`` is
        triggered, at most ``timeout`` s (the wait set is rebuilt only
        after a subscription changed)."""
        if self._waitset is None:
            self.build_waitset()
        self._waitset.wait(timeout)

    def publisher_count(self, topic) -> int:
        """Publishers matched by the subscription of ``topic``: a latched topic's
        volatile one, which matches latched and volatile publishers alike."""
        sub = self.volatile.get(topic) or self.subs.get(topic)
        return 0 if sub is None else sub.get_publisher_count()

    def publishers(self, topic) -> list:
        """The graph's publishers on ``topic`` (rclpy TopicEndpointInfo); none
        when the node is going down."""
        try:
            return self.node.get_publishers_info_by_topic(topic)
        except RuntimeError:  # rclpy's RCLError, InvalidHandle: the node is going down
            return []

    def offered_qos(self, topic) -> list:
        """The QoS profiles the publishers of ``topic`` offer: the recorder's
        own status publisher's only when it is the only one known (its first
        status on /diagnostics)."""
        infos = self.publishers(topic)
        others = [i for i in infos if not own_endpoint(self.node, i)]
        return [i.qos_profile for i in (others or infos)]

    def discover(self) -> tuple[list[str], list[str]]:
        """Subscribe the pending topics the graph now shows, and subscribe best
        effort where a best-effort publisher appeared. Returns the nodes every
        one of whose publishers on recorded topics these subscriptions have
        matched (sorted), and the topics that have a publisher."""
        node = self.node
        if self.pending:
            for name, types in node.get_topic_names_and_types():
                if name in self.pending and types:
                    del self.pending[name]
                    self.subscribe(name, types[0])
        complete: dict[str, bool] = {}     # node -> every publisher of it matched
        published = []
        #: topic -> the nodes whose publishers on it are all matched (sorted):
        #: a starting node checks its own topics by this, as the graph here
        #: may not show all of its publishers yet
        self.matched_on = {}
        for topic, sub in list(self.subs.items()):
            try:
                infos = node.get_publishers_info_by_topic(topic)
            except RuntimeError:  # rclpy's RCLError, InvalidHandle: the node is going down
                continue
            # The subscription's own count is the reader's side of each match
            # (its own status publisher's too); the graph shows a publisher no
            # earlier than the match begins.
            matched = self.publisher_count(topic) >= len(infos)
            infos = [i for i in infos if not own_endpoint(node, i)]
            for info in infos:
                name = T.endpoint_node_name(info)
                complete[name] = complete.get(name, True) and matched
            if matched and infos:
                self.matched_on[topic] = sorted({T.endpoint_node_name(i) for i in infos})
            if infos:
                published.append(topic)
                self._follow_best_effort(topic, sub, infos)
        return sorted(name for name, ok in complete.items() if ok), published

    def _follow_best_effort(self, topic, sub, infos) -> None:
        """A best-effort publisher (a sensor driver) does not match a reliable
        subscription: follow rosbag2 and subscribe best effort then."""
        if (sub.qos_profile.reliability == ReliabilityPolicy.RELIABLE and
                any(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
                    for i in infos)):
            q = sub.qos_profile
            be = QoSProfile(history=q.history, depth=q.depth,
                            reliability=ReliabilityPolicy.BEST_EFFORT,
                            durability=q.durability)
            print(f'record: {topic} has a best-effort publisher; '
                  'subscribing best effort', file=sys.stderr, flush=True)
            self.subscribe(topic, self.types[topic], be)
