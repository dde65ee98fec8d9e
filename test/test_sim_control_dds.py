"""Faults and simulation control on the running rig, over DDS (separate processes).

- one lockstep rig run with a fault of every kind at different legs and
  times, recorded: the bag equals ``sim``'s faulted run sample for sample
  (what the sensors said, the forces, the ground truth), the stuck leg holds
  in the bag while the true one moves, the dropped-out leg is NaN, the
  plant's statuses in the bag are WARN naming the active faults, and the
  summary and ``plot`` give each fault's interval;
- a client node pauses a lockstep rig (no sample comes while paused), steps
  it by ``step_count`` samples, changes its ``faults`` at run time (a bad
  list refused with the reason, nothing changed), resets it (a new run from
  sample 0 that controller and fk follow) and resumes it; the controller
  never reports a lost sensor;
- the same client pauses, resumes and resets a realtime rig; ``~/step`` is
  refused there;
- the example fault detector, run as the controller's law, trips on a stuck
  sensor injected with ``--fault``.

Every wait is bounded; every process is stopped by its pid (``Rig.stop``).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from ros_harness import logs_of, rig_env, run_to_end

from stewart63_ros import bagio
from stewart63_ros.bagio import header_stamp_ns as stamp_ns
from stewart63_ros.core.controllers.simulate import run_sampled
from stewart63_ros.core.plumbing.params import load_mechanism
from stewart63_ros.tools.rig_process import Rig

REPO = Path(__file__).resolve().parents[1]
PARAMS = REPO / 'config' / 'stewart63.yaml'
RATE = 1000.0
#: Bound on a rig's start-up (discovery, kernels) and on a whole run.
START_TIMEOUT = 150.0
ERROR, WARN = 2, 1
PLANT, CONTROLLER = 'stewart63/plant', 'stewart63/controller'

#: One fault of every kind, at different legs and times, within one second.
RIG_FAULTS = ['sensor_stuck:leg_2@0.1', 'sensor_bias:leg_1:0.004@0.2',
              'sensor_noise:leg_3:0.001@0.3-0.6', 'sensor_dropout:leg_5@0.4-0.45',
              'sensor_delay:leg_6:0.005@0.05', 'actuator_dead:leg_4@0.5-0.7',
              'actuator_weak:leg_6:0.5@0.6', 'actuator_stuck:leg_1@0.3-0.4',
              'actuator_saturation:all:2500@0.8']
RIG_DURATION = 1.0


@pytest.fixture(scope='module')
def mech():
    return load_mechanism(PARAMS)


def level_of(status) -> int:
    level = status.level
    return level[0] if isinstance(level, (bytes, bytearray)) else int(level)


def nan_equal(a, b, atol) -> bool:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return bool(np.all(np.isnan(a) == np.isnan(b))
                and np.all(np.abs(np.nan_to_num(a) - np.nan_to_num(b)) <= atol))


# -- every kind on the rig ---------------------------------------------------------------
def test_every_fault_kind_on_the_lockstep_rig_is_sims(setup, ros, monkeypatch, tmp_path, mech):
    from stewart63_ros.core.mechanics.dynamics import POS
    rig_env(ros, monkeypatch)
    bag = tmp_path / 'bag'
    rig = Rig(PARAMS, mode='lockstep', duration=RIG_DURATION, record=bag,
              log_dir=tmp_path / 'rig', extra_params={'plant': {'faults': RIG_FAULTS}})
    ok, codes, logs = run_to_end(rig, START_TIMEOUT)
    assert ok and codes == {'record': 0, 'controller': 0, 'fk': 0, 'plant': 0}, logs
    summary = rig.summary()
    n = int(round(RIG_DURATION * RATE)) + 1
    assert summary['samples'] == n and summary['force_timeouts'] == 0, summary

    ref = run_sampled(setup, RIG_DURATION, RATE, faults=RIG_FAULTS)
    # the summary's faults are sim's, interval for interval
    assert summary['faults'] == ref.faults
    assert [f['active_from_s'] for f in summary['faults']] == [
        0.1, 0.2, 0.3, 0.4, 0.05, 0.5, 0.6, 0.3, 0.8]
    assert [f['active_until_s'] for f in summary['faults']] == [
        None, None, 0.6, 0.45, None, 0.7, None, 0.4, None]

    lengths = {stamp_ns(m): m for _, _, m in bagio.read_messages(bag, ['leg_lengths'])}
    forces = {stamp_ns(m): m for _, _, m in bagio.read_messages(bag, ['leg_forces'])}
    truth = {stamp_ns(m): m for _, _, m in bagio.read_messages(bag, ['ground_truth/pose'])}
    assert sorted(lengths) == [k * 1_000_000 for k in range(n)]
    dropped = range(400, 450)
    # no answer to a sample with a dropped-out leg: no leg_forces of its stamp
    assert sorted(forces) == [k * 1_000_000 for k in range(n) if k not in dropped]
    for k in range(n):
        s = k * 1_000_000
        sensed = np.concatenate([lengths[s].position, lengths[s].velocity])
        assert nan_equal(sensed, ref.measured[k], 1e-9), (k, sensed, ref.measured[k])
        if s in forces:
            assert np.max(np.abs(np.asarray(forces[s].effort) - ref.forces[k])) <= 1e-5, k
        p = truth[s].pose.position
        assert np.max(np.abs(np.array([p.x, p.y, p.z]) - ref.states[k, POS])) <= 1e-9, k
    # what the bag shows: leg 2's sensor holds from 0.1 s, leg 5 has no reading 0.4-0.45 s
    held = [lengths[k * 1_000_000].position[1] for k in range(100, n)]
    assert len(set(held)) == 1
    assert all(np.isnan(lengths[k * 1_000_000].position[4]) for k in dropped)

    # the plant's statuses in the bag: WARN naming the active faults, each fault's state
    statuses = [st for _, _, msg in bagio.read_messages(bag, ['/diagnostics'])
                for st in msg.status if st.name == PLANT]
    warned = [st.message for st in statuses if level_of(st) == WARN
              and st.message.startswith('faults active:')]
    assert any('actuator_dead:leg_4@0.5-0.7 (since 0.5 s)' in m for m in warned), warned
    last = {kv.key: kv.value for kv in statuses[-1].values}
    assert last['fault: actuator_dead:leg_4@0.5-0.7'] == 'ended: active 0.500000-0.700000 s'
    assert last['fault: sensor_stuck:leg_2@0.1'] == 'active since 0.100000 s'
    from stewart63_ros.tools.plot import load_faults, main
    shaded = {f['fault']: (f['active_from_s'], f['active_until_s']) for f in load_faults(bag)}
    assert shaded == {f['fault']: (f['active_from_s'], f['active_until_s'])
                      for f in ref.faults}
    assert main([str(bag), '--out', str(tmp_path / 'bag.png')]) == 0


# -- the test's client of the plant's services ---------------------------------------------
class Client:
    """Subscriptions to the rig's samples, forces, poses and statuses; the
    plant's services and parameters."""

    def __init__(self, ros):
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from rcl_interfaces.srv import SetParameters
        from sensor_msgs.msg import JointState
        from std_srvs.srv import SetBool, Trigger

        from stewart63_ros import topics as T
        self.ros = ros
        self.node = node = ros.node('client')
        self.samples, self.forces, self.poses = [], [], []
        self.statuses = []          # (level, message, values) of the plant
        self.controller_levels = []
        node.create_subscription(JointState, '/leg_lengths',
                                 lambda m: self.samples.append(stamp_ns(m)), T.RECORD_SUB)
        node.create_subscription(JointState, '/leg_forces',
                                 lambda m: self.forces.append(stamp_ns(m)), T.RECORD_SUB)
        node.create_subscription(PoseStamped, '/platform_pose',
                                 lambda m: self.poses.append(stamp_ns(m)), T.RECORD_SUB)
        node.create_subscription(DiagnosticArray, '/diagnostics', self.on_diag,
                                 T.DIAGNOSTICS_QOS)
        self.pause = node.create_client(SetBool, '/plant/pause')
        self.step = node.create_client(Trigger, '/plant/step')
        self.reset = node.create_client(Trigger, '/plant/reset')
        self.params = node.create_client(SetParameters, '/plant/set_parameters')
        self.SetBool, self.Trigger = SetBool, Trigger

    def on_diag(self, msg):
        for st in msg.status:
            values = {kv.key: kv.value for kv in st.values}
            if st.name == PLANT:
                self.statuses.append((level_of(st), st.message, values))
            elif st.name == CONTROLLER:
                self.controller_levels.append((level_of(st), st.message))

    def wait_ready(self, rig):
        for client in (self.pause, self.step, self.reset, self.params):
            assert client.wait_for_service(timeout_sec=START_TIMEOUT), logs_of(rig.log_dir)

    def call(self, client, request):
        future = client.call_async(request)
        assert self.ros.spin_until(future.done, 30), 'no answer from %s' % client.srv_name
        return future.result()

    def set_pause(self, on: bool):
        return self.call(self.pause, self.SetBool.Request(data=on))

    def trigger(self, client):
        return self.call(client, self.Trigger.Request())

    def set_param(self, name, value):
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter
        request = SetParameters.Request(parameters=[Parameter(name, value=value)
                                                    .to_parameter_msg()])
        result = self.call(self.params, request).results[0]
        return result.successful, result.reason

    def wait_status(self, predicate, timeout=30.0, since=None):
        """The first plant status from now on (or from index ``since``) that
        satisfies ``predicate``."""
        start = len(self.statuses) if since is None else since
        found = []

        def seen():
            found[:] = [s for s in self.statuses[start:] if predicate(s)]
            return bool(found)
        assert self.ros.spin_until(seen, timeout), self.statuses[-3:]
        return found[0]

    def wait_paused(self, sample=None):
        return self.wait_status(lambda s: s[2].get('run') == 'paused' and (
            sample is None or s[2].get('sample') == str(sample)))


def start_rig(ros, monkeypatch, tmp_path, mode, compose=False, extra=None):
    rig_env(ros, monkeypatch)
    client = Client(ros)        # before the plant: its first sample waits for us
    # compose 'bus': separate processes, the plant on the field bus (rig --bus canopen)
    bus = 'canopen' if compose == 'bus' else None
    rig = Rig(PARAMS, mode=mode, duration=None, log_dir=tmp_path / 'rig',
              compose=compose is True, extra_params=extra, bus=bus)
    rig.start()
    try:
        client.wait_ready(rig)
        assert ros.spin_until(lambda: len(client.samples) >= 10, START_TIMEOUT), logs_of(
            tmp_path / 'rig')
    except BaseException:
        rig.stop()          # a rig that did not come up: no node left running
        raise
    return rig, client


def stop_rig(rig, client):
    # Our readers go first: a stopping node waits (up to 2 s each) for readers
    # to acknowledge its last messages, and a composed rig's three nodes in
    # turn would outlast the 3.5 s a stop may take.
    for sub in list(client.node.subscriptions):
        client.node.destroy_subscription(sub)
    codes = rig.stop()
    assert set(codes.values()) == {0}, (codes, logs_of(rig.log_dir))
    # The controller took every silence for what it was: never a lost sensor.
    errors = [m for level, m in client.controller_levels if level == ERROR]
    assert errors == [], errors
    return rig.summary()


@pytest.mark.parametrize('compose', [False, True, 'bus'], ids=['processes', 'composed', 'bus'])
def test_pause_step_faults_and_reset_of_a_lockstep_rig(ros, monkeypatch, tmp_path, compose):
    rig, client = start_rig(ros, monkeypatch, tmp_path, 'lockstep', compose)
    try:
        answer = client.set_pause(True)
        assert answer.success and answer.message.startswith('paused before sample ')
        k = int(answer.message.split()[3])
        status = client.wait_paused(k)
        assert status[2]['run_number'] == '1'
        # the samples published before the pause reach us (the plant may be ahead)
        last = (k - 1) * 1_000_000
        assert ros.spin_until(lambda: client.samples[-1] == last, 30), client.samples[-1]
        n = len(client.samples)
        # Two more reports while paused (one a second): no sample came meanwhile.
        client.wait_paused(k)
        client.wait_paused(k)
        assert len(client.samples) == n
        assert client.set_pause(True).message == 'already paused before sample %d' % k

        # ~/step: step_count samples, then paused again
        assert client.set_param('step_count', 0)[0] is False
        ok, reason = client.set_param('step_count', 5)
        assert ok, reason
        answer = client.trigger(client.step)
        assert answer.success, answer.message
        assert answer.message == ('stepping 5 samples (%d to %d), then paused before sample %d'
                                  % (k, k + 4, k + 5))
        client.wait_paused(k + 5)
        stepped = [(k + i) * 1_000_000 for i in range(5)]
        assert ros.spin_until(lambda: len(client.samples) >= n + 5
                              and set(stepped) <= set(client.forces), 30), client.forces[-5:]
        assert client.samples[n:] == stepped, 'exactly step_count samples'
        assert client.forces[-5:] == stepped, 'the controller answered each'

        # faults at run time: a bad list is refused whole, nothing changes
        ok, reason = client.set_param('faults', ['sensor_bias:leg_1:0.01', 'sensor_stuck:leg_8'])
        assert not ok and "bad fault 'sensor_stuck:leg_8': unknown leg 'leg_8'" in reason
        status = client.wait_paused(k + 5)
        assert not [key for key in status[2] if key.startswith('fault: ')]
        # a fault whose times are already past would never act: refused with the reason
        ok, reason = client.set_param('faults', ['actuator_dead:leg_3@0-0.001'])
        assert not ok and "'actuator_dead:leg_3@0-0.001' ends at 0.001 s" in reason, reason
        assert 'would never act' in reason, reason
        ok, reason = client.set_param('faults', ['sensor_bias:leg_1:0.01',
                                                 'actuator_dead:leg_2@0.001'])
        assert ok, reason
        assert client.trigger(client.step).success
        status = client.wait_paused(k + 10)
        t0 = '%.6f' % ((k + 5) / RATE)
        assert status[2]['fault: sensor_bias:leg_1:0.01'] == 'active since %s s' % t0
        assert status[0] == WARN and status[1].startswith('faults active: ')

        # ~/reset while paused: a new run at sample 0, still paused
        since = len(client.statuses)
        answer = client.trigger(client.reset)
        assert answer.success, answer.message
        assert answer.message.startswith('resetting after sample %d: run 2 ' % (k + 9))
        # A second reset while the first is pending (its 1 s quiet, which
        # began as the first was answered) is refused.
        run_3 = 'resetting before the first sample of run 2: run 3 starts'
        again = client.trigger(client.reset)
        if again.success:
            # A loaded machine answered it after the quiet: run 2 had begun,
            # paused before its first sample, and this is the reset below.
            assert again.message.startswith(run_3), again.message
        else:
            assert again.message == (
                'a reset is already pending (run 2 starts after the quiet)'), again
            client.wait_status(lambda s: s[2].get('run') == 'reset', since=since)
            status = client.wait_paused(0)
            assert status[2]['run_number'] == '2' and status[2]['resets'] == '1'
            assert status[2]['fault: sensor_bias:leg_1:0.01'] == 'scheduled from 0 s'
            # a reset before the new run's first sample says so (not "after sample -1")
            answer = client.trigger(client.reset)
            assert answer.success and answer.message.startswith(run_3), answer.message
        status = client.wait_status(lambda s: s[2].get('run') == 'paused'
                                    and s[2].get('run_number') == '3')
        assert status[2]['sample'] == '0' and status[2]['resets'] == '2'
        poses, forces = len(client.poses), len(client.forces)
        assert client.set_pause(False).success
        # The new run: stamps from 0 again, answered by the controller, posed by fk.
        # (From the unpause on: run 1's first answer may have gone out before
        # this client, which the rig does not name, was matched.)
        assert ros.spin_until(lambda: 0 in client.forces[forces:], 30), client.forces[-3:]
        assert ros.spin_until(lambda: 0 in client.poses[poses:], 30)
        client.wait_status(lambda s: s[2].get('run') == 'running' and s[2].get(
            'fault: sensor_bias:leg_1:0.01') == 'active since 0.000000 s')
        # ['']: no faults (a string list, as `ros2 param set /plant faults "['']"` sends)
        ok, reason = client.set_param('faults', [''])
        assert ok, reason
        status = client.wait_status(lambda s: s[0] != WARN)
        assert status[2]['fault: sensor_bias:leg_1:0.01'].endswith(', removed')
        ok, reason = client.set_param('faults', [True])      # not a string list
        assert not ok and 'Wrong parameter type' in reason, reason     # rclpy's own check
    finally:
        summary = stop_rig(rig, client)
    assert summary['resets'] == 2 and summary['run_number'] == 3, summary
    runs = [(f['fault'], f['run']) for f in summary['faults']]
    # (run 2 published no sample: its faults never acted)
    assert runs == [('sensor_bias:leg_1:0.01', 1), ('actuator_dead:leg_2@0.001', 1),
                    ('sensor_bias:leg_1:0.01', 3), ('actuator_dead:leg_2@0.001', 3)], runs
    # run 1's faults ended with it, after its last sample (k + 9): not "to the end"
    assert [(f['state'], f['active_from_s'], f['active_until_s'])
            for f in summary['faults'][:2]] == [('ended', (k + 5) / RATE, (k + 10) / RATE)] * 2


def test_pause_and_reset_of_a_realtime_rig(ros, monkeypatch, tmp_path):
    # A watchdog of 0.5 s, not 0.1 s: a loaded machine's hiccup is not what this
    # test is about, and the pause (two reports, 2 s) and the reset's quiet (1 s)
    # still outlast it.
    rig, client = start_rig(ros, monkeypatch, tmp_path, 'realtime',
                            extra={'controller': {'watchdog_timeout': 0.5}})
    try:
        answer = client.trigger(client.step)
        assert not answer.success and 'needs clock_mode lockstep' in answer.message
        assert client.set_pause(True).success
        status = client.wait_paused()
        k = int(status[2]['sample'])
        client.wait_paused(k)           # a second report: the samples in flight are in
        n = len(client.samples)
        client.wait_paused(k)           # and a third: more than the watchdog's 0.1 s
        assert len(client.samples) == n
        paused_at = client.samples[-1]
        assert client.set_pause(False).success
        assert ros.spin_until(lambda: len(client.samples) > n + 100, 30)
        # Stamps go on from the present (wall time): the pause is a gap in them.
        gap = client.samples[n] - paused_at
        assert gap > 1e9, gap
        # (wall-time stamps: float seconds since 1970, exact to a few hundred ns)
        assert np.all(np.abs(np.diff(client.samples[n:n + 100]) - 1_000_000) < 1000)
        answer = client.trigger(client.reset)
        assert answer.success
        status = client.wait_status(lambda s: s[2].get('run_number') == '2'
                                    and s[2].get('run') == 'running')
        m = len(client.samples)
        assert ros.spin_until(lambda: len(client.samples) > m + 100, 30)
    finally:
        summary = stop_rig(rig, client)
    assert summary['resets'] == 1
    log = (rig.log_dir / 'controller.log').read_text()
    assert 'the plant paused its run' in log, log[-2000:]


# -- the example detector on the rig ----------------------------------------------------------
def test_the_example_fault_detector_trips_on_the_rig(setup, ros, monkeypatch, tmp_path):
    rig_env(ros, monkeypatch)
    rig = Rig(PARAMS, mode='lockstep', duration=0.3, log_dir=tmp_path / 'rig',
              extra_params={'controller': {
                  'control_law': 'stewart63_ros.examples.fault_detector:CheckedPD'},
                  # no answers after the trip: do not wait a second for each
                  'plant': {'faults': ['sensor_stuck:leg_2@0.1'], 'force_timeout': 0.01}})
    ok, codes, logs = run_to_end(rig, START_TIMEOUT)
    assert ok and codes == {'controller': 0, 'fk': 0, 'plant': 0}, logs
    controller = json.loads((tmp_path / 'rig' / 'controller_summary.json').read_text())
    assert controller['values']['law_failures'] > 0, controller
    assert 'SensorFault: sensor fault on leg_2 at t = 0.1' in controller['status'], controller
    assert 'control law failed, forces withheld' in controller['status']
    plant = rig.summary()
    assert plant['force_timeouts'] > 0 and plant['faults'][0]['active_from_s'] == 0.1
    # It tripped where sim's run with the same law and fault trips.
    from stewart63_ros.core.controllers.laws import Controller, LawError
    with pytest.raises(LawError) as info:
        run_sampled(setup, 0.3, RATE, controller=Controller(
            setup, {}, law='stewart63_ros.examples.fault_detector:CheckedPD'),
            faults=['sensor_stuck:leg_2@0.1'])
    # (the same leg and sample; the millimetres printed may round differently)
    assert str(info.value).split('SensorFault: ')[1].split(':')[0] in controller['status']
