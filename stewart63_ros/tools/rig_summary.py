"""What ``rig`` prints at the end of a run: each node's summary line, the
wall time's parts, the supervisor's trips, an unfinished homing, and the
state the drives were left in.
"""
from __future__ import annotations

import sys

# Light imports only up to main's first line, which installs the stop
# handlers: a Ctrl-C while numpy and scipy load (a third of a second) could
# otherwise be swallowed by a library's bare ``except`` and never stop the rig.


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
