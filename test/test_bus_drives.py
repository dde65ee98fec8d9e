"""The bridge's master against drives it did not write (test/cia402_drive.py).

Six strict CiA 402 drives on raw python-can frames, on the local bus
(``s63hub``), with an EDS as drives ship: all eight PDOs valid and mapped
(test/cia402_drive.eds), answering each SYNC late on purpose. Checked:

- the drive itself refuses what the standards forbid (its abort codes, the
  PDO re-mapping rules, the state machine), or the rest proves nothing;
- the master brings all six up, maps its three PDOs and switches every other
  off; afterwards an independent listener sees no frame with a COB-ID
  nobody configured, and the load measured on the wire is within 1 point of
  the planned one (with the PDOs a drive ships with left on, a TPDO3 at
  every SYNC adds 3.5 points at 100 Hz, 6.9 at 200 Hz);
- a drive whose TPDO3 cannot be switched off is refused, naming 0x1802:01;
- a frame nobody configured gives the ERROR naming its COB-ID, and traffic
  over the plan a WARN; in a rig over the bus the bridge's /diagnostics
  says so (the one DDS test here).
"""
from __future__ import annotations

import struct
import threading
import time
from pathlib import Path

import pytest
from cia402_drive import (
    ABORT_NO_OBJECT,
    ABORT_NO_SUBINDEX,
    ABORT_NOT_MAPPABLE,
    ABORT_READ_ONLY,
    ABORT_STATE,
    ABORT_VALUE,
    FAULT,
    FRA,
    OE,
    RTSO,
    SOD,
    DriveRack,
    StrictDrive,
)
from test_bus import CONFIG, channels

from stewart63_ros.canbus.busload import WARN_POINTS, WireLoad, known_cob_ids
from stewart63_ros.core.machine.bus import load_bus_config

EDS = Path(__file__).resolve().with_name('cia402_drive.eds')
RATE = 100.0
#: s: each drive's answer to a SYNC, late within the 10 ms period on purpose
SYNC_DELAYS = {1: 0.001, 2: 0.002, 3: 0.003, 4: 0.0005, 5: 0.0025, 6: 0.004}


def strict_config(tmp_path, eds=EDS):
    """The packaged device config with every leg's EDS ``eds``, on channels of its own."""
    path = tmp_path / 'canopen.yaml'
    path.write_text(CONFIG.read_text().replace('eds: stewart63_drive.eds', 'eds: %s' % eds))
    return load_bus_config(path, channels=channels())


# -- the drive is strict --------------------------------------------------------------------
class Frames:
    """A drive's frames out, for the tests that drive it without a bus."""

    def __init__(self):
        self.sent = []

    def __call__(self, cob, data):
        self.sent.append((cob, data))

    def sdo(self, drive, command, index, sub, value=0, size=4):
        self.sent.clear()
        if command == 'write':
            head = 0x23 | (4 - size) << 2
            data = struct.pack('<BHB', head, index, sub) + (
                value & (1 << 8 * size) - 1).to_bytes(size, 'little').ljust(4, b'\0')
        else:
            data = struct.pack('<BHB4x', 0x40, index, sub)
        drive.receive(0x600 + drive.node_id, data, time.monotonic())
        (cob, answer), = self.sent
        assert cob == 0x580 + drive.node_id
        if answer[0] == 0x80:
            return 'abort', struct.unpack_from('<I', answer, 4)[0]
        return 'ok', struct.unpack_from('<i', answer, 4)[0]


def test_strict_drive_aborts_what_the_standards_forbid():
    out = Frames()
    drive = StrictDrive(EDS, 3, out)
    assert out.sent == [(0x703, b'\x00')]                           # boot-up
    assert out.sdo(drive, 'read', 0x2000, 0) == ('abort', ABORT_NO_OBJECT)
    assert out.sdo(drive, 'read', 0x1018, 9) == ('abort', ABORT_NO_SUBINDEX)
    assert out.sdo(drive, 'write', 0x6041, 0, 6, 2) == ('abort', ABORT_READ_ONLY)
    assert out.sdo(drive, 'write', 0x6060, 0, 4, 1) == ('abort', ABORT_VALUE)    # not in 0x6502
    # TPDO3 exists as shipped: its mapping and its id stay; bit 31 alone may change
    assert out.sdo(drive, 'read', 0x1802, 1) == ('ok', 0x40000383)
    assert out.sdo(drive, 'write', 0x1A02, 0, 0, 1) == ('abort', ABORT_STATE)
    assert out.sdo(drive, 'write', 0x1802, 1, 0x40000390) == ('abort', ABORT_VALUE)
    assert out.sdo(drive, 'write', 0x1802, 1, 0xC0000383) == ('ok', 0)
    assert out.sdo(drive, 'write', 0x1A02, 1, 0x60640020) == ('abort', ABORT_STATE)  # count 2
    assert out.sdo(drive, 'write', 0x1A02, 0, 0, 1) == ('ok', 0)
    assert out.sdo(drive, 'write', 0x1A02, 1, 0x60760020) == ('abort', ABORT_NOT_MAPPABLE)
    assert out.sdo(drive, 'write', 0x1A02, 1, 0x60640010) == ('abort', ABORT_NOT_MAPPABLE)
    assert out.sdo(drive, 'write', 0x1602, 1, 0x60410010) == ('abort', ABORT_STATE)  # RPDO3 on
    assert out.sdo(drive, 'write', 0x1802, 1, 0x00000701) == ('abort', ABORT_VALUE)  # heartbeat's
    drive.receive(0x000, bytes([0x01, 3]), time.monotonic())     # NMT start: operational
    assert out.sdo(drive, 'write', 0x1A02, 0, 0, 1) == ('abort', ABORT_STATE)


def test_strict_drive_state_machine_and_late_sync_answers():
    out = Frames()
    clock = [100.0]
    drive = StrictDrive(EDS, 1, out, sync_delay=0.003, fault_reaction_s=0.02,
                        clock=lambda: clock[0])
    for cw, state in ((0x0F, SOD), (0x07, SOD), (0x06, RTSO), (0x0F, OE), (0x00, SOD)):
        drive.command(cw)
        assert drive.state == state, (hex(cw), drive.state)
    drive.fail()
    assert drive.state == FRA
    drive.command(0x80)                             # no reset from FAULT REACTION ACTIVE
    drive.command(0x00)
    drive.tick(clock[0] + 0.03)
    assert drive.state == FAULT
    drive.command(0x80)                             # the cause is still there
    assert drive.state == FAULT
    drive.fault_cause = False
    drive.command(0x00)
    drive.command(0x80)
    assert drive.state == SOD
    # operational: a SYNC's TPDOs (types 1) leave sync_delay later, not before
    drive.receive(0x000, bytes([0x01, 0]), clock[0])
    out.sent.clear()
    drive.receive(0x080, b'', clock[0])
    assert out.sent == []
    drive.tick(clock[0] + 0.002)
    assert out.sent == []
    drive.tick(clock[0] + 0.003)
    assert sorted(cob for cob, _ in out.sent) == [0x181, 0x281, 0x381]
    drive.values[(0x1007, 0)] = 2000                # a 2 ms window: 3 ms late is dropped
    out.sent.clear()
    drive.receive(0x080, b'', clock[0])
    drive.tick(clock[0] + 0.01)
    assert out.sent == []


# -- the master against six strict drives -------------------------------------------------
class Wire:
    """Six strict drives on two buses, an independent listener on each, and
    the bridge's master (and its wire load) on them."""

    def __init__(self, tmp_path, read_only=None, eds=EDS):
        import can

        from stewart63_ros.canbus.master import Master
        self.config = config = strict_config(tmp_path, eds)
        self.racks, self.listeners, self.seen = [], [], []
        self._lock = threading.Lock()
        for bus in config.buses:
            self.racks.append(DriveRack(can.Bus(interface='s63hub', channel=bus.channel), {
                leg.node_id: dict(sync_delay=SYNC_DELAYS[leg.node_id],
                                  read_only=(read_only or {}).get(leg.node_id, ()))
                for leg in config.legs_on(bus.name)}, eds))
            sniffer = can.Bus(interface='s63hub', channel=bus.channel)
            self.listeners.append(can.Notifier(sniffer, [self._recorder(bus.name)], 0.1))
        self.log = []
        self.closed = False
        self.master = Master(config, RATE, log=self.log.append)
        self.wire = WireLoad(config, RATE)
        self.wire.attach(self.master.networks)
        self.drives = {node: drive for rack in self.racks for node, drive in rack.drives.items()}
        for leg in config.legs:
            self.drives[leg.node_id].position = leg.counts(1.6 + 0.01 * leg.leg)
            self.drives[leg.node_id].velocity = 0

    def _recorder(self, bus):
        def record(msg):        # stamped by the sender (s63hub: its wall clock)
            with self._lock:
                self.seen.append((msg.timestamp, bus, msg.arbitration_id))
        return record

    def bring_up(self):
        master = self.master
        master.reset_all()
        assert master.wait_for_boot(5.0) == []
        ups = [master.bring_up(link) for link in master.links]
        deadline = time.monotonic() + 5.0
        while any(link.booted for link in master.links) and time.monotonic() < deadline:
            master.bring_up_rebooted()
        deadline = time.monotonic() + 5.0       # the NMT starts are on their way
        while time.monotonic() < deadline and any(
                self.drives[link.leg.node_id].nmt != 'OPERATIONAL'
                for link in master.links if link.up):
            time.sleep(0.01)
        return ups

    def run(self, cycles, forces=None, restart=True):
        """``cycles`` cycles at RATE on the wall clock (each waiting for every
        TPDO, as lockstep does: a loaded machine must not decide the test);
        the errors of the last. ``rate``: the cycles' rate achieved. The
        wire's window starts with the first cycle (``restart``)."""
        master = self.master
        period = 1.0 / RATE
        t0 = time.monotonic()
        if restart:
            self.wire.restart(t0)
        errors = []
        for k in range(cycles):
            while time.monotonic() < t0 + k * period:
                time.sleep(0.0005)
            master.sync(k)
            while not master.collect(time.monotonic() + 0.5, 0.002, 0.002):
                pass
            master.missing()
            errors = master.errors()
            master.command(forces, bool(errors))
        while time.monotonic() < t0 + cycles * period:
            time.sleep(0.0005)
        self.end = time.monotonic()
        self.rate = cycles / (self.end - t0)
        return errors

    def frames_since(self, start):
        with self._lock:
            return [(bus, cob) for t, bus, cob in self.seen if t >= start]

    def close(self):
        if self.closed:
            return
        self.closed = True
        # every reader stopped before any connection closes: a hub that ends
        # as its buses go (canbus/hub.py) must find no thread still reading
        for rack in self.racks:
            rack.stop()
        for notifier in self.listeners:
            notifier.stop()
        self.master.close()
        for rack in self.racks:
            rack.close()
        for notifier in self.listeners:
            notifier.bus.shutdown()


@pytest.fixture
def wire(tmp_path):
    made = []

    def make(**kwargs):
        made.append(Wire(tmp_path, **kwargs))
        return made[-1]
    yield make
    for w in made:
        w.close()


@pytest.mark.slow        # (the hub: a process per bus)
def test_six_strict_drives_come_up_with_only_the_bridges_pdos_on_the_wire(wire):
    w = wire()
    w.master.sync_window_us = 7500          # the bridge's realtime window at RATE
    assert w.bring_up() == [True] * 6, w.log
    # the window it judges TPDOs by is the drives' own (0x1007, CiA 301)
    assert {node: d.values[(0x1007, 0)] for node, d in w.drives.items()} == dict.fromkeys(
        w.drives, 7500)
    for node, drive in w.drives.items():
        assert drive.state == OE and drive.nmt == 'OPERATIONAL', (node, drive.state)
        comms = [*range(0x1400, 0x1600), *range(0x1800, 0x1A00)]
        on = {index for index in comms if (index, 1) in drive.values
              and not drive.values[(index, 1)] & 1 << 31}
        assert on == {0x1400, 0x1800, 0x1801}, (node, sorted(map(hex, on)))
        assert drive.values[(0x1600, 0)] == 2 and drive.values[(0x1600, 2)] == 0x60710010
        assert drive.aborts == [], (node, drive.aborts)
    assert any('RPDO2, RPDO3, RPDO4, TPDO3, TPDO4 off' in line for line in w.log), w.log
    start = time.time()     # (the frames' stamps: the sender's wall clock)
    legs = w.config.legs
    forces = [100.0, -50.0, 0.0, 500.0, 1.0, -2000.0]
    assert w.run(int(2 * RATE), forces) == []
    # every reading is its drive's, every torque as commanded
    lengths, _ = w.master.readings()
    assert lengths == pytest.approx([1.6 + 0.01 * i for i in range(6)], abs=2e-6)
    for leg in legs:
        assert w.drives[leg.node_id].values[(0x6077, 0)] == leg.permille(forces[leg.leg])
    # nothing but what the bridge configured, seen by a listener of its own
    configured = {0x080} | {cob + leg.node_id for leg in legs
                            for cob in (0x180, 0x200, 0x280, 0x700)}
    frames = w.frames_since(start)
    seen = {cob for _, cob in frames}
    assert seen <= configured, sorted(map(hex, seen - configured))
    assert {0x180 + leg.node_id for leg in legs} <= seen
    # the load measured on the wire is the planned one, within a point (the
    # plan for the rate the cycles ran at: on a loaded machine a little under RATE)
    assert w.wire.measure(w.end)
    plan = {load.bus: load.percent for load in w.config.loads(w.rate)}
    for bus, (planned, measured, _, unknown) in w.wire.figures.items():
        assert planned == pytest.approx(7.645)
        assert abs(measured - plan[bus]) <= 1.0, (bus, plan[bus], measured, w.rate)
        assert unknown == ()
    assert w.wire.verdict() == ('', '')


@pytest.mark.slow        # (the hub: a process per bus)
def test_a_drive_whose_tpdo3_cannot_be_switched_off_is_refused_naming_the_object(wire):
    w = wire(read_only={3: [(0x1802, 1)]})
    start = time.time()
    ups = w.bring_up()
    assert ups == [True, True, False, True, True, True], w.log
    leg_3 = w.master.links[2]
    assert not leg_3.up
    error = leg_3.boot_error
    assert error.startswith('leg_3 (node 3, bus a): bring-up failed: TPDO3 cannot be disabled: '
                            '0x1802:01 refused the write of 0xC0000383'), error
    assert '0x06010002' in error and '\n' not in error
    assert error.endswith('(refused, not retried: the drive or its EDS must change)'), error
    assert (0x1802, 1, 0x06010002) in w.drives[3].aborts
    # refused once: no reset, no second try (a boot-up cannot make it writable)
    assert [line for line in w.log if line.startswith('leg_3')] == [error], w.log
    w.master.reset_all()                    # its next boot-up is not brought up either
    assert w.master.wait_for_boot(5.0) == []
    assert w.master.bring_up_rebooted() == ['leg_%d (node %d, bus %s)' % (i, i, 'a' if i < 4
                                                                          else 'b')
                                            for i in (1, 2, 4, 5, 6)]
    assert not leg_3.up and leg_3.boot_error == error
    boot_ups = [t for t, _, cob in w.seen if cob == 0x703 and t >= start]
    assert len(boot_ups) == 2, boot_ups     # the two resets' own: none of a retry


@pytest.mark.slow        # (the hub: a process per bus)
def test_a_frame_nobody_configured_is_an_error_naming_its_cob_id(wire):
    import can
    w = wire()
    assert w.bring_up() == [True] * 6, w.log
    # (open to the end: the hub forwards nothing now, and a bus closing while
    # it introduces another ends no hub, test_bus.py; the stranger is simply
    # heard until the test ends)
    stranger = can.Bus(interface='s63hub', channel=w.config.buses[1].channel)
    try:
        w.wire.restart()
        t_send = time.time()
        stranger.send(can.Message(arbitration_id=0x384, data=b'\x01\x02', is_extended_id=False))
        w.run(20, restart=False)
        assert w.wire.measure(min_window=0.0)
        error, _ = w.wire.verdict()
        assert error.startswith('unknown frames on bus b: COB-ID 0x384 '), (
            error, w.wire.unknown, [x for x in w.seen if x[2] == 0x384], t_send)
        values = w.wire.values()
        assert values['bus_unknown_cob_ids/b'] == '0x384 (1)'
        assert values['bus_unknown_cob_ids/a'] == 'none'
        w.run(10)
        assert w.wire.measure(min_window=0.0)
        assert w.wire.verdict()[0] == ''                   # gone with the next window
    finally:
        w.close()
        stranger.shutdown()


class Msg:
    def __init__(self, cob, dlc, extended=False):
        self.arbitration_id, self.dlc, self.is_extended_id = cob, dlc, extended
        self.is_error_frame = self.is_remote_frame = False


def test_wire_load_warns_over_the_plan_and_counts_frames_as_the_plan_does():
    config = load_bus_config(CONFIG)
    load = WireLoad(config, 1000.0)
    assert known_cob_ids(config, 'a')[0x181] == 'TPDO1'
    assert 0x383 not in known_cob_ids(config, 'a')
    load.restart(0.0)
    for _ in range(1000):       # one second of the plan on bus a, no heartbeat
        load.count('a', Msg(0x080, 0))
        for node in (1, 2, 3):
            load.count('a', Msg(0x200 + node, 4))
            load.count('a', Msg(0x180 + node, 8))
    assert load.measure(1.0, min_window=0.0)
    planned, measured, rate, unknown = load.figures['a']
    assert measured == pytest.approx(74.5) and planned == pytest.approx(74.7, abs=0.05)
    assert rate == 7000 and unknown == ()
    assert load.verdict() == ('', '')
    for _ in range(1000):       # and a TPDO3 (6 bytes) of one drive at every SYNC
        load.count('a', Msg(0x080, 0))
        for node in (1, 2, 3):
            load.count('a', Msg(0x200 + node, 4))
            load.count('a', Msg(0x180 + node, 8))
        load.count('a', Msg(0x381, 6))
    assert load.measure(2.0, min_window=0.0)
    assert load.figures['a'][1] == pytest.approx(74.5 + 11.5)
    error, warning = load.verdict()
    assert error.startswith('unknown frames on bus a: COB-ID 0x381 ')
    assert warning == ('bus load measured on the wire: bus a 86.0 %%, planned 74.7 %%: over '
                       'by more than %g points (other traffic?)' % WARN_POINTS)


def test_the_bridge_names_a_stray_cob_id_on_its_diagnostics(ros, monkeypatch, tmp_path):
    # The node's side of the wire load: a rig over the bus (the plant's
    # drives), and a stranger on bus b sending a frame nobody configured.
    import os

    import can
    from test_bus_rig import run_bus_rig

    from stewart63_ros import bagio
    stop = threading.Event()

    def stray():        # (drains the channel too: a reader must keep up with the hub)
        bus = can.Bus(interface='s63hub', channel='rig%d-b' % os.getpid())
        notifier = can.Notifier(bus, [lambda msg: None], 0.1)
        try:
            while not stop.wait(0.2):
                bus.send(can.Message(arbitration_id=0x384, data=b'\x01', is_extended_id=False))
        finally:
            notifier.stop()
            bus.shutdown()
    thread = threading.Thread(target=stray, daemon=True)
    thread.start()
    try:
        bag, _, bridge, logs = run_bus_rig(ros, monkeypatch, tmp_path, 'lockstep', 1.0)
    finally:
        stop.set()
        thread.join(5)
    errors, values = [], {}
    for _, _, msg in bagio.read_messages(bag, ['/diagnostics']):
        for status in msg.status:
            if status.name.endswith('canopen_bridge'):
                level = status.level if isinstance(status.level, int) \
                    else int.from_bytes(status.level, 'little')
                if level == 2:
                    errors.append(status.message)
                values.update({kv.key: kv.value for kv in status.values})
    assert any('unknown frames on bus b: COB-ID 0x384 ' in e for e in errors), (errors, logs)
    assert values['bus_unknown_cob_ids/a'] == 'none'
    assert values['bus_unknown_cob_ids/b'].startswith('0x384 (')
    assert values['bus_load_computed_percent/b'] == '74.7'
    assert float(values['bus_load_percent/b']) > 0.0
