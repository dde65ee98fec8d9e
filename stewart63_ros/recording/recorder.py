"""The recorder node: raw subscriptions to the rig's topics, written into a bag.

``record`` (``stewart63_ros/tools/record.py``) is its command line; ``rig``
and the tests use the ``Recorder`` class in-process. See docs/bags.md.

The Recorder composes its parts, each with one job: ``RecordedTopics``
(recording/recorder_topics.py: the subscriptions, and what the ROS graph shows
of their publishers), ``BagOut`` (recording/recorder_bag.py: the bag),
``RecorderStatus`` and ``LossCount`` (recording/recorder_status.py: what it says
on /diagnostics) and ``Intake`` (recording/recorder_intake.py: the one path
every message takes into the bag). Its own job is the recording loop: open,
wait, take, housekeeping, close.
"""
from __future__ import annotations

import threading
import time
from pathlib import Path

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from stewart63_ros import topics as T
from stewart63_ros.middleware import use_rig_profile
from stewart63_ros.recording.recorder_bag import (
    BagOut,
    BatchWriter,
    header_stamp_ns,
    qos_to_rosbags,
)
from stewart63_ros.recording.recorder_intake import Intake
from stewart63_ros.recording.recorder_status import LossCount, RecorderStatus
from stewart63_ros.recording.recorder_topics import RecordedTopics, message_class
from stewart63_ros.runtime.lockstep import ProgressPublisher

# BatchWriter, qos_to_rosbags and message_class are imported from here too.
__all__ = ['BatchWriter', 'Recorder', 'header_stamp_ns',
           'message_class', 'qos_to_rosbags']


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
        self.error: BaseException | None = None
        self.bag = BagOut(self.path)
        #: messages written per full topic name
        self.counts = self.bag.counts
        self.losses = LossCount()
        #: messages of each topic that never reached the bag (see LossCount)
        self.lost = self.losses.lost
        self.subs: RecordedTopics | None = None         # from open()
        self.status: RecorderStatus | None = None       # from open()
        self.intake: Intake | None = None               # from open()
        self._context = context
        self._own_context = context is None
        self._domain_id = domain_id
        self._ros_args = ros_args
        self._node_name = node_name
        self._node = None
        self._executor = None
        self._stop = threading.Event()
        self._thread = None
        self._next_flush = 0.0
        self._next_discovery = 0.0
        self._closed = False
        self._lock = threading.Lock()

    # ----------------------------------------------------------------- setup
    def open(self):
        """Create the bag and the subscriptions; returns self with ``ready`` set."""
        self.bag.check_new()
        if self._context is None:
            use_rig_profile()
            self._context = rclpy.Context()
            rclpy.init(args=self._ros_args, context=self._context, domain_id=self._domain_id)
        try:
            node = self._node = Node(self._node_name, namespace=self.namespace or None,
                                     context=self._context, start_parameter_services=False)
            self.bag.open(node.get_namespace())
            self.subs = RecordedTopics(node, self._on_message, self.counts)
            for name in self.requested:
                self.subs.request(name)
            # The recorder's own status, also when /diagnostics is not
            # recorded: starting nodes wait for what it says.
            self.status = RecorderStatus(node, self.path, self.counts, self.losses,
                                         self.subs.subs)
            diag, lengths = (node.resolve_topic_name(t) for t in (T.DIAGNOSTICS, T.LEG_LENGTHS))
            self.intake = Intake(self.bag, self.subs, self.status, self.losses,
                                 ProgressPublisher(node),
                                 diag if diag in self.subs.subs else None,
                                 lengths if lengths in self.subs.subs else None)
            if self.fast_path:
                try:
                    self.subs.build_waitset()
                except Exception:  # noqa: BLE001 - other rclpy versions: the executor path
                    self.fast_path = False
            if not self.fast_path:
                self._executor = SingleThreadedExecutor(context=self._context)
                self._executor.add_node(node)
            now = time.monotonic()
            self._next_flush = now + self.flush_period
            self._next_discovery = now
        except BaseException:
            self._teardown(abort=True)
            raise
        self.ready.set()
        return self

    @property
    def full_name(self) -> str:
        """The recorder node's full name (after ``open``)."""
        return self._node.get_fully_qualified_name()

    @property
    def domain_id(self) -> int:
        """The ROS domain it records (after ``open``)."""
        return self._context.get_domain_id()

    def _subscribe(self, full, type_name, qos=None):
        """Subscribe ``full`` now (RecordedTopics.subscribe)."""
        self.subs.subscribe(full, type_name, qos)

    def _on_message(self, topic, data, info, tag='main'):
        """A message the executor hands a subscription (Intake.on_message)."""
        self.intake.on_message(topic, data, info, tag)

    # -------------------------------------------------------------- recording
    def spin_once(self, timeout=0.1):
        """Wait up to ``timeout`` s for messages, write what arrived, do housekeeping."""
        if self.fast_path:
            self.subs.wait(timeout)
            if self.intake.take_all() and self.batch_period > 0 and not self._stop.is_set():
                # Let the next messages gather in the subscriptions' queues
                # (the middleware receives and acknowledges them meanwhile):
                # one wake-up and one pass over the topics for a batch,
                # instead of one per message, which would take CPU from the
                # nodes being recorded.
                time.sleep(min(self.batch_period, timeout))
        else:
            self._executor.spin_once(timeout_sec=timeout)
        # Said after either path (the executor's messages note their progress
        # in Intake.write but do not say it), and repeated while nothing
        # changes, so a lost word cannot hold a lockstep plant.
        self.intake.say_progress()
        self._housekeeping()

    def take_available(self) -> int:
        """Write what has arrived, without waiting; the periodic flush and
        discovery as ``spin_once``. For a loop that hosts the recorder with
        other nodes in one thread (the composed rig): the number written."""
        n = self.intake.take_all()
        self._housekeeping()
        return n

    def _housekeeping(self):
        now = time.monotonic()
        if now >= self._next_discovery:
            self._next_discovery = now + self.discovery_period
            self._discover()
        self.status.report(now)
        if now >= self._next_flush:
            self._next_flush = now + self.flush_period
            self.flush()

    def flush(self):
        """Write the buffered messages to disk (BagOut.flush): what a hard kill
        of this process can lose."""
        self.bag.flush()

    def _discover(self):
        """Topics and publishers the graph shows now (RecordedTopics.discover):
        a connection for each topic published, the matched nodes to say."""
        matched, published = self.subs.discover()
        for topic in published:
            if topic not in self.bag.conns:
                self.intake.add_connection(topic)
        self.status.matched(matched, self.subs.matched_on)

    # ------------------------------------------------------------ public state
    @property
    def topics(self) -> list[str]:
        """The full names of the topics subscribed so far (more may come: a
        topic of unknown type is subscribed once the ROS graph shows it)."""
        return list(self.subs.subs) if self.subs is not None else []

    def publisher_counts(self, topics=None):
        """Publishers the recorder's own subscriptions have matched, per
        subscribed topic (or per topic of ``topics``, relative names resolved
        in the recorder's namespace). A latched command topic counts those of
        its volatile subscription, which matches latched and volatile
        publishers alike (RecordedTopics.subscribe).

        This is the reader's side of the match: a publisher can already count
        the recorder while the recorder does not know it yet, and what it
        sends then is lost to the recorder."""
        names = ([self._node.resolve_topic_name(t) for t in topics] if topics
                 else list(self.subs.subs))
        return {t: self.subs.publisher_count(t) for t in names}

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

    # -------------------------------------------------------------- lifecycle
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
        guard = self.subs.guard if self.subs is not None else None
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
            if self._node is not None and self.bag.is_open:
                try:
                    self.intake.take_all()
                except Exception:  # noqa: BLE001 - the bag is closed whatever the last take met
                    pass
        finally:
            self._teardown(abort=False)
        return dict(self.counts)

    def _teardown(self, abort):
        try:
            self.bag.close(abort)
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
        """One line: the messages recorded per topic, and the ones lost."""
        return self.bag.summary(self.lost)
