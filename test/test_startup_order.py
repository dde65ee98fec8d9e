"""What ``rig`` tells its plant to wait for before the first sample
(runtime/startup.py), checked through the rig's own parameter file."""
from __future__ import annotations

import yaml

from stewart63_ros.runtime.handshake import plant_startup_parameters, recorder_waits_for
from stewart63_ros.tools.rig_process import Rig


def test_a_recording_lockstep_rig_holds_its_plant_for_fk_and_the_recorder():
    params = plant_startup_parameters(('plant', 'controller', 'fk'), True, 'lockstep', False)
    assert params == {'lengths_subscribers': 3, 'lengths_peers': ['controller', 'fk'],
                      'lockstep_peers': ['fk', 'record']}


def test_composed_and_realtime_rigs_have_no_lockstep_peers():
    for mode, compose in (('lockstep', True), ('realtime', False)):
        params = plant_startup_parameters(('plant', 'controller', 'fk'), True, mode, compose)
        assert 'lockstep_peers' not in params


def test_a_plant_whose_controller_runs_elsewhere_waits_for_it_too():
    params = plant_startup_parameters(('plant',), False, 'lockstep', False)
    assert params['lengths_subscribers'] == 1 and params['lengths_peers'] == ['controller']
    assert params['lockstep_peers'] == []
    assert recorder_waits_for(('plant',)) == []
    assert recorder_waits_for(('controller', 'fk')) == ['leg_forces', 'platform_pose']


def test_the_rigs_parameter_file_carries_them_to_the_plant(tmp_path):
    from stewart63_ros.paths import default_params_path
    rig = Rig(default_params_path(), record=tmp_path / 'bag', log_dir=tmp_path / 'logs')
    doc = yaml.safe_load(rig.overlay().read_text())
    plant = doc['/**/plant']['ros__parameters']
    assert plant['lockstep_peers'] == ['fk', 'record'] and plant['lengths_subscribers'] == 3
    assert doc['/**']['ros__parameters']['wait_for_subscribers'] == 1
