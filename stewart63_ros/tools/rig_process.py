"""The processes of one rig (``Rig``): each node spawned with the rig's
parameter file and its overlay, started in order, watched, and stopped on
every way out (the bridge before the plant whose drives answer its safe
stop). ``rig`` is the command that runs one.
"""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

# Light imports only: rig imports this module before main's first line installs
# the stop handlers (rig.py says why).
from stewart63_ros.core.plumbing.node_names import NODES
from stewart63_ros.paths import RIG_CLOCK_MODE
from stewart63_ros.runtime.forkserver import ForkedProcess, ForkServer, server_for
from stewart63_ros.runtime.launcher import signals_deferred
from stewart63_ros.tools.cli import ros_namespace

#: Bound on the nodes' start-up until the recorder has matched them [s]. It
#: includes loading the numba kernels, which a fresh install (or a changed
#: core) compiles first: more than a minute on a loaded two-core machine.
START_TIMEOUT = 180.0
MODULES = {'plant': 'stewart63_ros.nodes.plant', 'controller': 'stewart63_ros.nodes.controller',
           'fk': 'stewart63_ros.nodes.fk_node', 'record': 'stewart63_ros.tools.record',
           'composed': 'stewart63_ros.nodes.composed', 'view': 'stewart63_ros.tools.view',
           'supervisor': 'stewart63_ros.nodes.supervisor',
           'canopen_bridge': 'stewart63_ros.nodes.canopen_bridge'}


def default_log_dir(record=None, namespace='') -> Path:
    """Where the nodes' logs go without --log-dir: beside the bag (``DIR.logs``)
    with --record DIR, else one reused folder per namespace under ROS_HOME
    (default ~/.ros): ``stewart63/rig_logs/<namespace or default>``."""
    if record:
        record = Path(record)
        return record.with_name(record.name + '.logs')
    home = Path(os.environ.get('ROS_HOME') or Path.home() / '.ros')
    name = (namespace or '').strip('/').replace('/', '_') or 'default'
    return home / 'stewart63' / 'rig_logs' / name


class Rig:
    """The processes of one rig; ``start()``, ``wait()``, ``stop()``."""

    def __init__(self, params, mode=RIG_CLOCK_MODE, duration=None, record=None, namespace='',
                 log_dir=None, extra_params=None, nodes=NODES, realtime_priority=0,
                 compose=False, supervisor=False, bus=None, fork_server=None):
        self.params = str(params)
        #: ``rig --supervisor``: the supervisor between controller and plant
        self.supervisor = bool(supervisor)
        self.mode = mode
        self.duration = duration
        self.record = record
        self.namespace = ros_namespace(namespace or '')     # ValueError: not a ROS namespace
        self.log_dir = Path(log_dir or default_log_dir(record, namespace))
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.summary_file = self.log_dir / 'plant_summary.json'
        self.summary_file.unlink(missing_ok=True)    # a reused folder: not last run's
        self.extra_params = dict(extra_params or {})
        self.nodes = tuple(nodes)
        #: SCHED_FIFO priority for the plant and the controller (fk one
        #: below), 0: normal scheduling. See RigNode.
        self.realtime_priority = int(realtime_priority)
        #: One process (``composed``) hosts the nodes and the recorder.
        self.compose = bool(compose)
        #: 'canopen': the plant on the field bus, and canopen_bridge (docs/bus.md)
        self.bus = bus
        self.procs: dict[str, subprocess.Popen | ForkedProcess] = {}
        #: where the processes are forked from (``start()`` starts one if
        #: None: runtime/forkserver.py); ``rig`` starts it before its checks
        self.fork_server: ForkServer | None = fork_server
        #: the plant's own parameter file (the machine), read after ``params``
        self.plant_params = None

    def overlay(self) -> Path:
        """A second parameter file with what the rig decides; it comes after the
        user's file, so it wins over the user's node sections (a ``-p`` does not)."""
        # lazy: rclpy costs 302 ms; --help answers without it
        from stewart63_ros.runtime.handshake import plant_startup_parameters
        # Who waits for whom before the first sample: runtime/handshake.py.
        shared = {'clock_mode': self.mode, 'wait_for_subscribers': 1 if self.record else 0}
        plant = dict(shared, summary_file=str(self.summary_file),
                     **plant_startup_parameters(self.nodes, bool(self.record), self.mode,
                                                self.compose))
        if self.duration:
            plant['duration'] = float(self.duration)
        doc = {'/**': {'ros__parameters': shared}, '/**/plant': {'ros__parameters': plant}}
        if self.realtime_priority:
            # fk one below: it shares the middleware's shared-memory ports
            # with the loop, and a preempted holder of a port lock would
            # stall the plant (measured: 3 ms publishes with fk left out).
            plant['realtime_priority'] = self.realtime_priority
            doc['/**/controller'] = {'ros__parameters': dict(
                shared, realtime_priority=self.realtime_priority)}
            doc['/**/fk'] = {'ros__parameters': dict(
                shared, realtime_priority=max(1, self.realtime_priority - 1))}
        for node in ('controller', 'fk'):
            if node in self.nodes:
                section = doc.setdefault('/**/%s' % node, {'ros__parameters': dict(shared)})
                section['ros__parameters']['summary_file'] = str(
                    self.log_dir / ('%s_summary.json' % node))
        if self.supervisor:
            supervised(doc, plant, shared, self.log_dir)
        if self.bus:
            self.bus_overlay(doc, shared)
        # One rate: the bridge's SYNCs and the supervisor's sample count (its
        # trip samples, its force-rate check) follow the plant's sensor_rate
        # where the files give it the plant only (main() refuses two).
        plant_rate = sample_rates(self.params, self.plant_params)['plant']
        if plant_rate is not None:
            for node in rate_followers(self.bus, self.supervisor):
                doc['/**/%s' % node]['ros__parameters']['sensor_rate'] = plant_rate
        for node, values in self.extra_params.items():
            section = doc.setdefault('/**/%s' % node, {'ros__parameters': dict(shared)})
            section['ros__parameters'].update(values)
        path = self.log_dir / 'rig_params.yaml'
        import yaml  # lazy: yaml costs 76 ms; --help answers without it
        # Whole or not at all: a node forked just before may be reading it
        part = path.with_name(path.name + '.part')
        part.write_text(yaml.safe_dump(doc, sort_keys=False))
        os.replace(part, path)
        return path

    def bus_overlay(self, doc, shared) -> None:
        """--bus canopen: the plant on the bus; the bridge publishes the samples,
        so the plant's start-up waits (handshake.py) become the bridge's, and
        with --supervisor its answer to every sample, the stale forces' fail
        safe, and the homing's zero (the drives' home offsets). The buses of
        the local hub get channels of this rig's own."""
        plant = doc['/**/plant']['ros__parameters']
        bridge = dict(shared, summary_file=str(self.log_dir / 'canopen_bridge_summary.json'))
        for key in ('lengths_subscribers', 'lengths_peers', 'lockstep_peers', 'duration',
                    'answer_every_sample', 'force_stale_ms'):
            if key in plant:
                bridge[key] = plant[key] if key == 'duration' else plant.pop(key)
        if self.supervisor:
            doc['/**/supervisor']['ros__parameters']['homed_offset_node'] = 'canopen_bridge'
        plant['io'] = 'canopen'
        # lazy: core.plumbing.params costs 715 ms (numba); --help answers without it
        from stewart63_ros.core.machine.bus import load_bus_config
        from stewart63_ros.core.plumbing.params import file_parameters
        config_file = file_parameters(self.params).get('bus_config') or None
        buses = load_bus_config(config_file).buses
        if all(bus.interface == 's63hub' for bus in buses):
            channels = ['rig%d-%s' % (os.getpid(), bus.name) for bus in buses]
            plant['bus_channels'], bridge['bus_channels'] = channels, list(channels)
        doc['/**/canopen_bridge'] = {'ros__parameters': bridge}

    def ros_args(self, name):
        own = ['--params-file', str(self.plant_params)] if (
            name == 'plant' and self.plant_params) else []
        args = ['--ros-args', '--params-file', self.params] + own + [
            '--params-file', str(self.overlay())]
        if self.supervisor and name in ('controller', 'composed'):
            # lazy: the node costs 1050 ms; --help answers without it
            from stewart63_ros.nodes.supervisor import REQUEST_TOPIC
            # composed: the controller's alone (a rule naming the node)
            args += ['-r', '%s%s:=%s' % ('controller:' if name == 'composed' else '',
                                         'leg_forces', REQUEST_TOPIC)]
        if self.namespace:
            args += ['-r', '__ns:=%s' % self.namespace]
        return args

    def spawn(self, name, argv):
        log_path = self.log_dir / ('%s.log' % name)
        # Own process group: a Ctrl-C in the terminal reaches only the rig,
        # which then stops each child itself, in order. A stop signal during
        # the start is acted on once the child is known (and so stopped too).
        with signals_deferred():
            proc = None
            if self.fork_server is not None:    # a fork: its own session too
                proc = self.fork_server.spawn_or_say(MODULES[name], argv, log_path)
                if proc is None:        # the server failed, and said why
                    self.fork_server = None
            if proc is None:
                with open(log_path, 'w') as log:
                    proc = subprocess.Popen([sys.executable, '-m', MODULES[name]] + argv,
                                            stdout=log, stderr=subprocess.STDOUT,
                                            start_new_session=True)
            self.procs[name] = proc
        return proc

    def start(self):
        """Recorder first; then controller and fk; the plant once they are
        matched (the order and its reasons: runtime/handshake.py). The
        processes are forks of one that has loaded the core (runtime/forkserver.py)."""
        if self.fork_server is None:
            self.fork_server = server_for(str(self.log_dir / 'forkserver'))
        if self.compose:
            argv = ['--nodes', ','.join(self.composed_nodes())]
            if self.record:
                argv += ['--record', str(self.record)]
            self.spawn('composed', argv + self.ros_args('composed'))
            if self.bus and 'plant' in self.nodes:      # the machine: its own process
                self.spawn('plant', self.ros_args('plant'))
            return
        # lazy: rclpy costs 302 ms; --help answers without it
        from stewart63_ros.runtime.handshake import MATCHED_LINE, READY_LINE, recorder_waits_for
        downstream = [n for n in self.nodes if n != 'plant']
        wanted = recorder_waits_for(self.nodes)
        if self.record:
            argv = [str(self.record)]
            if wanted:
                argv += ['--wait-for-publishers'] + wanted + [
                    '--wait-timeout', '%g' % START_TIMEOUT]
            if self.namespace:
                argv += ['--namespace', self.namespace]
            self.spawn('record', argv)
            self.wait_for_line('record', READY_LINE, 30)
        if self.supervisor:         # first: the controller's barrier then sees it
            self.spawn('supervisor', self.ros_args('supervisor'))
        for name in downstream:
            self.spawn(name, self.ros_args(name))
        if self.record and wanted:
            self.wait_for_line('record', MATCHED_LINE, START_TIMEOUT + 10)
        if self.bus and 'plant' in self.nodes:
            self.spawn('canopen_bridge', self.ros_args('canopen_bridge'))
        if 'plant' in self.nodes:
            self.spawn('plant', self.ros_args('plant'))

    def composed_nodes(self) -> list[str]:
        """The nodes ``composed`` hosts with --compose: the rig's, the
        supervisor with --supervisor, and with --bus the bridge in place of
        the plant (which stands in for the drives: the machine, its own process)."""
        names = [n for n in self.nodes if not (self.bus and n == 'plant')]
        if self.supervisor:
            names.insert(names.index('controller'), 'supervisor')
        if self.bus:
            names.append('canopen_bridge')
        return names

    def wait_for_line(self, name, line, timeout):
        log = self.log_dir / ('%s.log' % name)
        deadline = time.monotonic() + timeout
        while True:
            try:
                if line in log.read_text().split():
                    return
            except OSError:
                pass
            for other, other_proc in self.procs.items():   # a node that died starting
                if other_proc.poll() is not None:
                    raise RuntimeError('%s exited (%d): %s' % (other, other_proc.returncode,
                                                                self.log_tail(other)))
            if time.monotonic() > deadline:
                raise RuntimeError('%s did not print %s within %g s' % (name, line, timeout))
            time.sleep(0.02)

    def start_view(self, port: int, timeout: float = 60.0) -> str:
        """Start ``view`` on this rig; its URL once it serves."""
        argv = ['--port', str(port), '--params', self.params]
        if self.namespace:
            argv += ['--namespace', self.namespace]
        proc = self.spawn('view', argv)
        log = self.log_dir / 'view.log'
        deadline = time.monotonic() + timeout
        while True:
            try:
                for line in log.read_text().splitlines():
                    if line.startswith('view: http'):
                        return line.split()[1]
            except OSError:
                pass
            if proc.poll() is not None:
                raise RuntimeError('view exited (%d): %s' % (proc.returncode,
                                                             self.log_tail('view')))
            if time.monotonic() > deadline:
                raise RuntimeError('view did not start within %g s' % timeout)
            time.sleep(0.05)

    def log_tail(self, name, lines=5):
        try:
            return ' | '.join((self.log_dir / ('%s.log' % name)).read_text().splitlines()[-lines:])
        except OSError:
            return ''

    def failed(self):
        """Names of nodes that exited with an error."""
        return [n for n, p in self.procs.items() if p.poll() not in (None, 0)]

    def wait(self, timeout=None) -> bool:
        """Until the plant ends its run (True), a node dies, or ``timeout`` (False)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        runner = self.runner()
        plant = self.procs.get(runner)
        while True:
            if self.failed():
                return False
            if plant is not None and plant.poll() == 0:
                return True
            if any(p.poll() is not None for n, p in self.procs.items()
                   if n not in self.ending_with_run()):
                return False
            if deadline is not None and time.monotonic() > deadline:
                return False
            time.sleep(POLL)    # the stop begins at most this late after the run's end

    #: s: the longest ``supervisor_fail_safe`` waits (lockstep: each sample
    #: without an answer waits the plant's force_timeout, 1 s by default)
    FAIL_SAFE_WAIT = 120.0
    FAIL_SAFE_LINE = 'zero force from sample'

    def supervisor_fail_safe(self) -> str:
        """After the supervisor died (a SIGKILL, a crash) while the plant (or
        the bridge, for the drives) runs: wait, bounded, until that node's
        fail safe acts (``force_stale_ms``: its log's "zero force from
        sample N"), so the stop that follows does not hide it. Returns that
        line ('' : nothing to wait for, or it did not come)."""
        dead = self.procs.get('supervisor')
        holder = self.procs.get('canopen_bridge' if self.bus else self.runner())
        if not self.supervisor or dead is None or dead.poll() in (None, 0) or holder is None:
            return ''
        name = 'canopen_bridge' if self.bus else self.runner()
        print('rig: the supervisor ended (%s) during the run: waiting (at most %g s) for the '
              '%s\'s fail safe (force_stale_ms) before stopping' % (
                  dead.returncode, self.FAIL_SAFE_WAIT, name), flush=True)
        # A loaded run may have failed safe before (a late supervisor): only
        # a stretch that began about when it died counts (the rig sees a death
        # within its 0.2 s poll; realtime acts 50 ms after, lockstep later).
        since = time.time() - 0.5
        deadline = time.monotonic() + self.FAIL_SAFE_WAIT
        while holder.poll() is None and time.monotonic() < deadline:
            try:
                lines = (self.log_dir / ('%s.log' % name)).read_text().splitlines()
            except OSError:
                lines = []
            for line in reversed(lines):    # '[ERROR] [<unix time>] [plant]: <text>'
                stamp = re.match(r'\[\w+\] \[([0-9.]+)\] \[[^]]*\]: (.*)', line)
                if stamp and self.FAIL_SAFE_LINE in line and float(stamp.group(1)) >= since:
                    return '%s: %s' % (name, stamp.group(2))
            time.sleep(0.05)
        return ''

    def runner(self) -> str:
        """The process whose end is the end of the run (the plant's)."""
        return 'composed' if self.compose and not self.bus else 'plant'

    def ending_with_run(self) -> set[str]:
        """The processes that end by themselves at the end of the run: the
        runner, and with --bus the bridge's (it counts the samples too, and
        may end a moment before the plant: with exit 0, not a failure)."""
        ending = {self.runner()}
        if self.bus and self.duration:
            ending.add('composed' if self.compose else 'canopen_bridge')
        return ending

    def stop(self, grace=4.0):
        """SIGINT the nodes (the recorder last, so it gets their final messages).

        Returns each process's exit code; a process that ended by the SIGINT
        sent here (one still importing, before its handler is in place) has
        stopped as asked: 0.
        """
        interrupted = set()
        # --bus: the bridge (alone or composed) before the plant, whose drives
        # answer its safe stop before they go (plant_bus.py, PlantBus.close)
        order = [n for n in ('composed', 'canopen_bridge', 'plant', 'controller', 'supervisor',
                             'fk', 'view')
                 if n in self.procs] + (
            ['record'] if 'record' in self.procs else [])
        # The nodes together, then the recorder; each group on one deadline,
        # so stopping takes at most grace + 1.5 s a group, however many hang.
        for group in ([n for n in order if n != 'record'], ['record']):
            procs = [self.procs[n] for n in group if n in self.procs]
            for name, proc in zip(group, procs):
                if proc.poll() is None:
                    proc.send_signal(signal.SIGINT)
                    interrupted.add(name)
            # A node exits by itself STOP_DEADLINE after the signal, with its
            # stacks (launcher.arm_stop_deadline): grace outlasts that.
            for escalate, timeout in ((None, grace), (_dump_stacks, 0.5),
                                      (lambda proc: proc.terminate(), 1.0),
                                      (lambda proc: proc.kill(), None)):
                for proc in procs:
                    if escalate is not None and proc.poll() is None:
                        escalate(proc)
                _wait_all(procs, timeout)
        if self.fork_server is not None and not self.fork_server.shared:
            self.fork_server.close()
        return {n: 0 if n in interrupted and p.returncode == -signal.SIGINT else p.returncode
                for n, p in self.procs.items()}

    def summary(self, node='plant'):
        """The summary JSON a node wrote when it ended (None if it wrote none)."""
        path = self.summary_file if node == 'plant' else self.log_dir / ('%s_summary.json' % node)
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError):
            return None


def _dump_stacks(proc) -> None:
    """Ask a process that ignored SIGINT for its Python stacks (in its log;
    see launcher.dump_stacks_on_sigusr1) before it is terminated."""
    proc.send_signal(signal.SIGUSR1)


#: s: how often rig looks whether its processes have ended (Popen.wait's own
#: back-off sleeps up to 50 ms, a sixth of the stop's budget)
POLL = 0.005


def _wait_all(procs, timeout):
    """Wait for every process until one common deadline (None: for ever)."""
    deadline = None if timeout is None else time.monotonic() + timeout
    while any(proc.poll() is None for proc in procs):
        if deadline is not None and time.monotonic() >= deadline:
            return
        time.sleep(POLL)


def supervised(doc: dict, plant: dict, shared: dict, log_dir: Path) -> None:
    """``rig --supervisor``'s part of the overlay (docs/supervisor.md): the
    plant waits for the supervisor as for the controller, waits for its answer
    to every sample (a sample with a missing reading too), and applies zero
    force once its newest answers a sample older than ``stale_forces_ms``
    (the supervisor's default: the plant fails safe when the supervisor dies)."""
    # lazy: numpy costs 50 ms; --help answers without it
    from stewart63_ros.core.plumbing.node_parameters import default
    plant['lengths_subscribers'] += 1
    plant['lengths_peers'] = plant['lengths_peers'] + ['supervisor']
    plant['answer_every_sample'] = True
    plant.setdefault('force_stale_ms', default('stale_forces_ms'))
    doc['/**/supervisor'] = {'ros__parameters': dict(
        shared, summary_file=str(log_dir / 'supervisor_summary.json'))}


def rate_followers(bus, supervisor) -> list[str]:
    """The nodes of a rig that count the plant's samples at its rate: the
    bridge (``--bus``: the plant steps one period a SYNC) and the supervisor."""
    return [node for node, on in (('canopen_bridge', bus), ('supervisor', supervisor)) if on]


def sample_rates(params, plant_params=None) -> dict:
    """The ``sensor_rate`` [Hz] the parameter files give each node that has
    one in a rig (the plant's after its ``plant_params``); None where the
    files set none."""
    # lazy: core.plumbing.params costs 715 ms (numba); --help answers without it
    from stewart63_ros.core.plumbing.params import read_parameter_file
    plant = read_parameter_file(params, 'plant', allow_empty=True)
    if plant_params:
        plant.update(read_parameter_file(plant_params, 'plant', allow_empty=True))
    rates = {'plant': plant.get('sensor_rate')}
    for node in ('canopen_bridge', 'supervisor'):
        rates[node] = read_parameter_file(params, node, allow_empty=True).get('sensor_rate')
    return rates
