"""The rig's start-up order: who waits for whom before the plant's first sample.

The plant's samples drive every other node (the controller answers them, fk
poses them, the recorder writes them), so the nodes start in this order, and
nothing anybody publishes is lost:

1. ``rig --record``: the recorder first. ``record`` prints ``READY`` once it
   has a subscription on every topic (tools/record.py); ``rig`` waits for
   that line (tools/rig.py, ``Rig.start``). Composed, the recorder is opened
   before the nodes are made (nodes/composed.py).
2. The controller and fk. Each node waits before its first message
   (``RigNode.wait_for_matches``: ``StartupBarrier`` below) until every data
   publisher has ``wait_for_subscribers`` matched subscriptions (``rig``
   sets 1 when it records) and every subscription the ROS graph shows on its
   topic, after ``discovery_settle`` s for the graph to show what already
   runs; then a new match settles for ``MATCH_SETTLE`` s, and a recorder
   that the graph shows on its topics must name the node under
   ``matched_publishers`` on /diagnostics (nodes/handshake.py: the
   recorder's side of the match, which only the recorder sees).
3. ``rig --record``: the recorder prints ``MATCHED`` once it has matched the
   publishers of the controller and fk run here (``recorder_waits_for``,
   below); ``rig`` waits for that line, then starts the plant.
4. The plant waits as every node does (2.), and for what its samples need
   (``PlantStartup``): in lockstep a ``leg_forces`` publisher (a controller:
   lockstep steps only on its answers); ``lengths_subscribers`` matched
   subscriptions on ``leg_lengths`` (``rig``: controller + fk + recorder, +1
   for a controller run elsewhere); a subscription on ``leg_lengths`` from
   each node named in ``lengths_peers`` (a count alone is not enough: a
   recorder started first fills it while fk, still loading, has none yet, and
   fk would miss the run); in lockstep the progress publisher of each node
   named in ``lockstep_peers`` (nodes/lockstep.py). ``rig`` writes these
   parameters for the plant (``plant_startup_parameters``, below, through
   ``Rig.overlay``).
5. Composed (``rig --compose``): one process, the same waits in the same
   order: controller, then fk, then the plant (``Composed.run``).

Every wait is bounded by ``discovery_timeout``: a node still missing a peer
then starts anyway, with a warning in its log and on /diagnostics.
"""
from __future__ import annotations

import time

from stewart63_ros import topics


def plant_startup_parameters(nodes, record: bool, mode: str, compose: bool) -> dict:
    """The plant's start-up parameters for a rig (4. in the module's doc).

    Args:
        nodes: the nodes this rig runs here ('plant', 'controller', 'fk').
        record: the rig records (its recorder is one more reader).
        mode: the plant's ``clock_mode``.
        compose: the nodes share one process (``rig --compose``).

    Returns:
        {key: value} for the plant's section of the rig's parameter file.
    """
    wait = 1 if record else 0
    # A plant whose controller runs elsewhere (--nodes) waits for that one
    # too, or a realtime run would start without control.
    remote = 0 if 'controller' in nodes else 1
    out = {'lengths_subscribers': sum(n in nodes for n in ('controller', 'fk')) + wait + remote,
           'lengths_peers': ['controller'] + (['fk'] if 'fk' in nodes else [])}
    if mode == 'lockstep' and not compose:
        # The readers outside the control loop hold the plant back rather
        # than lose samples (nodes/lockstep.py). Composed, one loop serves
        # them all and none can fall behind.
        out['lockstep_peers'] = (['fk'] if 'fk' in nodes else []) + (['record'] if record else [])
    return out


def recorder_waits_for(nodes) -> list[str]:
    """The topics whose publishers ``rig``'s recorder must match (``MATCHED``)
    before the plant starts: those of the controller and fk run here."""
    return [t for n, t in (('controller', topics.LEG_FORCES), ('fk', topics.PLATFORM_POSE))
            if n in nodes]


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
