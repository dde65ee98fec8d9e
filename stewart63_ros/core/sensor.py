"""A model of the linear leg sensors: what the plant publishes as ``leg_lengths``."""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from stewart63_ros.core.node_parameters import read as read_declared


class SensorModel:
    """Optional linear-sensor imperfections; all off by default.

    ``sensor_noise`` [m] and ``sensor_rate_noise`` [m/s]: Gaussian standard
    deviations; ``sensor_resolution`` [m]: quantisation step of L;
    ``sensor_delay`` [samples]: transport delay; ``sensor_seed``: RNG seed.

    Args:
        params: the plant's parameters (the keys above; missing ones are off).

    Raises:
        ParameterError: a value out of its declared range (core/node_parameters.py).
    """

    def __init__(self, params: Mapping[str, Any]) -> None:
        self.noise = read_declared(params, 'sensor_noise')
        self.rate_noise = read_declared(params, 'sensor_rate_noise')
        self.resolution = read_declared(params, 'sensor_resolution')
        self.delay = read_declared(params, 'sensor_delay')
        self.rng = np.random.default_rng(read_declared(params, 'sensor_seed'))
        self.history = []

    def measure(self, lengths: np.ndarray,
                rates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What the sensors report for one sample of the true lengths and rates.

        Args:
            lengths: true L (6,) [m]; rates: true dL/dt (6,) [m/s].

        Returns:
            (L (6,), dL/dt (6,)) as reported: delayed, noisy, quantised as set.
        """
        if self.delay:
            self.history.append((lengths, rates))
            lengths, rates = self.history[0]
            if len(self.history) > self.delay:
                self.history.pop(0)
        if self.noise:
            lengths = lengths + self.rng.normal(0.0, self.noise, 6)
        if self.rate_noise:
            rates = rates + self.rng.normal(0.0, self.rate_noise, 6)
        if self.resolution:
            lengths = np.round(lengths / self.resolution) * self.resolution
        return lengths, rates
