"""ODrive's CAN protocol ("CANSimple"): the second protocol beside CANopen.

This module is where a lab adds its own drive: a host side (``ODriveLegs``:
what the bridge's master does for CANopen, for ODrives) and a device side
(``FakeODrive``: what the plant's drives do, for tests), on any python-can
bus. The leg's scaling is the same ``core.machine.bus.LegDrive`` as for CANopen; an
ODrive counts motor turns, so a leg's length is
``offset_m + direction * turns * lead_m / gear_ratio`` and its torque
``direction * F * lead_m / (2 pi gear_ratio efficiency)`` newton-metres.

Frames (ODrive firmware 0.5/0.6, little-endian): arbitration id
``node_id << 5 | command``;

- 0x01 heartbeat (drive -> host): axis error u32, axis state u8, ...;
- 0x07 Set_Axis_State (host -> drive): requested state u32 (8: closed loop, 1: idle);
- 0x09 Get_Encoder_Estimates (drive -> host, cyclic or on a remote frame):
  position f32 [turns], velocity f32 [turns/s];
- 0x0B Set_Controller_Mode: control mode u32 (1: torque), input mode u32 (1: passthrough);
- 0x0E Set_Input_Torque (host -> drive): torque f32 [N m].

The bridge node speaks CANopen only in this release; this module is tested
against ``FakeODrive`` on the local bus (test/test_bus.py).
"""
from __future__ import annotations

import math
import struct

import can

from stewart63_ros.core.machine.bus import LegDrive

HEARTBEAT, SET_AXIS_STATE, ENCODER_ESTIMATES = 0x01, 0x07, 0x09
SET_CONTROLLER_MODE, SET_INPUT_TORQUE = 0x0B, 0x0E
AXIS_IDLE, AXIS_CLOSED_LOOP = 1, 8
TORQUE_CONTROL, PASSTHROUGH = 1, 1


def frame_id(node_id: int, command: int) -> int:
    """The arbitration id of ``command`` for ODrive axis ``node_id`` (0..63)."""
    return (node_id << 5) | command


def split_id(arbitration_id: int) -> tuple[int, int]:
    """(node id, command) of an arbitration id."""
    return arbitration_id >> 5, arbitration_id & 0x1F


def metres_per_turn(leg: LegDrive) -> float:
    """Leg length per motor turn [m]: the lead over the gear ratio."""
    return leg.lead_m / leg.gear_ratio


class ODriveLegs:
    """The host side: six legs on ODrive axes (node ids from the legs' config).

    Args:
        bus: a python-can bus.
        legs: the legs' ``LegDrive`` entries (node_id: the ODrive axis id).
    """

    def __init__(self, bus: can.BusABC, legs) -> None:
        self.bus = bus
        self.legs = {leg.node_id: leg for leg in legs}
        self.lengths = {leg.leg: math.nan for leg in legs}
        self.rates = {leg.leg: math.nan for leg in legs}
        self.axis_state = {leg.node_id: None for leg in legs}

    def _send(self, node_id: int, command: int, data: bytes) -> None:
        self.bus.send(can.Message(arbitration_id=frame_id(node_id, command), data=data,
                                  is_extended_id=False))

    def enable(self) -> None:
        """Torque control, passthrough, closed loop: each axis."""
        for node_id in self.legs:
            self._send(node_id, SET_CONTROLLER_MODE, struct.pack('<II', TORQUE_CONTROL,
                                                                 PASSTHROUGH))
            self._send(node_id, SET_AXIS_STATE, struct.pack('<I', AXIS_CLOSED_LOOP))

    def command(self, forces) -> None:
        """Each axis's input torque [N m] for its leg's force [N]."""
        for node_id, leg in self.legs.items():
            torque = leg.direction * float(forces[leg.leg]) / leg.newtons_per_nm
            self._send(node_id, SET_INPUT_TORQUE, struct.pack('<f', torque))

    def take(self, msg: can.Message) -> None:
        """A frame from the bus: encoder estimates and heartbeats are kept."""
        node_id, command = split_id(msg.arbitration_id)
        leg = self.legs.get(node_id)
        if leg is None:
            return
        if command == ENCODER_ESTIMATES and len(msg.data) >= 8:
            turns, turns_s = struct.unpack_from('<ff', msg.data)
            self.lengths[leg.leg] = leg.offset_m + leg.direction * turns * metres_per_turn(leg)
            self.rates[leg.leg] = leg.direction * turns_s * metres_per_turn(leg)
        elif command == HEARTBEAT and len(msg.data) >= 5:
            self.axis_state[node_id] = msg.data[4]


class FakeODrive:
    """The device side of one ODrive axis, for tests: it keeps the torque
    it is given (applied only in closed loop with torque control) and sends
    its encoder estimates for a leg length and rate (``answer``)."""

    def __init__(self, bus: can.BusABC, leg: LegDrive) -> None:
        self.bus = bus
        self.leg = leg
        self.state = AXIS_IDLE
        self.control_mode = 0
        self.torque = 0.0

    def take(self, msg: can.Message) -> None:
        node_id, command = split_id(msg.arbitration_id)
        if node_id != self.leg.node_id:
            return
        if command == SET_AXIS_STATE:
            self.state = struct.unpack_from('<I', msg.data)[0]
        elif command == SET_CONTROLLER_MODE:
            self.control_mode = struct.unpack_from('<I', msg.data)[0]
        elif command == SET_INPUT_TORQUE:
            self.torque = struct.unpack_from('<f', msg.data)[0]

    @property
    def force(self) -> float:
        """The piston force [N] it applies: none unless closed-loop torque control."""
        if self.state != AXIS_CLOSED_LOOP or self.control_mode != TORQUE_CONTROL:
            return 0.0
        return self.leg.direction * self.torque * self.leg.newtons_per_nm

    def answer(self, length: float, rate: float) -> None:
        """Its encoder estimates and heartbeat for a leg length [m] and rate [m/s]."""
        per_turn = metres_per_turn(self.leg)
        turns = self.leg.direction * (length - self.leg.offset_m) / per_turn
        self.bus.send(can.Message(
            arbitration_id=frame_id(self.leg.node_id, ENCODER_ESTIMATES),
            data=struct.pack('<ff', turns, self.leg.direction * rate / per_turn),
            is_extended_id=False))
        self.bus.send(can.Message(arbitration_id=frame_id(self.leg.node_id, HEARTBEAT),
                                  data=struct.pack('<IBBBx', 0, self.state, 0, 0),
                                  is_extended_id=False))
