"""Sensor and actuator faults of the plant, injected on purpose (docs/faults.md).

One implementation for ``sim`` (core/controllers/simulate.py) and the ``plant`` node: a
``FaultModel`` sees every sample of a run in order. ``begin(k)`` starts
sample k (t = k / rate, the run's time), ``sense`` turns the six readings the
sensors would give into what ``leg_lengths`` carries, ``actuate`` turns the
commanded piston forces into the ones the pistons apply. The true state (the
ground-truth topics, sim's states) never goes through it.

A fault is written ``KIND:LEG[:VALUE][@T_START[-T_END]]``:

- ``LEG``: ``leg_1`` ... ``leg_6``, or ``all``;
- ``T_START`` [s] (default 0) and ``T_END`` [s] (default: never): the fault
  acts on the samples with T_START <= t < T_END;
- kinds (VALUE, unit):

  ``sensor_stuck``       --          the reading (length and rate) freezes at its
                                     value on the fault's first sample
  ``sensor_bias``        m           added to the length reading
  ``sensor_noise``       m (> 0)     Gaussian noise of that standard deviation
                                     on the length reading
  ``sensor_dropout``     --          no reading: NaN for that leg's length and rate
                                     (the sample is incomplete, see ``sense``)
  ``sensor_delay``       s (> 0)     the leg's reading from that long ago
                                     (rounded to whole samples, at least one)
  ``actuator_dead``      --          no force
  ``actuator_weak``      0..1        that fraction of the commanded force
  ``actuator_stuck``     --          holds the force applied just before the
                                     fault's first sample
  ``actuator_saturation`` N (> 0)    |force| clipped to VALUE

Bus faults, for a plant that stands on the field bus as the legs' drives
(``io: canopen``, docs/bus.md; elsewhere refused), act on the device's side
of the bus (canbus/devices.py):

  ``bus_no_boot``        --          the drive is off: no boot-up, hears nothing;
                                     it boots when the fault ends
  ``bus_heartbeat_lost`` --          a pulled cable: the drive neither sends
                                     (heartbeat, TPDOs) nor hears
  ``bus_emcy``           code        an EMCY with that error code (decimal or
                                     0x hex, 1..0xFFFF) at the start, the error
                                     reset EMCY 0x0000 at the end
  ``bus_drive_fault``    --          the drive falls into FAULT; a fault reset is
                                     refused until the fault ends
  ``bus_tpdo_missing``   --          no TPDO (position, velocity) at the SYNCs

On one sample the sensor faults act in the order delay, stuck, bias, noise,
dropout, and the actuator faults stuck, dead, weak, saturation. Two faults of
one kind on one leg: biases and noises add, fractions multiply, the lowest
saturation and the longest delay win.
"""
from __future__ import annotations

import dataclasses
import math
import re
from collections import deque
from typing import Any, Iterable

import numpy as np

from stewart63_ros.core.plumbing.legs import LEG_NAMES

#: kind -> (value: None (takes none) or (unit, check, what a value must be))
KINDS: dict[str, tuple | None] = {
    'sensor_stuck': None,
    'sensor_bias': ('m', lambda v: True, 'a finite number of metres'),
    'sensor_noise': ('m', lambda v: v > 0, 'a standard deviation > 0 in metres'),
    'sensor_dropout': None,
    'sensor_delay': ('s', lambda v: 0 < v <= 10.0, 'a delay in seconds, > 0 and <= 10'),
    'actuator_dead': None,
    'actuator_weak': ('', lambda v: 0 <= v <= 1, 'a fraction from 0 to 1'),
    'actuator_stuck': None,
    'actuator_saturation': ('N', lambda v: v > 0, 'a force limit > 0 in newtons'),
    'bus_no_boot': None,
    'bus_heartbeat_lost': None,
    'bus_emcy': ('code', lambda v: v == int(v) and 1 <= v <= 0xFFFF,
                 'an EMCY error code from 1 to 0xFFFF'),
    'bus_drive_fault': None,
    'bus_tpdo_missing': None,
}
#: the prefix of the kinds that act on the field bus (io: canopen)
BUS_PREFIX = 'bus_'
SENSOR_ORDER = ('sensor_delay', 'sensor_stuck', 'sensor_bias', 'sensor_noise',
                'sensor_dropout')
ACTUATOR_ORDER = ('actuator_stuck', 'actuator_dead', 'actuator_weak', 'actuator_saturation')

_NUMBER = r'(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?'
_TIMES = re.compile(r'(%s)(?:-(%s))?' % (_NUMBER, _NUMBER))
#: A sample is "in" a fault from T_START on: t >= T_START - EPS (t = k / rate
#: is not exact in binary; 1e-9 s is far below any sample period).
EPS = 1e-9


class FaultError(ValueError):
    """A fault string that cannot be injected; the message names it and says why."""


@dataclasses.dataclass(frozen=True)
class Fault:
    """One parsed fault. ``legs``: 0-based leg indices; ``end``: math.inf for never."""
    text: str
    kind: str
    leg: str
    legs: tuple
    value: float | None
    start: float
    end: float

    @property
    def sensor(self) -> bool:
        """True for a sensor fault (``sensor_*``), False for an actuator or bus fault."""
        return self.kind.startswith('sensor_')

    @property
    def bus(self) -> bool:
        """True for a fault of the field bus (``bus_*``)."""
        return self.kind.startswith(BUS_PREFIX)

    def scheduled(self, t: float) -> bool:
        """Whether the fault acts on a sample at time ``t`` [s] of the run.

        Args:
            t: the sample's run time [s] (k / rate).

        Returns:
            True when start <= t < end (to ``EPS``).
        """
        return self.start - EPS <= t < self.end - EPS


def parse_fault(text: str) -> Fault:
    """``KIND:LEG[:VALUE][@T_START[-T_END]]`` -> Fault.

    Args:
        text: the fault as written (surrounding blanks are ignored).

    Returns:
        The Fault; its ``text`` is the stripped string, its name everywhere.

    Raises:
        FaultError: not a string, or a malformed or out-of-range fault; the
            message names it and says why.
    """
    if not isinstance(text, str):
        raise FaultError('bad fault %r: expected a string KIND:LEG[:VALUE][@T_START[-T_END]]'
                         % (text,))
    text = text.strip()

    def bad(why):
        return FaultError('bad fault %r: %s' % (text, why))

    head, at, timing = text.partition('@')
    parts = head.split(':')
    if len(parts) not in (2, 3) or not all(parts):
        raise bad('expected KIND:LEG[:VALUE][@T_START[-T_END]]')
    kind, leg = parts[0], parts[1]
    if kind not in KINDS:
        raise bad('unknown kind %r (one of %s)' % (kind, ', '.join(KINDS)))
    if leg == 'all':
        legs = tuple(range(6))
    elif leg in LEG_NAMES:
        legs = (LEG_NAMES.index(leg),)
    else:
        raise bad('unknown leg %r (leg_1 ... leg_6 or all)' % leg)
    spec = KINDS[kind]
    value = None
    if len(parts) == 3:
        if spec is None:
            raise bad('%s takes no value' % kind)
        try:
            value = float(parts[2])
        except ValueError:
            try:
                value = float(int(parts[2], 0))     # an EMCY code in hex: 0x2310
            except ValueError:
                raise bad('value %r is not a number' % parts[2]) from None
        if not math.isfinite(value) or not spec[1](value):
            raise bad('value %s out of range: %s takes %s' % (parts[2], kind, spec[2]))
    elif spec is not None:
        raise bad('%s needs a value: %s' % (kind, spec[2]))
    start, end = 0.0, math.inf
    if at:
        match = _TIMES.fullmatch(timing)
        if match is None:
            raise bad('bad time %r: expected @T_START or @T_START-T_END, seconds >= 0'
                      % ('@' + timing))
        start = float(match.group(1))
        if match.group(2) is not None:
            end = float(match.group(2))
            if not end > start:
                raise bad('the end %s s is not after the start %s s' % (match.group(2),
                                                                       match.group(1)))
        if not math.isfinite(start) or (match.group(2) is not None
                                         and not math.isfinite(end)):
            raise bad('times must be finite')
    return Fault(text, kind, leg, legs, value, start, end)


def parse_faults(texts: Iterable[str] | str | None) -> list[Fault]:
    """A list of fault strings (a ``faults`` parameter, repeated ``--fault``s).

    Args:
        texts: an iterable of strings; None or an empty list: no faults; one
            string: one fault. A list of one blank string stands for no
            faults, so that ``ros2 param set /plant faults "['']"`` (a string
            list) clears them; a blank string beside faults is refused.

    Returns:
        The Faults in order.

    Raises:
        FaultError: not an iterable, the first bad fault (a blank one among
            others too), or one given twice (the same fault however written:
            ``x@1`` and ``x@1.0``).
    """
    if texts is None:
        return []
    if isinstance(texts, str):
        texts = [texts]
    try:
        items = list(texts)
    except TypeError:
        raise FaultError('faults must be a list of strings, got %r' % (texts,)) from None
    if len(items) == 1 and isinstance(items[0], str) and not items[0].strip():
        return []                       # [''] : no faults
    faults, seen = [], {}
    for item in items:
        if isinstance(item, str) and not item.strip():
            raise FaultError("bad fault %r: a blank fault (only [''] alone stands for no "
                             'faults)' % item)
        fault = parse_fault(item)
        same = (fault.kind, fault.legs, fault.value, fault.start, fault.end)
        if same in seen:
            raise FaultError('fault %r is given twice%s' % (fault.text, '' if seen[same] ==
                             fault.text else ' (as %r)' % seen[same]))
        seen[same] = fault.text
        faults.append(fault)
    return faults


def _fmt(t: float) -> str:
    return '%.6f' % t


@dataclasses.dataclass
class FaultState:
    """What one fault did in one run: when it acted, what it holds."""
    fault: Fault
    run: int = 1
    active: bool = False
    started: float | None = None     # run time [s] of its first faulted sample
    ended: float | None = None       # run time of the first sample after it
    removed: bool = False            # taken out at run time (``set_faults``)
    hold: object = None              # stuck faults: the values held
    samples: int = 1                 # sensor_delay: the delay in samples

    def status(self) -> str:
        """The text /diagnostics shows under ``fault: <fault>``.

        Returns:
            'scheduled from S s[ to E s]', 'removed before it started',
            'active since S s[ (until E s)]' or 'ended: active S-E s[, removed]'
            (run times, ``interval_from_status`` reads them back).
        """
        f = self.fault
        if self.started is None:
            if self.removed:
                return 'removed before it started'
            until = '' if f.end == math.inf else ' to %g s' % f.end
            return 'scheduled from %g s%s' % (f.start, until)
        if self.active:
            until = '' if f.end == math.inf else ' (until %g s)' % f.end
            return 'active since %s s%s' % (_fmt(self.started), until)
        return 'ended: active %s-%s s%s' % (_fmt(self.started), _fmt(self.ended),
                                            ', removed' if self.removed else '')

    def summary(self) -> dict[str, Any]:
        """What the fault did, as plain JSON types (``sim``'s summary, ``Result.faults``).

        Returns:
            {'fault', 'kind', 'leg': str, 'value': float or None, 'start_s',
            'end_s' (None: never) [s], 'run': int, 'active_from_s',
            'active_until_s': run times [s] or None, 'state': 'scheduled',
            'active', 'ended' or 'removed'}.
        """
        f = self.fault
        return {'fault': f.text, 'kind': f.kind, 'leg': f.leg, 'value': f.value,
                'start_s': f.start, 'end_s': None if f.end == math.inf else f.end,
                'run': self.run, 'active_from_s': self.started,
                'active_until_s': self.ended if self.started is not None else None,
                'state': ('active' if self.active else 'ended' if self.started is not None
                          else 'removed' if self.removed else 'scheduled')}


_INTERVAL = re.compile(r'active (?:since (%s) s|(%s)-(%s) s)' % (_NUMBER, _NUMBER, _NUMBER))


def interval_from_status(text: str) -> tuple[float, float | None] | None:
    """When a fault acted, read back from its ``FaultState.status`` text.

    Args:
        text: a status text (or any text containing one).

    Returns:
        (start [s], end [s] or None while active), run times; None for a
        fault that has not acted.
    """
    match = _INTERVAL.search(text)
    if match is None:
        return None
    if match.group(1) is not None:
        return float(match.group(1)), None
    return float(match.group(2)), float(match.group(3))


class FaultModel:
    """The faults of one plant, applied sample by sample.

    Args:
        faults: the Faults (``parse_faults``).
        rate: sample rate [Hz] (t = k / rate; sensor delays in samples).
        seed: seed of the fault noise (its own stream, apart from the sensor
            model's noise).
        bus: the plant stands on a field bus (``io: canopen``): bus faults
            are accepted (and act through ``bus_active``); elsewhere they are
            refused.

    Raises:
        FaultError: a bus fault without a bus.
    """

    def __init__(self, faults: Iterable[Fault] = (), rate: float = 1000.0,
                 seed: int = 0, bus: bool = False) -> None:
        self.bus = bool(bus)
        self.rate = float(rate)
        self.period = 1.0 / self.rate
        self.seed = int(seed)
        self.run = 1
        self.past: list[FaultState] = []        # removed faults, faults of earlier runs
        self.states: list[FaultState] = []
        self.t = 0.0
        self._start_run()
        self.set_faults(faults)

    def _start_run(self) -> None:
        self.rng = np.random.default_rng([self.seed, 1])
        self.applied = np.zeros(6)              # the last forces ``actuate`` returned
        self.history: deque = deque(maxlen=1)   # past readings, for sensor_delay
        self._sensor: list[FaultState] = []     # active now, in application order
        self._actuator: list[FaultState] = []
        self.t = 0.0
        self.next_t = 0.0                       # run time of the next sample to begin

    # -- configuration ------------------------------------------------------------------
    @property
    def faults(self) -> list[Fault]:
        """The faults of this run (removed ones not), in order."""
        return [s.fault for s in self.states]

    def set_faults(self, faults: Iterable[Fault], next_sample: int | None = None) -> list[str]:
        """Replace the list of faults (at run time: between two samples).

        A fault already there (the same text) keeps its state; a new one
        acts from the next sample its times include; a removed one that had
        acted is kept, ended now, for the record. A new fault whose times
        include no sample from the next one on would never act in this run:
        the whole list is refused.

        Args:
            faults: the new list (``parse_faults``).
            next_sample: the index of the run's next sample, when the caller
                knows it (a plant that calls ``begin`` only while it has
                faults); None: the one after the last ``begin``.

        Returns:
            What changed, one line each, for the log.

        Raises:
            FaultError: a new fault ends before the run's next sample, or a bus
                fault on a model without a bus (nothing changed).
        """
        faults = list(faults)
        for fault in faults:
            if fault.bus and not self.bus:
                raise FaultError('fault %r acts on the field bus: it needs the plant on the '
                                 'bus (io: canopen, docs/bus.md)' % fault.text)
        if next_sample is not None:
            self.next_t = next_sample / self.rate
        old = {s.fault.text: s for s in self.states}
        for fault in faults:
            if fault.text not in old and fault.end - EPS <= self.next_t:
                raise FaultError(
                    'fault %r ends at %g s, before the next sample of this run (t = %s s): '
                    'it would never act (its times are the run\'s, from its first sample)'
                    % (fault.text, fault.end, ('%.6f' % self.next_t).rstrip('0').rstrip('.')))
        new_texts = {f.text for f in faults}
        events = []
        for state in self.states:
            if state.fault.text not in new_texts:
                state.removed = True
                if state.active:
                    state.active, state.ended = False, self.t
                self.past.append(state)
                events.append('fault %s removed (%s)' % (state.fault.text, state.status()))
        self.states = []
        for fault in faults:
            state = old.get(fault.text)
            if state is None:
                state = FaultState(fault, run=self.run)
                if fault.kind == 'sensor_delay':
                    state.samples = max(1, int(round(fault.value / self.period)))
                events.append('fault %s added (%s)' % (fault.text, state.status()))
            self.states.append(state)
        longest = max([s.samples for s in self.states if s.fault.kind == 'sensor_delay'],
                      default=0)
        if longest + 1 != self.history.maxlen:
            self.history = deque(self.history, maxlen=longest + 1)
        self._order()
        return events

    def reset(self) -> None:
        """A new run from its first sample: every fault starts over (its
        schedule counts from the new run's t = 0); the old states are kept
        in ``past`` for the record; a fault active to the end of the old run
        ends there (at the time its next sample would have had)."""
        for state in self.states:
            if state.active:
                state.active, state.ended = False, self.next_t
        self.past.extend(s for s in self.states if s.started is not None)
        self.run += 1
        faults = self.faults
        self.states = []
        self._start_run()
        self.set_faults(faults)

    def _order(self) -> None:
        active = [s for s in self.states if s.active]
        self._sensor = sorted((s for s in active if s.fault.sensor),
                              key=lambda s: SENSOR_ORDER.index(s.fault.kind))
        self._actuator = sorted((s for s in active if not s.fault.sensor and not s.fault.bus),
                                key=lambda s: ACTUATOR_ORDER.index(s.fault.kind))

    # -- the samples -----------------------------------------------------------------------
    def begin(self, k: int) -> list[str]:
        """Start sample ``k`` of the run (t = k / rate): faults start and end here.

        Args:
            k: the sample's index in the run, from 0.

        Returns:
            one line per fault that started or ended on this sample (empty
            on most samples).
        """
        t = self.t = k / self.rate      # k / rate: 0.7 where k * period gives 0.70...01
        self.next_t = (k + 1) / self.rate
        events = []
        for state in self.states:
            on = state.fault.scheduled(t)
            if on and not state.active:
                if state.started is not None:
                    continue        # a fault acts once per run (its times are one interval)
                state.active, state.started = True, t
                state.hold = None
                if state.fault.kind == 'actuator_stuck':
                    state.hold = self.applied[list(state.fault.legs)].copy()
                events.append('fault %s started at %s s' % (state.fault.text, _fmt(t)))
            elif not on and state.active:
                state.active, state.ended = False, t
                events.append('fault %s ended at %s s' % (state.fault.text, _fmt(t)))
        if events:
            self._order()
        return events

    def sense(self, lengths: np.ndarray,
              rates: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
        """What the sensors report on this sample.

        Args:
            lengths, rates: the six readings without faults (6,) [m], [m/s].

        Returns:
            (lengths, rates, complete): new arrays when a fault acted (the
            inputs are not changed); ``complete`` is False when a leg's
            reading is missing (NaN: ``sensor_dropout``).
        """
        if self.history.maxlen > 1:
            self.history.append((lengths, rates))
        if not self._sensor:
            return lengths, rates, True
        lengths = np.array(lengths, dtype=float)
        rates = np.array(rates, dtype=float)
        complete = True
        for state in self._sensor:
            f = state.fault
            legs = list(f.legs)
            if f.kind == 'sensor_delay':
                past_l, past_r = self.history[max(0, len(self.history) - 1 - state.samples)]
                lengths[legs], rates[legs] = past_l[legs], past_r[legs]
            elif f.kind == 'sensor_stuck':
                if state.hold is None:
                    state.hold = (lengths[legs].copy(), rates[legs].copy())
                lengths[legs], rates[legs] = state.hold
            elif f.kind == 'sensor_bias':
                lengths[legs] += f.value
            elif f.kind == 'sensor_noise':
                lengths[legs] += self.rng.normal(0.0, f.value, len(legs))
            else:   # sensor_dropout
                lengths[legs] = rates[legs] = np.nan
                complete = False
        return lengths, rates, complete

    def actuate(self, forces: np.ndarray) -> np.ndarray:
        """The forces the pistons apply for the commanded ones; remembered for
        ``actuator_stuck``.

        Args:
            forces: (6,) the commanded piston forces [N].

        Returns:
            (6,) the applied forces [N]: a new array when a fault acted (the
            input is not changed), else ``forces`` itself.
        """
        if self._actuator:
            forces = np.array(forces, dtype=float)
            for state in self._actuator:
                f = state.fault
                legs = list(f.legs)
                if f.kind == 'actuator_stuck':
                    forces[legs] = state.hold
                elif f.kind == 'actuator_dead':
                    forces[legs] = 0.0
                elif f.kind == 'actuator_weak':
                    forces[legs] *= f.value
                else:   # actuator_saturation
                    forces[legs] = np.clip(forces[legs], -f.value, f.value)
        self.applied = forces
        return forces

    def bus_active(self) -> dict[int, dict[str, float | None]]:
        """The bus faults acting on this sample.

        Returns:
            {leg (0-based): {kind: value}}, only the legs with one.
        """
        out: dict[int, dict[str, float | None]] = {}
        for state in self.states:
            if state.active and state.fault.bus:
                for leg in state.fault.legs:
                    out.setdefault(leg, {})[state.fault.kind] = state.fault.value
        return out

    # -- reports -----------------------------------------------------------------------------
    @property
    def active(self) -> list[FaultState]:
        """The states of the faults acting now, in list order."""
        return [s for s in self.states if s.active]

    def active_text(self) -> str:
        """'faults active: a (since t s), b (since ...)', or '' when none is."""
        active = self.active
        if not active:
            return ''
        return 'faults active: ' + ', '.join('%s (since %g s)' % (s.fault.text, s.started)
                                             for s in active)

    def status_values(self) -> dict[str, str]:
        """{'fault: <fault>': status text} for every fault of this run and the
        ones removed from it (the /diagnostics values)."""
        out = {}
        for state in [s for s in self.past if s.run == self.run] + self.states:
            out['fault: ' + state.fault.text] = state.status()
        return out

    def summary(self) -> list[dict[str, Any]]:
        """Every fault of every run so far (``FaultState.summary``), in order."""
        return [s.summary() for s in self.past + self.states]
