"""A node's side of the start-up order: ``StartupBarrier`` (every node) and
``PlantStartup`` (what the plant waits for besides).

The order itself, who waits for whom and why, is described once, with the
rest of the handshake, in runtime/handshake.py (for users: docs/interface.md,
"The handshake between nodes, recorder and rig").
"""
from __future__ import annotations

import time

from stewart63_ros import topics
from stewart63_ros.runtime import recorders


class StartupBarrier:
    """``wait(extra)`` before a RigNode's first message (its ``wait_for_matches``; 2.).

    Uses the node's ``data_publishers``, ``optional_publishers``, health
    publisher, ``wait_for_subscribers``, ``discovery_settle``,
    ``discovery_timeout`` and ``created``, and what the recorders say
    (``word``: handshake.RecorderWord).
    """

    def __init__(self, node, word):
        self.node = node
        self.word = word

    #: s: how often a node still waiting for its peers says what it waits for.
    WAIT_REPORT_PERIOD = 5.0

    def graph_subscriptions(self, pub) -> list:
        """The subscriptions the ROS graph shows on ``pub``'s topic that can
        match it (same type, compatible QoS): a recorder, viewer or driver
        started before this node."""
        cls = pub.msg_type
        type_name = '%s/msg/%s' % (cls.__module__.split('.')[0], cls.__name__)
        return [info for info in self.node.get_subscriptions_info_by_topic(pub.topic_name)
                if info.topic_type == type_name
                and topics.can_match(pub.qos_profile, info.qos_profile)]

    def wait(self, extra=None) -> bool:
        """Bounded wait (``discovery_timeout``) before the first message until
        every data publisher has matched ``wait_for_subscribers``
        subscriptions and every subscription the ROS graph shows on its topic,
        every recorder that could lose this node's messages has matched it
        (``recorders_missing``), and ``extra()`` (a list of what else is
        missing) is empty.

        No fixed settle by default: these events end the wait, not a clock.
        ``discovery_settle`` (0 unless set) gives the graph that long from
        the node's start to show a subscriber that runs already and that
        neither the run nor this machine names (a recorder on another host).
        A subscription that matched after a sample was sent still gets it:
        the writer counted it as matched, and its heartbeat (50 ms,
        config/fastdds.xml) repairs the sample (test/test_startup_order.py
        shows it). Says at once what it waits for, and again every few s."""
        node = self.node
        if node.started:
            return True         # (once: run_on waits too, after a node's own wait)
        pubs = node.data_publishers + [node.health.pub]
        # Recorders running on this machine (runtime/recorders.py): known
        # before discovery shows them, so waited for like one it shows.
        # (A test's stand-in for a node has no ROS context: no recorders then.)
        context = getattr(node, 'context', None)
        noted = [] if context is None else recorders.running(context.get_domain_id())

        def missing():
            out = []
            age = time.monotonic() - node.created
            if age < node.discovery_settle:
                out.append('discovery of the ROS graph (%.1f of %g s, discovery_settle)'
                           % (age, node.discovery_settle))
            for pub in pubs:
                floor = node.wait_for_subscribers
                if id(pub) in node.optional_publishers:
                    floor = 0
                want = max(floor, len(self.graph_subscriptions(pub)))
                have = pub.get_subscription_count()
                if have < want:
                    out.append('%s: %d of %d subscriptions matched'
                               % (pub.topic_name, have, want))
            out += self.recorders_missing(pubs, noted)
            return out + (list(extra()) if extra is not None else [])

        log = node.get_logger()
        start = time.monotonic()
        deadline = start + node.discovery_timeout
        next_report = start
        waiting = missing()
        while waiting and time.monotonic() < deadline:
            now = time.monotonic()
            if now >= next_report:
                log.info('waiting (at most %.1f s more, discovery_timeout) for: %s'
                         % (deadline - now, '; '.join(waiting)))
                next_report = now + self.WAIT_REPORT_PERIOD
            # 10 ms: a match is no executor event, so this is how soon one is seen
            node.executor_.spin_once(timeout_sec=min(0.01, max(0.0, deadline - now)))
            if node.after_batch is not None:
                # The turn may have served the node's 1 kHz input (it is in
                # the executor too): report it now (fk's lockstep progress;
                # the plant runs on only once fk says it has handled a sample).
                node.after_batch()
            waiting = missing()
        node.started = True
        # Its outputs are matched: now it may take its input (see subscribe_input).
        subscribe = getattr(node, 'subscribe_input', None)
        if subscribe is not None:
            subscribe()
        if not waiting:
            log.info('matched after %.2f s' % (time.monotonic() - start))
            return True
        log.warning('discovery: still missing after %.1f s: %s; starting anyway'
                 % (node.discovery_timeout, '; '.join(waiting)))
        node.health.warning = 'started before all subscribers matched'
        return False


    def recorders_missing(self, pubs, noted) -> list[str]:
        """What the recorders still miss to record this node from its first
        message: each one the graph shows on a topic of ``pubs`` or that is
        ``noted`` running here must have said on /diagnostics what it records
        (``RecorderWord``); on each such topic the graph must show its
        subscription (so the count above holds the writer's side of the
        match), and it must name this node under ``matched_publishers``
        (its side: only it sees that)."""
        node = self.node
        me = node.get_fully_qualified_name()
        word = self.word
        shown = {}          # recorder -> topics of pubs it subscribes, as the graph shows
        for pub in pubs:
            for name in map(topics.endpoint_node_name, self.graph_subscriptions(pub)):
                shown.setdefault(name, set()).add(pub.topic_name)
        out = []
        for name in sorted(set(noted) | (set(shown) & set(word.matched))):
            if name not in word.matched:
                out.append('%s (recording on this machine) to say what it records' % name)
                continue
            mine = {pub.topic_name for pub in pubs} & word.recorded.get(name, set())
            for topic in sorted(mine - shown.get(name, set())):
                out.append('%s: the subscription of %s' % (topic, name))
            # Its side, topic by topic: its graph may show only some of this
            # node's publishers yet, and name it matched on those alone.
            on = getattr(word, 'matched_on', {}).get(name, {})
            unmatched = sorted(t for t in mine if me not in on.get(t, ()))
            if unmatched:
                out.append('%s to match %s on %s' % (name, me, ', '.join(unmatched)))
            elif (mine or name in shown) and me not in word.matched[name]:
                out.append('%s to match %s\'s publishers' % (name, me))
        return out


class PlantStartup:
    """What the plant waits for besides its subscribers (4. in the module's doc):
    its parameters ``lengths_subscribers`` and ``lengths_peers`` (full
    names), the controller's answers in lockstep, and its lockstep peers
    (``peers``: a ``lockstep.PeerWindow``, or None)."""

    def __init__(self, plant):
        self.plant = plant
        # Lockstep cannot start before the controller is there to answer.
        self.need_forces = 1 if plant.mode == 'lockstep' else 0

    def missing(self) -> list[str]:
        """What the plant still waits for (empty: nothing)."""
        plant = self.plant
        out = []
        if plant.sub_forces is None:
            return out      # on the bus: the bridge waits for these (canopen_bridge)
        if plant.sub_forces.get_publisher_count() < self.need_forces:
            out.append('a %s publisher (a controller: lockstep steps only on its '
                       'answers)' % plant.sub_forces.topic_name)
        lengths = plant.outputs.pub_lengths
        have = lengths.get_subscription_count()
        if have < plant.lengths_subscribers:
            out.append('%s: %d of %d subscriptions matched (lengths_subscribers)'
                       % (lengths.topic_name, have, plant.lengths_subscribers))
        shown = {topics.endpoint_node_name(info) for info in
                 plant.get_subscriptions_info_by_topic(lengths.topic_name)}
        for peer in plant.lengths_peers:
            if peer not in shown:
                out.append('%s: no subscription from %s yet (lengths_peers)'
                           % (lengths.topic_name, peer))
        if plant.peers is not None:
            out += plant.peers.missing_publishers()
        return out


class FirstAnswer:
    """Before a node answers the first sample of a source (a plant, or a
    plant started again): ``wait(source)`` until its answer's writer
    ``pub`` has matched the subscription that answer is for.

    The race it ends: the plant counts the controller's writer as matched
    (its side) and sends sample 0, which the controller answers at once; if
    the controller's writer has not discovered the plant's subscription yet,
    the answer is sent to nobody and never repaired (a volatile writer owes
    nothing to a reader it matches later), and a lockstep plant then waits
    its whole ``discovery_timeout`` for it (20 s, a plant started under a
    running controller at ``-n 2``). The sample itself proves the source's
    participant is discovered; its subscription shows in the graph, and is
    matched by the writer, within a discovery exchange.

    ``to_source``: the answer goes to the sample's own node (the controller's
    ``leg_forces`` to the plant, the supervisor's); else (a controller whose
    forces a supervisor takes) to whatever the graph shows on the topic, at
    least one. Bounded by ``discovery_timeout``; a wait is logged."""

    def __init__(self, node, pub, input_topic: str, to_source: bool = True):
        self.node, self.pub, self.to_source = node, pub, to_source
        self.input_topic = node.resolve_topic_name(input_topic)
        self.answered = None        # the source whose first sample was answered

    def source_node(self, source: bytes) -> str | None:
        """The full name of the node whose publisher has GID ``source``."""
        for info in self.node.get_publishers_info_by_topic(self.input_topic):
            gid = bytes(info.endpoint_gid)
            n = min(len(gid), len(source), 16)
            if n and gid[:n] == source[:n]:
                return topics.endpoint_node_name(info)
        return None

    def missing(self, source: bytes) -> str:
        """What the first answer to ``source`` still waits for ('' : nothing)."""
        shown = self.node.startup.graph_subscriptions(self.pub)
        have = self.pub.get_subscription_count()
        if have < len(shown):
            return '%s: %d of %d subscriptions matched' % (self.pub.topic_name, have, len(shown))
        if not self.to_source:
            return '' if shown else 'a %s subscription' % self.pub.topic_name
        name = self.source_node(source)
        if name is None:
            return 'the sender of %s in the ROS graph' % self.input_topic
        if name not in {topics.endpoint_node_name(info) for info in shown}:
            return '%s: the subscription of %s' % (self.pub.topic_name, name)
        return ''

    def wait(self, source) -> None:
        """Called before each answer: returns at once but for a new source."""
        if source is None or source == self.answered:
            return
        self.answered = source
        node = self.node
        start = time.monotonic()
        deadline = start + node.discovery_timeout
        waiting = first = self.missing(source)
        while waiting and time.monotonic() < deadline:
            time.sleep(0.001)       # the graph is the middleware's: no executor turn needed
            waiting = self.missing(source)
        waited = time.monotonic() - start
        if waiting:
            node.get_logger().warning('first answer to a new source sent after %.1f s '
                                      '(discovery_timeout) without %s' % (waited, waiting))
        elif first:
            node.get_logger().info('first answer to a new source: waited %.3f s for %s'
                                   % (waited, first))
