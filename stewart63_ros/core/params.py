"""The mechanism description: read, validate and freeze the parameter file.

The file is a ROS 2 parameter file (docs/interface.md): shared keys under
``/**: ros__parameters:``, node-specific keys under ``/**/<node>:``. This module
knows no ROS; the nodes and ``sim`` read the same file through it.
"""
from __future__ import annotations

import dataclasses
import difflib
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import yaml

# ParameterError lives in the leaf module errors; importing it from here works too.
from stewart63_ros.core.errors import ParameterError

# The legs' names live in the leaf module legs; importing them from here works too.
from stewart63_ros.core.legs import LEG_NAMES, LEG_VERTEX  # noqa: F401
from stewart63_ros.core.node_parameters import NODE_KEYS
from stewart63_ros.core.node_parameters import read as read_declared
from stewart63_ros.core.rotation import rotation_from_euler
from stewart63_ros.paths import default_params_path


def _section_applies(key: str, node_name: str | None) -> int:
    """0: no; 1: the wildcard section; 2: a section naming this node."""
    key = key.strip()
    if key in ('/**', '**'):
        return 1
    if node_name and (key == node_name or key.rstrip('/').split('/')[-1] == node_name):
        return 2
    return 0


def read_parameter_file(path: str | os.PathLike, node_name: str | None = None,
                        allow_empty: bool = False) -> dict:
    """Flatten a ROS 2 parameter file into {name: value} for one node.

    Wildcard ``/**`` keys first, then the node's own section overrides them.

    Args:
        path: the parameter file.
        node_name: the node whose section (``/**/<node>:`` or ``<node>:``)
            applies; None: the wildcard sections only.
        allow_empty: a file with no section for this node gives {} (a second
            file that only adds another node's keys) instead of an error.

    Returns:
        {key: value} as YAML read it.

    Raises:
        ParameterError: the file cannot be read, is not YAML, or not a ROS 2
            parameter file.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ParameterError('params file', 'cannot read %s (%s)' % (path, exc.strerror)) from None
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ParameterError('params file', '%s is not valid YAML: %s' % (path, exc)) from None
    if not isinstance(doc, dict):
        raise ParameterError('params file', '%s is not a ROS 2 parameter file '
                             '(expected "/**: ros__parameters: ...")' % path)
    merged: dict = {}
    for rank in (1, 2):
        for key, section in doc.items():
            if _section_applies(str(key), node_name) != rank:
                continue
            if not isinstance(section, dict) or 'ros__parameters' not in section:
                raise ParameterError(str(key), 'section has no ros__parameters')
            merged.update(section['ros__parameters'] or {})
    if not merged and not allow_empty:
        raise ParameterError('params file', '%s has no "/**: ros__parameters:" section' % path)
    return merged


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
    """A validated 6-3 platform, its masses, friction, limits, gains and scenario.

    Arrays are read-only. Leg i (0-based) meets vertex ``LEG_VERTEX[i]``.
    """
    base_points: np.ndarray          # (6, 3) b_i, base frame
    platform_points: np.ndarray      # (3, 3) p_k, platform frame
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
    kp: np.ndarray
    kv: np.ndarray
    setpoint_lengths: np.ndarray
    initial_position: np.ndarray
    initial_velocity: np.ndarray
    initial_orientation: np.ndarray
    initial_orientation_rate: np.ndarray
    extra: Mapping[str, Any] = dataclasses.field(default_factory=dict)

    @property
    def leg_platform_points(self) -> np.ndarray:
        """(6, 3): the platform vertex of each leg, platform frame (p_k repeated)."""
        return self.platform_points[LEG_VERTEX]

    def replace(self, **changes: Any) -> Mechanism:
        """A copy with some fields changed, validated again.

        Args:
            **changes: field names and new values (``platform_inertia`` as six
                numbers or the (3, 3) matrix).

        Returns:
            The new mechanism.

        Raises:
            ParameterError: the changed mechanism is not valid.
        """
        params = self.to_params()
        params.update({k: (np.asarray(v).ravel().tolist() if np.ndim(v) else v)
                       for k, v in changes.items()})
        if 'platform_inertia' in changes and np.shape(changes['platform_inertia']) == (3, 3):
            m = np.asarray(changes['platform_inertia'])
            params['platform_inertia'] = [m[0, 0], m[1, 1], m[2, 2], m[0, 1], m[0, 2], m[1, 2]]
        return mechanism_from_params(params)

    def to_params(self) -> dict:
        """The flat parameter dictionary this mechanism was built from.

        Returns:
            {key: value} with lists for arrays, ``extra`` included.
        """
        out = dict(self.extra)
        for field in dataclasses.fields(self):
            if field.name == 'extra':
                continue
            value = getattr(self, field.name)
            if field.name == 'platform_inertia':
                value = [value[0, 0], value[1, 1], value[2, 2],
                         value[0, 1], value[0, 2], value[1, 2]]
            out[field.name] = np.asarray(value).ravel().tolist() if np.ndim(value) else value
        return out


_KNOWN = {f.name for f in dataclasses.fields(Mechanism)} - {'extra'}

def known_keys(params: Mapping[str, Any] | None = None) -> set[str]:
    """Every key some executable reads: the mechanism's and every node's, and
    those of the user's control law that ``params`` names, if any.

    Args:
        params: parameters whose ``control_law`` may name a user's law.

    Returns:
        The set of key names.
    """
    keys = set(_KNOWN).union(*NODE_KEYS.values())
    law = (params or {}).get('control_law')
    if isinstance(law, str) and ':' in law:
        try:
            from stewart63_ros.core.laws import law_class
            keys |= set(getattr(law_class(law), 'parameters', ()) or ())
        except Exception:  # noqa: BLE001 - a law that cannot load is the controller's error
            pass
    return keys


def unknown_keys(params: Mapping[str, Any] | Iterable[str]) -> list[str]:
    """One message per key of ``params`` that no executable reads, with the
    nearest known key when one is close.

    Args:
        params: a mapping of parameters, or just the keys.

    Returns:
        Messages in key order, e.g. "sensor_rat: unknown parameter (did you
        mean sensor_rate?)"; empty when every key is known.
    """
    known = known_keys(params if isinstance(params, Mapping) else None)
    keys = params
    out = []
    for key in keys:
        key = str(key)
        if key in known:
            continue
        close = difflib.get_close_matches(key, sorted(known), n=1, cutoff=0.75)
        out.append('%s: unknown parameter%s' % (
            key, ' (did you mean %s?)' % close[0] if close else ', read by no executable'))
    return out


def file_parameters(path: str | os.PathLike) -> dict:
    """Every key of every ``ros__parameters`` section of a parameter file,
    once each, in file order, with its last value (for a check of the whole
    file).

    Args:
        path: the parameter file (already known to be readable YAML).

    Returns:
        {key: value}.
    """
    doc = yaml.safe_load(Path(path).read_text())
    params: dict = {}
    if isinstance(doc, dict):
        for section in doc.values():
            if isinstance(section, dict) and isinstance(section.get('ros__parameters'), dict):
                params.update(section['ros__parameters'])
    return params


def _missing_hint(key: str, params: Mapping[str, Any]) -> str:
    """For a missing key: the unknown key in ``params`` that looks like it."""
    known = known_keys(params)
    strangers = [str(k) for k in params if str(k) not in known]
    close = difflib.get_close_matches(key, strangers, n=1, cutoff=0.75)
    return ' (the file has the unknown key %s: a typo?)' % close[0] if close else ''


def mechanism_from_params(params: Mapping[str, Any]) -> Mechanism:
    """Validate a flat parameter dictionary; every error names its key.

    A missing key that looks like an unknown key of ``params`` says so
    (``platform_mass: missing (the file has the unknown key platfrom_mass:
    a typo?)``).

    Args:
        params: {key: value}, the mechanism's keys and any others (kept in ``extra``).

    Returns:
        The validated, immutable mechanism.

    Raises:
        ParameterError: a key missing or out of its range (docs/interface.md).
    """
    try:
        return _mechanism_from_params(params)
    except ParameterError as exc:
        if exc.problem == 'missing':
            hint = _missing_hint(exc.key, params)
            if hint:
                raise ParameterError(exc.key, exc.problem + hint) from None
        raise


def _mechanism_from_params(params: Mapping[str, Any]) -> Mechanism:
    base = _vector(params, 'base_points', 18).reshape(6, 3)
    plat = _vector(params, 'platform_points', 9).reshape(3, 3)
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
        kp=_vector(params, 'kp', 6),
        kv=_vector(params, 'kv', 6),
        setpoint_lengths=_vector(params, 'setpoint_lengths', 6),
        initial_position=_vector(params, 'initial_position', 3),
        initial_velocity=_vector(params, 'initial_velocity', 3),
        initial_orientation=_vector(params, 'initial_orientation', 3),
        initial_orientation_rate=_vector(params, 'initial_orientation_rate', 3),
        extra={k: v for k, v in params.items() if k not in _KNOWN},
    )
    for key in ('kp', 'kv'):
        if np.any(getattr(mech, key) < 0):
            raise ParameterError(key, 'gains must be >= 0')
    # The end stops belong to the model the plant integrates (and sim); an
    # infinitely stiff one is allowed (the integrators then report it). The
    # sensors' zero offsets belong to the machine the file describes.
    for key in ('endstop_stiffness', 'endstop_damping', 'leg_length_offset'):
        read_declared(params, key)
    if np.any(mech.setpoint_lengths <= 0):
        raise ParameterError('setpoint_lengths', 'lengths must be > 0')
    if mech.leg_lower_com > lmax or mech.leg_upper_com > lmax:
        raise ParameterError('leg_lower_com' if mech.leg_lower_com > lmax else 'leg_upper_com',
                             'centre of mass lies beyond the longest leg (%g m)' % lmax)
    _check_initial_pose(mech)
    return mech


def _check_geometry(base: np.ndarray, plat: np.ndarray) -> None:
    for i in range(6):
        for j in range(i + 1, 6):
            if np.linalg.norm(base[i] - base[j]) < 1e-6:
                pair = (i // 2 == j // 2)
                raise ParameterError('base_points', '%s b_%d and b_%d coincide'
                                     % ('the pair' if pair else 'points', i + 1, j + 1))
    for i in range(3):
        for j in range(i + 1, 3):
            if np.linalg.norm(plat[i] - plat[j]) < 1e-6:
                raise ParameterError('platform_points', 'p_%d and p_%d coincide' % (i + 1, j + 1))
    normal = np.cross(plat[1] - plat[0], plat[2] - plat[0])
    scale = max(np.linalg.norm(plat[1] - plat[0]), np.linalg.norm(plat[2] - plat[0])) ** 2
    if np.linalg.norm(normal) < 1e-9 * scale:
        raise ParameterError('platform_points', 'the three vertices are collinear')
    # The base points must span a plane; six points on one line leave the
    # platform free to rotate about that line.
    centred = base - base.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    if sv[1] < 1e-9 * max(sv[0], 1e-12):
        raise ParameterError('base_points', 'all six base points are collinear')


def _check_initial_pose(mech: Mechanism) -> None:
    # Imported here, not at the top: kinematics loads numba (about 0.2 s),
    # which a program that only reads a parameter file does not need.
    from stewart63_ros.core.kinematics import leg_lengths
    rot = rotation_from_euler(mech.initial_orientation)
    lengths = leg_lengths(mech, mech.initial_position, rot)
    for key, values in (('initial_position', lengths), ('setpoint_lengths', mech.setpoint_lengths)):
        bad = np.flatnonzero((values < mech.leg_length_min) | (values > mech.leg_length_max))
        if bad.size:
            i = int(bad[0])
            raise ParameterError(
                key, 'leg_%d length %.4f m is outside the stroke [leg_length_min %g, '
                'leg_length_max %g]' % (i + 1, values[i], mech.leg_length_min, mech.leg_length_max))


def load_mechanism(path: str | os.PathLike | None = None, node_name: str | None = None,
                   overrides: Mapping[str, Any] | None = None) -> Mechanism:
    """Read and validate a parameter file (default: the packaged one).

    Args:
        path: the parameter file; None: the packaged ``config/stewart63.yaml``.
        node_name: the node whose section applies, as in ``read_parameter_file``.
        overrides: values that replace the file's.

    Returns:
        The validated mechanism.

    Raises:
        ParameterError: as ``read_parameter_file`` and ``mechanism_from_params``.
    """
    params = read_parameter_file(path if path is not None else default_params_path(), node_name)
    if overrides:
        params.update(overrides)
    return mechanism_from_params(params)
