"""``s63hub``: a python-can interface linking the processes of one machine.

This kernel has no ``vcan`` module, and python-can's ``udp_multicast``
interface lost 148 of 1000 frames sent in one burst here (datagrams dropped
by a full receive buffer). This interface loses none: every bus of a channel
is a stream connection to one hub process (a Unix-domain socket in the
abstract namespace: loopback only, no file left behind), which forwards each
frame, in order, to every other bus of the channel, as a CAN bus does. A
stream never drops: a reader that falls behind holds the hub back
(back-pressure), never loses a frame.

The first bus opened on a channel starts its hub (``python -m
stewart63_ros.canbus.hub CHANNEL``, its own session); the hub ends once its
last bus has closed. Use it as any python-can interface::

    can.Bus(interface='s63hub', channel='rig')

(registered under python-can's ``can.interface`` entry points by setup.py).
Classic CAN frames only (up to 8 data bytes); no bit timing is modelled: a
frame takes as long as the sockets take (tens of microseconds), so the bus
load is computed, not felt (core/bus.py, docs/bus.md).
"""
from __future__ import annotations

import collections
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
#: s: how long a new bus waits for the hub it started to listen
HUB_START_TIMEOUT = 5.0
#: s: a hub with no bus left ends after this long (a bus opening just then finds it)
HUB_IDLE_GRACE = 1.0


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
    """A stream to ``channel``'s hub, started first if none runs."""
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
        self._sock = connect(self.channel)
        self._buffer = bytearray()
        self._own = collections.deque() if receive_own_messages else None
        self._send_lock = threading.Lock()
        #: the hub closed this bus's stream (it ended): the bus is silent from
        #: then on, as a pulled cable is, and sending fails
        self.gone = False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        record = pack(msg)
        with self._send_lock:
            try:
                self._sock.sendall(record)
            except OSError as exc:
                raise can.CanOperationError('s63hub: the hub is gone (%s)' % exc) from exc
        if self._own is not None:
            self._own.append(record)

    def _recv_internal(self, timeout: float | None):
        if self._own:
            return unpack(self._own.popleft(), self.channel), False
        size = RECORD.size
        if self.gone:
            time.sleep(timeout or 0.0)
            return None, False
        if len(self._buffer) < size:
            ready, _, _ = select.select([self._sock], [], [], timeout)
            if not ready:
                return None, False
            try:
                chunk = self._sock.recv(65536)
            except OSError as exc:
                raise can.CanOperationError('s63hub: the hub is gone (%s)' % exc) from exc
            if not chunk:           # the hub ended: silence, not an error in the reader
                self.gone = True
                return None, False
            self._buffer += chunk
            if len(self._buffer) < size:
                return None, False
        record = bytes(self._buffer[:size])
        del self._buffer[:size]
        return unpack(record, self.channel), False

    def fileno(self) -> int:
        return self._sock.fileno()

    def shutdown(self) -> None:
        try:
            self._sock.close()
        finally:
            super().shutdown()

    @staticmethod
    def _detect_available_configs():
        return []


def serve(channel: str) -> None:
    """The hub of ``channel``: forward every record to every other bus, in
    order, until no bus has been connected for HUB_IDLE_GRACE s."""
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        listener.bind(address(channel))
    except OSError:         # another hub won the race: it serves the channel
        return
    listener.listen(64)
    clients: dict[int, tuple[socket.socket, bytearray]] = {}
    size = RECORD.size
    idle_since = time.monotonic()
    while clients or time.monotonic() - idle_since < HUB_IDLE_GRACE:
        ready, _, _ = select.select([listener] + [c for c, _ in clients.values()], [], [], 0.2)
        for sock in ready:
            if sock is listener:
                client, _ = listener.accept()
                clients[client.fileno()] = (client, bytearray())
                continue
            own, buffer = clients[sock.fileno()]
            try:
                chunk = sock.recv(65536)
            except OSError:
                chunk = b''
            if not chunk:
                del clients[sock.fileno()]
                sock.close()
                if not clients:
                    idle_since = time.monotonic()
                continue
            buffer += chunk
            whole = len(buffer) - len(buffer) % size
            if not whole:
                continue
            out = bytes(buffer[:whole])
            del buffer[:whole]
            for fd, (other, _) in list(clients.items()):
                if other is own:
                    continue
                try:
                    other.sendall(out)      # blocks while that reader is full: no loss
                except OSError:
                    clients.pop(fd, None)
                    other.close()
    listener.close()


if __name__ == '__main__':
    serve(sys.argv[1])
