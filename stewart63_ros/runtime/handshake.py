"""The handshake between the rig's nodes, its recorder and ``rig``: its words
and its order, in one place (for users: docs/interface.md, "The handshake
between nodes, recorder and rig").

**Start-up: who waits for whom before the plant's first sample.**
The plant's samples drive every other node (the controller answers them, fk
poses them, the recorder writes them), so the nodes start in this order, and
nothing anybody publishes is lost:

1. ``rig --record``: the recorder first. ``record`` prints ``READY`` once it
   has a subscription on every topic (tools/record.py); ``rig`` waits for
   that line (tools/rig.py, ``Rig.start``). Composed, the recorder is opened
   before the nodes are made (nodes/composed.py).
2. The controller and fk. Each node waits before its first message
   (``RigNode.wait_for_matches``: ``startup.StartupBarrier``) until every data
   publisher has ``wait_for_subscribers`` matched subscriptions (``rig``
   sets 1 when it records) and every subscription the ROS graph shows on its
   topic, and a recorder that the graph shows on its topics must name the
   node under ``matched_publishers`` on /diagnostics (below: the recorder's
   side of the match, which only the recorder sees). A ``record`` running
   on this machine is waited for so before discovery shows it: it leaves a
   note (runtime/recorders.py), and on each topic its status says it records
   (``recorded/<topic>``) the node waits for its subscription, matched. No
   fixed settle: these events end the wait (``discovery_settle``, 0 by
   default, adds one for a subscriber on another host the run does not
   name). Only then does each (and a supervisor) subscribe to
   ``leg_lengths`` (``RigNode.subscribe_input``): it answers no sample
   before its outputs are matched, and the plant, which waits for these
   subscriptions (4.), waits so for the end of their start-up.
3. ``rig --record``: the recorder prints ``MATCHED`` once it has matched the
   publishers of the controller and fk run here (``recorder_waits_for``,
   below); ``rig`` waits for that line, then starts the plant.
4. The plant waits as every node does (2.), and for what its samples need
   (``startup.PlantStartup``): in lockstep a ``leg_forces`` publisher (a controller:
   lockstep steps only on its answers); ``lengths_subscribers`` matched
   subscriptions on ``leg_lengths`` (``rig``: controller + fk + recorder, +1
   for a controller run elsewhere); a subscription on ``leg_lengths`` from
   each node named in ``lengths_peers`` (a count alone is not enough: a
   recorder started first fills it while fk, still loading, has none yet, and
   fk would miss the run); in lockstep the progress publisher of each node
   named in ``lockstep_peers`` (runtime/lockstep.py). ``rig`` writes these
   parameters for the plant (``plant_startup_parameters``, below, through
   ``Rig.overlay``).
5. Composed (``rig --compose``): one process, the same waits in the same
   order: controller, then fk, then the plant (``Composed.run``).

Every wait is bounded by ``discovery_timeout``: a node still missing a peer
then starts anyway, with a warning in its log and on /diagnostics. In
lockstep, the first answer of the controller (or a supervisor) to a new
source waits besides for its writer's side of that match
(``startup.FirstAnswer``), and the plant ends its run only once each
lockstep peer has handled the last sample (``lockstep.PeerWindow.drain``):
its exit is what makes ``rig`` stop the others.

**The words on /diagnostics.**

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

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.serialization import deserialize_message

from stewart63_ros import topics
from stewart63_ros.runtime.rclpy_internals import take

MATCHED = 'matched_publishers'
CONFIRMS = 'confirms'
FINAL = 'final'
FINAL_PREFIX = 'final/'
#: a recorder's status: ``recorded/<full topic name>`` per topic it records
RECORDED_PREFIX = 'recorded/'
#: a recorder's status: ``matched_publishers/<full topic name>``, the nodes
#: whose publishers on that topic its subscription has matched
MATCHED_ON_PREFIX = MATCHED + '/'
RUN = 'run'
RUN_ENDED = 'ended'
#: What ``record`` prints on its standard output, one line each, for ``rig``
#: (the start-up order above): subscribed to every topic; matched
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
        # than lose samples (runtime/lockstep.py). Composed, one loop serves
        # them all and none can fall behind.
        out['lockstep_peers'] = (['fk'] if 'fk' in nodes else []) + (['record'] if record else [])
    return out


def plant_run(msg, plant_status: str) -> dict[str, str]:
    """What the plant (status name ``plant_status``) says of its run in a
    /diagnostics message: ``{'run': ..., 'run_number': ...}``, the keys it
    holds (the controller and the bridge follow the plant's run by them)."""
    out = {}
    for status in msg.status:
        if status.name == plant_status:
            for kv in status.values:
                if kv.key in (RUN, 'run_number'):
                    out[kv.key] = kv.value
    return out


def recorder_waits_for(nodes) -> list[str]:
    """The topics whose publishers ``rig``'s recorder must match (``MATCHED``)
    before the plant starts: those of the controller and fk run here."""
    return [t for n, t in (('controller', topics.LEG_FORCES), ('fk', topics.PLATFORM_POSE))
            if n in nodes]

class RecorderWord:
    """What the rig's recorders say to this node on /diagnostics.

    ``matched``: recorder's full name -> the nodes it says it has matched;
    ``confirmed``: a recorder said its bag holds all this node published.
    """

    def __init__(self, node):
        self.node = node
        self.matched: dict[str, set] = {}
        #: recorder's full name -> the full names of the topics it records
        #: (its status's ``recorded/<topic>`` keys)
        self.recorded: dict[str, set] = {}
        #: recorder's full name -> {topic: the nodes it has matched there}
        self.matched_on: dict[str, dict] = {}
        self.confirmed = False
        self.sub = node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS,
                                            self.on_status, topics.DIAGNOSTICS_QOS, raw=True)

    def on_status(self, data) -> None:
        """A /diagnostics message, read while the node starts or stops."""
        node = self.node
        if node.started and (not node.closing or self.confirmed):
            return
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
                    self.recorded[recorder] = {
                        v.key[len(RECORDED_PREFIX):] for v in status.values
                        if v.key.startswith(RECORDED_PREFIX)}
                    self.matched_on[recorder] = {
                        v.key[len(MATCHED_ON_PREFIX):]: set(v.value.split(','))
                        for v in status.values if v.key.startswith(MATCHED_ON_PREFIX)}
                elif kv.key == CONFIRMS and node.closing and me in kv.value.split(','):
                    self.confirmed = True

    def take_waiting(self) -> None:
        """Read what has come, without the executor (the node is stopping)."""
        while True:
            data = take(self.sub)
            if data is None:
                return
            self.on_status(data)
