"""The bridge's side of the bus: the CANopen master, on the ``canopen`` library.

``Master`` brings each leg's drive up (``bring_up``: NMT, the PDO mapping
written by SDO from the EDS, the heartbeat, mode 10 = cyclic synchronous
torque, the CiA 402 state machine to OPERATION ENABLED, NMT start), then runs
the cycle the bridge node drives: ``sync`` (a SYNC on every bus), ``collect``
(each leg's TPDO1 received in that SYNC's window: canbus/cycle.py),
``command`` (each drive's RPDO1: controlword and target torque). Heartbeats,
EMCYs, statuswords (TPDO2) and boot-up messages arrive in the notifier's
thread and are judged in ``errors``: a leg with an error gets no torque, and
while any leg has one the bridge withholds torque from all (zero torque to
the drives that listen). A drive that boots again is brought up again; a
drive in FAULT gets a fault reset (never in FAULT REACTION ACTIVE), then
shutdown, switch on, enable, one step per cycle. ``safe_stop`` leaves every
drive READY TO SWITCH ON with zero torque, NMT pre-operational.

No ROS here: nodes/canopen_bridge.py is the shell.
"""
from __future__ import annotations

import math
import struct
import threading
import time

from stewart63_ros.canbus.cycle import NOTIFIER_CYCLE, SETTLE_POLL, CycleSide
from stewart63_ros.canbus.devices import PDO_CODES, open_bus
from stewart63_ros.canbus.hub import batched
from stewart63_ros.canbus.pdo import PdoRefused, configure_pdos
from stewart63_ros.canbus.sync import SyncWindows
from stewart63_ros.core.machine.bus import (
    CW_DISABLE_OPERATION,
    CW_ENABLE,
    CW_SHUTDOWN,
    FAULT_REACTION_ACTIVE,
    HOME_OFFSET,
    MODE_CST,
    OPERATION_ENABLED,
    READY_TO_SWITCH_ON,
    REQUIRED_OBJECTS,
    RPDO1,
    TPDO1,
    TPDO2,
    BusConfig,
    BusConfigError,
    LegDrive,
    check_load,
    drive_state,
    frame_bits,
    next_controlword,
)

#: EMCY error code of an error reset (no error)
EMCY_NO_ERROR = 0x0000
#: s: an SDO answer's bound during bring-up (the library's 0.3 s is short for
#: a device process that is itself still starting on a loaded machine)
SDO_TIMEOUT = 1.0
#: bring-ups of one drive that fail in a row before the master stops resetting it
BRING_UP_TRIES = 3
#: s: at bring-up, how long a drive in FAULT REACTION ACTIVE is given to reach FAULT
FAULT_REACTION_WAIT = 1.0
#: s: the safe stop waits this long for the drives' statuswords, then asks by SDO
STOP_CONFIRM = 0.3
#: s: an SDO answer's bound during the stop (it must end within the stop deadline)
STOP_SDO_TIMEOUT = 0.2
#: s: the SDO confirmations of the stop end this long after its wait (a bus gone
#: silent must not hold the stop past the launcher's deadline)
STOP_SDO_BUDGET = 0.6
#: NMT enter pre-operational (CiA 301)
NMT_PRE_OPERATIONAL = 0x80
#: CiA 301's synchronous window length [µs] (UNSIGNED32; 0: none)
SYNC_WINDOW_LENGTH = 0x1007


class DriveRefused(BusConfigError):
    """A drive that answers the bring-up with a no that a reset will not
    change (a rated torque other than the config's): refused once, not retried."""


#: SDO aborts that say the transfer went wrong (0x0503...., 0x0504....: toggle
#: bit, timeout, CRC, memory) or the drive cannot do it now (general error,
#: local control, its present state): worth a reset and another try; any
#: other abort is the drive's final answer
TRANSIENT_ABORT_CLASSES = (0x0503, 0x0504)
TRANSIENT_ABORTS = (0x08000000, 0x08000020, 0x08000021, 0x08000022)


def refused_for_good(exc: Exception) -> bool:
    """Whether a bring-up's failure is the drive's final answer (an object
    it refuses, a PDO it cannot switch off, a value it does not keep), not
    silence or a state it may leave (a timeout, a drive still in FAULT)."""
    code = getattr(exc, 'code', None)       # an SDO abort's (PdoRefused keeps it)
    if code is not None:
        return code >> 16 not in TRANSIENT_ABORT_CLASSES and code not in TRANSIENT_ABORTS
    return isinstance(exc, (PdoRefused, DriveRefused))


def check_eds(leg: LegDrive, od) -> None:
    """Refuse an EDS that lacks an object the bridge maps or drives.

    Raises:
        BusConfigError: naming the leg, the EDS and the missing object.
    """
    for index, what in REQUIRED_OBJECTS.items():
        if index not in od:
            raise BusConfigError('%s (node %d): EDS %s has no 0x%04X (%s), which the bridge '
                                 'needs' % (leg.name, leg.node_id, leg.eds, index, what))
    for index, _ in RPDO1 + TPDO1 + TPDO2:
        if not getattr(od[index], 'pdo_mappable', True):
            raise BusConfigError('%s (node %d): EDS %s: 0x%04X is not PDO-mappable'
                                 % (leg.name, leg.node_id, leg.eds, index))


def pdo_struct(od, objects) -> struct.Struct:
    """The layout of a PDO mapping ``objects`` ((index, bits) ...), from the EDS's types."""
    return struct.Struct('<' + ''.join(PDO_CODES[od[index].data_type] for index, _ in objects))


class Link:
    """What the master knows of one leg's drive (updated from the notifier's thread)."""

    def __init__(self, leg: LegDrive, node, network) -> None:
        self.leg = leg
        self.node = node
        self.network = network
        self.name = '%s (node %d, bus %s)' % (leg.name, leg.node_id, leg.bus)
        self.up = False             # brought up and started
        self.booted = False         # a boot-up came since the last bring-up
        self.boot_error = ''        # why the last bring-up failed
        self.statusword = None
        self.emcy_code = EMCY_NO_ERROR
        self.emcys = 0
        self.heartbeat = None       # (SYNC whose window it came in, its reception time)
        self.tpdo = None            # (position counts, velocity counts) of ``tpdo_sync``
        self.tpdo_sync = None       # the SYNC whose window ``tpdo`` came in
        self.tpdo_firm = False      # surely that SYNC's answer (see Master._take_tpdo)
        self.tpdo_taken_at = 0.0    # time.monotonic() it was taken
        self.answered = None        # the SYNC of the newest TPDO seen (late ones too)
        self.missed_tpdo = 0
        self.late_tpdo = 0          # TPDOs that came after their SYNC's window
        self.missed_in_a_row = 0    # windows closed without its TPDO, in a row
        self.silent_since = None    # the first SYNC of that run of missing TPDOs
        self.last_cw = 0
        self.failed_bring_ups = 0   # in a row
        self.refused = False        # the drive refused the bring-up for good (not retried)
        node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT
        od = node.object_dictionary
        self.rpdo_struct = pdo_struct(od, RPDO1)
        self.tpdo_struct = pdo_struct(od, TPDO1)
        self.status_struct = pdo_struct(od, TPDO2)

    @property
    def state(self) -> str:
        return drive_state(self.statusword) if self.statusword is not None else 'unknown'


class Master(CycleSide):
    """The master of the legs' buses (see the module's doc).

    Args:
        config: the device config (core/machine/bus.py).
        rate: the sample rate [Hz]: the SYNC rate.
        log: ``log(text)`` for what the master does (the node's logger).

    Raises:
        BusLoadError: the configuration does not fit its buses at ``rate``.
        BusConfigError: an EDS without the objects mapped.
        ValueError: an unknown interface, or a channel it cannot open.
    """

    def __init__(self, config: BusConfig, rate: float, log=print) -> None:
        # lazy: optional: canopen costs 273 ms; the simulated bus runs without it
        import canopen
        check_load(config.loads(rate))
        self.config = config
        self.rate = float(rate)
        self.log = log
        self.cycle = -1
        #: µs written to each drive's 0x1007 at bring-up, where its EDS has it
        #: (None: not written); the bridge sets its own window (bridge_cycles)
        self.sync_window_us: int | None = None
        #: the drives were left safe (``safe_stop``): no RPDO any more
        self.stopped = False
        #: bits seen on each bus (sent and received, worst-case stuffing): the measured load
        self.bits = {bus.name: 0 for bus in config.buses}
        self.networks = {}
        self.links: list[Link] = []
        self._arrived = threading.Condition()
        #: the SYNCs' send times: the window each frame is received in
        self.windows = SyncWindows()
        self._open = False          # the cycle's window: closed once judged (``missing``)
        self._opened_at = 0.0       # time.monotonic() of the cycle's SYNC
        #: per bus, the reception time of the newest frame taken (any node's):
        #: how far the receive side has got
        self.received_to = {bus.name: 0.0 for bus in config.buses}
        #: the buses the loop reads itself, with their listeners (None: the
        #: notifier threads read them); their descriptors (cycle.py)
        self._pumped = None
        self._fds: list[int] = []
        ods = {}
        for leg in config.legs:
            od = ods.get(leg.eds) or canopen.import_od(leg.eds)
            ods[leg.eds] = od
            check_eds(leg, od)
        try:
            for bus in config.buses:
                network = canopen.Network(open_bus(bus.interface, bus.channel, bus.bitrate))
                # (its reader thread looks at its stop flag this often: a stop
                # signal must end the bridge within the launcher's deadline)
                network.NOTIFIER_CYCLE = NOTIFIER_CYCLE
                network.connect()
                self.networks[bus.name] = network
            for leg in config.legs:
                network = self.networks[leg.bus]
                node = canopen.RemoteNode(leg.node_id, canopen.import_od(leg.eds, leg.node_id))
                network.add_node(node)
                link = Link(leg, node, network)
                self.links.append(link)
                network.subscribe(0x180 + leg.node_id, self._on_tpdo1(link))
                network.subscribe(0x280 + leg.node_id, self._on_tpdo2(link))
                network.subscribe(0x80 + leg.node_id, self._on_emcy(link))
                network.subscribe(0x700 + leg.node_id, self._on_heartbeat(link))
        except Exception:
            self.close()
            raise
        #: SYNCs in a row without a TPDO after which a drive is an error (1:
        #: the first miss, as in lockstep, where a miss has waited ``bus_timeout``)
        self.tpdo_error_cycles = 1
        #: s without a heartbeat after which a drive counts as lost (3 periods)
        self.heartbeat_limit = 3 * config.heartbeat_ms / 1000.0 if config.heartbeat_ms \
            else math.inf
        #: the heartbeats' clock: 'wall' (realtime: reception times) or 'run'
        #: (lockstep: the run's time, k / rate, which the plant's drives beat in)
        self.clock = 'run'

    def close(self) -> None:
        for network in self.networks.values():
            try:
                network.disconnect()
            except Exception:  # noqa: BLE001 - closing: the bus may be gone already
                pass

    # -- bring-up ------------------------------------------------------------------------
    def reset_all(self) -> None:
        """NMT reset communication to every node: each answers with its boot-up."""
        for network in self.networks.values():
            network.send_message(0, [0x82, 0])

    def wait_for_boot(self, timeout: float) -> list[Link]:
        """Wait up to ``timeout`` s for every drive's boot-up; the ones missing."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            missing = [link for link in self.links if not link.booted]
            if not missing:
                return []
            time.sleep(0.01)
        return [link for link in self.links if not link.booted]

    def describe(self, links: list[Link]) -> str:
        """``links``' drives by bus, for a message: "nodes 1, 2 on bus a
        (s63hub channel x)"."""
        parts = []
        for bus in self.config.buses:
            ids = [str(link.leg.node_id) for link in links if link.leg.bus == bus.name]
            if ids:
                parts.append('node%s %s on bus %s (%s channel %s)' % (
                    's' if len(ids) > 1 else '', ', '.join(ids), bus.name, bus.interface,
                    bus.channel))
        return '; '.join(parts)

    def bring_up(self, link: Link) -> bool:
        """Configure one booted drive and enable it (see the module's doc).
        False with ``link.boot_error`` set when the drive refused or went quiet."""
        with self.receiving_in_threads():       # SDO answers come while it waits
            return self._bring_up(link)

    def _bring_up(self, link: Link) -> bool:
        # lazy: optional: canopen costs 273 ms; the simulated bus runs without it
        import canopen
        leg, node = link.leg, link.node
        link.booted = False
        try:
            switched_off = configure_pdos(node, leg)   # only the bridge's PDOs on
            if switched_off:
                self.log('%s: %s off (unused)' % (link.name, ', '.join(switched_off)))
            node.sdo[0x1017].raw = self.config.heartbeat_ms
            if self.sync_window_us is not None and SYNC_WINDOW_LENGTH in node.object_dictionary:
                # the window the bridge judges TPDOs by: a drive that has it
                # sends no synchronous TPDO later (CiA 301), none goes on the
                # bus to be counted late
                node.sdo[SYNC_WINDOW_LENGTH].raw = self.sync_window_us
            rated = node.sdo[0x6076].raw
            if rated != leg.rated_torque_mnm:
                raise DriveRefused('rated torque 0x6076 is %d mN m, the config says %d'
                                   % (rated, leg.rated_torque_mnm))
            node.sdo[0x6060].raw = MODE_CST
            cw = self.enable_by_sdo(node)
            link.statusword = node.sdo[0x6041].raw
            link.last_cw = cw
            if drive_state(link.statusword) != OPERATION_ENABLED:
                raise BusConfigError('drive stays in %s' % link.state)
            link.emcy_code = EMCY_NO_ERROR
            node.nmt.send_command(0x01)         # NMT start: PDOs from now on
        except (canopen.SdoCommunicationError, canopen.SdoAbortedError, BusConfigError,
                OSError) as exc:
            link.failed_bring_ups += 1
            link.boot_error = '%s: bring-up failed: %s' % (link.name, exc)
            if refused_for_good(exc):   # the drive said no: a reset will not change that
                link.refused = True
                link.boot_error += ' (refused, not retried: the drive or its EDS must change)'
            elif link.failed_bring_ups < BRING_UP_TRIES:     # once more, from its boot-up
                node.nmt.send_command(0x81)
                link.boot_error += ' (reset, try %d of %d)' % (link.failed_bring_ups + 1,
                                                              BRING_UP_TRIES)
            self.log(link.boot_error)
            return False
        if link.booted:     # it booted again meanwhile: its configuration is lost
            link.boot_error = '%s: booted again during its bring-up' % link.name
            self.log(link.boot_error + ': brought up once more')
            return False
        link.up = True
        link.boot_error = ''
        link.failed_bring_ups = 0
        link.heartbeat = (max(self.cycle, 0), time.time())
        link.tpdo_sync = link.answered = None
        link.missed_in_a_row = 0
        link.silent_since = None
        self.log('%s: up (PDOs mapped, mode 10, OPERATION ENABLED, NMT started)' % link.name)
        return True

    @staticmethod
    def enable_by_sdo(node) -> int:
        """CiA 402 by SDO to OPERATION ENABLED: shutdown, switch on, enable,
        a fault reset first from FAULT. A drive in FAULT REACTION ACTIVE is
        left to finish its reaction (it takes no controlword then, and a
        fault reset is for FAULT only), up to FAULT_REACTION_WAIT s.
        Returns the last controlword written."""
        cw = 0
        steps = 0
        waited_until = time.monotonic() + FAULT_REACTION_WAIT
        while steps < 6:            # at most: fault reset, 0, shutdown, switch on, enable
            state = drive_state(node.sdo[0x6041].raw)
            if state == OPERATION_ENABLED:
                break
            if state == FAULT_REACTION_ACTIVE and time.monotonic() < waited_until:
                time.sleep(0.01)
                continue
            cw = next_controlword(state, cw)
            node.sdo[0x6040].raw = cw
            steps += 1
        return cw

    def write_home_offset(self, link: Link, metres: float) -> int:
        """A homing's offset [m] for ``link``'s leg into its drive's home offset
        0x607C (SDO): its position actual value is homed from its next TPDO.
        A drive that boots again has lost it (power-on value 0): home again.
        Returns the counts written.

        Raises:
            BusConfigError: the EDS has no 0x607C, or the drive is not up.
            canopen.SdoCommunicationError, canopen.SdoAbortedError: the drive
                did not take it.
        """
        if HOME_OFFSET not in link.node.object_dictionary:
            raise BusConfigError('%s: its EDS %s has no 0x%04X (home offset)'
                                 % (link.name, link.leg.eds, HOME_OFFSET))
        if not link.up:
            raise BusConfigError('%s is not up' % link.name)
        counts = link.leg.home_offset_counts(metres)
        with self.receiving_in_threads():
            link.node.sdo[HOME_OFFSET].raw = counts
        return counts

    def bring_up_rebooted(self) -> list[str]:
        """Bring up the drives that sent a boot-up since (not one refused for
        good: its boot-up changes nothing); their names."""
        self.pump()                 # (a boot-up waiting on a bus the loop reads)
        return [link.name for link in self.links
                if link.booted and not link.refused and self.bring_up(link)]

    def errors(self) -> list[str]:
        """Why torque is withheld now, one line per leg at fault (empty: none)."""
        out = []
        for link in self.links:
            if not link.up:
                out.append('%s: booted, being brought up' % link.name if link.booted
                           else link.boot_error or '%s: not booted (no boot-up message)'
                           % link.name)
                continue
            # realtime: an isolated miss is a late message (a warning, counted,
            # ``late_tpdos``); silent this many SYNCs in a row, a bus fault
            if link.missed_in_a_row >= self.tpdo_error_cycles:
                out.append('%s: TPDO missing since SYNC %d (silent: cable, power?)'
                           % (link.name, link.silent_since))
            age = self.heartbeat_age(link)
            if age > self.heartbeat_limit:
                out.append('%s: heartbeat lost (none for %.0f ms)' % (link.name, 1000 * age))
            if link.emcy_code != EMCY_NO_ERROR:
                out.append('%s: EMCY 0x%04X' % (link.name, link.emcy_code))
            if link.state != OPERATION_ENABLED:
                out.append('%s: drive in %s' % (link.name, link.state))
        return out

    def command(self, forces, withhold: bool, shut_down: bool = False) -> None:
        """Each drive's RPDO1: the controlword towards OPERATION ENABLED and
        the target torque for its leg's force [N]; zero torque to all when
        ``withhold`` (or ``forces`` is None); with ``shut_down`` zero torque
        and the controlwords down to READY TO SWITCH ON (a lost controller)."""
        if self.stopped:        # the drives are left safe: nothing enables them again
            return
        # one write a bus for the cycle's RPDOs (s63hub): the drives' side
        # wakes once, not once a drive
        with batched(network.bus for network in self.networks.values()):
            for link in self.links:
                if link.up:
                    self._command(link, forces, withhold, shut_down)

    def _command(self, link: Link, forces, withhold: bool, shut_down: bool) -> None:
        """One drive's RPDO1 of ``command``."""
        if shut_down:
            cw = CW_DISABLE_OPERATION if link.state == OPERATION_ENABLED else CW_SHUTDOWN
        elif link.statusword is not None:
            cw = next_controlword(link.state, link.last_cw)
        else:
            cw = link.last_cw
        torque = 0
        if not (withhold or shut_down) and forces is not None:
            torque = link.leg.permille(float(forces[link.leg.leg]))
        self._rpdo(link, cw, torque)

    # -- the stop -------------------------------------------------------------------------
    def _rpdo(self, link: Link, cw: int, torque: int) -> None:
        data = link.rpdo_struct.pack(cw, torque)
        link.network.send_message(0x200 + link.leg.node_id, data)
        self.bits[link.leg.bus] += frame_bits(len(data))
        link.last_cw = cw

    def safe_stop(self, confirm_timeout: float = STOP_CONFIRM) -> dict[str, str]:
        """Leave every drive safe, whatever way the bridge stops (docs/bus.md,
        "Stopping"): zero target torque, then disable operation (0x07) and
        shutdown (0x06): READY TO SWITCH ON, power stage off (the drive's
        brake holds, if it has one); then NMT enter pre-operational: no PDO
        acts any more, SDO, EMCY and heartbeat go on. A drive whose TPDO2
        does not confirm within ``confirm_timeout`` s is told again by SDO
        (0x6071 = 0, 0x6040 = 0x06) and read back. Nothing is enabled after
        this (``command`` sends nothing).

        Returns:
            {leg name: READY TO SWITCH ON, or "not confirmed (last seen
            ...)"} for the drives that were up; the others get the NMT only.
        """
        self.stopped = True
        with self.receiving_in_threads():       # statuswords and SDO answers, from here on
            return self._safe_stop(confirm_timeout)

    def _safe_stop(self, confirm_timeout: float) -> dict[str, str]:
        # lazy: optional: canopen costs 273 ms; the simulated bus runs without it
        import canopen
        up = [link for link in self.links if link.up]
        for link in up:
            cw = CW_ENABLE if link.state == OPERATION_ENABLED else link.last_cw
            self._rpdo(link, cw, 0)                    # zero torque, in the state it is
            self._rpdo(link, CW_DISABLE_OPERATION, 0)
            self._rpdo(link, CW_SHUTDOWN, 0)
        deadline = time.monotonic() + confirm_timeout
        with self._arrived:
            while any(link.state != READY_TO_SWITCH_ON for link in up):
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._arrived.wait(min(left, SETTLE_POLL))
        states = {}
        for link in up:
            if link.state != READY_TO_SWITCH_ON and time.monotonic() < deadline + STOP_SDO_BUDGET:
                link.node.sdo.RESPONSE_TIMEOUT = STOP_SDO_TIMEOUT
                try:
                    link.node.sdo[0x6071].raw = 0
                    link.node.sdo[0x6040].raw = CW_SHUTDOWN
                    link.statusword = link.node.sdo[0x6041].raw
                except (canopen.SdoCommunicationError, canopen.SdoAbortedError,
                        OSError) as exc:
                    self.log('%s: safe stop not confirmed: %s' % (link.name, exc))
            states[link.leg.name] = link.state if link.state == READY_TO_SWITCH_ON else \
                'not confirmed (last seen %s)' % link.state
        for link in self.links:
            try:
                link.node.nmt.send_command(NMT_PRE_OPERATIONAL)
            except OSError as exc:      # the bus is gone: nothing reaches the drive
                self.log('%s: NMT pre-operational not sent: %s' % (link.name, exc))
            link.up = False
        return states
