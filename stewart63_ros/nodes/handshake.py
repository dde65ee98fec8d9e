"""The /diagnostics handshake between the rig's nodes, its recorder and ``rig``.

The one place for its words; what it does, step by step, for users:
docs/interface.md, "The handshake between nodes, recorder and rig".

- at start-up the recorder's status names, under ``matched_publishers``, the
  nodes every one of whose publishers it has matched; a starting node waits
  for its own name before its first message (``startup.StartupBarrier``);
- a stopping node's last status says ``final: true`` and, under
  ``final/<topic>``, how many messages it published on each topic; the
  recorder answers with ``confirms`` (the statuses' names) once its bag holds
  them, and the node stops waiting (``stopping.Flush``);
- the plant says ``run: ended`` when no more samples come because its run is
  over, so the controller tells the end of a run from a lost sensor.

``RecorderWord`` is a node's side: one raw subscription to /diagnostics,
read only while the node starts and while it stops.
"""
from __future__ import annotations

from stewart63_ros import topics

MATCHED = 'matched_publishers'
CONFIRMS = 'confirms'
FINAL = 'final'
FINAL_PREFIX = 'final/'
RUN = 'run'
RUN_ENDED = 'ended'
#: What ``record`` prints on its standard output, one line each, for ``rig``
#: (start-up order: nodes/startup.py): subscribed to every topic; matched
#: the publishers it was told to wait for.
READY_LINE = 'READY'
MATCHED_LINE = 'MATCHED'


def final_counts(values: dict) -> dict[str, int] | None:
    """``{topic: count}`` of a last status's values (``None`` if the status
    is not a node's last one)."""
    if values.get(FINAL) != 'true':
        return None
    out = {}
    for key, value in values.items():
        if key.startswith(FINAL_PREFIX):
            try:
                out[key[len(FINAL_PREFIX):]] = int(value)
            except ValueError:
                pass
    return out


class RecorderWord:
    """What the rig's recorders say to this node on /diagnostics.

    ``matched``: recorder's full name -> the nodes it says it has matched;
    ``confirmed``: a recorder said its bag holds all this node published.
    """

    def __init__(self, node):
        from diagnostic_msgs.msg import DiagnosticArray
        self.node = node
        self.matched: dict[str, set] = {}
        self.confirmed = False
        self.sub = node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS,
                                            self.on_status, topics.DIAGNOSTICS_QOS, raw=True)

    def on_status(self, data) -> None:
        """A /diagnostics message, read while the node starts or stops."""
        node = self.node
        if node.started and (not node.closing or self.confirmed):
            return
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.serialization import deserialize_message
        try:
            msg = deserialize_message(bytes(data), DiagnosticArray)
        except Exception:   # noqa: BLE001 - not a status we can read: not a confirmation
            return
        me = node.health.status_name
        for status in msg.status:
            for kv in status.values:
                if kv.key == MATCHED and not node.started:
                    recorder = status.name[len(topics.STATUS_PREFIX):]
                    self.matched[recorder] = set(kv.value.split(','))
                elif kv.key == CONFIRMS and node.closing and me in kv.value.split(','):
                    self.confirmed = True

    def take_waiting(self) -> None:
        """Read what has come, without the executor (the node is stopping)."""
        from stewart63_ros.nodes.rclpy_internals import take
        while True:
            data = take(self.sub)
            if data is None:
                return
            self.on_status(data)
