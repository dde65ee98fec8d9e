"""A sample belongs to its SYNC; time, not cycles; the safe stop (docs/bus.md).

The master against a small test double on the local bus (``s63hub``) that
answers each SYNC k with counts that name k (position 1000 k + node id), on
a plan: at once, late within the window, after the next SYNC, or not at
all; and that beats its heartbeats on the wall clock. Each published sample
must hold its own SYNC's counts; a late TPDO is counted and never used.
Then the CiA 402 side: no fault reset in FAULT REACTION ACTIVE, and the
safe stop against the plant standing in for the drives.
"""
from __future__ import annotations

import dataclasses
import math
import struct
import threading
import time

import can
import numpy as np
import pytest
from test_bus import CONFIG, Bench, bench, channels  # noqa: F401 - the fixture

from stewart63_ros.canbus.sync import Schedule, SyncWindows
from stewart63_ros.core.machine.bus import (
    FAULT,
    FAULT_REACTION_ACTIVE,
    OPERATION_ENABLED,
    READY_TO_SWITCH_ON,
    STATUSWORDS,
    load_bus_config,
)

#: s: the double's cycle: long, so that a loaded machine keeps the plan's order
PERIOD = 0.1
WINDOW = 0.75 * PERIOD
#: the cob id that makes the master's receive thread sleep (a lagging receive side)
STALL_COB = 0x7F0


def counts(k: int, node: int) -> int:
    return 1000 * k + node


class SyncDouble:
    """Six drives on two buses that answer SYNCs by plan (see the module's doc).

    ``plan(node, k)``: seconds after SYNC k to answer, None for no answer,
    or 'next' to answer only once SYNC k + 1 has come (then k's TPDO goes
    out first, k + 1's 5 ms later).
    """

    def __init__(self, config, plan, heartbeat_s=None):
        self.config = config
        self.plan = plan
        self.heartbeat_s = heartbeat_s
        self.beating = {leg.node_id for leg in config.legs}
        self.stop = False
        self.buses = {b.name: can.Bus(interface='s63hub', channel=b.channel)
                      for b in config.buses}
        self.threads = [threading.Thread(target=self._serve, args=(name,), daemon=True)
                        for name in self.buses]
        for t in self.threads:
            t.start()

    def send(self, bus, cob, data):
        self.buses[bus].send(can.Message(arbitration_id=cob, data=data, is_extended_id=False))

    def tpdo(self, bus, node, k):
        self.send(bus, 0x180 + node, struct.pack('<ii', counts(k, node), 0))

    def _serve(self, name):
        nodes = [leg.node_id for leg in self.config.legs if leg.bus == name]
        timers = []
        k = -1
        held = {}               # node: the SYNC it owes once the next one comes
        next_beat = time.monotonic()
        while not self.stop:
            if self.heartbeat_s and time.monotonic() >= next_beat:
                for node in nodes:
                    if node in self.beating:
                        self.send(name, 0x700 + node, b'\x05')
                next_beat += self.heartbeat_s
            msg = self.buses[name].recv(0.002)
            if msg is None or msg.arbitration_id != 0x80:
                continue
            k += 1
            for node in nodes:
                if node in held:
                    self.tpdo(name, node, held.pop(node))
                    timers.append(threading.Timer(0.005, self.tpdo, (name, node, k)))
                    timers[-1].start()
                    continue
                when = self.plan(node, k)
                if when == 'next':
                    held[node] = k
                elif when is not None:
                    timers.append(threading.Timer(when, self.tpdo, (name, node, k)))
                    timers[-1].start()
        for t in timers:
            t.cancel()

    def close(self):
        self.stop = True
        for t in self.threads:
            t.join(2)
        for bus in self.buses.values():
            bus.shutdown()


@pytest.fixture
def double():
    made = []

    def make(plan, heartbeat_ms=None):
        from stewart63_ros.canbus.master import Master
        config = load_bus_config(CONFIG, channels=channels())
        if heartbeat_ms:
            config = dataclasses.replace(config, heartbeat_ms=heartbeat_ms)
        d = SyncDouble(config, plan, heartbeat_ms / 1000.0 if heartbeat_ms else None)
        master = Master(config, 1.0 / PERIOD, log=lambda text: None)
        for link in master.links:          # taken as brought up (the double has no SDO)
            link.up = True
            link.statusword = STATUSWORDS[OPERATION_ENABLED]
        d.master = master
        made.append(d)
        return d
    yield make
    for d in made:
        d.close()
        d.master.close()


def realtime_cycle(master, k):
    """One realtime cycle of the bridge's (nodes/bridge_cycles.py): SYNC, window, readings."""
    started = time.monotonic()
    master.sync(k)
    master.collect(started + WINDOW, WINDOW, WINDOW, catch_up=0.15 * PERIOD)
    master.missing()
    lengths, _ = master.readings()
    time.sleep(max(0.0, started + PERIOD - time.monotonic()))
    return lengths


def read_counts(master, lengths):
    """The counts each leg's reading came from (None for NaN)."""
    return [None if math.isnan(v) else leg.counts(v) for leg, v in zip(master.config.legs,
                                                                          lengths)]


def test_windows_file_a_time_under_the_last_sync_sent_before_it():
    w = SyncWindows()
    assert w.window_of(5.0) is None
    for k, at in enumerate((10.0, 10.1, 10.2)):
        w.sent(k, at)
    assert [w.window_of(t) for t in (9.9, 10.0, 10.05, 10.1, 10.25)] == [None, 0, 0, 1, 2]
    w.sent(0, 20.0)             # a new run: indices from 0 again
    assert w.window_of(20.5) == 0 and w.last == (0, 20.0)


def test_schedule_skips_the_syncs_a_stall_missed_and_never_bursts():
    s = Schedule(t0=100.0, period=0.001)
    assert s.advance(100.0005) == 0 and s.slot == 1          # on time
    assert s.advance(100.0016) == 0 and s.slot == 2          # late within its slot: sent
    # a 90 ms stall: the slots whose time is over are skipped; the one running
    # now is sent at once, the next one a period after it
    skipped = s.advance(100.0925)
    assert skipped == 89 and s.skipped == 89 and s.slot == 92
    assert s.due() <= 100.0925 < s.due() + 0.001
    assert s.advance(100.0926) == 0 and s.due() > 100.0926    # and on, one a period


def test_each_sample_holds_its_own_syncs_counts_late_ones_are_counted_not_used(double):
    # node 1: every answer late within the window (0.55 of the period: past
    # the old cut at 0.5, as a drive answering 3 ms into 5 ms is); node 2:
    # SYNC 3's answer only after SYNC 4 (then SYNC 4's own); node 4: none at 5.
    def plan(node, k):
        if node == 1:
            return 0.55 * PERIOD
        if node == 2 and k == 3:
            return 'next'
        if node == 4 and k == 5:
            return None
        return 0.002
    d = double(plan)
    master = d.master
    got = [read_counts(master, realtime_cycle(master, k)) for k in range(8)]
    for k, row in enumerate(got):
        expected = [counts(k, node) for node in range(1, 7)]
        if k == 3:
            expected[1] = None          # node 2 did not answer within SYNC 3's window
        if k == 5:
            expected[3] = None
        assert row == expected, (k, row)
    late = {link.leg.node_id: link.late_tpdo for link in master.links}
    missed = {link.leg.node_id: link.missed_tpdo for link in master.links}
    assert late == {1: 0, 2: 1, 3: 0, 4: 0, 5: 0, 6: 0}, late
    assert missed == {1: 0, 2: 1, 3: 0, 4: 1, 5: 0, 6: 0}, missed


def test_a_receive_side_that_lags_files_frames_under_their_own_sync(double):
    # The master's receive thread is held up past SYNC 3's window (as a
    # loaded machine does): the TPDOs of SYNC 3 it then gets to are late,
    # never SYNC 4's readings.
    d = double(lambda node, k: 0.003)
    master = d.master
    network = master.networks['a']
    network.subscribe(STALL_COB, lambda cob, data, stamp: time.sleep(1.5 * PERIOD))
    for k in range(3):
        assert None not in read_counts(master, realtime_cycle(master, k))
    started = time.monotonic()
    master.sync(3)
    d.send('a', STALL_COB, b'')             # before SYNC 3's answers on bus a
    master.collect(started + WINDOW, WINDOW, WINDOW, catch_up=0.15 * PERIOD)
    master.missing()
    row3 = read_counts(master, master.readings()[0])
    time.sleep(max(0.0, started + PERIOD - time.monotonic()))
    row4 = read_counts(master, realtime_cycle(master, 4))
    assert row3[:3] == [None] * 3 and row3[3:] == [counts(3, n) for n in (4, 5, 6)], row3
    assert row4 == [counts(4, n) for n in range(1, 7)], row4
    assert [link.late_tpdo for link in master.links] == [1, 1, 1, 0, 0, 0]


def test_heartbeats_are_judged_on_reception_time_a_stall_is_no_loss(double):
    d = double(lambda node, k: 0.002, heartbeat_ms=50)    # lost after 150 ms
    master = d.master
    master.clock = 'wall'
    time.sleep(0.1)
    for k in range(3):
        realtime_cycle(master, k)
    assert master.errors() == []
    # A stall of the whole bridge (its receive thread too) for 0.4 s: no SYNC;
    # the heartbeats that came meanwhile are judged on their reception times.
    stalled = threading.Event()

    def stall(cob, data, stamp):
        time.sleep(0.4)
        stalled.set()
    master.networks['a'].subscribe(STALL_COB, stall)
    d.send('a', STALL_COB, b'')
    assert stalled.wait(5.0)
    realtime_cycle(master, 3)           # one SYNC after the stall
    assert not [e for e in master.errors() if 'heartbeat' in e], master.errors()
    d.beating.discard(2)                # node 2 stops beating: lost after 150 ms
    time.sleep(0.25)
    realtime_cycle(master, 4)
    lost = [e for e in master.errors() if 'heartbeat lost' in e]
    assert len(lost) == 1 and lost[0].startswith('leg_2 (node 2, bus a)'), master.errors()


def test_fault_reset_only_from_fault_never_in_fault_reaction_active(bench):  # noqa: F811
    b = bench()
    master = b.master
    master.reset_all()
    assert master.wait_for_boot(5.0) == []
    assert all(master.bring_up(link) for link in master.links)
    drive = b.devices.drives[1]
    heard = []
    write = drive.write

    def recording(index, sub, value):
        if index == 0x6040:
            heard.append((drive.drive.state, value))
        write(index, sub, value)
    drive.write = recording
    for k in range(3):
        assert b.cycle(k) == []
    with b._lock:
        drive.drive.state = FAULT_REACTION_ACTIVE       # braking before FAULT
        drive._sync_state()
    k = 3
    for _ in range(10):
        b.cycle(k)
        k += 1
    assert master.links[1].state == FAULT_REACTION_ACTIVE
    in_reaction = [cw for state, cw in heard if state == FAULT_REACTION_ACTIVE]
    assert in_reaction and not any(cw & 0x80 for cw in in_reaction), in_reaction
    with b._lock:
        drive.drive.state = FAULT                       # the reaction is over
        drive._sync_state()
    for _ in range(20):
        errors = b.cycle(k)
        k += 1
        if not errors:
            break
    assert errors == [] and drive.drive.state == OPERATION_ENABLED
    assert any(state == FAULT and cw & 0x80 for state, cw in heard), heard


def test_safe_stop_leaves_every_drive_disabled_with_zero_torque(bench):  # noqa: F811
    b = bench()
    master = b.master
    master.reset_all()
    assert master.wait_for_boot(5.0) == []
    assert all(master.bring_up(link) for link in master.links)
    for k in range(3):
        assert b.cycle(k, np.full(6, 300.0)) == []
    assert all(f > 250 for f in b.devices.forces())
    states = master.safe_stop()
    assert states == {leg.name: READY_TO_SWITCH_ON for leg in master.config.legs}, states
    time.sleep(0.1)
    for drive in b.devices.drives:
        assert drive.drive.state == READY_TO_SWITCH_ON, drive.leg.name
        assert drive.torque_permille == 0 and drive.force == 0.0
        assert drive.nmt == 'PRE-OPERATIONAL'
    master.command(np.full(6, 300.0), withhold=False)        # nothing enables them again
    time.sleep(0.1)
    assert all(d.drive.state == READY_TO_SWITCH_ON for d in b.devices.drives)


def test_a_silent_drive_in_lockstep_costs_one_wait_not_one_a_sample(bench):  # noqa: F811
    # lockstep: a drive that answered the SYNC before is waited for up to
    # bus_timeout; one already silent only a grace after the others. A
    # pulled cable (300 samples) costs one bus_timeout, not 300.
    b = bench()
    master = b.master
    master.reset_all()
    assert master.wait_for_boot(5.0) == []
    assert all(master.bring_up(link) for link in master.links)
    bus_timeout = 0.5

    def lockstep_cycle(k):
        master.sync(k)
        master.collect(time.monotonic() + bus_timeout, 0.002, 0.002)
        missing = master.missing()
        master.command(np.full(6, 100.0), withhold=bool(master.errors()))
        return missing
    for k in range(3):
        assert lockstep_cycle(k) == []
    with b._lock:
        b.faults = {3: {'bus_tpdo_missing': None}}
    started = time.monotonic()
    for k in range(3, 103):
        assert [link.leg.name for link in lockstep_cycle(k)] == ['leg_4'], k
    took = time.monotonic() - started
    with b._lock:
        b.faults = {}
    assert lockstep_cycle(103) == []
    print('\n100 lockstep samples with a silent drive: %.2f s (bus_timeout %.1f s)'
          % (took, bus_timeout))
    assert took < bus_timeout + 100 * 0.1, took     # one wait, then a grace a sample


def lockstep_cycle(master, k, bus_timeout=0.1, pause=0.0):
    """One lockstep cycle of the bridge's rules (nodes/bridge_cycles.py)."""
    from stewart63_ros.nodes.bridge_cycles import LOCKSTEP_GRACE, LOCKSTEP_SETTLE
    master.sync(k)
    master.collect(time.monotonic() + bus_timeout, LOCKSTEP_GRACE, LOCKSTEP_SETTLE)
    master.missing()
    row = read_counts(master, master.readings()[0])
    time.sleep(pause)
    return row


def test_lockstep_a_late_answer_after_the_next_sync_is_not_that_syncs_reading(double):
    # node 2 answers SYNC 2 only once SYNC 3 has come, then SYNC 3's own 5 ms
    # later: sample 3 holds SYNC 3's counts, SYNC 2's frame is counted late
    d = double(lambda node, k: 'next' if node == 2 and k == 2 else 0.001)
    master = d.master
    rows = [lockstep_cycle(master, k) for k in range(5)]
    assert rows[2][1] is None and rows[3][1] == counts(3, 2), rows
    assert all(row == [counts(k, n) for n in range(1, 7)] for k, row in enumerate(rows)
               if k != 2), rows
    assert master.links[1].late_tpdo == 1 and master.links[1].missed_tpdo == 1


def test_lockstep_a_drive_whose_answer_came_late_is_waited_for_not_taken_as_silent(double):
    # node 4 misses SYNC 1's window (its answer comes after bus_timeout, before
    # SYNC 2), then answers every SYNC 30 ms after the others: it is alive,
    # waited for (bus_timeout), not given the 2 ms of a silent drive
    def plan(node, k):
        if node == 4:
            return 0.15 if k == 1 else 0.03
        return 0.001
    d = double(plan)
    master = d.master
    rows = [lockstep_cycle(master, k, pause=0.1 if k == 1 else 0.0) for k in range(6)]
    assert rows[1][3] is None, rows
    assert all(row == [counts(k, n) for n in range(1, 7)] for k, row in enumerate(rows)
               if k != 1), rows
    assert master.links[3].late_tpdo == 1 and master.links[3].missed_tpdo == 1


def test_a_repeated_warning_of_the_cycle_is_let_through_once_a_period_per_key():
    # The bridge's late-TPDO and stall warnings repeat every cycle under load;
    # rclpy's own throttle costs ~1 ms a call before it stays silent, so the
    # clock is looked at first (runtime/diagnostics.py, LogThrottle).
    from stewart63_ros.runtime.diagnostics import LogThrottle
    due = LogThrottle(0.05)
    assert [due('late TPDO'), due('late TPDO'), due('stalled'), due('late TPDO')] == [
        True, False, True, False]
    time.sleep(0.06)
    assert [due('late TPDO'), due('late TPDO')] == [True, False]
