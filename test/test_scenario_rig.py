"""Scenarios on the lockstep rig (tools/scenario.py starting `rig`): the same
samples, hence the same verdicts and values, as `run: sim`."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from stewart63_ros.core.scenario import evaluate, load_scenarios, run_sim
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
