"""``canopen_bridge`` leaves the drives safe on every way out (docs/bus.md, "Stopping").

The bridge runs as its own process, as on a machine; the plant's drives
(canbus/devices.py) stand on the bus in this process, served in a thread (a
sample per SYNC, constant readings). After each way out (the end of
``duration``, SIGINT, SIGTERM, an exception in the loop) every drive must
read READY TO SWITCH ON with zero target torque and NMT pre-operational;
while the controller is lost, the drives are shut down too. And a bridge
with no drive on its bus says at once what it waits for and ends with a
one-line reason.
"""
from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest
from ros_harness import wait_matched
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


# The exception: the loop's publish raises at its tenth sample.
RAISES = '''
import sys
from stewart63_ros.nodes import canopen_bridge as b
publish = b.BridgeNode.publish
def failing(self, ns):
    if self.k >= 10:
        raise RuntimeError('a bug in the loop')
    return publish(self, ns)
b.BridgeNode.publish = failing
b.main(['canopen_bridge'] + sys.argv[1:])
'''


@pytest.mark.parametrize('way', ['duration', 'SIGINT', 'SIGTERM', 'exception'])
def test_every_way_out_leaves_the_drives_disabled_with_zero_torque(ros, drives, way):
    if way == 'duration':
        proc = start_bridge(ros, drives, '-p', 'duration:=0.5')
    elif way == 'exception':
        proc = start_bridge(ros, drives, script=RAISES)
    else:
        proc = start_bridge(ros, drives)
    wait_enabled(drives, proc)
    if way.startswith('SIG'):
        proc.popen.send_signal(getattr(signal, way))
    code = proc.wait(60)
    assert code == (1 if way == 'exception' else 0), proc.describe()
    assert drives.states() == [SAFE] * 6, (drives.states(), proc.describe())
    assert drives.devices.forces() == [0.0] * 6
    assert 'safe stop: zero torque, shutdown, NMT pre-operational: leg_1: ready to switch on' \
        in proc.stderr() + proc.stdout(), proc.describe()


def test_a_lost_controller_shuts_the_drives_down_until_it_answers_again(ros, drives):
    proc = start_bridge(ros, drives, '-p', 'force_timeout:=0.3')
    wait_enabled(drives, proc)
    node = ros.node('controller')
    pub = node.create_publisher(JointState, topics.LEG_FORCES, topics.STREAM_PUB)
    answering = [True]

    def answer(msg):
        if answering[0]:
            out = JointState(header=msg.header, name=list(msg.name), effort=[50.0] * 6)
            pub.publish(out)
    sub = node.create_subscription(JointState, topics.LEG_LENGTHS, answer, topics.LATEST_SUB)
    assert wait_matched(sub, 1, 30) and wait_matched(pub, 1, 30)
    assert ros.spin_until(lambda: all(f > 40 for f in drives.devices.forces()), 30), \
        (drives.devices.forces(), proc.describe())
    answering[0] = False            # the controller is lost
    assert ros.spin_until(lambda: all(s[0] == READY_TO_SWITCH_ON and s[1] == 0
                                      for s in drives.states()), 10), drives.states()
    assert drives.devices.forces() == [0.0] * 6
    assert 'controller lost' in proc.stderr() + proc.stdout()
    answering[0] = True             # back: enabled again, torque again
    assert ros.spin_until(lambda: all(f > 40 for f in drives.devices.forces()), 10), \
        drives.states()
    proc.popen.send_signal(signal.SIGINT)
    assert proc.wait(60) == 0, proc.describe()
    assert drives.states() == [SAFE] * 6


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
    proc = start_bridge(ros, drives, '-p', 'summary_file:=%s' % summary)
    wait_enabled(drives, proc)
    time.sleep(0.5)
    before = len(drives.sync_times)
    os.killpg(proc.pid, signal.SIGSTOP)     # its group: the interpreter may be a child
    time.sleep(0.6)
    os.killpg(proc.pid, signal.SIGCONT)
    time.sleep(1.0)
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
