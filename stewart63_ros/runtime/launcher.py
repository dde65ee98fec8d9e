"""Starting and stopping a process of the rig: options, rclpy, stop signals, exit codes."""
from __future__ import annotations

import argparse
import contextlib
import ctypes
import faulthandler
import os
import signal
import sys
import time

from stewart63_ros.core.plumbing.errors import ParameterError
from stewart63_ros.middleware import use_rig_profile
from stewart63_ros.runtime.realtime import reduce_timer_slack


def make_parser(prog: str, description: str) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=prog, description=description,
        epilog='ROS arguments follow --ros-args, e.g. --ros-args --params-file '
        'config/stewart63.yaml -r __ns:=/rig2 -p name:=value (docs/interface.md).')
    return parser


class StopSignals:
    """SIGINT and SIGTERM: the first one asks for a stop, every later one is only noted.

    The one stop-signal handler of every process of the rig: the nodes
    (``STOP`` below), ``rig``, ``record``, ``play`` and ``view``. A
    terminal's Ctrl-C under ``ros2 launch`` reaches a process twice (from
    the terminal's process group and forwarded by launch), then comes
    launch's SIGTERM: a second KeyboardInterrupt inside ``close()`` would cut
    the flush to the recorder short and end the process with a traceback.

    What differs between the processes is chosen here:

    - ``on_stop``: called on every signal, so it must be safe to call again
      and from a signal handler (``Recorder.request_stop``, ``Event.set``):
      for a tool whose loop waits for its own stop request.
    - ``deadline``: the first signal starts the stop deadline
      (``arm_stop_deadline``). For a process that only stops itself (a node,
      ``record``); not for ``rig``, whose stop of its children takes longer
      by design, nor for ``play``, which a test may run in its own process.
    - ``interrupt``: the first signal raises KeyboardInterrupt wherever the
      main thread waits (a node's start-up, compiling kernels, waiting for
      peers), once. ``rig`` turns it on with ``interrupt_from_now()`` once
      its options are read; ``record``, ``play`` and ``view`` never raise,
      their loops stop through ``on_stop``. A node's hot loop sets
      ``interruptible`` False and checks ``requested`` once per message
      instead: interrupted between publishing a message and counting it, a
      node would report one message fewer than the recorder got.

    ``restore()`` puts back the handlers ``install()`` replaced: for a tool's
    ``main`` that a test or a script may call in its own process (``play``).
    """

    def __init__(self, on_stop=None, *, deadline=True, interrupt=True):
        self.on_stop = on_stop
        self.deadline = deadline
        self.received = []      # the signals' names, in order
        self.requested = False
        self.interruptible = True
        self.armed = interrupt  # False once raised, or once closing: nothing to interrupt
        self.previous = {}

    def install(self):
        for sig in (signal.SIGINT, signal.SIGTERM):
            self.previous[sig] = signal.signal(sig, self)
        return self

    def restore(self) -> None:
        """Put back the handlers ``install`` replaced."""
        for sig, handler in self.previous.items():
            signal.signal(sig, handler)
        self.previous = {}

    def interrupt_from_now(self) -> None:
        """From here the first stop signal raises KeyboardInterrupt; one that
        came before raises it now (``rig`` then starts nothing)."""
        self.armed = True
        if self.requested:
            self.armed = False
            raise KeyboardInterrupt

    def __call__(self, signum, frame):
        self.received.append(signal.Signals(signum).name)
        if not self.requested and self.deadline:
            arm_stop_deadline()
        self.requested = True
        if self.on_stop is not None:
            self.on_stop()
        if self.armed and self.interruptible:
            self.armed = False
            raise KeyboardInterrupt


#: This process's stop signals when it runs a node (one per process, like the handlers).
STOP = StopSignals(deadline=True, interrupt=True)


def _first_line(exc) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def run(prog: str, description: str, node_class, argv=None, extra_args=None) -> int:
    """Parse --help / own options, start rclpy, run the node until shutdown.

    Exits 2 with a one-line message on a parameter error; SIGTERM and Ctrl-C
    stop the node cleanly.
    """
    argv = list(sys.argv if argv is None else argv)
    parser = make_parser(prog, description)
    if extra_args:
        extra_args(parser)
    # lazy: runtime.parameters costs 2102 ms (numba); record, rig import this
    from stewart63_ros.runtime.parameters import check_params_files, ros_arguments, set_arguments
    set_arguments(argv)
    try:
        # rcl would end in a traceback on a missing file or a bad -p.
        check_params_files(argv)
        ros_arguments(argv)
    except ParameterError as exc:
        print('%s: parameter error: %s' % (prog, exc), file=sys.stderr)
        return 2
    use_rig_profile()       # before rclpy makes the participant
    import rclpy  # lazy: rclpy costs 302 ms: --help and bad options answer without it
    from rclpy.utilities import remove_ros_args
    try:
        own_args = remove_ros_args(argv)[1:]
    except Exception as exc:  # noqa: BLE001 - rcl's refusal of the ROS arguments
        print('%s: error: bad ROS arguments: %s' % (prog, _first_line(exc)), file=sys.stderr)
        return 2
    options = parser.parse_args(own_args)
    # lazy: rclpy costs 302 ms: --help and bad options answer without it
    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions
    reduce_timer_slack()
    # Our own handlers: Ctrl-C and SIGTERM raise KeyboardInterrupt, so the
    # node flushes its last messages to the recorder before rclpy shuts down.
    try:
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as exc:  # noqa: BLE001 - rcl's refusal of the ROS arguments
        print('%s: error: bad ROS arguments: %s' % (prog, _first_line(exc)), file=sys.stderr)
        return 2
    # SIGTERM (from rig, systemd, docker, launch) ends the node like Ctrl-C does.
    signals = STOP.install()
    dump_stacks_on_sigusr1()
    node = None
    code = 0
    try:
        node = node_class(options)
        code = node.run() or 0
    except ParameterError as exc:
        print('%s: parameter error: %s' % (prog, exc), file=sys.stderr)
        code = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        code = 0
    finally:
        signals.armed = False
        if node is not None:
            started = time.monotonic()
            try:
                node.close()
            except Exception as exc:  # noqa: BLE001 - shutting down anyway: say why, go on
                print('%s: while closing: %s' % (prog, exc), file=sys.stderr)
            # In the node's log, so that a slow stop shows where it went.
            flushed = getattr(node, 'flushed', '')
            print('%s: stopped (exit %d, close took %.2f s%s%s)'
                  % (prog, code, time.monotonic() - started,
                     ', flush: %s' % flushed if flushed else '',
                     ', signals: %s' % ' '.join(signals.received) if signals.received else ''),
                  flush=True)
            # Its run and its flush have decided its exit code: a teardown
            # stuck in the middleware (eProsima/Fast-DDS#6502) must not turn
            # that into a failed run. (A flush that timed out exits 0 with a
            # working teardown too: its log says so.)
            exit_natively_after(TEARDOWN_BOUND, code)
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
        ignore_stop_signals()
    # Also after a constructor that refused its parameters: the half-made
    # node's middleware objects, collected by the interpreter's finalization
    # after rclpy's shutdown, ended a refusal (exit 2) by SIGSEGV once here.
    end_process(code)       # (never returns)


def end_process(code: int) -> None:
    """Exit now with ``code``, past the interpreter's finalization: a node
    that has closed (its summary written, its messages flushed, the
    middleware shut down) has nothing left to do, and unloading numba's
    LLVM and the middleware's libraries took a fifth of a second per
    process, the larger part of a rig's stop. An exception on its way out
    never gets here: it ends the process with its traceback."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)


#: s from the end of a node's flush (its messages delivered) to its exit with
#: its own code, whatever the teardown does (``exit_natively_after``). The
#: teardown took 8.9 ms median, 219 ms at most over 459 processes here.
TEARDOWN_BOUND = 1.0


class _Sigval(ctypes.Union):
    _fields_ = [('sival_int', ctypes.c_int), ('sival_ptr', ctypes.c_void_p)]


class _Sigevent(ctypes.Structure):
    """glibc's ``struct sigevent`` (64 bytes), as SIGEV_THREAD uses it."""
    _fields_ = [('sigev_value', _Sigval), ('sigev_signo', ctypes.c_int),
                ('sigev_notify', ctypes.c_int), ('sigev_notify_function', ctypes.c_void_p),
                ('sigev_notify_attributes', ctypes.c_void_p), ('_pad', ctypes.c_char * 32)]


class _Itimerspec(ctypes.Structure):
    _fields_ = [('interval_s', ctypes.c_long), ('interval_ns', ctypes.c_long),
                ('value_s', ctypes.c_long), ('value_ns', ctypes.c_long)]


_SIGEV_THREAD, _CLOCK_MONOTONIC = 2, 1
_exit_timers = []       # kept alive with the process


def exit_natively_after(seconds: float, code: int) -> bool:
    """In ``seconds``, end this process with exit status ``code`` (``_exit``:
    no clean-up), unless it has ended by then.

    A POSIX timer whose expiry calls libc's ``_exit(code)`` in a thread of
    its own: it needs neither the GIL nor the interpreter, so it fires while
    the main thread is stuck in the middleware holding the GIL (the Fast DDS
    teardown deadlock, eProsima/Fast-DDS#6502, where no Python watchdog
    runs; faulthandler's deadline fires too but can only exit 1). Returns
    False where the platform has no such timer (the stop deadline then
    remains the bound)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        create, settime = libc.timer_create, libc.timer_settime
        exit_address = ctypes.cast(libc._exit, ctypes.c_void_p).value
    except (OSError, AttributeError):
        return False
    event = _Sigevent()
    event.sigev_notify = _SIGEV_THREAD
    event.sigev_value.sival_int = int(code)
    # The thread calls _exit(sigev_value): a union passed by value in the
    # first integer register, whose low 32 bits are the int code.
    event.sigev_notify_function = exit_address
    timer = ctypes.c_void_p()
    if create(_CLOCK_MONOTONIC, ctypes.byref(event), ctypes.byref(timer)) != 0:
        return False
    whole, part = divmod(max(float(seconds), 1e-3), 1.0)
    spec = _Itimerspec(0, 0, int(whole), int(part * 1e9))
    if settime(timer, 0, ctypes.byref(spec), None) != 0:
        return False
    _exit_timers.append((event, timer))
    return True


#: s from the first stop signal to a forced exit: a node flushes to its
#: recorder for at most RigNode.FLUSH_ON_SIGNAL, and stopping must stay well
#: inside a launcher's 5 s before it escalates.
STOP_DEADLINE = 3.5


def arm_stop_deadline(seconds: float = STOP_DEADLINE) -> None:
    """A process still running ``seconds`` after its first stop signal prints
    every thread's Python stack and exits with code 1 (``faulthandler``'s own
    watchdog thread: it fires even while the main thread is stuck inside the
    middleware, where a Python signal handler never runs). So a stop always
    stops, and a hang says where it was."""
    faulthandler.dump_traceback_later(seconds, exit=True)


@contextlib.contextmanager
def signals_deferred():
    """Inside, SIGINT and SIGTERM are held back and handed to the handlers
    in force once the block ends: a stop that arrives while a child process
    is being started (``Popen``) would otherwise leave that child running,
    unknown to the parent that stops the others."""
    held = []
    sigs = (signal.SIGINT, signal.SIGTERM)
    previous = {sig: signal.signal(sig, lambda signum, frame: held.append(signum))
                for sig in sigs}
    try:
        yield
    finally:
        for sig in sigs:
            signal.signal(sig, previous[sig])
        for signum in held:
            handler = previous[signal.Signals(signum)]
            if callable(handler):
                handler(signum, None)
            elif handler == signal.SIG_DFL and signum == signal.SIGINT:
                raise KeyboardInterrupt


def dump_stacks_on_sigusr1() -> None:
    """``kill -USR1 <pid>`` prints every thread's Python stack to stderr.

    ``rig`` sends it to a process that has not stopped within its grace
    period, before SIGTERM and SIGKILL: the log then shows where it hung.
    """
    faulthandler.register(signal.SIGUSR1, all_threads=True)


def ignore_stop_signals() -> None:
    """From here to the process's end, SIGINT and SIGTERM are ignored.

    Python puts the default handlers back when the interpreter finalizes
    (unloading the middleware takes a moment): a second Ctrl-C or launch's
    SIGTERM arriving then would end a process that has stopped cleanly with
    -2 or -15. An ignored signal stays ignored through finalization.
    """
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
