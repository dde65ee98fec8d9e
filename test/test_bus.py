"""The field bus without ROS: the load arithmetic, the scaling, the CiA 402
state machine, the config file, the bus faults' parsing, the local bus
(``s63hub``) between processes, and the master against the plant's drives
on it (bring-up, a cycle, every bus fault named and recovered from).

Numbers are checked against something independent: frame sizes against the
CAN frame's fields counted by hand, the scaling by round trips and by hand,
the bus's effect on the paper's run against the torque resolution.
"""
from __future__ import annotations

import dataclasses
import subprocess
import sys
import textwrap
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

from stewart63_ros.core.machine import bus as corebus
from stewart63_ros.core.machine.bus import (
    FAULT,
    OPERATION_ENABLED,
    SWITCH_ON_DISABLED,
    BusConfigError,
    BusLoadError,
    Cia402Drive,
    check_load,
    drive_state,
    frame_bits,
    load_bus_config,
    next_controlword,
)
from stewart63_ros.core.machine.faults import FaultError, FaultModel, parse_fault

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / 'config' / 'canopen.yaml'
EDS = REPO / 'config' / 'stewart63_drive.eds'


def channels(n=2):
    """Channels of this test's own: hub channels are machine-wide names."""
    tag = uuid.uuid4().hex[:8]
    return ['t%s-%d' % (tag, i) for i in range(n)]


# -- bus load ------------------------------------------------------------------------
def test_frame_bits_count_the_fields_and_worst_case_stuffing():
    # SOF 1, id 11, RTR 1, IDE 1, r0 1, DLC 4, data 8n, CRC 15 are stuffed;
    # CRC delimiter 1, ACK 2, EOF 7, intermission 3 are not; at worst one
    # stuff bit follows every 4 bits after the first (5 equal bits in a row).
    for n in range(9):
        stuffed = 1 + 11 + 1 + 1 + 1 + 4 + 8 * n + 15
        assert frame_bits(n) == stuffed + 13 + (stuffed - 1) // 4
    assert frame_bits(0) == 55 and frame_bits(8) == 135
    with pytest.raises(ValueError):
        frame_bits(9)


def test_packaged_config_fits_and_six_drives_on_one_bus_are_refused_with_what_fits():
    config = load_bus_config(CONFIG)
    loads = config.loads(1000.0)
    check_load(loads)                                   # two buses: fits
    assert [round(x.percent, 1) for x in loads] == [74.7, 74.7]
    # SYNC + 3 RPDOs of 4 bytes + 3 TPDOs of 8 bytes, and heartbeats
    assert loads[0].bits == 55 + 3 * frame_bits(4) + 3 * frame_bits(8)
    one = dataclasses.replace(config, buses=config.buses[:1], legs=tuple(
        dataclasses.replace(leg, bus='a') for leg in config.legs))
    with pytest.raises(BusLoadError) as refused:
        check_load(one.loads(1000.0))
    text = str(refused.value)
    assert '143.9 %' in text and 'at most 694 Hz' in text, text
    assert 'no classic CAN bitrate carries 1000 Hz' in text
    check_load(one.loads(694.0))                        # the rate it names fits
    with pytest.raises(BusLoadError, match='at 500 Hz it needs 800 kbit/s'):
        check_load(dataclasses.replace(one, buses=(dataclasses.replace(
            one.buses[0], bitrate=500_000),)).loads(500.0))


# -- scaling -------------------------------------------------------------------------
def test_counts_and_per_mille_round_trip_with_direction_and_resolution():
    config = load_bus_config(CONFIG)
    up, down = config.legs[0], config.legs[3]           # leg_4 counts the other way
    assert down.direction == -1
    for leg in (up, down):
        for length in (1.2, 1.6, 1.9034567):
            assert abs(leg.metres(leg.counts(length)) - length) <= leg.metres_per_count / 2
        assert abs(leg.metres_per_second(leg.counts_s(0.0123456)) - 0.0123456) <= 5e-7
        for force in (-2999.0, -10.0, 0.0, 0.4, 1234.5):
            assert abs(leg.force(leg.permille(force)) - force) <= leg.force_step_n / 2 + 1e-9
    assert up.counts(1.5) == 500000 and down.counts(1.5) == 1000000
    # by hand: 1 per mille of 200 mN m through a 5:1 gear, 5 mm lead, 90 %
    assert up.force_step_n == pytest.approx(0.2e-3 * 2 * np.pi * 5 * 0.9 / 0.005)
    assert down.permille(100.0) == -up.permille(100.0)
    assert up.permille(1e9) == 32767                    # INTEGER16 clamps


# -- CiA 402 ---------------------------------------------------------------------------
def test_master_controlwords_take_a_drive_from_fault_to_operation_enabled():
    drive = Cia402Drive()
    drive.mode = corebus.MODE_CST
    drive.fail()
    drive.fault_active = True
    cw = 0
    for _ in range(4):                                  # reset refused while the fault acts
        cw = next_controlword(drive_state(drive.statusword), cw)
        drive.command(cw)
    assert drive.state == FAULT and not drive.torque_enabled
    drive.fault_active = False
    states = []
    for _ in range(6):
        cw = next_controlword(drive_state(drive.statusword), cw)
        drive.command(cw)
        states.append(drive.state)
    assert states[-1] == OPERATION_ENABLED and drive.torque_enabled, states
    assert SWITCH_ON_DISABLED in states
    drive.command(0x00)                                 # disable voltage
    assert not drive.torque_enabled
    drive.mode = 0
    for cw in (0x06, 0x07, 0x0F):
        drive.command(cw)
    assert drive.state == OPERATION_ENABLED and not drive.torque_enabled   # not mode 10


# -- the config file ------------------------------------------------------------------------
@pytest.mark.parametrize('edit, why', [
    (('metres_per_count: 1.0e-6', 'metres_per_count: 0', 1), 'metres_per_count must be > 0'),
    (('node_id: 2', 'node_id: 200', 1), 'node_id must be 1..127'),
    (('node_id: 2', 'node_id: 1', 1), 'node ids repeat on bus a'),
    (('bus: b, node_id: 4', 'bus: c, node_id: 4', 1), 'must name one of the buses'),
    (('leg: leg_2', 'leg: leg_1', 1), 'legs must list leg_1 ... leg_6 once each'),
    (('eds: stewart63_drive.eds', 'eds: missing.eds', 1), 'no such file'),
    (('direction: 1', 'direction: 2', 1), 'direction must be 1 or -1'),
])
def test_bad_config_is_refused_naming_the_key(tmp_path, edit, why):
    text = CONFIG.read_text().replace(*edit)
    (tmp_path / 'stewart63_drive.eds').write_text(EDS.read_text())
    path = tmp_path / 'canopen.yaml'
    path.write_text(text)
    with pytest.raises(BusConfigError, match=why.replace('.', r'\.')):
        load_bus_config(path)


def test_channels_given_must_match_the_buses():
    with pytest.raises(BusConfigError, match='1 channels given for the 2 buses'):
        load_bus_config(CONFIG, channels=['x'])
    assert [b.channel for b in load_bus_config(CONFIG, channels=['x', 'y']).buses] == ['x', 'y']


# -- bus faults ------------------------------------------------------------------------
def test_bus_faults_parse_and_are_refused_without_the_bus():
    fault = parse_fault('bus_emcy:leg_3:0x2310@0.2-0.3')
    assert fault.bus and fault.value == 0x2310 and not fault.sensor
    with pytest.raises(FaultError, match='needs a value'):
        parse_fault('bus_emcy:leg_3')
    with pytest.raises(FaultError, match='out of range'):
        parse_fault('bus_emcy:leg_3:0x10000')
    with pytest.raises(FaultError, match='io: canopen'):
        FaultModel([parse_fault('bus_no_boot:leg_1')], 1000.0)
    model = FaultModel([parse_fault('bus_drive_fault:leg_2@0.001')], 1000.0, bus=True)
    model.begin(1)
    assert model.bus_active() == {1: {'bus_drive_fault': None}}
    forces = np.arange(6.0)
    assert model.actuate(forces) is forces               # not an actuator fault


# -- the local bus -------------------------------------------------------------------------
def test_s63hub_links_processes_and_loses_no_frame_of_a_burst():
    import can
    channel = channels(1)[0]
    receiver = can.Bus(interface='s63hub', channel=channel)
    n = 20000
    sender = subprocess.Popen([sys.executable, '-c', textwrap.dedent('''
        import can, sys
        bus = can.Bus(interface='s63hub', channel=sys.argv[1])
        for i in range(%d):
            bus.send(can.Message(arbitration_id=i %% 0x7FF, data=i.to_bytes(4, 'little'),
                                 is_extended_id=False))
        bus.shutdown()
    ''' % n), channel])
    try:
        got = []
        while len(got) < n:
            msg = receiver.recv(30.0)
            assert msg is not None, 'only %d of %d frames arrived' % (len(got), n)
            got.append(int.from_bytes(msg.data, 'little'))
        assert got == list(range(n))                    # all, in order
        assert sender.wait(30) == 0
    finally:
        if sender.poll() is None:
            sender.kill()
        receiver.shutdown()


def test_s63hub_a_bus_that_closes_while_another_is_introduced_ends_no_hub():
    # The old hub forwarded frames and, when a write to a closing bus failed,
    # closed a socket still in its select list (KeyError: the hub ended and
    # the channel with it). Now a bus gone while a newcomer is introduced
    # gets no link, the hub goes on, and the buses left still hear each other.
    import socket

    import can

    from stewart63_ros.canbus import hub
    newcomer, newcomer_far = socket.socketpair()
    gone, gone_far = socket.socketpair()
    live, live_far = socket.socketpair()
    gone_far.close()
    try:
        hub._introduce(newcomer, {gone.fileno(): gone, live.fileno(): live})
        word, fds, _, _ = socket.recv_fds(newcomer_far, 1, hub.MAX_FDS)
        assert word == hub.PEERS and len(fds) == 1      # the live bus only
        for fd in fds + socket.recv_fds(live_far, 1, hub.MAX_FDS)[1]:
            socket.socket(fileno=fd).close()
    finally:
        for sock in (newcomer, newcomer_far, gone, live, live_far):
            sock.close()
    channel = channels(1)[0]
    first, second = (can.Bus(interface='s63hub', channel=channel) for _ in range(2))
    buses = [second]
    try:
        first.shutdown()                        # gone without a word, then at once:
        second.send(can.Message(arbitration_id=0x101, is_extended_id=False))
        buses += [can.Bus(interface='s63hub', channel=channel) for _ in range(2)]
        buses[1].send(can.Message(arbitration_id=0x102, is_extended_id=False))
        second, third, fourth = buses
        for bus in (second, fourth):            # the hub is alive, the links are
            msg = bus.recv(5.0)
            assert msg is not None and msg.arbitration_id == 0x102
        assert [bus.recv(0.2) for bus in buses] == [None] * 3
    finally:
        for bus in buses:
            bus.shutdown()


def test_unknown_interface_is_a_clear_error():
    from stewart63_ros.canbus.devices import open_bus
    with pytest.raises(ValueError, match="unknown python-can interface 'nosuch'"):
        open_bus('nosuch', 'x', 1_000_000)


# -- the master against the plant's drives ----------------------------------------------------
class Bench:
    """The plant's drives served in a thread (a sample per SYNC, constant
    readings), and a master on the same buses."""

    def __init__(self, config_path=CONFIG, booted=range(6), heartbeat_ms=None, faults=None):
        from stewart63_ros.canbus.devices import DeviceSet
        from stewart63_ros.canbus.master import Master
        config = load_bus_config(config_path, channels=channels())
        if heartbeat_ms is not None:
            config = dataclasses.replace(config, heartbeat_ms=heartbeat_ms)
        self.devices = DeviceSet(config, booted=booted)
        self.faults: dict = faults or {}
        self.lengths = np.array([1.9, 1.9, 1.6, 1.6, 1.6, 1.6])
        self.rates = np.linspace(-0.01, 0.01, 6)
        self.k = 0
        self._stop = False
        self._lock = threading.Lock()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()
        self.master = Master(config, 1000.0, log=lambda text: None)

    def _serve(self):
        devices = self.devices
        while not self._stop:
            with self._lock:
                if devices.poll(0.0):
                    devices.take_sync()
                    devices.apply_faults(self.faults)
                    devices.heartbeats(self.k / 1000.0)
                    devices.answer_sync(self.lengths, self.rates)
                    self.k += 1
                    continue
            devices.poll(0.002)

    def cycle(self, k, forces=None):
        master = self.master
        master.bring_up_rebooted()
        master.sync(k)
        master.collect(time.monotonic() + 1.0, 0.002, 0.002)    # lockstep's rules
        master.missing()
        errors = master.errors()
        master.command(forces if forces is not None else np.full(6, 100.0), bool(errors))
        return errors

    def close(self):
        self._stop = True
        self.thread.join(5)
        self.master.close()
        self.devices.close()


@pytest.fixture
def bench():
    made = []

    def make(**kwargs):
        made.append(Bench(**kwargs))
        return made[-1]
    yield make
    for b in made:
        b.close()


def test_bring_up_then_cycles_read_counts_as_metres_and_apply_torque(bench):
    b = bench()
    b.master.reset_all()
    assert b.master.wait_for_boot(5.0) == []
    assert all(b.master.bring_up(link) for link in b.master.links)
    forces = np.array([100.0, -50.0, 0.0, 500.0, 1.0, -2000.0])
    for k in range(3):          # (a cycle's SYNC follows the NMT start on the stream)
        assert b.cycle(k, forces) == []
    drives = b.devices.drives
    assert all(d.nmt == 'OPERATIONAL' and d.drive.torque_enabled for d in drives)
    # the mapping the device follows is the one the master wrote by SDO
    assert drives[0].values[(0x1A00, 1)] == 0x6064 << 16 | 32
    lengths, rates = b.master.readings()
    assert np.allclose(lengths, b.lengths, atol=1e-6)
    assert np.allclose(rates, b.rates, atol=1e-6)
    legs = b.master.config.legs
    expected = [leg.force(leg.permille(f)) for leg, f in zip(legs, forces)]
    assert np.allclose(b.devices.forces(), expected)
    assert np.allclose(b.devices.forces(), forces, atol=legs[0].force_step_n / 2 + 1e-9)


def test_node_that_does_not_answer_is_named_and_others_run(bench):
    b = bench(booted=[0, 1, 2, 3, 4], faults={5: {'bus_no_boot': None}})   # leg_6: never
    b.master.reset_all()
    missing = b.master.wait_for_boot(1.0)
    assert [link.leg.name for link in missing] == ['leg_6']
    for link in b.master.links:
        if link.booted:
            assert b.master.bring_up(link)
    errors = b.cycle(0)
    assert errors == ['leg_6 (node 6, bus b): not booted (no boot-up message)']
    lengths, _ = b.master.readings()
    assert np.isnan(lengths[5]) and np.all(np.isfinite(lengths[:5]))
    assert b.devices.forces() == [0.0] * 6      # torque withheld from all


def test_a_drive_that_boots_again_during_its_bring_up_is_brought_up_again_before_sync_0(
        bench):
    # The rig's race: a reset heard by the drives after the boot-up the master
    # took; the second boot-up comes while leg_1 is being configured (and
    # resets what was written). The master must not call it up, and brings
    # it up again before SYNC 0, which every drive then answers.
    b = bench()
    b._stop = True
    b.thread.join(5)
    master = b.master
    master.reset_all()
    deadline = time.monotonic() + 5.0
    while any(not link.booted for link in master.links) and time.monotonic() < deadline:
        b.devices.poll(0.01)
    assert all(link.booted for link in master.links)
    master.reset_all()          # not served yet: heard once leg_1's bring-up has begun
    b._stop = False
    b.thread = threading.Thread(target=b._serve, daemon=True)
    threading.Timer(0.05, b.thread.start).start()
    assert not master.bring_up(master.links[0])
    assert not master.links[0].up and 'booted again' in master.links[0].boot_error
    assert master.bring_up_rebooted() == [link.name for link in master.links]
    assert b.cycle(0) == [] and master.missing() == [] and master.late_tpdos() == []


def test_realtime_tpdo_miss_is_late_until_it_persists_for_tpdo_error_cycles(bench):
    b = bench()
    master = b.master
    master.reset_all()
    assert master.wait_for_boot(5.0) == []
    assert all(master.bring_up(link) for link in master.links)
    master.tpdo_error_cycles = 3            # the bridge's tpdo_missing_error_ms, in SYNCs
    assert b.cycle(0) == []
    b.faults = {3: {'bus_tpdo_missing': None}}
    for k in (1, 2):        # missed, not yet persistent: late (WARN), torque kept
        assert b.cycle(k) == [], k
        assert master.late_tpdos() == ['leg_4 (node 4, bus b): TPDO missed at SYNC %d '
                                       '(%d missed in all)' % (k, k)]
    assert b.cycle(3) == ['leg_4 (node 4, bus b): TPDO missing since SYNC 1 (silent: '
                          'cable, power?)']
    assert master.late_tpdos() == []
    b.faults = {}
    assert b.cycle(4) == [] and master.late_tpdos() == []


def test_eds_without_mapped_objects_is_refused(tmp_path):
    from stewart63_ros.canbus.master import Master
    text = EDS.read_text()
    start = text.index('[6064]')
    end = text.index('[', start + 1)
    (tmp_path / 'stewart63_drive.eds').write_text(text[:start] + text[end:])
    (tmp_path / 'canopen.yaml').write_text(CONFIG.read_text())
    config = load_bus_config(tmp_path / 'canopen.yaml', channels=channels())
    with pytest.raises(BusConfigError, match=r'has no 0x6064 \(position actual value\)'):
        Master(config, 1000.0)


BUS_FAULTS = [({1: {'bus_drive_fault': None}}, 'leg_2 (node 2, bus a): EMCY 0x5000'),
              ({2: {'bus_emcy': 0x2310}}, 'leg_3 (node 3, bus a): EMCY 0x2310'),
              ({3: {'bus_tpdo_missing': None}}, 'leg_4 (node 4, bus b): TPDO missing'),
              ({4: {'bus_heartbeat_lost': None}}, 'leg_5 (node 5, bus b): TPDO missing'),
              ({5: {'bus_no_boot': None}}, 'leg_6 (node 6, bus b): TPDO missing')]


def test_each_bus_fault_is_named_within_three_cycles_torque_withheld_then_recovered(bench):
    import itertools
    b = bench(heartbeat_ms=5)       # heartbeat lost after 15 cycles
    b.master.reset_all()
    assert b.master.wait_for_boot(5.0) == []
    assert all(b.master.bring_up(link) for link in b.master.links)
    cycles = itertools.count()
    for _ in range(3):
        assert b.cycle(next(cycles)) == []
    for fault, named in BUS_FAULTS:         # one after the other, on one bus
        with b._lock:
            b.faults = fault
        seen = []
        for _ in range(3):
            seen.append(b.cycle(next(cycles)))
            if any(named in e for e in seen[-1]):
                break
        assert any(named in e for e in seen[-1]), (fault, seen)
        for _ in range(20):                 # the fault goes on: torque stays withheld
            errors = b.cycle(next(cycles))
        assert errors and b.devices.forces() == [0.0] * 6, (fault, errors)
        if 'bus_heartbeat_lost' in next(iter(fault.values())):
            assert any('heartbeat lost' in e for e in errors), errors
        with b._lock:
            b.faults = {}
        for _ in range(20):                 # back: the drive is brought back
            errors = b.cycle(next(cycles))
            if not errors:
                break
        assert errors == [], (fault, errors)
        b.cycle(next(cycles))
        assert np.allclose(b.devices.forces(), 100.0, atol=1.0), fault     # torque again


def test_odrive_protocol_against_a_fake_odrive_on_the_local_bus():
    import can

    from stewart63_ros.canbus.odrive import AXIS_CLOSED_LOOP, FakeODrive, ODriveLegs
    config = load_bus_config(CONFIG)
    channel = channels(1)[0]
    host_bus = can.Bus(interface='s63hub', channel=channel)
    drive_bus = can.Bus(interface='s63hub', channel=channel)
    try:
        host = ODriveLegs(host_bus, config.legs)
        fakes = [FakeODrive(drive_bus, leg) for leg in config.legs]

        def deliver(bus, takers, count):
            for _ in range(count):
                msg = bus.recv(5.0)
                assert msg is not None
                for taker in takers:
                    taker.take(msg)

        forces = np.array([100.0, -50.0, 0.0, 500.0, 1.0, -2000.0])
        host.command(forces)                            # before enabling: no force
        deliver(drive_bus, fakes, 6)
        assert [f.force for f in fakes] == [0.0] * 6
        host.enable()
        host.command(forces)
        deliver(drive_bus, fakes, 18)
        # float32 torque: forces back to a few parts in 1e7
        assert np.allclose([f.force for f in fakes], forces, rtol=1e-6, atol=1e-4)
        lengths = [1.9, 1.9, 1.6, 1.65, 1.6, 1.6]
        for fake, length in zip(fakes, lengths):
            fake.answer(length, 0.01)
        deliver(host_bus, [host], 12)
        assert np.allclose([host.lengths[i] for i in range(6)], lengths, atol=1e-6)
        assert np.allclose([host.rates[i] for i in range(6)], 0.01, atol=1e-6)
        assert set(host.axis_state.values()) == {AXIS_CLOSED_LOOP}
    finally:
        host_bus.shutdown()
        drive_bus.shutdown()


def test_bus_faults_without_the_bus_are_refused_by_sim_and_rig(tmp_path):
    for argv in (['-m', 'stewart63_ros.tools.sim', '--duration', '0.01', '--out',
                  str(tmp_path / 'sim')],
                 ['-m', 'stewart63_ros.tools.rig', '--duration', '0.01']):
        done = subprocess.run([sys.executable, *argv, '--fault', 'bus_emcy:leg_2:0x2310'],
                              capture_output=True, text=True, timeout=120)
        assert done.returncode == 2, done
        assert "'bus_emcy:leg_2:0x2310' acts on the field bus" in done.stderr, done.stderr
        assert 'Traceback' not in done.stderr


def test_heartbeats_follow_the_run_time_and_start_again_with_a_new_run():
    import can

    from stewart63_ros.canbus.devices import DeviceSet
    config = load_bus_config(CONFIG, channels=channels())
    listener = can.Bus(interface='s63hub', channel=config.buses[0].channel)
    devices = DeviceSet(config)
    try:
        for drive in devices.drives:
            drive.write(0x1017, 0, 100)             # as the master's SDO does

        def beats(t):
            devices.heartbeats(t)
            got = []
            while True:
                msg = listener.recv(0.5)
                if msg is None:
                    return got
                if 0x700 < msg.arbitration_id < 0x780 and msg.data[0]:
                    got.append(msg.arbitration_id - 0x700)
        while listener.recv(0.2) is not None:       # the boot-ups
            pass
        assert beats(0.0) == [1, 2, 3]              # bus a's drives
        assert beats(0.05) == []
        assert beats(0.1) == [1, 2, 3]
        assert beats(0.0) == [1, 2, 3]              # reset: run time from 0 again
    finally:
        devices.close()
        listener.shutdown()


def test_plant_drives_beat_on_the_wall_clock_in_realtime_before_the_run_too():
    # The bridge judges realtime heartbeats on their reception times, so the
    # plant's drives beat on the wall clock there, from 0x1017's write on: a
    # run not yet started, or SYNCs skipped after a stall, must not make them
    # look lost (test_supervisor_bus tripped on that). Lockstep: run time only
    # (test_heartbeats_follow_the_run_time...).
    import can

    from stewart63_ros.canbus.devices import DeviceSet
    from stewart63_ros.nodes.plant_bus import PlantBus
    config = load_bus_config(CONFIG, channels=channels())
    listener = can.Bus(interface='s63hub', channel=config.buses[0].channel)
    devices = DeviceSet(config)
    plant = type('Plant', (PlantBus,), {})()
    plant.mode, plant.devices = 'realtime', devices
    try:
        for drive in devices.drives:
            drive.write(0x1017, 0, 100)
        while listener.recv(0.2) is not None:       # the boot-ups
            pass
        beats = []
        start = time.monotonic()
        while time.monotonic() - start < 0.35:      # the plant's idle timer, no run
            PlantBus.serve_bus_idle(plant)
            msg = listener.recv(0.002)
            if msg is not None and 0x700 < msg.arbitration_id < 0x780:
                beats.append(msg.arbitration_id - 0x700)
        assert beats in ([1, 2, 3] * 3, [1, 2, 3] * 4), beats  # at 0, 0.1, 0.2, 0.3 s
    finally:
        devices.close()
        listener.shutdown()


def test_the_loop_reads_the_buses_itself_and_an_sdo_meanwhile_gets_its_threads_back(bench):
    """Realtime: the bridge's loop reads the buses (no notifier thread wakes
    per cycle); a drive brought up again (SDO) meanwhile gets its answers."""
    b = bench()
    master = b.master
    master.reset_all()
    assert master.wait_for_boot(5.0) == []
    assert all(master.bring_up(link) for link in master.links)
    assert master.receive_in_loop()
    ours = [bus.channel for bus in master.config.buses]

    def readers():
        return [t.name for t in threading.enumerate()
                if t.name.startswith('Notifier') and any(c in t.name for c in ours)]
    assert readers() == []
    for k in range(3):
        assert b.cycle(k) == []
    assert np.allclose(master.readings()[0], b.lengths, atol=1e-6)
    b.devices.drives[2].boot()              # it boots again: brought up by SDO in the loop
    time.sleep(0.05)
    for k in range(3, 6):
        assert b.cycle(k) == [], k
    assert master.links[2].up and readers() == []   # read by the loop again
    assert np.allclose(master.readings()[0], b.lengths, atol=1e-6)
    states = master.safe_stop()
    assert set(states.values()) == {'READY TO SWITCH ON'}
