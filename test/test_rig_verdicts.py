"""What `rig` says of a run before and after it, without starting one: a
supervisor file it would refuse (once, exit 2), a run that ended during the
homing (said, not "no trip" with an error figure)."""
from __future__ import annotations

import subprocess
import sys

import yaml

from stewart63_ros.paths import default_params_path
from stewart63_ros.tools import rig, rig_summary

PLANT = {'clock_mode': 'lockstep', 'rate_hz': 1000.0, 'samples': 501,
         'positioning_error_percent': 31.8, 'loop_latency': {'count': 0},
         'missed_cycles': 0, 'force_timeouts': 0, 'endstop_samples': 0}


class FakeRig:
    supervisor, bus, nodes = True, None, ()

    def __init__(self, homed):
        self.supervisor_summary = {'trips': [], 'values': {'homed': homed, 'trips': 0}}

    def summary(self, node='plant'):
        return PLANT if node == 'plant' else self.supervisor_summary


def test_a_run_that_ends_during_the_homing_says_so(capsys):
    rig_summary.print_summary(FakeRig('false'), 2.0)
    out = capsys.readouterr().out
    assert 'the run ended before the homing finished (homed: false)' in out, out
    assert '31.8' not in out and 'supervisor: no trip' not in out, out
    rig_summary.print_summary(FakeRig('true'), 2.0)
    out = capsys.readouterr().out
    assert 'homing' not in out and '31.8000 %' in out and 'supervisor: no trip' in out, out


def test_homing_retract_on_the_packaged_machine_is_refused_once_exit_2(tmp_path):
    doc = yaml.safe_load(default_params_path().read_text())
    doc['/**/supervisor'] = {'ros__parameters': {'homing': True,
                                                 'homing_direction': 'retract'}}
    path = tmp_path / 'retract.yaml'
    path.write_text(yaml.safe_dump(doc))
    # Before anything starts (bounded: nothing is started).
    done = subprocess.run([sys.executable, '-m', 'stewart63_ros.tools.rig', '--params', str(path),
                           '--supervisor', '--duration', '0.1', '--log-dir',
                           str(tmp_path / 'logs')], capture_output=True, text=True, timeout=120)
    err = done.stderr
    assert done.returncode == 2, err
    lines = [line for line in err.splitlines() if 'homing_direction' in line]
    assert len(lines) == 1 and lines[0].startswith('rig: error: supervisor: parameter error: '
                                                   'homing_direction: retract'), err
    assert rig.supervisor_problem(default_params_path(), {}) == ''
