"""A node's parameters as the core's flat dictionary, from its ROS arguments.

The nodes read their parameters the way ``sim`` does, with the precedence a
user expects rather than rcl's (where a file's ``/**/plant:`` entry beats a
``-p`` on the command line):

1. the ``--params-file`` files in the order given, each one's ``/**``
   section, then its section for this node; a later file wins. The files
   given are the whole model: nothing falls back to the packaged file. No
   file given: the packaged ``config/stewart63.yaml``;
2. then every ``-p name:=value`` (value read as YAML, as rcl does).

The result is also what the node declares as its ROS parameters, so
``ros2 param get`` shows what the node runs with. Every key the node reads
(the model's and its own, core/plumbing/node_parameters.py) is declared, given or not
(with its default), with a ``ParameterDescriptor`` made from its one
declaration: ``ros2 param list`` shows every key, ``ros2 param describe`` its
meaning and unit, its range, and ``read_only`` for a key fixed at start-up
(rcl then refuses a ``ros2 param set`` of it). See ``declare_parameters``.
"""
from __future__ import annotations

import dataclasses
import os
import sys

import yaml
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.parameter import Parameter

from stewart63_ros.core.plumbing.node_parameters import (
    NODE_KEYS,
    default,
    describe,
    node_keys,
    ros_value,
)
from stewart63_ros.core.plumbing.params import (
    ParameterError,
    default_params_path,
    read_parameter_file,
)
from stewart63_ros.runtime.ros_args import WITH_VALUE, split_ros_args

_argv: list[str] | None = None


def set_arguments(argv) -> None:
    """The process's command line, as the launcher got it (default: sys.argv)."""
    global _argv
    _argv = list(argv)


@dataclasses.dataclass
class RosArguments:
    params_files: list[str] = dataclasses.field(default_factory=list)
    #: (node name or None for every node, key, value text), in order
    overrides: list[tuple] = dataclasses.field(default_factory=list)
    node_name: str | None = None     # from -r __node:=NAME


def ros_arguments(argv) -> RosArguments:
    """The parameter-related ROS arguments of a command line (what follows
    each ``--ros-args``, up to ``--``). Raises ParameterError for a ``-p``
    without ``:=``."""
    out = RosArguments()
    args = split_ros_args(argv)[1]
    i = 0
    while i < len(args):
        arg = args[i]
        if arg in WITH_VALUE:
            value = args[i + 1] if i + 1 < len(args) else ''
            i += 1
            if arg in ('-p', '--param'):
                name, sep, text = value.partition(':=')
                if not sep or not name:
                    raise ParameterError('-p %s' % value, 'expected -p name:=value')
                node, _, key = name.rpartition(':')
                out.overrides.append((node or None, key, text))
            elif arg == '--params-file':
                out.params_files.append(value)
            elif arg in ('-r', '--remap'):
                target, _, name = value.partition(':=')
                if target.rpartition(':')[2] in ('__node', '__name'):
                    out.node_name = name
        i += 1
    return out


def check_params_files(argv) -> None:
    """Every ``--params-file`` exists and is readable, or ParameterError
    (before rclpy.init, which would end in a traceback)."""
    for path in ros_arguments(argv).params_files:
        if not os.path.isfile(path):
            raise ParameterError('params file', 'cannot read %s (%s)' % (
                path, 'no such file' if not os.path.exists(path) else 'not a file'))
        if not os.access(path, os.R_OK):
            raise ParameterError('params file', 'cannot read %s (permission denied)' % path)


def load_parameters(node_name: str, argv=None) -> tuple[str, dict]:
    """(node name after remapping, {key: value}) as described in the module."""
    argv = list((_argv if _argv is not None else sys.argv) if argv is None else argv)
    args = ros_arguments(argv)
    name = args.node_name or node_name
    params: dict = {}
    files = args.params_files or [str(default_params_path())]
    for i, path in enumerate(files):
        params.update(read_parameter_file(path, name, allow_empty=i > 0))
    for node, key, text in args.overrides:
        if node is not None and node.strip('/').rpartition('/')[2] != name:
            continue
        try:
            params[key] = yaml.safe_load(text) if text else ''
        except yaml.YAMLError:
            raise ParameterError(key, 'cannot read the value %r of -p %s:=%s'
                                 % (text, key, text)) from None
    return name, params


def ros_parameters(params: dict) -> list:
    """rclpy Parameters for ``params`` (values ROS cannot hold are left out:
    the node still uses them, but ``ros2 param`` does not show them)."""
    out = []
    for key, value in params.items():
        if isinstance(value, list) and any(isinstance(v, float) for v in value) and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
            value = [float(v) for v in value]      # [1, 2.5]: a double array
        try:
            out.append(Parameter(str(key), value=value))
        except (TypeError, ValueError):
            continue
    return out


#: core/plumbing/node_parameters.py's type names -> rclpy's parameter types
_TYPES = {'double': 'DOUBLE', 'integer': 'INTEGER', 'bool': 'BOOL', 'string': 'STRING',
          'double_array': 'DOUBLE_ARRAY', 'string_array': 'STRING_ARRAY'}


def descriptor(name: str, node: str, writable: bool = False):
    """The rcl_interfaces ParameterDescriptor of key ``name`` on ``node``
    (core/plumbing/node_parameters.describe: description with unit, range, read-only;
    ``writable``: not read-only whatever the declaration says)."""
    d = describe(name, node)
    out = ParameterDescriptor(name=name, description=d.description,
                              additional_constraints=d.constraints,
                              read_only=d.read_only and not writable,
                              dynamic_typing=d.dynamic_typing)
    if not d.dynamic_typing:
        out.type = getattr(Parameter.Type, _TYPES[d.type]).value
    if d.range is not None and d.type == 'integer':
        out.integer_range = [IntegerRange(from_value=d.range[0], to_value=d.range[1])]
    elif d.range is not None:
        out.floating_point_range = [FloatingPointRange(from_value=d.range[0],
                                                       to_value=d.range[1])]
    return out


def declare_parameters(node, kind: str, params: dict) -> None:
    """Declare the ROS parameters of ``node`` (a 'plant', 'controller' or
    'fk'), after its values passed their checks: every key it reads, with
    its value (given, or the default) and its descriptor; then every other
    key given (a user's law's, an unknown one), as it is, without one.
    The values are ours (this module's precedence), not rcl's.

    rclpy types a declared value by itself (an empty list as bytes), and no
    value goes into a read-only parameter once declared: so a key whose
    value rclpy would type otherwise (``[]``) is declared with its type
    alone, then set to its value, then given its descriptor (read-only too).
    This runs before the node's own set-parameters callback exists.
    """
    keys = node_keys(kind)
    values, fixed = [], []
    for name in keys:
        if name == 'use_sim_time':          # rclpy's own, declared by rclpy
            continue
        value = params.get(name)
        if value is None and name in NODE_KEYS[kind]:
            value = default(name, params)
        if value is None:                   # a model key left out (gravity: the model's default)
            continue
        desc = descriptor(name, kind)
        value = ros_value(name, value, kind)
        try:
            typed = Parameter.Type.from_parameter_value(value).value == desc.type
        except TypeError:
            typed = False
        if desc.dynamic_typing or typed:
            node.declare_parameter(name, value, desc, ignore_override=True)
            continue
        kind_of = Parameter.Type(desc.type)
        node.declare_parameter(name, kind_of, descriptor(name, kind, writable=True),
                               ignore_override=True)
        values.append(Parameter(name, kind_of, value))
        if desc.read_only:
            fixed.append((name, desc))
    for param, result in zip(values, node.set_parameters(values)):
        if not result.successful:           # (the checks passed: a declaration out of step)
            raise ParameterError(param.name, result.reason)
    for name, desc in fixed:
        node.set_descriptor(name, desc)
    for param in ros_parameters(params):
        if param.name not in keys and param.name != 'use_sim_time':
            node.declare_parameter(param.name, param.value, _dynamic(), ignore_override=True)


def _dynamic():
    return ParameterDescriptor(dynamic_typing=True)
