"""Which SYNC a frame answers, judged on time (CiA 301's synchronous window).

The master keeps the wall time (``time.time()``, the clock python-can
stamps received frames with) at which it sent each SYNC. A frame received
at time t lies in the window of the last SYNC sent before t: a synchronous
TPDO received there answers that SYNC, whenever the bridge's loop gets
round to it. So a receive side that lags (a loaded machine, the GIL) still
files every frame under the SYNC it answered, and a frame that comes after
its window has closed is late, never the next sample's reading.

``Schedule`` is the realtime SYNC clock: after a stall it skips the SYNCs
whose time has passed (counted) and never sends a burst. ``silent_cycles``:
how many SYNCs in a row a drive may miss before it is a bus fault.

No ROS and no CAN library here.
"""
from __future__ import annotations

import bisect
import collections
import math


class SyncWindows:
    """The send times of the recent SYNCs, and the window a time falls in.

    Args:
        keep: how many SYNCs are remembered (older frames are strays).
    """

    def __init__(self, keep: int = 1024) -> None:
        self._times: collections.deque[float] = collections.deque(maxlen=keep)
        self._indices: collections.deque[int] = collections.deque(maxlen=keep)

    def sent(self, index: int, at: float) -> None:
        """SYNC ``index`` went out at wall time ``at`` [s] (before its frame
        was handed to the bus, so every answer is received after it)."""
        if self._times and at < self._times[-1]:      # the wall clock stepped back
            self.clear()
        self._times.append(at)
        self._indices.append(index)

    def clear(self) -> None:
        """Forget every SYNC (a new run: its indices start at 0 again)."""
        self._times.clear()
        self._indices.clear()

    def window_of(self, stamp: float) -> int | None:
        """The index of the last SYNC sent at or before wall time ``stamp``
        [s]; None before the first remembered SYNC."""
        i = bisect.bisect_right(self._times, stamp)
        return self._indices[i - 1] if i else None

    @property
    def last(self) -> tuple[int, float] | None:
        """(index, send time) of the newest SYNC; None before the first."""
        return (self._indices[-1], self._times[-1]) if self._times else None


class Schedule:
    """The realtime SYNC clock: SYNC slot n is due at ``t0 + n * period``.

    Args:
        t0: the monotonic time of slot 0 [s].
        period: the sample period [s].
    """

    def __init__(self, t0: float, period: float) -> None:
        self.t0 = t0
        self.period = period
        self.slot = 0
        #: slots whose time passed while the bridge was stalled: no SYNC was sent
        self.skipped = 0

    def restart(self, t0: float) -> None:
        """Slot 0 is at ``t0`` from now on (the clock starts again there)."""
        self.t0 = t0
        self.slot = 0

    def due(self) -> float:
        """When the current slot's SYNC is due (monotonic [s])."""
        return self.t0 + self.slot * self.period

    def advance(self, now: float) -> int:
        """The next slot, skipping those already over at ``now`` (a slot is
        over once the next one is due: a SYNC sent then would be a burst).
        Returns how many were skipped this time."""
        self.slot += 1
        behind = math.floor((now - self.due()) / self.period)
        skip = max(0, behind)
        self.slot += skip
        self.skipped += skip
        return skip


def silent_cycles(missing_ms: float, rate: float) -> int:
    """SYNCs in a row a drive's TPDO may miss before it is a bus fault.

    The bridge's ``tpdo_missing_error_ms`` in cycles at ``rate`` [Hz]: the
    SYNCs that cover that time, at least one. Counted in SYNCs sent, not on
    the clock: a stall of the bridge, whose SYNCs are skipped, makes no drive
    look silent (docs/bus.md). A time, not a count, so that a rate does not
    change what is a fault: 20 ms is 4 cycles at 200 Hz, 20 at 1 kHz, the
    supervisor's ``stale_lengths_ms`` either way.
    """
    return max(1, math.ceil(missing_ms * rate / 1000.0 - 1e-9))
