"""The paper's PD law on leg lengths, eq. (40), with force saturation."""
from __future__ import annotations

import numpy as np


def pd_forces(lengths, rates, setpoint, kp, kv, max_force):
    """F_i = Kp_i ((L_i)_0 - L_i) - Kv_i dL_i/dt, clipped to +-max_force [N], eq. (40)."""
    force = np.asarray(kp) * (np.asarray(setpoint) - lengths) - np.asarray(kv) * rates
    return np.clip(force, -max_force, max_force)


class PDController:
    """Eq. (40) with the gains, setpoint and saturation of one mechanism."""

    def __init__(self, mech, setpoint=None):
        self.kp = np.array(mech.kp)
        self.kv = np.array(mech.kv)
        self.max_force = mech.max_force
        self.setpoint = np.array(mech.setpoint_lengths if setpoint is None else setpoint, float)

    def __call__(self, lengths, rates):
        return pd_forces(lengths, rates, self.setpoint, self.kp, self.kv, self.max_force)
