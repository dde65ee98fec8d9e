"""RigNode: the rclpy Node every stewart63 node derives from."""
from __future__ import annotations

import json
import time

from rcl_interfaces.msg import SetParametersResult
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from stewart63_ros import topics
from stewart63_ros.core.plumbing.node_parameters import BY_NAME as DECLARED
from stewart63_ros.core.plumbing.node_parameters import NODE_KEYS, describe, node_keys
from stewart63_ros.core.plumbing.node_parameters import read as read_declared
from stewart63_ros.core.plumbing.params import ParameterError, setup_from_params, unknown_keys
from stewart63_ros.core.precompile import COMPILE_NOTICE, kernel_cache_cold
from stewart63_ros.runtime import wire
from stewart63_ros.runtime.checks import Rejected, SkipCounter, source_of
from stewart63_ros.runtime.diagnostics import Health
from stewart63_ros.runtime.handshake import RecorderWord
from stewart63_ros.runtime.hotloop import HotLoop
from stewart63_ros.runtime.launcher import STOP
from stewart63_ros.runtime.parameters import declare_parameters, load_parameters, ros_parameters
from stewart63_ros.runtime.realtime import realtime_scheduling
from stewart63_ros.runtime.sources import SourceWatch
from stewart63_ros.runtime.startup import StartupBarrier
from stewart63_ros.runtime.stopping import Flush


class RigNode(HotLoop, Node):
    """Loads the setup (``setup``: mechanism, gains, task, settings) from the
    node's parameters and owns the diagnostics.

    Its hot loop (``run_on``, ``housekeeping``, ``drive_by``): runtime/hotloop.py.

    Node-specific keys shared by all nodes (docs/interface.md, "Parameters"):
    ``wait_for_subscribers`` (int, 0): before its first message, wait until
    every data publisher of this node has that many matched subscriptions
    (``rig --record`` sets 1 so that the recorder misses nothing);
    ``discovery_timeout`` (s, 20): the bound on that wait (who waits for whom
    before the first sample: runtime/handshake.py);
    ``realtime_priority`` (0..99, 0): when not 0, the node's threads run
    SCHED_FIFO at that priority (where the OS allows it; a warning and normal
    scheduling where it does not), so that other work on the machine cannot
    keep a 1 kHz loop waiting for a CPU for a scheduler slice (3-4 ms).
    """

    def __init__(self, name: str):
        # Parameters as runtime/parameters.py reads them (a -p wins over the
        # files; a file given is the whole model), checked, then declared as
        # the node's ROS parameters (each with its descriptor) so that ros2
        # param shows what the node runs with.
        self.created = time.monotonic()       # the graph's discovery starts about now
        _, params = load_parameters(name)
        super().__init__(name, parameter_overrides=ros_parameters(params),
                         automatically_declare_parameters_from_overrides=False,
                         allow_undeclared_parameters=True)
        self.kind = name                      # 'plant', 'controller', 'fk' (whatever remapped)
        self.params = params
        self._check_unknown_keys()
        #: the machine, gains, task and settings of its parameters (core/mechanics/setup.py)
        self.setup = setup_from_params(self.params)
        self.mech = self.setup.mechanism
        for key in NODE_KEYS[name]:           # every key it reads passes its check first
            self.param(key)
        declare_parameters(self, name, self.params)
        if kernel_cache_cold():
            self.get_logger().info(COMPILE_NOTICE)
        self.wait_for_subscribers = self.param('wait_for_subscribers')
        self.discovery_timeout = self.param('discovery_timeout')
        # 0 unless set: the start-up waits for events, not a clock (startup.py).
        self.discovery_settle = self.param('discovery_settle')
        if not self.discovery_settle <= self.discovery_timeout:
            raise ParameterError('discovery_settle', 'must be from 0 to discovery_timeout '
                                 '(%g s), got %r' % (self.discovery_timeout,
                                                     self.discovery_settle))
        self.health = Health(self, name)
        self._skip_counters = {}
        #: called after each batch of messages, and after each executor turn
        #: that may have served some (run_on, the start-up wait): fk's
        #: lockstep progress
        self.after_batch = None
        #: where close() writes the node's summary as JSON ('' : nowhere)
        self.summary_file = self.param('summary_file')
        self.summary_written = False
        self.realtime_priority = self._realtime_priority()
        self._executor = None       # made on first use: see executor_
        self.data_publishers = []
        self.optional_publishers = set()
        self.started = False        # diagnostics wait for the peers, like the data
        # Run-time changes through the parameter services: only the keys a
        # node registers with ``tunable`` may change; every other one is
        # refused with a reason (the model is fixed once the node runs).
        self._tunable = {}
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.create_timer(1.0, self.report)
        self.closing = False         # the next report is the last one (see close)
        self.flushed = ''           # how the flush at close ended, for the node's log
        #: monotonic time by which close's flush must end (None: its own bound);
        #: the nodes of one process share one (composed), so their stop stays
        #: within the stop deadline however many of them wait
        self.flush_deadline = None
        # The parts that do one job each: what the recorders say on
        # /diagnostics, the wait before the first message, the flush at the end.
        self.recorder_word = RecorderWord(self)
        self.startup = StartupBarrier(self, self.recorder_word)
        self.stop_flush = Flush(self, self.recorder_word)

    # -- run-time parameter changes --------------------------------------------
    def tunable(self, name: str, apply) -> None:
        """Let parameter ``name`` change at run time (``ros2 param set``).

        ``apply(value)`` puts the new value into effect at once, or raises
        ``ParameterError`` with the reason: the change is then refused and
        nothing changes. A declared key (core/plumbing/node_parameters.py) must be
        declared changeable at run time on this node, so that the interface
        page says so and its descriptor is not read-only (rcl refuses a set
        of a read-only one before this node sees it); ``apply`` gets its
        value as its declaration's check returns it.
        """
        if name in node_keys(self.kind) and describe(name, self.kind).read_only:
            raise ValueError('%s is declared fixed at start-up on the %s '
                             '(core/plumbing/node_parameters.py)'
                             % (name, self.kind))
        self._tunable[name] = apply

    def _on_set_parameters(self, parameters):
        for param in parameters:
            if param.name == 'use_sim_time':      # rclpy's own, applied by rclpy
                continue
            apply = self._tunable.get(param.name)
            if apply is None:
                return SetParametersResult(successful=False, reason=(
                    '%s cannot be changed while the node runs (the model and the node '
                    'set-up are fixed at start-up); restart the node with the new value'
                    % param.name))
            declared = DECLARED.get(param.name)
            try:
                apply(declared.check(param.name, param.value) if declared else param.value)
            except ParameterError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
            self.params[param.name] = param.value
            self.get_logger().info('parameter %s set to %r' % (param.name, param.value))
        return SetParametersResult(successful=True)

    @property
    def executor_(self) -> SingleThreadedExecutor:
        """This node's executor, made on first use, after the constructor: a
        constructor that raises (a parameter error) leaves no executor whose
        __del__ would print a traceback after rclpy has shut down."""
        if self._executor is None:
            self._executor = SingleThreadedExecutor()
            self._executor.add_node(self)
        return self._executor

    # -- parameters ---------------------------------------------------------
    def _check_unknown_keys(self) -> None:
        """Name every key no executable reads (a typo?): a warning, or with
        the parameter ``strict_parameters: true`` a ParameterError."""
        strict = self.param('strict_parameters')
        problems = unknown_keys(self.params)
        if problems and strict:
            raise ParameterError(problems[0].partition(':')[0], problems[0].partition(': ')[2]
                                 + ' (strict_parameters is true)')
        for problem in problems:
            self.get_logger().warning('%s; ignored' % problem)

    def param(self, name: str):
        """The value of the declared key ``name`` (core/plumbing/node_parameters.py):
        as given, or its default; checked (ParameterError: exit 2)."""
        return read_declared(self.params, name)

    def peer_names(self, name: str) -> list:
        """Parameter ``name``: a list of node names, relative to this node's
        namespace unless they start with '/', as full names."""
        return [v if v.startswith('/') else topics.node_full_name(self.get_namespace(), v)
                for v in self.param(name)]

    def _realtime_priority(self) -> int:
        value = self.param('realtime_priority')
        if value:
            refused = realtime_scheduling(value)
            if refused:
                self.get_logger().warning('realtime_priority %d refused by the OS (%s): normal '
                                       'scheduling' % (value, refused))
                return 0
            self.get_logger().info('SCHED_FIFO, priority %d' % value)
        return value

    # -- start-up -----------------------------------------------------------
    def publisher(self, msg_type, topic, qos, required: bool = True):
        """A data publisher: counted, flushed at the end, and waited for before
        the first message. ``required=False`` (a side output such as
        ``markers``): ``wait_for_subscribers`` does not apply to it; the
        subscriptions the graph shows on it are still waited for."""
        pub = self.create_publisher(msg_type, topic, qos)
        self.data_publishers.append(pub)
        if not required:
            self.optional_publishers.add(id(pub))
        return pub

    def subscribe_input(self) -> None:
        """Subscribe to the node's 1 kHz input (controller, fk: ``leg_lengths``).

        Called once, as the start-up wait ends (``startup.StartupBarrier``),
        not in the constructor: a node that answers samples must not take
        one before its own outputs are matched, or its answers would go to
        writers not yet matched by their readers (a recorder started first
        lost fk's first marker arrays that way, served by the executor
        turns of fk's wait). And the plant waits for this subscription
        (``lengths_peers``, ``lengths_subscribers``): so it sends its first
        sample only once each of these nodes has ended its wait, the
        start-up order of runtime/handshake.py."""

    def wait_for_matches(self, extra=None) -> bool:
        """Bounded wait before the first message until the node's subscribers
        are matched (``startup.StartupBarrier.wait``); True if they all are."""
        return self.startup.wait(extra)

    def report(self):
        if self.started:
            self.health.report(final=self.closing)

    def run(self):
        self.wait_for_matches()
        self.executor_.spin()

    # -- sources of the 1 kHz input (runtime/sources.py) -------------------------
    def watch_source(self, subscription, topic: str, gate) -> None:
        """Watch the sources of the 1 kHz input ``subscription`` (its StampGate:
        ``gate``) for collisions and restarts: see ``sources.SourceWatch``."""
        self.source_watch = SourceWatch(self, subscription, topic, gate)

    def count_skips(self, topic: str, source, info) -> None:
        """Count the messages on ``topic`` that never reached this node,
        from the sequence numbers of each publisher (checks.SkipCounter):
        on /diagnostics (``skipped/<topic>``) and in the summary."""
        counter = self._skip_counters.get(topic)
        if counter is None:
            counter = self._skip_counters[topic] = SkipCounter()
        gap = counter.note(source, info)
        if gap:
            self.health.skip(topic, gap)

    def take_forces(self, data: bytes, info, gate) -> tuple[int, object] | None:
        """A serialized ``leg_forces`` message (the plant's or the bridge's
        hot input): counted, its sender's skips counted, checked against
        ``gate`` and accepted. Returns (stamp ns, the six forces), or None
        for a rejected one (counted on /diagnostics)."""
        self.health.received[topics.LEG_FORCES] += 1
        source = source_of(info)
        self.count_skips(topics.LEG_FORCES, source, info)
        try:
            ns, _, _, _, values = wire.joint_state_sample(data, gate, ('effort',),
                                                          source=source)
        except Rejected as exc:
            self.health.reject(topics.LEG_FORCES, exc)
            return None
        self.accept_sample(gate, ns, source, topics.LEG_FORCES)
        return ns, values['effort']

    def accept_sample(self, gate, ns: int, source, topic: str) -> None:
        """Accept a checked sample; a new run of its source is logged (and counted)."""
        if gate.new_run:
            self.get_logger().warning('%s: a new run of its source (%s): accepted, %d so far'
                                   % (topic, gate.new_run, gate.restarts + 1))
        gate.accept(ns, source)

    def flush(self, timeout: float = 2.0) -> str:
        """Let the recorder receive everything before exiting (``stopping.Flush``)."""
        return self.stop_flush.flush(timeout)

    def summary(self) -> dict:
        """What the node did: counters, latency, its last status."""
        h = self.health
        return {'node': self.get_fully_qualified_name(), 'received': dict(h.received),
                'published': dict(h.published), 'rejected': dict(h.rejected),
                'rejected_total': sum(h.rejected.values()),
                'skipped': dict(h.skipped),
                'loop_latency': h.latency.summary(),
                'status': '; '.join(m for m in (h.collision, h.fault) if m) or h.warning or 'ok',
                'values': {k: v if isinstance(v, (int, float, list)) else str(v)
                           for k, v in h.values.items()}}

    def write_summary_file(self, summary: dict) -> None:
        self.summary_written = True
        if self.summary_file:
            with open(self.summary_file, 'w') as stream:
                json.dump(summary, stream, indent=1)

    #: s: the flush's bound when the node was stopped by a signal (a launcher
    #: escalates after 5 s) and at the normal end of a run, when a recorder
    #: that lags on a loaded machine is given longer to take the last messages.
    FLUSH_ON_SIGNAL, FLUSH_AT_END = 2.0, 6.0

    def close(self):
        self.closing = True
        self.report()
        started = time.monotonic()
        timeout = self.FLUSH_ON_SIGNAL if STOP.requested else self.FLUSH_AT_END
        if self.flush_deadline is not None:     # shared with the other nodes of a process
            timeout = max(0.0, min(timeout, self.flush_deadline - started))
        how = self.flush(timeout)
        self.flushed = '%s after %.3f s' % (how, time.monotonic() - started)
        if not self.summary_written:
            self.write_summary_file(self.summary())

