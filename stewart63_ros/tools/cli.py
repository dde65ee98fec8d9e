"""What the command lines share: loading a parameter file, naming its unknown keys,
ending quietly when the reader of the output goes away."""
from __future__ import annotations

import functools
import os
import select
import sys
from collections.abc import Callable

# Nothing heavy at import: every executable, the nodes and `record` (whose stop
# handlers come before rclpy loads) import this module first.

STRICT_HELP = ('refuse (exit 2) a parameter file with a key no executable reads, instead '
               'of a warning')


def load_checked(prog: str, path=None, node_name=None, strict=False):
    """The validated mechanism of ``path`` (default: the packaged file), or
    None after a one-line error on stderr (the caller exits 2). Every key no
    executable reads is named first: a warning, an error with ``strict``."""
    from stewart63_ros.core.params import (
        ParameterError,
        default_params_path,
        file_parameters,
        load_mechanism,
        unknown_keys,
    )
    path = str(path or default_params_path())
    try:
        problems = unknown_keys(file_parameters(path))
    except Exception:  # noqa: BLE001 - unreadable or not YAML: load_mechanism says how
        problems = []
    for problem in problems:
        print('%s: %s: %s: %s' % (prog, 'error' if strict else 'warning', path, problem),
              file=sys.stderr)
    try:
        mech = load_mechanism(path, node_name=node_name)
    except ParameterError as exc:
        print('%s: parameter error: %s: %s' % (prog, path, exc), file=sys.stderr)
        return None
    if strict and problems:
        print('%s: parameter error: %s: unknown keys refused (--strict)' % (prog, path),
              file=sys.stderr)
        return None
    return mech


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
    from stewart63_ros.core.precompile import COMPILE_NOTICE, kernel_cache_cold
    if kernel_cache_cold():
        print('%s: %s%s' % (prog, who, COMPILE_NOTICE), file=sys.stderr, flush=True)


#: Exit status after the output pipe closed (128 + SIGPIPE, as a C tool killed by it).
CLOSED_PIPE_STATUS = 141


def _stdout_closed() -> bool:
    """True when nobody reads standard output any more (a pipe whose reader exited)."""
    try:
        fd = sys.stdout.fileno()
        poller = select.poll()
        poller.register(fd, select.POLLOUT)
        return any(event & select.POLLERR for _, event in poller.poll(0))
    except (AttributeError, OSError, ValueError):
        return False


def quiet_on_closed_pipe(main: Callable) -> Callable:
    """Wrap an executable's ``main`` so that it ends quietly (exit status 141, no
    traceback) when its output pipe closes: ``analyze modes | head -3``. Every
    console script of setup.py goes through it (test/test_tools_cli.py)."""
    @functools.wraps(main)
    def guarded(*args, **kwargs):
        try:
            try:
                return main(*args, **kwargs)
            finally:
                sys.stdout.flush()  # here, not at exit, where a failure is printed
        except BrokenPipeError:
            if not _stdout_closed():
                raise               # some other pipe: not ours to hide
            # Python flushes stdout again at exit: point it at /dev/null first.
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            os.close(devnull)
            return CLOSED_PIPE_STATUS
    guarded.quiet_on_closed_pipe = True
    return guarded
