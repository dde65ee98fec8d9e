"""Control laws: six piston forces from the measured leg lengths and rates.

Every law follows one interface, so that ``sim``, the controller node and a
user's own law are interchangeable:

- constructed once as ``Law(mech, params)``: the ``Mechanism`` (geometry,
  masses, limits: the machine) and the controller's parameter dictionary
  (every key of the parameter file that applies to the controller: the gains
  ``kp``, ``kv``, the task's ``setpoint_lengths`` and ``initial_*``, the
  settings; ``Setup.to_params()``);
- called once per sample as ``law(t, lengths, rates, ref)`` with the sample
  time t [s], the measured L_i [m] and dL_i/dt [m/s] (numpy arrays (6,)) and
  the reference sample ``ref`` (a ``ReferenceSample``: ``ref.position``,
  ``ref.rotation``, ``ref.velocity``, ``ref.omega``, ``ref.acceleration``,
  ``ref.alpha``, ``ref.lengths``, ``ref.rates``; valid during the call only);
  it returns the six piston forces [N] (positive extends the piston);
- ``parameters``: the names of the parameters it reads, which the controller
  lets change at run time through ``set_parameter(name, value)`` (raise
  ``ValueError`` with the reason to refuse a value; nothing may change then).

The caller saturates the forces at +-max_force. A law that raises, or returns
anything but six finite numbers, has its forces withheld (``LawError``).

Built-in laws (``LAWS``):

- ``pd``: eq. (40), F = Kp (L_ref - L) - Kv (dL/dt - dL_ref/dt). With a fixed
  setpoint (dL_ref/dt = 0) it is the paper's law to the bit.
- ``pd_gravity``: eq. (40) plus the piston forces that hold platform and both
  parts of every leg against gravity at the measured pose: H F_g = eta(q, 0)
  (eq. 38 with zero velocity and acceleration), the pose from tracking forward
  kinematics of the measured lengths.
- ``computed_torque``: inverse dynamics of eq. (38) with the plant's own model
  in task space. Pose and twist from tracking FK of the measured lengths and
  rates; the commanded acceleration is
  a_c = a_ref + Kd (xdot_ref - xdot) + Kp (x_ref - x)
  per axis (x, y, z and the rotation vector of R_ref R^T), and
  F = H^-1 (J a_c + eta). With an exact model the error of each axis obeys
  e'' + Kd e' + Kp e = 0: natural frequency sqrt(Kp), damping ratio
  Kd / (2 sqrt(Kp)). Defaults ``ct_kp`` = 2500 1/s^2, ``ct_kd`` = 100 1/s:
  50 rad/s (8 Hz), critically damped.
"""
from __future__ import annotations

import importlib
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from stewart63_ros.core.controllers.control import PDGains, pd_force, pd_law, pd_leg, saturated
from stewart63_ros.core.controllers.reference import (
    I_ACC,
    I_ALPHA,
    I_LEN,
    I_OMEGA,
    I_POS,
    I_RATE,
    I_VEL,
    R_ACC,
    R_LEN,
    R_RATE,
    SAMPLE_SIZE,
    Reference,
    ReferenceSample,
)
from stewart63_ros.core.controllers.tracking import rotation_error
from stewart63_ros.core.mechanics.dynamics import Dynamics, inverse_dynamics_forces
from stewart63_ros.core.mechanics.fk import ForwardKinematics
from stewart63_ros.core.mechanics.fk_tracking import pose_and_twist
from stewart63_ros.core.mechanics.setup import task_from_params
from stewart63_ros.core.plumbing._jit import njit
from stewart63_ros.core.plumbing.errors import ParameterError
from stewart63_ros.core.plumbing.node_parameters import gain_vector, law_name
from stewart63_ros.core.plumbing.node_parameters import read as read_declared

if TYPE_CHECKING:
    from stewart63_ros.core.mechanics.mechanism import Mechanism
    from stewart63_ros.core.mechanics.setup import Setup

class LawError(RuntimeError):
    """A law that raised or returned forces that cannot be applied."""


# -- compiled kernels -----------------------------------------------------------------------
@njit
def _saturate(f, max_force):
    """Clip f to +-max_force in place; False (f untouched) if any entry is not finite."""
    for i in range(f.size):
        if not np.isfinite(f[i]):
            return False
    for i in range(f.size):
        f[i] = saturated(f[i], max_force)
    return True


# -- laws as kernels ------------------------------------------------------------------------
@njit
def _pd(lengths, rates, ref, kp, kv, max_force):
    """Eq. (40) towards the reference's lengths and rates, saturated (the sample
    array whole: two slices per call would cost more than the law)."""
    out = np.empty(6)
    for i in range(6):
        out[i] = pd_leg(lengths[i], rates[i], ref[I_LEN + i], ref[I_RATE + i], kp[i], kv[i],
                        max_force)
    return out


@njit
def _pd_gravity(const, base, plat, inertia, lengths, rates, pos, rot, ref, kp, kv, max_force):
    """Eq. (40) plus the holding forces H^-1 eta(q, 0) at the pose (t, R)."""
    zero = np.zeros(6)
    hold = inverse_dynamics_forces(const, base, plat, inertia, rot, pos, zero[:3], zero[3:],
                                   zero)
    out = np.empty(6)
    for i in range(6):
        f = pd_force(lengths[i], rates[i], ref[I_LEN + i], ref[I_RATE + i], kp[i], kv[i])
        out[i] = saturated(f + hold[i], max_force)
    return out


@njit
def _computed_torque(const, base, plat, inertia, pos, rot, twist, ref, kp, kd, max_force):
    """F = H^-1 (J a_c + eta), a_c = a_ref + Kd e' + Kp e (task space)."""
    e_rot = rotation_error(ref, rot)
    acc = np.empty(6)
    for a in range(3):
        acc[a] = (ref[I_ACC + a] + kd[a] * (ref[I_VEL + a] - twist[a])
                  + kp[a] * (ref[I_POS + a] - pos[a]))
        acc[3 + a] = (ref[I_ALPHA + a] + kd[3 + a] * (ref[I_OMEGA + a] - twist[3 + a])
                      + kp[3 + a] * e_rot[a])
    f = inverse_dynamics_forces(const, base, plat, inertia, rot, pos, twist[:3], twist[3:], acc)
    for i in range(6):
        f[i] = min(max(f[i], -max_force), max_force)
    return f


# -- the pose estimate ------------------------------------------------------------------------
class PoseEstimator:
    """Tracking FK of the measured lengths and rates (pose and twist): Newton from
    the previous estimate (``fk_tracking.pose_and_twist``, compiled), falling back on the
    assembly mode nearest the previous estimate when Newton fails.

    Starts at ``start``; ``position`` (3,), ``rotation`` (3, 3) and ``twist``
    (6,) hold the last estimate.

    Args:
        mech: the mechanism.
        start: (position (3,) [m], rotation (3, 3)), the run's initial pose.
    """

    def __init__(self, mech: Mechanism, start: tuple[ArrayLike, ArrayLike]) -> None:
        self.fk = ForwardKinematics(mech, start=start)
        self.position = np.array(start[0], dtype=float)
        self.rotation = np.array(start[1], dtype=float)
        self.twist = np.zeros(6)

    def __call__(self, lengths: np.ndarray,
                 rates: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Estimate the pose and twist of one sample.

        Args:
            lengths: L (6,) [m]; rates: dL/dt (6,) [m/s].

        Returns:
            (t (3,) [m], R (3, 3), twist (6,) = v [m/s], omega [rad/s], base frame).

        Raises:
            NoAssemblyError: the lengths admit no assembly.
        """
        fk = self.fk
        t, rot, twist, ok = pose_and_twist(fk.base, fk.legp, lengths, rates, self.position,
                                           self.rotation, 12)
        if not ok:
            mode = fk.nearest(lengths, self.position, self.rotation)   # NoAssemblyError
            t, rot = mode.position, mode.rotation
            v, w = fk.twist(t, rot, rates)
            twist = np.concatenate([v, w])
        self.position, self.rotation, self.twist = t, rot, twist
        return t, rot, twist


# -- the built-in laws ------------------------------------------------------------------------
class _LegGains:
    """The gains of eq. (40), ``kp`` [N/m] and ``kv`` [N s/m] per leg: read and
    checked here only (``gain_vector``), at start and at every change."""

    parameters = ('kp', 'kv')

    def _read_gains(self, params: Mapping[str, Any]) -> None:
        for name in self.parameters:
            if params.get(name) is None:
                raise ParameterError(name, 'missing')
            self.set_parameter(name, params[name])

    def set_parameter(self, name: str, value: Any) -> None:
        """Change the gain ``name`` (one of ``parameters``); ParameterError to refuse."""
        setattr(self, name, gain_vector(name, value))


class PDLaw(_LegGains):
    """``pd``: eq. (40) on every leg, towards the reference's lengths and rates.

    Args:
        mech: the mechanism (``max_force``).
        params: the controller's parameters (``kp``, ``kv``: six gains each).
    """

    def __init__(self, mech: Mechanism, params: Mapping[str, Any]) -> None:
        self.max_force = float(mech.max_force)
        self._read_gains(params)
        self.estimate = None

    def __call__(self, t: float, lengths: np.ndarray, rates: np.ndarray,
                 ref: ReferenceSample) -> np.ndarray:
        """The forces (6,) [N], saturated, for one sample (the module's law interface)."""
        return _pd(lengths, rates, ref.array, self.kp, self.kv, self.max_force)


class _ModelLaw:
    """A law that uses the plant's model at the estimated pose, tracked from
    the run's initial pose (the task's keys of ``params``)."""

    def __init__(self, mech: Mechanism, params: Mapping[str, Any]) -> None:
        self.max_force = float(mech.max_force)
        self.args = Dynamics(mech).kernel_args()
        task = task_from_params(mech, params)
        self.estimator = PoseEstimator(mech, (task.initial_position, task.initial_rotation))

    @property
    def estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """(position (3,) [m], rotation (3, 3)) of the last estimate."""
        return self.estimator.position, self.estimator.rotation


class PDGravityLaw(_LegGains, _ModelLaw):
    """``pd_gravity``: eq. (40) plus the forces holding the mechanism against gravity.

    Args:
        mech: the mechanism.
        params: the controller's parameters (``kp``, ``kv``).
    """

    def __init__(self, mech: Mechanism, params: Mapping[str, Any]) -> None:
        super().__init__(mech, params)
        self._read_gains(params)

    def holding_forces(self, position: ArrayLike, rotation: ArrayLike) -> np.ndarray:
        """H^-1 eta(q, 0): piston forces that hold the mechanism still at this pose.

        Args:
            position: t (3,) [m]; rotation: R (3, 3).

        Returns:
            (6,) forces [N].
        """
        zero = np.zeros(6)
        return inverse_dynamics_forces(*self.args, np.asarray(rotation, float),
                                       np.asarray(position, float), zero[:3], zero[3:], zero)

    def __call__(self, t: float, lengths: np.ndarray, rates: np.ndarray,
                 ref: ReferenceSample) -> np.ndarray:
        """The forces (6,) [N], saturated, for one sample (the module's law interface)."""
        pos, rot, _ = self.estimator(lengths, rates)
        return _pd_gravity(*self.args, lengths, rates, pos, rot, ref.array, self.kp, self.kv,
                           self.max_force)


class ComputedTorqueLaw(_ModelLaw):
    """``computed_torque``: inverse dynamics in task space with reference feedforward.

    Args:
        mech: the mechanism.
        params: the controller's parameters (``ct_kp`` [1/s^2], ``ct_kd`` [1/s]:
            six per task axis x, y, z, rx, ry, rz).
    """

    parameters = ('ct_kp', 'ct_kd')

    def __init__(self, mech: Mechanism, params: Mapping[str, Any]) -> None:
        super().__init__(mech, params)
        self.ct_kp = read_declared(params, 'ct_kp')
        self.ct_kd = read_declared(params, 'ct_kd')

    def set_parameter(self, name: str, value: Any) -> None:
        """Change the gain ``name`` (one of ``parameters``); ParameterError to refuse."""
        setattr(self, name, gain_vector(name, value))

    def __call__(self, t: float, lengths: np.ndarray, rates: np.ndarray,
                 ref: ReferenceSample) -> np.ndarray:
        """The forces (6,) [N], saturated, for one sample (the module's law interface)."""
        pos, rot, twist = self.estimator(lengths, rates)
        return _computed_torque(*self.args, pos, rot, twist, ref.array, self.ct_kp,
                                self.ct_kd, self.max_force)


LAWS = {'pd': PDLaw, 'pd_gravity': PDGravityLaw, 'computed_torque': ComputedTorqueLaw}
#: Every parameter a built-in law reads (all tunable at run time).
LAW_PARAMETERS = ('kp', 'kv', 'ct_kp', 'ct_kd')
#: The laws whose only restoring force is Kp times a leg's length error (eq. 40).
HOLDING_GAIN_LAWS = ('pd', 'pd_gravity')


def holding_gain_problem(law: str, kp: ArrayLike) -> str | None:
    """Why ``law`` with these gains cannot hold a pose, or None: the one rule of
    ``analyze`` and ``sweep``. Under eq. (40) a leg whose Kp is zero feels no
    force from its length error, so nothing brings it (or the platform) back.

    Args:
        law: the law's name; only ``HOLDING_GAIN_LAWS`` are checked.
        kp: the six position gains Kp_i [N/m].

    Returns:
        ``'the pd law cannot hold the pose: kp is zero on leg_3'`` (the first
        such leg), or None when every Kp_i > 0 or the law is another one.
    """
    if law not in HOLDING_GAIN_LAWS:
        return None
    gains = np.asarray(kp, dtype=float).ravel()
    zero = np.flatnonzero(~(gains > 0))
    if zero.size == 0:
        return None
    return 'the %s law cannot hold the pose: kp is zero on leg_%d' % (law, int(zero[0]) + 1)


def law_class(name: str) -> type:
    """The class of a built-in law, or of a user's ``package.module:Class``.

    Args:
        name: ``pd``, ``pd_gravity``, ``computed_torque`` or ``package.module:Class``.

    Returns:
        The class (imported, for a user's law).

    Raises:
        ParameterError: (key ``control_law``) an unknown name, a module that
            cannot be imported, or no such class in it.
    """
    law_name('control_law', name)
    if name in LAWS:
        return LAWS[name]
    if ':' not in name:
        raise ParameterError('control_law', 'unknown law %r: one of %s, or package.module:Class'
                             % (name, ', '.join(LAWS)))
    module_name, _, attr = name.partition(':')
    try:
        module = importlib.import_module(module_name)
    except Exception as exc:  # noqa: BLE001 - any import failure of user code is refused
        raise ParameterError('control_law', 'cannot import %s: %s: %s'
                             % (module_name, type(exc).__name__, exc)) from None
    cls = getattr(module, attr, None)
    if cls is None or not callable(cls):
        raise ParameterError('control_law', '%s has no class %s' % (module_name, attr))
    return cls


def make_law(name: str, mech: Mechanism, params: Mapping[str, Any]) -> Any:
    """Build the law ``name`` (built-in or ``package.module:Class``) from the parameters.

    Args:
        name: as for ``law_class``.
        mech: the mechanism; params: the controller's parameters.

    Returns:
        The law: callable as ``law(t, lengths, rates, ref)``.

    Raises:
        ParameterError: (key ``control_law``, or the law's own key) it cannot be built.
    """
    cls = law_class(name)
    try:
        law = cls(mech, params)
    except ParameterError:
        raise
    except Exception as exc:  # noqa: BLE001 - a user's constructor may raise anything
        raise ParameterError('control_law', '%s could not be built: %s: %s'
                             % (name, type(exc).__name__, exc)) from None
    if not callable(law):
        raise ParameterError('control_law', '%s is not callable as law(t, lengths, rates, ref)'
                             % name)
    return law


def _start_pose(setup: Setup) -> tuple[np.ndarray, np.ndarray]:
    """The run's initial pose: the assembly mode a lengths reference takes."""
    return setup.task.initial_position, setup.task.initial_rotation


class Controller:
    """A law with its reference: ``forces(t, lengths, rates)`` per sample.

    ``reference`` (a ``Reference``; default: hold the task's ``setpoint_lengths``) is
    sampled at ``t - start`` (``start``: the reference's time 0 on the sample
    clock; None: the first sample's time). Forces are saturated at max_force;
    a law that raises or returns anything but six finite numbers raises
    ``LawError`` (the caller withholds the forces).

    Args:
        setup: the machine, gains, task and settings (``params.load_setup``).
        params: the controller's parameters, over ``setup.to_params()``.
        law: the law's name (default: ``params['control_law']``, else ``pd``).
        reference: what to follow (default: hold ``setup.task.setpoint_lengths``).
        start: the reference's time 0 on the sample clock [s] (None: the first sample).

    Raises:
        ParameterError: the law cannot be built from the parameters.
    """

    def __init__(self, setup: Setup, params: Mapping[str, Any] | None = None,
                 law: str | None = None, reference: Reference | None = None,
                 start: float | None = 0.0) -> None:
        self.setup = setup
        self.mech = mech = setup.mechanism
        self.params = setup.to_params()
        self.params.update(params or {})
        self.max_force = float(mech.max_force)
        name = law if law is not None else read_declared(self.params, 'control_law')
        self.law = make_law(name, mech, self.params)
        self.law_name = name
        self.sample = ReferenceSample(np.zeros(SAMPLE_SIZE))
        self.set_reference(reference or Reference.constant_lengths(
            mech, setup.task.setpoint_lengths, near=_start_pose(setup)), start)

    def set_reference(self, reference: Reference, start: float | None = None) -> None:
        """Follow ``reference`` from ``start`` on the sample clock (None: the next sample)."""
        self.reference = reference
        self.start = start
        if reference.kind == 'lengths':     # fixed: sampled once, here
            reference.sample(0.0, self.sample.array)
        self._choose_path()

    def set_law(self, name: str) -> None:
        """Switch law (a new one built from the current parameters); ParameterError to refuse."""
        self.law = make_law(name, self.mech, self.params)
        self.law_name = name
        self.params['control_law'] = name
        self._choose_path()

    def _choose_path(self) -> None:
        # The one fast path: the built-in pd law towards fixed lengths is eq. (40)
        # with (dL/dt)_0 = 0, which the compiled loops (``pd_gains``) and
        # ``forces`` evaluate directly, without a reference sample per call.
        fixed = self.reference.kind == 'lengths' and type(self.law) is PDLaw
        self._fixed_pd = self.law if fixed else None

    def pd_gains(self) -> PDGains | None:
        """Eq. (40) towards fixed lengths, if that is what this controller computes.

        Returns:
            ``PDGains`` (setpoint, kp, kv, max_force) of the built-in ``pd`` law
            holding a lengths reference (the compiled loops of ``simulate`` run
            it themselves); None for any other law or reference.
        """
        law = self.law
        if law is not self._fixed_pd:
            return None
        return PDGains(self.sample.array[R_LEN], law.kp, law.kv, self.max_force)

    def set_parameter(self, name: str, value: Any) -> None:
        """A gain of the active law (checked by it); other laws' gains are checked
        and kept for when they become active. ParameterError to refuse."""
        if name in getattr(self.law, 'parameters', ()):
            try:
                self.law.set_parameter(name, value)
            except ParameterError:
                raise
            except Exception as exc:  # noqa: BLE001 - a user law's refusal
                raise ParameterError(name, str(exc)) from None
        elif name in LAW_PARAMETERS:
            gain_vector(name, value)
        self.params[name] = value

    def forces(self, t: float, lengths: np.ndarray, rates: np.ndarray) -> np.ndarray:
        """The law's forces for one sample.

        Args:
            t: the sample time [s] on the sample clock.
            lengths: L (6,) [m]; rates: dL/dt (6,) [m/s]; float arrays.

        Returns:
            (6,) forces [N], saturated at +-max_force.

        Raises:
            LawError: the law raised, or returned anything but six finite numbers.
        """
        if self.start is None:
            self.start = t
        ref = self.sample
        law = self.law
        if law is self._fixed_pd:       # the fast path (``_choose_path``)
            return pd_law(lengths, rates, ref.array[R_LEN], law.kp, law.kv, self.max_force)
        self.reference.sample(t - self.start, ref.array)
        try:
            f = law(t, lengths, rates, ref)
            if type(f) is not np.ndarray or f.dtype != np.float64:
                f = np.asarray(f, dtype=float)
        except Exception as exc:  # noqa: BLE001 - any failure of the law withholds the forces
            raise LawError('%s raised %s: %s' % (self.law_name, type(exc).__name__, exc)) from exc
        if f.shape != (6,) or not _saturate(f, self.max_force):
            raise LawError('%s returned %s, not six finite forces'
                           % (self.law_name, np.array2string(np.asarray(f), precision=4)))
        return f

    def __call__(self, lengths: np.ndarray, rates: np.ndarray, t: float = 0.0) -> np.ndarray:
        """``forces(t, lengths, rates)``, in the argument order of the sensors' reading."""
        return self.forces(t, lengths, rates)

    @property
    def estimate(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(position (3,), rotation (3, 3)) the law estimated at the last sample, or None."""
        return getattr(self.law, 'estimate', None)

    def reference_lengths(self) -> np.ndarray:
        """The desired leg lengths (6,) [m] of the last reference sample (a view)."""
        return self.sample.array[R_LEN]

    def reference_rates(self) -> np.ndarray:
        """The desired leg rates (6,) [m/s] of the last reference sample (a view)."""
        return self.sample.array[R_RATE]

    def reference_acceleration(self) -> np.ndarray:
        """The desired acceleration (3,) [m/s^2] of the last reference sample (a view)."""
        return self.sample.array[R_ACC]


class PDController(Controller):
    """The paper's controller: the built-in ``pd`` law holding fixed leg lengths,
    eq. (40), with the setup's gains and the mechanism's saturation (``sim``'s default).

    Args:
        setup: the machine (``max_force``), gains (``kp``, ``kv``) and task
            (``setpoint_lengths``).
        setpoint: (6,) lengths to hold [m] instead of ``setup.task.setpoint_lengths``.
        params: the controller's parameters, over ``setup.to_params()``.

    Raises:
        ParameterError: a gain the law refuses.
        ValueError: a setpoint that is not six finite lengths.
    """

    def __init__(self, setup: Setup, setpoint: ArrayLike | None = None,
                 params: Mapping[str, Any] | None = None) -> None:
        lengths = np.array(setup.task.setpoint_lengths if setpoint is None else setpoint, float)
        if lengths.shape != (6,) or not np.all(np.isfinite(lengths)):
            raise ValueError('setpoint must be six finite lengths')
        super().__init__(setup, params, law='pd',
                         reference=Reference.constant_lengths(setup.mechanism, lengths,
                                                              near=_start_pose(setup)))

    @property
    def setpoint(self) -> np.ndarray:
        """The lengths held (6,) [m], (L_i)_0 of eq. (40) (a view)."""
        return self.sample.array[R_LEN]

    @property
    def kp(self) -> np.ndarray:
        """Kp (6,) [N/m] of the law."""
        return self.law.kp

    @property
    def kv(self) -> np.ndarray:
        """Kv (6,) [N s/m] of the law."""
        return self.law.kv
