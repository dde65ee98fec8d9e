"""RigNode: the rclpy Node every stewart63 node derives from."""
from __future__ import annotations

import gc
import time

from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from stewart63_ros import topics
from stewart63_ros.core.params import ParameterError, mechanism_from_params, unknown_keys
from stewart63_ros.core.precompile import COMPILE_NOTICE, kernel_cache_cold
from stewart63_ros.nodes.checks import SkipCounter
from stewart63_ros.nodes.diagnostics import Health
from stewart63_ros.nodes.launcher import STOP
from stewart63_ros.nodes.parameters import load_parameters, ros_parameters
from stewart63_ros.nodes.rclpy_internals import DirectTake, run_timer_if_ready, take
from stewart63_ros.nodes.realtime import realtime_scheduling

#: What rmw names a publisher whose node the graph does not know yet.
UNKNOWN_NODE = '_NODE_NAME_UNKNOWN_'


class RigNode(Node):
    """Loads the mechanism from the node's parameters and owns the diagnostics.

    Node-specific keys shared by all nodes (docs/interface.md, "Parameters"):
    ``wait_for_subscribers`` (int, 0): before its first message, wait until
    every data publisher of this node has that many matched subscriptions
    (``rig --record`` sets 1 so that the recorder misses nothing);
    ``discovery_timeout`` (s, 20): the bound on that wait;
    ``realtime_priority`` (0..99, 0): when not 0, the node's threads run
    SCHED_FIFO at that priority (where the OS allows it; a warning and normal
    scheduling where it does not), so that other work on the machine cannot
    keep a 1 kHz loop waiting for a CPU for a scheduler slice (3-4 ms).
    """

    def __init__(self, name: str):
        # Parameters as nodes/parameters.py reads them (a -p wins over the
        # files; a file given is the whole model), declared as the node's
        # ROS parameters so that ros2 param shows what the node runs with.
        self._created = time.monotonic()       # the graph's discovery starts about now
        _, params = load_parameters(name)
        super().__init__(name, parameter_overrides=ros_parameters(params),
                         automatically_declare_parameters_from_overrides=True,
                         allow_undeclared_parameters=True)
        self.params = params
        self._check_unknown_keys()
        self.mech = mechanism_from_params(self.params)
        if kernel_cache_cold():
            self.get_logger().info(COMPILE_NOTICE)
        self.wait_for_subscribers = int(self.param('wait_for_subscribers', 0))
        self.discovery_timeout = self.positive('discovery_timeout', 20.0)
        # A participant announces itself every 3 s after its first burst (Fast
        # DDS): one lost exchange and the graph shows a running recorder only
        # then (measured 0.6-1.4 s here, and more than 2 s in 1 of ~10 loaded
        # starts). 4 s outlasts one period.
        self.discovery_settle = float(self.param('discovery_settle', 4.0))
        if not 0 <= self.discovery_settle <= self.discovery_timeout:
            raise ParameterError('discovery_settle', 'must be from 0 to discovery_timeout '
                                 '(%g s), got %r' % (self.discovery_timeout,
                                                     self.discovery_settle))
        self.health = Health(self, name)
        self._skip_counters = {}
        #: called by run_on after each batch of messages (fk's lockstep progress)
        self.after_batch = None
        #: where close() writes the node's summary as JSON ('' : nowhere)
        self.summary_file = str(self.param('summary_file', ''))
        self.summary_written = False
        self.realtime_priority = self._realtime_priority()
        self._executor = None       # made on first use: see executor_
        self.data_publishers = []
        self._optional_publishers = set()
        self.started = False        # diagnostics wait for the peers, like the data
        # Run-time changes through the parameter services: only the keys a
        # node registers with ``tunable`` may change; every other one is
        # refused with a reason (the model is fixed once the node runs).
        self._tunable = {}
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.create_timer(1.0, self.report)
        self.closing = False         # the next report is the last one (see close)
        self._recorded = False      # a recorder confirmed it holds everything (see flush)
        self.flushed = ''           # how the flush at close ended, for the node's log
        #: called while flush waits: a recorder in the same thread takes its messages
        self.while_flushing = None
        from diagnostic_msgs.msg import DiagnosticArray

        from stewart63_ros import topics
        #: recorder's full name -> the nodes it says it has matched (see
        #: wait_for_matches and Recorder._report)
        self._recorders_matched: dict[str, set] = {}
        self._confirmations = self.create_subscription(
            DiagnosticArray, topics.DIAGNOSTICS, self._on_confirmation, topics.DIAGNOSTICS_QOS,
            raw=True)

    # -- run-time parameter changes --------------------------------------------
    def tunable(self, name: str, apply) -> None:
        """Let parameter ``name`` change at run time (``ros2 param set``).

        ``apply(value)`` checks the new value and puts it into effect at once,
        or raises ``ParameterError`` with the reason: the change is then
        refused and nothing changes.
        """
        self._tunable[name] = apply

    def _on_set_parameters(self, parameters):
        from rcl_interfaces.msg import SetParametersResult
        for param in parameters:
            if param.name == 'use_sim_time':      # rclpy's own, applied by rclpy
                continue
            apply = self._tunable.get(param.name)
            if apply is None:
                return SetParametersResult(successful=False, reason=(
                    '%s cannot be changed while the node runs (the model and the node '
                    'set-up are fixed at start-up); restart the node with the new value'
                    % param.name))
            try:
                apply(param.value)
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
        strict = self.params.get('strict_parameters', False)
        if not isinstance(strict, bool):
            raise ParameterError('strict_parameters', 'must be true or false, got %r' % (strict,))
        problems = unknown_keys(self.params)
        if problems and strict:
            raise ParameterError(problems[0].partition(':')[0], problems[0].partition(': ')[2]
                                 + ' (strict_parameters is true)')
        for problem in problems:
            self.get_logger().warning('%s; ignored' % problem)

    def param(self, name, default):
        return self.params.get(name, default)

    def peer_names(self, name) -> list:
        """Parameter ``name``: a list of node names, relative to this node's
        namespace unless they start with '/', as full names."""
        value = self.param(name, [])
        if isinstance(value, str) or not all(isinstance(v, str) and v.strip('/')
                                             for v in value):
            raise ParameterError(name, 'expected a list of node names, got %r' % (value,))
        return [v if v.startswith('/') else topics.node_full_name(self.get_namespace(), v)
                for v in value]

    def positive(self, name, default) -> float:
        try:
            value = float(self.param(name, default))
        except (TypeError, ValueError):
            raise ParameterError(name, 'expected a number, got %r'
                                 % self.param(name, default)) from None
        if not value > 0 or value == float('inf'):
            raise ParameterError(name, 'must be a positive finite number, got %r' % value)
        return value

    def _realtime_priority(self) -> int:
        value = self.param('realtime_priority', 0)
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 99:
            raise ParameterError('realtime_priority', 'must be an integer from 0 (normal '
                                 'scheduling) to 99, got %r' % (value,))
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
            self._optional_publishers.add(id(pub))
        return pub

    #: s: how often a node still waiting for its peers says what it waits for.
    WAIT_REPORT_PERIOD = 5.0
    #: s: how long a new match must hold before the first message (wait_for_matches).
    MATCH_SETTLE = 1.0

    def graph_subscriptions(self, pub) -> list:
        """The subscriptions the ROS graph shows on ``pub``'s topic that can
        match it (same type, compatible QoS): a recorder, viewer or driver
        started before this node."""
        cls = pub.msg_type
        type_name = '%s/msg/%s' % (cls.__module__.split('.')[0], cls.__name__)
        return [info for info in self.get_subscriptions_info_by_topic(pub.topic_name)
                if info.topic_type == type_name
                and topics.can_match(pub.qos_profile, info.qos_profile)]

    def wait_for_matches(self, extra=None) -> bool:
        """Bounded wait (``discovery_timeout``) before the first message until
        every data publisher has matched ``wait_for_subscribers``
        subscriptions and every subscription the ROS graph shows on its topic
        (so a recorder started before the rig gets everything from the first
        message), and ``extra()`` (a list of what else is missing) is empty.
        The graph is given ``discovery_settle`` s from the node's start to
        show what already runs. A new match must then hold for
        ``MATCH_SETTLE`` s: a publisher counts a subscription as matched as
        soon as it has discovered it, but the subscription drops what comes
        before it has discovered the publisher in turn (a volatile reader
        starts at the first sample it sees announced), which under load has
        lagged tens of ms. Says at once what it waits for, and again every
        few s."""
        pubs = self.data_publishers + [self.health.pub]
        counts = {id(pub): (pub.get_subscription_count(), self._created) for pub in pubs}

        me = self.get_fully_qualified_name()

        def missing():
            out = []
            recorders = set()
            # Discovery of what already runs takes a moment (seconds, loaded):
            # until then the graph may not show a subscriber started before us.
            age = time.monotonic() - self._created
            if age < self.discovery_settle:
                out.append('discovery of the ROS graph (%.1f of %g s, discovery_settle)'
                           % (age, self.discovery_settle))
            now = time.monotonic()
            for pub in pubs:
                floor = self.wait_for_subscribers
                if id(pub) in self._optional_publishers:
                    floor = 0
                subscribers = self.graph_subscriptions(pub)
                recorders.update(name for name in map(topics.endpoint_node_name, subscribers)
                                 if name in self._recorders_matched)
                want = max(floor, len(subscribers))
                have = pub.get_subscription_count()
                if have != counts[id(pub)][0]:
                    counts[id(pub)] = (have, now)
                if have < want:
                    out.append('%s: %d of %d subscriptions matched'
                               % (pub.topic_name, have, want))
                elif now - counts[id(pub)][1] < self.MATCH_SETTLE:
                    out.append('%s: a new match settling' % pub.topic_name)
            for name in sorted(recorders):
                if me not in self._recorders_matched[name]:
                    out.append('%s to match %s\'s publishers' % (name, me))
            return out + (list(extra()) if extra is not None else [])

        log = self.get_logger()
        start = time.monotonic()
        deadline = start + self.discovery_timeout
        next_report = start
        waiting = missing()
        while waiting and time.monotonic() < deadline:
            now = time.monotonic()
            if now >= next_report:
                log.info('waiting (at most %.1f s more, discovery_timeout) for: %s'
                         % (deadline - now, '; '.join(waiting)))
                next_report = now + self.WAIT_REPORT_PERIOD
            self.executor_.spin_once(timeout_sec=min(0.05, max(0.0, deadline - now)))
            waiting = missing()
        self.started = True
        if not waiting:
            log.info('matched after %.2f s' % (time.monotonic() - start))
            return True
        log.warning('discovery: still missing after %.1f s: %s; starting anyway'
                 % (self.discovery_timeout, '; '.join(waiting)))
        self.health.warning = 'started before all subscribers matched'
        return False

    def report(self):
        if self.started:
            self.health.report(final=self.closing)

    def run(self):
        self.wait_for_matches()
        self.executor_.spin()

    # -- sources of the 1 kHz input ---------------------------------------------
    #: s: how often the number of publishers on the watched input is checked
    SOURCE_CHECK_PERIOD = 0.25
    #: s: a collision ends once the input has had one source for this long
    COLLISION_CLEAR_AFTER = 1.0

    def watch_source(self, subscription, topic: str, gate) -> None:
        """Watch the sources of the 1 kHz input ``subscription`` (its StampGate: ``gate``).

        Two publishers that both sent samples within ``COLLISION_WINDOW``
        (interleaved, or alternating in runs) are a collision: ERROR on
        /diagnostics naming the publishers (two rigs in one domain under one
        namespace feed each other) until the input has had a single sender
        for ``COLLISION_CLEAR_AFTER``. More than one publisher matched while
        only one sends is a warning: a killed source's endpoint stays in the
        graph until its lease runs out, a ``play`` may not have started yet.
        New runs of the source (a restarted plant, a bag played again) are
        counted as ``source_restarts``.
        """
        self._watched = (subscription, topic, gate)
        self._single_since = None
        self.collisions = 0
        self.health.values['source_restarts'] = 0
        self.health.values['collisions'] = 0
        self.create_timer(self.SOURCE_CHECK_PERIOD, self.check_sources)

    #: s: two publishers sending within this window of each other collide
    COLLISION_WINDOW = 1.0

    def publisher_names(self, topic: str) -> list:
        """'/ns/node (gid ...)' of each publisher the graph knows on ``topic``."""
        try:
            infos = self.get_publishers_info_by_topic(self.resolve_topic_name(topic))
        except Exception:   # noqa: BLE001 - naming is a courtesy; the count is the finding
            return []
        return ['%s/%s (gid %s)' % (i.node_namespace.rstrip('/'), i.node_name,
                                    bytes(i.endpoint_gid[:12]).hex()) for i in infos]

    def check_sources(self) -> None:
        sub, topic, gate = self._watched
        h = self.health
        count = sub.get_publisher_count()
        senders = gate.senders(self.COLLISION_WINDOW)
        h.values['source_restarts'] = gate.restarts
        h.source_warning = ''
        if len(senders) > 1:
            self._single_since = None
            # The graph may not know a new publisher's node yet: its name is
            # looked up again on later checks while the collision lasts.
            first = not h.collision
            if first or UNKNOWN_NODE in h.collision:
                if first:
                    self.collisions += 1
                    h.values['collisions'] = self.collisions
                names = self.publisher_names(topic)
                if len(names) < len(senders):
                    names += ['gid %s' % g[:12].hex() for g in senders]
                collision = ('collision: %d publishers send on %s: %s; two rigs in one '
                             'domain under one namespace? samples of the second source '
                             'refused' % (len(senders), sub.topic_name, ', '.join(names)))
                if getattr(self, 'WITHHOLDS_ON_COLLISION', False):
                    collision += '; forces withheld'
                if collision != h.collision:
                    h.collision = collision
                    self.get_logger().error(h.collision)
                    if self.started:
                        h.report()
            return
        if count > 1:
            h.source_warning = ('%d publishers matched on %s, one sends: %s' % (
                count, sub.topic_name, ', '.join(self.publisher_names(topic))))
        if h.collision:
            now = time.monotonic()
            if self._single_since is None:
                self._single_since = now
            elif now - self._single_since >= self.COLLISION_CLEAR_AFTER:
                self.get_logger().info('collision over: one publisher sends on %s again'
                                       % sub.topic_name)
                h.collision = ''

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

    def accept_sample(self, gate, ns: int, source, topic: str) -> None:
        """Accept a checked sample; a new run of its source is logged (and counted)."""
        if gate.new_run:
            self.get_logger().warning('%s: a new run of its source (%s): accepted, %d so far'
                                   % (topic, gate.new_run, gate.restarts + 1))
        gate.accept(ns, source)

    # -- hot loops -----------------------------------------------------------
    #: s: the longest a node in a hot loop (run_on, the plant's loops) goes
    #: without an executor turn, for what only the executor serves: parameter
    #: services and QoS event reports. A turn costs 150-500 us of Python (the
    #: executor rebuilds its wait set of some 30 entities), so it is kept rare:
    #: the node's timers are run directly when due, and its other
    #: subscriptions are taken directly (see housekeeping).
    EXECUTOR_PERIOD = 0.1

    def start_hot_loop(self, hot) -> DirectTake:
        """Set up housekeeping around the 1 kHz subscription ``hot``.

        Also takes everything made so far (modules, kernels, middleware
        objects: hundreds of thousands) out of Python's cyclic garbage
        collector: a full collection over them stops the process for 20-40 ms
        at some point of every run, 20-40 missed 1 kHz cycles; what the loop
        makes is still collected.
        """
        gc.collect()
        gc.freeze()
        # From here a stop signal is a flag the loop checks (see StopSignals).
        STOP.interruptible = False
        if STOP.requested:
            raise KeyboardInterrupt
        self._side_subs = [s for s in self.subscriptions if s is not hot]
        self._next_turn = 0.0
        self._next_executor_turn = 0.0
        return DirectTake(self, hot)

    def housekeeping(self, now: float, turn_ok: bool = True) -> float:
        """Between two messages of the hot loop: take what came in on the
        node's other subscriptions (a microsecond each when nothing did), then,
        if one is due, either run the due timers or give the executor a turn
        (one of the two, to keep each call short). ``turn_ok=False`` puts that
        off (the caller is short of time), by 0.1 s at most. Returns the
        monotonic time of the next due one: the caller should not block past it.
        """
        for sub in self._side_subs:
            msg = take(sub)
            if msg is not None:
                sub.callback(msg)
        if now < self._next_turn or not (turn_ok or now > self._next_turn + 0.1):
            return self._next_turn
        if not self._run_due_timers() and now >= self._next_executor_turn:
            self.executor_.spin_once(timeout_sec=0)
            self._next_executor_turn = time.monotonic() + self.EXECUTOR_PERIOD
        now = time.monotonic()
        wake = self._next_executor_turn
        for timer in self.timers:
            left = timer.time_until_next_call()
            if left is not None:
                wake = min(wake, now + max(0.0, left * 1e-9))
        self._next_turn = wake
        return wake

    def _run_due_timers(self) -> bool:
        """Call the node's due timers as the executor would; True if any was."""
        ran = False
        for timer in list(self.timers):
            ran = run_timer_if_ready(timer) or ran
        return ran

    #: the most messages taken in one batch before housekeeping (run_on)
    BATCH_MAX = 1000

    def run_on(self, subscription, batch_period: float = 0.0):
        """Serve ``subscription`` directly (see DirectTake), with housekeeping
        after every message: a turn of the executor then falls in the time
        the peer needs to send the next one.

        ``batch_period`` > 0 [s]: after a message, take what else is queued,
        then let the next ones gather that long (or until housekeeping is
        due) before waiting again: one wake-up per batch instead of one per
        message, for a node nothing waits on (every message is still
        served, in order)."""
        import rclpy
        self.wait_for_matches()
        direct = self.start_hot_loop(subscription)
        while rclpy.ok() and not STOP.requested:
            wake = self.housekeeping(time.monotonic())
            if direct.poll(wake - time.monotonic()) and batch_period > 0:
                n = 1
                while n < self.BATCH_MAX and not STOP.requested and direct.poll(0.0):
                    n += 1
                if self.after_batch is not None:
                    self.after_batch()
                pause = min(batch_period, wake - time.monotonic())
                if pause > 0 and not STOP.requested:
                    time.sleep(pause)

    def flush_publishers(self) -> list:
        """What ``flush`` waits for: every publisher of the node."""
        return self.data_publishers + [self.health.pub]

    def _on_confirmation(self, data) -> None:
        """A /diagnostics message. While the node starts: a recorder's status
        names under ``matched_publishers`` the nodes whose publishers it has
        matched (wait_for_matches). While it stops: a recorder's status that
        names this node under ``confirms`` holds all it published (flush)."""
        if self.started and (not self.closing or self._recorded):
            return
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.serialization import deserialize_message
        try:
            msg = deserialize_message(bytes(data), DiagnosticArray)
        except Exception:   # noqa: BLE001 - not a status we can read: not a confirmation
            return
        me = self.health.status_name
        for status in msg.status:
            for kv in status.values:
                if kv.key == 'matched_publishers' and not self.started:
                    recorder = status.name[len(topics.STATUS_PREFIX):]
                    self._recorders_matched[recorder] = set(kv.value.split(','))
                elif kv.key == 'confirms' and self.closing and me in kv.value.split(','):
                    self._recorded = True

    #: s: how often flush looks at the acknowledgements and confirmations
    FLUSH_POLL = 0.005

    def flush(self, timeout: float = 2.0) -> str:
        """Let reliable subscribers (the recorder) receive everything before exiting.

        Done when the package's recorder confirms on /diagnostics that it
        holds every message the node's last status says it published (a few
        ms after that status), or when every subscriber has acknowledged
        everything, or at ``timeout``. The acknowledgements alone are slow: a
        subscriber acknowledges at the writer's next heartbeat (Fast DDS:
        every 3 s), long after it has the data, and a stop must stay well
        inside a launcher's 5 s. Returns how it ended: ``recorder``,
        ``acknowledged`` or ``timeout``.
        """
        from rclpy.duration import Duration
        deadline = time.monotonic() + timeout
        now_ = Duration(seconds=0)

        def unacked(pub):
            try:
                return pub.get_subscription_count() > 0 and not pub.wait_for_all_acked(now_)
            except RuntimeError:     # a publisher already destroyed: nothing left to send
                return False
        pending = [p for p in self.flush_publishers() if unacked(p)]
        while pending:
            if self._recorded:
                return 'recorder'
            if time.monotonic() >= deadline:
                return 'timeout'
            if self.while_flushing is not None:
                self.while_flushing()
            time.sleep(self.FLUSH_POLL)
            while True:         # the confirmation, taken here: no executor turns now
                data = take(self._confirmations)
                if data is None:
                    break
                self._on_confirmation(data)
            pending = [p for p in pending if unacked(p)]
        return 'acknowledged'

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
            import json
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
        how = self.flush(self.FLUSH_ON_SIGNAL if STOP.requested else self.FLUSH_AT_END)
        self.flushed = '%s after %.3f s' % (how, time.monotonic() - started)
        if not self.summary_written:
            self.write_summary_file(self.summary())

