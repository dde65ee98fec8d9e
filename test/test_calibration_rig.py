"""A calibration end to end on the lockstep rig (docs/calibration.md):
a machine built off its drawing (``calibrate machine``, played by the plant
with ``rig --plant-params``, its simulated tracker on ``tracker/pose``),
``calibrate plan`` -> ``rig --reference --record`` -> ``calibrate fit`` on
the bag; then fk restarted on the calibrated file reports the true pose.
"""
from __future__ import annotations

import json

import numpy as np

from stewart63_ros import bagio
from stewart63_ros.tools import calibrate

#: Bound on one rig run (start-up with discovery, the run, the stop) [s].
RIG_TIMEOUT = 240.0
TRACKER_NOISE = 1e-4
SENSOR_RATE = 200.0     # Hz: the rigs' (see the test)


def run_rig(ros, tmp_path, name, *args):
    """Run a lockstep rig to its end; exit 0 (with --reference: within
    rig's --tracking-bound, 5 cm and 0.1 rad). Returns its standard output."""
    proc = ros.python('-m', 'stewart63_ros.tools.rig', '--mode', 'lockstep',
                      '--log-dir', str(tmp_path / (name + '.logs')), *args, name=name)
    code = proc.wait(RIG_TIMEOUT)
    assert code == 0, proc.describe()
    return proc.stdout()


def poses_by_stamp(bag, topic):
    out = {}
    for _, _, msg in bagio.read_messages(bag, [topic]):
        p, q = msg.pose.position, msg.pose.orientation
        out[bagio.header_stamp_ns(msg)] = (np.array([p.x, p.y, p.z]),
                                           np.array([q.x, q.y, q.z, q.w]))
    return out


def fk_error(bag):
    """Largest distance of fk's platform_pose from the plant's ground truth [m]."""
    from stewart63_ros.core.mechanics.rotation import (
        rotation_angle_between,
        rotation_from_quaternion,
    )
    truth = poses_by_stamp(bag, 'ground_truth/pose')
    fk = poses_by_stamp(bag, 'platform_pose')
    common = sorted(set(truth) & set(fk))
    assert len(common) > 100
    position = max(np.linalg.norm(truth[s][0] - fk[s][0]) for s in common)
    angle = max(float(rotation_angle_between(rotation_from_quaternion(truth[s][1])[None],
                                             fk[s][1][None])[0]) for s in common)
    return position, angle


def test_plan_run_record_fit_on_the_lockstep_rig(ros, tmp_path):
    machine = tmp_path / 'machine.yaml'
    assert calibrate.main(['machine', '--seed', '4', '--out', str(machine),
                           '--tracker-rate', '50', '--tracker-noise', str(TRACKER_NOISE),
                           str(TRACKER_NOISE)]) == 0
    # Lockstep samples cost wall time here, and the fit uses the tracker's
    # 50 Hz: the rigs sample at SENSOR_RATE (the supervisor follows the
    # plant's rate), not the packaged 1 kHz.
    text = machine.read_text()
    assert 'sensor_rate: 1000.0' in text, text
    machine.write_text(text.replace('sensor_rate: 1000.0', 'sensor_rate: %g' % SENSOR_RATE))
    # Short holds and quick moves (the fastest the supervisor allows): lockstep
    # time costs wall time here.
    assert calibrate.main(['plan', '--poses', '10', '--out', str(tmp_path / 'plan'),
                           '--hold', '0.3', '--move', '0.4', '--leg-speed', '0.4']) == 0
    plan = json.loads((tmp_path / 'plan' / 'plan.json').read_text())
    bag = tmp_path / 'bag'
    # The plan flown under the supervisor, on the machine it was not planned
    # on: it must neither trip nor lose the plan (rig exits 1 beyond its
    # tracking bound; the plan of 10 leg-speed-1.0 poses of the packaged
    # mechanism on this machine once ended 0.295 m and 1.1 rad away).
    out = run_rig(ros, tmp_path, 'rig', '--plant-params', str(machine), '--control-law',
                  'pd_gravity', '--reference', str(tmp_path / 'plan' / 'reference.csv'),
                  '--supervisor', '--duration', '%.3f' % plan['duration_s'], '--record', str(bag))
    assert 'supervisor: no trip' in out, out
    tracking = json.loads((tmp_path / 'rig.logs' / 'plant_summary.json').read_text())[
        'tracking_error']
    print('\nplan tracked on the machine: position max %.3g mm, orientation max %.3g mrad'
          % (tracking['position_max_m'] * 1e3, tracking['orientation_max_rad'] * 1e3))
    # In its own process, as a user runs it (one BLAS thread: tools/calibrate.py).
    fit = ros.python('-m', 'stewart63_ros.tools.calibrate', 'fit', '--measurements', str(bag),
                     '--out', str(tmp_path / 'fit'), name='fit')
    assert fit.wait(RIG_TIMEOUT) == 0, fit.describe()
    report = json.loads((tmp_path / 'fit' / 'report.json').read_text())
    before, after = report['held_out']['before'], report['held_out']['after']
    print('\nrig calibration: %d tracker samples, reading RMS %.3g -> %.3g mm; held-out fk '
          'position RMS %.3g -> %.3g mm, angle RMS %.3g -> %.3g mrad' % (
              report['source']['used'], report['rms_before_m'] * 1e3,
              report['rms_after_m'] * 1e3, before['position_rms_m'] * 1e3,
              after['position_rms_m'] * 1e3, before['angle_rms_rad'] * 1e3,
              after['angle_rms_rad'] * 1e3))
    assert report['unidentifiable'] == []
    assert before['position_rms_m'] > 2e-3
    # Within 3x the tracker's noise (per axis, so sqrt(3) of it as a distance).
    assert after['position_rms_m'] < 3 * TRACKER_NOISE * np.sqrt(3)
    assert after['position_rms_m'] * 10 < before['position_rms_m']
    assert after['angle_rms_rad'] * 10 < before['angle_rms_rad']

    # Controller and fk restarted on the calibrated file, the plant still the
    # machine: fk removes the offsets and reports the true pose.
    bag2 = tmp_path / 'bag2'
    run_rig(ros, tmp_path, 'rig2', '--params', str(tmp_path / 'fit' / 'calibrated.yaml'),
            '--plant-params', str(machine), '--control-law', 'pd_gravity',
            '--duration', '0.5', '--record', str(bag2))
    position, angle = fk_error(bag2)
    print('fk on the calibrated file: max error %.3g mm, %.3g mrad' % (position * 1e3,
                                                                      angle * 1e3))
    assert position < 5e-4 and angle < 5e-4
