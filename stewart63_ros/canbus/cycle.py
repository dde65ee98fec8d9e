"""The master's cycle, the receive side: which SYNC each frame answers
(mixed into canbus/master.py's ``Master``).

Frames arrive in the ``canopen`` library's notifier thread, each with its
reception time (python-can's stamp: SocketCAN's kernel time, ``s63hub``'s
time the frame went on the hub; a stamp more than 10 s from the wall clock
is no reception time and is replaced by the time the frame is read). A
TPDO1 belongs to the SYNC whose window it was received in (canbus/sync.py),
whenever the bridge's loop gets round to it: sample k holds only TPDOs
received between SYNC k and the close of its window (``missing``); one
received later is late, counted (``Link.late_tpdo``), never another
sample's reading. A drive that did not answer the SYNC before may be
answering that one late: its first TPDO in a window is firm only once the
window's settle time has passed or a second one came (then the second is
this SYNC's and the first was late). A missing TPDO leaves that leg NaN in
the sample, in lockstep and realtime alike. Heartbeats are judged on their
reception times (realtime) or on the run's time (lockstep, where the
plant's drives beat in run time).

**Where frames are read.** Until the realtime loop starts, each bus has the
library's notifier thread (SDO answers during the bring-up need it). The
realtime loop reads its buses itself (``receive_in_loop``): it drains them
when it sends a SYNC and while it waits for the cycle's TPDOs (a ``select``
on the buses, not a condition the notifier threads signal), so a cycle
wakes one thread of the bridge, not three, and no frame waits for the GIL
between two threads. Anything that needs answers while the loop is not
reading (an SDO: a drive brought up again, a home offset, the safe stop)
runs ``receiving_in_threads``, which gives the buses their notifier threads
back for its duration. Frames go through the same listeners either way
(canopen's dispatch, the wire's load count).

No ROS here.
"""
from __future__ import annotations

import contextlib
import math
import select
import struct
import time

import can

from stewart63_ros.core.machine.bus import frame_bits

#: s: a frame's stamp further than this from the wall clock is not a reception time
STAMP_TRUST = 10.0
#: s: the longest the safe stop sleeps before it looks at the clock again
SETTLE_POLL = 0.005
#: s: a notifier thread's wait per turn (the library's 1 s, one per bus, made a
#: stopping bridge miss the launcher's 3.5 s deadline)
NOTIFIER_CYCLE = 0.1


class CycleSide:
    """The receive side and the cycle's window (see the module's doc); a
    ``link`` is a drive's ``master.Link``.
    Uses the master's ``links``, ``windows``, ``networks``, ``bits``,
    ``received_to``, ``rate``, ``clock``, ``heartbeat_limit``,
    ``tpdo_error_cycles`` and its lock ``_arrived``."""

    # -- frames in (the notifier's thread) --------------------------------------------------
    def _received(self, link, timestamp: float, data_bytes: int) -> float:
        """Count a frame's bits and note how far the receive side has got;
        its reception time (python-can's stamp; now if the interface has none)."""
        now = time.time()
        # (an interface whose stamps are not wall-clock times, a device's own
        # clock say, is judged on when the frame is read)
        stamp = timestamp if timestamp and abs(timestamp - now) < STAMP_TRUST else now
        self.bits[link.leg.bus] += frame_bits(min(data_bytes, 8))
        if stamp > self.received_to[link.leg.bus]:
            self.received_to[link.leg.bus] = stamp
        return stamp

    def _on_tpdo1(self, link):
        unpack = link.tpdo_struct.unpack_from

        def on(cob_id, data, timestamp):
            stamp = self._received(link, timestamp, len(data))
            if len(data) < link.tpdo_struct.size:
                return
            with self._arrived:
                self._take_tpdo(link, unpack(data), self.windows.window_of(stamp))
        return on

    def _take_tpdo(self, link, values, sync: int | None) -> None:
        """A TPDO1 received in the window of SYNC ``sync`` (under the lock).

        It is the cycle's reading only while the cycle's window is open;
        after that it is late (counted, never another sample's reading). A
        drive that did not answer the SYNC before may be answering that one
        late: its first TPDO in this window is not firm until the window's
        end (or a second one comes, which is this SYNC's: the first was late).
        """
        if sync is None:                # before any SYNC remembered: no answer to one
            return
        if link.answered is None or sync > link.answered:
            previous, link.answered = link.answered, sync
        else:
            previous = sync - 1
        if sync != self.cycle or not self._open:
            link.late_tpdo += 1
            return
        if link.tpdo_sync == sync:      # a second TPDO in this window: the first was late
            link.late_tpdo += 1
            link.tpdo_firm = True
        else:
            link.tpdo_firm = previous is None or previous >= sync - 1
        link.tpdo = values
        link.tpdo_sync = sync
        link.tpdo_taken_at = time.monotonic()
        if not self._awaited():         # the cycle's waiter wakes once, not once a drive
            self._arrived.notify()

    def _on_tpdo2(self, link):
        def on(cob_id, data, timestamp):
            self._received(link, timestamp, len(data))
            if len(data) >= link.status_struct.size:
                link.statusword = link.status_struct.unpack_from(data)[0]
                with self._arrived:
                    self._arrived.notify()
        return on

    def _on_emcy(self, link):
        def on(cob_id, data, timestamp):
            self._received(link, timestamp, len(data))
            if len(data) >= 2:
                link.emcy_code = struct.unpack_from('<H', data)[0]
                link.emcys += 1
        return on

    def _on_heartbeat(self, link):
        def on(cob_id, data, timestamp):
            if not data:
                return
            stamp = self._received(link, timestamp, 1)
            if data[0] == 0:            # boot-up: configured from scratch again
                link.booted = True
                link.up = False
            sync = self.windows.window_of(stamp)
            link.heartbeat = (max(sync if sync is not None else 0, 0), stamp)
        return on

    def heartbeat_age(self, link) -> float:
        """How old ``link``'s newest heartbeat is [s]: in the run's time
        (lockstep) or on the wall clock measured to the newest frame the
        receive side has taken from its bus, so a receive side that lags
        after a stall does not make a heartbeat look old (``clock``)."""
        if link.heartbeat is None:
            return 0.0
        sync, stamp = link.heartbeat
        if self.clock == 'run':
            return max(0, self.cycle - sync) / self.rate
        now = time.time()
        horizon = self.received_to[link.leg.bus]
        if now - horizon > self.heartbeat_limit:     # the whole bus is silent
            horizon = now
        return max(0.0, horizon - stamp)

    # -- who reads the buses ------------------------------------------------------------
    def receive_in_loop(self) -> bool:
        """From now on the caller's thread reads the buses (``pump``), in
        ``sync`` and ``collect``: the notifier threads stop. False (threads
        kept) when a bus cannot be waited on (no ``fileno``)."""
        if self._pumped is not None:
            return True
        try:
            fds = [network.bus.fileno() for network in self.networks.values()]
        except (AttributeError, NotImplementedError, OSError):
            return False
        if any(fd < 0 for fd in fds):
            return False
        pumped = []
        for network in self.networks.values():
            notifier = network.notifier
            listeners = list(notifier.listeners)
            notifier.stop(2 * NOTIFIER_CYCLE)
            pumped.append((network.bus, listeners))
        self._fds = fds
        self._pumped = pumped
        return True

    @contextlib.contextmanager
    def receiving_in_threads(self):
        """For the block, each bus has its notifier thread again (an SDO
        waits for its answer while the loop is not reading); then, if the
        loop was reading, it reads again."""
        pumped = self._pumped
        if pumped is None:
            yield
            return
        self.pump()
        self._pumped = None
        for network, (bus, listeners) in zip(self.networks.values(), pumped):
            network.notifier = can.Notifier(bus, listeners, NOTIFIER_CYCLE)
        try:
            yield
        finally:
            if not self.stopped:
                self.receive_in_loop()

    def pump(self) -> int:
        """Read every frame that has come on the buses and hand each to the
        bus's listeners (as its notifier thread would); how many. Nothing
        while the notifier threads read."""
        n = 0
        for bus, listeners in self._pumped or ():
            msg = bus.recv(0.0)
            while msg is not None:
                n += 1
                for listener in listeners:
                    listener(msg)
                msg = bus.recv(0.0)
        return n

    def _wait_frames(self, timeout: float) -> None:
        """Wait up to ``timeout`` s for frames (under the lock): the loop's
        own read (``pump``), or the notifier threads' signal."""
        if self._pumped is None:
            self._arrived.wait(timeout)
            return
        if self.pump() == 0 and timeout > 0:
            try:
                select.select(self._fds, [], [], timeout)
            except (OSError, ValueError):
                time.sleep(min(timeout, SETTLE_POLL))
            self.pump()

    # -- the cycle ----------------------------------------------------------------------
    def sync(self, cycle: int) -> None:
        """Cycle ``cycle`` starts: a SYNC on every bus; its window opens.
        (The loop that reads the buses takes what came first: a late answer
        to the SYNC before, a heartbeat; each is judged by its stamp.)"""
        self.pump()
        with self._arrived:
            self.cycle = cycle
            self._open = True
            self._opened_at = time.monotonic()
            # (before the frames go out: every answer is received after this)
            self.windows.sent(cycle, time.time())
        for name, network in self.networks.items():
            network.send_message(0x80, b'')
            self.bits[name] += frame_bits(0)

    def _done(self, silent_grace: float, settle: float) -> float:
        """When every drive that is up is done with this cycle (under the
        lock): a time (``time.monotonic()``) to look again at, inf while a
        drive that answered the SYNC before is still awaited."""
        if self._awaited():
            return math.inf
        silent = False
        last = self._opened_at
        ready = -math.inf
        for link in self.links:
            if not link.up:
                continue
            if link.tpdo_sync == self.cycle:
                last = max(last, link.tpdo_taken_at)
                if not link.tpdo_firm:
                    ready = max(ready, link.tpdo_taken_at + settle)
            else:
                silent = True       # nothing from it for the SYNC before, not even late
        return max(ready, last + silent_grace) if silent else ready

    def _awaited(self) -> bool:
        """Whether a drive that is up, and answered the SYNC before (even
        late), has not answered this one yet (under the lock)."""
        cycle = self.cycle
        for link in self.links:
            if link.up and link.tpdo_sync != cycle and not (
                    link.missed_in_a_row and (link.answered is None
                                              or link.answered < cycle - 1)):
                return True
        return False

    def all_in(self) -> bool:
        """Whether every drive that is up has answered this cycle's SYNC
        already (drives whose answers were armed for it: canbus/hub.py)."""
        self.pump()
        with self._arrived:
            return all(link.tpdo_sync == self.cycle for link in self.links if link.up)

    @property
    def opened_at(self) -> float:
        """``time.monotonic()`` at the cycle's SYNC: its window starts there."""
        return self._opened_at

    def _receive_pending(self) -> bool:
        """Frames on a bus not yet taken by the receive side (it lags)."""
        for network in self.networks.values():
            try:
                ready, _, _ = select.select([network.bus.fileno()], [], [], 0)
            except (AttributeError, NotImplementedError, OSError, ValueError):
                continue
            if ready:
                return True
        return False

    def collect(self, until: float, silent_grace: float, settle: float,
                give_back: float = math.inf, catch_up: float = 0.0) -> bool:
        """Wait for this cycle's TPDO1s (see the module's doc).

        Args:
            until: the window's end (``time.monotonic()``): then it is over.
            silent_grace: s a drive that missed the SYNC before is waited for
                once the others are in (a drive known silent costs no more).
            settle: s a drive's first TPDO after a miss waits for a second
                (which would make the first a late answer to the SYNC before).
            give_back: s after which the call returns False to let the
                caller serve its node (call again).
            catch_up: s beyond ``until`` given to a receive side that has
                frames waiting (their reception times decide, not this).

        Returns:
            True when every drive that is up is done or the window is over
            (then ``missing``); False when ``give_back`` passed first.
        """
        start = time.monotonic()
        with self._arrived:
            while True:
                now = time.monotonic()
                done_at = self._done(silent_grace, settle)
                if now >= done_at:
                    return True
                if now >= until:
                    if self._pumped is not None:    # what came by now, judged by its stamp
                        self.pump()
                        return True
                    if now >= until + catch_up or not self._receive_pending():
                        return True
                    self._arrived.wait(0.0005)
                    continue
                if now >= start + give_back:
                    return False
                self._wait_frames(min(until, start + give_back, done_at) - now)

    def missing(self) -> list:
        """The cycle is over: its window closes (a TPDO received in it from
        now on is late) and the drives that are up without its TPDO are
        counted."""
        with self._arrived:
            self._open = False
        missing = []
        for link in self.links:
            if not link.up:
                continue
            if link.tpdo_sync == self.cycle:
                link.missed_in_a_row = 0
                link.silent_since = None
                continue
            missing.append(link)
            link.missed_tpdo += 1
            link.missed_in_a_row += 1
            if link.silent_since is None:
                link.silent_since = self.cycle
        return missing

    def readings(self) -> tuple[list[float], list[float]]:
        """This cycle's leg lengths [m] and rates [m/s], from the TPDOs
        received in its window only: NaN where none came (the rule for a
        missing TPDO, in lockstep and realtime alike)."""
        lengths, rates = [math.nan] * 6, [math.nan] * 6
        with self._arrived:
            for link in self.links:
                if link.tpdo_sync == self.cycle and link.tpdo is not None:
                    lengths[link.leg.leg] = link.leg.metres(link.tpdo[0])
                    rates[link.leg.leg] = link.leg.metres_per_second(link.tpdo[1])
        return lengths, rates

    def new_run(self) -> None:
        """The plant started a new run: SYNC indices from 0 again."""
        with self._arrived:
            self.windows.clear()
            self.cycle = -1
            for link in self.links:
                if link.heartbeat is not None:
                    link.heartbeat = (0, time.time())
                link.tpdo_sync = link.answered = None
                link.missed_in_a_row = 0
                link.silent_since = None

    def late_tpdos(self) -> list[str]:
        """The drives whose TPDO missed this cycle but not yet for
        ``tpdo_error_cycles`` SYNCs in a row (not errors): one line each."""
        return ['%s: TPDO missed at SYNC %d (%d missed in all)'
                % (link.name, self.cycle, link.missed_tpdo) for link in self.links
                if link.up and 0 < link.missed_in_a_row < self.tpdo_error_cycles]
