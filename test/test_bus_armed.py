"""Answers armed for a SYNC on the local bus (``s63hub``, canbus/hub.py).

A drive's answers to a SYNC leave the moment the SYNC passes, whenever the
process standing in for the drive wakes: every reader (the master, a
sniffer) gets them after that SYNC and stamped after it, never before it,
never held for the SYNC after.
"""
from __future__ import annotations

import threading
import time
import uuid

import can
import pytest

from stewart63_ros.canbus.hub import ARM_MAX, batched, can_arm


def frame(cob_id, data=b''):
    return can.Message(arbitration_id=cob_id, data=data, is_extended_id=False)


def drain(bus, wait=0.05):
    return list(iter(lambda: bus.recv(wait), None))


@pytest.fixture
def wire():
    """A master, a drive and a sniffer on one channel of this test's own."""
    channel = 'arm%s' % uuid.uuid4().hex[:8]
    buses = [can.Bus(interface='s63hub', channel=channel) for _ in range(3)]
    yield buses
    for bus in buses:
        bus.shutdown()


def sync_seen_by(master, drive):
    """The master sends a SYNC; the stamp the drive reads on it."""
    master.send(frame(0x80))
    msg = drive.recv(2.0)
    assert msg is not None and msg.arbitration_id == 0x80
    return msg.timestamp


def test_armed_answers_wait_for_the_next_sync_and_come_after_it_in_order(wire):
    master, drive, sniffer = wire
    last = sync_seen_by(master, drive)
    drain(sniffer)
    with batched([drive], {drive: last}):
        drive.send(frame(0x181, b'\x01\x02'))
        drive.send(frame(0x281, b'\x03'))
    assert drain(master) == [] and drain(sniffer) == []     # not on the wire yet
    master.send(frame(0x80))
    got = drain(master)
    seen = drain(sniffer)
    assert [m.arbitration_id for m in got] == [0x181, 0x281]
    assert [m.arbitration_id for m in seen] == [0x80, 0x181, 0x281]
    sync_stamp = seen[0].timestamp
    assert sync_stamp < got[0].timestamp < got[1].timestamp < sync_stamp + 1e-3
    assert [m.timestamp for m in seen[1:]] == [m.timestamp for m in got]
    assert bytes(got[0].data) == b'\x01\x02'


def test_an_answer_armed_after_its_sync_passed_goes_out_at_once_not_a_sync_later(wire):
    master, drive, sniffer = wire
    last = sync_seen_by(master, drive)
    master.send(frame(0x80))                # the drive has not read this one yet
    time.sleep(0.01)
    armed_at = time.time()
    with batched([drive], {drive: last}):
        drive.send(frame(0x181, b'\x05'))
    got = master.recv(1.0)
    assert got is not None and got.arbitration_id == 0x181
    assert got.timestamp >= armed_at        # when it went out: armed after the SYNC
    assert [m.arbitration_id for m in drain(sniffer)][-2:] == [0x80, 0x181]


def test_a_reader_blocked_in_recv_wakes_when_its_own_sync_releases_answers(wire):
    # (the master's notifier thread waits in recv while its loop sends the SYNC)
    master, drive, _ = wire
    last = sync_seen_by(master, drive)
    with batched([drive], {drive: last}):
        drive.send(frame(0x183))
    time.sleep(0.02)
    assert master.recv(0.01) is None        # read and held for the SYNC
    got = []
    reader = threading.Thread(target=lambda: got.append(master.recv(5.0)))
    reader.start()
    time.sleep(0.05)
    master.send(frame(0x80))
    reader.join(6.0)
    assert got and got[0] is not None and got[0].arbitration_id == 0x183


def test_a_set_larger_than_one_arming_record_counts_arrives_whole_and_in_order(wire):
    master, drive, _ = wire
    last = sync_seen_by(master, drive)
    n = ARM_MAX + 45
    with batched([drive], {drive: last}):
        for i in range(n):
            drive.send(frame(0x181, i.to_bytes(2, 'little')))
    master.send(frame(0x80))
    got = drain(master, 0.2)
    assert [int.from_bytes(m.data, 'little') for m in got] == list(range(n))


def test_frames_sent_without_arming_go_out_at_once_and_only_the_local_bus_arms(wire):
    master, drive, _ = wire
    with batched([drive]):
        drive.send(frame(0x701, b'\x05'))
    assert [m.arbitration_id for m in drain(master)] == [0x701]
    assert can_arm([master, drive])
    virtual = can.Bus(interface='virtual', channel='arm-%s' % uuid.uuid4().hex[:6])
    try:
        assert not can_arm([drive, virtual])
        with pytest.raises(ValueError, match='only s63hub'):
            with batched([virtual], {virtual: 0.0}):
                pass
    finally:
        virtual.shutdown()
