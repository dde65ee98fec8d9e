"""A node's side of the start-up order: ``StartupBarrier`` (every node) and
``PlantStartup`` (what the plant waits for besides).

The order itself, who waits for whom and why, is described once, with the
rest of the handshake, in runtime/handshake.py (for users: docs/interface.md,
"The handshake between nodes, recorder and rig").
"""
from __future__ import annotations

import time

from stewart63_ros import topics


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
    #: s: how long a new match must hold before the first message (wait_for_matches).
    MATCH_SETTLE = 1.0

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
        node = self.node
        pubs = node.data_publishers + [node.health.pub]
        counts = {id(pub): (pub.get_subscription_count(), node.created) for pub in pubs}

        me = node.get_fully_qualified_name()
        matched = self.word.matched

        def missing():
            out = []
            recorders = set()
            # Discovery of what already runs takes a moment (seconds, loaded):
            # until then the graph may not show a subscriber started before us.
            age = time.monotonic() - node.created
            if age < node.discovery_settle:
                out.append('discovery of the ROS graph (%.1f of %g s, discovery_settle)'
                           % (age, node.discovery_settle))
            now = time.monotonic()
            for pub in pubs:
                floor = node.wait_for_subscribers
                if id(pub) in node.optional_publishers:
                    floor = 0
                subscribers = self.graph_subscriptions(pub)
                recorders.update(name for name in map(topics.endpoint_node_name, subscribers)
                                 if name in matched)
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
                if me not in matched[name]:
                    out.append('%s to match %s\'s publishers' % (name, me))
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
            node.executor_.spin_once(timeout_sec=min(0.05, max(0.0, deadline - now)))
            if node.after_batch is not None:
                # The turn may have served the node's 1 kHz input (it is in
                # the executor too): report it now (fk's lockstep progress;
                # the plant runs on only once fk says it has handled a sample).
                node.after_batch()
            waiting = missing()
        node.started = True
        if not waiting:
            log.info('matched after %.2f s' % (time.monotonic() - start))
            return True
        log.warning('discovery: still missing after %.1f s: %s; starting anyway'
                 % (node.discovery_timeout, '; '.join(waiting)))
        node.health.warning = 'started before all subscribers matched'
        return False


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
