"""The field bus's arithmetic: bus load, scaling, the CiA 402 state machine,
and the device config file (docs/bus.md). No ROS, no CAN library.

- **Bus load**: the bits of a classic CAN data frame with worst-case bit
  stuffing (``frame_bits``), the frames one sample cycle puts on a bus
  (``cycle_frames``) and the share of the bitrate they take
  (``BusLoad``); a configuration over 100 % is refused with the rates that fit.
- **Scaling**: encoder counts <-> metres (per leg: scale, offset,
  direction), piston force [N] <-> target torque in per mille of the rated
  torque (lead, gear ratio, efficiency).
- **CiA 402**: the drive states read from a statusword, the controlword that
  takes a drive one step towards *operation enabled* (the master's side), and
  the state machine a drive follows (the device's side, ``Cia402Drive``).
- **Config**: ``load_bus_config`` reads config/canopen.yaml (buses, and per
  leg: bus, node id, EDS, scaling, actuator) and refuses what cannot work.
"""
from __future__ import annotations

import dataclasses
import difflib
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from stewart63_ros.core.plumbing.legs import LEG_NAMES
from stewart63_ros.paths import default_params_path

# -- bus load ------------------------------------------------------------------------
#: bits of a standard (11-bit id) data frame outside the data field that are
#: stuffed: SOF, id, RTR, IDE, r0, DLC, CRC (Davis et al. 2007, eq. 4)
STUFFED_OVERHEAD = 34
#: bits that are never stuffed: CRC delimiter, ACK slot and delimiter, EOF, intermission
FIXED_OVERHEAD = 13
#: the bitrates of classic CAN a lab can set (bit/s)
STANDARD_BITRATES = (125_000, 250_000, 500_000, 800_000, 1_000_000)


def frame_bits(data_bytes: int) -> int:
    """Bits a standard classic CAN data frame takes on the wire, worst-case
    stuffing included (one stuff bit per four of the stuffed part).

    Args:
        data_bytes: bytes in the data field, 0 to 8.

    Returns:
        47 + 8 n + floor((34 + 8 n - 1) / 4): 55 bits for a SYNC, 135 for 8 bytes.

    Raises:
        ValueError: ``data_bytes`` outside 0..8.
    """
    if not 0 <= data_bytes <= 8:
        raise ValueError('a classic CAN frame carries 0 to 8 bytes, not %r' % (data_bytes,))
    stuffed = STUFFED_OVERHEAD + 8 * data_bytes
    return stuffed + FIXED_OVERHEAD + (stuffed - 1) // 4


def cycle_frames(drives: int, rpdo_bytes: int, tpdo_bytes: int) -> list[tuple[str, int]]:
    """The frames one sample cycle puts on one bus: a SYNC, then per drive
    its RPDO (controlword and target torque) and its synchronous TPDO
    (position and velocity).

    Args:
        drives: drives on the bus.
        rpdo_bytes, tpdo_bytes: data bytes of each.

    Returns:
        [(what, data bytes)], one entry per frame.
    """
    return ([('SYNC', 0)] + [('RPDO', rpdo_bytes)] * drives + [('TPDO', tpdo_bytes)] * drives)


@dataclasses.dataclass(frozen=True)
class BusLoad:
    """The load one configuration puts on one bus.

    Attributes:
        bus: the bus's name.
        frames: frames per cycle.
        bits: bits per cycle (worst-case stuffing).
        rate: cycles per second [Hz].
        bitrate: the bus's bitrate [bit/s].
        background_bits_s: bits per second besides the cycle (heartbeats).
    """
    bus: str
    frames: int
    bits: int
    rate: float
    bitrate: int
    background_bits_s: float = 0.0

    @property
    def bits_per_second(self) -> float:
        """Bits a second on the bus: the cycles' and the background's."""
        return self.bits * self.rate + self.background_bits_s

    @property
    def percent(self) -> float:
        """Per cent of the bitrate the configuration takes."""
        return 100.0 * self.bits_per_second / self.bitrate

    def max_rate(self) -> float:
        """The highest sample rate [Hz] this bus carries at its bitrate."""
        return max(0.0, (self.bitrate - self.background_bits_s) / self.bits)

    def min_bitrate(self) -> int | None:
        """The lowest standard bitrate that carries this rate, None if none does."""
        for bitrate in STANDARD_BITRATES:
            if self.bits_per_second <= bitrate:
                return bitrate
        return None

    def text(self) -> str:
        """One line: frames, bits, rate, kbit/s and per cent of the bitrate."""
        return ('bus %s: %d frames a cycle, %d bits (worst-case stuffing) at %g Hz = '
                '%.0f kbit/s, %.1f %% of %g kbit/s' % (
                    self.bus, self.frames, self.bits, self.rate, self.bits_per_second / 1e3,
                    self.percent, self.bitrate / 1e3))


class BusLoadError(ValueError):
    """A configuration the bus cannot carry; the message says why and what fits."""


def check_load(loads: list[BusLoad]) -> None:
    """Refuse a configuration that puts more than 100 % on any bus.

    Args:
        loads: one BusLoad per bus.

    Raises:
        BusLoadError: naming the bus, its load, the highest rate it carries
            at its bitrate and the lowest bitrate that carries the rate.
    """
    for load in loads:
        if load.percent > 100.0:
            faster = load.min_bitrate()
            raise BusLoadError(
                '%s: over 100 %%, refused. At %g kbit/s it carries at most %.0f Hz; %s; '
                'or split the drives over more buses (docs/bus.md, "Bus load")' % (
                    load.text(), load.bitrate / 1e3, math.floor(load.max_rate()),
                    'at %g Hz it needs %g kbit/s' % (load.rate, faster / 1e3) if faster
                    else 'no classic CAN bitrate carries %g Hz' % load.rate))


def heartbeat_bits_s(devices: int, heartbeat_ms: float) -> float:
    """Bits per second the heartbeats of ``devices`` take (one byte each).

    Args:
        devices: heartbeat producers on the bus.
        heartbeat_ms: their period [ms]; 0: none.

    Returns:
        bit/s.
    """
    return devices * frame_bits(1) * 1000.0 / heartbeat_ms if heartbeat_ms > 0 else 0.0


# -- scaling ---------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class LegDrive:
    """One leg's device on the bus and how its numbers become SI.

    Attributes:
        leg: 0-based leg index.
        bus: the name of the bus it is on.
        node_id: its CANopen node id (1..127).
        eds: path of its EDS/DCF file.
        metres_per_count: length per encoder count [m] (> 0).
        offset_m: the leg length at count 0 [m].
        direction: +1 or -1: counts grow with the length, or shrink.
        lead_m: screw lead [m per motor-side revolution of the screw].
        gear_ratio: motor revolutions per screw revolution.
        efficiency: of screw and gear, (0, 1].
        rated_torque_mnm: the drive's rated torque 0x6076 [mN m].
    """
    leg: int
    bus: str
    node_id: int
    eds: str
    metres_per_count: float
    offset_m: float
    direction: int
    lead_m: float
    gear_ratio: float
    efficiency: float
    rated_torque_mnm: int

    @property
    def name(self) -> str:
        """The leg's name (leg_1 ... leg_6)."""
        return LEG_NAMES[self.leg]

    def metres(self, counts: int) -> float:
        """Leg length [m] from the position actual value [counts]."""
        return self.offset_m + self.direction * self.metres_per_count * counts

    def metres_per_second(self, counts_s: int) -> float:
        """Leg rate [m/s] from the velocity actual value [counts/s]."""
        return self.direction * self.metres_per_count * counts_s

    def counts(self, metres: float) -> int:
        """Position actual value [counts] for a leg length [m] (the device's
        side: the encoder's resolution rounds it)."""
        return int(round(self.direction * (metres - self.offset_m) / self.metres_per_count))

    def counts_s(self, metres_s: float) -> int:
        """Velocity actual value [counts/s] for a leg rate [m/s]."""
        return int(round(self.direction * metres_s / self.metres_per_count))

    def home_offset_counts(self, metres: float) -> int:
        """Home offset 0x607C [counts] that takes ``metres`` (a homing's
        offset: reading minus true length) off the position actual value: the
        drive reports its position minus this (CiA 402: the zero is the home
        position moved by the home offset).

        Args:
            metres: the offset found for this leg [m].

        Returns:
            The counts to write, rounded to the encoder's resolution.
        """
        return int(round(self.direction * metres / self.metres_per_count))

    @property
    def newtons_per_nm(self) -> float:
        """Piston force [N] per motor torque [N m]: 2 pi gear efficiency / lead."""
        return 2.0 * math.pi * self.gear_ratio * self.efficiency / self.lead_m

    def permille(self, force_n: float) -> int:
        """Target torque 0x6071 [per mille of rated torque] for a piston force
        [N] (along the leg, extending positive), clamped to INTEGER16. The
        direction applies as for the length: a drive whose counts shrink as
        the leg extends pushes the leg out with negative torque."""
        torque_nm = self.direction * force_n / self.newtons_per_nm
        value = int(round(1000.0 * torque_nm * 1000.0 / self.rated_torque_mnm))
        return max(-32768, min(32767, value))

    def force(self, permille: int) -> float:
        """Piston force [N] a drive applies at target torque ``permille``."""
        torque_nm = permille * self.rated_torque_mnm / 1.0e6
        return self.direction * torque_nm * self.newtons_per_nm

    @property
    def force_step_n(self) -> float:
        """The force of one per mille [N]: the command's resolution."""
        return self.rated_torque_mnm / 1.0e6 * self.newtons_per_nm


# -- CiA 402 ---------------------------------------------------------------------------
NOT_READY = 'NOT READY TO SWITCH ON'
SWITCH_ON_DISABLED = 'SWITCH ON DISABLED'
READY_TO_SWITCH_ON = 'READY TO SWITCH ON'
SWITCHED_ON = 'SWITCHED ON'
OPERATION_ENABLED = 'OPERATION ENABLED'
QUICK_STOP_ACTIVE = 'QUICK STOP ACTIVE'
FAULT_REACTION_ACTIVE = 'FAULT REACTION ACTIVE'
FAULT = 'FAULT'
#: (mask, value, state) of the statusword, CiA 402-2 table 30
STATUSWORD_STATES = (
    (0x4F, 0x00, NOT_READY), (0x4F, 0x40, SWITCH_ON_DISABLED), (0x6F, 0x21, READY_TO_SWITCH_ON),
    (0x6F, 0x23, SWITCHED_ON), (0x6F, 0x27, OPERATION_ENABLED), (0x6F, 0x07, QUICK_STOP_ACTIVE),
    (0x4F, 0x0F, FAULT_REACTION_ACTIVE), (0x4F, 0x08, FAULT))
#: the statusword a drive reports in each state (bit 9 remote, bit 5 quick stop off)
STATUSWORDS = {NOT_READY: 0x0200, SWITCH_ON_DISABLED: 0x0240, READY_TO_SWITCH_ON: 0x0221,
               SWITCHED_ON: 0x0223, OPERATION_ENABLED: 0x0227, QUICK_STOP_ACTIVE: 0x0207,
               FAULT_REACTION_ACTIVE: 0x020F, FAULT: 0x0208}
CW_DISABLE_VOLTAGE, CW_SHUTDOWN, CW_SWITCH_ON, CW_ENABLE = 0x00, 0x06, 0x07, 0x0F
#: disable operation: OPERATION ENABLED -> SWITCHED ON (the same bits as switch on)
CW_DISABLE_OPERATION = 0x07
CW_FAULT_RESET = 0x80
#: modes of operation 0x6060: cyclic synchronous torque
MODE_CST = 10


def drive_state(statusword: int) -> str:
    """The CiA 402 state a statusword 0x6041 reports.

    Args:
        statusword: the 16-bit statusword.

    Returns:
        One of the state names (``NOT_READY`` ... ``FAULT``).
    """
    for mask, value, state in STATUSWORD_STATES:
        if statusword & mask == value:
            return state
    return NOT_READY


def next_controlword(state: str, last: int) -> int:
    """The master's controlword that takes a drive one step towards
    OPERATION ENABLED (shutdown, switch on, enable; from FAULT a fault
    reset, which acts on a rising edge of bit 7: after one, a 0 first).
    In FAULT REACTION ACTIVE the drive is still reacting (braking, say) and
    takes no controlword: no fault reset then (it would be a rising edge
    the drive ignores, or acts on too early), disable voltage (0x00), so the
    reset that follows in FAULT is a rising edge.

    Args:
        state: the drive's state (``drive_state``).
        last: the controlword sent last.

    Returns:
        The controlword to send now.
    """
    if state == FAULT:
        return CW_DISABLE_VOLTAGE if last & CW_FAULT_RESET else CW_FAULT_RESET
    if state == FAULT_REACTION_ACTIVE:
        return CW_DISABLE_VOLTAGE
    return {SWITCH_ON_DISABLED: CW_SHUTDOWN, READY_TO_SWITCH_ON: CW_SWITCH_ON,
            SWITCHED_ON: CW_ENABLE, OPERATION_ENABLED: CW_ENABLE,
            QUICK_STOP_ACTIVE: CW_DISABLE_VOLTAGE}.get(state, CW_DISABLE_VOLTAGE)


class Cia402Drive:
    """The device side of the CiA 402 state machine (CiA 402-2 fig. 8), as
    far as a torque-controlled drive needs it.

    A drive starts in SWITCH ON DISABLED (its NOT READY phase is over once
    it has booted). ``command(controlword)`` applies the master's
    controlword; ``fail()`` puts it in FAULT, where it stays until a fault
    reset comes while ``fault_active`` is False. Torque acts only in
    OPERATION ENABLED with mode 10 (``torque_enabled``).
    """

    def __init__(self) -> None:
        self.state = SWITCH_ON_DISABLED
        self.mode = 0
        self.fault_active = False
        self._last = 0

    @property
    def statusword(self) -> int:
        """The statusword 0x6041 of the drive's state."""
        return STATUSWORDS[self.state]

    @property
    def torque_enabled(self) -> bool:
        """Whether the drive applies its target torque (enabled, mode 10)."""
        return self.state == OPERATION_ENABLED and self.mode == MODE_CST

    def fail(self) -> None:
        """An internal fault: FAULT, held while ``fault_active``."""
        self.state = FAULT

    def command(self, controlword: int) -> None:
        """Apply controlword 0x6040 (the transitions of CiA 402-2 table 28)."""
        rising_reset = controlword & CW_FAULT_RESET and not self._last & CW_FAULT_RESET
        self._last = controlword
        state = self.state
        if state == FAULT_REACTION_ACTIVE:     # reacting: no controlword acts until FAULT
            return
        if state == FAULT:
            if rising_reset and not self.fault_active:
                self.state = SWITCH_ON_DISABLED
            return
        cw = controlword & 0x8F
        if controlword & 0x02 == 0:                      # disable voltage
            self.state = SWITCH_ON_DISABLED
        elif controlword & 0x06 == 0x02:                 # quick stop
            self.state = SWITCH_ON_DISABLED if state != OPERATION_ENABLED else QUICK_STOP_ACTIVE
        elif cw & 0x87 == 0x06:                          # shutdown
            self.state = READY_TO_SWITCH_ON
        elif cw == 0x07 and state in (READY_TO_SWITCH_ON, OPERATION_ENABLED):
            self.state = SWITCHED_ON                      # switch on / disable operation
        elif cw == 0x0F and state in (READY_TO_SWITCH_ON, SWITCHED_ON, QUICK_STOP_ACTIVE):
            self.state = OPERATION_ENABLED               # enable operation (3+4 at once too)


# -- the config file -------------------------------------------------------------------------
#: What a leg's drive must have in its EDS for the bridge's PDOs and state machine.
REQUIRED_OBJECTS = {0x6040: 'controlword', 0x6041: 'statusword', 0x6060: 'modes of operation',
                    0x6064: 'position actual value', 0x606C: 'velocity actual value',
                    0x6071: 'target torque', 0x6076: 'motor rated torque',
                    0x1400: 'RPDO1 communication', 0x1600: 'RPDO1 mapping',
                    0x1800: 'TPDO1 communication', 0x1A00: 'TPDO1 mapping',
                    0x1801: 'TPDO2 communication', 0x1A01: 'TPDO2 mapping'}
#: The objects mapped: RPDO1 (controlword, target torque), TPDO1 (position,
#: velocity; at every SYNC), TPDO2 (statusword; when it changes).
RPDO1 = ((0x6040, 16), (0x6071, 16))
TPDO1 = ((0x6064, 32), (0x606C, 32))
TPDO2 = ((0x6041, 16),)
#: Home offset (CiA 402): a homing's zero, written by SDO (``homed_offset``).
HOME_OFFSET = 0x607C


@dataclasses.dataclass(frozen=True)
class Bus:
    """One bus: its name, python-can interface, channel and bitrate."""
    name: str
    interface: str
    channel: str
    bitrate: int


@dataclasses.dataclass(frozen=True)
class BusConfig:
    """A device config file (config/canopen.yaml): buses, heartbeat, legs."""
    path: str
    buses: tuple[Bus, ...]
    heartbeat_ms: int
    legs: tuple[LegDrive, ...]

    def legs_on(self, bus: str) -> list[LegDrive]:
        """The legs whose drives are on bus ``bus``."""
        return [leg for leg in self.legs if leg.bus == bus]

    def loads(self, rate: float) -> list[BusLoad]:
        """The load at sample rate ``rate`` [Hz] on each bus."""
        out = []
        for bus in self.buses:
            drives = len(self.legs_on(bus.name))
            frames = cycle_frames(drives, sum(b for _, b in RPDO1) // 8,
                                  sum(b for _, b in TPDO1) // 8)
            out.append(BusLoad(bus.name, len(frames), sum(frame_bits(n) for _, n in frames),
                               float(rate), bus.bitrate,
                               heartbeat_bits_s(drives, self.heartbeat_ms)))
        return out


class BusConfigError(ValueError):
    """A device config file that cannot work; the message names the key and why."""


#: The keys of a device config file: at the top, per bus, per leg.
TOP_KEYS = ('buses', 'heartbeat_ms', 'legs')
BUS_KEYS = ('name', 'interface', 'channel', 'bitrate')
LEG_KEYS = ('leg', 'bus', 'node_id', 'eds', 'metres_per_count', 'offset_m', 'direction',
            'lead_m', 'gear_ratio', 'efficiency', 'rated_torque_mnm')


def _refuse_unknown(where: str, entry: dict, known: tuple[str, ...]) -> None:
    """A key the bridge does not read is refused, naming it and a close match
    (``hearbeat_ms: 20`` ran with the default 100 ms, silently)."""
    for key in entry:
        if key not in known:
            close = difflib.get_close_matches(str(key), known, n=1)
            raise BusConfigError('%s: unknown key %r%s (known: %s)' % (
                where, key, ': did you mean %s?' % close[0] if close else '',
                ', '.join(known)))


def _field(where: str, entry: dict, key: str, kind, check=None, why: str = '',
           default: Any = None):
    if key not in entry:
        if default is not None:
            return default
        raise BusConfigError('%s: %s is missing' % (where, key))
    value = entry[key]
    try:
        if kind is int and (isinstance(value, bool) or float(value) != int(value)):
            raise ValueError
        value = kind(value)
    except (TypeError, ValueError):
        raise BusConfigError('%s: %s must be %s, got %r' % (
            where, key, 'an integer' if kind is int else 'a number' if kind is float
            else 'a string', entry[key])) from None
    if kind is float and not math.isfinite(value):
        raise BusConfigError('%s: %s must be finite, got %r' % (where, key, value))
    if check is not None and not check(value):
        raise BusConfigError('%s: %s %s, got %r' % (where, key, why, entry[key]))
    return value


def default_bus_config_path() -> Path:
    """The packaged config/canopen.yaml (beside the parameter file)."""
    return default_params_path().with_name('canopen.yaml')


def load_bus_config(path: str | os.PathLike | None = None,
                    channels: list[str] | None = None,
                    interface: str = '', bitrate: int = 0) -> BusConfig:
    """Read and check a device config file.

    Args:
        path: the YAML file; None or '': the packaged config/canopen.yaml.
        channels: when given, the channel of each bus in the file's order
            (a rig gives its own, so two rigs on one machine do not meet).
        interface: when not '', the python-can interface of every bus.
        bitrate: when not 0, the bitrate of every bus [bit/s].

    Returns:
        The BusConfig; EDS paths made absolute (relative to the file).

    Raises:
        BusConfigError: an unknown key (with a close match), a missing or
            bad key (a scale of zero, a node id
            outside 1..127 or used twice on a bus, a leg missing or given
            twice, an unknown bus, a missing EDS file); the message names it.
    """
    path = Path(path) if path else default_bus_config_path()
    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise BusConfigError('bus config %s: %s' % (path, exc)) from None
    if not isinstance(doc, dict) or not isinstance(doc.get('buses'), list) \
            or not isinstance(doc.get('legs'), list):
        raise BusConfigError('bus config %s: expected a mapping with lists buses and legs'
                             % path)
    _refuse_unknown('bus config %s' % path, doc, TOP_KEYS)
    if channels and len(channels) != len(doc['buses']):
        raise BusConfigError('bus_channels: %d channels given for the %d buses of %s'
                             % (len(channels), len(doc['buses']), path))
    buses = []
    for i, entry in enumerate(doc['buses']):
        where = '%s: buses[%d]' % (path, i)
        if not isinstance(entry, dict):
            raise BusConfigError('%s: expected a mapping' % where)
        _refuse_unknown(where, entry, BUS_KEYS)
        name = _field(where, entry, 'name', str)
        buses.append(Bus(name, interface or _field(where, entry, 'interface', str),
                         channels[i] if channels else _field(where, entry, 'channel', str),
                         bitrate or _field(where, entry, 'bitrate', int, lambda v: v > 0,
                                           'must be > 0')))
    names = [b.name for b in buses]
    if len(set(names)) != len(names):
        raise BusConfigError('%s: bus names repeat: %s' % (path, names))
    heartbeat = _field(str(path), doc, 'heartbeat_ms', int, lambda v: 0 <= v <= 65535,
                       'must be 0..65535 ms', default=100)
    legs = []
    for i, entry in enumerate(doc['legs']):
        where = '%s: legs[%d]' % (path, i)
        if not isinstance(entry, dict):
            raise BusConfigError('%s: expected a mapping' % where)
        # before the fields: a misspelt key is unknown, not another key missing
        _refuse_unknown('%s (%s)' % (where, entry['leg']) if isinstance(entry.get('leg'), str)
                        else where, entry, LEG_KEYS)
        leg_name = _field(where, entry, 'leg', str, lambda v: v in LEG_NAMES,
                          'must be one of leg_1 ... leg_6')
        where = '%s (%s)' % (where, leg_name)
        bus = _field(where, entry, 'bus', str, lambda v: v in names,
                     'must name one of the buses %s' % names)
        eds = Path(_field(where, entry, 'eds', str))
        eds = eds if eds.is_absolute() else path.parent / eds
        if not eds.is_file():
            raise BusConfigError('%s: eds %s: no such file' % (where, eds))
        legs.append(LegDrive(
            LEG_NAMES.index(leg_name), bus,
            _field(where, entry, 'node_id', int, lambda v: 1 <= v <= 127, 'must be 1..127'),
            str(eds),
            _field(where, entry, 'metres_per_count', float, lambda v: v > 0,
                   'must be > 0 (the length of one encoder count)'),
            _field(where, entry, 'offset_m', float),
            _field(where, entry, 'direction', int, lambda v: v in (1, -1), 'must be 1 or -1'),
            _field(where, entry, 'lead_m', float, lambda v: v > 0, 'must be > 0'),
            _field(where, entry, 'gear_ratio', float, lambda v: v > 0, 'must be > 0'),
            _field(where, entry, 'efficiency', float, lambda v: 0 < v <= 1,
                   'must be in (0, 1]'),
            _field(where, entry, 'rated_torque_mnm', int, lambda v: v > 0,
                   'must be > 0 (mN m, as 0x6076)')))
    given = sorted(leg.leg for leg in legs)
    if given != list(range(6)):
        raise BusConfigError('%s: legs must list leg_1 ... leg_6 once each, got %s'
                             % (path, [LEG_NAMES[i] for i in given]))
    for bus in names:
        ids = [leg.node_id for leg in legs if leg.bus == bus]
        if len(set(ids)) != len(ids):
            raise BusConfigError('%s: node ids repeat on bus %s: %s' % (path, bus, ids))
    legs.sort(key=lambda leg: leg.leg)
    return BusConfig(str(path), tuple(buses), heartbeat, tuple(legs))


class OverTheBus:
    """A controller as it acts through the bus: it reads the lengths and
    rates the drives' counts give (``LegDrive.counts`` then ``metres``), and
    its forces act as the drives apply them (``permille`` then ``force``).
    The same arithmetic as the bridge and the plant's drives, in one
    process: ``simulate.run_sampled(..., controller=OverTheBus(law, legs))``
    predicts a lockstep run over the bus, quantisation and all.

    Args:
        controller: a ``laws.Controller`` (its ``forces(t, lengths, rates)``).
        legs: the six legs' drives (``BusConfig.legs``), in leg order.
    """

    def __init__(self, controller: Any, legs: Any) -> None:
        self.controller = controller
        self.legs = tuple(legs)

    def pd_gains(self) -> None:
        """No compiled fast path: the bus's quantisation acts on every sample."""
        return None

    def forces(self, t: float, lengths: Any, rates: Any) -> Any:
        """The forces [N] the drives apply for readings ``lengths`` [m],
        ``rates`` [m/s] at time ``t`` [s]."""
        read_l = [leg.metres(leg.counts(v)) for leg, v in zip(self.legs, lengths)]
        read_r = [leg.metres_per_second(leg.counts_s(v)) for leg, v in zip(self.legs, rates)]
        forces = self.controller.forces(t, np.array(read_l), np.array(read_r))
        return np.array([leg.force(leg.permille(f)) for leg, f in zip(self.legs, forces)])
