"""One parameter model (core/mechanics/setup.py, docs/design.md "One parameter model"):
the ``Mechanism`` is the machine alone; gains, task and settings sit beside it
in a ``Setup``, and every declared key lives in exactly one of the four."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from stewart63_ros.core.mechanics.dynamics import Dynamics
from stewart63_ros.core.mechanics.fk import ForwardKinematics
from stewart63_ros.core.mechanics.kinematics import leg_lengths
from stewart63_ros.core.mechanics.mechanism import MECHANISM_KEYS, Mechanism, validated
from stewart63_ros.core.mechanics.setup import GAIN_KEYS, TASK_KEYS, Setup
from stewart63_ros.core.plumbing.errors import ParameterError
from stewart63_ros.core.plumbing.node_parameters import DECLARED, MODEL, default
from stewart63_ros.core.plumbing.params import file_parameters, setup_from_params


def _packaged_with_every_key(path) -> dict:
    """The packaged file's keys, and every declared key it leaves out at its default."""
    params = file_parameters(path)
    for d in DECLARED:
        params.setdefault(d.name, default(d.name, params))
    return params


def test_the_mechanism_is_the_machine_alone():
    fields = {f.name for f in dataclasses.fields(Mechanism)}
    assert not fields & {'kp', 'kv', 'setpoint_lengths', 'initial_position', 'initial_velocity',
                         'initial_orientation', 'initial_orientation_rate', 'extra'}
    # the model's end stops and the sensors' zeros are the machine's, typed
    assert {'endstop_stiffness', 'endstop_damping', 'leg_length_offset'} <= fields


def test_kinematics_and_dynamics_take_a_machine_made_without_gains_or_task(default_params_file):
    params = file_parameters(default_params_file)
    machine_only = {k: v for k, v in params.items() if k in MECHANISM_KEYS}
    assert 'kp' not in machine_only and 'setpoint_lengths' not in machine_only
    mech = validated(machine_only)
    dyn = Dynamics(mech)
    position, rotation = mech.neutral_pose()
    lengths = leg_lengths(mech, position, rotation)
    assert np.all((lengths > mech.leg_length_min) & (lengths < mech.leg_length_max))
    y = np.zeros(13)
    y[:3], y[6] = position, 1.0
    assert np.all(np.isfinite(dyn.derivative(y, np.zeros(6))))
    mode = ForwardKinematics(mech).all_modes(lengths)[0]
    np.testing.assert_allclose(mode.position, position, atol=1e-9)


def test_every_declared_key_lives_in_exactly_one_place_and_round_trips(default_params_file):
    params = _packaged_with_every_key(default_params_file)
    setup = setup_from_params(params)
    places = {'mechanism': {f.name for f in dataclasses.fields(setup.mechanism)},
              'gains': {f.name for f in dataclasses.fields(setup.gains)},
              'task': {f.name for f in dataclasses.fields(setup.task)},
              'settings': set(setup.settings)}
    flat = setup.to_params()
    for key in [m.name for m in MODEL] + [d.name for d in DECLARED]:
        holders = [name for name, keys in places.items() if key in keys]
        assert len(holders) == 1, (key, holders)
        given, kept = params[key], flat[key]
        if isinstance(given, (str, bool)) or given is None or (
                isinstance(given, list) and given and isinstance(given[0], str)):
            assert kept == given, key
        else:
            np.testing.assert_array_equal(np.ravel(kept), np.ravel(given), err_msg=key)
    assert places['gains'] == GAIN_KEYS and places['task'] == TASK_KEYS
    # the settings are read through their declarations, read-only
    assert setup.setting('sensor_rate') == float(params['sensor_rate'])
    with pytest.raises(TypeError):
        setup.settings['sensor_rate'] = 1.0
    again = setup_from_params(flat)
    assert isinstance(again, Setup) and again.to_params() == flat


def test_every_change_goes_through_the_checks(default_setup):
    with pytest.raises(ParameterError, match='kp'):
        default_setup.replace(kp=[4000.0, -1.0, 4000.0, 4000.0, 4000.0, 4000.0])
    with pytest.raises(ParameterError, match='setpoint_lengths'):
        default_setup.replace(setpoint_lengths=[9.0] * 6)          # outside the stroke
    with pytest.raises(ParameterError, match='initial_position'):
        # a shorter stroke puts the task outside it: checked with the new machine
        default_setup.with_mechanism(default_setup.mechanism.replace(leg_length_max=1.3))
    with pytest.raises(ParameterError, match='not a field of the mechanism'):
        default_setup.mechanism.replace(kp=[1.0] * 6)
    changed = default_setup.replace(kv=[1.0] * 6, endstop_damping=7.0)
    assert changed.gains.kv.tolist() == [1.0] * 6 and changed.mechanism.endstop_damping == 7.0
    assert not changed.gains.kv.flags.writeable
