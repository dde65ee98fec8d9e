"""The plant's summary of a run: what ``plant_summary.json`` holds.

``TrackingError`` adds the true tracking error against the reference motion
the controller follows (``rig --reference``), sample by sample;
``run_summary`` gathers the rest from the plant when the run ends.
"""
from __future__ import annotations

import time

import numpy as np

from stewart63_ros.core.controllers.reference import ReferenceError
from stewart63_ros.core.controllers.reference_files import load_reference
from stewart63_ros.core.controllers.tracking import accumulate_tracking, tracking_summary
from stewart63_ros.core.mechanics.dynamics import POS, QUAT
from stewart63_ros.core.mechanics.rotation import matrix_from_quaternion
from stewart63_ros.core.plumbing.params import ParameterError

#: The tracking error in the summary counts samples from this time [s] on.
TRACKING_FROM = 1.0


class TrackingError:
    """The true tracking error of a run against the reference in ``reference_file``."""

    def __init__(self, mech, reference_file: str):
        try:
            self.reference = load_reference(mech, reference_file)
        except ReferenceError as exc:
            raise ParameterError('reference_file', str(exc)) from None
        self._accumulate = accumulate_tracking
        self._matrix = matrix_from_quaternion
        self.totals = np.zeros(8)
        self.ref_sample = np.empty(36)

    def add(self, t: float, lengths, y) -> None:
        """The sample at reference time ``t`` [s] (from ``TRACKING_FROM`` on: the
        caller checks, a call per sample saved): the true ``lengths``, state ``y``."""
        self.reference.sample(t, self.ref_sample)
        quat = y[QUAT] / np.sqrt(y[QUAT] @ y[QUAT])
        self._accumulate(self.totals, lengths, self.ref_sample, y[POS], self._matrix(quat), True)

    def reset(self) -> None:
        """A new run (``~/reset``) counts from zero."""
        self.totals[:] = 0.0

    def summary(self) -> dict:
        return dict(from_s=TRACKING_FROM, **tracking_summary(self.totals))


def run_summary(plant, stopped: bool) -> dict:
    """What the plant did in its run (``stopped``: by a signal), for its summary file."""
    lengths, _ = plant.dyn.lengths_and_rates(plant.y)
    setpoint = plant.setup.task.setpoint_lengths
    errors = 100.0 * np.abs(lengths - setpoint) / setpoint
    summary = {
        'clock_mode': plant.mode, 'rate_hz': plant.rate, 'samples': plant.k + 1,
        'sim_time_s': plant.k * plant.period,
        'final_leg_lengths_m': lengths.tolist(),
        'final_leg_errors_percent': errors.tolist(),
        'positioning_error_percent': float(errors.max()),
        'loop_latency': plant.health.latency.summary(),
        'force_timeouts': plant.timeouts, 'missed_cycles': plant.missed,
        'late_cycles': plant.late, 'endstop_samples': plant.endstop_samples,
        'wall_time_s': time.time() - plant.t0_wall,
        'run_began_unix_s': plant.run_began_unix, 'run_ended_unix_s': time.time(),
        'skipped': dict(plant.health.skipped),
        'stopped_by_signal': stopped,
        'run_number': plant.run_number, 'resets': plant.resets,
        'faults': plant.fault_model.summary(),
    }
    peers = plant.peers
    if peers is not None:
        summary['lockstep_peers'] = {
            'window': peers.window, 'held_s': round(peers.held_s, 3),
            'held_samples': peers.holds, 'dropped': dict(peers.dropped)}
    if plant.tracking is not None:
        summary['tracking_error'] = plant.tracking.summary()
    if plant.devices is not None:
        # realtime on the local bus: the samples whose drives' answers were
        # armed for their SYNC (nodes/plant_bus.py), the others answered it
        summary['bus_samples_armed'] = plant.samples_armed
    return summary
