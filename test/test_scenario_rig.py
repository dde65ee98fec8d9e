"""Scenarios on the lockstep rig (tools/scenario.py starting `rig`): the same
samples, hence the same verdicts and values, as `run: sim`."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from stewart63_ros.core.scenarios.parsing import load_scenarios, scenarios_from_dict
from stewart63_ros.core.scenarios.running import run_sim
from stewart63_ros.core.scenarios.verdicts import evaluate
from stewart63_ros.tools import scenario as tool

REPO = Path(__file__).resolve().parents[1]


def test_the_paper_scenario_on_the_lockstep_rig_is_sims_sample_for_sample(ros, tmp_path):
    scenario, = load_scenarios(REPO / 'scenarios' / 'rig' / 'paper_lockstep.yaml')
    rig = tool.run_rig(scenario, tmp_path, ros.domain_id)
    sim = run_sim(dataclasses.replace(scenario, run='sim'))
    assert len(rig.times) == len(sim.times) == 2001
    np.testing.assert_array_equal(rig.times, sim.times)
    # plant, controller over DDS: the same arithmetic, the same bits
    np.testing.assert_array_equal(rig.lengths, sim.lengths)
    np.testing.assert_array_equal(rig.forces, sim.forces)
    physics = [e for e in scenario.expect if e.metric != 'lost_messages']
    on_rig = [(v.value, v.passed, v.at_s) for v in evaluate(rig, physics)]
    assert on_rig == [(v.value, v.passed, v.at_s) for v in evaluate(sim, physics)]
    assert all(passed for _, passed, _ in on_rig)
    assert rig.lost_messages == 0


def test_a_trip_expectation_on_the_lockstep_rig_is_sims_trip(ros, tmp_path):
    """`rig --supervisor` trips on the sample the core supervisor in sim does,
    with the same cause: the same verdict and measured value."""
    scenario, = load_scenarios(REPO / 'scenarios' / 'rig' / 'supervisor_lockstep.yaml')
    assert scenario.supervised
    rig = tool.run_rig(scenario, tmp_path, ros.domain_id)
    sim = run_sim(dataclasses.replace(scenario, run='sim'))
    assert [(t.cause, t.sample, t.latency_samples) for t in rig.trips] == [
        (t.cause, t.sample, t.latency_samples) for t in sim.trips] == [('lengths_stale', 529, 0)]
    trip = [e for e in scenario.expect if e.metric == 'trip']
    on_rig, in_sim = evaluate(rig, trip)[0], evaluate(sim, trip)[0]
    assert (on_rig.value, on_rig.passed, on_rig.measured) == (
        in_sim.value, in_sim.passed, in_sim.measured) == (29.0, True, in_sim.measured)
    assert 'lengths_stale at sample 529' in on_rig.text()
    assert rig.lost_messages == 0


def test_a_realtime_scenario_gives_every_verdict_its_measured_value(ros, tmp_path):
    """`run: realtime` (the rig at the wall clock): every expectation gets a
    verdict with a value, the transport's counts included. Timing here is the
    machine's: the values are checked for what they are, not for a bound."""
    scenario, = scenarios_from_dict({
        'name': 'paper-realtime', 'run': 'realtime', 'duration': 1.5,
        'expect': {'final_error_percent': {'max': 100.0}, 'max_force': {'max': 3000.0},
                   'endstop_samples': {'max': 1000000},
                   'missed_cycles': {'max': 1000000}, 'lost_messages': {'max': 1000000}}})
    outcome = tool.run_one(scenario, domain=ros.domain_id)
    assert not outcome.error, outcome.error
    values = {v.expectation.metric: v.value for v in outcome.verdicts}
    assert list(values) == ['final_error_percent', 'max_force', 'endstop_samples',
                            'missed_cycles', 'lost_messages']
    assert all(np.isfinite(v) for v in values.values()), values
    assert values['max_force'] > 0 and values['final_error_percent'] > 0
    for count in ('missed_cycles', 'lost_messages', 'endstop_samples'):
        assert values[count] >= 0 and values[count] == int(values[count])
    trace = outcome.trace       # about 1.5 s of samples at 1 kHz, stamped from 0
    assert trace.times[0] == 0 and 1000 < len(trace.times) <= 1501
    text = [v.text() for v in outcome.verdicts]
    assert any(t.startswith('missed_cycles = ') for t in text)
    assert any(t.startswith('lost_messages = ') for t in text)


def test_a_scenario_runs_over_the_bus_on_the_lockstep_rig(ros, tmp_path):
    """`bus: canopen` (it was an unknown key): the rig runs with `--bus canopen`,
    the plant as the six drives and canopen_bridge between the bus and the
    topics, every sample over the bus; a drive's EMCY (a bus fault, refused
    without `bus:`) does not disturb it."""
    import json
    scenario, = load_scenarios(REPO / 'scenarios' / 'rig' / 'bus_lockstep.yaml')
    assert scenario.bus == 'canopen' and scenario.faults
    trace = tool.run_rig(scenario, tmp_path, ros.domain_id)
    bridge = json.loads((tmp_path / 'logs' / 'canopen_bridge_summary.json').read_text())
    assert bridge['cycles'] >= len(trace.times) - 1 == 1000, bridge
    verdicts = evaluate(trace, scenario.expect)
    assert all(v.passed for v in verdicts), [v.text() for v in verdicts]
