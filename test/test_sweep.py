"""`sweep`: each row is a single `sim` run, failures are marked, Dask gives the same rows.

- a row's final error is `sim`'s on a parameter file with that row's values
  (``sweep_report.write_run_parameters``): the same printed digits, and in-process
  the same bits;
- summary.json's percentiles are numpy's of runs.csv's columns;
- a run whose law raises or whose integration fails is a row with
  ``diverged`` 1 and its reason, and the sweep goes on;
- on a Dask ``LocalCluster`` of two worker processes on the loopback the
  rows are those of the local processes, bit for bit;
- bad input: one line naming the problem, exit status 2.
"""
from __future__ import annotations

import contextlib
import csv
import io
import json

import numpy as np
import pytest

from stewart63_ros.core.analysis import sweep, sweep_plan, sweep_report
from stewart63_ros.core.controllers.control import pd_law
from stewart63_ros.core.controllers.simulate import run_continuous, run_sampled
from stewart63_ros.core.mechanics.dynamics import Dynamics
from stewart63_ros.core.plumbing.params import load_setup
from stewart63_ros.tools import sim
from stewart63_ros.tools import sweep as sweep_tool


class FlakyLaw:
    """Eq. (40) that raises after 0.2 s on a platform heavier than 17 kg."""

    parameters = ()

    def __init__(self, mech, params):
        self.mech = mech
        self.kp = np.array(params['kp'], float)
        self.kv = np.array(params['kv'], float)

    def __call__(self, t, lengths, rates, ref):
        if self.mech.platform_mass > 17.0 and t > 0.2:
            raise ValueError('too heavy for this law')
        return pd_law(lengths, rates, ref.lengths, self.kp, self.kv, self.mech.max_force)


def read_rows(path):
    with open(path) as fh:
        return list(csv.DictReader(fh))


def run_tool(argv):
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        status = sweep_tool.main(argv)
    return status, out.getvalue()


def sim_error(params_file, tmp_path) -> str:
    """`sim`'s printed positioning error for a parameter file."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert sim.main(['--params', str(params_file), '--out', str(tmp_path / 'sim'),
                         '--no-figure']) == 0
    line = next(s for s in out.getvalue().splitlines()
                if s.startswith('positioning_error_percent'))
    return line.split()[-1]


def test_vary_is_parsed_and_draws_are_reproducible():
    var = sweep_plan.parse_vary('kp[2]=3000:5000')
    assert (var.name, var.index, var.low, var.high, var.key) == ('kp', 2, 3000.0, 5000.0,
                                                                 'kp[2]')
    assert sweep_plan.parse_vary(' platform_mass = 10:20').index is None
    variations = [var, sweep_plan.parse_vary('platform_mass=10:20')]
    a = sweep_plan.draw_values(variations, 50, seed=4)
    assert np.array_equal(a, sweep_plan.draw_values(variations, 50, seed=4))
    assert np.all((a[:, 0] >= 3000) & (a[:, 0] <= 5000) & (a[:, 1] >= 10) & (a[:, 1] <= 20))
    grid = sweep_plan.draw_values(variations, 10, grid=True)      # round(sqrt(10)) = 3 per key
    assert grid.shape == (9, 2)
    assert sorted(set(grid[:, 0])) == [3000.0, 4000.0, 5000.0]


def test_settling_time_of_a_known_response():
    times = np.linspace(0.0, 10.0, 1001)
    lengths = np.tile(1.0 - np.exp(-times)[:, None], (1, 6))
    # travel 1 - e^-10, band 2 % of it: |e^-t - e^-10| <= 0.02 (1 - e^-10) from
    # t = -ln(0.02 + 0.98 e^-10) = 3.9097 s, i.e. the sample at 3.91 s
    assert sweep.settling_time(times, lengths) == pytest.approx(3.91, abs=1e-9)
    ringing = np.tile(np.sin(8 * times)[:, None], (1, 6))
    assert np.isnan(sweep.settling_time(times, ringing))


@pytest.mark.slow      # forks worker processes
def test_rows_equal_single_sim_runs(setup, tmp_path, default_params_file):
    out = tmp_path / 'sweep'
    status, text = run_tool(['--runs', '6', '--vary', 'platform_mass=12:19', '--vary',
                             'kv[1]=200:400', '--seed', '3', '--workers', '2',
                             '--out', str(out)])
    assert status == 0 and '6 runs in' in text
    rows = read_rows(out / 'runs.csv')
    assert list(rows[0]) == ['run', 'param.platform_mass', 'param.kv[1]', 'final_error_percent',
                             'max_force', 'settling_time_s', 'endstop_samples', 'diverged',
                             'failure']
    assert [int(r['run']) for r in rows] == list(range(6))
    variations = [sweep_plan.parse_vary('platform_mass=12:19'),
                  sweep_plan.parse_vary('kv[1]=200:400')]
    for row in rows[:3]:
        values = [float(row['param.platform_mass']), float(row['param.kv[1]'])]
        params = tmp_path / ('run%s.yaml' % row['run'])
        sweep_report.write_run_parameters(default_params_file, params, variations, values)
        # sim prints round(error, 4)
        assert float(sim_error(params, tmp_path)) == round(float(row['final_error_percent']), 4)
        # In-process the very same number: sim's arithmetic, bit for bit.
        run_setup = load_setup(params, node_name='plant')
        dyn = Dynamics(run_setup.mechanism)
        result = run_continuous(run_setup, 10.0, dyn=dyn)
        exact = result.final_leg_error_percent(dyn, run_setup.task.setpoint_lengths).max()
        assert float(row['final_error_percent']) == exact
        assert float(row['max_force']) == np.abs(result.forces).max()
        assert int(row['endstop_samples']) == result.endstop_samples
    summary = json.loads((out / 'summary.json').read_text())
    errors = np.array([float(r['final_error_percent']) for r in rows])
    assert summary['columns']['final_error_percent']['p50'] == pytest.approx(
        np.percentile(errors, 50), rel=1e-12)
    assert summary['columns']['param.platform_mass']['p100'] == pytest.approx(
        max(float(r['param.platform_mass']) for r in rows))
    assert summary['runs'] == 6 and summary['diverged_runs'] == 0
    assert (out / 'sweep.png').stat().st_size > 10000


def test_a_run_whose_law_raises_or_that_diverges_is_marked(tmp_path):
    """In this process (one worker): a law raising on heavy platforms, and a
    gain so stiff that the integrator gives up; the other runs finish."""
    status, _ = run_tool(['--runs', '3', '--grid', '--vary', 'platform_mass=10:20',
                          '--control-law', 'test_sweep:FlakyLaw', '--duration', '0.5',
                          '--workers', '1', '--out', str(tmp_path / 'law'), '--no-figure'])
    assert status == 0
    rows = read_rows(tmp_path / 'law' / 'runs.csv')
    assert [r['diverged'] for r in rows] == ['0', '0', '1']
    assert 'the control law failed' in rows[2]['failure'] and 'too heavy' in rows[2]['failure']
    assert rows[2]['final_error_percent'] == 'nan'
    status, _ = run_tool(['--runs', '2', '--grid', '--vary', 'kp[0]=4000:1e9', '--workers',
                          '1', '--out', str(tmp_path / 'stiff'), '--no-figure'])
    assert status == 0
    rows = read_rows(tmp_path / 'stiff' / 'runs.csv')
    assert [r['diverged'] for r in rows] == ['0', '1']
    assert 'integration failed' in rows[1]['failure']
    summary = json.loads((tmp_path / 'stiff' / 'summary.json').read_text())
    assert summary['diverged_runs'] == 1
    assert summary['columns']['final_error_percent']['count'] == 1


@pytest.mark.slow      # a Dask cluster of two worker processes
def test_dask_local_cluster_gives_the_same_rows(tmp_path):
    distributed = pytest.importorskip('distributed')
    argv = ['--runs', '40', '--vary', 'platform_mass=10:20', '--vary',
            'initial_position[0]=-0.05:0.05', '--seed', '11', '--no-figure']
    assert run_tool(argv + ['--out', str(tmp_path / 'local')])[0] == 0
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  host='127.0.0.1', dashboard_address=None) as cluster:
        status, text = run_tool(argv + ['--scheduler', cluster.scheduler_address,
                                        '--out', str(tmp_path / 'dask')])
    assert status == 0 and 'dask tcp://127.0.0.1' in text and '2 workers' in text
    assert (tmp_path / 'dask' / 'runs.csv').read_text() == \
        (tmp_path / 'local' / 'runs.csv').read_text()


@pytest.mark.parametrize('argv, words', [
    (['--runs', '0'], '--runs must be at least 1'),
    (['--runs', '5', '--vary', 'platfrom_mass=10:20'], 'unknown parameter platfrom_mass'),
    (['--runs', '5', '--vary', 'platform_mass=-1:20'], 'outside the valid range'),
    (['--runs', '5', '--vary', 'initial_position[2]=0.1:1.0'], 'outside the stroke'),
    (['--runs', '5', '--vary', 'kp=1:2'], 'vary one element'),
    (['--runs', '5', '--vary', 'kp[6]=1:2'], 'index 0 to 5'),
    (['--runs', '5', '--vary', 'kp[0]=5:1'], 'above HI'),
    (['--runs', '5', '--vary', 'clock_mode=1:2'], 'the runs do not read clock_mode'),
    (['--runs', '5', '--scheduler', 'bogus'], '--scheduler bogus: not a scheduler address'),
    (['--runs', '5', '--fault', 'actuator_dead:leg_{0..6}@1'], "unknown leg 'leg_0'"),
    (['--runs', '5', '--fault', 'actuator_dead:leg_2@U(5,1)'], '5 is above 1'),
    (['--runs', '5', '--fault', ''], '--fault: empty'),
    (['--runs', '5', '--fault', 'sensor_bias:leg_2:{0.1,x}'], "'x' is not a number"),
    (['--runs', '5', '--fault', 'actuator_dead:leg_2', '--control', 'continuous'],
     'use --control sampled'),
    (['--runs', '5', '--control-law', 'nope'], 'unknown law'),
    (['--runs', '5', '--duration', '0'], '--duration'),
])
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, argv, words):
    assert sweep_tool.main(argv + ['--out', str(tmp_path)]) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if 'error' in line]
    assert len(lines) == 1 and words in lines[0] and 'Traceback' not in err, err
    assert not (tmp_path / 'runs.csv').exists()


def test_a_varied_key_never_shares_a_column_with_a_metric(tmp_path):
    """`--vary max_force=...` used to overwrite the max_force metric's column."""
    out = tmp_path / 'force'
    status, text = run_tool(['--runs', '3', '--vary', 'max_force=100:300', '--seed', '2',
                             '--duration', '1', '--workers', '1', '--no-figure',
                             '--out', str(out)])
    assert status == 0
    header = (out / 'runs.csv').read_text().splitlines()[0].split(',')
    assert header == ['run', 'param.max_force'] + list(sweep_report.METRICS) + ['failure']
    summary = json.loads((out / 'summary.json').read_text())
    assert {'param.max_force', 'max_force'} <= set(summary['columns'])
    for row in read_rows(out / 'runs.csv'):
        # the metric is the largest force of the run: at most the varied limit,
        # and the limit itself where the law saturates
        assert float(row['max_force']) <= float(row['param.max_force']) + 1e-9


@pytest.mark.parametrize('key, words', [
    ('sensor_rate=100:1000', 'sensor_rate is read only under --control sampled'),
    ('step_count=1:5', 'the runs do not read step_count'),
    ('use_sim_time=0:1', 'the runs do not read use_sim_time'),
    ('faults=1:2', 'faults are swept with --fault'),
    ('sensor_seed=1:5', 'seeds the noise of faults'),
])
def test_a_key_the_runs_do_not_read_is_refused(tmp_path, capsys, key, words):
    assert sweep_tool.main(['--runs', '3', '--vary', key, '--out', str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and words in err, err
    assert 'keys that can be varied: ' in err and 'platform_mass' in err
    assert not (tmp_path / 'runs.csv').exists()


def test_sensor_rate_takes_effect_under_sampled_control(default_setup, tmp_path, default_mech):
    out = tmp_path / 'rate'
    status, _ = run_tool(['--runs', '2', '--control', 'sampled', '--vary',
                          'sensor_rate=200:1000', '--duration', '1', '--seed', '5',
                          '--workers', '1', '--no-figure', '--out', str(out)])
    assert status == 0
    rows = read_rows(out / 'runs.csv')
    assert rows[0]['settling_time_s'] != rows[1]['settling_time_s']
    dyn = Dynamics(default_mech)
    for row in rows:
        result = run_sampled(default_setup, 1.0, float(row['param.sensor_rate']), dyn=dyn)
        assert float(row['final_error_percent']) == \
            result.final_leg_error_percent(dyn, default_setup.task.setpoint_lengths).max()
    # --rate fixes the control rate: then sensor_rate is not read, and refused
    assert sweep_tool.main(['--runs', '2', '--control', 'sampled', '--rate', '500', '--vary',
                            'sensor_rate=200:1000', '--out', str(tmp_path / 'no')]) == 2


def test_a_zero_gain_is_refused_by_sweep_and_analyze_alike(tmp_path, capsys,
                                                           default_params_file):
    from stewart63_ros.tools import analyze
    assert sweep_tool.main(['--runs', '3', '--vary', 'kp[0]=0:0.001',
                            '--out', str(tmp_path)]) == 2
    assert 'kp is zero on leg_1' in capsys.readouterr().err
    zero = tmp_path / 'zero_kp.yaml'
    sweep_report.write_run_parameters(default_params_file, zero,
                                      [sweep_plan.parse_vary('kp[%d]=0:0' % i) for i in range(6)],
                                      [0.0] * 6)
    assert sweep_tool.main(['--runs', '3', '--params', str(zero),
                            '--out', str(tmp_path)]) == 2
    swept = capsys.readouterr().err.strip()
    assert analyze.main(['modes', '--params', str(zero)]) == 2
    analyzed = capsys.readouterr().err.strip()
    phrase = 'the pd law cannot hold the pose: kp is zero on leg_1'
    assert phrase in swept and phrase in analyzed, (swept, analyzed)
    assert not (tmp_path / 'runs.csv').exists()


def test_fault_patterns_draw_legs_and_times():
    pattern = sweep_plan.parse_fault_pattern('actuator_dead:leg_{1..6}@U(1,5)', 1)
    assert [a.column for a in pattern.axes] == ['fault1.leg', 'fault1.start_s']
    assert pattern.resolve([4.0, 2.5]) == 'actuator_dead:leg_4@2.5'
    values = sweep_plan.draw_values(pattern.axes, 600, seed=7)
    assert set(values[:, 0]) == {1.0, 2.0, 3.0, 4.0, 5.0, 6.0}
    assert np.all((values[:, 1] >= 1) & (values[:, 1] <= 5))
    # each leg about as likely (600 draws: 100 each, +- 4 standard deviations)
    counts = np.bincount(values[:, 0].astype(int))[1:]
    assert np.all(np.abs(counts - 100) < 4 * np.sqrt(100 * 5 / 6)), counts
    grid = sweep_plan.draw_values(pattern.axes, 18, grid=True)      # every leg x 3 times
    assert grid.shape == (18, 2) and sorted(set(grid[:, 0])) == [1, 2, 3, 4, 5, 6]
    bias = sweep_plan.parse_fault_pattern('sensor_bias:leg_2:{-0.01,0.02}@1-U(2,3)', 2)
    assert [a.column for a in bias.axes] == ['fault2.value', 'fault2.end_s']
    assert bias.resolve([0.02, 2.25]) == 'sensor_bias:leg_2:0.02@1-2.25'


@pytest.mark.slow      # 3 faulted runs and 3 sim runs
def test_a_fault_sweep_row_is_a_sim_run_with_that_fault(tmp_path, default_params_file):
    out = tmp_path / 'faults'
    status, text = run_tool(['--runs', '3', '--fault', 'actuator_dead:leg_{1..6}@U(0.5,1.5)',
                             '--duration', '2', '--seed', '4', '--workers', '1',
                             '--no-figure', '--out', str(out)])
    assert status == 0
    rows = read_rows(out / 'runs.csv')
    assert list(rows[0])[:4] == ['run', 'fault1.leg', 'fault1.start_s', 'fault1']
    for row in rows:
        leg, start = int(float(row['fault1.leg'])), float(row['fault1.start_s'])
        assert row['fault1'] == 'actuator_dead:leg_%d@%r' % (leg, start)
        assert row['diverged'] == '0'
        printed = io.StringIO()
        with contextlib.redirect_stdout(printed):
            assert sim.main(['--params', str(default_params_file), '--duration', '2',
                             '--fault', row['fault1'], '--out', str(tmp_path / 'sim'),
                             '--no-figure']) == 0
        line = next(s for s in printed.getvalue().splitlines()
                    if s.startswith('positioning_error_percent'))
        assert float(line.split()[-1]) == round(float(row['final_error_percent']), 4)
    summary = json.loads((out / 'summary.json').read_text())
    assert summary['control'] == 'sampled' and summary['faults'] == [
        'actuator_dead:leg_{1..6}@U(0.5,1.5)']


@pytest.mark.slow      # a Dask scheduler and two worker processes, one killed mid-sweep
def test_a_dask_worker_killed_mid_sweep_is_reported_and_its_runs_done_again(tmp_path):
    """The summary used to say `2 workers` after one of them was killed."""
    import os
    import signal
    import subprocess
    import sys
    import threading
    import time
    distributed = pytest.importorskip('distributed')
    dask_cli = os.path.join(os.path.dirname(sys.executable), 'dask')
    argv = ['--runs', '24', '--fault', 'actuator_dead:leg_{1..6}@U(0.2,0.8)', '--duration',
            '1.5', '--seed', '8', '--no-figure']
    assert run_tool(argv + ['--workers', '1', '--out', str(tmp_path / 'local')])[0] == 0
    with distributed.LocalCluster(n_workers=0, host='127.0.0.1', dashboard_address=None,
                                  processes=True) as cluster, \
            distributed.Client(cluster.scheduler_address) as watcher:
        workers = [subprocess.Popen([dask_cli, 'worker', cluster.scheduler_address,
                                     '--no-nanny', '--nthreads', '1', '--name', 'w%d' % k],
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                   for k in range(2)]
        try:
            watcher.wait_for_workers(2, timeout=120)
            done = {}

            def sweep_on_the_cluster():
                status, text = run_tool(argv + ['--scheduler', cluster.scheduler_address,
                                                '--out', str(tmp_path / 'dask')])
                done.update(status=status, text=text)
            sweep_thread = threading.Thread(target=sweep_on_the_cluster)
            sweep_thread.start()
            # both workers busy with the sweep's runs: kill one of them, hard
            deadline = time.monotonic() + 240
            while time.monotonic() < deadline and not done:
                busy = [w for w, tasks in watcher.processing().items()
                        if any(str(t).startswith('_run_chunk_on_worker') for t in tasks)]
                if len(busy) == 2:
                    break
                time.sleep(0.05)
            assert not done, 'the sweep ended before both workers were busy'
            os.kill(workers[1].pid, signal.SIGKILL)
            sweep_thread.join(timeout=300)
            assert not sweep_thread.is_alive()
        finally:
            for proc in workers:
                if proc.poll() is None:
                    proc.terminate()
                    try:
                        proc.wait(timeout=20)
                    except subprocess.TimeoutExpired:
                        proc.kill()
                        proc.wait()
    assert done['status'] == 0
    text = done['text']
    assert '(dask tcp://127.0.0.1' in text
    assert '1 worker; 1 of the 2 at the start lost mid-sweep' in text, text
    summary = json.loads((tmp_path / 'dask' / 'summary.json').read_text())
    assert (summary['workers'], summary['workers_at_start'], summary['workers_lost']) == (1, 2, 1)
    # the killed worker's runs were done again: every row, bit for bit the local ones
    assert (tmp_path / 'dask' / 'runs.csv').read_text() == \
        (tmp_path / 'local' / 'runs.csv').read_text()
