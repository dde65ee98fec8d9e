"""The mechanism: the machine a run drives, validated (``Mechanism``), and the
checks that make one from a flat parameter dictionary (``validated``).

The machine is everything the kinematics and dynamics need and nothing a run
chooses: geometry, masses, inertias, friction, gravity, the stroke and its end
stops, the force limit and the sensors' zero offsets. The gains of eq. (40),
the setpoint and the initial state, and the nodes' settings are the run's:
``setup.Setup`` holds them beside the mechanism (docs/design.md, "One
parameter model").

A leaf module: it imports nothing of the package but other leaf modules
(``errors``, ``legs``, ``node_parameters``), so every module can name
``Mechanism`` in its type hints without an import circle
(test/test_imports.py). Reading the parameter file is ``params``' job.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from stewart63_ros.core.plumbing.errors import ParameterError
from stewart63_ros.core.plumbing.legs import LEG_VERTEX, SIX_JOINTS
from stewart63_ros.core.plumbing.node_parameters import read as read_declared


def _vector(params: Mapping[str, Any], key: str, size: int) -> np.ndarray:
    if key not in params:
        raise ParameterError(key, 'missing')
    value = params[key]
    if isinstance(value, (int, float)) and size == 1:
        value = [value]
    try:
        arr = np.asarray(value, dtype=float).ravel()
    except (TypeError, ValueError):
        raise ParameterError(key, 'expected %d numbers, got %r' % (size, value)) from None
    if arr.size != size:
        raise ParameterError(key, 'expected %d numbers, got %d' % (size, arr.size))
    if not np.all(np.isfinite(arr)):
        raise ParameterError(key, 'non-finite value (NaN or Inf) in %r' % (value,))
    arr.setflags(write=False)
    return arr


def _scalar(params, key, positive=False, nonnegative=False) -> float:
    value = float(_vector(params, key, 1)[0])
    if positive and value <= 0:
        raise ParameterError(key, 'must be > 0, got %g' % value)
    if nonnegative and value < 0:
        raise ParameterError(key, 'must be >= 0, got %g' % value)
    return value


def _check_axisymmetric_inertia(key, axial_transverse):
    axial, transverse = axial_transverse
    if axial < 0 or transverse <= 0:
        raise ParameterError(key, 'axial must be >= 0 and transverse > 0, got %s'
                             % list(axial_transverse))
    # Principal moments (axial, t, t) obey the triangle inequality: axial <= 2 t.
    if axial > 2 * transverse * (1 + 1e-12):
        raise ParameterError(key, 'axial %g > 2 x transverse %g breaks the triangle inequality'
                             % (axial, transverse))



def inertia_matrix(six: np.ndarray) -> np.ndarray:
    """[Ixx, Iyy, Izz, Ixy, Ixz, Iyz] -> the symmetric 3x3 matrix (elements, not products).

    Args:
        six: (6,) the matrix elements [kg m^2], as ``platform_inertia`` lists them.

    Returns:
        (3, 3) the symmetric inertia matrix.
    """
    ixx, iyy, izz, ixy, ixz, iyz = six
    return np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])


def _frozen(arr) -> np.ndarray:
    arr = np.array(arr, dtype=float)
    arr.setflags(write=False)
    return arr


@dataclasses.dataclass(frozen=True, eq=False)
class Mechanism:
    """A validated platform, a 6-3 or a 6-6: the machine, and nothing a run chooses.

    Arrays are read-only. ``platform_points`` holds 3 vertices (a 6-3, the
    paper's: leg i, 0-based, meets vertex ``LEG_VERTEX[i]``) or 6 joints (a 6-6:
    leg i at joint i); ``leg_platform_points`` is always the (6, 3) point of each
    leg, and the dynamics and kinematics read only it.
    Every field is a key of the parameter file, declared (unit, range, words)
    in core/plumbing/node_parameters.py: the model's keys in ``MODEL``, the end stops
    and the sensors' zero offsets in ``DECLARED``.
    """
    base_points: np.ndarray          # (6, 3) b_i, base frame
    platform_points: np.ndarray      # (3, 3) p_k of a 6-3, or (6, 3) p_i of a 6-6; platform frame
    platform_mass: float
    platform_com: np.ndarray         # (3,)
    platform_inertia: np.ndarray     # (3, 3) about the COM, platform frame
    leg_lower_mass: float
    leg_upper_mass: float
    leg_lower_com: float
    leg_upper_com: float
    leg_lower_inertia: np.ndarray    # (axial, transverse)
    leg_upper_inertia: np.ndarray
    piston_damping: float
    ujoint_damping: float
    gravity: np.ndarray
    leg_length_min: float
    leg_length_max: float
    max_force: float
    endstop_stiffness: float         # [N/m] past the stroke; inf: rigid
    endstop_damping: float           # [N s/m]
    leg_length_offset: np.ndarray    # (6,) o_i [m]: a sensor reads L_i + o_i

    @property
    def layout(self) -> str:
        """'6-3' (three platform vertices, legs in pairs) or '6-6' (six joints)."""
        return '6-3' if len(self.platform_points) == 3 else '6-6'

    @property
    def leg_vertex(self) -> np.ndarray:
        """(6,) the row of ``platform_points`` each leg meets: ``LEG_VERTEX``
        for a 6-3, 0 … 5 for a 6-6."""
        return LEG_VERTEX if len(self.platform_points) == 3 else SIX_JOINTS

    @property
    def leg_platform_points(self) -> np.ndarray:
        """(6, 3): the platform joint of each leg, platform frame (a 6-3's p_k
        repeated for its two legs)."""
        return self.platform_points[self.leg_vertex]

    def leg_vectors(self, position: ArrayLike, rot: np.ndarray) -> np.ndarray:
        """S_i = R p_i + t - b_i, eq. (2) (``kinematics.leg_vectors`` is this).

        Args:
            position: t (3,) [m], base frame; rot: R (3, 3), platform to base.

        Returns:
            (6, 3) S_i [m], from each U-joint to its platform vertex, base frame.
        """
        return self.leg_platform_points @ rot.T + np.asarray(position) - self.base_points

    def neutral_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """A pose of the machine alone, for when no run gives one (a run's
        start is its task's initial pose): the platform level, its vertices'
        centre over the base points' centre, on the side the base plane's
        normal (z up) points to, the legs' mean square length at mid-stroke.

        Returns:
            (position t (3,) [m], rotation R (3, 3) = identity).
        """
        base = self.base_points
        normal = np.linalg.svd(base - base.mean(0))[2][2]
        normal = normal if normal[2] >= 0 else -normal
        legs = self.leg_platform_points - self.platform_points.mean(0) + base.mean(0) - base
        flat = legs - np.outer(legs @ normal, normal)       # in the base plane
        mid = 0.5 * (self.leg_length_min + self.leg_length_max)
        height = np.sqrt(max(mid ** 2 - float(np.mean(np.sum(flat ** 2, axis=1))),
                             (0.1 * mid) ** 2))
        return base.mean(0) - self.platform_points.mean(0) + height * normal, np.eye(3)

    def replace(self, **changes: Any) -> Mechanism:
        """A copy with some fields changed, validated again (the checks of
        ``validated``, the one path of every change).

        Args:
            **changes: field names and new values (``platform_inertia`` as six
                numbers or the (3, 3) matrix).

        Returns:
            The new mechanism.

        Raises:
            ParameterError: the changed mechanism is not valid, or a name is
                not one of its fields.
        """
        unknown = sorted(set(changes) - MECHANISM_KEYS)
        if unknown:
            raise ParameterError(unknown[0], 'not a field of the mechanism')
        return validated(changed_params(self.to_params(), changes))

    def to_params(self) -> dict:
        """The flat parameter dictionary this mechanism was built from.

        Returns:
            {key: value} of every field, with lists for arrays.
        """
        out = {}
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if field.name == 'platform_inertia':
                value = [value[0, 0], value[1, 1], value[2, 2],
                         value[0, 1], value[0, 2], value[1, 2]]
            out[field.name] = np.asarray(value).ravel().tolist() if np.ndim(value) else value
        return out

def changed_params(params: Mapping[str, Any], changes: Mapping[str, Any]) -> dict:
    """``params`` with ``changes`` over it, as a parameter file holds them: lists
    for arrays, ``platform_inertia`` as six numbers when given as the matrix.

    Args:
        params: the flat parameter dictionary.
        changes: keys and new values.

    Returns:
        A new flat dictionary (not yet checked).
    """
    out = dict(params)
    out.update({k: (np.asarray(v).ravel().tolist() if np.ndim(v) else v)
                for k, v in changes.items()})
    if 'platform_inertia' in changes and np.shape(changes['platform_inertia']) == (3, 3):
        m = np.asarray(changes['platform_inertia'])
        out['platform_inertia'] = [m[0, 0], m[1, 1], m[2, 2], m[0, 1], m[0, 2], m[1, 2]]
    return out


#: The keys the mechanism holds (the others of a parameter file are the run's:
#: ``setup.Setup``).
MECHANISM_KEYS = frozenset(f.name for f in dataclasses.fields(Mechanism))


def validated(params: Mapping[str, Any]) -> Mechanism:
    """The mechanism of a flat parameter dictionary, every value checked.

    Args:
        params: {key: value}, the mechanism's keys (any others are ignored
            here: they are the run's, ``setup.setup_from_params``).

    Returns:
        The validated, immutable mechanism.

    Raises:
        ParameterError: a key missing or out of its range (docs/interface.md),
            named in the error.
    """
    base = _vector(params, 'base_points', 18).reshape(6, 3)
    plat = _platform_points(params)
    _check_geometry(base, plat)

    inertia6 = _vector(params, 'platform_inertia', 6)
    inertia = inertia_matrix(inertia6)
    eig = np.linalg.eigvalsh(inertia)
    if eig[0] <= 0:
        raise ParameterError('platform_inertia', 'not positive definite (eigenvalues %s)'
                             % np.round(eig, 6).tolist())
    if eig[2] > eig[0] + eig[1] + 1e-12 * eig[2]:
        raise ParameterError('platform_inertia', 'principal moments %s break the triangle '
                             'inequality' % np.round(eig, 6).tolist())

    lower_inertia = _vector(params, 'leg_lower_inertia', 2)
    upper_inertia = _vector(params, 'leg_upper_inertia', 2)
    _check_axisymmetric_inertia('leg_lower_inertia', lower_inertia)
    _check_axisymmetric_inertia('leg_upper_inertia', upper_inertia)

    lmin = _scalar(params, 'leg_length_min', positive=True)
    lmax = _scalar(params, 'leg_length_max', positive=True)
    if lmax <= lmin:
        raise ParameterError('leg_length_max',
                             'must exceed leg_length_min (%g <= %g)' % (lmax, lmin))

    mech = Mechanism(
        base_points=_frozen(base),
        platform_points=_frozen(plat),
        platform_mass=_scalar(params, 'platform_mass', positive=True),
        platform_com=_vector(params, 'platform_com', 3),
        platform_inertia=_frozen(inertia),
        leg_lower_mass=_scalar(params, 'leg_lower_mass', positive=True),
        leg_upper_mass=_scalar(params, 'leg_upper_mass', positive=True),
        leg_lower_com=_scalar(params, 'leg_lower_com', nonnegative=True),
        leg_upper_com=_scalar(params, 'leg_upper_com', nonnegative=True),
        leg_lower_inertia=lower_inertia,
        leg_upper_inertia=upper_inertia,
        piston_damping=_scalar(params, 'piston_damping', nonnegative=True),
        ujoint_damping=_scalar(params, 'ujoint_damping', nonnegative=True),
        gravity=_vector(params, 'gravity', 3) if 'gravity' in params
        else _frozen([0.0, 0.0, -9.81]),
        leg_length_min=lmin,
        leg_length_max=lmax,
        max_force=_scalar(params, 'max_force', positive=True),
        # declared with the nodes' keys (a default each), checked by their declaration
        endstop_stiffness=read_declared(params, 'endstop_stiffness'),
        endstop_damping=read_declared(params, 'endstop_damping'),
        leg_length_offset=_frozen(read_declared(params, 'leg_length_offset')),
    )
    if mech.leg_lower_com > lmax or mech.leg_upper_com > lmax:
        raise ParameterError('leg_lower_com' if mech.leg_lower_com > lmax else 'leg_upper_com',
                             'centre of mass lies beyond the longest leg (%g m)' % lmax)
    return mech


def _platform_points(params: Mapping[str, Any]) -> np.ndarray:
    """(3, 3) for 9 numbers (a 6-3), (6, 3) for 18 (a 6-6)."""
    value = params.get('platform_points')
    size = np.size(value) if isinstance(value, (list, tuple, np.ndarray)) else 9
    if size not in (9, 18):
        raise ParameterError('platform_points', 'expected 9 numbers (a 6-3: p_1 … p_3) or 18 '
                             '(a 6-6: p_1 … p_6), got %d' % size)
    return _vector(params, 'platform_points', size).reshape(-1, 3)


def _check_geometry(base: np.ndarray, plat: np.ndarray) -> None:
    for i in range(6):
        for j in range(i + 1, 6):
            if np.linalg.norm(base[i] - base[j]) < 1e-6:
                pair = (i // 2 == j // 2)
                raise ParameterError('base_points', '%s b_%d and b_%d coincide'
                                     % ('the pair' if pair else 'points', i + 1, j + 1))
    # A 6-6's joints are six: two that coincide make it a different mechanism
    # (write a 6-3, or a 6-4, which the rig does not model), so refuse them.
    legs = ('legs %d and %d' if len(plat) == 6 else 'legs %d, %d')
    for i in range(len(plat)):
        for j in range(i + 1, len(plat)):
            if np.linalg.norm(plat[i] - plat[j]) < 1e-6:
                which = (legs % (i + 1, j + 1) if len(plat) == 6 else
                         'legs %d, %d and %d, %d' % (2 * i + 1, 2 * i + 2, 2 * j + 1, 2 * j + 2))
                raise ParameterError('platform_points', 'p_%d and p_%d coincide (%s)'
                                     % (i + 1, j + 1, which))
    centred_plat = plat - plat.mean(axis=0)
    sv_plat = np.linalg.svd(centred_plat, compute_uv=False)
    if sv_plat[1] < 1e-9 * max(sv_plat[0], 1e-12):
        raise ParameterError('platform_points', 'the %s are collinear'
                             % ('three vertices' if len(plat) == 3 else 'six joints'))
    # The base points must span a plane; six points on one line leave the
    # platform free to rotate about that line.
    centred = base - base.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    if sv[1] < 1e-9 * max(sv[0], 1e-12):
        raise ParameterError('base_points', 'all six base points are collinear')
