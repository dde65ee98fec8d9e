"""Scenario files, verdicts, JUnit XML and the report (core/scenarios/,
tools/scenario.py).

The measured values are checked against the simulation's own results
computed here another way (``simulate.run_sampled`` and ``Result``'s
methods, the loop in Python), not against saved output.
"""
import dataclasses
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from stewart63_ros.core.controllers.simulate import run_sampled
from stewart63_ros.core.mechanics.dynamics import Dynamics
from stewart63_ros.core.plumbing.params import load_setup
from stewart63_ros.core.scenarios.parsing import load_scenarios, scenarios_from_dict
from stewart63_ros.core.scenarios.running import run_sim, wrench_samples
from stewart63_ros.core.scenarios.scenario import ScenarioError
from stewart63_ros.core.scenarios.verdicts import evaluate
from stewart63_ros.tools import scenario as tool

REPO = Path(__file__).resolve().parents[1]

# The Jenkins / Ant JUnit report schema (testsuites > testsuite > testcase,
# failure/error with message and type, system-out), as CI servers read it.
JUNIT_XSD = """<?xml version="1.0" encoding="UTF-8"?>
<xs:schema xmlns:xs="http://www.w3.org/2001/XMLSchema" elementFormDefault="qualified">
  <xs:complexType name="detail">
    <xs:simpleContent>
      <xs:extension base="xs:string">
        <xs:attribute name="message" type="xs:string"/>
        <xs:attribute name="type" type="xs:string"/>
      </xs:extension>
    </xs:simpleContent>
  </xs:complexType>
  <xs:attributeGroup name="counts">
    <xs:attribute name="failures" type="xs:nonNegativeInteger"/>
    <xs:attribute name="errors" type="xs:nonNegativeInteger"/>
    <xs:attribute name="time" type="xs:decimal"/>
  </xs:attributeGroup>
  <xs:element name="testsuites">
    <xs:complexType>
      <xs:sequence>
        <xs:element name="testsuite" minOccurs="0" maxOccurs="unbounded">
          <xs:complexType>
            <xs:sequence>
              <xs:element name="properties" minOccurs="0"/>
              <xs:element name="testcase" minOccurs="0" maxOccurs="unbounded">
                <xs:complexType>
                  <xs:sequence>
                    <xs:choice minOccurs="0" maxOccurs="unbounded">
                      <xs:element name="skipped" type="detail"/>
                      <xs:element name="error" type="detail"/>
                      <xs:element name="failure" type="detail"/>
                    </xs:choice>
                    <xs:element name="system-out" type="xs:string" minOccurs="0"/>
                    <xs:element name="system-err" type="xs:string" minOccurs="0"/>
                  </xs:sequence>
                  <xs:attribute name="name" type="xs:string" use="required"/>
                  <xs:attribute name="classname" type="xs:string"/>
                  <xs:attribute name="time" type="xs:decimal"/>
                </xs:complexType>
              </xs:element>
              <xs:element name="system-out" type="xs:string" minOccurs="0"/>
              <xs:element name="system-err" type="xs:string" minOccurs="0"/>
            </xs:sequence>
            <xs:attribute name="name" type="xs:string" use="required"/>
            <xs:attribute name="tests" type="xs:nonNegativeInteger" use="required"/>
            <xs:attributeGroup ref="counts"/>
            <xs:attribute name="skipped" type="xs:nonNegativeInteger"/>
            <xs:attribute name="timestamp" type="xs:dateTime"/>
            <xs:attribute name="hostname" type="xs:string"/>
          </xs:complexType>
        </xs:element>
      </xs:sequence>
      <xs:attribute name="name" type="xs:string"/>
      <xs:attribute name="tests" type="xs:nonNegativeInteger"/>
      <xs:attributeGroup ref="counts"/>
    </xs:complexType>
  </xs:element>
</xs:schema>
"""


def write(tmp_path, text, name='s.yaml'):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def validate_junit(path):
    xmlschema = pytest.importorskip('xmlschema')
    xmlschema.XMLSchema(JUNIT_XSD).validate(str(path))
    from junitparser import JUnitXml
    return JUnitXml.fromfile(str(path))


PASSING = """
scenarios:
  - name: paper
    duration: 3.0
    expect:
      final_error_percent: {max: 1.0}
      max_force: {max: 3000.0}
"""


def test_a_passing_scenario_exits_0_and_writes_valid_junit_and_a_report(tmp_path, capsys):
    path = write(tmp_path, PASSING)
    junit = tmp_path / 'junit.xml'
    code = tool.main(['run', str(path), '--junit', str(junit), '--out', str(tmp_path / 'out')])
    out = capsys.readouterr().out
    assert code == 0, out
    assert 'PASS paper' in out
    xml = validate_junit(junit)
    cases = [case for suite in xml for case in suite]
    assert [c.name for c in cases] == ['paper']
    broken = tmp_path / 'broken.xml'        # the schema does check: a test case needs a name
    broken.write_text(junit.read_text().replace('testcase name="paper"', 'testcase'))
    with pytest.raises(Exception, match='name'):
        validate_junit(broken)
    assert cases[0].is_passed
    report = (tmp_path / 'out' / 'report.md').read_text()
    assert '1 of 1 scenarios pass' in report
    assert (tmp_path / 'out' / 'figures' / 'paper.png').stat().st_size > 1000


def test_the_measured_values_are_the_simulations(tmp_path):
    """final error, max force, end stops against run_sampled's own Result."""
    scenario, = load_scenarios(write(tmp_path, PASSING))
    setup = load_setup()
    dyn = Dynamics(setup.mechanism)
    result = run_sampled(setup, 3.0, 1000.0, dyn=dyn, loop='python')
    trace = run_sim(scenario)
    verdicts = evaluate(trace, scenario.expect)
    final = float(result.final_leg_error_percent(dyn, setup.task.setpoint_lengths).max())
    assert verdicts[0].value == pytest.approx(final, rel=1e-12)
    assert verdicts[1].value == pytest.approx(np.abs(result.forces).max(), rel=1e-12)


def test_each_kind_of_expectation_fails_with_its_value_bound_and_time(tmp_path):
    """One scenario per metric, each bound set to fail; the verdict's value is
    checked against an independent computation from the samples."""
    ref = REPO / 'scenarios' / 'references' / 'six_axis.csv'
    path = write(tmp_path, """
    scenarios:
      - name: bounds
        duration: 4.0
        params: {leg_length_min: 1.5}
        wrench: [{from: 2.0, to: 2.5, force: [0, 0, -3000]}]
        expect:
          final_error_percent: {max: 0.5, to: 3.0}
          tracking_error_rms_m: {max: 0.001}
          tracking_error_max_m: {max: 0.01, from: 1.0}
          settling_time_s: {max: 0.1}
          overshoot_percent: {max: 0.01}
          max_force: {max: 100.0, from: 0.0, to: 1.0}
          endstop_samples: {max: 5}
          missed_cycles: {min: 1}
          lost_messages: {min: 1}
      - name: detector
        duration: 3.5
        control_law: stewart63_ros.examples.fault_detector:CheckedPD
        reference: %s
        faults: [sensor_bias:leg_2:0.01@3.0]
        expect:
          withheld_samples: {max: 3, from: 3.0}
    """ % ref)
    bounds, detector = load_scenarios(path)
    trace = run_sim(bounds)
    verdicts = {v.expectation.metric: v for v in evaluate(trace, bounds.expect)}
    assert not any(v.passed for v in verdicts.values())
    t = trace.times
    err = np.abs(trace.lengths - trace.reference)
    k3 = int(np.argmin(np.abs(t - 3.0)))
    assert verdicts['final_error_percent'].value == pytest.approx(
        np.max(100 * err[k3] / trace.reference[k3]))
    assert verdicts['final_error_percent'].at_s == pytest.approx(3.0)
    late = t >= 1.0 - 1e-9
    assert verdicts['tracking_error_rms_m'].value == pytest.approx(np.sqrt(np.mean(err[late] ** 2)))
    over = np.flatnonzero(err[late].max(axis=1) > 0.01)
    assert verdicts['tracking_error_max_m'].value == pytest.approx(err[late].max())
    assert verdicts['tracking_error_max_m'].at_s == pytest.approx(t[late][over[0]])
    assert verdicts['settling_time_s'].value > 0.1
    assert verdicts['overshoot_percent'].value > 0.01
    forces = np.abs(trace.forces[t <= 1.0 + 1e-9]).max(axis=1)
    assert verdicts['max_force'].value == pytest.approx(forces.max())
    assert verdicts['max_force'].at_s == pytest.approx(t[np.flatnonzero(forces > 100.0)[0]])
    outside = np.flatnonzero(np.any(trace.lengths < 1.5, axis=1))
    assert verdicts['endstop_samples'].value == outside.size > 5
    assert verdicts['endstop_samples'].at_s == pytest.approx(t[outside[5]])
    # the endstop count is the simulation's own (Result.endstop_samples)
    setup = load_setup().replace(leg_length_min=1.5)
    wrench = wrench_samples(bounds.wrench, t)
    assert outside.size == run_sampled(setup, 4.0, 1000.0, loop='python',
                                       wrench=wrench).endstop_samples
    assert verdicts['missed_cycles'].value == 0 and verdicts['lost_messages'].value == 0
    text = verdicts['max_force'].text()
    assert 'max_force = ' in text and '<= 100 N' in text and 'FAIL by' in text and 't = ' in text

    trace = run_sim(detector)
    verdict, = evaluate(trace, detector.expect)
    assert not verdict.passed
    assert verdict.value == trace.withheld[trace.times >= 3.0].sum() > 3
    assert verdict.at_s == pytest.approx(trace.times[np.flatnonzero(trace.withheld)[3]])


def test_a_failing_scenario_exits_1_with_the_failure_in_junit(tmp_path, capsys):
    path = write(tmp_path, """
    scenarios:
      - name: too-strict
        duration: 2.0
        expect:
          max_force: {max: 100.0}
          final_error_percent: {max: 5.0}
    """)
    junit = tmp_path / 'j.xml'
    assert tool.main(['run', str(path), '--junit', str(junit), '--out', str(tmp_path / 'o'),
                      '--no-figures']) == 1
    out = capsys.readouterr().out
    assert 'FAIL too-strict' in out and 'max_force = 233.676 N (<= 100 N' in out
    xml = validate_junit(junit)
    case, = [c for s in xml for c in s]
    failure, = case.result
    assert failure.type == 'ExpectationFailed'
    assert 'max_force = 233.676 N' in failure.message and 'FAIL by 133.676 N' in failure.message
    assert 'final_error_percent' not in failure.message      # it passed


def test_a_law_that_raises_has_every_sample_withheld(tmp_path, capsys):
    path = write(tmp_path, """
    scenarios:
      - name: law-fails
        duration: 1.0
        run: sim
        control_law: stewart63_ros.examples.my_law:Failing
        expect:
          withheld_samples: {max: 0}
    """)
    junit = tmp_path / 'j.xml'
    assert tool.main(['run', str(path), '--junit', str(junit), '--out', str(tmp_path / 'o'),
                      '--no-figures']) == 1
    # a law that raises on every sample: every sample withheld, the run finishes
    case, = [c for s in validate_junit(junit) for c in s]
    assert 'withheld_samples = 1001' in case.result[0].message


@pytest.mark.parametrize('text, expected', [
    ('  - name: a\n    duraton: 2\n    expect: {max_force: {max: 1}}\n',
     'scenarios[0] (a).duraton: unknown key (did you mean duration?)'),
    ('  - name: a\n    expect: {max_forse: {max: 1}}\n',
     'scenarios[0] (a).expect.max_forse: unknown metric (did you mean max_force?)'),
    ('  - name: a\n    expect: {max_force: {mx: 1}}\n',
     'expect.max_force.mx: unknown key (did you mean max?)'),
    ('  - name: a\n    params: {platfrom_mass: 3}\n    expect: {max_force: {max: 1}}\n',
     'params.platfrom_mass: unknown parameter (did you mean platform_mass?)'),
    ('  - name: a\n    run: lockstpe\n    expect: {max_force: {max: 1}}\n',
     "run: 'lockstpe' is not one of sim, lockstep, realtime (did you mean lockstep?)"),
    ('  - name: a\n    faults: [sensor_stuck:leg_1@1]\n'
     '    expect: {trip: {cause: tracking_eror, within: 9}}\n',
     "expect.trip.cause: unknown trip cause 'tracking_eror' (did you mean tracking_error?)"),
    ('  - name: a\n    faults: [sensor_stuck:leg_1@1]\n'
     '    expect: {trip: {cause: stroke, whithin: 9}}\n',
     'expect.trip.whithin: unknown key (did you mean within?)'),
    ('  - name: a\n    expect: {trip: {cause: stroke, within: 9}}\n',
     'expect.trip.after: the scenario has no fault to count from'),
    ('  - name: a\n    expect: {trip: {cause: stroke, within: 2.5, after: 1}}\n',
     'expect.trip.within: a whole number of samples'),
    ('  - name: a\n    expect: {no_trip: {max: 0}}\n', 'expect.no_trip: expected true'),
    ('  - name: a\n    expect: {no_trpi: true}\n', 'unknown metric (did you mean no_trip?)'),
    ('  - name: a\n    params: {trip_force: 100}\n    expect: {max_force: {max: 1}}\n',
     'params.trip_force: read by the supervisor, which runs only in a scenario that '
     'expects a trip'),
    ('  - name: a\n    params: {request_timeout: 1}\n    expect: {no_trip: true}\n',
     'params.request_timeout: the supervisor node\'s only, not sim\'s'),
    ('  - name: a\n    params: {descent_speed: 0.9}\n    expect: {no_trip: true}\n',
     'descent_speed: 0.9 m/s is not below trip_leg_speed'),
    ('  - name: a\n    expect: {max_force: {max: 1}, max_force: {max: 2}}\n',
     'max_force: given twice in one mapping'),
    ('  - name: a\n    params: {sensor_noise: 0.001}\n    expect: {max_force: {max: 1}}\n',
     'params.sensor_noise: read by the plant node only, not by sim'),
    ('  - name: a\n    faults: [sensor_stuk:leg_1]\n    expect: {max_force: {max: 1}}\n',
     'faults: '),
    ('  - name: a\n    duration: 2\n    expect: {max_force: {max: 1, from: 1, to: 3}}\n',
     'must lie inside the run'),
    ('  - name: a\n    expect: {lost_messages: {max: 0, from: 1}}\n',
     'counts the whole run'),
    ('  - name: a\n    duration: 2\n    wrench: [{from: 2, to: 3, force: [0, 0, 1]}]\n'
     '    expect: {max_force: {max: 1}}\n', 'it would never act'),
    ('  - name: a\n    run: lockstep\n    wrench: [{force: [0, 0, 1]}]\n'
     '    expect: {max_force: {max: 1}}\n', 'a wrench schedule runs in sim only'),
    ('  - name: a\n    matrix: {params.platform_mas: [1, 2]}\n    expect: {max_force: {max: 1}}\n',
     'platform_mas: unknown parameter (did you mean platform_mass?)'),
    ('  - name: a\n    params: {platform_mass: -3}\n    expect: {max_force: {max: 1}}\n',
     'platform_mass'),
    ('  - name: a\n    bus: canopen\n    expect: {max_force: {max: 1}}\n',
     'bus: a scenario runs over the bus on the rig: run: lockstep or realtime, not sim'),
    ('  - name: a\n    run: lockstep\n    bus: canopn\n    expect: {max_force: {max: 1}}\n',
     "bus: 'canopn' is not one of canopen (did you mean canopen?)"),
    ('  - name: a\n    run: lockstep\n    faults: [bus_emcy:leg_3:0x2310@0.5]\n'
     '    expect: {max_force: {max: 1}}\n', 'it needs bus: canopen'),
])
def test_a_bad_file_gets_one_line_naming_the_key_and_exit_2(tmp_path, capsys, text, expected):
    path = write(tmp_path, 'scenarios:\n' + text)
    assert tool.main(['run', str(path), '--out', str(tmp_path / 'o')]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert err.startswith('scenario: error: %s' % path)
    assert expected in err, err
    assert not (tmp_path / 'o').exists()


def test_a_matrix_expands_to_one_scenario_per_combination_named_by_its_values(tmp_path):
    path = write(tmp_path, """
    scenarios:
      - name: m
        duration: 1.0
        matrix:
          control_law: [pd, pd_gravity]
          params.platform_mass: [10.0, 20.0]
        expect: {max_force: {max: 3000}}
    """)
    scenarios = load_scenarios(path)
    assert [s.name for s in scenarios] == [
        'm[control_law=pd,platform_mass=10]', 'm[control_law=pd,platform_mass=20]',
        'm[control_law=pd_gravity,platform_mass=10]', 'm[control_law=pd_gravity,platform_mass=20]']
    assert scenarios[3].control_law == 'pd_gravity' and scenarios[3].params == {
        'platform_mass': 20.0}
    # the mass takes effect: pd_gravity's holding forces grow with it
    forces = [evaluate(run_sim(s), s.expect)[0].value for s in scenarios[2:]]
    assert forces[1] > forces[0]


def test_the_wrench_schedule_is_the_python_loops_with_the_wrench(tmp_path):
    """The compiled loop in segments of one wrench each == Dynamics.step per
    sample with that sample's wrench (the plant node's arithmetic)."""
    scenario, = scenarios_from_dict({
        'name': 'push', 'duration': 1.0, 'wrench': [
            {'from': 0.2, 'to': 0.5, 'force': [0, 0, -200]},
            {'from': 0.5, 'to': 0.7, 'torque': [5, 0, 0]}],
        'expect': {'max_force': {'max': 3000}}})
    trace = run_sim(scenario)
    setup = load_setup()
    wrench = wrench_samples(scenario.wrench, trace.times)
    assert wrench[200, 2] == -200 and wrench[199, 2] == 0 and wrench[500, 3] == 5
    reference = run_sampled(setup, 1.0, 1000.0, loop='python', wrench=wrench)
    plain = run_sampled(setup, 1.0, 1000.0)
    np.testing.assert_array_equal(trace.forces, reference.forces)
    assert np.abs(trace.forces - plain.forces).max() > 1.0      # the push took effect
    with pytest.raises(ValueError, match='wrench must be'):
        run_sampled(setup, 1.0, 1000.0, wrench=wrench[:-1])


def test_same_file_same_values_and_parallel_equals_serial():
    scenarios = tool.load_files([REPO / 'scenarios' / 'paper.yaml'])
    scenarios = [dataclasses.replace(s, duration=3.0, expect=tuple(
        e for e in s.expect if (e.t_to or 0) <= 3.0 and (e.t_from or 0) < 3.0))
        for s in scenarios]
    serial = tool.run_all(scenarios, jobs=1, keep_traces=False)
    again = tool.run_all(scenarios, jobs=1, keep_traces=False)
    parallel = tool.run_all(scenarios, jobs=2, keep_traces=False)

    def values(outcomes):
        return [(o.scenario.name, [(v.value, v.passed, v.at_s) for v in o.verdicts])
                for o in outcomes]
    assert values(serial) == values(again) == values(parallel)


@pytest.mark.slow
def test_a_dask_cluster_gives_the_serial_verdicts():
    distributed = pytest.importorskip('distributed')
    scenarios = tool.load_files([REPO / 'scenarios' / 'paper.yaml'])[:2]
    scenarios = [dataclasses.replace(s, duration=1.0, expect=tuple(
        e for e in s.expect if (e.t_to or 0) <= 1.0 and (e.t_from or 0) < 1.0))
        for s in scenarios]
    cluster = distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                       host='127.0.0.1', dashboard_address=None)
    try:
        remote = tool.run_all(scenarios, scheduler=cluster.scheduler_address, keep_traces=False)
    finally:
        cluster.close()
    here = tool.run_all(scenarios, keep_traces=False)
    assert [[(v.value, v.passed) for v in o.verdicts] for o in remote] == [
        [(v.value, v.passed) for v in o.verdicts] for o in here]


def test_a_missing_file_is_one_line_and_exit_2(tmp_path, capsys):
    assert tool.main(['run', str(tmp_path / 'none.yaml')]) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'none.yaml: cannot read (No such file or directory)' in err


@pytest.mark.slow
def test_the_package_suite_passes_and_gives_a_report(tmp_path):
    """`make test` runs the package's own scenarios (sim), as a CI job would."""
    files = sorted(str(p) for p in (REPO / 'scenarios').glob('*.yaml'))
    junit = tmp_path / 'suite.xml'
    proc = subprocess.run([sys.executable, '-m', 'stewart63_ros.tools.scenario', 'run', *files,
                           '--junit', str(junit), '--out', str(tmp_path / 'report'),
                           '--jobs', '2'], capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    xml = validate_junit(junit)
    names = [c.name for s in xml for c in s]
    assert 'paper' in names and 'track-computed_torque' in names
    assert sum(n.startswith('detect[') for n in names) == 4
    # the supervisor's trips: each provoked cause, and the paper's run without one
    assert {'paper-supervised', 'trip-sensor_stuck', 'trip-sensor_dropout', 'trip-actuator_dead',
            'trip-stroke', 'trip-pose_box'} <= set(names)
    assert sum(n.startswith('trip-detector[') for n in names) == 4
    assert (tmp_path / 'report' / 'report.md').read_text().count('![') == len(names)


@pytest.mark.slow
def test_a_lab_runs_scenarios_from_its_own_pytest_file(tmp_path):
    """The pytest plugin (entry point pytest11): a file and a dict, one pass, one fail."""
    write(tmp_path, PASSING, 'mine.yaml')
    (tmp_path / 'test_my_controller.py').write_text(textwrap.dedent("""
        def test_file(run_scenarios):
            outcomes = run_scenarios('mine.yaml')
            assert outcomes[0].verdicts[0].value < 1.0

        def test_built_in_python(run_scenarios):
            run_scenarios({'name': 'strict', 'duration': 1.0,
                           'expect': {'max_force': {'max': 100.0}}})
    """))
    proc = subprocess.run([sys.executable, '-m', 'pytest', '-q', '-p', 'no:cacheprovider',
                           '-p', 'no:xdist', '--scenario-junit', str(tmp_path / 'j.xml'),
                           str(tmp_path)], capture_output=True, text=True, cwd=tmp_path,
                          timeout=600)
    out = proc.stdout + proc.stderr
    assert '1 failed, 1 passed' in out, out
    assert 'strict: max_force = 233.676 N (<= 100 N' in out, out
    names = [c.name for s in validate_junit(tmp_path / 'j.xml') for c in s]
    assert names == ['paper', 'strict']


def test_scenario_errors_are_scenarioerror():
    with pytest.raises(ScenarioError, match='matrix'):
        from stewart63_ros.core.scenarios.parsing import scenario_from_dict
        scenario_from_dict({'name': 'a', 'matrix': {'duration': [1]}, 'expect': {}})


def test_a_run_that_diverges_is_an_error_in_junit_and_exit_1(tmp_path, capsys):
    path = write(tmp_path, """
    scenarios:
      - name: unstable
        duration: 1.0
        params: {kp: [1.0e9, 1.0e9, 1.0e9, 1.0e9, 1.0e9, 1.0e9], max_force: 1.0e12}
        expect:
          max_force: {max: 3000}
    """)
    junit = tmp_path / 'j.xml'
    assert tool.main(['run', str(path), '--junit', str(junit), '--out', str(tmp_path / 'o')]) == 1
    assert 'the run failed: the simulation diverged' in capsys.readouterr().out
    case, = [c for s in validate_junit(junit) for c in s]
    error, = case.result
    assert error.type == 'RunFailed' and 'diverged' in error.message


# -- the supervisor's trips ------------------------------------------------------------------
SIX_AXIS = REPO / 'scenarios' / 'references' / 'six_axis.csv'


def test_trip_expectations_give_cause_sample_and_latency_beside_the_bound(tmp_path, capsys):
    """The trip's sample against the supervisor's rule (a dropout trips once no
    reading came for stale_lengths_ms) and against the trace (the first sample
    with a leg outside the soft stroke); each way a trip expectation fails."""
    path = write(tmp_path, """
    scenarios:
      - name: dropout
        duration: 1.0
        faults: [sensor_dropout:leg_2@0.5-0.6]
        params: {stale_lengths_ms: 30.0}
        expect:
          trip: {cause: lengths_stale, within: 29}
          no_trip: true
      - name: wrong-cause
        duration: 1.0
        faults: [sensor_dropout:leg_2@0.5-0.6]
        expect:
          trip: {cause: tracking_error, within: 100}
      - name: late
        duration: 1.0
        faults: [sensor_dropout:leg_2@0.5-0.6]
        expect:
          trip: {cause: lengths_stale, within: 10}
      - name: early
        duration: 1.0
        params: {stale_lengths_ms: 5.0}
        faults: [sensor_dropout:leg_2@0.2-0.3]
        expect:
          trip: {cause: lengths_stale, within: 10, after: 0.5}
      - name: none
        duration: 1.0
        expect:
          trip: {cause: stroke, within: 100, after: 0.5}
      - name: stroke
        duration: 3.0
        control_law: pd_gravity
        reference: %s
        params: {stroke_margin: 0.27}
        expect:
          trip: {cause: stroke, within: 1000, after: 2.0}
    """ % SIX_AXIS)
    junit = tmp_path / 'j.xml'
    assert tool.main(['run', str(path), '--junit', str(junit), '--out', str(tmp_path / 'o')]) == 1
    out = capsys.readouterr().out
    outcomes = {o.scenario.name: o for o in tool.run_all(load_scenarios(path))}
    # 30 ms without a reading: sample 500 + 29 (0.5 s at 1 kHz), safe force at once
    trip, none = outcomes['dropout'].verdicts
    assert (trip.value, trip.passed, trip.at_s) == (29.0, True, None)
    assert trip.measured == 'lengths_stale at sample 529 (t = 0.5290 s; safe force after 0 samples)'
    assert outcomes['dropout'].trace.trips[0].latency_samples == 0
    assert (none.value, none.passed, none.at_s) == (1.0, False, 0.529)
    assert 'no_trip = 1 trip: lengths_stale at sample 529' in none.text()
    assert 'none expected): FAIL at t = 0.5290 s' in none.text()
    wrong, = outcomes['wrong-cause'].verdicts
    assert (wrong.value, wrong.passed, wrong.at_s) == (19.0, False, 0.519)
    assert wrong.why == 'the cause is lengths_stale, not tracking_error'
    late, = outcomes['late'].verdicts
    assert (late.value, late.passed, late.why) == (19.0, False, 'late by 9 samples')
    assert late.text().startswith('trip = lengths_stale at sample 519 (t = 0.5190 s; safe force '
                                  'after 0 samples), +19 samples (lengths_stale within 10 samples '
                                  'of the fault sensor_dropout:leg_2@0.5-0.6): FAIL (late by 9 '
                                  'samples) at t = 0.5190 s')
    early, = outcomes['early'].verdicts
    assert (early.value, early.passed) == (-296.0, False)
    assert early.why == 'it tripped 296 samples before t = 0.5 s'
    nothing, = outcomes['none'].verdicts
    assert np.isnan(nothing.value) and not nothing.passed and nothing.at_s == 0.6
    assert nothing.text() == ('trip = no trip (stroke within 100 samples of t = 0.5 s): '
                              'FAIL (no trip) at t = 0.6000 s')
    # the stroke trip: the first sample with a leg outside the soft stroke
    stroke = outcomes['stroke']
    soft_min = load_setup().mechanism.leg_length_min + 0.27
    first = int(np.flatnonzero(stroke.trace.lengths.min(axis=1) < soft_min)[0])
    assert stroke.trace.trips[0].sample == first
    assert stroke.verdicts[0].value == first - 2000 and stroke.verdicts[0].passed
    # the same lines in the output, JUnit and the report
    assert 'trip = lengths_stale at sample 519' in out
    cases = {c.name: c for s in validate_junit(junit) for c in s}
    assert 'FAIL (late by 9 samples) at t = 0.5190 s' in cases['late'].result[0].message
    assert cases['stroke'].is_passed
    report = (tmp_path / 'o' / 'report.md').read_text()
    assert ('| trip | lengths_stale within 10 samples of the fault sensor_dropout:leg_2@0.5-0.6 | '
            'lengths_stale at sample 519 (t = 0.5190 s; safe force after 0 samples), +19 samples '
            '| 0.5-0.51 | **FAIL** at 0.5190 s: late by 9 samples |') in report


def test_sim_runs_the_supervisor_as_run_supervised_does(tmp_path):
    """A scenario's supervised run is core.machine.supervisor.run_supervised with the
    limits of its params, sample for sample; the limits take effect."""
    from stewart63_ros.core.controllers.laws import Controller
    from stewart63_ros.core.controllers.reference import Reference
    from stewart63_ros.core.machine.faults import FaultModel, parse_faults
    from stewart63_ros.core.machine.supervisor import Supervisor, limits_from_params, run_supervised
    scenario, = scenarios_from_dict({
        'name': 'push', 'duration': 2.5, 'faults': ['actuator_weak:leg_1:0.5@1.0'],
        'wrench': [{'from': 1.5, 'force': [200.0, 0, 0]}],
        'params': {'pose_box': [-0.02, -0.3, 0.5, 0.02, 0.3, 1.6]},
        'expect': {'trip': {'cause': 'pose_box', 'within': 1000, 'after': 1.5}}})
    trace = run_sim(scenario)
    setup = load_setup()
    mech, start = setup.mechanism, (setup.task.initial_position, setup.task.initial_rotation)
    params = {'pose_box': [-0.02, -0.3, 0.5, 0.02, 0.3, 1.6]}
    from stewart63_ros.core.mechanics.fk import FKTracker
    tracker = FKTracker(mech, *start)

    def pose(lengths):
        result = tracker.solve(lengths)
        return result.position, result.rotation
    supervisor = Supervisor(setup, limits_from_params(mech, params), 1000.0,
                            Reference.constant_lengths(mech, setup.task.setpoint_lengths,
                                                       near=start), pose)
    out = run_supervised(setup, supervisor, 2.5, 1000.0, FaultModel(
        parse_faults(['actuator_weak:leg_1:0.5@1.0']), 1000.0), Controller(setup),
        wrench=wrench_samples(scenario.wrench, trace.times))
    np.testing.assert_array_equal(trace.forces, out['forces'])
    np.testing.assert_array_equal(trace.lengths, out['lengths'])
    assert [(t.cause, t.sample) for t in trace.trips] == [
        (t.cause, round(t.sample_ns * 1e-6)) for t in supervisor.trips]
    assert trace.trips[0].cause == 'pose_box' and trace.trips[0].sample > 1500
    # without the push the box holds: the wrench acts in the supervised loop
    calm = run_sim(dataclasses.replace(scenario, wrench=()))
    assert calm.trips == ()


# -- a reference from a topic file ---------------------------------------------------------
def write_reference_bag(path, times, poses, *topics):
    """A bag holding the motion as one pose_trajectory, and/or as pose_setpoint messages."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from scipy.spatial.transform import Rotation

    from stewart63_ros import bagio
    store = bagio.typestore()
    t = store.types
    quats = Rotation.from_euler('ZYX', poses[:, :2:-1]).as_quat()     # R = Rz Ry Rx

    def header(ns):
        return t['std_msgs/msg/Header'](stamp=t['builtin_interfaces/msg/Time'](
            sec=ns // 10**9, nanosec=ns % 10**9), frame_id='base')
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        if 'pose_trajectory' in topics:
            msg_t = t['trajectory_msgs/msg/MultiDOFJointTrajectory']
            points = [t['trajectory_msgs/msg/MultiDOFJointTrajectoryPoint'](
                transforms=[t['geometry_msgs/msg/Transform'](
                    translation=t['geometry_msgs/msg/Vector3'](*p[:3]),
                    rotation=t['geometry_msgs/msg/Quaternion'](*q))],
                velocities=[], accelerations=[],
                time_from_start=t['builtin_interfaces/msg/Duration'](
                    sec=int(round(s * 1e9)) // 10**9, nanosec=int(round(s * 1e9)) % 10**9))
                for s, p, q in zip(times, poses, quats)]
            conn = writer.add_connection('/pose_trajectory', msg_t.__msgtype__, typestore=store)
            msg = msg_t(header=header(5 * 10**9), joint_names=['platform'], points=points)
            writer.write(conn, 5 * 10**9, store.serialize_cdr(msg, msg.__msgtype__))
        if 'pose_setpoint' in topics:
            msg_t = t['geometry_msgs/msg/PoseStamped']
            conn = writer.add_connection('/pose_setpoint', msg_t.__msgtype__, typestore=store)
            for s, p, q in zip(times, poses, quats):
                ns = 7 * 10**9 + int(round(s * 1e9))
                msg = msg_t(header=header(ns), pose=t['geometry_msgs/msg/Pose'](
                    position=t['geometry_msgs/msg/Point'](*p[:3]),
                    orientation=t['geometry_msgs/msg/Quaternion'](*q)))
                writer.write(conn, ns, store.serialize_cdr(msg, msg.__msgtype__))


@pytest.mark.parametrize('topic', ['pose_trajectory', 'pose_setpoint'])
def test_a_topic_file_reference_gives_the_csvs_verdicts_and_values(tmp_path, topic):
    from stewart63_ros.core.controllers.reference_files import read_reference_csv
    times, poses = read_reference_csv(SIX_AXIS)
    write_reference_bag(tmp_path / 'motion', times, poses, topic)
    doc = {'name': 'track', 'duration': 4.0, 'control_law': 'pd_gravity',
           'faults': ['sensor_stuck:leg_2@3.0'],
           'params': {'trip_tracking_error': 0.01, 'trip_tracking_time': 0.05},
           'expect': {'tracking_error_max_m': {'max': 0.007, 'from': 2.0, 'to': 2.99},
                      'tracking_error_rms_m': {'max': 0.003, 'from': 2.0, 'to': 2.99},
                      'trip': {'cause': 'tracking_error', 'within': 300}}}
    from_csv, = scenarios_from_dict(dict(doc, reference=str(SIX_AXIS)))
    from_bag, = scenarios_from_dict(dict(doc, reference='motion'), tmp_path)
    csv_trace, bag_trace = run_sim(from_csv), run_sim(from_bag)
    np.testing.assert_allclose(bag_trace.reference, csv_trace.reference, rtol=0, atol=1e-12)
    csv_verdicts = evaluate(csv_trace, from_csv.expect)
    bag_verdicts = evaluate(bag_trace, from_bag.expect)
    assert [v.passed for v in bag_verdicts] == [v.passed for v in csv_verdicts] == [
        True, True, True]
    for a, b in zip(bag_verdicts, csv_verdicts):
        assert a.value == pytest.approx(b.value, rel=1e-9, abs=1e-12)
        assert a.measured == b.measured and a.at_s == b.at_s
    assert bag_trace.trips == csv_trace.trips


@pytest.mark.parametrize('folder, expected', [
    ('empty', 'empty: not a bag (no metadata.yaml)'),
    ('both', 'both: holds both pose_trajectory and pose_setpoint: a reference is one of them'),
])
def test_a_topic_file_it_cannot_follow_is_one_line_and_exit_2(tmp_path, capsys, folder,
                                                              expected):
    from stewart63_ros.core.controllers.reference_files import read_reference_csv
    times, poses = read_reference_csv(SIX_AXIS)
    write_reference_bag(tmp_path / 'both', times, poses, 'pose_setpoint', 'pose_trajectory')
    (tmp_path / 'empty').mkdir()
    path = write(tmp_path, """
    scenarios:
      - name: a
        reference: %s
        expect: {max_force: {max: 1}}
    """ % folder)
    assert tool.main(['run', str(path), '--out', str(tmp_path / 'o')]) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'reference: ' in err and expected in err, err


def test_trajectory_poses_turn_twists_into_euler_rates():
    """core.controllers.reference.trajectory_poses (the controller's and the topic file's
    conversion) against finite differences of scipy's rotations: omega from
    R(t + h) R(t)^T, theta's rates from theta(t +- h), 2 pi jumps unwrapped."""
    from scipy.spatial.transform import Rotation

    from stewart63_ros.core.controllers.reference_files import trajectory_poses

    def theta(t):       # R = Rz Ry Rx; theta_z passes pi (a jump in the quaternion's Euler angles)
        return np.array([0.2 * np.sin(t), 0.1 * t - 0.05 * t ** 2, 2.8 + 0.4 * t])

    def rot(t):
        return Rotation.from_euler('ZYX', theta(t)[::-1])

    times = np.linspace(0.0, 2.0, 9)
    h = 1e-5

    def omega(t):       # base frame: R(t + h) R(t)^T = exp([omega] h)
        return ((rot(t + h) * rot(t - h).inv()).as_rotvec()) / (2 * h)
    quats = np.array([rot(t).as_quat() for t in times])
    twists = np.array([np.r_[0.1, 0.0, -0.2, omega(t)] for t in times])
    accels = np.array([np.r_[0.0, 0.0, 0.0, (omega(t + 1e-3) - omega(t - 1e-3)) / 2e-3]
                       for t in times])
    poses, rates, accs = trajectory_poses(np.zeros((9, 3)), quats, twists, accels)
    np.testing.assert_allclose(poses[:, 3:], [theta(t) for t in times], atol=1e-12)
    want = [(theta(t + h) - theta(t - h)) / (2 * h) for t in times]
    np.testing.assert_allclose(rates[:, 3:], want, atol=1e-6)
    np.testing.assert_allclose(rates[:, :3], twists[:, :3])
    want = [(theta(t + 1e-3) - 2 * theta(t) + theta(t - 1e-3)) / 1e-6 for t in times]
    np.testing.assert_allclose(accs[:, 3:], want, atol=1e-4)


def test_the_summarys_wall_time_is_the_time_the_user_waited(tmp_path):
    """`scenario run`'s last line: the wall time from the command's start to its
    end (it gave the runs' 3.7 s for a 23 s wait), with the figures' share apart."""
    import re
    import time
    path = write(tmp_path, '''
        scenarios:
          - name: short
            duration: 0.2
            expect: {max_force: {max: 3000.0}}
        ''')
    started = time.perf_counter()
    done = subprocess.run([sys.executable, '-m', 'stewart63_ros.tools.scenario', 'run',
                           str(path), '--out', str(tmp_path / 'o')], capture_output=True,
                          text=True, timeout=300)
    waited = time.perf_counter() - started
    assert done.returncode == 0, done.stderr
    line = done.stdout.strip().splitlines()[-1]
    found = re.search(r'; ([\d.]+) s wall in all: start-up and files ([\d.]+) s, runs ([\d.]+) '
                      r's, report and figures ([\d.]+) s;', line)
    assert found, line
    in_all, startup, runs, report = map(float, found.groups())
    # The process's own life: all but the fork before it and the exit after (no
    # bound on any part: this machine's timing is not the code's).
    assert 0.5 * waited - 1.0 <= in_all <= waited, (in_all, waited, line)
    assert abs(startup + runs + report - in_all) < 0.05 * in_all + 0.02, line
    assert startup > 0 and runs > 0 and report > 0, line
