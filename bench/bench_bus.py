"""The field bus's costs: prints figures, asserts nothing (docs/performance.md).

- the bridge's cost per sample: the master's SYNC, collect, readings,
  judgement and RPDOs for six drives on two ``s63hub`` buses, against the
  plant's drives served by another process (a round trip per cycle), and the
  CPU time each side spends per sample (the master's includes its notifier
  thread);
- lockstep over the bus beside the DDS-only rig: samples per second;
- realtime at ``--rate`` (the packaged 1 kHz), separate processes and
  composed with the supervisor (``rig --bus canopen --compose --supervisor``):
  the bridge's missed cycles, each leg's missed TPDOs, leg_lengths to force,
  and SYNC to the torques' RPDO on the wire (a passive bus on each channel,
  the sender's stamps), the bus load planned and as the bridge's
  /diagnostics measures it; the load average beside every run; from the
  per-cycle traces (canbus/trace.py), where the misses fell (the first
  second, by tenths of the run, the longest run of them), SYNCs skipped,
  and each side's CPU time a cycle.
- ``--accept``: the composed bridge's target (docs/bus.md), two 30 s realtime
  runs against their lockstep run, PASS or FAIL per figure (exit 0: pass).
  Run it with nothing else on the machine:

    bench_bus.py [--cycles N] [--duration S] [--rate HZ] [--repeat N] [--no-rig]
    bench_bus.py --accept [--duration 30] [--rate 1000]
"""
from __future__ import annotations

import argparse
import glob
import os
import subprocess
import sys
import tempfile
import textwrap
import threading
import time
import uuid

import can
import numpy as np
from bench_loop import private_domain

from stewart63_ros.canbus.master import Master
from stewart63_ros.canbus.trace import TRACE_ENV
from stewart63_ros.core.machine.bus import load_bus_config
from stewart63_ros.paths import default_params_path
from stewart63_ros.tools.rig_process import Rig

DEVICES = textwrap.dedent('''
    import sys, time
    import numpy as np
    from stewart63_ros.core.machine.bus import load_bus_config
    from stewart63_ros.canbus.devices import DeviceSet
    config = load_bus_config(None, channels=sys.argv[1:3])
    devices = DeviceSet(config)
    lengths = np.array([1.9, 1.9, 1.6, 1.6, 1.6, 1.6]); rates = np.zeros(6)
    n = 0; busy = 0.0; cpu0 = None
    print('ready', flush=True)
    while n < int(sys.argv[3]):
        if devices.poll(0.01):
            if cpu0 is None:
                cpu0 = time.process_time()
            t = time.perf_counter()
            devices.take_sync(); devices.heartbeats(n / 1000.0)
            devices.answer_sync(lengths, rates); devices.forces()
            busy += time.perf_counter() - t
            n += 1
    time.sleep(0.2)
    devices.poll(0.0)
    print('device side: %.1f us a sample answering SYNC (6 drives), %.1f us CPU a sample '
          'in all' % (busy / n * 1e6, (time.process_time() - cpu0) / n * 1e6), flush=True)
    devices.close()
''')


def bridge_cost(cycles: int) -> None:
    tag = uuid.uuid4().hex[:8]
    channels = ['bench%s-a' % tag, 'bench%s-b' % tag]
    devices = subprocess.Popen([sys.executable, '-c', DEVICES, *channels, str(cycles)],
                               stdout=subprocess.PIPE, text=True)
    try:
        assert devices.stdout.readline().strip() == 'ready'
        config = load_bus_config(None, channels=channels)
        master = Master(config, 1000.0, log=lambda text: None)
        master.reset_all()
        master.wait_for_boot(10.0)
        for link in master.links:
            master.bring_up(link)
        forces = np.full(6, 100.0)
        own = 0.0
        cpu = time.process_time()
        start = time.perf_counter()
        for k in range(cycles):
            t = time.perf_counter()
            master.sync(k)
            own += time.perf_counter() - t
            master.collect(time.monotonic() + 1.0, 0.002, 0.002)    # lockstep's rules
            t = time.perf_counter()
            master.missing()
            master.readings()
            errors = master.errors()
            master.command(forces, bool(errors))
            own += time.perf_counter() - t
        wall = time.perf_counter() - start
        cpu = time.process_time() - cpu
        print('bridge side: %d cycles, %.1f us a cycle round trip (SYNC to the last of six '
              'TPDOs and the RPDOs out), %.1f us of its own work a cycle (SYNC, readings, '
              'judgement, RPDOs), %.1f us CPU a cycle with its notifier thread'
              % (cycles, wall / cycles * 1e6, own / cycles * 1e6, cpu / cycles * 1e6),
              flush=True)
        master.close()
        print(devices.communicate(timeout=30)[0].strip())
    finally:
        if devices.poll() is None:
            devices.kill()


#: COB-ID bases: SYNC, and each drive's RPDO1 (controlword, target torque)
SYNC_COB, RPDO1_BASE = 0x080, 0x200


class WireWatch:
    """A passive bus on each of a rig's local buses (``s63hub``): every frame
    with its sender's time stamp, read in bulk every 50 ms (one wake-up of
    this process each time, not one a frame). From them: SYNC to the last
    RPDO of the same cycle (the torques answering that SYNC's sample, as the
    bridge sent them), and the cycles with no RPDO before the next SYNC."""

    def __init__(self, channels):
        self.buses = {name: can.Bus(interface='s63hub', channel=channel)
                      for name, channel in channels.items()}
        self.frames = {name: [] for name in channels}
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self):
        while True:
            for name, bus in self.buses.items():
                msg = bus.recv(0.0)
                while msg is not None:
                    self.frames[name].append((msg.timestamp, msg.arbitration_id))
                    msg = bus.recv(0.0)
            if self.stop.is_set():
                return
            time.sleep(0.05)

    def close(self):
        self.stop.set()
        self.thread.join(5.0)
        for bus in self.buses.values():
            bus.shutdown()

    def sync_to_rpdo(self) -> tuple[np.ndarray, int, int]:
        """(SYNC -> last RPDO of its cycle [s] for every bus and cycle that
        had one, the cycles without an RPDO, the cycles in all)."""
        latencies, empty, cycles = [], 0, 0
        for frames in self.frames.values():
            sync = last = None
            for stamp, cob in frames:
                if cob == SYNC_COB:
                    if sync is not None:
                        cycles += 1
                        if last is None:
                            empty += 1
                        else:
                            latencies.append(last - sync)
                    sync, last = stamp, None
                elif RPDO1_BASE < cob < RPDO1_BASE + 0x80 and sync is not None:
                    last = stamp
        return np.array(latencies), empty, cycles


def measured_loads(bridge: dict) -> dict:
    """The bus loads on the bridge's /diagnostics (its summary's values):
    planned (``bus_load_computed_percent/<bus>``) and whatever it measures
    (``bus_load_percent/<bus>``; a listener on the wire where
    canbus/busload.py is in the tree). {key: percent}."""
    values = (bridge or {}).get('values', {})
    return {key: float(value) for key, value in values.items()
            if key.startswith('bus_load') and str(value).replace('.', '', 1).isdigit()}


def where_missed(folder) -> dict | None:
    """From the per-cycle traces of a realtime run (canbus/trace.py): where
    the bridge's misses fall and what each cycle cost. None without traces."""
    found = {}
    for name in ('canopen_bridge', 'plant'):
        files = glob.glob(os.path.join(folder, '%s-*.npz' % name))
        if not files:
            return None
        with np.load(files[0]) as z:
            found[name] = ({f: z['rows'][:, i] for i, f in enumerate(z['fields'])},
                           z['gc'])
    b, bgc = found['canopen_bridge']
    p, _ = found['plant']
    if len(b['k']) < 3:
        return None
    t0 = b['due'][0]
    bad = b['missing'] > 0
    runs, run = [], 0
    for x in bad:
        run = run + 1 if x else 0
        if x:
            runs.append(run)
    when = b['due'][bad] - t0
    span = max(1.0, b['ended'][-1] - t0)
    in_gc = bgc[(bgc[:, 0] >= t0)] if len(bgc) else bgc
    # the plant's answers armed for their SYNC (canbus/hub.py) were ready
    # before it: its answer time is that of the samples it answered on a SYNC
    armed = p['armed'] > 0 if 'armed' in p else np.zeros(len(p['k']), bool)
    answered = (p['answered'] - p['sync_seen'])[~armed]
    return {
        'missing_cycles': int(bad.sum()), 'longest_run': int(max(runs, default=0)),
        'first_second': int((when < 1.0).sum()),
        'per_tenth': np.histogram(when, bins=10, range=(0, span))[0].tolist(),
        'skipped_syncs': int(b['skipped'].sum()),
        'sync_late_p99_ms': float(np.percentile(b['woke'] - b['due'], 99) * 1e3),
        'bridge_cpu_us': float(np.median(np.diff(b['cpu'])) * 1e6),
        'plant_cpu_us': float(np.median(np.diff(p['cpu'])) * 1e6),
        'armed_percent': float(100 * armed.mean()) if len(armed) else 0.0,
        'plant_answer_p99_ms': float(np.percentile(answered, 99) * 1e3) if len(answered)
        else 0.0,
        'gc_over_1ms': int((in_gc[:, 2] > 1e-3).sum()) if len(in_gc) else 0}


def rig_run(mode, duration, compose=False, supervisor=False, bus='canopen', hz=1000.0,
            watch=False, log_dir=None, priority=0) -> dict | None:
    """One rig run to its end; its figures (None if it did not end). In
    realtime over the bus, with the bridge's and the drives' per-cycle
    traces (``where``: where the misses fell)."""
    log_dir = log_dir or tempfile.mkdtemp(prefix='bench_bus_')
    traced = mode == 'realtime' and bus and TRACE_ENV not in os.environ
    if traced:
        os.environ[TRACE_ENV] = os.path.join(log_dir, 'trace')
    extra = {n: {'sensor_rate': hz} for n in ('plant', 'canopen_bridge')} \
        if hz != 1000.0 else {}
    rig = Rig(default_params_path(), mode, duration, log_dir=log_dir, bus=bus,
              extra_params=extra, compose=compose, supervisor=supervisor,
              realtime_priority=priority)
    watcher = None
    if watch and bus:
        buses = load_bus_config(None).buses
        if all(b.interface == 's63hub' for b in buses):     # the channels rig gives them
            watcher = WireWatch({b.name: 'rig%d-%s' % (os.getpid(), b.name) for b in buses})
    load_before = os.getloadavg()[0]
    try:
        rig.start()
        ok = rig.wait(timeout=120 + 60 * duration)
    finally:
        rig.stop()
        if watcher is not None:
            watcher.close()
        if traced:
            del os.environ[TRACE_ENV]
    plant = rig.summary()
    bridge = rig.summary('canopen_bridge') if bus else None
    if not ok or plant is None or (bus and bridge is None):
        print('%s %s run failed; logs in %s' % (mode, bus or 'dds', log_dir), flush=True)
        return None
    runner = bridge or plant
    out = {'samples': plant['samples'], 'wall_s': plant['wall_time_s'],
           'error_percent': plant['positioning_error_percent'],
           'cycles': runner.get('cycles', plant['samples']),
           'missed_cycles': runner['missed_cycles'],
           'latency': runner['loop_latency'], 'load_average': (load_before,
                                                               os.getloadavg()[0])}
    if bridge:
        out['tpdo_missed'] = bridge['tpdo_missed']
        out['bus_load'] = measured_loads(bridge)
        out['planned_load'] = bridge['bus_load_computed_percent']
    if supervisor:
        trips = (rig.summary('supervisor') or {}).get('trips')
        out['trips'] = ['%s at sample %d' % (t['cause'], t['sample']) for t in trips or []] \
            if trips is not None else ['no supervisor summary']
        out['trip_details'] = [t.get('detail', '')[:200] for t in trips or []]
    if mode == 'realtime' and bus:
        out['where'] = where_missed(os.environ.get(TRACE_ENV) or os.path.join(log_dir, 'trace'))
    if watcher is not None:
        lat, empty, cycles = watcher.sync_to_rpdo()
        out['sync_to_rpdo'] = {'count': len(lat), 'no_rpdo_cycles': empty, 'cycles': cycles}
        if len(lat):
            out['sync_to_rpdo'].update({'p50_us': float(np.percentile(lat, 50) * 1e6),
                                        'p99_us': float(np.percentile(lat, 99) * 1e6)})
    return out


def describe(name, run) -> str:
    if run is None:
        return '%s: failed' % name
    text = '%s: %d samples, %.0f samples/s, final error %.4f %%, missed cycles %d of %d' % (
        name, run['samples'], run['samples'] / run['wall_s'], run['error_percent'],
        run['missed_cycles'], run['cycles'])
    if 'tpdo_missed' in run:
        text += ', TPDOs missed %s' % ' '.join('%d' % v for v in run['tpdo_missed'].values())
    lat = run['latency']
    if lat.get('count'):
        text += '; leg_lengths -> force p50 %.3f ms, p99 %.3f ms' % (lat['p50_ms'],
                                                                       lat['p99_ms'])
    wire = run.get('sync_to_rpdo')
    if wire and wire.get('count'):
        text += '; SYNC -> RPDO p50 %.0f us, p99 %.0f us (%d cycles without one)' % (
            wire['p50_us'], wire['p99_us'], wire['no_rpdo_cycles'])
    if 'trips' in run:
        text += '; %s' % (', '.join(run['trips']) or 'no trip')
    if 'bus_load' in run:
        measured = {k.split('/')[-1]: v for k, v in run['bus_load'].items()
                    if 'computed' not in k}
        text += '; bus load planned %s %%, measured on the bridge\'s /diagnostics %s' % (
            ' '.join('%s %.1f' % kv for kv in run['planned_load'].items()),
            ' '.join('%s %.1f %%' % kv for kv in measured.items()) or 'none')
    text += ' (load average %.1f -> %.1f)' % run['load_average']
    for detail in run.get('trip_details', []):
        text += '\n  trip: %s' % detail
    where = run.get('where')
    if where:
        text += ('\n  where: %d cycles with a TPDO missing (%d in the first second, longest '
                 'run %d; by tenths of the run %s), %d SYNCs skipped, SYNC late p99 %.2f ms, '
                 '%.1f %% of the samples armed for their SYNC, the others\' answer p99 %.2f '
                 'ms; CPU a cycle: bridge\'s process %.0f us, plant '
                 '%.0f us; %d GC pauses over 1 ms' % (
                     where['missing_cycles'], where['first_second'], where['longest_run'],
                     ' '.join(map(str, where['per_tenth'])), where['skipped_syncs'],
                     where['sync_late_p99_ms'], where['armed_percent'],
                     where['plant_answer_p99_ms'],
                     where['bridge_cpu_us'], where['plant_cpu_us'], where['gc_over_1ms']))
    return text


def figures(prefix, run) -> dict:
    """bench_all's keys for one realtime run."""
    if run is None:
        return {}
    out = {prefix + 'missed_fraction': run['missed_cycles'] / max(1, run['cycles'])}
    if 'tpdo_missed' in run:
        out[prefix + 'tpdo_missed_fraction'] = max(run['tpdo_missed'].values()) / max(
            1, run['cycles'])
    wire = run.get('sync_to_rpdo') or {}
    if wire.get('count'):
        out[prefix + 'sync_rpdo_p50_us'] = wire['p50_us']
        out[prefix + 'sync_rpdo_p99_us'] = wire['p99_us']
    return out


def measure(duration: float = 5.0, repeat: int = 1, rate: float = 1000.0) -> dict:
    """The bus's realtime figures for bench_all: separate processes, then
    composed and supervised (``rig --bus canopen --compose --supervisor``),
    at ``rate``; medians of ``repeat`` runs each."""
    results: dict = {}
    with private_domain():
        for prefix, compose, supervisor in (('bus_rt_separate_', False, False),
                                            ('bus_rt_composed_', True, True)):
            runs = []
            for _ in range(repeat):
                run = rig_run('realtime', duration, compose, supervisor, hz=rate, watch=True)
                print(describe('realtime %g Hz, %s' % (rate, 'composed, supervised' if compose
                                                        else 'separate'), run), flush=True)
                if run is not None:
                    runs.append(figures(prefix, run))
                    if 'planned_load' in run:
                        results['bus_load_planned_percent'] = max(run['planned_load'].values())
                    measured = [v for k, v in run.get('bus_load', {}).items()
                                if 'computed' not in k]
                    if measured:
                        results['bus_load_measured_percent'] = max(measured)
            for key in (runs[0] if runs else {}):
                results[key] = float(np.median([r[key] for r in runs if key in r]))
    return results


def lockstep_beside_direct(duration: float) -> None:
    with private_domain():
        for bus in (None, 'canopen'):
            print(describe('lockstep %s' % (bus or 'dds only'),
                           rig_run('lockstep', duration, bus=bus)), flush=True)


def uptime() -> str:
    return subprocess.run(['uptime'], capture_output=True, text=True).stdout.strip()


def accept(duration: float = 30.0, runs: int = 2, rate: float = 1000.0,
           priority: int = 0) -> int:
    """The composed bridge's target (docs/bus.md): ``rig --bus canopen --compose
    --supervisor`` in realtime at ``rate`` for ``duration`` s, ``runs`` times
    in a row, each against the lockstep run of the same rig: bridge cycles
    missed and each leg's missed TPDOs at most 0.1 %, no trip, final error
    within 0.01 points of lockstep's. Exit 0 when every run passes. ``priority``:
    ``rig --realtime-priority`` (SCHED_FIFO for the plant standing in for the
    drives, and the composed process), 0: normal scheduling."""
    print('acceptance: realtime %g Hz, composed and supervised over the bus, %g s, %d runs, '
          'realtime priority %d; nothing else should run (uptime: %s)'
          % (rate, duration, runs, priority, uptime()), flush=True)
    failed = 0
    with private_domain():
        reference = rig_run('lockstep', duration, compose=True, supervisor=True, hz=rate)
        print(describe('lockstep reference', reference), flush=True)
        if reference is None:
            return 1
        for i in range(runs):
            run = rig_run('realtime', duration, compose=True, supervisor=True, hz=rate,
                          priority=priority)
            print(describe('realtime run %d' % (i + 1), run), flush=True)
            if run is None:
                failed += 1
                continue
            cycles = max(1, run['cycles'])
            checks = [
                ('bridge cycles missed %.3f %% <= 0.1 %%' % (100 * run['missed_cycles'] / cycles),
                 run['missed_cycles'] <= 0.001 * cycles),
                ('each leg\'s TPDOs missed, at most %.3f %% <= 0.1 %%' % (
                    100 * max(run['tpdo_missed'].values()) / cycles),
                 max(run['tpdo_missed'].values()) <= 0.001 * cycles),
                ('no trip (%s)' % (', '.join(run['trips']) or 'none'), not run['trips']),
                ('final error %.4f %% within 0.01 points of lockstep\'s %.4f %%' % (
                    run['error_percent'], reference['error_percent']),
                 abs(run['error_percent'] - reference['error_percent']) <= 0.01)]
            for text, ok in checks:
                print('  %s %s' % ('PASS' if ok else 'FAIL', text))
            failed += not all(ok for _, ok in checks)
    print('acceptance: %s (uptime: %s)' % ('PASS' if not failed else '%d of %d runs FAILED'
                                           % (failed, runs), uptime()), flush=True)
    return 1 if failed else 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--cycles', type=int, default=5000)
    parser.add_argument('--duration', type=float, default=5.0,
                        help='simulated seconds of each rig run')
    parser.add_argument('--rate', type=float, default=1000.0,
                        help='the realtime runs\' sample rate [Hz]')
    parser.add_argument('--repeat', type=int, default=1, help='realtime runs of each kind')
    parser.add_argument('--no-rig', action='store_true', help='only the bridge\'s cost')
    parser.add_argument('--accept', action='store_true',
                        help='the acceptance check of the composed bridge instead (30 s runs '
                        'unless --duration is given, two in a row): exit 0 if it passes')
    parser.add_argument('--realtime-priority', type=int, default=0, metavar='P',
                        help='--accept: rig --realtime-priority P for the realtime runs')
    args = parser.parse_args(argv)
    if args.accept:
        given = any(a.startswith('--duration') for a in (argv or sys.argv[1:]))
        return accept(args.duration if given else 30.0, 2, args.rate, args.realtime_priority)
    if args.realtime_priority:
        parser.error('--realtime-priority is for --accept')
    print('uptime: %s' % uptime(), flush=True)
    bridge_cost(args.cycles)
    if not args.no_rig:
        lockstep_beside_direct(min(args.duration, 3.0))
        measure(args.duration, args.repeat, args.rate)
    print('uptime: %s' % uptime(), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
