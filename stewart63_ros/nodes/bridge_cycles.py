"""The bridge's cycle, in lockstep and in realtime (mixed into nodes/canopen_bridge.py).

Each cycle: a SYNC on every bus; its window collects each drive's TPDO
(canbus/master.py: a frame belongs to the SYNC whose window it was received
in, so a late one is counted, never another sample's reading); the readings
go out as ``leg_lengths`` stamped with the SYNC's time; the controller's
answer becomes each drive's RPDO.

- lockstep: the next SYNC goes out once the controller has answered (or
  ``force_timeout`` passed). A drive that answered the SYNC before, even
  late, is waited for up to ``bus_timeout`` (a load spike must not decide
  a run); a drive silent since (not even a late answer) only
  ``LOCKSTEP_GRACE`` after the others: a pulled cable costs one
  ``bus_timeout``, not one a sample.
- realtime: SYNC on the wall clock (``canbus.sync.Schedule``); a window
  lasts ``SYNC_WINDOW`` of the period; after a stall the SYNCs whose time
  has passed are skipped and counted (``syncs_skipped``), never sent in a
  burst.
- A controller whose forces stop (after it had answered) is lost after
  ``force_timeout`` s of wall clock, at least ``CONTROLLER_LOST_MIN``
  (lockstep: while a sample waits for it). Then zero torque and the drives
  shut down (READY TO SWITCH ON) until it answers again (docs/bus.md,
  "Stopping").
"""
from __future__ import annotations

import time

from stewart63_ros.canbus.sync import Schedule
from stewart63_ros.canbus.trace import CycleTrace
from stewart63_ros.runtime.launcher import STOP

#: s: the slice of a wait between two turns of housekeeping
SLICE = 0.02
#: the plant's ``run`` values during which its drives hold the SYNCs (no error)
HELD_RUN = ('paused', 'reset')
#: s: lockstep: once the others are in, how long a drive silent since the SYNC
#: before is waited for (the plant answers every drive of a SYNC at once)
LOCKSTEP_GRACE = 0.002
#: s: lockstep: how long a drive's first TPDO after a miss waits for a second
#: (which would make it the late answer to the SYNC before): paid after a miss only
LOCKSTEP_SETTLE = 0.05
#: realtime: the synchronous window, a share of the period: a TPDO received
#: later than this after its SYNC is late (the reading is NaN for that sample)
SYNC_WINDOW = 0.75
#: realtime: a share of the period given beyond the window to a receive side
#: that has frames waiting (they are judged on their reception times)
CATCH_UP = 0.15
#: the columns of the realtime loop's per-cycle trace (canbus/trace.py)
TRACE_FIELDS = ('k', 'slot', 'due', 'woke', 'synced', 'collected', 'published', 'ended',
                'missing', 'answer_missed', 'skipped', 'cpu', 'thread_cpu')
#: s: the controller is lost after no force for ``force_timeout`` s, and at least this
#: long (a short lockstep ``force_timeout`` must not stop the drives at one slow answer)
CONTROLLER_LOST_MIN = 1.0


class BridgeCycles:
    """The loops of the bridge (see the module's doc)."""

    def wait_for_tpdos(self, first: bool) -> bool:
        """Lockstep (and realtime's SYNC 0): wait for this cycle's TPDOs,
        serving the node meanwhile. While the plant holds its run (paused,
        reset) there is no timeout. False if a stop was requested or the
        plant started a new run."""
        timeout = max(self.bus_timeout, self.boot_timeout) if first else self.bus_timeout
        until = time.monotonic() + timeout
        idle = getattr(self.forces_in, 'idle', None)      # composed: the others' side work
        while not self.master.collect(until, LOCKSTEP_GRACE, LOCKSTEP_SETTLE, give_back=SLICE):
            if STOP.requested or self.new_run:
                return False
            self.serve(0.0)
            if idle is not None and self.forces_in.deferred:
                idle()
            if self.plant_run in HELD_RUN:
                until = time.monotonic() + timeout
        return True

    def run_lockstep(self, n_samples):
        master = self.master
        k = 0
        while not STOP.requested:
            if self.new_run or self.plant_run in HELD_RUN:
                renewed = self.hold_for_plant()
                if renewed is None:
                    return
                if renewed:         # a pause goes on at its own sample, a new run at 0
                    k = 0
            if self.peers is not None and not self.peers.hold(k * self.period_ns, self.serve):
                return
            for name in master.bring_up_rebooted():
                self.get_logger().info('%s: back on the bus' % name)
            self.k = k
            started = time.perf_counter()
            master.sync(k)
            if not self.wait_for_tpdos(first=k == 0):
                continue
            self.bus_wait_s += time.perf_counter() - started
            master.missing()
            self.judge()
            ns = k * self.period_ns
            complete = self.publish(ns)
            timeout = self.force_timeout if k else max(self.force_timeout,
                                                       self.discovery_timeout)
            started = time.perf_counter()
            if (complete or self.answer_every_sample) and \
                    not self.wait_for_answer(ns, timeout):
                if STOP.requested:
                    return
                self.timeouts += 1
                self.timeouts_in_a_row += 1
                self.health.warning = 'no force for sample %d within %.3f s' % (k, timeout)
                self.get_logger().warning(self.health.warning)
            else:
                self.timeouts_in_a_row = 0
            self.answer_wait_s += time.perf_counter() - started
            self.write_torques(k, ns)
            if n_samples is not None and k >= n_samples:
                return
            k += 1

    def hold_for_plant(self) -> bool | None:
        """The plant holds its run (paused, reset): wait until it runs again.
        None if a stop was requested meanwhile; True if it runs a new run (its
        SYNCs count from 0 again); False if the same run goes on (a pause, a
        step: the next SYNC is the sample the plant paused before, not 0)."""
        renewed = False
        while self.plant_run in HELD_RUN or self.new_run:
            renewed = renewed or self.new_run or self.plant_run == 'reset'
            self.new_run = False
            if STOP.requested:
                return None
            self.serve(SLICE)
        if renewed:
            self.force = None
            self.force_ns = None
            self.force_gate.last_ns = None
            self.master.new_run()       # the new run's SYNCs count from 0 again
        return renewed

    def wait_for_answer(self, ns, timeout) -> bool:
        deadline = time.monotonic() + timeout
        while self.force_ns != ns:
            now = time.monotonic()
            if now >= deadline or STOP.requested:
                return False
            wake = min(deadline, self.housekeeping(now))
            if self.force_ns == ns:
                break
            self.forces_in.poll(max(0.0, wake - time.monotonic()))
        return True

    def run_realtime(self, n_samples):
        master = self.master
        # SYNC 0 waits for the drives' first answer (the plant may still be
        # starting); the wall-clock schedule starts once sample 0 is answered
        # and the nodes are warm (warm_up). A drive that
        # booted again is brought up first: after SYNC 0 its bring-up would
        # drop the TPDO it answered with.
        for name in master.bring_up_rebooted():
            self.get_logger().info('%s: back on the bus' % name)
        # this thread reads the buses from here on: a cycle wakes it alone,
        # not the notifier threads too (canbus/cycle.py)
        if not master.receive_in_loop():
            self.get_logger().info('a bus has no file descriptor: its frames are read by '
                                   'notifier threads')
        idle = getattr(self.forces_in, 'idle', None)
        self.warm_up(idle)
        master.sync(0)
        if not self.wait_for_tpdos(first=True):
            return
        schedule = self.schedule = Schedule(time.monotonic(), self.period)
        t0_wall = time.time()
        trace = CycleTrace.from_env('canopen_bridge', TRACE_FIELDS,
                                    (n_samples or 600_000) + 1)
        try:
            self._realtime_cycles(n_samples, schedule, t0_wall, trace)
        finally:
            if trace is not None:
                trace.write()

    def _realtime_cycles(self, n_samples, schedule, t0_wall, trace):
        master = self.master
        clock, cpu, thread_cpu = time.monotonic, time.process_time, time.thread_time
        k = 0
        answered_ns = None
        # composed: the other nodes' side work (fk, housekeeping) is done while
        # the drives answer a SYNC, not between the answer and the next SYNC;
        # when their answers came with the SYNC (armed: canbus/hub.py), once
        # the sample is answered
        idle = getattr(self.forces_in, 'idle', None)
        side_work_due = False
        while not STOP.requested:
            due = schedule.due()
            while True:     # at least once: composed, this serves the controller too
                wake = due if idle else min(due, self.housekeeping(time.monotonic()))
                answered = self.forces_in.poll(max(0.0, wake - time.monotonic()))
                if side_work_due and (answered or time.monotonic() >= due):
                    side_work_due = False
                    self.housekeeping(time.monotonic())
                    idle()
                if time.monotonic() >= due:
                    break
            woke = clock()
            answer_missed = bool(k and self.force_ns != answered_ns)
            if answer_missed:
                self.missed += 1
            for name in master.bring_up_rebooted():
                self.get_logger().info('%s: back on the bus' % name)
            self.k = k
            synced = clock()
            if k:
                master.sync(k)
                if idle is not None:
                    side_work_due = master.all_in()
                    if not side_work_due:
                        self.housekeeping(time.monotonic())
                        idle()
                window = SYNC_WINDOW * self.period
                master.collect(master.opened_at + window, window, window,
                               catch_up=CATCH_UP * self.period)
            collected = clock()
            missing = master.missing()
            self.judge()
            # the SYNC's time: its slot, never later than it went out; sample 0
            # is stamped once SYNC 0 is answered (a plant standing in for the
            # drives may take seconds to start), the slots once it is answered
            ns = int(round((min(t0_wall + schedule.slot * self.period,
                                master.windows.last[1]) if k else t0_wall) * 1e9))
            # an answer is awaited for a complete sample, or for every sample
            # when the supervisor answers them all (a NaN sample it answers in
            # time is not a missed cycle: its TPDO is counted missing)
            complete = self.publish(ns)
            answered_ns = ns if complete or self.answer_every_sample else self.force_ns
            published = clock()
            if self.errors or self.controller_lost() or self.force_is_stale(k, ns,
                                                                              self.force_ns):
                self.write_torques(k, ns)
            if not k:           # the clock starts once sample 0 is answered: SYNC 1 now
                self.answer_sample_0(ns, complete)
                schedule.restart(time.monotonic() - self.period)
                t0_wall = time.time() - self.period
            ended = clock()
            slot = schedule.slot
            skipped = schedule.advance(ended) if n_samples is None or k < n_samples else 0
            if trace is not None:
                trace.add(k, slot, due, woke, synced, collected, published, ended,
                          len(missing), answer_missed, skipped, cpu(), thread_cpu())
            if n_samples is not None and k >= n_samples:
                return
            k += 1
            if skipped:         # a stall: those SYNCs' time is gone, none is sent late
                self.health.values['syncs_skipped'] = schedule.skipped
                if self.health.log_due('stalled'):  # (rclpy's throttle costs ~1 ms a call)
                    self.get_logger().warning('stalled: %d SYNCs skipped (%d in all)'
                                              % (skipped, schedule.skipped))

    def warm_up(self, idle) -> None:
        """Realtime, before SYNC 0: the side work of this node and of the
        nodes composed with it done once (first executor turns and reports
        cost milliseconds), so that it does not fall in the first cycles."""
        for _ in range(len(getattr(self.forces_in, 'nodes', ())) + 1):
            self.housekeeping(time.monotonic())
            if idle is not None:
                idle()

    def answer_sample_0(self, ns: int, complete: bool) -> None:
        """Realtime: the SYNC clock starts once sample 0 is answered (when an
        answer is awaited): the answering nodes' first pass costs 5-15 ms
        here, which on the clock would be SYNCs skipped."""
        if (complete or self.answer_every_sample) and not self.wait_for_answer(
                ns, max(self.force_timeout, self.discovery_timeout)):
            self.get_logger().warning('no answer to sample 0: the SYNC clock starts anyway')

    def controller_lost(self) -> bool:
        """Whether the controller, having answered, is lost: no force for
        ``lost_after`` s of wall clock (in lockstep, while a sample waits for
        its answer: a bridge waiting for a silent drive has not asked).
        Said once each time it happens."""
        lost = self.force is not None and time.monotonic() - self.force_at > self.lost_after \
            and (self.mode != 'lockstep' or self.timeouts_in_a_row > 0)
        if lost != self.lost_controller:
            self.lost_controller = lost
            if lost:
                self.get_logger().error('controller lost: no leg_forces for %g s: zero '
                                        'torque, drives shut down' % self.lost_after)
            self.judge(force=True)
        return lost

    def write_torques(self, k: int, ns: int) -> None:
        """The cycle's RPDOs: the held force, or zero torque when a drive is
        at fault, the force is stale, or the controller is lost (then the
        drives are shut down too)."""
        lost = self.controller_lost()
        stale = self.force_is_stale(k, ns, self.force_ns)
        self.master.command(None if stale or lost else self.force,
                            withhold=bool(self.errors) or lost, shut_down=lost)
