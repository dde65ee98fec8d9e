"""A strict CiA 402 drive on raw CAN frames: a device the bridge's authors did not write.

The plant's drives (stewart63_ros/canbus/devices.py) were written together
with the bridge, and read their object dictionary through the same
``canopen`` library as the master: what one side gets wrong the other may
share. This drive shares nothing with the master. It is written from the
standards on python-can frames alone, with its own EDS reader, and it
refuses what a strict device refuses:

- **NMT** (CiA 301 7.2.8): boot-up in PRE-OPERATIONAL, start, stop,
  pre-operational, reset node (every object to its default), reset
  communication (0x1000-0x1FFF); SDO not in STOPPED, PDOs only in OPERATIONAL.
- **SDO server**, expedited transfers (7.2.4.3), with the abort codes:
  0x06020000 no object, 0x06090011 no sub-index, 0x06010002 read-only,
  0x06010001 write-only, 0x06070010 wrong length, 0x05040001 a command it
  does not serve (segmented, block), 0x06090030 a value out of range,
  0x06040041 an object that cannot be mapped, 0x06040042 a mapping longer
  than 64 bits, 0x08000022 a PDO remapped while it exists.
- **PDO rules** (7.5.2.35-38): while a PDO exists (COB-ID bit 31 clear)
  bits 0-29 of its COB-ID stay, its inhibit time stays and its mapping is
  not written; a mapping entry is written only while the count is 0; the
  count is checked against the entries; restricted COB-IDs are refused.
- **SYNC**: TPDOs of type 1..240 sampled at every n-th SYNC and sent
  ``sync_delay`` s later (late on purpose, within the SYNC window 0x1007: one
  later than the window is dropped, as CiA 301 says); type 0 on change at a
  SYNC; 254/255 on change (and by event timer). RPDOs of a synchronous type
  act at the next SYNC, 254/255 at once; a short RPDO is not processed
  (EMCY 0x8210).
- **Heartbeat** producer 0x1017 on the wall clock; **EMCY** 0x1014.
- **CiA 402 state machine** (CiA 402-2 fig. 8, table 28): SWITCH ON DISABLED
  -> READY TO SWITCH ON -> SWITCHED ON -> OPERATION ENABLED, quick stop,
  FAULT REACTION ACTIVE (``fault_reaction_s``) -> FAULT, fault reset (a
  rising edge of bit 7) only in FAULT and only once the cause is gone.
  Modes of operation 0x6060 limited to those 0x6502 lists.

The physics is a protocol peer's, not the plant's: the position integrates
``velocity`` (counts/s) between SYNCs; the torque actual value 0x6077 is the
target torque while enabled in mode 10.

``DriveRack`` serves drives on one python-can bus in a thread of its own.
Only the suite uses it (the rig's plant models the dynamics; this models
the standard), so it lives in test/, with its EDS test/cia402_drive.eds.
"""
from __future__ import annotations

import configparser
import dataclasses
import heapq
import struct
import threading
import time

import can

# -- the EDS -------------------------------------------------------------------------
#: data type -> (struct code): BOOLEAN, INTEGER8/16/32, UNSIGNED8/16/32
TYPES = {0x1: '?', 0x2: 'b', 0x3: 'h', 0x4: 'i', 0x5: 'B', 0x6: 'H', 0x7: 'I'}


@dataclasses.dataclass
class Entry:
    """One object (index, sub-index) of the dictionary, as its EDS says."""
    name: str
    data_type: int
    access: str
    default: int
    mappable: bool

    @property
    def layout(self) -> struct.Struct:
        return struct.Struct('<' + TYPES[self.data_type])

    @property
    def bits(self) -> int:
        return 8 * self.layout.size

    @property
    def readable(self) -> bool:
        return self.access != 'wo'

    @property
    def writable(self) -> bool:
        return self.access in ('rw', 'wo', 'rww', 'rwr')


def _number(text: str, node_id: int) -> int:
    text = text.strip().upper().replace('$NODEID', '%d' % node_id)
    return sum(int(part, 0) for part in text.split('+')) if text else 0


def read_eds(path, node_id: int) -> dict[tuple[int, int], Entry]:
    """The object dictionary of an EDS (CiA 306): {(index, sub-index): Entry};
    a plain variable is sub-index 0. Types beyond UNSIGNED32 are left out
    (nothing here needs a segmented transfer)."""
    eds = configparser.ConfigParser(interpolation=None, strict=False)
    eds.optionxform = str.lower
    eds.read(path)
    out = {}
    for section in eds.sections():
        head = section.lower()
        try:
            index = int(head[:4], 16)
        except ValueError:
            continue
        sub = int(head[7:], 16) if head[4:7] == 'sub' else 0 if len(head) == 4 else None
        fields = eds[section]
        if sub is None or 'datatype' not in fields:
            continue
        data_type = int(fields['datatype'], 0)
        if data_type not in TYPES:
            continue
        out[(index, sub)] = Entry(fields.get('parametername', ''), data_type,
                                  fields.get('accesstype', 'rw').lower(),
                                  _number(fields.get('defaultvalue', '0'), node_id),
                                  fields.get('pdomapping', '0').strip() == '1')
    return out


# -- the standards' numbers ---------------------------------------------------------------
ABORT_COMMAND = 0x05040001
ABORT_WRITE_ONLY = 0x06010001
ABORT_READ_ONLY = 0x06010002
ABORT_NO_OBJECT = 0x06020000
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_LENGTH = 0x06040042
ABORT_LENGTH = 0x06070010
ABORT_NO_SUBINDEX = 0x06090011
ABORT_VALUE = 0x06090030
ABORT_STATE = 0x08000022
INVALID = 1 << 31
NMT_BYTE = {'PRE-OPERATIONAL': 0x7F, 'OPERATIONAL': 0x05, 'STOPPED': 0x04}
EMCY_PDO_LENGTH = 0x8210
#: COB-IDs a PDO may not use (CiA 301 7.3.5: NMT, SYNC/EMCY, TIME, SDO, heartbeat, LSS)
RESTRICTED = ([range(0x000, 0x080), range(0x101, 0x181), range(0x581, 0x600),
               range(0x601, 0x680), range(0x6E0, 0x700), range(0x701, 0x800)])
SOD, RTSO, SO, OE = ('SWITCH ON DISABLED', 'READY TO SWITCH ON', 'SWITCHED ON',
                     'OPERATION ENABLED')
QSA, FRA, FAULT = 'QUICK STOP ACTIVE', 'FAULT REACTION ACTIVE', 'FAULT'
#: statusword per state (CiA 402-2 table 30; bit 4 voltage enabled, bit 9 remote,
#: bit 5 quick stop off): other bits than a master's masks look at, on purpose
STATUSWORD = {SOD: 0x0240, RTSO: 0x0231, SO: 0x0233, OE: 0x0237, QSA: 0x0217,
              FRA: 0x021F, FAULT: 0x0218}
MODE_CST = 10


def _pdo_kind(index: int) -> str | None:
    if 0x1400 <= index < 0x1600 or 0x1800 <= index < 0x1A00:
        return 'comm'
    if 0x1600 <= index < 0x1800 or 0x1A00 <= index < 0x1C00:
        return 'mapping'
    return None


class Refused(Exception):
    """An SDO request aborted with ``code``."""

    def __init__(self, code: int) -> None:
        super().__init__('0x%08X' % code)
        self.code = code


def check_write(od: dict, values: dict, index: int, sub: int, value: int) -> None:
    """What CiA 301 and 402 forbid to write: raises Refused with the abort code."""
    kind = _pdo_kind(index)
    if kind == 'comm':
        comm = index
        valid = not values[(comm, 1)] & INVALID
        if sub == 1:
            if valid and (value ^ values[(comm, 1)]) & 0x3FFFFFFF:
                raise Refused(ABORT_VALUE)      # bits 0-29 stay while it exists
            if value & (1 << 29) or not value & INVALID and any(
                    value & 0x7FF in r for r in RESTRICTED):
                raise Refused(ABORT_VALUE)      # 29-bit ids; restricted COB-IDs
        elif sub == 2:
            allowed = value <= 240 or value in (254, 255)
            if not allowed:
                raise Refused(ABORT_VALUE)      # reserved; RTR-only types unsupported
        elif sub == 3 and valid:
            raise Refused(ABORT_STATE)          # inhibit time stays while it exists
    elif kind == 'mapping':
        comm = index - 0x200
        if not values[(comm, 1)] & INVALID:
            raise Refused(ABORT_STATE)          # remapped while the PDO exists
        if sub == 0:
            _check_mapping(od, values, index, value)
        elif values[(index, 0)] != 0:
            raise Refused(ABORT_STATE)          # entries only while the count is 0
        elif value:
            _mappable(od, index, value)
    elif index == 0x6060 and not (1 <= value <= 10
                                  and values.get((0x6502, 0), 0) >> (value - 1) & 1):
        raise Refused(ABORT_VALUE)              # a mode 0x6502 does not list
    elif index == 0x1005 and value & (1 << 30):
        raise Refused(ABORT_VALUE)              # a SYNC consumer only

def _mappable(od: dict, mapping: int, entry_value: int) -> Entry:
    key = (entry_value >> 16, entry_value >> 8 & 0xFF)
    entry = od.get(key)
    receive = mapping < 0x1A00
    if entry is None or not entry.mappable or entry.bits != entry_value & 0xFF or (
            not entry.writable if receive else not entry.readable):
        raise Refused(ABORT_NOT_MAPPABLE)
    return entry

def _check_mapping(od: dict, values: dict, mapping: int, count: int) -> None:
    bits = 0
    for sub in range(1, count + 1):
        if (mapping, sub) not in od:
            raise Refused(ABORT_PDO_LENGTH)
        bits += _mappable(od, mapping, values[(mapping, sub)]).bits
    if bits > 64:
        raise Refused(ABORT_PDO_LENGTH)


class StrictDrive:
    """One drive (see the module's doc).

    Args:
        eds: its EDS file.
        node_id: 1..127.
        send: ``send(cob_id, data)`` puts a frame on the bus.
        sync_delay: s from a SYNC to its TPDOs (late on purpose).
        read_only: {(index, sub)} its firmware will not let a master write,
            whatever the EDS says (a fixed PDO).
        fault_reaction_s: how long FAULT REACTION ACTIVE lasts.
        clock: the time [s] (monotonic).
    """

    def __init__(self, eds, node_id: int, send, sync_delay: float = 0.0, read_only=(),
                 fault_reaction_s: float = 0.01, clock=time.monotonic) -> None:
        self.od = read_eds(eds, node_id)
        self.indices = {index for index, _ in self.od}
        for key in read_only:
            self.od[key] = dataclasses.replace(self.od[key], access='ro')
        self.node_id = node_id
        self._send = send
        self.sync_delay = sync_delay
        self.fault_reaction_s = fault_reaction_s
        self.clock = clock
        self.velocity = 0           # counts/s: the position integrates it
        self.position = 0.0         # counts
        self.fault_cause = False    # a fault reset is refused while True
        self.frames_out = 0
        self.aborts: list[tuple[int, int, int]] = []    # (index, sub, code), newest last
        self.powered = False
        self.power_on()

    # -- power, NMT --------------------------------------------------------------------
    def power_on(self) -> None:
        self.values = {key: entry.default for key, entry in self.od.items()}
        self._reset_communication()
        self.state = SOD
        self._last_cw = 0
        self._fra_until = None
        self._update()
        self._boot()

    def _reset_communication(self) -> None:
        for key, entry in self.od.items():
            if key[0] < 0x2000:
                self.values[key] = entry.default
        self.nmt = 'PRE-OPERATIONAL'
        self._queue: list[tuple[float, int, int, bytes]] = []     # (due, n, cob, data)
        self._n = 0
        self._sync_count: dict[int, int] = {}
        self._sent: dict[int, bytes] = {}
        self._held: dict[int, bytes] = {}      # synchronous RPDOs until the SYNC
        self._next_beat = None
        self._next_event: dict[int, float] = {}
        self._last_sync = None

    def _boot(self) -> None:
        self.powered = True
        self.send(0x700 + self.node_id, b'\x00')

    def send(self, cob_id: int, data: bytes) -> None:
        self.frames_out += 1
        self._send(cob_id, bytes(data))

    def on_nmt(self, data: bytes) -> None:
        if len(data) != 2 or data[1] not in (0, self.node_id):
            return
        command = data[0]
        if command == 0x01:
            was = self.nmt
            self.nmt = 'OPERATIONAL'
            if was != 'OPERATIONAL':
                self._sent.clear()          # event-driven TPDOs: their first event now
                self._events()
        elif command == 0x02:
            self.nmt = 'STOPPED'
        elif command == 0x80:
            self.nmt = 'PRE-OPERATIONAL'
        elif command == 0x81:
            self.power_on()
        elif command == 0x82:
            self._reset_communication()
            self._boot()

    # -- frames in ------------------------------------------------------------------------
    def receive(self, cob_id: int, data: bytes, now: float) -> None:
        """A frame from the bus."""
        if cob_id == 0x000:
            self.on_nmt(data)
        elif self.nmt == 'STOPPED':
            return
        elif cob_id == 0x600 + self.node_id:
            self.on_sdo(data)
        elif self.nmt != 'OPERATIONAL':
            return
        elif cob_id == self.values[(0x1005, 0)] & 0x7FF and len(data) <= 1:
            self.on_sync(now)
        else:
            for comm in self._valid_pdos(0x1400):
                if self.values[(comm, 1)] & 0x7FF == cob_id:
                    self.on_rpdo(comm, data)

    def on_sdo(self, data: bytes) -> None:
        if len(data) != 8:
            return
        command = data[0] >> 5
        index, sub = struct.unpack_from('<HB', data, 1)
        if command == 4:            # the client aborted: nothing to answer
            return
        try:
            if command == 1:
                self._download(data, index, sub)
                self.send(0x580 + self.node_id, struct.pack('<BHB4x', 0x60, index, sub))
            elif command == 2:
                raw = self._upload(index, sub)
                self.send(0x580 + self.node_id, struct.pack('<BHB', 0x43 | (4 - len(raw)) << 2,
                                                            index, sub) + raw.ljust(4, b'\0'))
            else:
                raise Refused(ABORT_COMMAND)
        except Refused as exc:
            self.aborts.append((index, sub, exc.code))
            self.send(0x580 + self.node_id, struct.pack('<BHBI', 0x80, index, sub, exc.code))

    def _entry(self, index: int, sub: int) -> Entry:
        entry = self.od.get((index, sub))
        if entry is None:
            raise Refused(ABORT_NO_OBJECT if index not in self.indices else ABORT_NO_SUBINDEX)
        return entry

    def _upload(self, index: int, sub: int) -> bytes:
        entry = self._entry(index, sub)
        if not entry.readable:
            raise Refused(ABORT_WRITE_ONLY)
        return entry.layout.pack(self.values[(index, sub)])

    def _download(self, data: bytes, index: int, sub: int) -> None:
        if not data[0] & 0x02:
            raise Refused(ABORT_COMMAND)        # segmented: no object here needs it
        entry = self._entry(index, sub)
        if not entry.writable:
            raise Refused(ABORT_READ_ONLY)
        size = 4 - (data[0] >> 2 & 3) if data[0] & 0x01 else entry.layout.size
        if size != entry.layout.size:
            raise Refused(ABORT_LENGTH)
        value = entry.layout.unpack_from(data, 4)[0]
        if _pdo_kind(index) == 'mapping' and self.nmt == 'OPERATIONAL':
            raise Refused(ABORT_STATE)      # (stricter than CiA 301, as many drives are)
        check_write(self.od, self.values, index, sub, value)
        self.write(index, sub, value)

    def write(self, index: int, sub: int, value: int) -> None:
        """A value written by SDO or RPDO, with its effect."""
        self.values[(index, sub)] = value
        if index == 0x6040:
            self.command(value)
        elif index == 0x6060:
            self.values[(0x6061, 0)] = value
        elif index == 0x1017:
            self._next_beat = self.clock() + value / 1000.0 if value else None
        self._update()

    def on_rpdo(self, comm: int, data: bytes, at_sync: bool = False) -> None:
        keys = self._mapped(comm + 0x200)
        layout = struct.Struct('<' + ''.join(TYPES[self.od[k].data_type] for k in keys))
        if len(data) < layout.size:
            self.emcy(EMCY_PDO_LENGTH, 0x10)        # not processed: length error
            return
        if self.values[(comm, 2)] <= 240 and not at_sync:
            self._held[comm] = bytes(data)          # acts at the next SYNC
            return
        for key, value in zip(keys, layout.unpack_from(data)):
            self.write(key[0], key[1], value)

    def on_sync(self, now: float) -> None:
        if self._last_sync is not None:             # the trivial physics
            self.position += self.velocity * (now - self._last_sync)
        self._last_sync = now
        held, self._held = self._held, {}
        for comm, data in held.items():
            self.on_rpdo(comm, data, at_sync=True)
        self._update()
        window = self.values.get((0x1007, 0), 0) / 1e6
        for comm in self._valid_pdos(0x1800):
            kind = self.values[(comm, 2)]
            if kind > 240:
                continue
            data = self._pack(comm)
            if kind == 0:
                if data == self._sent.get(comm):
                    continue
            else:
                count = self._sync_count.get(comm, 0) + 1
                self._sync_count[comm] = count
                if count % kind:
                    continue
            if window and self.sync_delay > window:
                continue                            # past the window: dropped
            self._sent[comm] = data
            self._later(now + self.sync_delay, self.values[(comm, 1)] & 0x7FF, data)

    # -- state ----------------------------------------------------------------------
    def command(self, cw: int) -> None:
        """Controlword 0x6040 (CiA 402-2 table 28)."""
        self._transition(cw)
        self._update()

    def _transition(self, cw: int) -> None:
        rising_reset = cw & 0x80 and not self._last_cw & 0x80
        self._last_cw = cw
        state = self.state
        if state == FAULT:
            if rising_reset and not self.fault_cause:
                self.state = SOD
                self.emcy(0x0000, 0x00)             # error reset
            return
        if state == FRA:
            return                                  # no command acts here
        if not cw & 0x02:                           # disable voltage
            self.state = SOD
        elif not cw & 0x04:                         # quick stop
            self.state = QSA if state == OE else SOD
        elif cw & 0x8F == 0x06 and state in (SOD, SO, OE):
            self.state = RTSO                       # shutdown (2, 6, 8)
        elif cw & 0x8F == 0x07 and state in (RTSO, OE):
            self.state = SO                         # switch on (3), disable operation (5)
        elif cw & 0x8F == 0x0F and state in (RTSO, SO, QSA):
            self.state = OE                         # enable operation (4; 3 + 4; 16)

    def fail(self, code: int = 0x5000) -> None:
        """An internal fault: FAULT REACTION ACTIVE, then FAULT; reset refused
        until ``fault_cause`` is cleared."""
        self.fault_cause = True
        self.state = FRA
        self._fra_until = self.clock() + self.fault_reaction_s
        self.emcy(code, 0x01)
        self._update()

    def emcy(self, code: int, register: int) -> None:
        self.values[(0x1001, 0)] = register
        cob = self.values.get((0x1014, 0), 0x80 + self.node_id)
        if self.nmt != 'STOPPED' and not cob & INVALID:
            self.send(cob & 0x7FF, struct.pack('<HB5x', code, register))

    def _update(self) -> None:
        values = self.values
        values[(0x6041, 0)] = STATUSWORD[self.state]
        values[(0x6064, 0)] = int(round(self.position)) - values.get((0x607C, 0), 0)
        values[(0x606C, 0)] = int(self.velocity)
        enabled = self.state == OE and values.get((0x6061, 0)) == MODE_CST
        values[(0x6077, 0)] = values.get((0x6071, 0), 0) if enabled else 0
        self._events()

    # -- PDOs ------------------------------------------------------------------------
    def _valid_pdos(self, base: int):
        return [i for i in range(base, base + 0x200)
                if (i, 1) in self.values and not self.values[(i, 1)] & INVALID]

    def _mapped(self, mapping: int) -> list[tuple[int, int]]:
        return [(e >> 16, e >> 8 & 0xFF) for e in
                (self.values[(mapping, s)] for s in range(1, self.values[(mapping, 0)] + 1))]

    def _pack(self, comm: int) -> bytes:
        keys = self._mapped(comm + 0x200)
        return b''.join(self.od[k].layout.pack(self.values[k]) for k in keys)

    def _events(self) -> None:
        """Event-driven TPDOs (254/255) whose data changed: out now."""
        if self.nmt != 'OPERATIONAL':
            return
        for comm in self._valid_pdos(0x1800):
            if self.values[(comm, 2)] >= 254:
                data = self._pack(comm)
                if data != self._sent.get(comm):
                    self._sent[comm] = data
                    self.send(self.values[(comm, 1)] & 0x7FF, data)

    def _later(self, due: float, cob: int, data: bytes) -> None:
        self._n += 1
        heapq.heappush(self._queue, (due, self._n, cob, data))

    # -- time -------------------------------------------------------------------------
    def tick(self, now: float) -> float:
        """What is due at ``now``; returns when the next thing is due."""
        while self._queue and self._queue[0][0] <= now:
            _, _, cob, data = heapq.heappop(self._queue)
            if self.nmt == 'OPERATIONAL':
                self.send(cob, data)
        if self._fra_until is not None and now >= self._fra_until:
            self._fra_until = None
            self.state = FAULT
            self._update()
        period = self.values.get((0x1017, 0), 0) / 1000.0
        if self._next_beat is not None and now >= self._next_beat:
            self.send(0x700 + self.node_id, bytes([NMT_BYTE[self.nmt]]))
            self._next_beat = max(self._next_beat + period, now)
        if self.nmt == 'OPERATIONAL':
            for comm in self._valid_pdos(0x1800):
                timer = self.values.get((comm, 5), 0) / 1000.0
                if timer and self.values[(comm, 2)] >= 254:
                    due = self._next_event.setdefault(comm, now + timer)
                    if now >= due:
                        self.send(self.values[(comm, 1)] & 0x7FF, self._pack(comm))
                        self._next_event[comm] = now + timer
        dues = [self._queue[0][0]] if self._queue else []
        dues += [t for t in (self._fra_until, self._next_beat) if t is not None]
        dues += list(self._next_event.values())
        return min(dues, default=now + 0.1)


class DriveRack:
    """Strict drives on one python-can bus, served by a thread of their own.

    Args:
        bus: the python-can bus (its own connection to the channel).
        drives: ``{node_id: dict(sync_delay=..., read_only=...)}``.
        eds: the EDS of every drive.
    """

    def __init__(self, bus: can.BusABC, drives: dict[int, dict], eds) -> None:
        self.bus = bus
        self.lock = threading.RLock()
        self.drives = {node: StrictDrive(eds, node, self._send, **options)
                       for node, options in drives.items()}
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True,
                                       name='cia402-rack-%s' % bus.channel_info)
        self.thread.start()

    def _send(self, cob_id: int, data: bytes) -> None:
        self.bus.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))

    def _serve(self) -> None:
        due = time.monotonic()
        while not self._stop.is_set():
            msg = self.bus.recv(max(0.0, min(0.01, due - time.monotonic())))
            now = time.monotonic()
            with self.lock:
                if msg is not None and not msg.is_error_frame and not msg.is_remote_frame \
                        and not msg.is_extended_id:
                    for drive in self.drives.values():
                        drive.receive(msg.arbitration_id, bytes(msg.data), now)
                due = min(drive.tick(now) for drive in self.drives.values())

    def stop(self) -> None:
        """The drives go quiet (the bus stays open)."""
        self._stop.set()
        self.thread.join(5)

    def close(self) -> None:
        self.stop()
        self.bus.shutdown()
