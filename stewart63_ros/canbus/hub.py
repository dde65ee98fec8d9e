"""``s63hub``: a python-can interface linking the processes of one machine.

This kernel has no ``vcan`` module, and python-can's ``udp_multicast``
interface lost 148 of 1000 frames sent in one burst here (datagrams dropped
by a full receive buffer). This interface loses none: the buses of a channel
are linked pairwise by stream connections (Unix-domain socket pairs), and a
frame sent on one is written to every other, in order, as a CAN bus carries
it to every node. A stream never drops: a reader that falls behind holds its
senders back (back-pressure), never loses a frame.

The hub of a channel (one process, a Unix-domain socket in the abstract
namespace: loopback only, no file left behind) only introduces the buses:
when one opens, the hub makes a socket pair for it and each bus already
there, and hands the two ends over (SCM_RIGHTS). Frames never pass through
the hub: one hop from sender to reader, not two (at 1 kHz the hub's
forwarding cost two more process wake-ups per frame, on each bus; docs/bus.md).
The first bus opened on a channel starts its hub (``python -m
stewart63_ros.canbus.hub CHANNEL``, its own session); the hub ends once its
last bus has closed. Use it as any python-can interface::

    can.Bus(interface='s63hub', channel='rig')

(registered under python-can's ``can.interface`` entry points by setup.py).

**Frames armed for the next SYNC.** A drive's answer to a SYNC leaves on
the wire the moment the SYNC passes: its CAN controller holds the frames
(a SYNC-triggered transmit mailbox), the drive's processor does not have to
wake in time. A process standing in for drives does the same with
``batched(buses, after_sync=...)``: the frames go to every peer at once,
marked to be delivered right after the first SYNC (COB-ID 0x80) stamped
later than ``after_sync`` (the stamp of the last SYNC the sender saw). A
reader keeps them until it sees that SYNC, its own or a peer's, then gives
them out after it, stamped just after the SYNC (or, if the SYNC had already
passed when they were armed, at the time they were armed): on the wire
they are the answer to that SYNC, whichever side is slow to wake. On a
machine whose kernel does not preempt (this one's: ``PREEMPT_NONE``) a
process woken for a SYNC can wait a millisecond for its CPU; armed
answers take that wait out of the SYNC's window (docs/bus.md). A reader
that opened after the SYNC an armed set refers to holds it until the next
SYNC.

What it guarantees: every frame sent after a bus's ``can.Bus(...)`` returned
reaches that bus, and the frames of one sender arrive in the order sent;
frames of two senders may interleave differently at two readers (a CAN bus
orders them once, by arbitration). A bus that closes is dropped by its peers
(a pulled cable: silence). Classic CAN frames only (up to 8 data bytes); no
bit timing is modelled: a frame takes as long as a socket write takes (a few
microseconds), so the bus load is computed, not felt (core/machine/bus.py, docs/bus.md).
"""
from __future__ import annotations

import collections
import contextlib
import math
import os
import select
import socket
import struct
import subprocess
import sys
import threading
import time

import can

#: one frame on the stream: timestamp, arbitration id, flags, dlc, 8 data bytes
RECORD = struct.Struct('<dIBB8s')
EXTENDED, REMOTE, ERROR = 1, 2, 4
#: flags of a record that is no frame: the next ``dlc`` records are armed for
#: the first SYNC stamped after this record's timestamp (see the module's doc)
ARM = 16
#: the SYNC's COB-ID (CiA 301 0x1005's default, the one the bridge sends)
SYNC_COB_ID = 0x80
#: records of one armed set at most (a record's dlc byte counts them)
ARM_MAX = 255
#: s: the frames released by a SYNC are stamped this far apart after it, in order
ARM_SPACING = 1e-6
#: armed sets a reader keeps for SYNCs to come at most (the oldest go)
ARM_PENDING_MAX = 64
#: the flags' byte in a record (the count of an armed set follows it)
FLAGS_AT = 12
#: s: how long a new bus waits for the hub it started to listen, and for its introduction
HUB_START_TIMEOUT = 5.0
#: s: a hub with no bus left ends after this long (a bus opening just then finds it)
HUB_IDLE_GRACE = 1.0
#: the hub's words on a bus's control stream: the peers already there (to a
#: new bus, with their ends), one new peer (to the others, with its end)
PEERS, NEW_PEER = b'N', b'P'
#: file descriptors in one SCM_RIGHTS message (Linux's SCM_MAX_FD)
MAX_FDS = 253


def address(channel: str) -> bytes:
    """The hub's socket address for ``channel`` (Linux abstract namespace)."""
    if not channel or '\0' in channel or len(channel) > 80:
        raise ValueError('s63hub channel must be a short non-empty name, got %r' % (channel,))
    return b'\0stewart63-can/' + channel.encode()


def pack(msg: can.Message) -> bytes:
    """``msg`` as one record of the stream."""
    if msg.is_fd or msg.dlc > 8:
        raise can.CanOperationError('s63hub carries classic CAN frames (at most 8 bytes)')
    flags = (EXTENDED if msg.is_extended_id else 0) | (REMOTE if msg.is_remote_frame else 0) \
        | (ERROR if msg.is_error_frame else 0)
    data = bytes(msg.data)
    return RECORD.pack(msg.timestamp or time.time(), msg.arbitration_id, flags,
                       msg.dlc, data.ljust(8, b'\0'))


def unpack(record: bytes, channel: str) -> can.Message:
    stamp, arbitration_id, flags, dlc, data = RECORD.unpack(record)
    return can.Message(timestamp=stamp, arbitration_id=arbitration_id,
                       is_extended_id=bool(flags & EXTENDED), is_remote_frame=bool(flags & REMOTE),
                       is_error_frame=bool(flags & ERROR), dlc=dlc,
                       data=data[:dlc] if not flags & REMOTE else None, channel=channel)


def _connect(channel: str) -> socket.socket | None:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.connect(address(channel))
    except (ConnectionRefusedError, FileNotFoundError):
        sock.close()
        return None
    return sock


def connect(channel: str) -> socket.socket:
    """The control stream to ``channel``'s hub, started first if none runs."""
    sock = _connect(channel)
    if sock is not None:
        return sock
    subprocess.Popen([sys.executable, '-m', 'stewart63_ros.canbus.hub', channel],
                     stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                     stderr=subprocess.DEVNULL, start_new_session=True, close_fds=True)
    deadline = time.monotonic() + HUB_START_TIMEOUT
    while time.monotonic() < deadline:
        sock = _connect(channel)
        if sock is not None:
            return sock
        time.sleep(0.01)
    raise can.CanInitializationError('s63hub: the hub of channel %r did not start within %g s'
                                     % (channel, HUB_START_TIMEOUT))


class Peer:
    """The stream to one other bus of the channel, and what came on it."""

    __slots__ = ('sock', 'buffer')

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.buffer = bytearray()


class HubBus(can.BusABC):
    """One bus on a hub channel (see the module's doc).

    Args:
        channel: the channel's name; the buses of one name are one CAN bus.
        receive_own_messages: also receive the frames this bus sends.
        bitrate: accepted for the interface's sake; the hub does not pace.
    """

    def __init__(self, channel: str = 'default', can_filters=None,
                 receive_own_messages: bool = False, bitrate: int | None = None, **kwargs):
        super().__init__(channel, can_filters=can_filters, **kwargs)
        self.channel = str(channel)
        self.channel_info = 's63hub channel %s' % self.channel
        self.bitrate = bitrate
        self._own = collections.deque() if receive_own_messages else None
        self._send_lock = threading.Lock()
        self._peer_lock = threading.Lock()
        #: the other buses (a tuple, replaced whole: a sender and a reader in
        #: two threads each see a consistent one)
        self._peers: tuple[Peer, ...] = ()
        self._by_fd: dict[int, Peer] = {}
        #: readable when a peer sent or the hub spoke (one descriptor for
        #: ``fileno``, which callers select on)
        self._poll = select.epoll()
        #: the hub ended: no bus opened later will reach this one
        self.gone = False
        #: the records sent since ``hold`` (None: each goes out as it is sent)
        self._held: bytearray | None = None
        #: armed sets read from peers whose SYNC has not passed here yet:
        #: (the stamp of the SYNC before theirs, their records)
        self._pending: list[tuple[float, list[bytes]]] = []
        #: records an armed set gave out after its SYNC, in order, to read first
        self._released: collections.deque[bytes] = collections.deque()
        #: the stamp of the newest SYNC this bus has seen, its own or a peer's
        self._last_sync = -math.inf
        self._arm_lock = threading.Lock()
        #: written when records are released (a reader blocked in ``poll``
        #: wakes when a SYNC this bus sends releases some)
        self._wake = os.eventfd(0, os.EFD_NONBLOCK)
        self._poll.register(self._wake, select.EPOLLIN)
        self._control = connect(self.channel)
        self._control.settimeout(HUB_START_TIMEOUT)
        try:
            word, fds = self._hear()
        except OSError as exc:
            self._control.close()
            raise can.CanInitializationError('s63hub: no introduction from the hub of %r: %s'
                                             % (self.channel, exc)) from None
        if word != PEERS:
            raise can.CanInitializationError('s63hub: the hub of %r said %r, not its peers'
                                             % (self.channel, word))
        self._control.setblocking(False)
        self._poll.register(self._control.fileno(), select.EPOLLIN)
        #: the control stream alone: a write looks at it for introductions
        #: (a poll, not a failed receive: a quarter of the cost, each write)
        self._control_poll = select.poll()
        self._control_poll.register(self._control.fileno(), select.POLLIN)
        self._add(fds)

    # -- the hub's introductions ---------------------------------------------------------
    def _hear(self, flags: int = 0) -> tuple[bytes, list[int]]:
        word, fds, _, _ = socket.recv_fds(self._control, 1, MAX_FDS, flags)
        return word, fds

    def _add(self, fds) -> None:
        with self._peer_lock:
            peers = list(self._peers)
            for fd in fds:
                peer = Peer(socket.socket(fileno=fd))
                self._by_fd[fd] = peer
                self._poll.register(fd, select.EPOLLIN)
                peers.append(peer)
            self._peers = tuple(peers)

    def _drop(self, peer: Peer) -> None:
        """A peer closed (its process ended): silence from it, as a pulled cable."""
        with self._peer_lock:
            if peer not in self._peers:
                return
            self._peers = tuple(p for p in self._peers if p is not peer)
            fd = peer.sock.fileno()
            self._by_fd.pop(fd, None)
            try:
                self._poll.unregister(fd)
            except (OSError, ValueError):
                pass
            peer.sock.close()

    def _introductions(self) -> None:
        """Take the peers the hub introduced since (without waiting)."""
        if self.gone or not self._control_poll.poll(0):
            return
        while True:
            try:
                word, fds = self._hear(socket.MSG_DONTWAIT)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                word, fds = b'', []
            if not word:                # the hub ended: the peers there are stay
                self.gone = True
                with self._peer_lock:
                    try:
                        self._poll.unregister(self._control.fileno())
                    except (OSError, ValueError):
                        pass
                return
            self._add(fds)

    # -- frames ----------------------------------------------------------------------------
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        record = pack(msg)
        with self._send_lock:
            if self._held is not None:
                self._held += record
            else:
                self._write(record)
        if self._own is not None:
            self._own.append(record)

    def _write(self, records: bytes) -> None:
        self._introductions()       # a bus opened just now hears these frames
        for peer in self._peers:
            try:
                peer.sock.sendall(records)  # blocks while that reader is full: no loss
            except OSError:
                self._drop(peer)
        size = RECORD.size
        for start in range(0, len(records), size):    # its own SYNC passes here too
            if is_sync(records, start):
                self._synced(RECORD.unpack_from(records, start)[0])

    def hold(self) -> None:
        """Keep the frames sent from now on until ``release``, which writes
        them to each peer at once: a reader wakes once for a drive set's
        answers to a SYNC, not once a frame (see ``batched``)."""
        with self._send_lock:
            if self._held is None:
                self._held = bytearray()

    def release(self, after_sync: float | None = None) -> None:
        """Send what was held since ``hold``, in order, and stop holding.
        ``after_sync``: arm them instead, for the first SYNC stamped later
        than this (the last SYNC the sender saw; see the module's doc)."""
        with self._send_lock:
            held, self._held = self._held, None
            if not held:
                return
            if after_sync is not None:
                held = armed(bytes(held), after_sync)
            self._write(bytes(held))

    # -- armed sets: delivered after their SYNC --------------------------------------------
    def _arm(self, after: float, records: list[bytes]) -> None:
        with self._arm_lock:
            if after < self._last_sync:         # its SYNC has passed here: out now
                self._give_out(records, self._last_sync)
            else:
                self._pending.append((after, records))
                del self._pending[:-ARM_PENDING_MAX]

    def _synced(self, stamp: float) -> None:
        """A SYNC stamped ``stamp`` passed: the sets armed for it go out."""
        with self._arm_lock:
            self._last_sync = max(self._last_sync, stamp)
            if not self._pending:
                return
            waiting = []
            for after, records in self._pending:
                if after < stamp:
                    self._give_out(records, stamp)
                else:
                    waiting.append((after, records))
            self._pending = waiting

    def _give_out(self, records: list[bytes], sync_stamp: float) -> None:
        """(under ``_arm_lock``) ``records`` to be read next, each stamped
        when it went on the wire: just after the SYNC, or when it was armed
        if that was later."""
        for i, record in enumerate(records):
            out = bytearray(record)
            own = RECORD.unpack_from(out)[0]
            struct.pack_into('<d', out, 0, max(own, sync_stamp + ARM_SPACING * (i + 1)))
            self._released.append(bytes(out))
        os.eventfd_write(self._wake, 1)

    def _take(self):
        """The next record to read: one an armed set gave out after its
        SYNC, else one already read from a peer, or None (an armed set read
        on the way is kept for its SYNC; a SYNC releases the sets armed for it)."""
        if self._released:
            return self._released.popleft()
        size = RECORD.size
        for peer in self._peers:
            buffer = peer.buffer
            while len(buffer) >= size:
                if buffer[FLAGS_AT] & ARM:
                    count = buffer[FLAGS_AT + 1]
                    if len(buffer) < size * (count + 1):
                        break                   # the rest of the set is on its way
                    after = RECORD.unpack_from(buffer)[0]
                    records = [bytes(buffer[size * i:size * (i + 1)]) for i in range(1, count + 1)]
                    del buffer[:size * (count + 1)]
                    self._arm(after, records)
                    if self._released:          # its SYNC had passed: out now
                        return self._released.popleft()
                    continue
                record = bytes(buffer[:size])
                del buffer[:size]
                if is_sync(record):
                    self._synced(RECORD.unpack_from(record)[0])
                return record
        return None

    def _recv_internal(self, timeout: float | None):
        if self._own:
            return unpack(self._own.popleft(), self.channel), False
        record = self._take()
        if record is not None:
            return unpack(record, self.channel), False
        try:
            ready = self._poll.poll(-1 if timeout is None else max(0.0, timeout))
        except InterruptedError:
            return None, False
        for fd, _ in ready:
            if fd == self._control.fileno():
                self._introductions()
                continue
            if fd == self._wake:                # (read: it wakes a wait once)
                try:
                    os.eventfd_read(self._wake)
                except BlockingIOError:
                    pass
                continue
            peer = self._by_fd.get(fd)
            if peer is None:
                continue
            try:
                chunk = peer.sock.recv(65536)
            except BlockingIOError:
                continue
            except OSError:
                chunk = b''
            if not chunk:
                self._drop(peer)
                continue
            peer.buffer += chunk
        record = self._take()
        return (unpack(record, self.channel) if record is not None else None), False

    def fileno(self) -> int:
        return self._poll.fileno()

    def shutdown(self) -> None:
        try:
            with self._peer_lock:
                for peer in self._peers:
                    peer.sock.close()
                self._peers = ()
                self._control.close()
                self._poll.close()
                os.close(self._wake)
        finally:
            super().shutdown()

    @staticmethod
    def _detect_available_configs():
        return []


@contextlib.contextmanager
def batched(buses, after_sync: dict | None = None):
    """Within the block, the frames sent on the ``s63hub`` buses among
    ``buses`` go out together at its end, one write per bus and peer (other
    interfaces send as usual): what a device set sends in answer to one SYNC.

    ``after_sync``: {bus: the stamp of the last SYNC it saw}: the frames of
    those buses are armed for the SYNC after that one instead (see the
    module's doc; every bus in it must be an ``s63hub`` bus, ``can_arm``)."""
    after_sync = after_sync or {}
    if not can_arm(after_sync):
        raise ValueError('s63hub: only s63hub buses arm frames for a SYNC')
    held = [bus for bus in buses if isinstance(bus, HubBus)]
    for bus in held:
        bus.hold()
    try:
        yield
    finally:
        for bus in held:
            bus.release(after_sync.get(bus))


def can_arm(buses) -> bool:
    """Whether every bus of ``buses`` can arm frames for a SYNC (``s63hub``)."""
    return all(isinstance(bus, HubBus) for bus in buses)


def is_sync(records: bytes, at: int = 0) -> bool:
    """Whether the record at ``at`` is a SYNC: COB-ID 0x80, no data or a counter."""
    # (bytes compared, not unpacked: every write is looked at)
    return records[at + 8:at + 14] in _SYNC_HEADS


#: a SYNC record's bytes after its stamp: COB-ID 0x80, no flags, dlc 0 or 1
_SYNC_HEADS = frozenset(struct.pack('<IBB', SYNC_COB_ID, 0, dlc) for dlc in (0, 1))


def armed(records: bytes, after_sync: float) -> bytes:
    """``records`` as armed sets for the first SYNC stamped after ``after_sync``."""
    size = RECORD.size
    out = bytearray()
    for start in range(0, len(records), size * ARM_MAX):
        chunk = records[start:start + size * ARM_MAX]
        out += RECORD.pack(after_sync, 0, ARM, len(chunk) // size, bytes(8)) + chunk
    return bytes(out)


def _introduce(newcomer: socket.socket, clients: dict[int, socket.socket]) -> None:
    """Link ``newcomer`` with every bus already on the channel: a socket pair
    each, one end to that bus (first, so that it hears the newcomer from
    then on), the other ends to the newcomer."""
    ends = []
    for other in list(clients.values()):
        mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            socket.send_fds(other, [NEW_PEER], [theirs.fileno()])
        except OSError:             # it is closing: no link
            mine.close()
        else:
            ends.append(mine)
        theirs.close()
    for start in range(0, max(len(ends), 1), MAX_FDS):
        batch = ends[start:start + MAX_FDS]
        socket.send_fds(newcomer, [PEERS if start == 0 else NEW_PEER], [e.fileno() for e in batch])
    for end in ends:
        end.close()


def serve(channel: str) -> None:
    """The hub of ``channel``: introduce every bus that opens to the others,
    until no bus has been connected for HUB_IDLE_GRACE s."""
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        listener.bind(address(channel))
    except OSError:         # another hub won the race: it serves the channel
        return
    listener.listen(64)
    clients: dict[int, socket.socket] = {}
    idle_since = time.monotonic()
    while clients or time.monotonic() - idle_since < HUB_IDLE_GRACE:
        ready, _, _ = select.select([listener] + list(clients.values()), [], [], 0.2)
        for sock in ready:
            if sock is listener:
                client, _ = listener.accept()
                try:
                    _introduce(client, clients)
                except OSError:
                    client.close()
                    continue
                clients[client.fileno()] = client
                continue
            try:                    # a bus never writes here: this is its close
                gone = not sock.recv(64)
            except OSError:
                gone = True
            if gone:
                clients.pop(sock.fileno(), None)
                sock.close()
                if not clients:
                    idle_since = time.monotonic()
    listener.close()


if __name__ == '__main__':
    serve(sys.argv[1])
