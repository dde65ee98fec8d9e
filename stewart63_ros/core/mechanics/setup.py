"""A run's parameters in their parts: the machine, the gains, the task, the
node settings (``Setup``), and the checks that make them from a flat parameter
dictionary (``validated_setup``).

Every key of the parameter file is declared once, in core/plumbing/node_parameters.py
(unit, range, words, check). Which object holds it at run time is the rule of
this module (docs/design.md, "One parameter model"):

- ``mechanism`` (``mechanism.Mechanism``): the machine, everything kinematics
  and dynamics need;
- ``gains`` (``Gains``): ``kp``, ``kv`` of eq. (40);
- ``task`` (``Task``): what a run asks of the machine and where it starts: the
  setpoint lengths (L_i)_0 and the initial pose and rates;
- ``settings``: every other key (sensor rate, seeds, faults, clock mode, ...),
  as given, read-only; ``Setup.setting(name)`` reads one through its
  declaration.

A leaf module (it imports leaf modules only), so every module may name these
types in its hints without an import circle (test/test_imports.py).
"""
from __future__ import annotations

import dataclasses
import types
from collections.abc import Mapping
from typing import Any

import numpy as np

from stewart63_ros.core.mechanics.mechanism import (
    MECHANISM_KEYS,
    Mechanism,
    changed_params,
    validated,
)
from stewart63_ros.core.mechanics.rotation import rotation_from_euler
from stewart63_ros.core.plumbing.errors import ParameterError
from stewart63_ros.core.plumbing.node_parameters import DEFAULT_COND_THRESHOLD, gain_vector
from stewart63_ros.core.plumbing.node_parameters import read as read_declared


def _frozen(arr: Any) -> np.ndarray:
    arr = np.array(arr, dtype=float)
    arr.setflags(write=False)
    return arr


def _lists(obj: Any) -> dict:
    """The fields of a dataclass as a flat {key: value}, lists for arrays."""
    return {f.name: (np.asarray(getattr(obj, f.name)).ravel().tolist()
                     if np.ndim(getattr(obj, f.name)) else getattr(obj, f.name))
            for f in dataclasses.fields(obj)}


@dataclasses.dataclass(frozen=True, eq=False)
class Gains:
    """The gains of eq. (40), per leg, read-only (6,) arrays.

    Attributes:
        kp: Kp [N/m], each >= 0.
        kv: Kv [N s/m], each >= 0.
    """
    kp: np.ndarray
    kv: np.ndarray


@dataclasses.dataclass(frozen=True, eq=False)
class Task:
    """What a run asks of the machine, and where it starts; read-only arrays.

    Attributes:
        setpoint_lengths: (L_i)_0 (6,) [m], the lengths eq. (40) holds.
        initial_position: t_0 (3,) [m], base frame.
        initial_velocity: dt_0/dt (3,) [m/s].
        initial_orientation: theta_0 (3,) [rad] (rotation.py's Euler angles).
        initial_orientation_rate: dtheta_0/dt (3,) [rad/s].
    """
    setpoint_lengths: np.ndarray
    initial_position: np.ndarray
    initial_velocity: np.ndarray
    initial_orientation: np.ndarray
    initial_orientation_rate: np.ndarray

    @property
    def initial_rotation(self) -> np.ndarray:
        """R_0 (3, 3), platform to base, of ``initial_orientation``."""
        return rotation_from_euler(self.initial_orientation)


#: The keys each part holds; every other key is a setting.
GAIN_KEYS = frozenset(f.name for f in dataclasses.fields(Gains))
TASK_KEYS = frozenset(f.name for f in dataclasses.fields(Task))


@dataclasses.dataclass(frozen=True, eq=False)
class Setup:
    """A run's parameters: the machine, the gains, the task and the settings.

    Attributes:
        mechanism: the machine.
        gains: Kp, Kv of eq. (40).
        task: the setpoint and the initial state.
        settings: every other key, as given (read-only); ``setting`` reads one.
    """
    mechanism: Mechanism
    gains: Gains
    task: Task
    settings: Mapping[str, Any] = dataclasses.field(
        default_factory=lambda: types.MappingProxyType({}))

    def setting(self, name: str) -> Any:
        """The value of the declared setting ``name``, defaulted and checked
        by its declaration (core/plumbing/node_parameters.py).

        Args:
            name: a key declared in ``node_parameters.DECLARED``.

        Returns:
            The checked value.

        Raises:
            ParameterError: the value does not pass the key's check.
            KeyError: ``name`` is not declared.
        """
        return read_declared(self.settings, name)

    def to_params(self) -> dict:
        """The flat parameter dictionary of every part.

        Returns:
            {key: value}, lists for arrays; ``validated_setup`` of it gives
            an equal setup.
        """
        return {**self.settings, **self.mechanism.to_params(), **_lists(self.gains),
                **_lists(self.task)}

    def replace(self, **changes: Any) -> Setup:
        """A copy with some keys changed, each in its part, validated again
        (the checks of ``validated_setup``, the one path of every change).

        Args:
            **changes: parameter keys and new values, of any part.

        Returns:
            The new setup.

        Raises:
            ParameterError: the changed setup is not valid.
        """
        return validated_setup(changed_params(self.to_params(), changes))

    def with_mechanism(self, mechanism: Mechanism) -> Setup:
        """This setup on another machine (the task checked against it again).

        Args:
            mechanism: the new machine.

        Returns:
            The new setup.

        Raises:
            ParameterError: the task does not fit the new machine's stroke.
        """
        return self.replace(**mechanism.to_params())


def gains_from_params(params: Mapping[str, Any]) -> Gains:
    """The gains of eq. (40), checked by their one check (``gain_vector``).

    Args:
        params: {key: value} with ``kp`` and ``kv``.

    Returns:
        The gains.

    Raises:
        ParameterError: a gain missing, not six numbers, or negative.
    """
    values = {}
    for key in sorted(GAIN_KEYS):
        if params.get(key) is None:
            raise ParameterError(key, 'missing')
        values[key] = _frozen(gain_vector(key, params[key]))
    return Gains(**values)


def _vector(params: Mapping[str, Any], key: str, size: int) -> np.ndarray:
    if key not in params:
        raise ParameterError(key, 'missing')
    try:
        arr = np.asarray(params[key], dtype=float).ravel()
    except (TypeError, ValueError):
        raise ParameterError(key, 'expected %d numbers, got %r' % (size, params[key])) from None
    if arr.size != size:
        raise ParameterError(key, 'expected %d numbers, got %d' % (size, arr.size))
    if not np.all(np.isfinite(arr)):
        raise ParameterError(key, 'non-finite value (NaN or Inf) in %r' % (params[key],))
    return _frozen(arr)


def task_from_params(mech: Mechanism, params: Mapping[str, Any]) -> Task:
    """The task of ``params``, checked against the machine's stroke.

    Args:
        mech: the machine the task is for.
        params: {key: value} with the task's keys.

    Returns:
        The task.

    Raises:
        ParameterError: a key missing or out of its range; the initial pose
            or the setpoint puts legs outside the stroke (eq. (5), every such
            leg named); the initial pose is singular (``START_COND_LIMIT``,
            the legs named).
    """
    task = Task(setpoint_lengths=_vector(params, 'setpoint_lengths', 6),
                initial_position=_vector(params, 'initial_position', 3),
                initial_velocity=_vector(params, 'initial_velocity', 3),
                initial_orientation=_vector(params, 'initial_orientation', 3),
                initial_orientation_rate=_vector(params, 'initial_orientation_rate', 3))
    if np.any(task.setpoint_lengths <= 0):
        raise ParameterError('setpoint_lengths', 'lengths must be > 0')
    legs = mech.leg_vectors(task.initial_position, task.initial_rotation)
    lengths = np.linalg.norm(legs, axis=1)  # eq. (5)
    for key, values in (('initial_position', lengths),
                        ('setpoint_lengths', task.setpoint_lengths)):
        bad = np.flatnonzero((values < mech.leg_length_min) | (values > mech.leg_length_max))
        if bad.size:     # every leg named: on a 6-6 a bad start often strands several
            raise ParameterError(
                key, '%s %s outside the stroke [leg_length_min %g, leg_length_max %g]' % (
                    ', '.join('leg_%d length %.4f m' % (i + 1, values[i]) for i in bad),
                    'is' if bad.size == 1 else 'are', mech.leg_length_min, mech.leg_length_max))
    _check_not_singular(mech, task, legs, lengths)
    return task


#: A start pose whose Jacobian's condition number exceeds this is refused
#: (the fk node's default ``singularity_threshold``).
START_COND_LIMIT = DEFAULT_COND_THRESHOLD


def _check_not_singular(mech: Mechanism, task: Task, legs: np.ndarray,
                        lengths: np.ndarray) -> None:
    """Refuse a start pose at (or next to) a singularity of J, row i = [s_i, q_i x s_i]
    (eq. 13): there the legs cannot hold the platform (J^T F = wrench has no
    bounded answer), the dynamics' J^T solve blows up and the forward kinematics
    cannot tell its branches apart. The legs named carry the left null vector
    w of J (J^T w ~ 0: forces in them that no wrench balances)."""
    s = legs / lengths[:, None]
    q = mech.leg_platform_points @ task.initial_rotation.T      # R p_i, base frame
    jac = np.hstack([s, np.cross(q, s)])
    sv = np.linalg.svd(jac, compute_uv=False)
    cond = np.inf if sv[-1] <= 0 else sv[0] / sv[-1]
    if cond <= START_COND_LIMIT:
        return
    w = np.linalg.svd(jac.T)[2][-1]       # J^T w = sigma_min w' : the weakest leg forces
    named = np.flatnonzero(np.abs(w) > 0.1 * np.abs(w).max()) + 1
    raise ParameterError('initial_position', 'the start pose is singular (Jacobian condition '
                         'number %.3g > %g): legs %s can pull against each other with no '
                         'wrench on the platform, which they cannot hold there; start the '
                         'platform elsewhere or change the geometry'
                         % (cond, START_COND_LIMIT, ', '.join(str(i) for i in named)))


def validated_setup(params: Mapping[str, Any]) -> Setup:
    """The setup of a flat parameter dictionary, every part checked.

    Args:
        params: {key: value}: the machine's, gains', task's keys and any
            others (the settings).

    Returns:
        The validated, immutable setup.

    Raises:
        ParameterError: a key missing or out of its range (docs/interface.md),
            named in the error.
    """
    mech = validated(params)
    gains = gains_from_params(params)
    task = task_from_params(mech, params)
    held = MECHANISM_KEYS | GAIN_KEYS | TASK_KEYS
    settings = types.MappingProxyType({k: v for k, v in params.items() if k not in held})
    return Setup(mech, gains, task, settings)
