"""The paper's PD law on leg lengths, eq. (40), with force saturation."""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from stewart63_ros.core._jit import njit, njit_kernel

if TYPE_CHECKING:
    from stewart63_ros.core.params import Mechanism


@njit_kernel
def pd_leg(length: float, rate: float, setpoint: float, kp: float, kv: float,
           max_force: float) -> float:
    """Eq. (40) for one leg, scalars: the arithmetic of ``pd_law`` (a NaN stays NaN,
    as with np.minimum/np.maximum), for the compiled right-hand side.

    Args:
        length: L [m]; rate: dL/dt [m/s]; setpoint: (L)_0 [m].
        kp: [N/m]; kv: [N s/m]; max_force: the saturation [N].

    Returns:
        The piston force [N], positive extends.
    """
    force = kp * (setpoint - length) - kv * rate
    if force > max_force:
        return max_force
    if force < -max_force:
        return -max_force
    return force


@njit
def pd_law(lengths: np.ndarray, rates: np.ndarray, setpoint: np.ndarray, kp: np.ndarray,
           kv: np.ndarray, max_force: float) -> np.ndarray:
    """Eq. (40) on six legs, compiled: Kp (L_0 - L) - Kv dL/dt, clipped to +-max_force.

    Args:
        lengths, rates, setpoint, kp, kv: float arrays (6,) [m, m/s, m, N/m, N s/m].
        max_force: the saturation [N].

    Returns:
        (6,) piston forces [N].
    """
    force = kp * (setpoint - lengths) - kv * rates
    return np.minimum(np.maximum(force, -max_force), max_force)


def pd_forces(lengths: ArrayLike, rates: ArrayLike, setpoint: ArrayLike, kp: ArrayLike,
              kv: ArrayLike, max_force: float) -> np.ndarray:
    """F_i = Kp_i ((L_i)_0 - L_i) - Kv_i dL_i/dt, clipped to +-max_force [N], eq. (40).

    Args:
        lengths, rates, setpoint, kp, kv: six values each, any sequence.
        max_force: the saturation [N].

    Returns:
        (6,) piston forces [N].
    """
    f = np.asarray
    return pd_law(f(lengths, float), f(rates, float), f(setpoint, float), f(kp, float),
               f(kv, float), float(max_force))


class PDController:
    """Eq. (40) with the gains, setpoint and saturation of one mechanism.

    Args:
        mech: the mechanism (``kp``, ``kv``, ``max_force``, ``setpoint_lengths``).
        setpoint: (6,) lengths to hold [m] instead of ``mech.setpoint_lengths``.
    """

    def __init__(self, mech: Mechanism, setpoint: ArrayLike | None = None) -> None:
        self.kp = np.array(mech.kp, dtype=float)
        self.kv = np.array(mech.kv, dtype=float)
        self.max_force = float(mech.max_force)
        self.setpoint = np.array(mech.setpoint_lengths if setpoint is None else setpoint, float)

    def __call__(self, lengths: np.ndarray, rates: np.ndarray) -> np.ndarray:
        """Eq. (40) on the measured legs.

        Args:
            lengths, rates: float arrays (6,) L [m], dL/dt [m/s].

        Returns:
            (6,) piston forces [N], clipped to +-max_force.
        """
        return pd_law(lengths, rates, self.setpoint, self.kp, self.kv, self.max_force)

    @property
    def setpoint(self) -> np.ndarray:
        """The lengths held (6,) [m], (L_i)_0 of eq. (40).

        Setting it stores a float copy of six finite values (any sequence).

        Raises:
            ValueError: on setting anything but six finite values.
        """
        return self._setpoint

    @setpoint.setter
    def setpoint(self, value: ArrayLike) -> None:
        """Set the lengths held (6,) [m]; ValueError unless six finite values."""
        value = np.array(value, dtype=float)
        if value.shape != (6,) or not np.all(np.isfinite(value)):
            raise ValueError('setpoint must be six finite lengths')
        self._setpoint = value
