"""`sweep`: each row is a single `sim` run, failures are marked, Dask gives the same rows.

- a row's final error is `sim`'s on a parameter file with that row's values
  (``sweep.write_run_parameters``): the same printed digits, and in-process
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

from stewart63_ros.core import sweep
from stewart63_ros.core.control import pd_law
from stewart63_ros.core.dynamics import Dynamics
from stewart63_ros.core.params import load_mechanism
from stewart63_ros.core.simulate import run_continuous
from stewart63_ros.tools import sim
from stewart63_ros.tools import sweep as sweep_tool


class FlakyLaw:
    """Eq. (40) that raises after 0.2 s on a platform heavier than 17 kg."""

    parameters = ()

    def __init__(self, mech, params):
        self.mech = mech

    def __call__(self, t, lengths, rates, ref):
        if self.mech.platform_mass > 17.0 and t > 0.2:
            raise ValueError('too heavy for this law')
        m = self.mech
        return pd_law(lengths, rates, ref.lengths, m.kp, m.kv, m.max_force)


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
    var = sweep.parse_vary('kp[2]=3000:5000')
    assert (var.name, var.index, var.low, var.high, var.key) == ('kp', 2, 3000.0, 5000.0,
                                                                 'kp[2]')
    assert sweep.parse_vary(' platform_mass = 10:20').index is None
    variations = [var, sweep.parse_vary('platform_mass=10:20')]
    a = sweep.draw_values(variations, 50, seed=4)
    assert np.array_equal(a, sweep.draw_values(variations, 50, seed=4))
    assert np.all((a[:, 0] >= 3000) & (a[:, 0] <= 5000) & (a[:, 1] >= 10) & (a[:, 1] <= 20))
    grid = sweep.draw_values(variations, 10, grid=True)      # round(sqrt(10)) = 3 per key
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
def test_rows_equal_single_sim_runs(tmp_path, default_params_file):
    out = tmp_path / 'sweep'
    status, text = run_tool(['--runs', '6', '--vary', 'platform_mass=12:19', '--vary',
                             'kv[1]=200:400', '--seed', '3', '--workers', '2',
                             '--out', str(out)])
    assert status == 0 and '6 runs in' in text
    rows = read_rows(out / 'runs.csv')
    assert list(rows[0]) == ['run', 'platform_mass', 'kv[1]', 'final_error_percent',
                             'max_force', 'settling_time_s', 'endstop_samples', 'diverged',
                             'failure']
    assert [int(r['run']) for r in rows] == list(range(6))
    variations = [sweep.parse_vary('platform_mass=12:19'), sweep.parse_vary('kv[1]=200:400')]
    for row in rows[:3]:
        values = [float(row['platform_mass']), float(row['kv[1]'])]
        params = tmp_path / ('run%s.yaml' % row['run'])
        sweep.write_run_parameters(default_params_file, params, variations, values)
        # sim prints round(error, 4)
        assert float(sim_error(params, tmp_path)) == round(float(row['final_error_percent']), 4)
        # In-process the very same number: sim's arithmetic, bit for bit.
        mech = load_mechanism(params, node_name='plant')
        dyn = Dynamics(mech)
        result = run_continuous(mech, 10.0, dyn=dyn)
        exact = result.final_leg_error_percent(dyn, mech.setpoint_lengths).max()
        assert float(row['final_error_percent']) == exact
        assert float(row['max_force']) == np.abs(result.forces).max()
        assert int(row['endstop_samples']) == result.endstop_samples
    summary = json.loads((out / 'summary.json').read_text())
    errors = np.array([float(r['final_error_percent']) for r in rows])
    assert summary['columns']['final_error_percent']['p50'] == pytest.approx(
        np.percentile(errors, 50), rel=1e-12)
    assert summary['columns']['platform_mass']['p100'] == pytest.approx(
        max(float(r['platform_mass']) for r in rows))
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
    (['--runs', '5', '--vary', 'clock_mode=1:2'], 'not a number'),
    (['--runs', '5', '--control-law', 'nope'], 'unknown law'),
    (['--runs', '5', '--duration', '0'], '--duration'),
])
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, argv, words):
    assert sweep_tool.main(argv + ['--out', str(tmp_path)]) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if 'error' in line]
    assert len(lines) == 1 and words in lines[0] and 'Traceback' not in err, err
    assert not (tmp_path / 'runs.csv').exists()
