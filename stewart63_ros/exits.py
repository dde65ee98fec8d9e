"""How every executable ends when nobody reads its output any more
(``analyze modes | head -3``): quietly, exit status 141, no traceback. A
leaf beside the core (standard library only), so nodes and tools both use it."""
from __future__ import annotations

import functools
import os
import select
import sys
from collections.abc import Callable

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
    console script of setup.py goes through it (test/test_closed_pipe.py)."""
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
