"""The paper's PD law on leg lengths, eq. (40), with force saturation."""
from __future__ import annotations

import numpy as np

from stewart63_ros.core._jit import njit, njit_kernel


@njit_kernel
def pd_leg(length, rate, setpoint, kp, kv, max_force):
    """Eq. (40) for one leg, scalars: the arithmetic of ``pd_law`` (a NaN stays NaN,
    as with np.minimum/np.maximum), for the compiled right-hand side."""
    force = kp * (setpoint - length) - kv * rate
    if force > max_force:
        return max_force
    if force < -max_force:
        return -max_force
    return force


@njit
def pd_law(lengths, rates, setpoint, kp, kv, max_force):
    force = kp * (setpoint - lengths) - kv * rates
    return np.minimum(np.maximum(force, -max_force), max_force)


def pd_forces(lengths, rates, setpoint, kp, kv, max_force):
    """F_i = Kp_i ((L_i)_0 - L_i) - Kv_i dL_i/dt, clipped to +-max_force [N], eq. (40)."""
    f = np.asarray
    return pd_law(f(lengths, float), f(rates, float), f(setpoint, float), f(kp, float),
               f(kv, float), float(max_force))


class PDController:
    """Eq. (40) with the gains, setpoint and saturation of one mechanism."""

    def __init__(self, mech, setpoint=None):
        self.kp = np.array(mech.kp, dtype=float)
        self.kv = np.array(mech.kv, dtype=float)
        self.max_force = float(mech.max_force)
        self.setpoint = np.array(mech.setpoint_lengths if setpoint is None else setpoint, float)

    def __call__(self, lengths, rates):
        return pd_law(lengths, rates, self.setpoint, self.kp, self.kv, self.max_force)

    @property
    def setpoint(self):
        return self._setpoint

    @setpoint.setter
    def setpoint(self, value):
        value = np.array(value, dtype=float)
        if value.shape != (6,) or not np.all(np.isfinite(value)):
            raise ValueError('setpoint must be six finite lengths')
        self._setpoint = value
