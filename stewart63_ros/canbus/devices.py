"""The simulated plant as CiA 402 drives on the bus: the device side.

One ``Drive`` per leg answers as a CANopen device would: boot-up message,
NMT (start, stop, pre-operational, resets), an SDO server (expedited
transfers, which every object of the EDS fits; the object dictionary and the
value types come from the EDS through the ``canopen`` library), PDOs
following the mapping the master wrote by SDO (RPDO1 applied on arrival;
TPDO1 at each SYNC, a synchronous transmission type; TPDO2 when its values
change, types 254/255), a heartbeat producer (0x1017), EMCY, and the CiA 402
state machine (core/machine/bus.py, ``Cia402Drive``): a drive not in OPERATION
ENABLED with mode 10 applies no torque. Its position actual value is its
encoder's count less the home offset 0x607C a homing wrote (the supervisor's
homing, through the bridge's ``homed_offset``); power-on resets it to 0.

Why not ``canopen.LocalNode``: its SDO server, PDOs and heartbeat run in the
notifier's thread and on the wall clock; the plant must answer SYNC *k* with
the state at sample *k*, in its own loop, with heartbeats in the run's time
(a paused lockstep run is not a dead device). ``DeviceSet`` therefore reads
the buses itself, in the plant's thread: deterministic, and no thread hop
per frame (its cost per sample: bench/bench_bus.py, docs/performance.md).

Bus faults (core/machine/faults.py, ``bus_*``) act here, on the device's side:
``bus_no_boot`` (the device is off: no boot-up, hears nothing; boots when the
fault ends), ``bus_heartbeat_lost`` (a pulled cable: the device neither
sends nor hears; having lost its master it disables its power stage, as a
drive's abort connection option 0x6007 does, and the master enables it again
when the cable is back),
``bus_emcy`` (an EMCY with the fault's error code at its start, the error
reset EMCY 0x0000 at its end), ``bus_drive_fault`` (the drive falls into
FAULT, with EMCY 0x5000; a fault reset is refused until the fault ends),
``bus_tpdo_missing`` (no TPDO1 at the SYNCs of the fault).
"""
from __future__ import annotations

import select
import struct
import time

import can

from stewart63_ros.canbus.hub import can_arm
from stewart63_ros.core.machine.bus import (
    FAULT,
    HOME_OFFSET,
    MODE_CST,
    BusConfig,
    Cia402Drive,
    LegDrive,
)

NMT_STATES = {'INITIALISING': 0x00, 'STOPPED': 0x04, 'OPERATIONAL': 0x05,
              'PRE-OPERATIONAL': 0x7F}
#: struct codes of the EDS data types a PDO may map
PDO_CODES = {0x1: '?', 0x2: 'b', 0x3: 'h', 0x4: 'i', 0x5: 'B', 0x6: 'H', 0x7: 'I'}
SDO_ABORT_NO_OBJECT = 0x06020000
SDO_ABORT_READ_ONLY = 0x06010002
SDO_ABORT_WRITE_ONLY = 0x06010001
SDO_ABORT_SIZE = 0x06070010
SDO_ABORT_COMMAND = 0x05040001
SDO_ABORT_STATE = 0x08000022
EMCY_DRIVE_FAULT = 0x5000
HOME_KEY = (HOME_OFFSET, 0)


def open_bus(interface: str, channel: str, bitrate: int) -> can.BusABC:
    """A python-can bus, or a clear error naming the interface and channel.

    Raises:
        ValueError: an unknown interface, or one that cannot open the channel.
    """
    if interface not in can.interfaces.VALID_INTERFACES:
        raise ValueError('unknown python-can interface %r (known: %s)' % (
            interface, ', '.join(sorted(can.interfaces.VALID_INTERFACES))))
    try:
        return can.Bus(interface=interface, channel=channel, bitrate=bitrate)
    except (can.CanError, OSError, ImportError, ValueError) as exc:
        raise ValueError('python-can interface %r cannot open channel %r: %s'
                         % (interface, channel, exc)) from None


class Drive:
    """One leg's drive (see the module's doc).

    Args:
        leg: its entry of the config file.
        od: its object dictionary (``canopen.import_od`` of its EDS, with its node id).
        send: ``send(cob_id, data)`` puts a frame on its bus.
    """

    def __init__(self, leg: LegDrive, od, send) -> None:
        self.leg = leg
        self.node_id = leg.node_id
        self.od = od
        self._send = send
        self.off = True             # not booted yet (bus_no_boot keeps it so)
        self.silent = False         # bus_heartbeat_lost: a pulled cable
        self.tpdo_missing = False   # bus_tpdo_missing
        self.emcy_code = 0
        self.boot_count = 0
        self.reset_values()

    def reset_values(self) -> None:
        """Power-on values: the EDS defaults, the state machine at its start."""
        # lazy: optional: canopen costs 273 ms; the simulated bus runs without it
        from canopen.objectdictionary import ODVariable
        self.values: dict[tuple[int, int], int] = {}
        self.vars = {}
        for obj in self.od.values():
            subs = [obj] if isinstance(obj, ODVariable) else list(obj.values())
            for var in subs:
                self.vars[(var.index, var.subindex)] = var
                default = var.default if var.default is not None else 0
                self.values[(var.index, var.subindex)] = default
        self.nmt = 'INITIALISING'
        self.drive = Cia402Drive()
        self.torque_permille = 0
        self._rpdo = self._tpdo1 = self._tpdo2 = None     # decoded mappings (cob, fmt, keys)
        self._tpdo2_sent = None
        self.heartbeat_ms = 0
        #: how many SYNCs its bus had carried when its last RPDO came (an
        #: RPDO after the newest SYNC: the torque for the cycle it opened)
        self.commanded_after = -1

    # -- frames out ---------------------------------------------------------------------
    def send(self, cob_id: int, data: bytes) -> None:
        if not (self.off or self.silent):
            self._send(cob_id, data)

    def boot(self) -> None:
        """Power on (or NMT reset): the boot-up message, then PRE-OPERATIONAL."""
        self.off = False
        self.reset_values()
        self.boot_count += 1
        self.nmt = 'PRE-OPERATIONAL'
        self.send(0x700 + self.node_id, b'\x00')

    def heartbeat(self) -> None:
        if self.heartbeat_ms:
            self.send(0x700 + self.node_id, bytes([NMT_STATES[self.nmt]]))

    def emcy(self, code: int, register: int) -> None:
        self.values[(0x1001, 0)] = register
        self.send(0x80 + self.node_id, struct.pack('<HB5x', code, register))

    # -- PDO mappings (as the master wrote them) ----------------------------------------------
    def _mapping(self, comm: int, mapping: int):
        cob = self.values.get((comm, 1), 0x80000000)
        if cob & 0x80000000:
            return None
        fmt, keys = '<', []
        for sub in range(1, self.values.get((mapping, 0), 0) + 1):
            entry = self.values[(mapping, sub)]
            key = (entry >> 16, (entry >> 8) & 0xFF)
            var = self.vars.get(key)
            if var is None or PDO_CODES.get(var.data_type) is None:
                return None
            fmt += PDO_CODES[var.data_type]
            keys.append(key)
        return cob & 0x7FF, struct.Struct(fmt), keys, self.values.get((comm, 2), 255)

    def _map_all(self) -> None:
        self._rpdo = self._mapping(0x1400, 0x1600)
        self._tpdo1 = self._mapping(0x1800, 0x1A00)
        self._tpdo2 = self._mapping(0x1801, 0x1A01)

    def _pack(self, mapping) -> bytes:
        _, fmt, keys, _ = mapping
        return fmt.pack(*[self.values[k] for k in keys])

    def _send_tpdo2_if_changed(self) -> None:
        mapping = self._tpdo2
        if self.nmt != 'OPERATIONAL' or mapping is None or mapping[3] < 254:
            return
        data = self._pack(mapping)
        if data != self._tpdo2_sent:
            self._tpdo2_sent = data
            self.send(mapping[0], data)

    # -- frames in ------------------------------------------------------------------------
    def on_nmt(self, command: int) -> None:
        if self.off or self.silent:
            return
        if command == 0x01:
            self.nmt = 'OPERATIONAL'
            self._map_all()
            self._tpdo2_sent = None
            self._sync_state()
        elif command == 0x02:
            self.nmt = 'STOPPED'
        elif command == 0x80:
            self.nmt = 'PRE-OPERATIONAL'
        elif command in (0x81, 0x82):
            self.boot()

    def on_sdo(self, data: bytes) -> None:
        """An SDO request (expedited download or upload)."""
        if self.off or self.silent or self.nmt == 'STOPPED' or len(data) < 8:
            return
        command = data[0] >> 5
        index, sub = struct.unpack_from('<HB', data, 1)
        var = self.vars.get((index, sub))
        reply = 0x580 + self.node_id

        def abort(code):
            self.send(reply, struct.pack('<BHBI', 0x80, index, sub, code))

        if command == 4:        # an abort from the client: nothing to answer
            return
        if var is None:
            return abort(SDO_ABORT_NO_OBJECT)
        if command == 1:        # initiate download
            if not data[0] & 0x02:
                return abort(SDO_ABORT_COMMAND)      # segmented: not needed by this EDS
            size = 4 - ((data[0] >> 2) & 3) if data[0] & 0x01 else 4
            if not var.writable:
                return abort(SDO_ABORT_READ_ONLY)
            if size * 8 != len(var):
                return abort(SDO_ABORT_SIZE)
            self.write(index, sub, var.decode_raw(bytes(data[4:4 + size])))
            self.send(reply, struct.pack('<BHB4x', 0x60, index, sub))
        elif command == 2:      # initiate upload
            if not var.readable:
                return abort(SDO_ABORT_WRITE_ONLY)
            raw = var.encode_raw(self.values[(index, sub)])
            self.send(reply, struct.pack('<BHB', 0x43 | ((4 - len(raw)) << 2), index, sub)
                      + raw.ljust(4, b'\0'))
        else:
            abort(SDO_ABORT_COMMAND)

    def write(self, index: int, sub: int, value: int) -> None:
        """A value written by SDO or RPDO, with its effect on the drive."""
        self.values[(index, sub)] = value
        if index == 0x6040:
            was = self.drive.state
            self.drive.command(value)
            if was == FAULT and self.drive.state != FAULT:
                self.emcy(0x0000, 0x00)         # fault reset: the error reset EMCY
            self._sync_state()
        elif index == 0x6060:
            self.drive.mode = value
            self._sync_state()
        elif index == 0x6071:
            self.torque_permille = value
        elif index == 0x1017:
            self.heartbeat_ms = value

    def _sync_state(self) -> None:
        self.values[(0x6041, 0)] = self.drive.statusword
        self.values[(0x6061, 0)] = self.drive.mode
        self._send_tpdo2_if_changed()

    def on_rpdo(self, data: bytes) -> bool:
        """An RPDO for this drive: its values written; False if it did not act."""
        mapping = self._rpdo
        if self.off or self.silent or self.nmt != 'OPERATIONAL' or mapping is None:
            return False
        _, fmt, keys, _ = mapping
        if len(data) < fmt.size:
            return False
        for key, value in zip(keys, fmt.unpack_from(data)):
            self.write(key[0], key[1], value)
        return True

    @property
    def answers_sync(self) -> bool:
        """Whether this drive sends a TPDO1 at a SYNC now (it is up, and
        operational with a synchronous TPDO1)."""
        mapping = self._tpdo1
        return (not (self.off or self.silent) and self.nmt == 'OPERATIONAL'
                and mapping is not None and 1 <= mapping[3] <= 240)

    # -- each sample ----------------------------------------------------------------------
    def answer_sync(self, length: float, rate: float) -> None:
        """SYNC: the sample's position (less the home offset 0x607C) and
        velocity into 0x6064 / 0x606C, and TPDO1 out (unless a fault keeps it)."""
        values = self.values
        # (the home offset a homing wrote, 0x607C: the zero moved by it)
        values[(0x6064, 0)] = self.leg.counts(length) - values.get(HOME_KEY, 0)
        values[(0x606C, 0)] = self.leg.counts_s(rate)
        mapping = self._tpdo1
        if (self.nmt == 'OPERATIONAL' and mapping is not None and 1 <= mapping[3] <= 240
                and not self.tpdo_missing):
            self.send(mapping[0], self._pack(mapping))

    @property
    def force(self) -> float:
        """The piston force [N] the drive applies now: none unless enabled in mode 10."""
        if self.off or not self.drive.torque_enabled:
            return 0.0
        return self.leg.force(self.torque_permille)

    def fail(self, active: bool) -> None:
        """bus_drive_fault: into FAULT (EMCY) while ``active``; a reset works after."""
        self.drive.fault_active = active
        if active and self.drive.state != FAULT:
            self.drive.fail()
            self.emcy(EMCY_DRIVE_FAULT, 0x01)
            self._sync_state()


class DeviceSet:
    """The six drives on their buses, served from the plant's loop.

    Args:
        config: the device config file (core/machine/bus.py, ``load_bus_config``).
        booted: the legs (0-based) to power on now (the others stay off:
            ``bus_no_boot`` at the run's start).
    """

    def __init__(self, config: BusConfig, booted=range(6)) -> None:
        # lazy: optional: canopen costs 273 ms; the simulated bus runs without it
        import canopen
        self.config = config
        self.buses = {}
        for bus in config.buses:
            self.buses[bus.name] = open_bus(bus.interface, bus.channel, bus.bitrate)
        self.drives: list[Drive] = []
        self.by_bus: dict[str, dict[int, Drive]] = {b.name: {} for b in config.buses}
        for leg in config.legs:
            od = canopen.import_od(leg.eds, leg.node_id)
            bus = self.buses[leg.bus]
            drive = Drive(leg, od, self._sender(bus))
            self.drives.append(drive)
            self.by_bus[leg.bus][leg.node_id] = drive
        self.syncs = {name: 0 for name in self.buses}      # SYNCs received, not yet answered
        self.syncs_seen = {name: 0 for name in self.buses}  # SYNCs received in all
        #: the stamp of the last SYNC received on each bus (None: none yet)
        self.last_sync: dict[str, float | None] = {name: None for name in self.buses}
        #: whether the answers to a SYNC can be armed before it (``s63hub``)
        self.can_arm = can_arm(self.buses.values())
        self.frames_in = 0
        self.frames_out = 0
        self._next_heartbeat = 0.0
        self._last_t = 0.0
        for i in booted:
            self.drives[i].boot()

    def _sender(self, bus):
        def send(cob_id, data):
            bus.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))
            self.frames_out += 1
        return send

    def close(self) -> None:
        for bus in self.buses.values():
            bus.shutdown()

    def poll(self, timeout: float) -> bool:
        """Take every frame that has come (waiting up to ``timeout`` s for
        the first): NMT, SDO and RPDOs act at once, a SYNC is counted for
        ``take_sync``. Returns True when every bus has a SYNC waiting."""
        waited = False
        while True:
            got = False
            for name, bus in self.buses.items():
                msg = bus.recv(0.0)
                while msg is not None:
                    got = True
                    self._dispatch(name, msg)
                    msg = bus.recv(0.0)
            if self.sync_ready() or got or waited or timeout <= 0:
                return self.sync_ready()
            try:
                select.select([b.fileno() for b in self.buses.values()], [], [], timeout)
            except (OSError, NotImplementedError, ValueError):
                time.sleep(min(timeout, 0.001))
            waited = True

    def _dispatch(self, bus: str, msg: can.Message) -> None:
        self.frames_in += 1
        cob = msg.arbitration_id
        data = msg.data
        drives = self.by_bus[bus]
        if cob == 0x080 and not data:
            self.syncs[bus] += 1
            self.syncs_seen[bus] += 1
            self.last_sync[bus] = msg.timestamp
        elif cob == 0x000 and len(data) >= 2:
            targets = drives.values() if data[1] == 0 else [drives.get(data[1])]
            for drive in targets:
                if drive is not None:
                    drive.on_nmt(data[0])
        elif 0x600 < cob < 0x680:
            drive = drives.get(cob - 0x600)
            if drive is not None:
                drive.on_sdo(bytes(data))
        else:
            for drive in drives.values():
                mapping = drive._rpdo
                if mapping is not None and mapping[0] == cob and drive.on_rpdo(bytes(data)):
                    drive.commanded_after = self.syncs_seen[bus]

    def sync_ready(self) -> bool:
        return all(self.syncs.values())

    def take_sync(self) -> None:
        """One SYNC of every bus is being answered."""
        for name in self.syncs:
            self.syncs[name] -= 1

    def next_answer_known(self) -> bool:
        """Whether the answers to the next SYNC are known now (on buses
        that can arm them, ``can_arm``): every bus has had a SYNC and none
        is waiting, and every drive that answers a SYNC has had its RPDO
        since the newest SYNC (the torque the physics steps with until the
        next one)."""
        if any(self.syncs.values()) or None in self.last_sync.values():
            return False
        answering = [d for d in self.drives if d.answers_sync]
        return bool(answering) and all(d.commanded_after == self.syncs_seen[d.leg.bus]
                                       for d in answering)

    def armed_after(self) -> dict:
        """{bus: the stamp of its last SYNC}: for ``batched``, to arm the
        answers for each bus's next SYNC."""
        return {self.buses[name]: stamp for name, stamp in self.last_sync.items()}

    def answer_sync(self, lengths, rates) -> None:
        """Each drive's TPDO1 for the sample (lengths [m], rates [m/s])."""
        for drive in self.drives:
            drive.answer_sync(float(lengths[drive.leg.leg]), float(rates[drive.leg.leg]))

    def heartbeats(self, t: float) -> None:
        """Heartbeats due at time ``t`` [s] (each drive's 0x1017 period): the
        run's time (lockstep) or the monotonic clock (realtime)."""
        if t < self._last_t:        # a new run (the plant's reset): its time from 0
            self._next_heartbeat = t
        self._last_t = t
        if t + 1e-9 < self._next_heartbeat:
            return
        periods = [d.heartbeat_ms for d in self.drives if d.heartbeat_ms]
        if not periods:
            self._next_heartbeat = t
            return
        for drive in self.drives:
            drive.heartbeat()
        self._next_heartbeat = t + min(periods) / 1000.0

    def forces(self) -> list[float]:
        """The six piston forces [N] the drives apply now."""
        return [d.force for d in self.drives]

    def apply_faults(self, active: dict[int, dict[str, float | None]]) -> list[str]:
        """The bus faults acting on this sample, per leg: {leg: {kind: value}}.
        Returns a line per change, for the log."""
        events = []
        for drive in self.drives:
            kinds = active.get(drive.leg.leg, {})
            name = '%s (node %d)' % (drive.leg.name, drive.node_id)
            if 'bus_no_boot' in kinds:
                if not drive.off:
                    drive.off = True
                    events.append('%s: powered off (bus_no_boot)' % name)
            elif drive.off:
                drive.boot()
                events.append('%s: boots' % name)
            silent = 'bus_heartbeat_lost' in kinds
            if silent != drive.silent:
                drive.silent = silent
                if silent:      # its master lost: abort connection (0x6007), no torque
                    drive.drive.command(0x00)
                    drive.values[(0x6041, 0)] = drive.drive.statusword
                events.append('%s: cable %s (bus_heartbeat_lost)'
                              % (name, 'pulled' if silent else 'back'))
            drive.tpdo_missing = 'bus_tpdo_missing' in kinds
            code = int(kinds.get('bus_emcy') or 0)
            if code != drive.emcy_code:
                drive.emcy_code = code
                drive.emcy(code, 0x01 if code else 0x00)
                events.append('%s: EMCY 0x%04X' % (name, code))
            failing = 'bus_drive_fault' in kinds
            if failing != drive.drive.fault_active:
                drive.fail(failing)
                events.append('%s: drive %s' % (name, 'in FAULT' if failing
                                                else 'fault cleared, reset accepted'))
        return events


__all__ = ['Drive', 'DeviceSet', 'open_bus', 'MODE_CST']
