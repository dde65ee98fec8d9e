"""Each node's health on /diagnostics: counters, latencies, and the status they make."""
from __future__ import annotations

import collections
import time
from typing import TYPE_CHECKING

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from stewart63_ros import topics
from stewart63_ros.runtime import handshake
from stewart63_ros.runtime.rclpy_internals import raw_publisher

if TYPE_CHECKING:
    # Only a hint: checks imports core.plumbing.params (scipy, a fifth of a second),
    # which the recorder, publishing through StatusPublisher, does not need
    # before it is ready.
    from stewart63_ros.runtime.checks import Rejected

#: the ``hardware_id`` of every status of the package's nodes
HARDWARE_ID = 'stewart63_ros'


class LogThrottle:
    """Whether a throttled message is due: at most one per ``period`` s and key.

    rclpy's ``throttle_duration_sec`` finds the caller's frame and source
    line (``inspect``: file stats, source reads) before it decides to stay
    silent: about 1 ms a call on this machine, a whole 1 kHz cycle, paid on
    every cycle of a warning that repeats (a late TPDO, a rejected sample),
    so a loaded loop grew slower the more it warned. This looks at the clock
    first; log through rclpy only when it says so.
    """

    def __init__(self, period: float = 1.0) -> None:
        self.period = period
        self._next: dict[str, float] = {}

    def __call__(self, key: str) -> bool:
        now = time.monotonic()
        if now < self._next.get(key, -1.0):
            return False
        self._next[key] = now + self.period
        return True


class StatusPublisher:
    """A node's status on /diagnostics, under the node's own name (``name``):
    what ``Health`` and the recorder (recording/recorder_status.py) publish through."""

    def __init__(self, node):
        self.node = node
        # 'stewart63/controller' in the root namespace, 'stewart63/rig2/controller'
        # in /rig2: /diagnostics is absolute, so two rigs must not share a name.
        self.name = topics.status_name(node.get_fully_qualified_name())
        self.pub = node.create_publisher(DiagnosticArray, topics.DIAGNOSTICS,
                                         topics.DIAGNOSTICS_QOS)

    def publish(self, level, message: str, values: list, stamp=None) -> None:
        """One status: ``level`` (a DiagnosticStatus level), ``message`` and
        ``values`` (diagnostic_msgs KeyValue: the keys written out where they
        are made, for test/test_interface_doc.py to find); stamped ``stamp``,
        or now."""
        status = DiagnosticStatus(level=level, name=self.name, message=message,
                                  hardware_id=HARDWARE_ID, values=values)
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = stamp if stamp is not None else self.node.get_clock().now().to_msg()
        self.pub.publish(msg)


class LatencyStats:
    """Recent latencies [s]: percentiles over a sliding window, max over all.

    The window is a preallocated ring (adding is one store, and the 1 Hz
    summary does not first copy 20000 Python floats out of a deque).
    """

    def __init__(self, window: int = 20000):
        self.window = np.zeros(window)
        self.count = 0
        self.max = 0.0

    def add(self, seconds: float) -> None:
        self.window[self.count % len(self.window)] = seconds
        self.count += 1
        if seconds > self.max:
            self.max = seconds

    def summary(self) -> dict:
        if not self.count:
            return {'count': 0}
        p50, p99 = np.percentile(self.window[:min(self.count, len(self.window))], (50, 99))
        return {'count': self.count, 'p50_ms': float(p50 * 1e3), 'p99_ms': float(p99 * 1e3),
                'max_ms': self.max * 1e3}


class Health:
    """Counters behind a node's /diagnostics status, published at about 1 Hz.

    State: ERROR when the node says so (``fault``, ``collision``), WARN when inputs were
    rejected or cycles were late in the last period, else OK.
    """

    def __init__(self, node, name: str):
        self.node = node
        self.name = name
        self.received = collections.Counter()
        self.published = collections.Counter()
        self.rejected = collections.Counter()
        #: messages that never reached the node, per topic (see checks.SkipCounter)
        self.skipped = collections.Counter()
        #: samples the middleware refused to publish, per topic (see ``sender``)
        self.publish_failed = collections.Counter()
        self._failed_at_report = 0
        #: topics on which every message must reach the node (fk's samples;
        #: any input in lockstep): a skip there is a loss, and a warning
        self.every_message = set()
        self._skipped_at_report = 0
        self.last_rejection = ''
        #: the node's repeated warnings, at most one a second each (``LogThrottle``)
        self.log_due = LogThrottle(1.0)
        self.latency = LatencyStats()
        self.fault = ''
        self.collision = ''     # more than one source on the 1 kHz input (see RigNode)
        self.source_warning = ''    # a second publisher matched, silent (see RigNode)
        self.warning = ''
        self.values = {}
        self._last_report = time.monotonic()
        self._received_at_report = collections.Counter()
        self._rejected_at_report = 0
        self.out = StatusPublisher(node)
        self.status_name = self.out.name
        self.pub = self.out.pub

    def reject(self, topic: str, exc: Rejected) -> None:
        self.rejected['%s/%s' % (topic, exc.reason)] += 1
        self.last_rejection = '%s: %s' % (topic, exc)
        if self.log_due('rejected'):
            self.node.get_logger().warning('rejected %s' % self.last_rejection)

    def sender(self, topic: str, publisher):
        """A function that publishes serialized bytes on ``publisher`` (see
        ``raw_publisher``) and counts them under ``topic``: in ``published``
        when the middleware took the sample, in ``publish_failed`` when it
        refused it. It returns whether the sample went out.

        A refusal is not the node's end: with a link cut (test_hosts), Fast
        DDS's reliable writer fills its history and ``publish`` raises rclpy's
        RCLError ("cannot publish data"). The sample is lost like any other
        lost message, counted and warned of, and the loop goes on. Only
        successful publishes count towards the final counts a recorder
        waits for (``report(final=True)``).
        """
        publish = raw_publisher(publisher)
        published = self.published
        failed = self.publish_failed
        logger = self.node.get_logger()

        def send(data) -> bool:
            try:
                publish(data)
            except RuntimeError as exc:     # rclpy's RCLError
                failed[topic] += 1
                if self.log_due('publish_failed/' + topic):
                    logger.warning('could not publish on %s (%d so far): %s'
                                   % (topic, failed[topic], str(exc).split(',')[0]))
                return False
            published[topic] += 1
            return True
        return send

    def skip(self, topic: str, n: int) -> None:
        """``n`` messages on ``topic`` never reached the node."""
        self.skipped[topic] += n
        if topic in self.every_message and self.log_due('skipped/' + topic):
            self.node.get_logger().warning(
                'lost %d %s messages (%d so far): they never reached this node'
                % (n, topic, self.skipped[topic]))

    def lost(self) -> int:
        """Messages lost on the topics that must see every message."""
        return sum(n for t, n in self.skipped.items() if t in self.every_message)

    def report(self, stamp=None, final=False) -> None:
        """Publish the status. ``final``: the node's last one, as it stops: it
        also says how many messages the node published on each topic
        (``final/<full topic name>``), so that a recorder can confirm it holds
        them all (see RigNode.flush)."""
        now = time.monotonic()
        period = max(now - self._last_report, 1e-9)
        rejected_total = sum(self.rejected.values())
        fresh_rejections = rejected_total - self._rejected_at_report
        lost = self.lost()
        fresh_losses = lost - self._skipped_at_report
        failed = sum(self.publish_failed.values())
        fresh_failures = failed - self._failed_at_report
        if self.fault or self.collision:
            level = DiagnosticStatus.ERROR
            message = '; '.join(m for m in (self.collision, self.fault) if m)
        elif fresh_losses:
            level = DiagnosticStatus.WARN
            message = 'lost %d messages that must all arrive (%s)' % (fresh_losses, ', '.join(
                sorted(t for t in self.every_message if self.skipped[t])))
        elif fresh_failures:
            level = DiagnosticStatus.WARN
            message = 'could not publish %d samples (%s)' % (fresh_failures, ', '.join(
                sorted(t for t, n in self.publish_failed.items() if n)))
        elif fresh_rejections or self.warning or self.source_warning:
            level = DiagnosticStatus.WARN
            message = self.warning or self.source_warning or 'rejected %d inputs (last: %s)' % (
                fresh_rejections, self.last_rejection)
        else:
            level, message = DiagnosticStatus.OK, 'ok'
        values = []
        for topic, n in sorted(self.received.items()):
            rate = (n - self._received_at_report[topic]) / period
            values.append(KeyValue(key='rate_hz/' + topic, value='%.1f' % rate))
            values.append(KeyValue(key='received/' + topic, value=str(n)))
        for topic, n in sorted(self.published.items()):
            values.append(KeyValue(key='published/' + topic, value=str(n)))
        for topic, n in sorted(self.skipped.items()):
            values.append(KeyValue(key='skipped/' + topic, value=str(n)))
        for topic, n in sorted(self.publish_failed.items()):
            values.append(KeyValue(key='publish_failed/' + topic, value=str(n)))
        values.append(KeyValue(key='rejected_total', value=str(rejected_total)))
        for key, n in sorted(self.rejected.items()):
            values.append(KeyValue(key='rejected/' + key, value=str(n)))
        for key, val in self.latency.summary().items():
            text = str(val) if isinstance(val, int) else '%.4g' % val   # counts in full
            values.append(KeyValue(key='latency/' + key, value=text))
        for key, val in self.values.items():
            values.append(KeyValue(key=key, value=str(val)))
        if final:
            values.append(KeyValue(key=handshake.FINAL, value='true'))
            for topic, n in sorted(self.published.items()):
                full = self.node.resolve_topic_name(topic)
                if full != topics.DIAGNOSTICS:
                    values.append(KeyValue(key=handshake.FINAL_PREFIX + full, value=str(n)))
        self.out.publish(level, message, values, stamp)
        self.published['/diagnostics'] += 1
        self._last_report = now
        self._received_at_report = collections.Counter(self.received)
        self._rejected_at_report = rejected_total
        self._skipped_at_report = lost
        self._failed_at_report = failed
