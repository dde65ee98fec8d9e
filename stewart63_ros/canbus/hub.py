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
        if self.gone:
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

    def hold(self) -> None:
        """Keep the frames sent from now on until ``release``, which writes
        them to each peer at once: a reader wakes once for a drive set's
        answers to a SYNC, not once a frame (see ``batched``)."""
        with self._send_lock:
            if self._held is None:
                self._held = bytearray()

    def release(self) -> None:
        """Send what was held since ``hold``, in order, and stop holding."""
        with self._send_lock:
            held, self._held = self._held, None
            if held:
                self._write(bytes(held))

    def _take(self):
        """A record already read from a peer, or None."""
        size = RECORD.size
        for peer in self._peers:
            if len(peer.buffer) >= size:
                record = bytes(peer.buffer[:size])
                del peer.buffer[:size]
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
        finally:
            super().shutdown()

    @staticmethod
    def _detect_available_configs():
        return []


@contextlib.contextmanager
def batched(buses):
    """Within the block, the frames sent on the ``s63hub`` buses among
    ``buses`` go out together at its end, one write per bus and peer (other
    interfaces send as usual): what a device set sends in answer to one SYNC."""
    held = [bus for bus in buses if isinstance(bus, HubBus)]
    for bus in held:
        bus.hold()
    try:
        yield
    finally:
        for bus in held:
            bus.release()


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
