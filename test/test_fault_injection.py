"""Faults injected on purpose (core/machine/faults.py), offline: no DDS.

- the syntax ``KIND:LEG[:VALUE][@T_START[-T_END]]``: every kind parses, a bad
  string is refused with one message naming it and why;
- each kind's effect in ``sim`` (``run_sampled(..., faults=...)``): the run is
  the fault-free run to the bit before the fault starts and differs after it
  as the fault predicts (a stuck sensor holds while the leg moves, a bias
  shifts the final length by the bias, a dead or weak actuator sags ...);
- the model's run-time changes and resets; ``sim --fault`` and ``rig
  --fault`` on the command line; ``plot`` reads the faulted intervals back;
- the example law's fault detector trips on a stuck sensor, not without one.
"""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from stewart63_ros.core.controllers.simulate import run_sampled
from stewart63_ros.core.machine.faults import (
    KINDS,
    FaultError,
    FaultModel,
    interval_from_status,
    parse_fault,
    parse_faults,
)
from stewart63_ros.core.mechanics.dynamics import POS
from stewart63_ros.core.plumbing.params import unknown_keys

REPO = Path(__file__).resolve().parents[1]
PARAMS = REPO / 'config' / 'stewart63.yaml'
RATE = 1000.0
DURATION = 2.0
START = 1.0                  # s: most faults start here, when the platform has settled
K0 = int(START * RATE)       # the first faulted sample


@pytest.fixture(scope='module')
def clean(setup, mech):
    """The fault-free sampled run (the compiled loop)."""
    return run_sampled(setup, DURATION, RATE)


def true_lengths(dyn, result) -> np.ndarray:
    return np.array([dyn.lengths_and_rates(y)[0] for y in result.states])


def faulted(setup, *faults, duration=DURATION):
    result = run_sampled(setup, duration, RATE, faults=list(faults))
    assert np.all(np.isfinite(result.states))
    return result


def assert_same_until(clean, result, k_end):
    """Bit for bit the fault-free run on samples 0 .. k_end - 1."""
    np.testing.assert_array_equal(result.states[:k_end], clean.states[:k_end])
    np.testing.assert_array_equal(result.forces[:k_end], clean.forces[:k_end])


# -- syntax ------------------------------------------------------------------------------
@pytest.mark.parametrize('text, kind, legs, value, start, end', [
    ('sensor_stuck:leg_2@1.0', 'sensor_stuck', (1,), None, 1.0, math.inf),
    ('sensor_bias:leg_1:0.005@2', 'sensor_bias', (0,), 0.005, 2.0, math.inf),
    ('sensor_noise:leg_3:0.002', 'sensor_noise', (2,), 0.002, 0.0, math.inf),
    ('sensor_dropout:leg_5@3-4', 'sensor_dropout', (4,), None, 3.0, 4.0),
    ('sensor_delay:all:0.005', 'sensor_delay', tuple(range(6)), 0.005, 0.0, math.inf),
    ('actuator_dead:leg_4@2.0', 'actuator_dead', (3,), None, 2.0, math.inf),
    ('actuator_weak:leg_6:0.5', 'actuator_weak', (5,), 0.5, 0.0, math.inf),
    ('actuator_stuck:leg_1@1', 'actuator_stuck', (0,), None, 1.0, math.inf),
    ('actuator_saturation:all:1500', 'actuator_saturation', tuple(range(6)), 1500.0, 0.0,
     math.inf),
    (' sensor_bias:leg_6:-1e-3@.5-2.5 ', 'sensor_bias', (5,), -1e-3, 0.5, 2.5),
])
def test_every_kind_parses(text, kind, legs, value, start, end):
    fault = parse_fault(text)
    assert (fault.kind, fault.legs, fault.value, fault.start, fault.end) == (
        kind, legs, value, start, end)
    assert fault.text == text.strip()


def test_the_kinds_are_the_documented_nine_and_the_five_of_the_bus():
    assert set(KINDS) == {'sensor_stuck', 'sensor_bias', 'sensor_noise', 'sensor_dropout',
                          'sensor_delay', 'actuator_dead', 'actuator_weak', 'actuator_stuck',
                          'actuator_saturation', 'bus_no_boot', 'bus_heartbeat_lost',
                          'bus_emcy', 'bus_drive_fault', 'bus_tpdo_missing'}


@pytest.mark.parametrize('text, why', [
    ('sensor_jammed:leg_1', "unknown kind 'sensor_jammed'"),
    ('sensor_stuck:leg_7', "unknown leg 'leg_7'"),
    ('sensor_stuck:1', "unknown leg '1'"),
    ('sensor_bias:leg_1', 'sensor_bias needs a value'),
    ('sensor_stuck:leg_1:0.1', 'sensor_stuck takes no value'),
    ('sensor_noise:leg_1:0', 'out of range'),
    ('sensor_noise:leg_1:-0.1', 'out of range'),
    ('actuator_weak:leg_1:1.5', 'out of range'),
    ('actuator_saturation:all:0', 'out of range'),
    ('sensor_delay:all:0', 'out of range'),
    ('sensor_bias:leg_1:nan', 'out of range'),
    ('sensor_bias:leg_1:abc', "value 'abc' is not a number"),
    ('sensor_dropout:leg_5@4-3', 'the end 3 s is not after the start 4 s'),
    ('sensor_dropout:leg_5@2-2', 'is not after the start'),
    ('sensor_dropout:leg_5@-1', "bad time '@-1'"),
    ('sensor_dropout:leg_5@soon', "bad time '@soon'"),
    ('sensor_dropout', 'expected KIND:LEG'),
    ('', 'expected KIND:LEG'),
])
def test_a_bad_fault_is_refused_with_its_name_and_the_reason(text, why):
    with pytest.raises(FaultError) as info:
        parse_fault(text)
    message = str(info.value)
    assert "bad fault '%s'" % text.strip() in message and why in message, message
    assert '\n' not in message


def test_a_list_of_faults():
    assert parse_faults(None) == parse_faults([]) == parse_faults('') == parse_faults(['']) == []
    assert [f.text for f in parse_faults('actuator_dead:leg_1')] == ['actuator_dead:leg_1']
    with pytest.raises(FaultError, match='given twice'):
        parse_faults(['actuator_dead:leg_1', ' actuator_dead:leg_1'])
    with pytest.raises(FaultError, match="bad fault 'x'"):
        parse_faults(['actuator_dead:leg_1', 'x'])      # the whole list is refused
    with pytest.raises(FaultError, match='expected a string'):
        parse_faults([3])


@pytest.mark.parametrize('texts, why', [
    (['actuator_dead:leg_1', 'actuator_dead:leg_1@0'],
     "fault 'actuator_dead:leg_1@0' is given twice (as 'actuator_dead:leg_1')"),
    (['sensor_bias:leg_2:0.01@1', 'sensor_bias:leg_2:1e-2@1.0'], 'is given twice'),
    (['actuator_dead:leg_1', ''], "bad fault '': a blank fault"),
    (['', ''], "bad fault '': a blank fault"),
])
def test_the_same_fault_written_twice_or_a_blank_one_beside_others_is_refused(texts, why):
    with pytest.raises(FaultError) as info:
        parse_faults(texts)
    assert why in str(info.value) and '\n' not in str(info.value), str(info.value)


def test_a_fault_whose_times_are_past_is_refused_at_run_time():
    model = FaultModel(parse_faults(['sensor_bias:all:0.1']), rate=1000.0)
    for k in range(50):
        model.begin(k)
    with pytest.raises(FaultError) as info:
        model.set_faults(parse_faults(['sensor_bias:all:0.1', 'actuator_dead:leg_1@0.01-0.05']))
    assert str(info.value) == (
        "fault 'actuator_dead:leg_1@0.01-0.05' ends at 0.05 s, before the next sample of "
        "this run (t = 0.05 s): it would never act (its times are the run's, from its first "
        "sample)")
    assert [f.text for f in model.faults] == ['sensor_bias:all:0.1']     # nothing changed
    # one that still has a sample to act on is taken; one already there is kept
    model.set_faults(parse_faults(['sensor_bias:all:0.1', 'actuator_dead:leg_1@0.01-0.051']))
    assert model.begin(50) == ['fault actuator_dead:leg_1@0.01-0.051 started at 0.050000 s']
    # a plant that begins samples only while it has faults says where its run is
    bare = FaultModel([], rate=1000.0)
    with pytest.raises(FaultError, match='ends at 60 s'):
        bare.set_faults(parse_faults(['actuator_dead:leg_1@40-60']), next_sample=70000)
    # after a reset the times count from the new run's 0 again
    model.reset()
    model.set_faults(parse_faults(['actuator_dead:leg_1@0.01-0.05']))


def test_sims_fault_options(tmp_path):
    from stewart63_ros.tools.sim import fault_list
    params = tmp_path / 'p.yaml'
    params.write_text(PARAMS.read_text() + "\n/**/plant:\n  ros__parameters:\n"
                      "    faults: ['']\n")
    assert fault_list(params) == []                 # the file's [''] stands for none
    assert [f.text for f in fault_list(params, ['actuator_dead:leg_1'])] == [
        'actuator_dead:leg_1']
    with pytest.raises(FaultError, match="bad fault '': expected KIND:LEG"):
        fault_list(params, [''])                    # --fault "" is no fault at all
    with pytest.raises(FaultError, match='given twice'):
        fault_list(params, ['actuator_dead:leg_1', 'actuator_dead:leg_1@0.0'])


def test_faults_and_step_count_are_known_plant_keys():
    assert unknown_keys(['faults', 'step_count']) == []


# -- each kind in sim --------------------------------------------------------------------
def test_no_faults_is_the_fault_free_run(setup, mech, clean):
    result = run_sampled(setup, DURATION, RATE, faults=[])
    assert_same_until(clean, result, len(clean.times))
    np.testing.assert_array_equal(result.applied, clean.forces)


def test_sensor_stuck_holds_its_value_while_the_leg_moves(setup, mech, dyn, clean):
    k0 = 100         # 0.1 s: leg 2 still extends towards its setpoint
    result = faulted(setup, 'sensor_stuck:leg_2@0.1')
    assert_same_until(clean, result, k0 + 1)
    true = true_lengths(dyn, result)
    held = result.measured[k0:, 1]
    assert np.all(held == held[0]) and np.all(result.measured[k0:, 7] == result.measured[k0, 7])
    assert held[0] == true[k0, 1]
    assert np.ptp(true[k0:, 1]) > 0.05, 'the true leg moved on'
    np.testing.assert_array_equal(result.measured[:, [0, 2, 3, 4, 5]], true[:, [0, 2, 3, 4, 5]])


def test_sensor_bias_shifts_the_final_length_by_the_bias(setup, mech, dyn, clean):
    bias = 0.005
    result = faulted(setup, 'sensor_bias:leg_1:%g@%g' % (bias, START))
    assert_same_until(clean, result, K0)
    assert not np.array_equal(result.states[K0 + 1], clean.states[K0 + 1])
    true = true_lengths(dyn, result)
    np.testing.assert_allclose(result.measured[K0:, 0] - true[K0:, 0], bias, rtol=1e-9)
    shift = true[-1] - true_lengths(dyn, clean)[-1]
    # PD drives the biased reading to the setpoint: the true leg ends short by the bias.
    assert abs(shift[0] + bias) < 0.1 * bias, shift
    assert np.all(np.abs(shift[1:]) < 0.1 * bias), shift


def test_sensor_noise_has_the_standard_deviation_given(setup, mech, dyn, clean):
    sigma = 0.002
    result = faulted(setup, 'sensor_noise:leg_3:%g@%g' % (sigma, START))
    assert_same_until(clean, result, K0)
    noise = result.measured[K0:, 2] - true_lengths(dyn, result)[K0:, 2]
    assert abs(np.std(noise) - sigma) < 0.1 * sigma and abs(np.mean(noise)) < 0.2 * sigma
    again = faulted(setup, 'sensor_noise:leg_3:%g@%g' % (sigma, START))
    np.testing.assert_array_equal(again.measured, result.measured)      # seeded


def test_sensor_dropout_reports_nan_and_the_last_force_holds(setup, mech, dyn, clean):
    k0, k1 = 500, 600
    result = faulted(setup, 'sensor_dropout:leg_5@0.5-0.6')
    assert_same_until(clean, result, k0)
    gone = result.measured[k0:k1]
    assert np.all(np.isnan(gone[:, [4, 10]]))
    assert np.all(np.isfinite(np.delete(gone, [4, 10], axis=1)))
    assert np.all(np.isfinite(result.measured[k1:]))
    # No answer to an incomplete sample: the force of sample k0 - 1 holds.
    np.testing.assert_array_equal(result.forces[k0:k1], np.repeat(
        result.forces[k0 - 1:k0], k1 - k0, axis=0))
    assert not np.array_equal(result.forces[k1], result.forces[k1 - 1])


def test_sensor_delay_reports_the_readings_of_that_long_ago(setup, mech, dyn, clean):
    k0, d = 50, 5        # 0.05 s, while the legs move; 5 ms = 5 samples
    result = faulted(setup, 'sensor_delay:all:0.005@0.05')
    assert_same_until(clean, result, k0)
    true = np.array([np.concatenate(dyn.lengths_and_rates(y)) for y in result.states])
    np.testing.assert_array_equal(result.measured[k0:], true[k0 - d:-d])
    assert not np.array_equal(result.states[-1], clean.states[-1])


def test_actuator_dead_applies_no_force_and_the_platform_sags(setup, mech, dyn, clean):
    result = faulted(setup, 'actuator_dead:leg_4@%g' % START)
    assert_same_until(clean, result, K0)
    assert np.all(result.applied[K0:, 3] == 0.0) and np.all(result.forces[K0:, 3] > 0)
    np.testing.assert_array_equal(np.delete(result.applied, 3, axis=1),
                                  np.delete(result.forces, 3, axis=1))
    assert true_lengths(dyn, result)[-1, 3] < true_lengths(dyn, clean)[-1, 3] - 0.05
    assert result.states[-1, POS][2] < clean.states[-1, POS][2] - 0.05, 'the platform sags'


def test_actuator_weak_applies_the_fraction_and_the_leg_sags(setup, mech, dyn, clean):
    result = faulted(setup, 'actuator_weak:leg_6:0.5@%g' % START)
    assert_same_until(clean, result, K0)
    np.testing.assert_allclose(result.applied[K0:, 5], 0.5 * result.forces[K0:, 5], rtol=1e-12)
    assert true_lengths(dyn, result)[-1, 5] < true_lengths(dyn, clean)[-1, 5] - 0.005


def test_actuator_stuck_holds_the_last_force(setup, mech, dyn, clean):
    k0 = 100             # 0.1 s: the forces still change
    result = faulted(setup, 'actuator_stuck:leg_1@0.1')
    assert_same_until(clean, result, k0)
    assert np.all(result.applied[k0:, 0] == clean.forces[k0 - 1, 0])
    assert np.ptp(result.forces[k0:, 0]) > 1.0, 'the controller commanded other forces'
    assert not np.array_equal(result.states[-1], clean.states[-1])


def test_actuator_saturation_clips_the_forces_and_the_platform_sags(setup, mech, dyn, clean):
    result = faulted(setup, 'actuator_saturation:all:50@%g' % START)
    assert_same_until(clean, result, K0)
    assert np.all(np.abs(result.applied[K0:]) <= 50.0)
    np.testing.assert_array_equal(result.applied[K0:], np.clip(result.forces[K0:], -50, 50))
    assert result.states[-1, POS][2] < clean.states[-1, POS][2] - 0.05


def test_a_fault_with_an_end_stops_acting_there(setup, mech, dyn, clean):
    result = faulted(setup, 'actuator_dead:leg_4@0.5-0.6')
    assert np.all(result.applied[500:600, 3] == 0)
    np.testing.assert_array_equal(result.applied[600:, 3], result.forces[600:, 3])
    assert result.faults == [{
        'fault': 'actuator_dead:leg_4@0.5-0.6', 'kind': 'actuator_dead', 'leg': 'leg_4',
        'value': None, 'start_s': 0.5, 'end_s': 0.6, 'run': 1, 'active_from_s': 0.5,
        'active_until_s': 0.6, 'state': 'ended'}]


# -- the model at run time ---------------------------------------------------------------
def test_run_time_changes_and_reset():
    model = FaultModel(parse_faults(['actuator_dead:leg_1@0.002', 'sensor_bias:all:0.1']),
                       rate=1000.0)
    ones = np.ones(6)
    assert 'scheduled from 0.002 s' in model.status_values()['fault: actuator_dead:leg_1@0.002']
    for k in range(4):
        model.begin(k)
        lengths, _, complete = model.sense(ones, ones)
        forces = model.actuate(ones)
    assert complete and lengths[0] == 1.1 and forces[0] == 0.0
    assert model.active_text() == ('faults active: actuator_dead:leg_1@0.002 (since 0.002 s), '
                                   'sensor_bias:all:0.1 (since 0 s)')
    # The bias stays (its state kept), the dead actuator goes, a new one comes.
    events = model.set_faults(parse_faults(['sensor_bias:all:0.1', 'actuator_weak:leg_2:0.5']))
    assert len(events) == 2 and 'removed' in events[0] and 'added' in events[1]
    model.begin(4)
    assert model.actuate(ones).tolist() == [1, 0.5, 1, 1, 1, 1]
    status = model.status_values()
    assert status['fault: actuator_dead:leg_1@0.002'] == (
        'ended: active 0.002000-0.003000 s, removed')
    assert interval_from_status(status['fault: actuator_dead:leg_1@0.002']) == (0.002, 0.003)
    assert interval_from_status(status['fault: sensor_bias:all:0.1']) == (0.0, None)
    model.reset()
    assert model.run == 2 and not model.active
    # the faults active to the end of run 1 ended with it, after its last sample (4)
    assert [(s['state'], s['active_until_s']) for s in model.summary()] == [
        ('ended', 0.003), ('ended', 0.005), ('ended', 0.005), ('scheduled', None),
        ('scheduled', None)]


# -- command lines -----------------------------------------------------------------------
def run_tool(tool, *args):
    return subprocess.run([sys.executable, '-m', 'stewart63_ros.tools.' + tool, *args],
                          capture_output=True, text=True, timeout=600, cwd=REPO)


@pytest.mark.slow
def test_sim_with_faults_prints_and_writes_them_and_plot_shades_them(tmp_path):
    out = tmp_path / 'run'
    proc = run_tool('sim', '--duration', '0.3', '--out', str(out),
                    '--fault', 'actuator_dead:leg_4@0.1-0.2', '--fault', 'sensor_stuck:leg_2@0.25')
    assert proc.returncode == 0, proc.stderr
    assert 'control                      "sampled"' in proc.stdout
    assert 'fault actuator_dead:leg_4@0.1-0.2' in proc.stdout
    assert 'active 0.1000-0.2000 s' in proc.stdout
    assert 'active from 0.2500 s to the end' in proc.stdout
    faults = json.loads((out / 'faults.json').read_text())
    assert [f['fault'] for f in faults] == ['actuator_dead:leg_4@0.1-0.2',
                                            'sensor_stuck:leg_2@0.25']
    from stewart63_ros.tools.plot import load_faults, main
    assert load_faults(out) == faults == load_faults(out / 'trajectory.csv')
    assert main([str(out), '--out', str(tmp_path / 'plot.png')]) == 0
    assert (tmp_path / 'plot.png').stat().st_size > 10000


@pytest.mark.slow
@pytest.mark.parametrize('tool', ['sim', 'rig'])
@pytest.mark.parametrize('fault, why', [
    ('sensor_stuck:leg_9', "unknown leg 'leg_9'"),
    ('actuator_weak:leg_1:2', 'out of range'),
    ('sensor_dropout:leg_1@3-1', 'is not after the start'),
    ('bogus:all', "unknown kind 'bogus'"),
])
def test_a_bad_fault_on_the_command_line_exits_2_with_one_line(tmp_path, tool, fault, why):
    args = ['--duration', '1', '--fault', 'actuator_dead:leg_1', '--fault', fault]
    if tool == 'sim':
        args += ['--out', str(tmp_path / 'out')]
    else:
        args += ['--log-dir', str(tmp_path / 'logs')]
    proc = run_tool(tool, *args)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('%s: error: bad fault' % tool), lines
    assert fault in lines[0] and why in lines[0], lines
    assert not (tmp_path / 'out').exists()


@pytest.mark.slow
def test_sim_refuses_faults_with_continuous_control(tmp_path):
    proc = run_tool('sim', '--duration', '0.1', '--out', str(tmp_path / 'o'),
                    '--control', 'continuous', '--fault', 'actuator_dead:leg_1')
    assert proc.returncode == 2
    assert proc.stderr.strip() == ('sim: error: faults act on the sensor samples: use '
                                   '--control sampled (the default with faults)')


# -- the example's fault detector --------------------------------------------------------
DETECTOR = 'stewart63_ros.examples.fault_detector:CheckedPD'


def test_the_example_detector_trips_on_a_stuck_sensor_only(setup, mech):
    from stewart63_ros.core.controllers.laws import Controller, LawError
    clean = run_sampled(setup, DURATION, RATE, controller=Controller(setup, {}, law=DETECTOR),
                        faults=[])
    pd = run_sampled(setup, DURATION, RATE)
    np.testing.assert_allclose(clean.states, pd.states, atol=1e-9)   # eq. (40) when healthy
    with pytest.raises(LawError, match='SensorFault: sensor fault on leg_2 at t = 0.1'):
        run_sampled(setup, DURATION, RATE, controller=Controller(setup, {}, law=DETECTOR),
                    faults=['sensor_stuck:leg_2@0.1'])
    # a dropout is refused before the law: the window restarts after the gap
    run_sampled(setup, DURATION, RATE, controller=Controller(setup, {}, law=DETECTOR),
                faults=['sensor_dropout:leg_2@0.1-0.2'])


def test_the_live_view_shows_the_run_state_and_each_fault():
    from stewart63_ros.tools.view_sources import run_lines
    lines = run_lines({'run': 'paused', 'sample': '120', 'run_number': '2',
                       'fault: sensor_bias:leg_1:0.01@5': 'scheduled from 5 s',
                       'fault: actuator_dead:leg_4': 'active since 0.000000 s'})
    assert lines == ['&nbsp;&nbsp;run **paused** at sample 120 (run 2)',
                     '&nbsp;&nbsp;fault `actuator_dead:leg_4`: **active since 0.000000 s**',
                     '&nbsp;&nbsp;fault `sensor_bias:leg_1:0.01@5`: scheduled from 5 s']
    assert run_lines({'run': 'running', 'sample': '3'}) == []


def test_a_plant_with_a_bad_fault_parameter_exits_2(ros):
    proc = ros.python('-m', 'stewart63_ros.nodes.plant', '--ros-args',
                      '-p', "faults:=['actuator_weak:leg_2:0.5', 'sensor_stuck:leg_0']")
    assert proc.wait(120) == 2, proc.describe()
    assert proc.stderr().strip().splitlines() == [
        "plant: parameter error: faults: bad fault 'sensor_stuck:leg_0': unknown leg 'leg_0' "
        "(leg_1 ... leg_6 or all)"], proc.describe()
