"""The paper's PD law on leg lengths, eq. (40), with force saturation: written
once (``pd_force``), compiled, and called by every law, loop and integrator
that applies it (``laws``, ``simulate``, ``dynamics.derivative_pd``).

F_i = Kp_i ((L_i)_0 - L_i) - Kv_i (dL_i/dt - (dL_i/dt)_0), clipped to
+-max_force; the paper's setpoint holds (dL_i/dt)_0 = 0, and then the rate
term is Kv_i dL_i/dt to the bit (x - 0.0 == x in IEEE arithmetic).
A NaN input gives a NaN force (never a saturated finite one), so a caller
that checks the forces sees it.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from stewart63_ros.core.plumbing._jit import njit, njit_kernel


class PDGains(NamedTuple):
    """Eq. (40) towards fixed lengths: what the compiled loops need of it.

    ``setpoint`` (L_i)_0 (6,) [m], ``kp`` (6,) [N/m], ``kv`` (6,) [N s/m],
    ``max_force`` the saturation [N].
    """
    setpoint: np.ndarray
    kp: np.ndarray
    kv: np.ndarray
    max_force: float

    def rows(self) -> np.ndarray:
        """[setpoint; kp; kv] (3, 6), as ``dynamics.derivative_pd`` and ``dopri`` take them."""
        return np.vstack([self.setpoint, self.kp, self.kv])


@njit_kernel
def pd_force(length: float, rate: float, setpoint: float, setpoint_rate: float, kp: float,
             kv: float) -> float:
    """Eq. (40) for one leg, unsaturated: the one place the law is written.

    Args:
        length: L [m]; rate: dL/dt [m/s].
        setpoint: (L)_0 [m]; setpoint_rate: (dL/dt)_0 [m/s] (0 for a fixed setpoint).
        kp: [N/m]; kv: [N s/m].

    Returns:
        Kp (L_0 - L) - Kv (dL/dt - dL_0/dt) [N], positive extends.
    """
    return kp * (setpoint - length) - kv * (rate - setpoint_rate)


@njit_kernel
def saturated(force: float, max_force: float) -> float:
    """``force`` clipped to +-max_force; a NaN stays NaN.

    Args:
        force: [N]; max_force: the saturation [N].

    Returns:
        The clipped force [N].
    """
    if force > max_force:
        return max_force
    if force < -max_force:
        return -max_force
    return force


@njit_kernel
def pd_leg(length: float, rate: float, setpoint: float, setpoint_rate: float, kp: float,
           kv: float, max_force: float) -> float:
    """Eq. (40) for one leg, saturated (``saturated(pd_force(...))``).

    Args:
        length, rate, setpoint, setpoint_rate, kp, kv: as ``pd_force``.
        max_force: the saturation [N].

    Returns:
        The piston force [N], positive extends.
    """
    return saturated(pd_force(length, rate, setpoint, setpoint_rate, kp, kv), max_force)


@njit
def pd_law(lengths: np.ndarray, rates: np.ndarray, setpoint: np.ndarray, kp: np.ndarray,
           kv: np.ndarray, max_force: float) -> np.ndarray:
    """Eq. (40) on six legs towards fixed lengths, compiled, saturated.

    Args:
        lengths, rates, setpoint, kp, kv: float arrays (6,) [m, m/s, m, N/m, N s/m].
        max_force: the saturation [N].

    Returns:
        (6,) piston forces [N].
    """
    out = np.empty(lengths.shape[0])
    for i in range(lengths.shape[0]):
        out[i] = pd_leg(lengths[i], rates[i], setpoint[i], 0.0, kp[i], kv[i], max_force)
    return out


def pd_forces(lengths: ArrayLike, rates: ArrayLike, setpoint: ArrayLike, kp: ArrayLike,
              kv: ArrayLike, max_force: float) -> np.ndarray:
    """``pd_law`` for any six-number sequences (tests, scripts).

    Args:
        lengths, rates, setpoint, kp, kv: six values each, any sequence.
        max_force: the saturation [N].

    Returns:
        (6,) piston forces [N].
    """
    f = np.asarray
    return pd_law(f(lengths, float), f(rates, float), f(setpoint, float), f(kp, float),
                  f(kv, float), float(max_force))
