"""`rig`: plant, controller and fk (and `record`) as separate processes over DDS.

    rig [--params FILE] [--mode realtime|lockstep] [--duration S] [--record DIR]
        [--namespace NS] [--nodes plant,controller,fk] [--realtime-priority P]
        [--compose] [--control-law NAME] [--reference CSV] [--fault FAULT]...
        [--supervisor] [--plant-params FILE] [--bus canopen] [--tracking-bound M RAD]

One parameter file and one namespace for all. Every node waits until its
peers are matched before the first sample, so a short run loses nothing at
its start. Ctrl-C or SIGTERM (any number of them) stops every process
cleanly; the exit status is non-zero if a node died or failed (a supervisor
that dies: the rig first waits for the plant's or bridge's fail safe, zero
force after force_stale_ms, says so, then stops; exit 1). With
--duration the run ends after S simulated seconds (the plant stops itself).
A summary is printed either way, for the part that ran. ``--nodes`` runs a
part of the rig (one host's share of a rig split across machines).
With --compose the nodes (and the recorder) run as nodes of one process
(``composed``), still over the DDS topics. --control-law sets the
controller's ``control_law``; --reference hands a reference CSV to the
controller (``reference_file``, time 0 = the first sample) and to the plant,
which reports the true tracking error in its summary; beyond
--tracking-bound the run lost its reference: rig says so and exits 1. --fault (repeatable)
adds a fault to the plant's ``faults`` (docs/faults.md); the summary names
each fault and when it acted. --supervisor puts the supervisor between the
controller and the plant, or the bridge with --bus canopen
(docs/supervisor.md); the summary lists its trips.
--plant-params gives the plant a file of its
own, read after --params (its keys win, for the plant only): the plant then
plays a machine built off the drawing that controller and fk run on
(docs/calibration.md). --bus canopen puts the plant on the field bus
as the legs' CiA 402 drives and starts ``canopen_bridge`` between the bus and
the topics (docs/bus.md).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

# Light imports only up to main's first line, which installs the stop
# handlers: a Ctrl-C while numpy and scipy load (a third of a second) could
# otherwise be swallowed by a library's bare ``except`` and never stop the rig.
from stewart63_ros.core.plumbing.errors import ParameterError
from stewart63_ros.core.plumbing.node_names import NODES
from stewart63_ros.paths import RIG_CLOCK_MODE, default_params_path
from stewart63_ros.runtime.launcher import (
    StopSignals,
    dump_stacks_on_sigusr1,
    ignore_stop_signals,
    signals_deferred,
)
from stewart63_ros.tools.cli import (
    STRICT_HELP,
    announce_compile,
    load_checked,
    quiet_on_closed_pipe,
    ros_namespace,
)

#: Bound on the nodes' start-up until the recorder has matched them [s]. It
#: includes loading the numba kernels, which a fresh install (or a changed
#: core) compiles first: more than a minute on a loaded two-core machine.
START_TIMEOUT = 180.0
#: --tracking-bound's default: position [m], orientation [rad]. A planned
#: calibration on a machine built off its drawing tracks within 2.7 cm (the
#: drawing's error and the law's lag, docs/calibration.md); a platform that
#: changes assembly mode ends 0.2-0.3 m and 1 rad away.
TRACKING_BOUND = (0.05, 0.1)
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
                 compose=False, supervisor=False, bus=None):
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
        self.procs: dict[str, subprocess.Popen] = {}
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
        path.write_text(yaml.safe_dump(doc, sort_keys=False))
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
        log = open(self.log_dir / ('%s.log' % name), 'w')
        # Own process group: a Ctrl-C in the terminal reaches only the rig,
        # which then stops each child itself, in order. A stop signal during
        # the start is acted on once the child is known (and so stopped too).
        with signals_deferred():
            proc = subprocess.Popen([sys.executable, '-m', MODULES[name]] + argv,
                                    stdout=log, stderr=subprocess.STDOUT,
                                    start_new_session=True)
            self.procs[name] = proc
        return proc

    def start(self):
        """Recorder first; then controller and fk; the plant once they are
        matched (the order and its reasons: runtime/handshake.py)."""
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
                                      (subprocess.Popen.terminate, 1.0),
                                      (subprocess.Popen.kill, None)):
                for proc in procs:
                    if escalate is not None and proc.poll() is None:
                        escalate(proc)
                _wait_all(procs, timeout)
        return {n: 0 if n in interrupted and p.returncode == -signal.SIGINT else p.returncode
                for n, p in self.procs.items()}

    def summary(self, node='plant'):
        """The summary JSON a node wrote when it ended (None if it wrote none)."""
        path = self.summary_file if node == 'plant' else self.log_dir / ('%s_summary.json' % node)
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError):
            return None


def print_drives_at_stop(bridge) -> None:
    """What the bridge's safe stop left the drives in (docs/bus.md, "Stopping"):
    one line when every drive confirmed READY TO SWITCH ON, else an ERROR
    naming each drive that did not."""
    states = (bridge or {}).get('drives_at_stop')
    if states is None:
        print('rig: error: the drives were NOT confirmed safe: the bridge wrote no summary '
              'of its safe stop', file=sys.stderr)
        return
    if not states:
        print('  drives: none was up at the bridge\'s stop (NMT pre-operational sent)')
        return
    unsafe = {leg: state for leg, state in states.items() if state != 'READY TO SWITCH ON'}
    if unsafe:
        print('rig: error: the drives were NOT all left safe: %s' % ', '.join(
            '%s: %s' % item for item in unsafe.items()), file=sys.stderr)
    else:
        print('  drives left safe: %s ready to switch on, zero torque, NMT pre-operational'
              % ', '.join(states))


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


def control_params(control_law=None, reference=None) -> dict:
    """Node parameters (for ``Rig(extra_params=...)``) that run ``control_law``
    on the reference CSV ``reference`` (plant: the tracking error in its summary)."""
    extra = {'controller': {}}
    if control_law:
        extra['controller']['control_law'] = str(control_law)
    if reference:
        path = str(Path(reference).resolve())
        extra['controller']['reference_file'] = path
        extra['plant'] = {'reference_file': path}
    return extra


class _DefaultsFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Every option's default in --help; an option without one (None) says in
    its own help what happens when it is left out."""

    def _get_help_string(self, action):
        if action.default is None or action.default is False or action.default == '':
            # said in the help, or a plain flag
            return action.help
        return super()._get_help_string(action)


@quiet_on_closed_pipe
def main(argv=None) -> int:
    # The first SIGINT or SIGTERM stops the rig (KeyboardInterrupt wherever it
    # waits, also in start()); later ones, and any once the rig is stopping
    # its nodes anyway, are only noted: a terminal's Ctrl-C under a launcher
    # arrives twice, then a SIGTERM, and must not cut the stop short. Set
    # first thing: one that comes while the options are read (nothing
    # started yet) is noted, and the rig then starts nothing. Explicitly for
    # SIGINT too: a rig started as a background job of a script inherits
    # SIGINT ignored, and `kill -INT` must stop it all the same. No stop
    # deadline: stopping the children (Rig.stop) may take longer.
    signals = StopSignals(deadline=False, interrupt=False).install()
    dump_stacks_on_sigusr1()
    parser = argparse.ArgumentParser(prog='rig', description=__doc__.split('\n\n')[0],
                                     formatter_class=_DefaultsFormatter)
    parser.add_argument('--params', metavar='FILE',
                        help='parameter file (default: the packaged %s)' % default_params_path())
    parser.add_argument('--mode', choices=('realtime', 'lockstep'), default=RIG_CLOCK_MODE,
                        help='clock mode of the plant')
    parser.add_argument('--duration', type=float, metavar='S',
                        help='simulated seconds, then stop (default: run until Ctrl-C)')
    parser.add_argument('--record', metavar='DIR',
                        help='record every topic into a new bag DIR (default: no recording)')
    parser.add_argument('--namespace', default='', metavar='NS',
                        help='namespace of this rig, e.g. /rig2 (rig2 is taken as /rig2; '
                        'default: the root namespace)')
    parser.add_argument('--log-dir', metavar='DIR',
                        help="where the nodes' logs go (default: DIR.logs beside the bag "
                        'with --record DIR, else $ROS_HOME/stewart63/rig_logs/<namespace>, '
                        '~/.ros without ROS_HOME; reused, overwritten by the next run)')
    parser.add_argument('--compose', action='store_true',
                        help='run the nodes (and the recorder) in one process, each still its '
                        'own node on the DDS topics: many times faster in lockstep, and the '
                        'controller answers in the same wake-up in realtime (docs/running.md: '
                        'when to use which)')
    parser.add_argument('--control-law', metavar='NAME',
                        help="the controller's law: pd (eq. 40), pd_gravity, computed_torque "
                        'or package.module:Class (default: control_law of the file, else pd)')
    parser.add_argument('--reference', metavar='CSV',
                        help='reference motion t,x,y,z,theta_x,theta_y,theta_z to follow from '
                        'the first sample; the summary prints the tracking error')
    parser.add_argument('--tracking-bound', type=float, nargs=2, default=TRACKING_BOUND,
                        metavar=('M', 'RAD'),
                        help='with --reference: a run whose true position error exceeds M or '
                        'whose orientation error exceeds RAD after the first second lost its '
                        'reference: the summary says so and rig exits 1 (0 0: no bound) '
                        '(default: %g %g)' % TRACKING_BOUND)
    parser.add_argument('--nodes', default=','.join(NODES), metavar='LIST',
                        help='the nodes this rig runs, a subset of plant,controller,fk '
                        '(default: all three), e.g. the plant on the platform\'s computer '
                        'and controller,fk on a workstation, with the same parameter file '
                        'and namespace; without the plant the rig runs until Ctrl-C or '
                        'SIGTERM')
    parser.add_argument('--realtime-priority', type=int, default=0, metavar='P',
                        help='run plant and controller SCHED_FIFO at priority P (1-99), fk '
                        'at P-1 (needs root or CAP_SYS_NICE, else a warning): keeps other '
                        'work on the machine from delaying the loop (0: normal scheduling)')
    parser.add_argument('--fault', action='append', default=[], metavar='FAULT',
                        help='inject a fault KIND:LEG[:VALUE][@T_START[-T_END]] into the plant, '
                        'e.g. actuator_dead:leg_4@2.0 (repeatable; added to the plant\'s '
                        'faults of the parameter file; docs/faults.md)')
    parser.add_argument('--supervisor', action='store_true',
                        help='put the supervisor between the controller and the plant: it '
                        'trips on its limits, latches, brings the platform down '
                        '(docs/supervisor.md); off by default, see there why')
    parser.add_argument('--plant-params', metavar='FILE',
                        help='a parameter file for the plant only, read after --params: the '
                        'machine as built (geometry, leg_length_offset, a simulated tracker) '
                        'while controller and fk run on --params (docs/calibration.md)')
    parser.add_argument('--bus', choices=('canopen',),
                        help='put the plant on the field bus as the legs\' CiA 402 drives and '
                        'start canopen_bridge between the bus and the topics (the device config: '
                        'bus_config, default config/canopen.yaml; docs/bus.md)')
    parser.add_argument('--strict', action='store_true', help=STRICT_HELP)
    parser.add_argument('--view', action='store_true',
                        help='also serve the live 3D view of this rig in a web browser '
                        '(`view`) and print its URL')
    parser.add_argument('--view-port', type=int, default=8080, metavar='P',
                        help='port of --view (default 8080; 0: any free port)')
    args = parser.parse_args(argv)
    try:     # as a user types it (rig2), absolute for the nodes' remap rule (/rig2)
        args.namespace = ros_namespace(args.namespace)
    except ValueError as exc:
        print('rig: error: --namespace: %s' % exc, file=sys.stderr)
        return 2
    params = args.params or str(default_params_path())
    if not all(b >= 0 for b in args.tracking_bound):       # NaN fails too
        parser.error('--tracking-bound takes two numbers >= 0 (metres, radians)')
    if args.view:
        # lazy: tools.view costs 2255 ms; only --view needs it
        from stewart63_ros.tools.view import port_free
        problem = port_free('127.0.0.1', args.view_port) if 0 <= args.view_port <= 65535 \
            else '--view-port must be from 0 to 65535'
        if problem:
            print('rig: error: --view: %s' % problem, file=sys.stderr)
            return 2
    if load_checked('rig', params, strict=args.strict) is None:
        return 2      # fail here, not in three processes
    if args.plant_params is not None:
        problem = plant_params_problem(args, params)
        if problem:
            print('rig: error: --plant-params: %s' % problem, file=sys.stderr)
            return 2
    fault_extra = {}
    if args.fault and 'plant' not in nodes_arg(args.nodes):
        parser.error('--fault acts in the plant: it needs plant in --nodes')
    if 'plant' in nodes_arg(args.nodes):
        # lazy: tools.sim costs 1092 ms (numba); only --fault needs it
        from stewart63_ros.core.machine.faults import FaultError
        from stewart63_ros.tools.sim import fault_list
        try:     # the file's faults and --fault's: fail here, with the reason, not in the plant
            faults = fault_list(params, args.fault)
        except FaultError as exc:
            print('rig: error: %s' % exc, file=sys.stderr)
            return 2
        if args.fault:
            fault_extra['faults'] = [f.text for f in faults]
        if any(f.bus for f in faults) and not args.bus:
            print('rig: error: fault %r acts on the field bus: add --bus canopen'
                  % next(f.text for f in faults if f.bus), file=sys.stderr)
            return 2
    announce_compile('rig', 'the nodes start by ')
    if args.duration is not None and not args.duration > 0:
        parser.error('--duration must be positive')
    extra = {}
    if args.control_law or args.reference:
        # lazy: tools.sim costs 1092 ms (numba); only --reference
        from stewart63_ros.core.controllers.reference import ReferenceError
        from stewart63_ros.tools.sim import make_controller
        try:     # fail here, with the reason, not in the controller
            make_controller(params, args.control_law, args.reference)
        except (ParameterError, ReferenceError) as exc:
            print('rig: error: %s' % exc, file=sys.stderr)
            return 2
        extra = control_params(args.control_law, args.reference)
    if fault_extra:
        extra.setdefault('plant', {}).update(fault_extra)
    if args.record and os.path.exists(args.record):
        print('rig: error: %s exists; record writes a new bag' % args.record, file=sys.stderr)
        return 2

    nodes = nodes_arg(args.nodes)
    unknown = [n for n in nodes if n not in NODES]
    if unknown or not nodes or len(set(nodes)) != len(nodes):
        parser.error('--nodes takes a comma-separated subset of %s, got %r'
                     % (','.join(NODES), args.nodes))
    nodes = tuple(n for n in NODES if n in nodes)
    if args.duration is not None and 'plant' not in nodes:
        parser.error('--duration ends the plant\'s run: it needs plant in --nodes (the '
                     'other nodes run until Ctrl-C or SIGTERM)')
    if not 0 <= args.realtime_priority <= 99:
        parser.error('--realtime-priority must be from 0 to 99')
    if args.supervisor and ('controller' not in nodes or 'plant' not in nodes):
        # (the plant's parameters of this rig say to wait for its answers)
        parser.error('--supervisor runs between the controller and the plant: it needs '
                     'both in --nodes')
    if args.supervisor and reference_file_extra(extra):
        extra.setdefault('supervisor', {})['reference_file'] = reference_file_extra(extra)
    if args.bus and 'plant' not in nodes:
        # (the bridge takes over the plant's start-up parameters of this rig)
        parser.error('--bus canopen starts the bridge beside the plant: it needs plant in '
                     '--nodes')
    if args.bus:
        # lazy: core.plumbing.params costs 715 ms (numba); --help answers without it
        from stewart63_ros.core.machine.bus import BusConfigError, load_bus_config
        from stewart63_ros.core.plumbing.params import file_parameters
        try:     # fail here, with the reason, not in two processes
            load_bus_config(file_parameters(params).get('bus_config') or None)
        except BusConfigError as exc:
            print('rig: error: %s' % exc, file=sys.stderr)
            return 2
    if args.supervisor:
        problem = supervisor_problem(params, extra.get('supervisor', {}))
        if problem:     # once, here, not from the supervisor's process as it fails
            print('rig: error: %s' % problem, file=sys.stderr)
            return 2
    two = two_rates(params, args.plant_params, rate_followers(args.bus, args.supervisor))
    if two:
        print('rig: error: %s' % two, file=sys.stderr)
        return 2
    rig = Rig(params, args.mode, args.duration, args.record, args.namespace, args.log_dir,
              nodes=nodes, realtime_priority=args.realtime_priority, compose=args.compose,
              extra_params=extra, supervisor=args.supervisor, bus=args.bus)
    rig.plant_params = args.plant_params and str(Path(args.plant_params).resolve())
    ok = False
    start, start_unix = time.monotonic(), time.time()
    try:
        signals.interrupt_from_now()    # raises at once for a signal during the options
        rig.start()
        if args.view:
            print('rig: live view at %s' % rig.start_view(args.view_port), flush=True)
        print('rig: %s, logs in %s' % (', '.join(rig.procs), rig.log_dir), flush=True)
        while not signals.requested:
            ok = rig.wait(timeout=0.2)
            if ok or rig.failed() or any(
                    p.poll() is not None for n, p in rig.procs.items()
                    if n not in rig.ending_with_run()):
                break
        if not ok and not signals.requested:
            fail_safe = rig.supervisor_fail_safe()
            if fail_safe:
                print('rig: fail safe acted after the supervisor ended: %s' % fail_safe,
                      flush=True)
    except KeyboardInterrupt:
        pass
    except RuntimeError as exc:
        print('rig: error: %s' % exc, file=sys.stderr)
    finally:
        signals.armed = False
        # Who had failed before the stop: a node interrupted while it was still
        # starting (importing, compiling) ends with whatever code that gives.
        failed_before = set(rig.failed())
        codes = rig.stop()
        ignore_stop_signals()      # the rig has stopped: nothing left to interrupt
    wall = time.monotonic() - start
    died = {n: c for n, c in codes.items() if c not in (0, None)}
    for name in died:
        how = ('exited' if name in failed_before or not signals.requested
               else 'ended, while stopping,')
        print('rig: %s %s with %s: %s' % (name, how, died[name], rig.log_tail(name)),
              file=sys.stderr)
    if signals.requested:
        print('rig: stopped by %s after %.2f s wall' % (signals.received[0], wall))
    print_summary(rig, wall, start_unix)
    if args.record:
        print('  bag: %s' % args.record)
    lost = lost_reference(rig.summary() if args.reference else None, args.tracking_bound)
    if lost:
        print('rig: error: %s' % lost, file=sys.stderr)
        return 1
    if signals.requested:
        return 1 if failed_before else 0
    if died or not ok:
        return 1
    return 0


def supervisor_problem(params, extra: dict) -> str:
    """Why the supervisor would refuse its parameters ('' if it would not): its
    limits, its homing (``homing_direction: retract`` on a machine whose legs
    cannot all be at their lower stops), its reference. Checked before anything
    starts: one line, exit 2 (it was the supervisor's log tail and exit 1)."""
    # lazy: core.machine.supervisor costs 1092 ms (numba, as tools.sim); --help answers without it
    from stewart63_ros.core.machine.supervisor import supervisor_from_params
    from stewart63_ros.core.plumbing.node_parameters import read as read_declared
    from stewart63_ros.core.plumbing.params import read_parameter_file, setup_from_params
    try:
        values = dict(read_parameter_file(params, 'supervisor'), **extra)
        setup = setup_from_params(values)
        values = dict(setup.to_params(), **values)
        supervisor_from_params(setup, values, read_declared(values, 'sensor_rate'))
    except ParameterError as exc:
        return 'supervisor: parameter error: %s' % exc
    return ''


def lost_reference(summary: dict | None, bound) -> str:
    """Why the plant's run lost the reference it was to follow ('' if it did not):
    its true position or orientation error (after the first second) beyond
    ``bound`` (metres, radians; 0 turns one off). A platform that changed
    assembly mode keeps its legs near the reference's and its pose 0.3 m away."""
    err = (summary or {}).get('tracking_error') or {}
    if not err.get('samples'):
        return ''
    position, angle = bound
    if position and err['position_max_m'] > position or angle and \
            err['orientation_max_rad'] > angle:
        return ('the platform lost its reference: true tracking error position max %.4g m, '
                'orientation max %.4g rad, beyond --tracking-bound %g m %g rad'
                % (err['position_max_m'], err['orientation_max_rad'], position, angle))
    return ''


def plant_params_problem(args, params) -> str:
    """Why --plant-params cannot be used ('' if it can): the plant's two files
    must make a valid mechanism, and the plant must run in its own process."""
    if args.compose and not getattr(args, 'bus', None):
        return ('the composed nodes share one process and its files: not with --compose '
                '(with --bus canopen the plant runs in its own process, and takes it)')
    if 'plant' not in nodes_arg(args.nodes):
        return 'it is the plant\'s file: it needs plant in --nodes'
    # lazy: core.plumbing.params costs 715 ms (numba); --help answers
    from stewart63_ros.core.plumbing.params import read_parameter_file, setup_from_params
    try:
        merged = read_parameter_file(params, 'plant')
        merged.update(read_parameter_file(args.plant_params, 'plant', allow_empty=True))
        setup_from_params(merged)
    except ParameterError as exc:
        return '%s: %s' % (args.plant_params, exc)
    return ''


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


def two_rates(params, plant_params, followers) -> str:
    """Why the files give ``followers`` (nodes that count the plant's
    samples) a ``sensor_rate`` other than the plant's; '' when they agree."""
    if not followers:
        return ''
    # lazy: core.plumbing.node_parameters costs 715 ms (numba, with core.plumbing.params); --help
    # answers
    from stewart63_ros.core.plumbing.node_parameters import BY_NAME
    rates = sample_rates(params, plant_params)
    plant_rate = rates['plant'] if rates['plant'] is not None else BY_NAME[
        'sensor_rate'].default
    for node in followers:
        if rates[node] is not None and rates[node] != plant_rate:
            why = ('the plant steps one period a SYNC' if node == 'canopen_bridge' else
                   'it numbers the samples and checks the force rate at its own')
            return ('one sample rate: %s sensor_rate %g Hz, plant %g Hz (%s): set sensor_rate '
                    'once, for both' % (node, rates[node], plant_rate, why))
    return ''


def nodes_arg(text: str) -> tuple:
    """The node names of a ``--nodes`` value, as given."""
    return tuple(n.strip() for n in text.split(',') if n.strip())


def wall_parts(summary: dict, wall: float, started_unix: float | None) -> dict | None:
    """The rig's ``wall`` seconds in parts [s]: ``start-up`` (processes,
    kernels, discovery, up to the plant's first sample), ``run`` (first sample
    to last, pauses included) and ``stop`` (the rest: the nodes' flush and
    exit). None when the plant's summary does not say when its run began."""
    began, ended = summary.get('run_began_unix_s'), summary.get('run_ended_unix_s')
    if started_unix is None or began is None or ended is None:
        return None
    startup = max(0.0, began - started_unix)
    run = max(0.0, min(ended - began, wall - startup))
    return {'start-up': startup, 'run': run, 'stop': max(0.0, wall - startup - run)}


def print_summary(rig, wall, started_unix=None):
    """The plant's summary (error, latency, missed cycles), then what the
    other nodes of this rig saw: for a timed run and for a stopped one alike.
    ``started_unix``: time.time() as the rig started (the wall time's parts)."""
    summary = rig.summary()
    supervisor = rig.summary('supervisor') if rig.supervisor else None
    homing = homing_unfinished(supervisor)
    if summary:
        lat = summary['loop_latency']
        parts = wall_parts(summary, wall, started_unix)
        mode = '%s, %g Hz%s' % (summary['clock_mode'], summary['rate_hz'],
                                ', stopped early' if summary.get('stopped_by_signal') else '')
        if parts is None:
            print('rig summary: %d samples; %.2f s wall in all (%s)'
                  % (summary['samples'], wall, mode))
        else:
            print('rig summary: %d samples in %.2f s wall (%s); start-up %.2f s, stop %.2f s, '
                  '%.2f s in all' % (summary['samples'], parts['run'], mode,
                                     parts['start-up'], parts['stop'], wall))
        if homing:      # the legs were on their way to the stops: no figure of the run's
            print('  final positioning error: none, %s' % homing)
        else:
            print('  final positioning error: %.4f %% (max over legs of |L - L0| / L0)'
                  % summary['positioning_error_percent'])
        if lat.get('count'):
            print('  loop latency (sample stamp -> force received): p50 %.3f ms, p99 %.3f ms, '
                  'max %.3f ms' % (lat['p50_ms'], lat['p99_ms'], lat['max_ms']))
        print('  missed cycles %d, force timeouts %d, end-stop samples %d' % (
            summary['missed_cycles'], summary['force_timeouts'], summary['endstop_samples']))
        peers = summary.get('lockstep_peers')
        if peers:
            print('  lockstep peers held the plant %d times, %.3f s in all%s' % (
                peers['held_samples'], peers['held_s'], ''.join(
                    '; DROPPED %s: %s' % item for item in peers['dropped'].items())))
        if summary.get('skipped'):
            print('  plant skipped (never received): %s' % _counts(summary['skipped']))
        if 'tracking_error' in summary:
            # lazy: tools.sim costs 1092 ms (numba); --help answers
            from stewart63_ros.tools.sim import format_tracking
            print('  ' + format_tracking(summary['tracking_error']))
        if summary.get('resets'):
            print('  resets %d (this summary is of run %d)' % (summary['resets'],
                                                              summary['run_number']))
        # lazy: tools.sim costs 1092 ms (numba); --help answers
        from stewart63_ros.tools.sim import format_fault
        for fault in summary.get('faults', ()):
            print('  ' + format_fault(fault))
    if rig.supervisor:
        print_trips(supervisor)
    if rig.bus:
        s = rig.summary('canopen_bridge')
        print('  canopen_bridge: %s' % ('no summary' if not s else
                                        '%g Hz, %d cycles, missed cycles %d, force timeouts '
                                        '%d, TPDOs missed %s, computed bus load %s %%' % (
                                            s['rate_hz'], s['cycles'], s['missed_cycles'],
                                            s['force_timeouts'], s['tpdo_missed'],
                                            s['bus_load_computed_percent'])))
        print_drives_at_stop(s)
    for node in ('controller', 'fk'):
        if node not in rig.nodes:
            continue
        s = rig.summary(node)
        if not s:
            print('  %s: no summary' % node)
            continue
        values = s.get('values', {})
        extra = ''.join(', %s %s' % (k.replace('_', ' '), values[k]) for k in (
            'source_restarts', 'collisions', 'forces_withheld') if values.get(k))
        skipped = s.get('skipped') or {}
        if skipped:
            extra += ', %s %s' % ('LOST' if node == 'fk' else 'skipped (stale)',
                                  _counts(skipped))
        print('  %s: received %s, published %s, rejected %d%s' % (
            node, _counts(s['received']), _counts(s['published']), s['rejected_total'],
            extra))


def reference_file_extra(extra: dict) -> str:
    """The reference CSV handed to the controller (``--reference``), or ''."""
    return extra.get('controller', {}).get('reference_file', '')


def homing_unfinished(summary) -> str:
    """'the run ended before the homing finished ...' when the supervisor's
    summary says it homes and is not homed; '' otherwise."""
    if (summary or {}).get('values', {}).get('homed') == 'false':
        return ('the run ended before the homing finished (homed: false): the controller '
                'never drove the platform')
    return ''


def print_trips(summary) -> None:
    """The supervisor's trips, one line each, in the rig's summary; a homing
    the run cut short is said first (it read "no trip" and an error figure)."""
    if not summary:
        print('  supervisor: no summary')
        return
    trips = summary.get('trips', [])
    homing = homing_unfinished(summary)
    print('  supervisor: %s%s' % (homing + '; ' if homing else '', '%d trip%s' % (
        len(trips), 's' * (len(trips) != 1)) if trips else 'no trip'))
    for trip in trips:
        print('    TRIP %s at sample %d (%s): %s, latency %s samples' % (
            trip['cause'], trip['sample'], trip['detail'], trip['action'],
            trip['latency_samples']))


def _counts(counter):
    return ', '.join('%s %d' % (t.lstrip('/'), n) for t, n in sorted(counter.items())
                     if t != '/diagnostics') or 'nothing'


if __name__ == '__main__':
    sys.exit(main())
