"""Helpers for tests that talk DDS, in this process and in child processes.

Rules they enforce (see the project's testing notes):
- every test gets its own ROS domain id, held by a lock file for as long as the
  test runs, so tests running at the same time on one machine (other checkouts,
  other developers) never see each other's topics;
- discovery stays on this host (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``);
- every child process runs in its own process group, with stdout and stderr
  going to files, and is stopped (SIGINT, then SIGTERM, then SIGKILL, each
  with a bounded wait) when the test ends, whatever happened;
- every wait is bounded; nothing assumes that a message arrives.

Use in a test module::

    from ros_harness import wait_for, wait_matched   # the `ros` fixture comes from conftest.py

    def test_x(ros):
        proc = ros.spawn([sys.executable, '-m', 'stewart63_ros.tools.record', str(bag)])
        assert ros.wait_line(proc, 'READY', timeout=20)
        node = ros.node('probe')
        sub = node.create_subscription(JointState, 'leg_lengths', got.append, 10)
        assert wait_matched(sub, 1, timeout=10)
        assert ros.spin_until(lambda: len(got) >= 5, timeout=5)

``python test/ros_harness.py`` runs nothing; the module has no side effects on import
other than making sure discovery stays local for this process.
"""
from __future__ import annotations

import contextlib
import fcntl
import itertools
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PYTHON = sys.executable

#: Usable domain ids (ROS 2 on Linux: 0..101 map to valid ports; 0 is everybody's default).
DOMAIN_RANGE = range(1, 101)
_LOCK_DIR = Path(tempfile.gettempdir()) / 'stewart63_ros_domains'
_counter = itertools.count()

# This process's own participant must stay local too.
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.pop('ROS_LOCALHOST_ONLY', None)   # deprecated since Jazzy; warns if set


class DomainLease:
    """A domain id held through a lock file until :meth:`release` (or exit)."""

    def __init__(self, domain_id: int, fd: int):
        self.domain_id = domain_id
        self._fd = fd

    def release(self):
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __int__(self):
        return self.domain_id

    def __repr__(self):
        return f'DomainLease({self.domain_id})'


def lease_domain_id() -> DomainLease:
    """A domain id no other live process on this machine holds (flock-based).

    Starts from a pid-based offset so parallel runs rarely contend; raises if all
    ids are taken.
    """
    _LOCK_DIR.mkdir(parents=True, exist_ok=True)
    ids = list(DOMAIN_RANGE)
    start = (os.getpid() * 7 + next(_counter) * 13) % len(ids)
    for k in range(len(ids)):
        domain_id = ids[(start + k) % len(ids)]
        fd = os.open(_LOCK_DIR / f'{domain_id}.lock', os.O_CREAT | os.O_RDWR, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            continue
        return DomainLease(domain_id, fd)
    raise RuntimeError('no free ROS domain id on this machine')


def unique_domain_id() -> int:
    """A leased domain id, held until this process exits."""
    lease = lease_domain_id()
    _leaked.append(lease)
    return lease.domain_id


_leaked: list[DomainLease] = []


def child_env(domain_id: int, extra: dict | None = None, *, other_venv: bool = False) -> dict:
    """Environment for a child process on ``domain_id``.

    Keeps the wheels bootstrapper's LD_LIBRARY_PATH for children of this venv
    (they would recompute the same); ``other_venv=True`` drops it so a child in
    another venv bootstraps itself.
    """
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(int(domain_id))
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env.pop('ROS_LOCALHOST_ONLY', None)
    env.pop('ROS_STATIC_PEERS', None)
    env['PYTHONUNBUFFERED'] = '1'
    if other_venv:
        env.pop('_ROS_WHEELS_BOOTSTRAP_COMPLETE', None)
        env.pop('LD_LIBRARY_PATH', None)
    if extra:
        env.update({k: str(v) for k, v in extra.items()})
    return env


class Proc:
    """A child process in its own process group, with its output in files."""

    def __init__(self, popen: subprocess.Popen, name: str, stdout: Path, stderr: Path,
                 dumps_stacks: bool = False):
        self.popen = popen
        #: one of the package's executables: SIGUSR1 prints its Python stacks
        self.dumps_stacks = dumps_stacks
        self.name = name
        self.stdout_path = stdout
        self.stderr_path = stderr

    @property
    def pid(self):
        return self.popen.pid

    @property
    def returncode(self):
        return self.popen.poll()

    def stdout(self) -> str:
        return self.stdout_path.read_text(errors='replace')

    def stderr(self) -> str:
        return self.stderr_path.read_text(errors='replace')

    def wait(self, timeout: float) -> int | None:
        """Exit code, or None if still running after ``timeout`` s."""
        try:
            return self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            return None

    def describe(self) -> str:
        return (f'[{self.name} pid {self.pid} rc {self.returncode}]\n'
                f'--- stdout ---\n{self.stdout()[-3000:]}\n'
                f'--- stderr ---\n{self.stderr()[-3000:]}')


def spawn(cmd, env: dict, log_dir, name: str | None = None, cwd=None) -> Proc:
    """Start ``cmd`` in a new session (own process group); stdout/stderr to files
    in ``log_dir``; stdin from /dev/null."""
    log_dir = Path(log_dir)
    log_dir.mkdir(parents=True, exist_ok=True)
    name = name or Path(str(cmd[0])).name
    tag = f'{name}-{next(_counter)}'
    out, err = log_dir / f'{tag}.out', log_dir / f'{tag}.err'
    with open(out, 'wb') as fo, open(err, 'wb') as fe:
        popen = subprocess.Popen([str(c) for c in cmd], env=env, cwd=cwd or REPO,
                                 stdin=subprocess.DEVNULL, stdout=fo, stderr=fe,
                                 start_new_session=True)
    ours = any(Path(str(c)).name in PACKAGE_EXECUTABLES or str(c).startswith('stewart63_ros.')
               for c in cmd)
    return Proc(popen, name, out, err, dumps_stacks=ours)


#: console scripts that print their stacks on SIGUSR1 (launcher.dump_stacks_on_sigusr1)
PACKAGE_EXECUTABLES = {'plant', 'controller', 'fk', 'composed', 'record', 'rig', 'view'}


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _signal_group(pgid: int, sig) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(pgid, sig)


def stop(proc: Proc, sigint_wait: float = 8.0, sigterm_wait: float = 4.0,
         sigkill_wait: float = 4.0) -> int | None:
    """Stop ``proc`` and everything in its process group: SIGINT, then SIGTERM,
    then SIGKILL, each followed by a bounded wait. Returns the leader's exit code
    (negative: killed by that signal)."""
    pgid = proc.popen.pid   # start_new_session: the group id is the leader's pid
    for sig, wait in ((signal.SIGINT, sigint_wait), (signal.SIGTERM, sigterm_wait),
                      (signal.SIGKILL, sigkill_wait)):
        if proc.popen.poll() is not None and not _group_alive(pgid):
            break
        if sig == signal.SIGTERM and proc.dumps_stacks and proc.popen.poll() is None:
            # It ignored SIGINT: where it hangs goes to its stderr first.
            _signal_group(pgid, signal.SIGUSR1)
            time.sleep(0.5)
        _signal_group(pgid, sig)
        deadline = time.monotonic() + wait
        while time.monotonic() < deadline:
            if proc.popen.poll() is not None and not _group_alive(pgid):
                break
            time.sleep(0.02)
    with contextlib.suppress(subprocess.TimeoutExpired):
        proc.popen.wait(0.5)
    return proc.popen.poll()


def wait_line(proc: Proc, text: str, timeout: float, stream: str = 'stdout') -> bool:
    """Wait (bounded) until a line of ``proc``'s stdout (or stderr) equals or
    starts with ``text``; False on timeout or if the process exited without it."""
    path = proc.stdout_path if stream == 'stdout' else proc.stderr_path
    deadline = time.monotonic() + timeout
    while True:
        lines = path.read_text(errors='replace').splitlines()
        if any(line.strip() == text or line.startswith(text) for line in lines):
            return True
        if proc.popen.poll() is not None or time.monotonic() >= deadline:
            lines = path.read_text(errors='replace').splitlines()
            return any(line.strip() == text or line.startswith(text) for line in lines)
        time.sleep(0.02)


def wait_until(predicate, timeout: float, period: float = 0.01) -> bool:
    """Poll ``predicate`` (no spinning) until true or ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while True:
        if predicate():
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(period)


def wait_matched(entity, count: int = 1, timeout: float = 10.0) -> bool:
    """Wait until a publisher has ``count`` matched subscriptions, or a
    subscription ``count`` matched publishers (bounded). Matching happens in
    the middleware's threads: no spinning needed."""
    if hasattr(entity, 'get_subscription_count'):
        getter = entity.get_subscription_count
    else:
        getter = entity.get_publisher_count
    return wait_until(lambda: getter() >= count, timeout)


def wait_for(predicate, timeout: float, executor=None, node=None, period: float = 0.01) -> bool:
    """Spin ``executor`` (or a temporary one for ``node``) until ``predicate()``
    is true or ``timeout`` s have passed."""
    own = None
    if executor is None and node is not None:
        from rclpy.executors import SingleThreadedExecutor
        own = executor = SingleThreadedExecutor(context=node.context)
        executor.add_node(node)
    try:
        deadline = time.monotonic() + timeout
        while True:
            if predicate():
                return True
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            if executor is not None:
                executor.spin_once(timeout_sec=min(period, remaining))
            else:
                time.sleep(min(period, remaining))
    finally:
        if own is not None:
            own.remove_node(node)
            own.shutdown(timeout_sec=1.0)


class RosContext:
    """An rclpy context on one domain, with nodes and an executor, for use in a test.

    ``rclpy.init(domain_id=...)`` works with the Kilted wheels (checked by
    test_bags), so this does not depend on ``ROS_DOMAIN_ID`` in the environment.
    """

    def __init__(self, domain_id: int):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        self.domain_id = int(domain_id)
        from stewart63_ros.middleware import use_rig_profile
        use_rig_profile()
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=self.domain_id)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.nodes = []

    def node(self, name: str, namespace: str | None = None, **kwargs):
        from rclpy.node import Node
        node = Node(name, namespace=namespace, context=self.context, **kwargs)
        self.nodes.append(node)
        self.executor.add_node(node)
        return node

    def spin_until(self, predicate, timeout: float, period: float = 0.01) -> bool:
        return wait_for(predicate, timeout, executor=self.executor, period=period)

    def spin_for(self, seconds: float):
        self.spin_until(lambda: False, seconds)

    def close(self):
        with contextlib.suppress(Exception):
            self.executor.shutdown(timeout_sec=1.0)
        for node in self.nodes:
            with contextlib.suppress(Exception):
                node.destroy_node()
        self.nodes = []
        with contextlib.suppress(Exception):
            self.context.try_shutdown()


@contextlib.contextmanager
def ros_context(domain_id: int):
    """``with ros_context(d) as rc: node = rc.node('probe')`` — always shut down."""
    rc = RosContext(domain_id)
    try:
        yield rc
    finally:
        rc.close()


class RosTest:
    """What the ``ros`` fixture gives a test: a private domain, child processes
    that are always stopped, and an in-process rclpy context on demand."""

    def __init__(self, lease: DomainLease, log_dir: Path):
        self.lease = lease
        self.domain_id = lease.domain_id
        self.log_dir = Path(log_dir)
        self.procs: list[Proc] = []
        self._rc: RosContext | None = None

    def env(self, extra: dict | None = None, **kwargs) -> dict:
        return child_env(self.domain_id, extra, **kwargs)

    def spawn(self, cmd, env: dict | None = None, name: str | None = None, **kwargs) -> Proc:
        """Start ``cmd`` on this test's domain; stopped at teardown at the latest."""
        proc = spawn(cmd, env if env is not None else self.env(), self.log_dir, name, **kwargs)
        self.procs.append(proc)
        return proc

    def python(self, *args, env: dict | None = None, name: str | None = None) -> Proc:
        """Start ``python args...`` with this venv's interpreter."""
        return self.spawn([PYTHON, *args], env=env, name=name)

    def stop(self, proc: Proc, **kwargs) -> int | None:
        return stop(proc, **kwargs)

    wait_line = staticmethod(wait_line)

    @property
    def rc(self) -> RosContext:
        if self._rc is None:
            self._rc = RosContext(self.domain_id)
        return self._rc

    def node(self, name: str, namespace: str | None = None, **kwargs):
        return self.rc.node(name, namespace, **kwargs)

    def spin_until(self, predicate, timeout: float) -> bool:
        return self.rc.spin_until(predicate, timeout)

    def cleanup(self):
        errors = []
        for proc in reversed(self.procs):
            try:
                stop(proc)
            except Exception as exc:  # noqa: BLE001 - keep going: stop the others
                errors.append(exc)
        if self._rc is not None:
            self._rc.close()
            self._rc = None
        # Processes killed by the test (or by stop) leave their segments.
        clean_dead_shm_segments()
        self.lease.release()
        if errors:
            raise errors[0]


def rig_env(ros, monkeypatch) -> None:
    """This process's environment for a ``Rig`` made in-process on the test's
    domain (its children inherit it): loopback discovery, unbuffered logs."""
    monkeypatch.setenv('ROS_DOMAIN_ID', str(ros.domain_id))
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    monkeypatch.delenv('ROS_LOCALHOST_ONLY', raising=False)
    monkeypatch.setenv('PYTHONUNBUFFERED', '1')


def logs_of(log_dir, tail: int = 3000) -> str:
    """The last ``tail`` characters of every log in ``log_dir``, for a failure message."""
    return '\n'.join('--- %s ---\n%s' % (p.name, p.read_text(errors='replace')[-tail:])
                     for p in sorted(Path(log_dir).glob('*.log')))


def run_to_end(rig, timeout: float) -> tuple[bool, dict, str]:
    """Start ``rig`` (a tools.rig_process.Rig), wait for the end of its run (bounded),
    always stop it: (whether it ran to its end, exit codes, its logs)."""
    ok = False
    try:
        rig.start()
        ok = rig.wait(timeout=timeout)
    finally:
        codes = rig.stop()
    return ok, codes, logs_of(rig.log_dir)


SHM_DIR = Path('/dev/shm')


def clean_dead_shm_segments(shm_dir: Path = SHM_DIR) -> int:
    """Remove the shared-memory files Fast DDS left behind for processes
    that are gone (killed ones cannot clean up): a segment or port whose
    ``_el`` lock file nobody holds any more. Fast DDS keeps that lock (an
    ``flock``) for as long as the owner lives, so a live rig's files are
    never touched. Returns how many files were removed."""
    import fcntl
    removed = 0
    for lock in sorted(shm_dir.glob('fastdds_*_el')):
        base = lock.with_name(lock.name[:-len('_el')])
        try:
            fd = os.open(lock, os.O_RDWR)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            continue        # held: its owner lives
        else:
            # (a port's named semaphore too: a process killed while it held
            # it would block the next one that opens the port)
            for path in (base, base.with_name(base.name + '_sl'),
                         base.with_name('sem.%s_mutex' % base.name), lock):
                with contextlib.suppress(FileNotFoundError):
                    path.unlink()
                    removed += 1
        finally:
            os.close(fd)
    return removed


@pytest.fixture
def ros(tmp_path):
    """A private ROS domain for one test; every process it spawns is stopped after."""
    lease = lease_domain_id()
    rt = RosTest(lease, tmp_path / 'logs')
    try:
        yield rt
    finally:
        rt.cleanup()
