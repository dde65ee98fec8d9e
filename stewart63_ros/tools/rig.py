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
import os
import sys
import time
from pathlib import Path

# Light imports only up to main's first line, which installs the stop
# handlers: a Ctrl-C while numpy and scipy load (a third of a second) could
# otherwise be swallowed by a library's bare ``except`` and never stop the rig.
from stewart63_ros.core.plumbing.errors import ParameterError
from stewart63_ros.core.plumbing.node_names import NODES
from stewart63_ros.paths import RIG_CLOCK_MODE, default_params_path
from stewart63_ros.runtime.forkserver import ForkServer, fork_server_wanted
from stewart63_ros.runtime.launcher import (
    StopSignals,
    dump_stacks_on_sigusr1,
    ignore_stop_signals,
)
from stewart63_ros.tools.cli import (
    STRICT_HELP,
    announce_compile,
    load_checked,
    quiet_on_closed_pipe,
    ros_namespace,
)
from stewart63_ros.tools.rig_process import Rig, default_log_dir, rate_followers, sample_rates
from stewart63_ros.tools.rig_summary import print_summary, reference_file_extra

#: --tracking-bound's default: position [m], orientation [rad]. A planned
#: calibration on a machine built off its drawing tracks within 2.7 cm (the
#: drawing's error and the law's lag, docs/calibration.md); a platform that
#: changes assembly mode ends 0.2-0.3 m and 1 rad away.
TRACKING_BOUND = (0.05, 0.1)


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
    try:     # it loads the core on the other core while this one checks the options
        fork_server = ForkServer(str(Path(args.log_dir or default_log_dir(
            args.record, args.namespace)) / 'forkserver')) if fork_server_wanted() else None
    except ValueError as exc:
        print('rig: error: %s' % exc, file=sys.stderr)
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
              extra_params=extra, supervisor=args.supervisor, bus=args.bus,
              fork_server=fork_server)
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


if __name__ == '__main__':
    sys.exit(main())
