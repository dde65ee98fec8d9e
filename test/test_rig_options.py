"""`rig`'s options and its summary line, without running a rig.

- ``--namespace rig2``, as a user types it, is the namespace ``/rig2`` for
  every process (rcl refuses a relative ``__ns`` remap); a name ROS refuses
  is refused in one line, exit 2, before anything starts;
- the summary tells the rig's start-up and stop from the run itself (a 5 s
  realtime run is not "5001 samples in 14.66 s").
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from stewart63_ros.tools.rig_process import Rig
from stewart63_ros.tools.rig_summary import print_summary

REPO = Path(__file__).resolve().parents[1]
PARAMS = REPO / 'config' / 'stewart63.yaml'


@pytest.mark.parametrize('typed, ns', [('rig2', '/rig2'), ('/rig2', '/rig2'),
                                       ('lab/rig2', '/lab/rig2'), ('', ''), ('/', '')])
def test_a_namespace_is_taken_as_ros_makes_it_absolute(tmp_path, typed, ns):
    from rclpy.utilities import remove_ros_args
    rig = Rig(PARAMS, namespace=typed, log_dir=tmp_path)
    assert rig.namespace == ns
    args = rig.ros_args('plant')
    assert ('__ns:=%s' % ns in args) == bool(ns), args
    # what every node does with them first (rcl parses the remap rules)
    assert remove_ros_args(['plant', *args]) == ['plant']


@pytest.mark.parametrize('typed, why', [
    ('rig 2', "must not contain characters other than alphanumerics, '_', or '/'"),
    ('2rig', 'must not have a token that starts with a number'),
    ('/rig2/', "must not end with a '/'"),
    ('/rig2//a', "must not contain repeated '/'"),
])
def test_a_namespace_ros_refuses_is_refused_before_anything_starts(ros, tmp_path, typed, why):
    logs = tmp_path / 'logs'
    # on a domain of its own: a rig that started anyway stays among its processes
    proc = subprocess.run([sys.executable, '-m', 'stewart63_ros.tools.rig', '--duration', '1',
                           '--namespace', typed, '--log-dir', str(logs)], env=ros.env(),
                          capture_output=True, text=True, timeout=300, cwd=REPO)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        "rig: error: --namespace: %r is not a ROS namespace: " % typed), lines
    assert why in lines[0], lines
    assert not logs.exists() and proc.stdout == ''


class _Ended:
    """A rig whose plant wrote ``summary``; no controller, no fk."""
    nodes = ('plant',)
    supervisor = False
    bus = None

    def __init__(self, summary):
        self._summary = summary

    def summary(self, node='plant'):
        return self._summary


def _plant_summary(began, ended):
    return {'samples': 5001, 'clock_mode': 'realtime', 'rate_hz': 1000.0,
            'loop_latency': {}, 'positioning_error_percent': 0.9367, 'missed_cycles': 0,
            'force_timeouts': 0, 'endstop_samples': 0, 'wall_time_s': ended - began,
            'run_began_unix_s': began, 'run_ended_unix_s': ended}


def test_the_summary_tells_start_up_and_stop_from_the_run(capsys):
    started = 1000.0
    # 8.2 s of start-up, a 5.01 s run, 1.45 s to stop: 14.66 s in all
    print_summary(_Ended(_plant_summary(started + 8.2, started + 13.21)), 14.66, started)
    first = capsys.readouterr().out.splitlines()[0]
    assert first == ('rig summary: 5001 samples in 5.01 s wall (realtime, 1000 Hz); '
                     'start-up 8.20 s, stop 1.45 s, 14.66 s in all'), first


def test_a_summary_without_the_run_times_names_no_run_time(capsys):
    summary = _plant_summary(0.0, 5.0)
    del summary['run_began_unix_s'], summary['run_ended_unix_s']
    print_summary(_Ended(summary), 14.66, 1000.0)
    first = capsys.readouterr().out.splitlines()[0]
    assert first == 'rig summary: 5001 samples; 14.66 s wall in all (realtime, 1000 Hz)', first


@pytest.mark.parametrize('options, node', [(['--supervisor'], 'supervisor'),
                                           (['--bus', 'canopen'], 'canopen_bridge')])
def test_a_follower_at_another_sample_rate_than_the_plant_is_refused(tmp_path, options, node):
    # The bridge's SYNCs and the supervisor's sample count follow the plant:
    # a file that gives one of them another rate is refused before anything starts.
    import yaml
    params = yaml.safe_load(PARAMS.read_text())
    params['/**/plant']['ros__parameters']['sensor_rate'] = 200.0
    params['/**/%s' % node] = {'ros__parameters': {'sensor_rate': 500.0}}
    (tmp_path / 'params.yaml').write_text(yaml.safe_dump(params))
    logs = tmp_path / 'logs'
    proc = subprocess.run([sys.executable, '-m', 'stewart63_ros.tools.rig', '--params',
                           str(tmp_path / 'params.yaml'), '--duration', '1', *options,
                           '--log-dir', str(logs)],
                          capture_output=True, text=True, timeout=120, cwd=REPO)
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    assert proc.stderr.strip() == (
        'rig: error: one sample rate: %s sensor_rate 500 Hz, plant 200 Hz (%s): set '
        'sensor_rate once, for both' % (node, {
            'supervisor': 'it numbers the samples and checks the force rate at its own',
            'canopen_bridge': 'the plant steps one period a SYNC'}[node])), proc.stderr
    assert not logs.exists() and proc.stdout == ''


def test_the_supervisor_and_the_bridge_take_the_plants_sample_rate(tmp_path):
    import yaml
    params = yaml.safe_load(PARAMS.read_text())
    params['/**/plant']['ros__parameters']['sensor_rate'] = 200.0
    (tmp_path / 'params.yaml').write_text(yaml.safe_dump(params))
    rig = Rig(tmp_path / 'params.yaml', log_dir=tmp_path / 'logs', supervisor=True,
              bus='canopen')
    doc = yaml.safe_load(rig.overlay().read_text())
    assert doc['/**/supervisor']['ros__parameters']['sensor_rate'] == 200.0
    assert doc['/**/canopen_bridge']['ros__parameters']['sensor_rate'] == 200.0
