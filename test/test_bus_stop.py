"""``canopen_bridge`` leaves the drives safe on every way out (docs/bus.md, "Stopping").

The bridge runs as its own process, as on a machine; the drives stand on the
bus in this process, served in threads: on bus a three strict CiA 402 drives
the bridge's authors did not write (test/cia402_drive.py, a third-party
EDS), on bus b three of the plant's (canbus/devices.py). A controller in
the test answers every sample with torque. After each way out (the end of
``duration``, SIGINT, SIGTERM, an exception in the loop, a lost controller
and then SIGINT) every drive must read READY TO SWITCH ON with zero target
torque and NMT pre-operational; while the controller is lost, the drives
are shut down too. And a bridge with no drive on its bus says at once what
it waits for and ends with a one-line reason.
"""
from __future__ import annotations

import dataclasses
import os
import signal
import threading
import time

import numpy as np
import pytest
from ros_harness import wait_until
from sensor_msgs.msg import JointState
from test_bus import CONFIG, channels

from stewart63_ros import topics
from stewart63_ros.core.machine.bus import OPERATION_ENABLED, READY_TO_SWITCH_ON, load_bus_config

pytestmark = [pytest.mark.dds, pytest.mark.slow]
RATE = 100.0


class Drives:
    """The plant's six drives on the bus, served in a thread."""

    def __init__(self, wall_heartbeats=False):
        from stewart63_ros.canbus.devices import DeviceSet
        #: heartbeats on the wall clock, as real drives beat (the plant's beat in run time)
        self.wall_heartbeats = wall_heartbeats
        self.sync_times = []        # time.monotonic() of each SYNC taken
        self.channels = channels()
        self.devices = DeviceSet(load_bus_config(CONFIG, channels=self.channels))
        self.lengths = np.array([1.9, 1.9, 1.6, 1.6, 1.6, 1.6])
        self.k = 0
        self.stop = False
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self):
        devices = self.devices
        started = time.monotonic()
        while not self.stop:
            if self.wall_heartbeats:
                devices.heartbeats(time.monotonic() - started)
            if devices.poll(0.002):
                devices.take_sync()
                self.sync_times.append(time.monotonic())
                if not self.wall_heartbeats:
                    devices.heartbeats(self.k / RATE)
                devices.answer_sync(self.lengths, np.zeros(6))
                self.k += 1

    def states(self):
        return [(d.drive.state, d.torque_permille, d.nmt) for d in self.devices.drives]

    def wait(self, predicate, timeout):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return True
            time.sleep(0.01)
        return predicate()

    def close(self):
        self.stop = True
        self.thread.join(5)
        self.devices.close()


SAFE = (READY_TO_SWITCH_ON, 0, 'PRE-OPERATIONAL')


@pytest.fixture
def drives(request):
    made = Drives(**getattr(request, 'param', {}))
    yield made
    made.close()


def start_bridge(ros, drives, *params, script=None):
    args = ['-p', 'bus_channels:=[%s]' % ','.join(drives.channels), '-p', 'clock_mode:=realtime',
            '-p', 'sensor_rate:=%g' % RATE, '-p', 'boot_timeout:=20.0', *params]
    if script:
        return ros.python('-c', script, '--ros-args', *args, name='canopen_bridge')
    return ros.python('-m', 'stewart63_ros.nodes.canopen_bridge', '--ros-args', *args,
                      name='canopen_bridge')


def wait_enabled(drives, proc):
    assert drives.wait(lambda: all(s[0] == OPERATION_ENABLED and s[2] == 'OPERATIONAL'
                                   for s in drives.states()) and drives.k > 5, 60), \
        (drives.states(), proc.describe())


class MixedDrives:
    """Both kinds of drive on one bridge's buses: on bus a three strict CiA 402
    drives on raw frames with a third-party EDS (test/cia402_drive.py, a
    device the bridge's authors did not write), on bus b three of the
    plant's drives (canbus/devices.py, the rig's stand-in). Every way out is
    judged on both at once; one set serves the module's bridges in turn (each
    bridge resets and brings them up again, as after any stop)."""

    def __init__(self, tmp_path):
        import can
        from cia402_drive import DriveRack
        from test_bus_drives import EDS

        from stewart63_ros.canbus.devices import DeviceSet
        self.channels = channels()
        self.config_path = tmp_path / 'canopen.yaml'
        self.config_path.write_text('\n'.join(     # the legs of bus a: the strict drive's EDS
            line.replace('eds: stewart63_drive.eds', 'eds: %s' % (
                EDS if 'bus: a,' in line else CONFIG.with_name('stewart63_drive.eds')))
            for line in CONFIG.read_text().splitlines()))
        config = load_bus_config(self.config_path, channels=self.channels)
        self.legs = config.legs
        self.rack = DriveRack(can.Bus(interface='s63hub', channel=self.channels[0]),
                              {leg.node_id: {} for leg in config.legs_on('a')}, EDS)
        self.strict = [self.rack.drives[leg.node_id] for leg in config.legs_on('a')]
        for drive, leg in zip(self.strict, config.legs_on('a')):
            drive.position = leg.counts(1.6)
        self.devices = DeviceSet(dataclasses.replace(
            config, buses=config.buses[1:], legs=tuple(config.legs_on('b'))), booted=range(3))
        self.lengths = np.array([1.6] * 6)
        self.torque_seen = [False] * 6      # a target torque other than 0, per leg
        self.stop = False
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self):
        devices = self.devices
        started = time.monotonic()
        while not self.stop:
            devices.heartbeats(time.monotonic() - started)   # on the wall clock, as drives beat
            if devices.poll(0.002):
                devices.take_sync()
                devices.answer_sync(self.lengths, np.zeros(6))
                for leg, (_, torque, _) in enumerate(self.states()):
                    self.torque_seen[leg] |= torque != 0

    def states(self):
        """(CiA 402 state, target torque [per mille], NMT state) of each leg."""
        with self.rack.lock:
            strict = [(d.state, d.values[(0x6071, 0)], d.nmt) for d in self.strict]
        return strict + [(d.drive.state, d.torque_permille, d.nmt)
                         for d in self.devices.drives]

    def torques(self):
        """What each drive applies [per mille]: 0x6077 of the strict ones."""
        with self.rack.lock:
            strict = [d.values[(0x6077, 0)] for d in self.strict]
        return strict + [d.torque_permille for d in self.devices.drives]

    def close(self):
        self.stop = True
        self.thread.join(5)
        self.rack.stop()
        self.devices.close()
        self.rack.close()


@pytest.fixture(scope='module')
def mixed_drives(tmp_path_factory):
    made = MixedDrives(tmp_path_factory.mktemp('mixed_drives'))
    yield made
    made.close()


# The exception: the loop's publish raises once torque has gone out for 20 samples.
RAISES = '''
import sys
from stewart63_ros.nodes import canopen_bridge as b
publish = b.BridgeNode.publish
def failing(self, ns):
    self.with_torque = getattr(self, 'with_torque', 0) + (self.force is not None)
    if self.with_torque > 20:
        raise RuntimeError('a bug in the loop')
    return publish(self, ns)
b.BridgeNode.publish = failing
b.main(['canopen_bridge'] + sys.argv[1:])
'''
FORCE = 50.0        # N: what the test's controller answers, while it answers


@pytest.mark.parametrize('way', ['duration', 'SIGINT', 'SIGTERM', 'exception',
                                 'lost controller'])
def test_every_way_out_leaves_strict_and_plant_drives_disabled_with_zero_torque(
        ros, mixed_drives, way):
    drives = mixed_drives
    drives.torque_seen[:] = [False] * 6
    # the controller, answering every sample with FORCE on each leg; matched
    # before the bridge's first sample (lengths_subscribers)
    node = ros.node('controller')
    pub = node.create_publisher(JointState, topics.LEG_FORCES, topics.STREAM_PUB)
    answering = [True]

    def answer(msg):
        if answering[0]:
            pub.publish(JointState(header=msg.header, name=list(msg.name), effort=[FORCE] * 6))
    node.create_subscription(JointState, topics.LEG_LENGTHS, answer, topics.LATEST_SUB)
    params = ['-p', 'bus_config:=%s' % drives.config_path, '-p', 'lengths_subscribers:=1',
              '-p', 'discovery_settle:=0.0']
    if way == 'duration':
        params += ['-p', 'duration:=1.0']
    if way == 'lost controller':
        params += ['-p', 'force_timeout:=0.3']
    proc = start_bridge(ros, drives, *params, script=RAISES if way == 'exception' else None)
    # torque on every drive first: the way out must take it away
    assert ros.spin_until(lambda: all(drives.torque_seen) or proc.popen.poll() is not None,
                          60), (drives.states(), proc.describe())
    assert all(drives.torque_seen), (drives.states(), proc.describe())
    if way.startswith('SIG'):
        proc.popen.send_signal(getattr(signal, way))
    elif way == 'lost controller':
        answering[0] = False
        # shut down while the bridge runs on: no torque, NMT still operational
        assert ros.spin_until(lambda: all(s[:2] == (READY_TO_SWITCH_ON, 0)
                                          for s in drives.states()), 10), drives.states()
        assert drives.torques() == [0] * 6
        assert [s[2] for s in drives.states()] == ['OPERATIONAL'] * 6
        assert 'controller lost' in proc.stderr() + proc.stdout()
        drives.torque_seen[:] = [False] * 6
        answering[0] = True         # back: enabled again, torque again
        assert ros.spin_until(lambda: all(drives.torque_seen), 10), drives.states()
        proc.popen.send_signal(signal.SIGINT)
    code = ros.spin_until(lambda: proc.popen.poll() is not None, 60) and proc.wait(1)
    assert code == (1 if way == 'exception' else 0), proc.describe()
    assert drives.states() == [SAFE] * 6, (drives.states(), proc.describe())
    assert drives.torques() == [0] * 6
    log = proc.stderr() + proc.stdout()
    assert 'safe stop: zero torque, shutdown, NMT pre-operational: %s' % ', '.join(
        '%s: ready to switch on' % leg.name for leg in drives.legs) in log, proc.describe()


def test_no_drive_on_the_bus_is_a_one_line_error_saying_what_it_waited_for(ros):
    names = channels()
    started = time.monotonic()
    proc = ros.python('-m', 'stewart63_ros.nodes.canopen_bridge', '--ros-args', '-p',
                      'bus_channels:=[%s]' % ','.join(names), '-p', 'boot_timeout:=2.0',
                      name='canopen_bridge')
    assert proc.wait(60) == 1, proc.describe()
    took = time.monotonic() - started
    err = proc.stderr()
    assert 'waiting up to 2 s (boot_timeout) for the boot-up of nodes 1, 2, 3 on bus a ' \
        '(s63hub channel %s)' % names[0] in err, err
    lines = [line for line in err.splitlines() if line.startswith('canopen_bridge: error:')]
    assert lines == ['canopen_bridge: error: no drive answered: no boot-up within 2 s '
                     '(boot_timeout) of an NMT reset from nodes 1, 2, 3 on bus a (s63hub '
                     'channel %s); nodes 4, 5, 6 on bus b (s63hub channel %s): drives '
                     'powered, bus wired and terminated, bitrate right?' % tuple(names)], err
    print('\nno drive: exit 1 after %.1f s (boot_timeout 2 s, start-up included)' % took)


@pytest.mark.parametrize('drives', [{'wall_heartbeats': True}], indirect=True)
def test_a_stalled_bridge_skips_the_syncs_it_missed_sends_no_burst_and_loses_no_heartbeat(
        ros, drives):
    # The bridge process stopped for 0.6 s (SIGSTOP: a machine that stalls
    # it), while the drives beat on the wall clock (100 ms: lost after 300 ms).
    import json
    summary = ros.log_dir / 'bridge_summary.json'
    # (no controller: the SYNC clock starts after discovery_timeout, 20 s by default)
    proc = start_bridge(ros, drives, '-p', 'summary_file:=%s' % summary,
                        '-p', 'discovery_timeout:=1.0')
    wait_enabled(drives, proc)
    time.sleep(0.5)
    before = len(drives.sync_times)
    os.killpg(proc.pid, signal.SIGSTOP)     # its group: the interpreter may be a child
    time.sleep(0.6)
    os.killpg(proc.pid, signal.SIGCONT)
    resumed_at = time.monotonic()
    # 60 SYNCs after the stall to judge the pace by (0.6 s at 100 Hz; a
    # loaded machine takes longer, and the bridge rightly skips the SYNCs it
    # was late for: a fixed second held only 46 at -n 3)
    assert wait_until(lambda: sum(t > resumed_at for t in drives.sync_times) >= 60, 30), (
        proc.describe())
    after = drives.sync_times[before - 1:]       # from the last SYNC before the stall
    proc.popen.send_signal(signal.SIGINT)
    assert proc.wait(60) == 0, proc.describe()
    gaps = np.diff(after)
    stall = int(np.argmax(gaps))
    assert gaps[stall] >= 0.5, gaps
    # after the stall, one SYNC a period, none sent to catch up: at most a
    # period's worth in any 50 ms (a catch-up would send 60 at once); the
    # drives here take them every 2 ms, so two may come close together
    resumed = np.array(after[stall + 1:])
    assert len(resumed) > 50, resumed
    most = max(int(np.sum((resumed >= t) & (resumed < t + 0.05))) for t in resumed)
    assert most <= 0.05 * RATE + 2, np.diff(resumed)[:20]
    log = proc.stderr() + proc.stdout()
    assert 'heartbeat lost' not in log, log
    assert 'SYNCs skipped' in log, log
    done = json.loads(summary.read_text())
    assert done['syncs_skipped'] >= 40, done
    print('\nstalled 0.6 s: %d SYNCs skipped, then at most %d SYNCs in 50 ms'
          % (done['syncs_skipped'], most))


def test_the_rig_summary_says_the_drives_were_left_safe_or_names_those_that_were_not(capsys):
    from stewart63_ros.tools.rig_summary import print_drives_at_stop
    safe = {'leg_%d' % i: READY_TO_SWITCH_ON for i in range(1, 7)}
    print_drives_at_stop({'drives_at_stop': safe})
    out, err = capsys.readouterr()
    assert out == ('  drives left safe: leg_1, leg_2, leg_3, leg_4, leg_5, leg_6 ready to '
                   'switch on, zero torque, NMT pre-operational\n') and err == ''
    print_drives_at_stop({'drives_at_stop': dict(
        safe, leg_3='not confirmed (last seen OPERATION ENABLED)')})
    out, err = capsys.readouterr()
    assert out == '' and err == ('rig: error: the drives were NOT all left safe: leg_3: not '
                                 'confirmed (last seen OPERATION ENABLED)\n')
    print_drives_at_stop(None)          # killed: no summary
    assert 'the drives were NOT confirmed safe' in capsys.readouterr().err
