"""A model of the linear leg sensors: what the plant publishes as ``leg_lengths``."""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from stewart63_ros.core.plumbing.errors import ParameterError
from stewart63_ros.core.plumbing.node_parameters import read as read_declared


class SensorModel:
    """Optional linear-sensor imperfections; all off by default.

    ``sensor_noise`` [m] and ``sensor_rate_noise`` [m/s]: Gaussian standard
    deviations; ``sensor_resolution`` [m]: quantisation step of L;
    ``sensor_delay`` [samples]: transport delay; ``sensor_seed``: RNG seed;
    ``leg_length_offset`` [m] (6): each sensor's zero offset, added to the
    true length (the controller and fk subtract the offset of their file).

    Args:
        params: the plant's parameters (the keys above; missing ones are off).

    Raises:
        ParameterError: a value out of its declared range (core/plumbing/node_parameters.py).
    """

    def __init__(self, params: Mapping[str, Any]) -> None:
        self.noise = read_declared(params, 'sensor_noise')
        self.rate_noise = read_declared(params, 'sensor_rate_noise')
        self.resolution = read_declared(params, 'sensor_resolution')
        self.delay = read_declared(params, 'sensor_delay')
        self.rng = np.random.default_rng(read_declared(params, 'sensor_seed'))
        offset = read_declared(params, 'leg_length_offset')
        self.offset = offset if np.any(offset) else None
        self.history = []

    def measure(self, lengths: np.ndarray,
                rates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What the sensors report for one sample of the true lengths and rates.

        Args:
            lengths: true L (6,) [m]; rates: true dL/dt (6,) [m/s].

        Returns:
            (L (6,), dL/dt (6,)) as reported: delayed, offset, noisy, quantised as set.
        """
        if self.delay:
            self.history.append((lengths, rates))
            lengths, rates = self.history[0]
            if len(self.history) > self.delay:
                self.history.pop(0)
        if self.offset is not None:
            lengths = lengths + self.offset
        if self.noise:
            lengths = lengths + self.rng.normal(0.0, self.noise, 6)
        if self.rate_noise:
            rates = rates + self.rng.normal(0.0, self.rate_noise, 6)
        if self.resolution:
            lengths = np.round(lengths / self.resolution) * self.resolution
        return lengths, rates


class TrackerModel:
    """A simulated pose tracker (motion capture, laser tracker): the true pose
    with Gaussian noise, every ``sensor_rate / tracker_rate`` samples.

    ``tracker_rate`` [Hz] (0: no tracker), ``tracker_position_noise`` [m] per
    axis, ``tracker_orientation_noise`` [rad] per axis of a rotation vector
    in the base frame (the pose turned further by it); seeded from
    ``sensor_seed`` on a stream of its own.

    Args:
        params: the plant's parameters.

    Raises:
        ParameterError: a value out of its range, or a rate that does not
            divide ``sensor_rate`` (the tracker samples with the sensors).
    """

    def __init__(self, params: Mapping[str, Any]) -> None:
        self.rate = read_declared(params, 'tracker_rate')
        self.position_noise = read_declared(params, 'tracker_position_noise')
        self.orientation_noise = read_declared(params, 'tracker_orientation_noise')
        self.every = 0
        if self.rate:
            sensor_rate = read_declared(params, 'sensor_rate')
            every = sensor_rate / self.rate
            if self.rate > sensor_rate or abs(every - round(every)) > 1e-9 * every:
                raise ParameterError('tracker_rate', 'must divide sensor_rate (%g Hz), got %g'
                                     % (sensor_rate, self.rate))
            self.every = int(round(every))
        self.rng = np.random.default_rng([read_declared(params, 'sensor_seed'), 7])

    def due(self, sample: int) -> bool:
        """Whether the tracker measures at sample number ``sample``.

        Args:
            sample: the plant's sample counter.

        Returns:
            True every ``sensor_rate / tracker_rate`` samples (never at rate 0).
        """
        return self.every > 0 and sample % self.every == 0

    def measure(self, position: np.ndarray, quaternion: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
        """The tracked pose of the true one.

        Args:
            position: t (3,) [m]; quaternion: (4,) x, y, z, w, unit.

        Returns:
            (position (3,), unit quaternion (4,)) with the noise added.
        """
        # lazy: core.mechanics.rotation costs 649 ms (numba, scipy)
        from stewart63_ros.core.mechanics.rotation import (
            quaternion_of_rotvec_times,
            rotation_from_quaternion,
        )
        position = position + self.rng.normal(0.0, self.position_noise, 3)
        turn = self.rng.normal(0.0, self.orientation_noise, 3)
        return position, quaternion_of_rotvec_times(turn, rotation_from_quaternion(quaternion))
