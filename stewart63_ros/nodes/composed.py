"""composed: the rig's nodes (and the recorder) as nodes of one process.

As a ROS 2 component container does: each is its own node, with its own
name, parameters (the same ``--params-file`` sections as when run alone) and
/diagnostics, and every message between them still goes over the DDS topics,
so a recorder, viewer or ``ros2 topic`` outside the process sees the same
graph. What changes is who waits: one thread serves all the nodes. After the
plant (or the bridge) publishes a sample, the loop takes it on the
supervisor's and the controller's subscriptions at once and runs their
callbacks, then takes the answering force on the plant's (the bridge's) side
(the middleware hands a message to a reader in the same process before
``publish`` returns), then fk's sample and the recorder's share. No process
switch and no wake-up between sample and answer.

    composed [--nodes plant,controller,fk] [--record DIR] --ros-args --params-file F ...

``--nodes`` takes any of plant, controller, fk, supervisor and
canopen_bridge; the nodes not hosted run elsewhere (another process or host)
and reach these over DDS as usual. The loop is driven by the plant, or by the
bridge (``canopen_bridge``: the machine's side of a rig on the field bus,
``--nodes controller,supervisor,fk,canopen_bridge``, docs/bus.md), never by
both: the plant standing in for the drives is the machine, its own process.
With the supervisor, the controller's ``leg_forces`` must be remapped for the
controller alone: ``-r controller:leg_forces:=leg_forces_request``.
``--record DIR`` adds the recorder (``record``), which writes what it takes
in the same loop.
"""
from __future__ import annotations

import sys
import time

from stewart63_ros.core.plumbing.node_names import ALL_NODES
from stewart63_ros.core.plumbing.node_names import NODES as NODE_NAMES
from stewart63_ros.exits import quiet_on_closed_pipe
from stewart63_ros.runtime.launcher import STOP, run


class Peers:
    """The subscriptions the composed loop serves, taken in the order a sample travels.

    The loop the plant is driven by (``HotLoop.drive_by``): ``start`` is given
    the plant's ``DirectTake`` on ``leg_forces`` and the plant's loop polls
    this instead (same ``poll``): before looking for a force it serves the
    nodes that answer the sample, and it waits on all of their subscriptions
    at once.
    """

    def __init__(self, context, answer_first=(), then=(), recorder=None, period=1e-3,
                 side_period=None, batch_then=False, tickers=()):
        self.context = context
        self.own = None                         # DirectTake of the plant's leg_forces, or None
        # (node, DirectTake): the supervisor's samples, the controller's, the
        # supervisor's requests (the controller's answers), in that order
        self.answer_first = list(answer_first)
        self.then = list(then)                  # (node, DirectTake): fk
        self.recorder = recorder
        self.period = period
        self.waiter = None                      # made by start
        self.nodes = list(dict.fromkeys(n for n, _ in self.answer_first + self.then))
        #: ``tick(now)`` after every pass over answer_first: the supervisor's
        #: ``attend`` (a request timeout, a trip that answers at once)
        self.tickers = list(tickers)
        self.next_side = 0.0
        if side_period is not None:
            self.side_period = side_period
        # Lockstep: fk's samples in batches, with the other side work (see serve).
        self.batch_then = batch_then
        #: the runner does the side work in its own waits (``idle``), serve leaves it
        self.deferred = False
        self._turn = 0                          # idle's node, in turn

    def start(self, own=None) -> Peers:
        """The loop begins; ``own``: the plant's DirectTake on ``leg_forces``
        (None: no plant in this process). Returns the loop, for the plant to
        poll (see ``HotLoop.start_hot_loop``)."""
        # lazy: rclpy costs 302 ms: --help answers without it
        from stewart63_ros.runtime.rclpy_internals import WaitAny
        self.own = own
        subs = [d.sub for _, d in self.answer_first + self.then] + ([own.sub] if own else [])
        self.waiter = WaitAny(self.context, subs)
        return self

    #: s: how often the loop looks at the peers' other subscriptions
    #: (setpoints), timers and parameter services when they are not due
    #: earlier: as often as a node running alone does at 1 kHz.
    #: The recorder's share is taken then too: its subscriptions queue up to
    #: ten thousand messages each, a few milliseconds' worth.
    SIDE_PERIOD = 1e-3
    #: s: the same in lockstep, where nothing waits on the wall clock: the
    #: timers (diagnostics at 1 Hz, the watchdog at 20 Hz, markers at 30 Hz)
    #: and the commands are served as often as they need, and the recorder's
    #: queues hold far more than this many milliseconds' worth.
    LOCKSTEP_SIDE_PERIOD = 10e-3
    #: s: in lockstep, each node's executor turn (parameter services, QoS
    #: events; a turn costs a few hundred microseconds) at most this often.
    LOCKSTEP_EXECUTOR_PERIOD = 0.25
    side_period = SIDE_PERIOD

    def serve(self, turn_ok: bool = True) -> bool:
        """One pass without waiting; True if a force was taken for the plant.

        One take per subscription: the middleware has delivered a sample to
        every reader in this process by the time ``publish`` returned, so a
        second take would find nothing (what is left is taken on the next
        pass or by ``drain``).
        """
        for _, direct in self.answer_first:
            direct.poll(0.0)
        if self.tickers:
            now = time.monotonic()
            for tick in self.tickers:
                tick(now)
        got = self.own.poll(0.0) if self.own is not None else False
        if self.deferred:       # the runner's idle() does the rest, while it waits
            return got
        if not self.batch_then:
            for _, direct in self.then:
                direct.poll(0.0)
        self._side(turn_ok)
        return got

    def idle(self) -> None:
        """The runner is waiting on something else (the bridge, for its
        drives' answers to a SYNC: a third of the period): do the work no
        answer waits for now, fk's samples, the nodes' housekeeping and the
        recorder's share, instead of between the answer and the next SYNC.
        From its first call on, ``serve`` leaves that work to it."""
        if not self.deferred:   # fk's samples no longer wake the loop's wait
            # lazy: rclpy costs 302 ms: --help answers without it
            from stewart63_ros.runtime.rclpy_internals import WaitAny
            self.deferred = True
            self.waiter = WaitAny(self.context, [d.sub for _, d in self.answer_first]
                                  + ([self.own.sub] if self.own else []))
        for node, direct in self.then:
            n = 0
            while n < node.BATCH_MAX and direct.poll(0.0):
                n += 1
        # one node's housekeeping a call, in turn (a turn of the executor or
        # a report costs up to half a millisecond: one per wait, not three)
        if self.nodes:
            self._turn = (self._turn + 1) % len(self.nodes)
            self.nodes[self._turn].housekeeping(time.monotonic(), True)
        if self.recorder is not None and time.monotonic() >= self.next_side:
            self.recorder.take_available()
            self.next_side = time.monotonic() + self.side_period

    def _side(self, turn_ok: bool) -> None:
        """The side work when due: fk in lockstep's batches, the nodes'
        housekeeping, the recorder's share."""
        now = time.monotonic()
        if now >= self.next_side:
            if self.batch_then:
                # Nothing waits for fk's poses in lockstep: its samples queue
                # (up to a thousand) and are served in a row, every side
                # period, each in order, where its code and data stay in the
                # processor's caches, instead of interleaved with the loop's.
                for node, direct in self.then:
                    n = 0
                    while n < node.BATCH_MAX and direct.poll(0.0):
                        n += 1
                now = time.monotonic()
            wake = now + self.side_period
            for node in self.nodes:
                wake = min(wake, node.housekeeping(now, turn_ok))
            self.next_side = wake
            if self.recorder is not None:
                self.recorder.take_available()

    def drain(self) -> None:
        """Serve what is still queued on the peers' subscriptions (at the end)."""
        for _, direct in self.answer_first + self.then:
            while direct.poll(0.0):
                pass
        if self.recorder is not None:
            self.recorder.take_available()

    def poll(self, timeout_sec: float) -> bool:
        """Serve everything; take a force, waiting up to ``timeout_sec`` for
        one (the plant's DirectTake.poll); False if none came."""
        deadline = time.monotonic() + timeout_sec
        turn_ok = timeout_sec > 0.6 * self.period
        while True:
            if self.serve(turn_ok):
                return True
            now = time.monotonic()
            if now >= deadline:
                return False
            self.waiter.wait((deadline if self.deferred else min(deadline, self.next_side))
                             - now)


class Composed:
    """The nodes of one process and the loop that drives them.

    Has the interface ``launcher.run`` drives (``run``, ``close``,
    ``destroy_node``): a parameter error in any node exits 2, Ctrl-C and
    SIGTERM stop every node cleanly, an exception in any node's callback
    ends the process with its traceback and a non-zero exit.
    """

    def __init__(self, options):
        import rclpy  # lazy: rclpy costs 302 ms: --help answers without it

        names = [n.strip() for n in options.nodes.split(',') if n.strip()]
        problem = hosting_problem(names)
        if problem:
            raise SystemExit('composed: --nodes %s: %s' % (options.nodes, problem))
        self.nodes = {}
        self.recorder = None
        self.loop = None
        self.closed = False
        if options.record:
            # First, so that its subscriptions exist before any node publishes.
            # lazy: the recorder costs 973 ms; only --record needs it
            from stewart63_ros.bagio import BagError
            from stewart63_ros.recording.recorder import Recorder
            self.recorder = Recorder(options.record, context=rclpy.get_default_context())
            try:
                self.recorder.open()
            except BagError as exc:
                print('composed: error: %s' % exc, file=sys.stderr)
                raise SystemExit(2) from None
        for name in HOST_ORDER:
            if name in names:
                self.nodes[name] = node_class(name)(options)
        supervisor = self.nodes.get('supervisor')
        if supervisor is not None and supervisor.core.homing is not None:
            # its homing sets the zero of a node of this process directly
            supervisor.zero_peer = self.nodes.get(supervisor.zero_node)

    def runner(self):
        """The node whose loop drives the others (the plant's or the
        bridge's), or None: the loop of this process runs until a stop."""
        return self.nodes.get('plant') or self.nodes.get('canopen_bridge')

    def run(self):
        nodes = self.nodes
        # Each node waits for its own subscribers (the recorder, with
        # wait_for_subscribers), as when it runs alone; the plant or the
        # bridge last (the start-up order: runtime/handshake.py).
        for name in ANSWERING + ('fk',):
            if name in nodes:
                nodes[name].wait_for_matches()
        directs = {n: nodes[n].start_hot_loop(nodes[n].sub_samples)
                   for n in ANSWERING + ('fk',) if n in nodes}
        runner = self.runner()
        context = next(iter(nodes.values())).context

        lockstep = runner is not None and runner.mode == 'lockstep'
        side_period = Peers.LOCKSTEP_SIDE_PERIOD if lockstep else Peers.SIDE_PERIOD
        if lockstep:
            for node in nodes.values():
                node.EXECUTOR_PERIOD = Peers.LOCKSTEP_EXECUTOR_PERIOD
        answer_first = [(nodes[n], directs[n]) for n in ANSWERING if n in directs]
        tickers = []
        supervisor = nodes.get('supervisor')
        if supervisor is not None:
            # lazy: rclpy costs 302 ms: --help answers without it
            from stewart63_ros.runtime.rclpy_internals import DirectTake
            # its requests: the controller's answers, taken in the same pass
            answer_first.append((supervisor, DirectTake(supervisor, supervisor.sub_requests)))
            tickers.append(supervisor.attend)
        loop = Peers(context, answer_first,
                     [(nodes[n], directs[n]) for n in ('fk',) if n in directs],
                     self.recorder, runner.period if runner is not None else 1e-3,
                     side_period, batch_then=lockstep, tickers=tickers)
        if runner is None:
            import rclpy  # lazy: rclpy costs 302 ms: --help answers without it

            self.loop = loop.start()
            while rclpy.ok() and not STOP.requested:
                loop.poll(0.1)
            return 0
        # The plant's (the bridge's) own loops, unchanged, driven by this one:
        # every take of a force goes through it (see Peers), and its
        # housekeeping (its other subscriptions, timers, executor) keeps the
        # pace of the others', not after every sample.
        self.loop = loop
        runner.drive_by(loop)
        return runner.run()

    def close(self):
        if self.closed:
            return
        self.closed = True
        errors = []
        if self.loop is not None and self.loop.waiter is not None:     # it has started
            self.loop.drain()
        # lazy: runtime.base costs 824 ms: --help answers without it
        from stewart63_ros.runtime.base import RigNode
        # One flush bound for all the nodes, not one each: three nodes waiting
        # in turn for a subscriber that never acknowledges would outlast the
        # stop deadline (launcher.STOP_DEADLINE).
        deadline = time.monotonic() + (RigNode.FLUSH_ON_SIGNAL if STOP.requested
                                       else RigNode.FLUSH_AT_END)
        for node in self.nodes.values():      # final diagnostics, flushed
            node.flush_deadline = deadline
            if self.recorder is not None:     # it confirms what it holds meanwhile
                node.stop_flush.while_flushing = self.recorder.take_available
            try:
                node.close()
            except Exception as exc:  # noqa: BLE001 - close the others all the same
                errors.append('%s: %s' % (node.get_name(), exc))
        if self.recorder is not None:
            self.recorder.close()             # takes what is still queued, then writes the index
            print(self.recorder.summary(), flush=True)
        if errors:
            raise RuntimeError('; '.join(errors))

    def destroy_node(self):
        for node in self.nodes.values():
            node.destroy_node()


#: The nodes that answer a sample, in the order the loop serves them.
ANSWERING = ('supervisor', 'controller')
#: The order the nodes are made in: the runner (plant or bridge) last, so
#: that its readers exist when it starts.
HOST_ORDER = ('supervisor', 'controller', 'fk', 'canopen_bridge', 'plant')


def hosting_problem(names) -> str:
    """Why one process cannot host the nodes ``names`` ('' if it can)."""
    unknown = sorted(set(names) - set(ALL_NODES))
    if unknown or not names or len(set(names)) != len(names):
        return 'a comma-separated subset of %s, each once' % ','.join(ALL_NODES)
    if 'plant' in names and 'canopen_bridge' in names:
        # Both drive the loop, and the bridge waits on the bus for the TPDOs
        # that only the plant's loop sends: in one thread, neither would go on.
        return ('the plant standing in for the drives and canopen_bridge each drive their '
                'own loop: the plant runs in a process of its own (it is the machine)')
    return ''


def node_class(name):
    """The node class of ``name``, imported on demand: a process imports only
    the nodes it hosts, and --help none."""
    if name == 'controller':
        from stewart63_ros.nodes.controller import ControllerNode  # lazy: costs 300 ms
        return ControllerNode
    if name == 'fk':
        from stewart63_ros.nodes.fk_node import FKNode  # lazy: costs 300 ms (the kernels)
        return FKNode
    if name == 'plant':
        from stewart63_ros.nodes.plant import PlantNode  # lazy: costs 400 ms (the kernels)
        return PlantNode
    if name == 'supervisor':
        from stewart63_ros.nodes.supervisor import SupervisorNode  # lazy: costs 1050 ms
        return SupervisorNode
    # lazy: python-can and canopen cost 565 ms; only a process that hosts the bridge
    from stewart63_ros.nodes.canopen_bridge import BridgeNode
    return BridgeNode


def _options(parser):
    parser.add_argument('--nodes', default=','.join(NODE_NAMES),
                        help='the nodes this process hosts, comma-separated, of %s '
                        '(default: %%(default)s)' % ','.join(ALL_NODES))
    parser.add_argument('--record', metavar='DIR',
                        help='also record every topic into a new bag DIR, in this process')


@quiet_on_closed_pipe
def main(argv=None):
    sys.exit(run('composed', __doc__.split('\n\n')[0], Composed, argv, extra_args=_options))


if __name__ == '__main__':
    main()
