"""The parameter file: read it, check its keys, and make the ``Setup`` of it
(the machine, gains, task and settings; the types and their checks live in
the leaf modules ``mechanism`` and ``setup``).

The file is a ROS 2 parameter file (docs/interface.md): shared keys under
``/**: ros__parameters:``, node-specific keys under ``/**/<node>:``. This module
knows no ROS; the nodes and ``sim`` read the same file through it.
"""
from __future__ import annotations

import difflib
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import yaml

from stewart63_ros.core.mechanics.mechanism import Mechanism, inertia_matrix  # noqa: F401
from stewart63_ros.core.mechanics.setup import Setup, validated_setup

# ParameterError lives in the leaf module errors; importing it from here works too.
from stewart63_ros.core.plumbing.errors import ParameterError

# The legs' names live in the leaf module legs, the Mechanism and its checks in
# the leaf module mechanism, the Setup in the leaf module setup; importing them
# from here works too.
from stewart63_ros.core.plumbing.legs import LEG_NAMES, LEG_VERTEX  # noqa: F401
from stewart63_ros.core.plumbing.node_parameters import MODEL_BY_NAME, NODE_KEYS
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


def known_keys(params: Mapping[str, Any] | None = None) -> set[str]:
    """Every key some executable reads: the mechanism's and every node's, and
    those of the user's control law that ``params`` names, if any.

    Args:
        params: parameters whose ``control_law`` may name a user's law.

    Returns:
        The set of key names.
    """
    keys = set(MODEL_BY_NAME).union(*NODE_KEYS.values())
    law = (params or {}).get('control_law')
    if isinstance(law, str) and ':' in law:
        try:
            # lazy: laws loads the numba kernels (926 ms), which
            # a program that only reads a parameter file does not need.
            from stewart63_ros.core.controllers.laws import law_class
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


def setup_from_params(params: Mapping[str, Any]) -> Setup:
    """Validate a flat parameter dictionary into its parts; every error names
    its key.

    A missing key that looks like an unknown key of ``params`` says so
    (``platform_mass: missing (the file has the unknown key platfrom_mass:
    a typo?)``).

    Args:
        params: {key: value}, every key a node or ``sim`` reads.

    Returns:
        The validated, immutable setup: ``mechanism``, ``gains``, ``task``,
        ``settings``.

    Raises:
        ParameterError: a key missing or out of its range (docs/interface.md).
    """
    try:
        return validated_setup(params)
    except ParameterError as exc:
        if exc.problem == 'missing':
            hint = _missing_hint(exc.key, params)
            if hint:
                raise ParameterError(exc.key, exc.problem + hint) from None
        raise


def mechanism_from_params(params: Mapping[str, Any]) -> Mechanism:
    """The machine of a flat parameter dictionary, the whole setup checked
    (``setup_from_params``).

    Args:
        params: {key: value}, every key a node or ``sim`` reads.

    Returns:
        The validated, immutable mechanism.

    Raises:
        ParameterError: a key missing or out of its range (docs/interface.md).
    """
    return setup_from_params(params).mechanism


def load_setup(path: str | os.PathLike | None = None, node_name: str | None = None,
               overrides: Mapping[str, Any] | None = None) -> Setup:
    """Read and validate a parameter file (default: the packaged one).

    Args:
        path: the parameter file; None: the packaged ``config/stewart63.yaml``.
        node_name: the node whose section applies, as in ``read_parameter_file``.
        overrides: values that replace the file's.

    Returns:
        The validated setup: ``mechanism``, ``gains``, ``task``, ``settings``.

    Raises:
        ParameterError: as ``read_parameter_file`` and ``setup_from_params``.
    """
    params = read_parameter_file(path if path is not None else default_params_path(), node_name)
    if overrides:
        params.update(overrides)
    return setup_from_params(params)


def load_mechanism(path: str | os.PathLike | None = None, node_name: str | None = None,
                   overrides: Mapping[str, Any] | None = None) -> Mechanism:
    """The machine of a parameter file, the whole file checked (``load_setup``).

    Args:
        path, node_name, overrides: as ``load_setup``.

    Returns:
        The validated mechanism.

    Raises:
        ParameterError: as ``load_setup``.
    """
    return load_setup(path, node_name, overrides).mechanism
