"""Start a rig's processes from one that has loaded the core once: a fork server.

Every node process imports numpy, scipy and numba, imports the core and
loads its numba kernels: about 1 s of CPU each, the most of a rig's
start-up (docs/design.md, "Start-up"), paid three to six times on two cores.
``rig`` starts this server first; it loads that once, and each node is a
fork of it that imports only what is left (rclpy, the messages, its node).

Only the ROS-free core is loaded before a fork: loading rclpy's libraries
starts threads (LTTng's listeners), a fork copies none of a process's threads
but keeps their locks, and a child could then wait on a lock forever. The
server checks that rclpy is not loaded before every fork and refuses to
fork if it is.

The protocol, one JSON object a line: ``rig`` writes ``{"module", "args",
"log", "cwd", "env"}`` on the server's stdin and reads ``{"pid"}`` (or
``{"error"}``) back on its stdout, and later ``{"exit": pid, "code"}`` when
the server has reaped that child (``code`` as ``Popen.returncode``: minus the
signal's number for a child a signal ended). The server ends once its stdin
is closed and its last child has ended. ``ForkServer`` is ``rig``'s side;
``ForkedProcess`` has the ``Popen`` methods ``rig`` uses.

    python -m stewart63_ros.runtime.forkserver [LABEL]

(``LABEL``, ignored, says whose server it is in ``ps``: ``rig`` gives its log folder.)
"""
from __future__ import annotations

import atexit
import gc
import importlib
import json
import os
import select
import signal
import subprocess
import sys
import threading
import time
import traceback

from setproctitle import setproctitle

#: The core modules the nodes import (test/test_forkserver.py checks that
#: these cover every node's), and numba's compiler made ready by loading one
#: kernel: the rest of a node's kernels then load in about 10 ms each.
PRELOAD = ('stewart63_ros.core.controllers.simulate', 'stewart63_ros.core.controllers.sensor',
           'stewart63_ros.core.controllers.tracking',
           'stewart63_ros.core.controllers.reference_files',
           'stewart63_ros.core.mechanics.fk_tracking', 'stewart63_ros.core.mechanics.assembly',
           'stewart63_ros.core.mechanics.markers', 'stewart63_ros.core.machine.supervisor',
           'stewart63_ros.core.machine.bus', 'stewart63_ros.core.plumbing.node_parameters',
           'stewart63_ros.core.plumbing.params', 'stewart63_ros.core.plumbing.stamps',
           'stewart63_ros.core.precompile')
WARM_KERNEL = ('stewart63_ros.core.mechanics.dynamics', 'lengths_rates')
#: Set to 0 to start every process with ``python -m`` instead (rig_process.py).
ENV_SWITCH = 'STEWART63_FORK_SERVER'
#: the server's own file descriptors, closed in each child
_SERVER_FDS: list[int] = []


def fork_server_wanted() -> bool:
    """Whether ``rig`` starts its processes as forks (``STEWART63_FORK_SERVER``
    unset or 1) or with ``python -m`` each (0)."""
    value = os.environ.get(ENV_SWITCH, '1')
    if value not in ('0', '1'):
        raise ValueError('%s must be 0 or 1, not %r' % (ENV_SWITCH, value))
    return value == '1'


#: After ``share_servers()``: the one server ``server_for`` gives (see there).
_SHARED: dict = {'on': False, 'server': None}


def share_servers() -> None:
    """Every later ``server_for`` of this process gives one server, which
    ends with the process: a process that starts many rigs (the tests, a
    bench) loads the core once, not once a rig."""
    _SHARED['on'] = True


def server_for(label: str) -> ForkServer | None:
    """The server a rig forks its processes from: None with
    ``STEWART63_FORK_SERVER=0``; after ``share_servers()`` the process's one
    (started with the first rig); else a new one, labelled ``label``, that
    the rig closes when it stops."""
    if not fork_server_wanted():
        return None
    if not _SHARED['on']:
        return ForkServer(label)
    shared = _SHARED['server']
    if shared is None or shared.proc.poll() is not None:
        shared = _SHARED['server'] = ForkServer('shared by %d' % os.getpid())
        shared.shared = True
    return shared


def preload() -> None:
    """Import ``PRELOAD`` and load ``WARM_KERNEL`` from numba's cache (a cold
    cache loads nothing: the nodes then compile, as they would alone)."""
    for name in PRELOAD:
        importlib.import_module(name)
    module, name = WARM_KERNEL
    dispatcher = getattr(importlib.import_module(module), name)
    for key in dispatcher._cache._cache_file._load_index():
        dispatcher.compile(key[0])      # key[0]: the signature it was cached under
        break


def _exit_code(code) -> int:
    """``sys.exit(code)``'s status, as the interpreter makes it."""
    if code is None:
        return 0
    if isinstance(code, int):
        return code
    print(code, file=sys.stderr)
    return 1


def run_child(request: dict) -> None:
    """In the forked child: become ``python -m module args`` with its output
    in ``log``, then exit as that interpreter would. Never returns."""
    code = 1
    try:
        os.setsid()     # its own process group: a Ctrl-C reaches only the rig
        # The signal handlers of a fresh interpreter.
        signal.set_wakeup_fd(-1)
        for sig in (signal.SIGTERM, signal.SIGCHLD, signal.SIGUSR1, signal.SIGHUP):
            signal.signal(sig, signal.SIG_DFL)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGPIPE, signal.SIG_IGN)
        log = os.open(request['log'], os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        null = os.open(os.devnull, os.O_RDONLY)
        os.dup2(null, 0)
        os.dup2(log, 1)
        os.dup2(log, 2)
        os.close(log)
        os.close(null)
        # ps, top and /proc show it as what it is: python -m module args
        # (before the environment changes: setproctitle finds its room there)
        setproctitle(' '.join([sys.executable, '-m', request['module']] + request['args']))
        os.chdir(request['cwd'])
        os.environ.clear()
        os.environ.update(request['env'])
        try:
            module = importlib.import_module(request['module'])
            sys.argv = [module.__file__] + list(request['args'])
            # ``python -m``: each module ends in ``main()`` or ``sys.exit(main())``
            code = _exit_code(module.main())
        except SystemExit as exc:
            code = _exit_code(exc.code)
        except KeyboardInterrupt:
            # As the interpreter ends on one (a stop while it still imports,
            # too): its traceback, then killed by SIGINT.
            traceback.print_exc()
            _finish()
            signal.signal(signal.SIGINT, signal.SIG_DFL)
            os.kill(os.getpid(), signal.SIGINT)
        except BaseException:  # noqa: BLE001 - the interpreter's own last resort
            traceback.print_exc()
            code = 1
        _finish()
    except BaseException:  # noqa: BLE001 - a child must never return into the server
        traceback.print_exc()
    os._exit(code)


def _finish() -> None:
    """What the interpreter does at its end: join threads, run atexit, flush."""
    try:
        threading._shutdown()
        atexit._run_exitfuncs()
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass


def serve() -> int:
    """The server's loop: fork on each request, report each child's end."""
    reply = os.fdopen(os.dup(1), 'w', buffering=1)
    os.dup2(2, 1)               # its own prints go to its log, not into the protocol
    try:
        preload()
    except Exception as exc:  # noqa: BLE001 - said to rig, which starts its nodes without it
        traceback.print_exc()
        reply.write(json.dumps({'error': 'loading the core failed: %s: %s'
                                % (type(exc).__name__, exc)}) + '\n')
        return 1
    # Out of the cyclic collector's sight: a child's collections then never
    # write to these objects (their pages stay shared, no copy-on-write fault
    # in a child's loop) nor spend time on them (the nodes do the same with
    # their own objects once their loop starts: runtime/hotloop.py).
    gc.freeze()
    # A child's end wakes the loop: SIGCHLD writes to this pipe.
    wake_read, wake_write = os.pipe()
    _SERVER_FDS.extend((wake_read, wake_write))
    os.set_blocking(wake_write, False)
    signal.set_wakeup_fd(wake_write)
    signal.signal(signal.SIGCHLD, lambda signum, frame: None)
    signal.signal(signal.SIGINT, signal.SIG_IGN)     # rig ends it by closing stdin
    children, pending, open_input = set(), b'', True
    reply.write(json.dumps({'ready': os.getpid()}) + '\n')
    while open_input or children:
        ready, _, _ = select.select([0, wake_read] if open_input else [wake_read], [], [], 1.0)
        if wake_read in ready:
            os.read(wake_read, 512)
        while children:
            pid, status = os.waitpid(-1, os.WNOHANG)
            if pid == 0:
                break
            children.discard(pid)
            reply.write(json.dumps({'exit': pid, 'code': os.waitstatus_to_exitcode(status)})
                        + '\n')
        if open_input and 0 in ready:
            chunk = os.read(0, 65536)
            open_input = bool(chunk)
            pending += chunk
            while b'\n' in pending:
                line, pending = pending.split(b'\n', 1)
                pid = fork(json.loads(line), reply)
                if pid:
                    children.add(pid)
    return 0


def fork(request: dict, reply) -> int | None:
    """Fork one child for ``request``; its pid (None: refused, said on ``reply``)."""
    if 'rclpy' in sys.modules:
        reply.write(json.dumps({'error': 'rclpy is loaded in the fork server'}) + '\n')
        return None
    sys.stdout.flush()
    sys.stderr.flush()
    pid = os.fork()
    if pid == 0:
        reply.close()
        for fd in _SERVER_FDS:
            os.close(fd)
        run_child(request)
    reply.write(json.dumps({'pid': pid}) + '\n')
    return pid


class ForkServer:
    """``rig``'s side: start the server, ask it for processes."""

    def __init__(self, label: str = ''):
        """``label``: on the server's command line only, for ``ps`` (whose it is)."""
        # Its own session: a Ctrl-C reaches only the rig, which ends the
        # server by closing its stdin. Its errors come back as replies.
        self.proc = subprocess.Popen([sys.executable, '-m', __name__] + ([label] if label else []),
                                     stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                     start_new_session=True)
        os.set_blocking(self.proc.stdout.fileno(), False)
        self.pending = b''
        self.codes: dict[int, int] = {}
        self.replies: list[dict] = []
        self.ready = False
        self.spawned = 0
        #: the process's one server (``server_for`` after ``share_servers``)
        self.shared = False

    def _read(self, timeout: float) -> bool:
        """Take in what the server has said, waiting at most ``timeout``;
        False once it has ended."""
        fd = self.proc.stdout.fileno()
        ready, _, _ = select.select([fd], [], [], max(0.0, timeout))
        if not ready:
            return True
        chunk = os.read(fd, 65536)
        if not chunk:
            return False
        self.pending += chunk
        while b'\n' in self.pending:
            line, self.pending = self.pending.split(b'\n', 1)
            message = json.loads(line)
            if 'exit' in message:
                self.codes[message['exit']] = message['code']
            elif 'ready' in message:
                self.ready = True
            else:
                self.replies.append(message)
        return True

    def _until(self, done, timeout: float, what: str):
        deadline = time.monotonic() + timeout
        while not done():
            if self.replies and 'error' in self.replies[0] and not self.ready:
                raise RuntimeError(self.replies[0]['error'])
            left = deadline - time.monotonic()
            if left <= 0:
                raise RuntimeError('no %s within %g s' % (what, timeout))
            if not self._read(min(left, 0.1)) and not done():
                raise RuntimeError('it ended (exit %s)' % self.proc.poll())

    def spawn(self, module: str, args: list[str], log_path, timeout: float = 180.0):
        """Start ``python -m module args`` as a fork, output in ``log_path``."""
        self._until(lambda: self.ready, timeout, 'ready')
        open(log_path, 'w').close()     # there (and empty) once the child is, as with Popen
        request = {'module': module, 'args': [str(a) for a in args], 'log': str(log_path),
                   'cwd': os.getcwd(), 'env': dict(os.environ)}
        self.proc.stdin.write((json.dumps(request) + '\n').encode())
        self.proc.stdin.flush()
        self._until(lambda: self.replies, 10.0, 'answer')
        message = self.replies.pop(0)
        if 'pid' not in message:
            raise RuntimeError(message.get('error'))
        self.spawned += 1
        return ForkedProcess(self, message['pid'], [module] + list(args))

    def spawn_or_say(self, module: str, args: list[str], log_path):
        """``spawn``; None if the server failed, said on stderr, and the
        server closed (and no longer shared): the caller starts the process
        with ``python -m`` instead."""
        try:
            return self.spawn(module, args, log_path)
        except RuntimeError as exc:
            print('rig: the fork server failed (%s): each process starts with python -m'
                  % exc, file=sys.stderr, flush=True)
            self.close()
            if _SHARED['server'] is self:
                _SHARED['server'] = None
            return None

    def __del__(self):
        if getattr(self, 'proc', None) is not None:
            try:
                self.close()
            except Exception:  # noqa: BLE001,S110 - the interpreter may be shutting down
                pass

    def close(self) -> None:
        """No more processes: the server ends once its children have (at
        once if it has none: one still loading is ended here)."""
        if self.proc.stdin and not self.proc.stdin.closed:
            try:
                self.proc.stdin.close()
            except OSError:
                pass
        if not self.spawned and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


class ForkedProcess:
    """A child of the fork server, as ``rig`` uses a ``subprocess.Popen``."""

    def __init__(self, server: ForkServer, pid: int, args: list[str]):
        self.server, self.pid, self.args = server, pid, args
        self.returncode = None

    def poll(self):
        if self.returncode is None:
            server = self.server
            alive = server._read(0.0)
            if self.pid in server.codes:
                self.returncode = server.codes.pop(self.pid)
            elif not alive and not os.path.exists('/proc/%d' % self.pid):
                self.returncode = 255       # the server died before it could say
        return self.returncode

    def wait(self, timeout=None):
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.poll() is None:
            left = 0.05 if deadline is None else min(0.05, deadline - time.monotonic())
            if left <= 0:
                raise subprocess.TimeoutExpired(self.args, timeout)
            self.server._read(left)
        return self.returncode

    def send_signal(self, sig) -> None:
        if self.poll() is None:
            os.kill(self.pid, sig)

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)


if __name__ == '__main__':
    sys.exit(serve())
