"""What the command lines share: loading a parameter file, naming its unknown keys,
ending quietly when the reader of the output goes away."""
from __future__ import annotations

import sys

from stewart63_ros.exits import CLOSED_PIPE_STATUS, quiet_on_closed_pipe  # noqa: F401 - for the tools

# Nothing heavy at import: every executable, the nodes and `record` (whose stop
# handlers come before rclpy loads) import this module first.

STRICT_HELP = ('refuse (exit 2) a parameter file with a key no executable reads, instead '
               'of a warning')


def load_checked(prog: str, path=None, node_name=None, strict=False):
    """The validated setup of ``path`` (default: the packaged file; its
    ``mechanism``, ``gains``, ``task``, ``settings``), or
    None after a one-line error on stderr (the caller exits 2). Every key no
    executable reads is named first: a warning, an error with ``strict``."""
    # lazy: core.plumbing.params costs 715 ms (numba); plot, record import cli
    from stewart63_ros.core.plumbing.params import (
        ParameterError,
        default_params_path,
        file_parameters,
        load_setup,
        unknown_keys,
    )
    path = str(path or default_params_path())
    try:
        problems = unknown_keys(file_parameters(path))
    except Exception:  # noqa: BLE001 - unreadable or not YAML: load_setup says how
        problems = []
    for problem in problems:
        print('%s: %s: %s: %s' % (prog, 'error' if strict else 'warning', path, problem),
              file=sys.stderr)
    try:
        setup = load_setup(path, node_name=node_name)
    except ParameterError as exc:
        print('%s: parameter error: %s: %s' % (prog, path, exc), file=sys.stderr)
        return None
    if strict and problems:
        print('%s: parameter error: %s: unknown keys refused (--strict)' % (prog, path),
              file=sys.stderr)
        return None
    return setup


def add_control_options(parser) -> None:
    """``--control continuous|sampled`` and ``--rate HZ``, as `sim` and `sweep` take them."""
    parser.add_argument('--control', choices=('continuous', 'sampled'), default=None,
                        help='PD inside the ODE (RK45, as the paper) or sampled and held, as '
                        'the rig (default: continuous; sampled with faults)')
    parser.add_argument('--rate', type=float, default=None,
                        help="sample rate [Hz]: the control rate when sampled (default: the "
                        "plant's sensor_rate), the output rate when continuous (default "
                        "100, the paper's h)")


def announce_compile(prog: str, who: str = '') -> None:
    """One line on stderr when the numba kernels are about to be compiled
    (a cold cache): otherwise a minute of silence."""
    # lazy: core.precompile costs 128 ms; every tool imports cli
    from stewart63_ros.core.precompile import COMPILE_NOTICE, kernel_cache_cold
    if kernel_cache_cold():
        print('%s: %s%s' % (prog, who, COMPILE_NOTICE), file=sys.stderr, flush=True)


def ros_namespace(text: str) -> str:
    """A rig's namespace as typed (``--namespace``): absolute as ROS names it
    (``rig2`` is ``/rig2``; ``''`` and ``/`` are the root namespace, returned
    as ``''``).

    Raises:
        ValueError: a name ROS refuses, with rcl's reason in one line.
    """
    if text in ('', '/'):
        return ''
    name = text if text.startswith('/') else '/' + text
    # lazy: rclpy costs 302 ms; every tool imports cli, --ns needs it
    from rclpy.exceptions import InvalidNamespaceException
    from rclpy.validate_namespace import validate_namespace
    try:
        validate_namespace(name)
    except InvalidNamespaceException as exc:
        reason = str(exc).splitlines()[0].partition(': ')[2].rstrip(':')
        raise ValueError('%r is not a ROS namespace: %s' % (text, reason)) from None
    return name
