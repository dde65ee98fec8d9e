"""The bus load as the wire carries it, beside the load the configuration plans.

``config.loads(rate)`` (core/machine/bus.py) is the plan: a SYNC, each drive's RPDO
and TPDO per cycle, the heartbeats. It cannot see a frame nobody planned: a
PDO a drive shipped with and nobody switched off, another master, a node id
not in the config. ``WireLoad`` counts what is on each bus: every frame the
master's CAN interface receives (all frames but its own, on a real bus as on
``s63hub``) and every frame it sends, each at the bits the plan counts it
with (``frame_bits``: worst-case stuffing). Per bus it reports:

- ``bus_load_percent/<bus>``: measured, over the last window (about 1 s);
- ``bus_load_computed_percent/<bus>``: planned;
- ``bus_frames_per_s/<bus>``; ``bus_unknown_cob_ids/<bus>``: the COB-IDs
  seen that nobody configured, with their counts, since the start.

Known COB-IDs are the configured ones: NMT 0x000, SYNC 0x080, and per
drive of the bus its EMCY (0x80 + id), its SDO (0x580 / 0x600 + id), its
heartbeat and boot-up (0x700 + id) and the PDOs the bridge maps
(canbus/pdo.py). ``verdict`` gives an ERROR naming the unknown COB-IDs of
the last window, and a WARN when the measured load exceeds the planned one
by more than ``WARN_POINTS``.

No ROS, no CAN library: a listener is any callable a python-can
``Notifier`` takes; docs/bus.md, "Bus load".
"""
from __future__ import annotations

import collections
import threading
import time

from stewart63_ros.canbus.pdo import bridge_cob_ids
from stewart63_ros.core.machine.bus import BusConfig, frame_bits

#: points of bus load the measured figure may exceed the planned one by
#: before a WARN (a TPDO2 on a state change, an SDO, jitter in the window)
WARN_POINTS = 2.0
#: s: the shortest window a measured figure is given over
MIN_WINDOW = 0.5
#: the unknown COB-IDs a message names at most
NAMED = 8
#: the start of the wire's WARN (so the node can tell it from its others)
WARNING_PREFIX = 'bus load measured on the wire'
#: bits of an extended (29-bit id) frame beyond a standard one's: 18 id bits,
#: SRR, IDE, with their worst-case stuffing
EXTENDED_EXTRA_BITS = 25
#: bits an error frame takes (flag, at most 12, and delimiter, 8)
ERROR_FRAME_BITS = 20
_DATA_BITS = tuple(frame_bits(n) for n in range(9))


def known_cob_ids(config: BusConfig, bus: str) -> dict[int, str]:
    """The COB-IDs configured on ``bus``: {COB-ID: what}."""
    known = {0x000: 'NMT', 0x080: 'SYNC'}
    for leg in config.legs_on(bus):
        node = leg.node_id
        known.update({0x80 + node: 'EMCY', 0x580 + node: 'SDO', 0x600 + node: 'SDO',
                      0x700 + node: 'heartbeat'})
        known.update(bridge_cob_ids(node))
    return known


def wire_bits(msg) -> int:
    """Bits a python-can message takes on the wire (the plan's estimate)."""
    if msg.is_error_frame:
        return ERROR_FRAME_BITS
    bits = _DATA_BITS[0 if msg.is_remote_frame else min(msg.dlc, 8)]
    return bits + EXTENDED_EXTRA_BITS if msg.is_extended_id else bits


class WireLoad:
    """Frames and bits seen on each bus of ``config`` (see the module's doc).

    Args:
        config: the device config.
        rate: the SYNC rate [Hz] the plan is made for.
    """

    def __init__(self, config: BusConfig, rate: float) -> None:
        self.config = config
        self.planned = {load.bus: load.percent for load in config.loads(rate)}
        self.bitrate = {bus.name: bus.bitrate for bus in config.buses}
        self.known = {bus.name: known_cob_ids(config, bus.name) for bus in config.buses}
        self.bits = {bus.name: 0 for bus in config.buses}
        self.frames = {bus.name: 0 for bus in config.buses}
        #: frames of COB-IDs nobody configured, per bus, since the start
        self.unknown = {bus.name: collections.Counter() for bus in config.buses}
        self._lock = threading.Lock()
        self._since = time.monotonic()
        self._at_window = self._snapshot()
        self.figures = {bus.name: (self.planned[bus.name], None, None, ())
                        for bus in config.buses}

    def _snapshot(self):
        return (dict(self.bits), dict(self.frames),
                {bus: dict(counts) for bus, counts in self.unknown.items()})

    def count(self, bus: str, msg) -> None:
        """A frame seen on ``bus`` (python-can message)."""
        cob = -1 if msg.is_error_frame else msg.arbitration_id
        bits = wire_bits(msg)
        with self._lock:
            self.bits[bus] += bits
            self.frames[bus] += 1
            if msg.is_extended_id or cob not in self.known[bus]:
                self.unknown[bus][cob] += 1

    def listener(self, bus: str):
        """A python-can listener (a callable) counting the frames of ``bus``
        (a fast path for classic data frames: about 15000 a second at 1 kHz)."""
        known, unknown, bits, lock = self.known[bus], self.unknown[bus], _DATA_BITS, self._lock
        count = self.count

        def on_message_received(msg) -> None:
            if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame \
                    or msg.dlc > 8:
                count(bus, msg)
                return
            with lock:
                self.bits[bus] += bits[msg.dlc]
                self.frames[bus] += 1
                if msg.arbitration_id not in known:
                    unknown[msg.arbitration_id] += 1
        return on_message_received

    def attach(self, networks: dict) -> None:
        """Count on the master's buses: ``{bus name: canopen.Network}``. Its
        notifier gets a listener for the frames the others send, and its
        python-can bus counts the frames it sends itself."""
        for name, network in networks.items():
            network.notifier.add_listener(self.listener(name))
            self._count_sends(name, network.bus)

    def _count_sends(self, name: str, bus) -> None:
        send = bus.send

        count = self.listener(name)

        def counted_send(msg, timeout=None):
            send(msg, timeout)
            count(msg)
        bus.send = counted_send

    # -- the figures ------------------------------------------------------------------
    def restart(self, now: float | None = None) -> None:
        """A new window from ``now`` (what came before it is not measured)."""
        with self._lock:
            self._at_window = self._snapshot()
            self._since = time.monotonic() if now is None else now

    def measure(self, now: float | None = None, min_window: float = MIN_WINDOW) -> bool:
        """Close the window if it is ``min_window`` s long: ``figures`` per
        bus = (planned %, measured %, frames/s, unknown COB-IDs of the
        window). False (figures unchanged) if the window is shorter."""
        now = time.monotonic() if now is None else now
        span = now - self._since
        if span < min_window or span <= 0.0:
            return False
        with self._lock:
            bits0, frames0, unknown0 = self._at_window
            self._at_window = self._snapshot()
            self._since = now
            for bus in self.bits:
                fresh = tuple(sorted(cob for cob, n in self.unknown[bus].items()
                                     if n > unknown0[bus].get(cob, 0)))
                self.figures[bus] = (
                    self.planned[bus], 100.0 * (self.bits[bus] - bits0[bus]) / span
                    / self.bitrate[bus], (self.frames[bus] - frames0[bus]) / span, fresh)
        return True

    def values(self) -> dict[str, str]:
        """The /diagnostics values of the last window (see the module's doc)."""
        out = {}
        for bus, (planned, measured, rate, _) in self.figures.items():
            out['bus_load_computed_percent/%s' % bus] = '%.1f' % planned
            out['bus_load_percent/%s' % bus] = '%.1f' % measured if measured is not None \
                else 'not yet measured'
            if rate is not None:
                out['bus_frames_per_s/%s' % bus] = '%.0f' % rate
            with self._lock:
                seen = self.unknown[bus].most_common()
            out['bus_unknown_cob_ids/%s' % bus] = ', '.join(
                '%s (%d)' % (_cob_text(cob), n) for cob, n in seen) or 'none'
        return out

    def verdict(self) -> tuple[str, str]:
        """(error, warning) of the last window: the unknown COB-IDs seen in
        it; a measured load over the planned one by more than WARN_POINTS."""
        errors, warnings = [], []
        for bus, (planned, measured, _, fresh) in self.figures.items():
            if fresh:
                named = ', '.join(_cob_text(cob) for cob in fresh[:NAMED])
                more = ' and %d more' % (len(fresh) - NAMED) if len(fresh) > NAMED else ''
                errors.append('unknown frames on bus %s: COB-ID %s%s (configured by nobody: '
                              'another node, or a PDO left on?)' % (bus, named, more))
            if measured is not None and measured > planned + WARN_POINTS:
                warnings.append('bus %s %.1f %%, planned %.1f %%: over by more than %g '
                                'points (other traffic?)' % (bus, measured, planned,
                                                              WARN_POINTS))
        return '; '.join(errors), ('%s: %s' % (WARNING_PREFIX, '; '.join(warnings))
                                   if warnings else '')


def _cob_text(cob: int) -> str:
    return 'error frame' if cob < 0 else '0x%03X' % cob
