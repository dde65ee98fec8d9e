"""What every node shares: start-up, parameters, input checks, diagnostics.

The nodes are thin shells around ``stewart63_ros.core``: they turn messages
into arrays, call the core, and turn arrays back into messages.
"""
from __future__ import annotations

import argparse
import collections
import signal
import sys
import time

import numpy as np

LEG_NAMES = ['leg_%d' % i for i in range(1, 7)]


# -- input checks (no ROS types needed) ---------------------------------------
class Rejected(ValueError):
    """An input message that must not reach the model; ``reason`` is a short key."""

    def __init__(self, reason: str, detail: str):
        super().__init__('%s: %s' % (reason, detail))
        self.reason = reason


def stamp_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def leg_vector(names, values, field: str) -> np.ndarray:
    """The six values of a JointState field, in leg order, or Rejected.

    Names must be exactly leg_1..leg_6 in order (an empty name list is taken
    as that order); values must be six finite numbers.
    """
    names = list(names)
    if names and names != LEG_NAMES:
        unknown = [n for n in names if n not in LEG_NAMES]
        if unknown:
            raise Rejected('unknown_joint_names', 'unknown joint names %s' % unknown[:6])
        raise Rejected('bad_joint_order', 'joint names %s are not leg_1..leg_6 in order' % names)
    arr = np.asarray(values, dtype=float)
    if arr.shape != (6,):
        raise Rejected('wrong_size', '%s has %d entries, expected 6' % (field, arr.size))
    if not np.all(np.isfinite(arr)):
        raise Rejected('non_finite', '%s holds NaN or Inf' % field)
    return arr


class StampGate:
    """Rejects a sample whose stamp is older than the last accepted one on its topic."""

    def __init__(self):
        self.last_ns = None

    def check(self, stamp) -> int:
        return self.check_ns(stamp_ns(stamp))

    def check_ns(self, ns: int) -> int:
        if self.last_ns is not None and ns < self.last_ns:
            raise Rejected('stamp_from_past', 'stamp %.9f s is older than the last accepted %.9f s'
                           % (ns * 1e-9, self.last_ns * 1e-9))
        return ns

    def accept(self, ns: int) -> None:
        self.last_ns = ns


def finite_vector(values, size: int, field: str) -> np.ndarray:
    arr = np.asarray(values, dtype=float)
    if arr.shape != (size,) or not np.all(np.isfinite(arr)):
        raise Rejected('non_finite' if arr.shape == (size,) else 'wrong_size',
                       '%s must be %d finite numbers' % (field, size))
    return arr


# -- latency statistics --------------------------------------------------------
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


# -- ROS side ------------------------------------------------------------------
def ros_time(seconds: float):
    """builtin_interfaces/Time from seconds (exact to the nanosecond)."""
    from builtin_interfaces.msg import Time
    ns = int(round(seconds * 1e9))
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


class Health:
    """Counters behind a node's /diagnostics status, published at about 1 Hz.

    State: ERROR when the node says so (``fault``), WARN when inputs were
    rejected or cycles were late in the last period, else OK.
    """

    def __init__(self, node, name: str):
        from diagnostic_msgs.msg import DiagnosticArray
        from stewart63_ros import topics
        self.node = node
        self.name = name
        # 'stewart63/controller' in the root namespace, 'stewart63/rig2/controller'
        # in /rig2: /diagnostics is absolute, so two rigs must not share a name.
        self.status_name = 'stewart63' + node.get_fully_qualified_name()
        self.received = collections.Counter()
        self.published = collections.Counter()
        self.rejected = collections.Counter()
        self.last_rejection = ''
        self.latency = LatencyStats()
        self.fault = ''
        self.warning = ''
        self.values = {}
        self._last_report = time.monotonic()
        self._received_at_report = collections.Counter()
        self._rejected_at_report = 0
        self.pub = node.create_publisher(DiagnosticArray, topics.DIAGNOSTICS,
                                         topics.DIAGNOSTICS_QOS)

    def reject(self, topic: str, exc: Rejected) -> None:
        self.rejected['%s/%s' % (topic, exc.reason)] += 1
        self.last_rejection = '%s: %s' % (topic, exc)
        self.node.get_logger().warn('rejected %s' % self.last_rejection,
                                    throttle_duration_sec=1.0)

    def report(self, stamp=None) -> None:
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
        now = time.monotonic()
        period = max(now - self._last_report, 1e-9)
        rejected_total = sum(self.rejected.values())
        fresh_rejections = rejected_total - self._rejected_at_report
        if self.fault:
            level, message = DiagnosticStatus.ERROR, self.fault
        elif fresh_rejections or self.warning:
            level = DiagnosticStatus.WARN
            message = self.warning or 'rejected %d inputs (last: %s)' % (
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
        values.append(KeyValue(key='rejected_total', value=str(rejected_total)))
        for key, n in sorted(self.rejected.items()):
            values.append(KeyValue(key='rejected/' + key, value=str(n)))
        for key, val in self.latency.summary().items():
            text = str(val) if isinstance(val, int) else '%.4g' % val   # counts in full
            values.append(KeyValue(key='latency/' + key, value=text))
        for key, val in self.values.items():
            values.append(KeyValue(key=key, value=str(val)))
        status = DiagnosticStatus(level=level, name=self.status_name,
                                  message=message, hardware_id='stewart63_ros', values=values)
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = stamp if stamp is not None else self.node.get_clock().now().to_msg()
        self.pub.publish(msg)
        self.published['/diagnostics'] += 1
        self._last_report = now
        self._received_at_report = collections.Counter(self.received)
        self._rejected_at_report = rejected_total


class DirectTake:
    """Wait on one subscription and take its messages without the executor.

    The executor rebuilds its wait set on every spin (100-200 microseconds in
    Python); a 1 kHz loop waits on a single subscription in a wait set of its
    own instead, the way rclpy's own ``wait_for_message`` does. A message that
    is already there is taken without waiting at all: even a wait that
    returns at once costs a futex call with a timeout (25 us here, 75 us with
    the kernel's default 50 us timer slack, see ``reduce_timer_slack``). The
    subscription stays in the executor too: either path hands the message to
    the same callback.
    """

    def __init__(self, node, subscription):
        from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
        self.sub = subscription
        self.wait_set = _rclpy.WaitSet(1, 0, 0, 0, 0, 0, node.context.handle)

    def poll(self, timeout_sec: float) -> bool:
        """Take one message, waiting up to ``timeout_sec`` for it, and run the
        callback on it; False if none came."""
        sub = self.sub
        handle = sub.handle
        taken = handle.take_message(sub.msg_type, sub.raw)
        if taken is None:
            if timeout_sec <= 0:
                return False
            ws = self.wait_set
            ws.clear_entities()
            ws.add_subscription(handle)
            ws.wait(int(timeout_sec * 1e9))
            taken = handle.take_message(sub.msg_type, sub.raw)
            if taken is None:
                return False
        sub.callback(taken[0])
        return True


def realtime_scheduling(priority: int) -> str:
    """SCHED_FIFO at ``priority`` (1-99) for every thread of this process,
    the middleware's included; threads started later inherit it. Returns ''
    or why it was refused (it needs root or CAP_SYS_NICE / an rtprio limit);
    nothing is changed then. Linux keeps 5 % of each second for other tasks
    (sched_rt_runtime_us), so a loop that never blocks cannot freeze the host.
    """
    import os
    try:
        param = os.sched_param(int(priority))
        main = os.getpid()
        os.sched_setscheduler(main, os.SCHED_FIFO, param)
        for tid in (int(t) for t in os.listdir('/proc/self/task')):
            if tid == main:
                continue
            try:
                os.sched_setscheduler(tid, os.SCHED_FIFO, param)
            except ProcessLookupError:      # a thread that has just ended
                pass
    except (OSError, AttributeError, ValueError) as exc:
        return str(exc) or type(exc).__name__
    return ''


def reduce_timer_slack(slack_ns: int = 1000) -> bool:
    """Set this thread's timer slack (Linux; inherited by threads it starts).

    The kernel lets a timed wait of a normal thread overrun by its timer
    slack, 50 us by default: every ``WaitSet.wait`` with a timeout (even 0,
    which DDS turns into a futex wait with a deadline of now) then costs
    50 us more, and a 1 kHz loop wakes up to 50 us late. Called before
    rclpy starts, so the middleware's threads inherit it. Harmless elsewhere
    (returns False).
    """
    try:
        import ctypes
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(29, int(slack_ns), 0, 0, 0) == 0   # PR_SET_TIMERSLACK
    except (OSError, AttributeError, TypeError):
        return False


def node_parameters(node, node_name: str) -> dict:
    """The flat parameter dictionary: packaged defaults, then the node's ROS parameters.

    Nodes start with ``automatically_declare_parameters_from_overrides``, so
    ``--params-file`` and ``-p name:=value`` arrive as declared parameters.
    """
    from stewart63_ros.core.params import default_params_path, read_parameter_file
    params = read_parameter_file(default_params_path(), node_name)
    for name, param in node._parameters.items():
        if name == 'use_sim_time':
            continue
        value = param.value
        if value is not None:
            params[name] = list(value) if not isinstance(value, (str, bool, int, float)) else value
    return params


def wait_until(node, executor, predicate, timeout: float) -> bool:
    """Spin until ``predicate()`` or ``timeout`` seconds; True if it held."""
    deadline = time.monotonic() + timeout
    while not predicate():
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return False
        executor.spin_once(timeout_sec=min(0.05, remaining))
    return True


def make_parser(prog: str, description: str) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=prog, description=description,
        epilog='ROS arguments follow --ros-args, e.g. --ros-args --params-file '
        'config/stewart63.yaml -r __ns:=/rig2 -p name:=value (README: parameters).')
    return parser


def _interrupt(*_):
    raise KeyboardInterrupt


def run(prog: str, description: str, node_class, argv=None, extra_args=None) -> int:
    """Parse --help / own options, start rclpy, run the node until shutdown.

    Exits 2 with a one-line message on a parameter error; SIGTERM and Ctrl-C
    stop the node cleanly.
    """
    from stewart63_ros.core.params import ParameterError
    argv = list(sys.argv if argv is None else argv)
    parser = make_parser(prog, description)
    if extra_args:
        extra_args(parser)
    import rclpy
    from rclpy.utilities import remove_ros_args
    options = parser.parse_args(remove_ros_args(argv)[1:])
    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions
    reduce_timer_slack()
    # Our own handlers: Ctrl-C and SIGTERM raise KeyboardInterrupt, so the
    # node flushes its last messages to the recorder before rclpy shuts down.
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    # SIGTERM (from rig, systemd, docker) ends the node like Ctrl-C does.
    signal.signal(signal.SIGTERM, _interrupt)
    signal.signal(signal.SIGINT, _interrupt)
    node = None
    code = 0
    try:
        node = node_class(options)
        code = node.run() or 0
    except ParameterError as exc:
        print('%s: parameter error: %s' % (prog, exc), file=sys.stderr)
        code = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        code = 0
    finally:
        if node is not None:
            started = time.monotonic()
            try:
                node.close()
            except Exception:  # noqa: BLE001 - shutting down anyway
                pass
            node.destroy_node()
            # In the node's log, so that a slow stop shows where it went.
            print('%s: stopped (exit %d, close took %.2f s)'
                  % (prog, code, time.monotonic() - started), flush=True)
        if rclpy.ok():
            rclpy.shutdown()
    return code
