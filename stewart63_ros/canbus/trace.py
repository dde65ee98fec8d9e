"""A per-cycle record of a realtime loop, kept in memory, written at the end.

Set ``STEWART63_CYCLE_TRACE=DIR`` in the environment of a rig (or of a node)
and the bridge's realtime loop (nodes/bridge_cycles.py) and the plant's
drives (nodes/plant_bus.py) each keep one row per cycle: times on the
monotonic clock, the process's and the loop thread's CPU time, the cycle's
outcome. Python's garbage collections are recorded too (start, generation,
duration). At the end each writes ``DIR/<name>-<pid>.npz``; bench/bench_bus.py
``--trace`` reads them (where the misses fall: at the start, periodic or
spread, and why). Without the variable nothing is kept, at no cost.

Rows are written into an array allocated at the start: a row costs about a
microsecond and makes no garbage. No ROS here.
"""
from __future__ import annotations

import gc
import os
import time

import numpy as np

#: the environment variable naming the folder the traces go to
TRACE_ENV = 'STEWART63_CYCLE_TRACE'


class CycleTrace:
    """Rows of ``fields`` (floats), at most ``capacity``; GC events beside.

    Args:
        name: the file's stem (``<name>-<pid>.npz``).
        fields: the columns.
        capacity: rows kept (later ones are dropped, counted).
    """

    def __init__(self, name: str, fields: tuple[str, ...], capacity: int) -> None:
        self.name = name
        self.fields = fields
        self.rows = np.full((capacity, len(fields)), np.nan)
        self.n = 0
        self.dropped = 0
        self.gc_events = np.full((20000, 3), np.nan)       # start, generation, duration
        self.n_gc = 0
        self._gc_start = 0.0
        gc.callbacks.append(self._on_gc)

    @classmethod
    def from_env(cls, name: str, fields: tuple[str, ...], capacity: int) -> CycleTrace | None:
        """A trace if ``STEWART63_CYCLE_TRACE`` names a folder, else None."""
        return cls(name, fields, capacity) if os.environ.get(TRACE_ENV) else None

    def _on_gc(self, phase: str, info: dict) -> None:
        if phase == 'start':
            self._gc_start = time.monotonic()
        elif self.n_gc < len(self.gc_events):
            self.gc_events[self.n_gc] = (self._gc_start, info.get('generation', -1),
                                         time.monotonic() - self._gc_start)
            self.n_gc += 1

    def add(self, *values: float) -> None:
        if self.n < len(self.rows):
            self.rows[self.n] = values
            self.n += 1
        else:
            self.dropped += 1

    def write(self) -> str | None:
        """Write ``DIR/<name>-<pid>.npz``; its path (None without the variable)."""
        if self._on_gc in gc.callbacks:
            gc.callbacks.remove(self._on_gc)
        folder = os.environ.get(TRACE_ENV)
        if not folder:
            return None
        os.makedirs(folder, exist_ok=True)
        path = os.path.join(folder, '%s-%d.npz' % (self.name, os.getpid()))
        np.savez(path, rows=self.rows[:self.n], fields=np.array(self.fields),
                 gc=self.gc_events[:self.n_gc], dropped=self.dropped)
        return path
