"""The PDOs of a drive at bring-up: only what the bridge uses stays on.

A drive ships with its PDOs valid and mapped (CiA 402's predefined sets:
RPDO1-4, TPDO1-4, several of them sent at every SYNC). The bridge uses
three: RPDO1 (controlword, target torque), TPDO1 (position, velocity at
every SYNC), TPDO2 (statusword on change). ``configure_pdos`` writes them by
SDO and switches every other PDO the drive's EDS lists off, so nothing the
bus load was planned without goes on the wire, and no RPDO left on accepts a
controlword on a COB-ID nobody configured (docs/bus.md, "PDOs").

The order is CiA 301's (7.5.2.35-38), the one a strict drive enforces:

1. the PDO off: COB-ID sub 1 with bit 31 set, nothing else changed (while a
   PDO is valid its COB-ID may change in bit 31 only);
2. the new COB-ID, still with bit 31; the transmission type (sub 2); the
   event timer 0 (sub 5) where the type is event-driven;
3. the mapping off: its count (sub 0) 0; the entries; the count;
4. the PDO on: the COB-ID without bit 31.

Then every PDO's COB-ID, type and mapping are read back and compared. A
write the drive aborts, or a value it does not keep, refuses the drive with
one line naming the object (``0x1802:01``) and the SDO abort.

No ROS; the master's SDO client (``canopen``) does the transfers.
"""
from __future__ import annotations

import dataclasses
import struct

from stewart63_ros.core.machine.bus import RPDO1, TPDO1, TPDO2, BusConfigError, LegDrive

#: COB-ID bit 31: the PDO does not exist (is off)
PDO_INVALID = 1 << 31
#: COB-ID bit 30 of a TPDO: no RTR allowed (kept as the drive has it)
RTR_NOT_ALLOWED = 1 << 30
#: the communication parameters of RPDO 1..512 and TPDO 1..512; each mapping
#: parameter is 0x200 above its communication parameter
RPDO_COMM, TPDO_COMM, PDO_SPAN, MAPPING_OFFSET = 0x1400, 0x1800, 0x200, 0x200
#: event timer sub-index of a TPDO's communication parameter
EVENT_TIMER = 5
U8, U16, U32 = struct.Struct('<B'), struct.Struct('<H'), struct.Struct('<I')


@dataclasses.dataclass(frozen=True)
class PdoPlan:
    """One PDO the bridge maps.

    Attributes:
        kind: 'RPDO' or 'TPDO'.
        number: 1-based.
        objects: ((index, bits), ...) mapped, in order.
        cob_base: COB-ID less the node id (CiA 301's predefined connection set).
        trans_type: transmission type (1: every SYNC; 255: event-driven).
    """
    kind: str
    number: int
    objects: tuple
    cob_base: int
    trans_type: int

    @property
    def comm(self) -> int:
        """Index of its communication parameter."""
        return (RPDO_COMM if self.kind == 'RPDO' else TPDO_COMM) + self.number - 1

    @property
    def mapping(self) -> int:
        """Index of its mapping parameter."""
        return self.comm + MAPPING_OFFSET

    def cob_id(self, node_id: int) -> int:
        return self.cob_base + node_id

    def entries(self) -> list[int]:
        """The mapping entries: index << 16 | sub-index << 8 | bits."""
        return [index << 16 | bits for index, bits in self.objects]


#: What the bridge maps; every other PDO of a drive is switched off.
BRIDGE_PDOS = (PdoPlan('RPDO', 1, RPDO1, 0x200, 255), PdoPlan('TPDO', 1, TPDO1, 0x180, 1),
               PdoPlan('TPDO', 2, TPDO2, 0x280, 255))


def pdo_name(comm: int) -> str:
    """'RPDO3' for 0x1402, 'TPDO1' for 0x1800."""
    if TPDO_COMM <= comm < TPDO_COMM + PDO_SPAN:
        return 'TPDO%d' % (comm - TPDO_COMM + 1)
    return 'RPDO%d' % (comm - RPDO_COMM + 1)


def listed_pdos(od) -> list[int]:
    """The communication parameters (0x1400.., 0x1800..) an EDS lists, in order."""
    return sorted(index for base in (RPDO_COMM, TPDO_COMM)
                  for index in range(base, base + PDO_SPAN) if index in od)


def bridge_cob_ids(node_id: int) -> dict[int, str]:
    """The PDO COB-IDs the bridge configures on drive ``node_id``: {COB-ID: 'TPDO1'}."""
    return {plan.cob_id(node_id): '%s%d' % (plan.kind, plan.number) for plan in BRIDGE_PDOS}


class PdoRefused(BusConfigError):
    """A drive that does not take the PDO configuration; names the object.
    ``code``: the SDO abort code, None for a value read back that differs."""

    code: int | None = None

    @classmethod
    def aborted(cls, text: str, abort) -> PdoRefused:
        refused = cls(text)
        refused.code = abort.code
        return refused


class _Sdo:
    """The SDO transfers of one bring-up, each failure one line naming the object."""

    def __init__(self, node) -> None:
        # lazy: optional: canopen costs 273 ms; the simulated bus runs without it
        import canopen
        self.client = node.sdo
        self.aborted = canopen.SdoAbortedError

    def read(self, index: int, sub: int, layout: struct.Struct, why: str) -> int:
        try:
            data = self.client.upload(index, sub)
        except self.aborted as exc:
            raise PdoRefused.aborted('%s: 0x%04X:%02X refused the read (SDO abort %s)'
                                     % (why, index, sub, exc), exc) from None
        if len(data) < layout.size:
            raise PdoRefused('%s: 0x%04X:%02X read %d bytes, expected %d'
                             % (why, index, sub, len(data), layout.size))
        return layout.unpack_from(data)[0]

    def write(self, index: int, sub: int, layout: struct.Struct, value: int, why: str) -> None:
        try:
            self.client.download(index, sub, layout.pack(value))
        except self.aborted as exc:
            raise PdoRefused.aborted('%s: 0x%04X:%02X refused the write of 0x%X (SDO abort %s)'
                                     % (why, index, sub, value, exc), exc) from None


def configure_pdos(node, leg: LegDrive) -> list[str]:
    """Map the bridge's PDOs on ``leg``'s drive and switch the others off
    (see the module's doc). Call it in PRE-OPERATIONAL, before NMT start.

    Args:
        node: the master's ``canopen.RemoteNode`` of the drive (its ``sdo``
            client and object dictionary, from the leg's EDS).
        leg: the leg's entry of the device config.

    Returns:
        The PDOs it switched off ('TPDO3', ...), for the log.

    Raises:
        PdoRefused: a write aborted or a read-back that differs, naming the
            PDO, the object (0x1802:01) and the SDO abort code.
        canopen.SdoCommunicationError: the drive did not answer.
    """
    sdo = _Sdo(node)
    od = node.object_dictionary
    planned = {plan.comm: plan for plan in BRIDGE_PDOS}
    unused = [comm for comm in listed_pdos(od) if comm not in planned]
    done = []
    for comm in unused:
        why = '%s cannot be disabled' % pdo_name(comm)
        cob = sdo.read(comm, 1, U32, why)
        if not cob & PDO_INVALID:
            sdo.write(comm, 1, U32, cob | PDO_INVALID, why)
            done.append(pdo_name(comm))
    wrote = {}
    for plan in BRIDGE_PDOS:
        name = '%s%d' % (plan.kind, plan.number)
        why = '%s cannot be mapped' % name
        cob = sdo.read(plan.comm, 1, U32, why)
        if not cob & PDO_INVALID:           # 1. off: bit 31 only
            sdo.write(plan.comm, 1, U32, cob | PDO_INVALID, why)
        keep = cob & RTR_NOT_ALLOWED if plan.kind == 'TPDO' else 0
        new_cob = keep | plan.cob_id(leg.node_id)
        sdo.write(plan.comm, 1, U32, new_cob | PDO_INVALID, why)  # 2. its COB-ID, still off
        sdo.write(plan.comm, 2, U8, plan.trans_type, why)
        if plan.kind == 'TPDO' and plan.trans_type >= 254 and _has(od, plan.comm, EVENT_TIMER):
            sdo.write(plan.comm, EVENT_TIMER, U16, 0, why)        # on change only
        sdo.write(plan.mapping, 0, U8, 0, why)                   # 3. the mapping
        for sub, entry in enumerate(plan.entries(), start=1):
            sdo.write(plan.mapping, sub, U32, entry, why)
        sdo.write(plan.mapping, 0, U8, len(plan.objects), why)
        sdo.write(plan.comm, 1, U32, new_cob, why)               # 4. on
        wrote[plan.comm] = new_cob
    _read_back(sdo, wrote, unused)
    return done


def _has(od, index: int, sub: int) -> bool:
    try:
        od[index][sub]
    except (KeyError, TypeError):
        return False
    return True


def _read_back(sdo: _Sdo, wrote: dict[int, int], unused: list[int]) -> None:
    """Every PDO as the drive now has it against what was written."""
    def check(index, sub, layout, expected, mask, name):
        got = sdo.read(index, sub, layout, '%s read back' % name)
        if got & mask != expected & mask:
            raise PdoRefused('%s read back: 0x%04X:%02X is 0x%X, 0x%X was written'
                             % (name, index, sub, got, expected))
    for plan in BRIDGE_PDOS:
        name = '%s%d' % (plan.kind, plan.number)
        check(plan.comm, 1, U32, wrote[plan.comm], PDO_INVALID | 0x1FFFFFFF, name)
        check(plan.comm, 2, U8, plan.trans_type, 0xFF, name)
        check(plan.mapping, 0, U8, len(plan.objects), 0xFF, name)
        for sub, entry in enumerate(plan.entries(), start=1):
            check(plan.mapping, sub, U32, entry, 0xFFFFFFFF, name)
    for comm in unused:
        check(comm, 1, U32, PDO_INVALID, PDO_INVALID, pdo_name(comm))
