"""``rig --supervisor --bus canopen``: the supervisor between the controller
and the bridge, the plant standing in for the drives on the bus (``s63hub``).

Two short lockstep rigs:

- homing over the bus: the plant's sensors carry hidden offsets; the
  supervisor homes the legs against their upper end stops and writes what it
  found to the drives' home offset 0x607C (through the bridge's
  ``homed_offset``). The offsets are recovered within the sensor's
  resolution, and from then on the drives' positions are the true lengths.
  Then the supervisor is killed while it forwards the controller's
  (non-zero) forces: the bridge sends zero torque from exactly
  ``stale_forces_ms`` after its last answer, and the drives apply none.
- ``rig --supervisor --bus canopen`` (the command line): a bus fault (a
  drive's TPDO missing) trips the supervisor on staleness of ``leg_lengths``
  on the sample the core's closed loop gives for the same missing reading.

Every wait is bounded; every process is stopped by its pid.
"""
from __future__ import annotations

import json
import os
import re
import signal
from pathlib import Path

import numpy as np
import pytest
from ros_harness import logs_of, rig_env
from scipy.spatial.transform import Rotation

from stewart63_ros.core.machine.bus import load_bus_config
from stewart63_ros.core.machine.supervisor import run_supervised, supervisor_from_params
from stewart63_ros.core.mechanics.fk import ForwardKinematics
from stewart63_ros.core.mechanics.kinematics import leg_lengths
from stewart63_ros.core.mechanics.rotation import euler_from_matrix, rotation_from_euler
from stewart63_ros.core.plumbing.params import load_mechanism, load_setup
from stewart63_ros.tools.rig_process import Rig

pytestmark = [pytest.mark.dds, pytest.mark.slow]
REPO = Path(__file__).resolve().parents[1]
PARAMS = REPO / 'config' / 'stewart63.yaml'
RATE = 1000.0
START_TIMEOUT = 150.0
NODES = ('plant', 'controller')
RESOLUTION = 1e-5           # the plant's sensor_resolution [m] (the drives count 1 µm)
HIDDEN = [0.003, -0.002, 0.005, 0.0, -0.004, 0.0012]


def homing_start() -> dict:
    """Every leg 2.2 m long (the platform tilted 27°, 1.74 m up): 10 cm from
    the upper stops, so the homing takes 1.96 s of simulated time."""
    setup = load_setup(PARAMS)
    mech, task = setup.mechanism, setup.task
    pose = ForwardKinematics(mech, start=(task.initial_position, task.initial_rotation)).all_modes(
        np.full(6, 2.2))[0]
    position = pose.position.round(3).tolist()
    euler = np.round(euler_from_matrix(pose.rotation), 3).tolist()
    setpoint = leg_lengths(mech, np.array(position), rotation_from_euler(np.array(euler)))
    return {'initial_position': position, 'initial_orientation': euler,
            'initial_velocity': [0.0] * 3, 'initial_orientation_rate': [0.0] * 3,
            'setpoint_lengths': setpoint.round(4).tolist()}


def test_homing_over_the_bus_sets_the_drives_and_a_killed_supervisor_leaves_no_torque(
        ros, monkeypatch, tmp_path):
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import JointState
    from std_srvs.srv import SetBool

    from stewart63_ros import bagio
    from stewart63_ros import topics as T
    rig_env(ros, monkeypatch)
    mech = load_mechanism(PARAMS)
    node = ros.node('client')
    statuses = {'supervisor': [], 'canopen_bridge': [], 'plant': []}
    readings, truth, answers = {}, {}, []

    def on_diag(msg):
        for status in msg.status:
            name = status.name.rsplit('/', 1)[-1]
            if name in statuses:
                statuses[name].append({kv.key: kv.value for kv in status.values})
    node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, T.DIAGNOSTICS_QOS)
    node.create_subscription(JointState, '/leg_lengths', lambda m: readings.__setitem__(
        bagio.header_stamp_ns(m), np.array(m.position)), T.RECORD_SUB)
    node.create_subscription(PoseStamped, '/' + T.TRUE_POSE, lambda m: truth.__setitem__(
        bagio.header_stamp_ns(m), m.pose), T.RECORD_SUB)
    node.create_subscription(JointState, '/leg_forces', lambda m: answers.append(
        (bagio.header_stamp_ns(m), np.array(m.effort))), T.RECORD_SUB)
    extra = {'plant': dict(homing_start(), homing_offset=HIDDEN, sensor_resolution=RESOLUTION),
             'controller': homing_start(),       # (one per section: rcl refuses YAML aliases)
             'supervisor': dict(homing_start(), homing=True, homing_speed=0.2, trip_tilt=0.6,
                                pose_box=[-0.3, -0.3, 0.5, 0.3, 0.3, 1.8],
                                request_timeout=0.02),
             # the supervisor is killed: each sample then waits this for its answer
             'canopen_bridge': {'force_timeout': 0.02}}
    rig = Rig(PARAMS, mode='lockstep', duration=None, nodes=NODES, log_dir=tmp_path / 'rig',
              supervisor=True, bus='canopen', extra_params=extra)

    def last(name, key):
        return next((v[key] for v in reversed(statuses[name]) if key in v), None)

    def wait_for(condition, timeout):
        """Spin until ``condition()``, bounded; fails at once if a node died."""
        ros.spin_until(lambda: condition() or any(
            proc.poll() is not None for name, proc in rig.procs.items() if name != 'supervisor'),
            timeout)
        assert condition(), logs_of(rig.log_dir)
    try:
        rig.start()
        wait_for(lambda: last('supervisor', 'homed') == 'true', START_TIMEOUT)
        found = np.array(json.loads(last('supervisor', 'homing/offsets')))
        assert np.all(np.abs(found - HIDDEN) <= RESOLUTION), (found, HIDDEN)
        # the drives' home offsets, in counts of 1 µm, as the supervisor found them
        config_legs = load_bus_config().legs
        wait_for(lambda: last('canopen_bridge', 'home_offset_counts'), 30)
        assert json.loads(last('canopen_bridge', 'home_offset_counts')) == [
            leg.home_offset_counts(found[leg.leg]) for leg in config_legs]
        # forwarding the controller's forces; then the drives read true
        wait_for(lambda: len(answers) > 0 and np.abs(answers[-1][1]).max() > 1
                 and answers[-1][0] > 2.05e9, 60)
        homed_stamps = sorted(ns for ns in readings if ns > 1.97e9 and ns in truth)
        assert len(homed_stamps) > 50
        for ns in homed_stamps[:: 10]:
            pose = truth[ns]
            quat = [pose.orientation.x, pose.orientation.y, pose.orientation.z,
                    pose.orientation.w]
            true = leg_lengths(mech, np.array([pose.position.x, pose.position.y,
                                               pose.position.z]),
                               Rotation.from_quat(quat).as_matrix())
            assert np.abs(readings[ns] - true).max() <= RESOLUTION, (ns, readings[ns], true)
        # killed: zero torque stale_forces_ms (50 samples) after its last answer.
        # This test's own record of the answers catches up first (a loaded
        # machine's spin lagged 289 answers behind the flat-out lockstep rig,
        # and a killed publisher's undelivered answers are lost): the plant
        # paused before sample k, every earlier sample answered.
        pause = node.create_client(SetBool, '/plant/pause')

        def hold(paused: bool) -> str:
            assert ros.spin_until(pause.service_is_ready, 30)
            future = pause.call_async(SetBool.Request(data=paused))
            assert ros.spin_until(future.done, 30) and future.result().success, future.result()
            return future.result().message
        k = int(re.search(r'paused before sample (\d+)', hold(True)).group(1))
        wait_for(lambda: max(ns for ns, _ in answers) == (k - 1) * 1_000_000, 30)
        os.kill(rig.procs['supervisor'].pid, signal.SIGKILL)
        rig.procs['supervisor'].wait(10)
        hold(False)
        wait_for(lambda: last('canopen_bridge', 'stale_force_from_sample'), 60)
        last_answer = max(ns for ns, _ in answers) // 1_000_000
        # A SIGKILL during a publish can deliver the last answer to one reader
        # (the bridge, this test) and not to the other: each gets its own copy.
        stale_from = int(last('canopen_bridge', 'stale_force_from_sample'))
        assert abs(stale_from - 51 - last_answer) <= 1, (stale_from, last_answer)
        wait_for(lambda: statuses['plant'] and json.loads(
            statuses['plant'][-1].get('bus_forces', '[1]')) == [0.0] * 6, 30)
    finally:
        codes = rig.stop()
    assert codes['supervisor'] == -signal.SIGKILL and codes['plant'] == 0 \
        and codes['controller'] == 0 and codes['canopen_bridge'] == 0, (codes,
                                                                       logs_of(rig.log_dir))
    # stopped by the rig (the bridge before the plant): the drives confirmed the safe stop
    assert rig.summary('canopen_bridge')['drives_at_stop'] == {
        leg.name: 'READY TO SWITCH ON' for leg in config_legs}, logs_of(rig.log_dir)


def test_rig_cli_runs_supervisor_on_the_bus_and_a_bus_fault_trips_on_stale_lengths(
        ros, tmp_path):
    import subprocess

    import yaml
    from ros_harness import PYTHON, child_env
    duration, fault = 0.3, 'bus_tpdo_missing:leg_3@0.1-0.13'
    # The bridge's own ERROR would trip too (diagnostics_error), on whichever
    # sample it reaches the supervisor: off here, to see the staleness limit
    # trip on its sample.
    params = yaml.safe_load(PARAMS.read_text())
    params['/**/supervisor'] = {'ros__parameters': {'trip_on_diagnostics': False}}
    params['/**/canopen_bridge'] = {'ros__parameters': {'bus_timeout': 0.05}}
    (tmp_path / 'params.yaml').write_text(yaml.safe_dump(params))
    done = subprocess.run([PYTHON, '-m', 'stewart63_ros.tools.rig', '--params',
                           str(tmp_path / 'params.yaml'), '--mode', 'lockstep', '--duration',
                           str(duration), '--nodes', ','.join(NODES), '--supervisor', '--bus',
                           'canopen', '--fault', fault, '--log-dir', str(tmp_path / 'rig')],
                          env=child_env(ros.domain_id), capture_output=True, text=True,
                          timeout=START_TIMEOUT)
    assert done.returncode == 0, (done.stdout, done.stderr, logs_of(tmp_path / 'rig'))
    assert 'supervisor: 1 trip' in done.stdout and 'lengths_stale' in done.stdout, done.stdout
    # the end of the run: the bridge's safe stop confirmed by the drives (the plant's)
    assert 'drives left safe: leg_1, leg_2, leg_3, leg_4, leg_5, leg_6 ready to switch on' \
        in done.stdout, (done.stdout, done.stderr)
    # the core, with that leg's reading missing over the same samples
    setup = load_setup(PARAMS)
    core_params = setup.to_params()
    core = supervisor_from_params(setup, core_params, RATE)
    run_supervised(setup, core, duration, RATE, ['sensor_dropout:leg_3@0.1-0.13'])
    assert core.trip.cause == 'lengths_stale'
    summary = json.loads((tmp_path / 'rig' / 'supervisor_summary.json').read_text())
    assert [(t['cause'], t['sample'], t['latency_samples']) for t in summary['trips']] == [
        ('lengths_stale', core.trip.sample_ns // 1_000_000, 0)], summary['trips']


def test_rig_cli_realtime_supervised_bus_answers_sync_0_and_prints_the_bus_rate(ros, tmp_path):
    # A file that sets the plant's rate only (200 Hz: what this shared machine
    # carries in realtime, docs/bus.md): the bus runs at it too. The drives'
    # start-up (a reset that reaches them after their power-on boot-up) must
    # not cost SYNC 0's TPDO, and an isolated late TPDO must not trip.
    import subprocess

    import yaml
    from ros_harness import PYTHON, child_env
    params = yaml.safe_load(PARAMS.read_text())
    params['/**/plant']['ros__parameters']['sensor_rate'] = 200.0
    # The paper's gains at 200 Hz with a realtime loop's delays overshoot the
    # packaged 0.5 m/s leg-speed limit now and then (0.504 m/s seen in CI): a
    # lab's limit, the drives' rated 1.5 m/s, as test_supervisor_dds does.
    # A stall of this shared machine (a controller kept off the CPU for
    # 90 ms, seen beside a busy core) is not what this test is about: its
    # staleness limits are a second, and a stall long enough to lose the
    # TPDOs for tpdo_missing_error_ms trips (allowed below).
    params['/**/supervisor'] = {'ros__parameters': {
        'trip_leg_speed': 1.5, 'stale_forces_ms': 1000.0, 'stale_lengths_ms': 1000.0}}
    params['/**/plant']['ros__parameters']['force_stale_ms'] = 1000.0
    (tmp_path / 'params.yaml').write_text(yaml.safe_dump(params))
    done = subprocess.run([PYTHON, '-m', 'stewart63_ros.tools.rig', '--params',
                           str(tmp_path / 'params.yaml'), '--mode', 'realtime', '--duration',
                           '1', '--nodes', ','.join(NODES), '--supervisor', '--bus', 'canopen',
                           '--log-dir', str(tmp_path / 'rig')],
                          env=child_env(ros.domain_id), capture_output=True, text=True,
                          timeout=START_TIMEOUT)
    logs = logs_of(tmp_path / 'rig')
    assert done.returncode == 0, (done.stdout, done.stderr, logs)
    assert '(realtime, 200 Hz)' in done.stdout and 'stopped early' not in done.stdout, \
        done.stdout
    assert 'canopen_bridge: 200 Hz, 201 cycles' in done.stdout, done.stdout
    bridge_log = (tmp_path / 'rig' / 'canopen_bridge.log').read_text()
    # No trip, unless the machine stalled the drives for tpdo_missing_error_ms
    # in a row (a persistent loss: ERROR by design), never for an isolated miss.
    assert 'supervisor: no trip' in done.stdout or 'TPDO missing since' in bridge_log, \
        (done.stdout, logs)
    assert 'SYNC 0 ' not in bridge_log and 'SYNC 0)' not in bridge_log, bridge_log
    bridge = json.loads((tmp_path / 'rig' / 'canopen_bridge_summary.json').read_text())
    assert bridge['rate_hz'] == 200.0 and bridge['cycles'] == 201, bridge
    # the supervisor counts the samples at the plant's rate (the file gives it none)
    supervisor = json.loads((tmp_path / 'rig' / 'supervisor_summary.json').read_text())
    assert all(t['sample'] <= 200 for t in supervisor['trips']), supervisor['trips']
    overlay = yaml.safe_load((tmp_path / 'rig' / 'rig_params.yaml').read_text())
    assert overlay['/**/supervisor']['ros__parameters']['sensor_rate'] == 200.0
