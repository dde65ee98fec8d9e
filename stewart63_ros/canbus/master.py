"""The bridge's side of the bus: the CANopen master, on the ``canopen`` library.

``Master`` brings each leg's drive up (``bring_up``: NMT, the PDO mapping
written by SDO from the EDS, the heartbeat, mode 10 = cyclic synchronous
torque, the CiA 402 state machine to OPERATION ENABLED, NMT start), then runs
the cycle the bridge node drives: ``sync`` (a SYNC on every bus), ``collect``
(each leg's TPDO1: position and velocity), ``command`` (each drive's RPDO1:
controlword and target torque). Heartbeats, EMCYs, statuswords (TPDO2) and
boot-up messages arrive in the notifier's thread and are judged in
``errors``: a leg with an error gets no torque, and while any leg has one the
bridge withholds torque from all (zero torque to the drives that listen).
A drive that boots again is brought up again; a drive in FAULT gets a fault
reset, then shutdown, switch on, enable, one step per cycle.

No ROS here: nodes/canopen_bridge.py is the shell.
"""
from __future__ import annotations

import math
import struct
import threading
import time

from stewart63_ros.canbus.devices import PDO_CODES, open_bus
from stewart63_ros.canbus.pdo import configure_pdos
from stewart63_ros.core.bus import (
    HOME_OFFSET,
    MODE_CST,
    OPERATION_ENABLED,
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
#: s: the notifier's wait per turn (the library's 1 s, one per bus, made a
#: stopping bridge miss the launcher's 3.5 s deadline)
NOTIFIER_CYCLE = 0.1


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
        self.heartbeat_cycle = None  # the cycle of the last heartbeat
        self.tpdo = None            # (position counts, velocity counts) of this cycle
        self.tpdo_cycle = -1
        self.missed_tpdo = 0
        self.silent_since = None    # the first cycle of a run of missing TPDOs
        self.last_cw = 0
        self.failed_bring_ups = 0   # in a row
        node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT
        od = node.object_dictionary
        self.rpdo_struct = pdo_struct(od, RPDO1)
        self.tpdo_struct = pdo_struct(od, TPDO1)
        self.status_struct = pdo_struct(od, TPDO2)

    @property
    def state(self) -> str:
        return drive_state(self.statusword) if self.statusword is not None else 'unknown'


class Master:
    """The master of the legs' buses (see the module's doc).

    Args:
        config: the device config (core/bus.py).
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
        #: bits seen on each bus (sent and received, worst-case stuffing): the measured load
        self.bits = {bus.name: 0 for bus in config.buses}
        self.networks = {}
        self.links: list[Link] = []
        self._arrived = threading.Condition()
        self._expected = 0
        self._got = 0
        self._first = None
        self._closed = False        # the cycle is judged: a TPDO now is too late for it
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
        #: cycles in a row without a TPDO after which a drive is an error (1:
        #: the first miss, as in lockstep, where a miss has waited ``bus_timeout``)
        self.tpdo_error_cycles = 1
        #: cycles without a heartbeat after which a drive counts as lost (3 periods)
        self.heartbeat_cycles = (3 * config.heartbeat_ms / 1000.0 * self.rate
                                 if config.heartbeat_ms else math.inf)

    def close(self) -> None:
        for network in self.networks.values():
            try:
                network.disconnect()
            except Exception:  # noqa: BLE001 - closing: the bus may be gone already
                pass

    # -- frames in (the notifier's thread) --------------------------------------------------
    def _on_tpdo1(self, link: Link):
        unpack = link.tpdo_struct.unpack_from

        def on(cob_id, data, timestamp):
            if len(data) < link.tpdo_struct.size:
                return
            self.bits[link.leg.bus] += frame_bits(len(data))
            with self._arrived:
                if link.tpdo_cycle != self.cycle and not self._closed:
                    link.tpdo = unpack(data)
                    link.tpdo_cycle = self.cycle
                    self._got += 1
                    self._arrived.notify()
        return on

    def _on_tpdo2(self, link: Link):
        def on(cob_id, data, timestamp):
            self.bits[link.leg.bus] += frame_bits(len(data))
            if len(data) >= link.status_struct.size:
                link.statusword = link.status_struct.unpack_from(data)[0]
        return on

    def _on_emcy(self, link: Link):
        def on(cob_id, data, timestamp):
            self.bits[link.leg.bus] += frame_bits(min(len(data), 8))
            if len(data) >= 2:
                link.emcy_code = struct.unpack_from('<H', data)[0]
                link.emcys += 1
        return on

    def _on_heartbeat(self, link: Link):
        def on(cob_id, data, timestamp):
            if not data:
                return
            self.bits[link.leg.bus] += frame_bits(1)
            if data[0] == 0:            # boot-up: configured from scratch again
                link.booted = True
                link.up = False
            link.heartbeat_cycle = max(self.cycle, 0)
        return on

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

    def bring_up(self, link: Link) -> bool:
        """Configure one booted drive and enable it (see the module's doc).
        False with ``link.boot_error`` set when the drive refused or went quiet."""
        # lazy: optional: canopen costs 273 ms; the simulated bus runs without it
        import canopen
        leg, node = link.leg, link.node
        link.booted = False
        try:
            switched_off = configure_pdos(node, leg)   # only the bridge's PDOs on
            if switched_off:
                self.log('%s: %s off (unused)' % (link.name, ', '.join(switched_off)))
            node.sdo[0x1017].raw = self.config.heartbeat_ms
            rated = node.sdo[0x6076].raw
            if rated != leg.rated_torque_mnm:
                raise BusConfigError('rated torque 0x6076 is %d mN m, the config says %d'
                                     % (rated, leg.rated_torque_mnm))
            node.sdo[0x6060].raw = MODE_CST
            cw = 0
            for _ in range(6):      # at most: fault reset, 0, shutdown, switch on, enable
                state = drive_state(node.sdo[0x6041].raw)
                if state == OPERATION_ENABLED:
                    break
                cw = next_controlword(state, cw)
                node.sdo[0x6040].raw = cw
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
            if link.failed_bring_ups < BRING_UP_TRIES:     # once more, from its boot-up
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
        link.heartbeat_cycle = max(self.cycle, 0)
        link.tpdo_cycle = -1
        self.log('%s: up (PDOs mapped, mode 10, OPERATION ENABLED, NMT started)' % link.name)
        return True

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
        link.node.sdo[HOME_OFFSET].raw = counts
        return counts

    def bring_up_rebooted(self) -> list[str]:
        """Bring up the drives that sent a boot-up since; their names."""
        return [link.name for link in self.links if link.booted and self.bring_up(link)]

    # -- the cycle ----------------------------------------------------------------------
    def sync(self, cycle: int) -> None:
        """Cycle ``cycle`` starts: a SYNC on every bus."""
        with self._arrived:
            self.cycle = cycle
            self._got = 0
            self._first = None
            self._closed = False
            self._expected = sum(link.up for link in self.links)
        for name, network in self.networks.items():
            network.send_message(0x80, b'')
            self.bits[name] += frame_bits(0)

    def collect(self, timeout: float, burst: float) -> bool:
        """Wait for this cycle's TPDO1s: until every drive that is up has
        answered, or ``burst`` s after the first (the drives of a bus answer
        a SYNC together). Returns False if none came within ``timeout`` s
        (call again to wait on), True when the cycle is complete or its
        burst is over (then ``missing``)."""
        start = time.monotonic()
        with self._arrived:
            while self._got < self._expected:
                now = time.monotonic()
                if self._got and self._first is None:
                    self._first = now
                if self._first is None and now >= start + timeout:
                    return False
                deadline = start + timeout if self._first is None else self._first + burst
                if now >= deadline:
                    break
                self._arrived.wait(deadline - now)
        return True

    def missing(self) -> list[Link]:
        """The cycle is over: the drives that are up and did not answer
        (counted). A TPDO that comes after this is not this cycle's."""
        with self._arrived:
            self._closed = True
        missing = [link for link in self.links if link.up and link.tpdo_cycle != self.cycle]
        for link in missing:
            link.missed_tpdo += 1
        return missing

    def readings(self) -> tuple[list[float], list[float]]:
        """This cycle's leg lengths [m] and rates [m/s]: NaN where no TPDO came."""
        lengths, rates = [math.nan] * 6, [math.nan] * 6
        for link in self.links:
            if link.tpdo_cycle == self.cycle and link.tpdo is not None:
                lengths[link.leg.leg] = link.leg.metres(link.tpdo[0])
                rates[link.leg.leg] = link.leg.metres_per_second(link.tpdo[1])
        return lengths, rates

    def errors(self) -> list[str]:
        """Why torque is withheld now, one line per leg at fault (empty: none)."""
        out = []
        for link in self.links:
            if not link.up:
                out.append('%s: booted, being brought up' % link.name if link.booted
                           else link.boot_error or '%s: not booted (no boot-up message)'
                           % link.name)
                continue
            if link.tpdo_cycle != self.cycle:
                if link.silent_since is None:
                    link.silent_since = self.cycle
                # realtime: an isolated miss is a late message (a warning, counted,
                # ``late_tpdos``); silent this many cycles in a row, a bus fault
                if self.cycle - link.silent_since + 1 >= self.tpdo_error_cycles:
                    out.append('%s: TPDO missing since SYNC %d (silent: cable, power?)'
                               % (link.name, link.silent_since))
            else:
                link.silent_since = None
            if link.heartbeat_cycle is not None and \
                    self.cycle - link.heartbeat_cycle > self.heartbeat_cycles:
                out.append('%s: heartbeat lost (none for %d cycles)'
                           % (link.name, self.cycle - link.heartbeat_cycle))
            if link.emcy_code != EMCY_NO_ERROR:
                out.append('%s: EMCY 0x%04X' % (link.name, link.emcy_code))
            if link.state != OPERATION_ENABLED:
                out.append('%s: drive in %s' % (link.name, link.state))
        return out

    def late_tpdos(self) -> list[str]:
        """The drives whose TPDO missed this cycle but not yet for
        ``tpdo_error_cycles`` cycles in a row (not errors): one line each."""
        return ['%s: TPDO missed at SYNC %d (%d missed in all)'
                % (link.name, self.cycle, link.missed_tpdo) for link in self.links
                if link.up and link.tpdo_cycle != self.cycle
                and self.cycle - (link.silent_since if link.silent_since is not None
                                  else self.cycle) + 1 < self.tpdo_error_cycles]

    def command(self, forces, withhold: bool) -> None:
        """Each drive's RPDO1: the controlword towards OPERATION ENABLED and
        the target torque for its leg's force [N]; zero torque to all when
        ``withhold`` (or ``forces`` is None)."""
        for link in self.links:
            if not link.up:
                continue
            cw = next_controlword(link.state, link.last_cw) if link.statusword is not None \
                else link.last_cw
            link.last_cw = cw
            torque = 0
            if not withhold and forces is not None:
                torque = link.leg.permille(float(forces[link.leg.leg]))
            data = link.rpdo_struct.pack(cw, torque)
            link.network.send_message(0x200 + link.leg.node_id, data)
            self.bits[link.leg.bus] += frame_bits(len(data))
