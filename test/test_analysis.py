"""The linear model, its modes and frequency responses, and the workspace map,
each against something that does not share its arithmetic.

- the linear model against the nonlinear one: a small force (open loop) or
  reference (closed loop) step from the equilibrium, integrated by the
  compiled RK45 at tight tolerances, against the linear step response from
  the matrix exponential; the gap is second order: it shrinks by 4 when the
  step halves (measured 3.9985 and 3.9995 open loop, 3.9984 and 3.9992
  closed loop);
- the frequency response against the nonlinear closed loop driven by a
  sinusoidal reference on leg_1, integrated by scipy's DOP853: gain and phase
  from a least-squares fit over whole periods after the transient (measured:
  within 1.1e-8 of the largest gain at 0.5, 3 and 20 Hz);
- the modes: a computed-torque loop must show its designed error dynamics
  (sqrt(ct_kp) rad/s, damping ct_kd / (2 sqrt(ct_kp))), the pairing and the
  figures of known two-degree-of-freedom systems; MuJoCo's linearization of
  the same mechanism is in test_analysis_mujoco.py;
- the output matrix against the Jacobian of eq. (13), the equilibrium
  against the dynamics (no acceleration), the numerical pd loop against the
  analytic one;
- the workspace's points against inverse kinematics, numpy's condition
  number and the holding forces from ``Dynamics.inverse_dynamics`` (LAPACK);
  a reachable point is held: the dynamics give it no acceleration.
"""
from __future__ import annotations

import csv
import json
import re

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.linalg import expm

from stewart63_ros.core.analysis import equilibrium, linear, modal
from stewart63_ros.core.analysis.workspace import workspace_map
from stewart63_ros.core.mechanics import dopri
from stewart63_ros.core.mechanics.dynamics import NO_WRENCH, Dynamics, derivative_pd
from stewart63_ros.core.mechanics.kinematics import jacobian, leg_lengths
from stewart63_ros.core.mechanics.rotation import rotation_from_euler
from stewart63_ros.tools import analyze

#: An uneven direction for the steps: every leg, different amounts and signs.
DIRECTION = np.array([1.0, -0.5, 0.3, 0.8, -1.0, 0.2])


@pytest.fixture(scope='module')
def dyn(default_mech):
    return Dynamics(default_mech)


@pytest.fixture(scope='module')
def open_model(default_setup, default_mech):
    return linear.linearize(default_setup, None)


@pytest.fixture(scope='module')
def pd_model(default_setup, default_mech):
    return linear.linearize(default_setup, 'pd')


def linear_step(model, du, times):
    """dx(t) of the linear model for a step du from rest at x0: the top right
    column of expm([[A, B du], [0, 0]] t)."""
    n = model.A.shape[0]
    aug = np.zeros((n + 1, n + 1))
    aug[:n, :n] = model.A
    aug[:n, n] = model.B @ du
    return np.array([expm(aug * t)[:n, n] for t in times])


def nonlinear_step(dyn, model, du, times, setup):
    """dx(t) of the nonlinear model: compiled RK45, rtol 1e-12, from the equilibrium."""
    eq = model.equilibrium
    if model.closed_loop:
        gains = np.vstack([model.u0 + du, setup.gains.kp, setup.gains.kv])
        states, _ = dopri.solve_pd(dyn, eq.state13(), times, gains=gains,
                                   max_force=setup.mechanism.max_force, endstops=False,
                                   rtol=1e-12, atol=1e-14)
    else:
        states, _ = dopri.solve_pd(dyn, eq.state13(), times, forces=model.u0 + du,
                                   endstops=False, rtol=1e-12, atol=1e-14)
    return equilibrium.chart_from_state13(states, eq)


@pytest.mark.parametrize('loop, size, duration', [('open', 2.0, 0.4), ('closed', 2e-3, 1.0)])
def test_linear_model_agrees_with_the_nonlinear_one_to_first_order(
        default_setup, dyn, open_model, pd_model, loop, size, duration):
    """A step of 2 N per leg (open loop: the platform starts to fall away, the
    model is unstable) or 2 mm of reference (closed loop), then half, then a
    quarter: the gap to the nonlinear response shrinks as the square."""
    model = open_model if loop == 'open' else pd_model
    times = np.linspace(0.0, duration, 41)
    gaps, sizes = [], []
    for eps in (size, size / 2, size / 4):
        du = eps * DIRECTION
        linear = linear_step(model, du, times)
        exact = nonlinear_step(dyn, model, du, times, default_setup)
        gaps.append(np.abs(exact - linear).max())
        sizes.append(np.abs(linear).max())
        # First order: the gap is a small part of the response itself.
        assert gaps[-1] < 0.02 * sizes[-1], (eps, gaps[-1], sizes[-1])
    for big, small in zip(gaps, gaps[1:]):
        assert 3.5 < big / small < 4.5, gaps          # quadratic in the step


def test_frequency_response_agrees_with_a_sine_excited_nonlinear_run(default_setup, default_mech,
                                                                     dyn,
                                                                     pd_model):
    """Reference L1_ref = u0_1 + 0.1 mm sin(2 pi f t) into the nonlinear closed
    loop (eq. 40 inside scipy's DOP853); after 1.5 s the transient has decayed
    (slowest mode e^(-12 t)); gain and phase of every leg from a fit over whole
    periods, at 0.5, 3 and 20 Hz (below, at and above the modes)."""
    model, eq = pd_model, pd_model.equilibrium
    args = dyn.kernel_args()
    kp, kv = np.asarray(default_setup.gains.kp), np.asarray(default_setup.gains.kv)
    amplitude = 1e-4
    for f in (0.5, 3.0, 20.0):
        omega = 2 * np.pi * f
        periods = 2 if f < 1 else 5
        t_end = 1.5 + periods / f

        def rhs(t, y):
            setpoint = model.u0.copy()
            setpoint[0] += amplitude * np.sin(omega * t)
            return derivative_pd(*args, y, np.zeros(6), NO_WRENCH, False,
                                 np.vstack([setpoint, kp, kv]), default_mech.max_force)

        times = np.linspace(t_end - periods / f, t_end, 200 * periods + 1)
        sol = solve_ivp(rhs, (0.0, t_end), eq.state13(), method='DOP853', rtol=1e-11,
                        atol=1e-13, t_eval=times)
        assert sol.success
        lengths = np.array([dyn.lengths_and_rates(y)[0] for y in sol.y.T])
        basis = np.column_stack([np.sin(omega * times), np.cos(omega * times),
                                 np.ones_like(times)])
        coef, *_ = np.linalg.lstsq(basis, lengths - model.y0, rcond=None)
        measured = (coef[0] + 1j * coef[1]) / amplitude          # (6,) leg_1 -> each leg
        predicted = modal.frequency_response(model, [f])[0][:, 0]
        scale = np.abs(predicted).max()
        assert np.abs(measured - predicted).max() < 1e-5 * scale, (f, measured, predicted)
        # The diagonal's gain and phase, as the Bode plot shows them.
        assert abs(abs(measured[0]) - abs(predicted[0])) < 1e-5 * abs(predicted[0])
        assert abs(np.degrees(np.angle(measured[0] / predicted[0]))) < 1e-3


def test_output_matrix_is_the_jacobian_and_the_equilibrium_holds(default_setup, default_mech, dyn,
                                                                  open_model):
    eq = open_model.equilibrium
    jac = jacobian(default_mech, eq.rotation, eq.position)     # rows [s_i, q_i x s_i]
    assert np.abs(open_model.C[:, :6] - jac).max() < 1e-8
    assert np.abs(open_model.C[:, 6:]).max() == 0.0
    # Held: no acceleration of the nonlinear model at x0 under u0 (eq. 38).
    dy = dyn.derivative(eq.state13(), eq.forces, with_endstops=False)
    assert np.abs(dy).max() < 1e-10
    # The default pose is the setpoint's: its leg lengths are setpoint_lengths.
    assert np.abs(eq.lengths - default_setup.task.setpoint_lengths).max() < 1e-9
    # Kinematic rows: d(position)/dt = velocity, d(phi)/dt = omega at rest.
    assert np.array_equal(open_model.A[:6, :6], np.zeros((6, 6)))
    assert np.abs(open_model.A[:6, 6:] - np.eye(6)).max() < 1e-9
    assert np.abs(open_model.B[:6]).max() == 0.0


def test_pd_loop_folded_in_analytically_equals_the_law_differenced(default_setup, pd_model):
    numeric = linear.closed_loop(default_setup, pd_model.equilibrium, 'pd', numeric=True)
    scale = np.abs(pd_model.A).max()
    assert np.abs(numeric.A - pd_model.A).max() < 1e-6 * scale
    assert np.abs(numeric.B - pd_model.B).max() < 1e-6 * np.abs(pd_model.B).max()
    assert np.abs(numeric.u0 - pd_model.u0).max() < 1e-9
    # The reference that holds the pose is L0 + F_hold / Kp: the gravity sag.
    eq = pd_model.equilibrium
    assert np.allclose(pd_model.u0, eq.lengths + eq.forces / default_setup.gains.kp, atol=1e-12)


def test_computed_torque_shows_its_designed_error_dynamics(default_setup, default_mech):
    """The law makes every task-space axis e'' + Kd e' + Kp e = 0: six modes at
    sqrt(ct_kp) / 2 pi Hz with damping ct_kd / (2 sqrt(ct_kp)), here with gains
    that differ from the defaults (30 rad/s, zeta 0.5)."""
    params = {'ct_kp': [900.0] * 6, 'ct_kd': [30.0] * 6}
    found = modal.modes(linear.linearize(default_setup, 'computed_torque', params=params))
    assert np.allclose(found.frequencies_hz, 30.0 / (2 * np.pi), rtol=1e-5)
    assert np.allclose(found.damping_ratios, 0.5, rtol=1e-5)
    assert all(found.stable)


def test_modes_of_known_second_order_systems():
    """Three uncoupled axes x'' + c x' + k x = 0 (underdamped, overdamped,
    divergent: k < 0), coupled by a rotation of coordinates: the figures come
    back, and a divergent mode is marked unstable."""
    ks = np.array([400.0, 100.0, -25.0, 900.0, 2500.0, 16.0])
    cs = np.array([8.0, 50.0, 3.0, 120.0, 10.0, 10.0])
    rot = np.linalg.qr(np.random.default_rng(3).normal(size=(6, 6)))[0]
    a = np.zeros((12, 12))
    a[:6, 6:] = np.eye(6)
    a[6:, :6] = -rot @ np.diag(ks) @ rot.T
    a[6:, 6:] = -rot @ np.diag(cs) @ rot.T
    model = linear.LinearModel(a, np.zeros((12, 6)), np.zeros((6, 12)), np.zeros((6, 6)),
                               np.zeros(12), np.zeros(6), np.zeros(6),
                               equilibrium.Equilibrium(np.zeros(3), np.eye(3), np.zeros(6),
                                                       np.ones(6), 1.0))
    found = modal.modes(model)
    expected = sorted(zip(np.sqrt(np.abs(ks)) / (2 * np.pi), cs / (2 * np.sqrt(np.abs(ks))),
                          ks > 0, range(6)))
    for k, (freq, zeta, stable, axis) in enumerate(expected):
        assert found.frequencies_hz[k] == pytest.approx(freq, rel=1e-9)
        assert found.damping_ratios[k] == pytest.approx(zeta, rel=1e-9)
        assert found.stable[k] == stable
        shape = rot[:, axis] / rot[np.argmax(np.abs(rot[:, axis])), axis]
        assert np.allclose(found.mode_shapes[k], shape, atol=1e-9)


def test_the_default_mechanism_modes(open_model, pd_model):
    """Figures docs/analysis.md quotes: held by constant forces the platform
    falls away in all six directions (each mode has one positive eigenvalue);
    the pd loop (eq. 40) is stable, slowest mode 2.59 Hz at damping 0.74."""
    open_modes, pd_modes = modal.modes(open_model), modal.modes(pd_model)
    assert not any(open_modes.stable)
    assert all(pd_modes.stable)
    assert pd_modes.frequencies_hz[0] == pytest.approx(2.5907, abs=1e-3)
    assert pd_modes.damping_ratios[0] == pytest.approx(0.7436, abs=1e-3)


# -- workspace -----------------------------------------------------------------------------
def test_workspace_points_agree_with_inverse_kinematics_and_holding_forces(default_mech):
    """A tilted orientation and a max_force low enough to bind: every point's
    reason from independent arithmetic (leg lengths of eq. 5, numpy's
    condition number, holding forces from LAPACK's solve of eq. 38), and a
    reachable point is held still by its forces."""
    mech = default_mech.replace(max_force=120.0)
    rot = rotation_from_euler([0.15, -0.1, 0.3])
    result = workspace_map(mech, rot, 0.1, max_condition=12.0,
                           bounds=(-1.0, 1.0, -1.0, 1.0, 0.2, 2.0))
    dyn = Dynamics(mech)
    counts = {r: int(np.sum(result.reason == r)) for r in ('ok', 'stroke', 'singular',
                                                          'max_force')}
    assert all(counts.values()), counts          # every limit binds somewhere
    zero = np.zeros(3)
    for k in np.random.default_rng(7).choice(len(result.points), 400, replace=False):
        p = result.points[k]
        lengths = leg_lengths(mech, p, rot)
        assert np.allclose(lengths, result.lengths[k], atol=1e-12)
        cond = np.linalg.cond(jacobian(mech, rot, p))
        forces = dyn.inverse_dynamics(rot, p, zero, zero, zero, zero)
        if np.any(lengths < mech.leg_length_min) or np.any(lengths > mech.leg_length_max):
            expected = 'stroke'
        elif cond > 12.0:
            expected = 'singular'
        elif np.abs(forces).max() > mech.max_force:
            expected = 'max_force'
        else:
            expected = 'ok'
        assert result.reason[k] == expected, (p, lengths, cond, forces)
        assert result.condition[k] == pytest.approx(cond, rel=1e-9)
        if expected != 'singular':
            assert result.max_force[k] == pytest.approx(np.abs(forces).max(), rel=1e-9)
        if expected == 'ok':
            eq = equilibrium.Equilibrium(p, rot, forces, lengths, cond)
            dy = dyn.derivative(eq.state13(), forces, with_endstops=False)
            assert np.abs(dy[7:]).max() < 1e-9


# -- the command line -----------------------------------------------------------------------
def test_analyze_linearize_writes_the_model(tmp_path, capsys, pd_model):
    assert analyze.main(['linearize', '--out', str(tmp_path)]) == 0
    data = np.load(tmp_path / 'linear.npz')
    assert data['A'].shape == (12, 12) and data['B'].shape == (12, 6)
    assert data['C'].shape == (6, 12) and data['D'].shape == (6, 6)
    assert np.array_equal(data['A'], pd_model.A) and np.array_equal(data['u0'], pd_model.u0)
    doc = json.loads((tmp_path / 'linear.json').read_text())
    assert np.array_equal(np.array(doc['B']), pd_model.B)
    assert [s['name'] for s in doc['states']][:4] == ['x', 'y', 'z', 'phi_x']
    assert doc['loop'] == 'closed' and doc['control_law'] == 'pd'
    assert 'reference' in doc['inputs'][0]['meaning']
    assert 'written' in capsys.readouterr().out


def test_analyze_modes_json_and_table(capsys, open_model):
    assert analyze.main(['modes', '--json', '--control-law', 'none']) == 0
    doc = json.loads(capsys.readouterr().out)
    assert set(doc) >= {'frequencies_hz', 'damping_ratios', 'mode_shapes', 'pose'}
    assert len(doc['frequencies_hz']) == 6 and np.shape(doc['mode_shapes']) == (6, 6)
    expected = modal.modes(open_model)
    assert np.allclose(doc['frequencies_hz'], expected.frequencies_hz)
    assert analyze.main(['modes']) == 0
    table = capsys.readouterr().out
    assert 'closed loop (pd)' in table and len(table.splitlines()) == 8


def test_analyze_freqresp_writes_csv_and_bode(tmp_path, capsys, pd_model):
    assert analyze.main(['freqresp', '--points', '7', '--fmin', '0.1', '--fmax', '10',
                         '--out', str(tmp_path)]) == 0
    with open(tmp_path / 'freqresp.csv') as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == ['f_hz', 'input', 'output', 'magnitude', 'phase_deg']
    assert len(rows) == 7 * 36
    assert {r['input'] for r in rows} == {'leg_%d' % i for i in range(1, 7)}
    g = modal.frequency_response(pd_model, [1.0])[0]
    row = next(r for r in rows if r['input'] == 'leg_2' and r['output'] == 'leg_5'
               and abs(float(r['f_hz']) - 1.0) < 1e-9)
    assert float(row['magnitude']) == pytest.approx(abs(g[4, 1]), rel=1e-8)
    as_complex = float(row['magnitude']) * np.exp(1j * np.radians(float(row['phase_deg'])))
    assert abs(as_complex - g[4, 1]) < 1e-6 * abs(g[4, 1])
    assert (tmp_path / 'bode.png').stat().st_size > 10000


def test_analyze_workspace_writes_csv_and_figure(tmp_path, capsys):
    assert analyze.main(['workspace', '--step', '0.2', '--out', str(tmp_path)]) == 0
    with open(tmp_path / 'workspace.csv') as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == ['x', 'y', 'z', 'reachable', 'reason', 'condition', 'max_force']
    assert {r['reason'] for r in rows} <= {'ok', 'stroke', 'singular', 'max_force'}
    assert all((r['reason'] == 'ok') == (r['reachable'] == '1') for r in rows)
    # The grid passes through the setpoint's position, which is reachable.
    assert any(r['reachable'] == '1' and abs(float(r['z']) - 1.0737) < 1e-3 and
               abs(float(r['x'])) < 1e-6 for r in rows)
    assert (tmp_path / 'workspace.png').stat().st_size > 10000
    # the size said first is the size written (within 10 %)
    said = capsys.readouterr().out.splitlines()[0]
    assert said.startswith('grid of %d points (step 0.2 m): workspace.csv about ' % len(rows))
    estimate = len(rows) * analyze.CSV_BYTES_PER_ROW
    assert abs((tmp_path / 'workspace.csv').stat().st_size - estimate) < 0.1 * estimate


def test_a_workspace_grid_that_would_not_fit_is_refused_before_it_is_made(tmp_path, capsys):
    """--step 0.001 used to die in numpy (Unable to allocate 222. GiB); --step
    0.01 silently wrote a 1.6 GB CSV."""
    assert analyze.main(['workspace', '--step', '0.001', '--out', str(tmp_path / 'a')]) == 2
    err = capsys.readouterr().err.strip()
    assert 'Traceback' not in err, err
    err = [line for line in err.splitlines() if 'error' in line]
    assert len(err) == 1, err
    err = err[0]
    count = int(re.search(r'a grid of (\d+) points needs about ([\d.]+ [kMGTP]?B) of memory',
                          err).group(1))
    assert count > 2.9e10                       # (0.05 / 0.001)^3 x the default 245134
    assert analyze.main(['workspace', '--step', '0.01', '--out', str(tmp_path / 'b')]) == 2
    err = capsys.readouterr().err
    assert 'workspace.csv would have' in err and 'GB' in err and '--large-output' in err
    assert not (tmp_path / 'a').exists() and not (tmp_path / 'b').exists()


def test_the_memory_bound_of_a_workspace_grid_holds(default_setup, default_mech):
    """``BYTES_PER_POINT`` bounds what workspace_map takes (numpy's allocations,
    traced), and ``check_grid_fits`` refuses what would not fit."""
    import tracemalloc

    from stewart63_ros.core.analysis import workspace
    pos, rot = equilibrium.setpoint_pose(default_setup)
    workspace_map(default_mech, rot, 0.3, through=pos)      # compiled outside the trace
    tracemalloc.start()
    try:
        result = workspace_map(default_mech, rot, 0.1, through=pos)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak / len(result.points) < workspace.BYTES_PER_POINT
    workspace.check_grid_fits(1000, available=10**9)
    with pytest.raises(workspace.GridTooLarge, match='a grid of 3000000 points needs about '
                       '720 MB of memory; 1.0 GB is available'):
        workspace.check_grid_fits(3_000_000, available=10**9)


@pytest.mark.parametrize('argv, words', [
    (['modes', '--pose', '0', '0', '2.5', '0', '0', '0'], 'outside the stroke'),
    (['modes', '--pose', '0', '0', '1.07', '0', '0', '0', '--max-condition', '2'],
     'singular pose'),
    (['modes', '--control-law', 'nope'], 'unknown law'),
    (['freqresp', '--fmin', '10', '--fmax', '1', '--out', 'x'], '--fmin'),
    (['workspace', '--step', '0', '--out', 'x'], '--step'),
])
def test_analyze_bad_input_is_one_line_and_exit_2(capsys, argv, words):
    assert analyze.main(argv) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if 'error' in line]
    assert len(lines) == 1 and words in lines[0] and 'Traceback' not in err, err


def test_a_law_that_cannot_hold_the_pose_is_refused(default_setup):
    with pytest.raises(equilibrium.AnalysisError, match='kp is zero on leg_3'):
        linear.linearize(default_setup.replace(kp=[4000, 4000, 0, 4000, 4000, 4000]), 'pd')
    with pytest.raises(equilibrium.AnalysisError, match='beyond max_force'):
        linear.linearize(default_setup.replace(max_force=50.0), None)
