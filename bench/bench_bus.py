"""The field bus's costs: prints figures, asserts nothing (docs/performance.md).

- the bridge's cost per sample: the master's SYNC, collect, readings,
  judgement and RPDOs for six drives on two ``s63hub`` buses, against the
  plant's drives served by another process (a round trip per cycle), and the
  CPU time each side spends per sample (the master's includes its notifier
  thread);
- the rig over the bus beside the DDS-only rig, in one sitting: lockstep
  samples per second and the loop latency (leg_lengths stamp to the
  answering force: the plant's in the direct rig, the bridge's over the bus),
  and realtime missed cycles at ``--rate``.

    bench_bus.py [--cycles N] [--duration S] [--rate HZ] [--no-rig]
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import textwrap
import time
import uuid

import numpy as np
from bench_loop import private_domain

from stewart63_ros.canbus.master import Master
from stewart63_ros.core.bus import load_bus_config
from stewart63_ros.paths import default_params_path
from stewart63_ros.tools.rig import Rig

DEVICES = textwrap.dedent('''
    import sys, time
    import numpy as np
    from stewart63_ros.core.bus import load_bus_config
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


def rig_runs(duration: float, rate: float) -> None:
    sys.path.insert(0, str(__import__('pathlib').Path(__file__).parent))

    def one(mode, bus, hz):
        log_dir = tempfile.mkdtemp(prefix='bench_bus_')
        extra = {n: {'sensor_rate': hz} for n in ('plant', 'canopen_bridge')} \
            if hz != 1000.0 else {}
        rig = Rig(default_params_path(), mode, duration, log_dir=log_dir, bus=bus,
                  extra_params=extra)
        try:
            rig.start()
            ok = rig.wait(timeout=120 + 60 * duration)
        finally:
            rig.stop()
        plant = rig.summary()
        bridge = rig.summary('canopen_bridge') if bus else None
        if not ok or plant is None:
            print('%s %s run failed; logs in %s' % (mode, bus or 'dds', log_dir))
            return
        latency = (bridge or plant)['loop_latency']
        missed = (bridge or plant)['missed_cycles']
        print('%-9s %-8s %4.0f Hz: %6.0f samples/s, latency p50 %.3f ms, p99 %.3f ms, '
              'missed cycles %d of %d' % (mode, bus or 'dds only', hz,
                                          plant['samples'] / plant['wall_time_s'],
                                          latency.get('p50_ms', float('nan')),
                                          latency.get('p99_ms', float('nan')),
                                          missed, plant['samples']), flush=True)

    with private_domain():
        for bus in (None, 'canopen'):
            one('lockstep', bus, 1000.0)
        for bus in (None, 'canopen'):
            one('realtime', bus, rate)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--cycles', type=int, default=5000)
    parser.add_argument('--duration', type=float, default=3.0)
    parser.add_argument('--rate', type=float, default=200.0,
                        help='the realtime runs\' sample rate [Hz]')
    parser.add_argument('--no-rig', action='store_true', help='only the bridge\'s cost')
    args = parser.parse_args(argv)
    bridge_cost(args.cycles)
    if not args.no_rig:
        rig_runs(args.duration, args.rate)
    return 0


if __name__ == '__main__':
    sys.exit(main())
