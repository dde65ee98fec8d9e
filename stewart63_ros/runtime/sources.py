"""Who sends a node's 1 kHz input: collisions of two sources, restarts of one."""
from __future__ import annotations

import time

#: What rmw names a publisher whose node the graph does not know yet.
UNKNOWN_NODE = '_NODE_NAME_UNKNOWN_'


class SourceWatch:
    """The sources of a RigNode's 1 kHz input ``subscription`` (its StampGate: ``gate``).

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

    #: s: how often the number of publishers on the watched input is checked
    SOURCE_CHECK_PERIOD = 0.25
    #: s: a collision ends once the input has had one source for this long
    COLLISION_CLEAR_AFTER = 1.0

    def __init__(self, node, subscription, topic: str, gate):
        self.node = node
        self.sub, self.topic, self.gate = subscription, topic, gate
        self._single_since = None
        self.collisions = 0
        node.health.values['source_restarts'] = 0
        node.health.values['collisions'] = 0
        node.create_timer(self.SOURCE_CHECK_PERIOD, self.check)

    #: s: two publishers sending within this window of each other collide
    COLLISION_WINDOW = 1.0

    def publisher_names(self, topic: str) -> list:
        """'/ns/node (gid ...)' of each publisher the graph knows on ``topic``."""
        try:
            infos = self.node.get_publishers_info_by_topic(self.node.resolve_topic_name(topic))
        except Exception:   # noqa: BLE001 - naming is a courtesy; the count is the finding
            return []
        return ['%s/%s (gid %s)' % (i.node_namespace.rstrip('/'), i.node_name,
                                    bytes(i.endpoint_gid[:12]).hex()) for i in infos]

    def check(self) -> None:
        """Every SOURCE_CHECK_PERIOD: collisions, restarts, silent extra publishers."""
        sub, topic, gate = self.sub, self.topic, self.gate
        node = self.node
        h = node.health
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
                if getattr(node, 'WITHHOLDS_ON_COLLISION', False):
                    collision += '; forces withheld'
                if collision != h.collision:
                    h.collision = collision
                    node.get_logger().error(h.collision)
                    if node.started:
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
                node.get_logger().info('collision over: one publisher sends on %s again'
                                       % sub.topic_name)
                h.collision = ''

