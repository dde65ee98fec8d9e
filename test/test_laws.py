"""Control laws and reference motions in the core (no ROS).

- ``pd`` through the law interface is eq. (40) to the bit; ``pd_gravity``
  removes the paper's static sag (continuous and 1 kHz sampled);
- ``pd_gravity``'s holding forces equal the virtual-work answer (finite
  differences of the potential energy);
- ``computed_torque`` follows a six-axis reference to < 0.1 mm / 1e-4 rad,
  and its error decays as the linear second-order system of its gains;
- reference motions: interpolant derivatives, inverse kinematics, the stroke
  check, holding the last pose; the user-law example; a failing law.
Figures are printed: run with ``-s`` to see them.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stewart63_ros.core.controllers.laws import Controller, LawError, PDGravityLaw
from stewart63_ros.core.controllers.reference import (
    R_ACC,
    R_ALPHA,
    R_LEN,
    R_OMEGA,
    R_POS,
    R_RATE,
    R_ROT,
    R_VEL,
    Reference,
    ReferenceError,
)
from stewart63_ros.core.controllers.reference_files import load_reference, write_reference_csv
from stewart63_ros.core.controllers.simulate import initial_state, run_continuous, run_sampled
from stewart63_ros.core.controllers.tracking import tracking_errors
from stewart63_ros.core.mechanics.dynamics import POS, QUAT
from stewart63_ros.core.mechanics.kinematics import jacobian, leg_lengths
from stewart63_ros.core.mechanics.rotation import quaternion_from_euler, rotation_from_euler
from stewart63_ros.core.plumbing.params import ParameterError

RATE = 1000.0


def six_axis_reference(setup, duration=6.0, step=0.01):
    """Sinusoids of 2-4 cm and 2-4 deg at 0.3-1 Hz about the initial pose,
    ramped in over 1 s (quintic smoothstep)."""
    t = np.arange(0.0, duration + 1e-9, step)
    ramp = np.clip(t, 0.0, 1.0)
    ramp = ramp ** 3 * (10 - 15 * ramp + 6 * ramp ** 2)
    amp = np.array([0.03, 0.02, 0.04, np.radians(3), np.radians(2), np.radians(4)])
    freq = np.array([0.5, 0.7, 0.3, 0.6, 0.8, 1.0])
    centre = np.concatenate([setup.task.initial_position, setup.task.initial_orientation])
    return t, centre + ramp[:, None] * amp * np.sin(2 * np.pi * freq * t[:, None])


# -- pd and pd_gravity on the paper's scenario ------------------------------------------------
def test_pd_through_the_law_interface_is_eq40_to_the_bit(setup, mech, dyn):
    plain = run_sampled(setup, 0.5, RATE, dyn=dyn)               # the compiled fast path
    law = run_sampled(setup, 0.5, RATE, dyn=dyn, controller=Controller(setup, law='pd'))
    assert np.array_equal(plain.forces, law.forces)
    assert np.array_equal(plain.states, law.states)


def test_one_fast_path_for_eq40_gives_the_general_paths_numbers(setup, mech, dyn):
    """The controller node, sim and sweep take one fast path for the built-in pd
    law towards fixed lengths (``pd_gains``); it answers what the law itself
    answers through a reference sample, to the bit, saturated or not, and a
    gain changed at run time reaches it at once."""
    ctl = Controller(setup, law='pd')
    gains = ctl.pd_gains()
    assert gains is not None and np.array_equal(gains.setpoint, setup.task.setpoint_lengths)
    rng = np.random.default_rng(3)
    sample = ctl.sample
    for scale in (1e-3, 1.0):           # inside the saturation, and far beyond it
        lengths = setup.task.setpoint_lengths + scale * rng.normal(size=6)
        rates = scale * rng.normal(size=6)
        fast = ctl.forces(0.1, lengths, rates)
        assert np.array_equal(fast, ctl.law(0.1, lengths, rates, sample))
    assert np.any(np.abs(fast) == mech.max_force)
    ctl.set_parameter('kp', [1000.0] * 6)
    assert np.array_equal(ctl.pd_gains().kp, [1000.0] * 6)
    # run_sampled: the compiled loop for it, the python loop its numbers
    compiled = run_sampled(setup, 0.05, RATE, dyn=dyn, controller=ctl)
    python = run_sampled(setup, 0.05, RATE, dyn=dyn, controller=ctl, loop='python')
    assert np.array_equal(compiled.forces, python.forces)
    assert not np.array_equal(compiled.forces, run_sampled(setup, 0.05, RATE, dyn=dyn).forces)
    # any other law, or a moving reference: no fast path
    t, poses = six_axis_reference(setup, 1.0)
    moving = Reference.from_poses(mech, t, poses)
    assert Controller(setup, law='pd', reference=moving).pd_gains() is None
    assert Controller(setup, law='pd_gravity').pd_gains() is None
    ctl.law = lambda t, L, Ld, ref: np.zeros(6)        # a law swapped in by hand
    assert ctl.pd_gains() is None and np.array_equal(ctl.forces(0.2, lengths, rates),
                                                     np.zeros(6))


@pytest.mark.parametrize('control', ['continuous', 'sampled'])
def test_pd_gravity_removes_the_static_sag(setup, mech, dyn, control):
    errors = {}
    for name in ('pd', 'pd_gravity'):
        if control == 'sampled':
            result = run_sampled(setup, 10.0, RATE, dyn=dyn, controller=Controller(setup, law=name))
        else:
            result = run_continuous(setup, 10.0, dyn=dyn, controller=Controller(setup, law=name))
        errors[name] = result.final_leg_error_percent(dyn, setup.task.setpoint_lengths).max()
    print('\n%s: final positioning error pd %.4f %%, pd_gravity %.3g %%'
          % (control, errors['pd'], errors['pd_gravity']))
    assert 0.9 < errors['pd'] < 1.0
    assert errors['pd_gravity'] < 0.01


def potential(dyn, position, rotation):
    y = np.zeros(13)
    y[POS] = position
    y[QUAT] = Rotation.from_matrix(rotation).as_quat()
    return dyn.energy(y)[1]


def test_holding_forces_equal_the_virtual_work_answer(setup, mech, dyn):
    """At a static pose, J^T F = dV/dx (x: position and a base-frame rotation
    vector): the pistons' work balances the change of potential energy of
    platform and legs, which ``Dynamics.energy`` computes independently."""
    law = PDGravityLaw(mech, setup.to_params())
    rng = np.random.default_rng(3)
    worst = 0.0
    for _ in range(5):
        position = setup.task.initial_position + rng.uniform(-0.05, 0.05, 3)
        rotation = rotation_from_euler(setup.task.initial_orientation + rng.uniform(-0.1, 0.1, 3))
        forces = law.holding_forces(position, rotation)
        grad = np.empty(6)
        h = 1e-6
        for k in range(6):
            d = np.zeros(3)
            d[k % 3] = h
            if k < 3:
                plus = potential(dyn, position + d, rotation)
                minus = potential(dyn, position - d, rotation)
            else:
                plus = potential(dyn, position, Rotation.from_rotvec(d).as_matrix() @ rotation)
                minus = potential(dyn, position, Rotation.from_rotvec(-d).as_matrix() @ rotation)
            grad[k] = (plus - minus) / (2 * h)
        work = jacobian(mech, rotation, position).T @ forces
        worst = max(worst, np.max(np.abs(work - grad)) / np.max(np.abs(grad)))
    print('\nholding forces vs virtual work: worst relative difference %.2e' % worst)
    assert worst < 1e-6


# -- computed torque ----------------------------------------------------------------------------
def test_computed_torque_tracks_a_six_axis_reference(setup, mech, dyn):
    ref = Reference.from_poses(mech, *six_axis_reference(setup))
    ref.check()
    errors = {}
    for name in ('pd', 'pd_gravity', 'computed_torque'):
        result = run_sampled(setup, 5.0, RATE, dyn=dyn,
                             controller=Controller(setup, law=name, reference=ref))
        errors[name] = tracking_errors(mech, ref, result.times, result.states, after=2.0)
        e = errors[name]
        print('\n%-16s after 2 s: position max %.3e m RMS %.3e m, orientation max %.3e rad '
              'RMS %.3e rad, legs max %.3e m' % (name, e['position_max_m'], e['position_rms_m'],
                                                 e['orientation_max_rad'],
                                                 e['orientation_rms_rad'], e['leg_max_m']))
    ct = errors['computed_torque']
    assert ct['position_max_m'] < 1e-4
    assert ct['orientation_max_rad'] < 1e-4
    assert errors['pd']['position_max_m'] > 10 * ct['position_max_m']


def second_order(e0, kp, kd, t):
    """e(t) of e'' + kd e' + kp e = 0, e(0) = e0, e'(0) = 0."""
    roots = np.roots([1.0, kd, kp]).astype(complex)
    if abs(roots[0] - roots[1]) < 1e-9:
        r = roots[0].real
        return e0 * (1 - r * t) * np.exp(r * t)
    r1, r2 = roots
    c1 = -e0 * r2 / (r1 - r2)
    c2 = e0 * r1 / (r1 - r2)
    return (c1 * np.exp(r1 * t) + c2 * np.exp(r2 * t)).real


@pytest.mark.parametrize('kp,kd', [(2500.0, 100.0), (400.0, 8.0)])
def test_computed_torque_error_decays_as_its_second_order_system(setup, mech, dyn, kp, kd):
    """Hold a pose; start 5 mm and 5 mrad away, at rest. With the exact model the
    error of every axis is e'' + Kd e' + Kp e = 0 (natural frequency sqrt(Kp),
    damping Kd / 2 sqrt(Kp)); 1 kHz sampling adds a small phase lag."""
    target = setup.task.initial_position, rotation_from_euler(setup.task.initial_orientation)
    ref = Reference.constant_pose(mech, *target)
    offset = np.array([0.005, -0.004, 0.003, 0.005, -0.003, 0.004])
    y0 = np.zeros(13)
    y0[POS] = target[0] - offset[:3]
    y0[QUAT] = (Rotation.from_rotvec(-offset[3:]) * Rotation.from_matrix(target[1])).as_quat()
    params = {'ct_kp': [kp] * 6, 'ct_kd': [kd] * 6}
    duration = 1.0 if kp > 1000 else 2.0
    result = run_sampled(setup, duration, RATE, dyn=dyn, y0=y0,
                         controller=Controller(setup, params, law='computed_torque',
                                               reference=ref))
    err_pos = target[0] - result.states[:, POS]
    err_rot = (Rotation.from_matrix(target[1])
               * Rotation.from_quat(result.states[:, QUAT]).inv()).as_rotvec()
    err = np.hstack([err_pos, err_rot])
    model = second_order(offset[None, :], kp, kd, result.times[:, None])
    worst = np.max(np.abs(err - model)) / np.max(np.abs(offset))
    # the decay rate: fitted on log |e| of the envelope vs the model's zeta * omega_n
    zeta_wn = kd / 2
    print('\nct_kp %g ct_kd %g (omega_n %.1f rad/s, zeta %.2f): max |e - e_model| = %.2e of the '
          'initial error' % (kp, kd, np.sqrt(kp), kd / (2 * np.sqrt(kp)), worst))
    assert worst < 0.03
    if kd / (2 * np.sqrt(kp)) < 1:
        # underdamped: peaks of |e_x| decay as exp(-zeta omega_n t)
        ex = np.abs(err[:, 0])
        peaks = [k for k in range(1, len(ex) - 1) if ex[k] >= ex[k - 1] and ex[k] > ex[k + 1]]
        t_p, e_p = result.times[peaks], ex[peaks]
        rate = -np.polyfit(t_p, np.log(e_p), 1)[0]
        print('  decay rate of the peaks %.3f 1/s, model zeta omega_n %.3f 1/s' % (rate, zeta_wn))
        assert abs(rate - zeta_wn) < 0.05 * zeta_wn


# -- reference motions --------------------------------------------------------------------------
def test_reference_derivatives_and_inverse_kinematics(setup, mech):
    t, poses = six_axis_reference(setup, duration=3.0, step=0.05)
    ref = Reference.from_poses(mech, t, poses)
    times = np.linspace(0.3123, 2.7123, 7)     # off the knots (every 0.05 s)
    h = 1e-5
    s, sp, sm = ref.sample_many(times), ref.sample_many(times + h), ref.sample_many(times - h)
    fd = lambda sl: (sp[:, sl] - sm[:, sl]) / (2 * h)                       # noqa: E731
    assert np.allclose(fd(R_POS), s[:, R_VEL], atol=1e-8)
    assert np.allclose(fd(R_VEL), s[:, R_ACC], atol=1e-6)
    assert np.allclose(fd(R_OMEGA), s[:, R_ALPHA], atol=1e-6)
    assert np.allclose(fd(R_LEN), s[:, R_RATE], atol=1e-8)
    for k in range(len(times)):
        rot = s[k, R_ROT].reshape(3, 3)
        # rows are the interpolated poses, R = Rz Ry Rx
        theta = Rotation.from_matrix(rot).as_euler('xyz')
        assert np.allclose(rotation_from_euler(theta), rot, atol=1e-14)
        assert np.allclose(leg_lengths(mech, s[k, R_POS], rot), s[k, R_LEN], atol=1e-14)
        # omega: dR/dt R^T = [omega]x
        wdot = (sp[k, R_ROT].reshape(3, 3) - sm[k, R_ROT].reshape(3, 3)) / (2 * h) @ rot.T
        assert np.allclose([wdot[2, 1], wdot[0, 2], wdot[1, 0]], s[k, R_OMEGA], atol=1e-8)
    # passes through every row, holds the first and last poses at rest
    assert np.allclose(ref.poses(t), poses, atol=1e-12)
    for outside in (-1.0, t[-1] + 0.5):
        s = ref.sample(outside)
        assert np.allclose(ref.poses([outside])[0], poses[0 if outside < 0 else -1], atol=1e-12)
        assert not np.any(s[12:24])


def test_reference_outside_the_stroke_is_refused_with_time_and_leg(setup, mech, tmp_path):
    t = np.array([0.0, 1.0, 2.0, 3.0])
    centre = np.concatenate([setup.task.initial_position, setup.task.initial_orientation])
    poses = np.repeat(centre[None], 4, axis=0)
    poses[2, 2] += 0.9                         # 0.9 m up at t = 2 s: legs overstretched
    path = tmp_path / 'ref.csv'
    write_reference_csv(path, t, poses)
    with pytest.raises(ReferenceError) as info:
        load_reference(mech, path)
    message = str(info.value)
    print('\n' + message)
    assert 'leg_' in message and 'outside the stroke' in message and 't = 1.' in message
    # speed and acceleration limits (off by default)
    poses[2, 2] = centre[2] + 0.05
    write_reference_csv(path, t, poses)
    load_reference(mech, path)
    with pytest.raises(ReferenceError, match='max_leg_speed'):
        load_reference(mech, path, max_leg_speed=0.01)
    with pytest.raises(ReferenceError, match='max_leg_acceleration'):
        load_reference(mech, path, max_leg_acceleration=0.01)


@pytest.mark.parametrize('text,problem', [
    ('t,x,y\n0,1,2\n', 'header'),
    ('t,x,y,z,theta_x,theta_y,theta_z\n', 'no poses'),
    ('t,x,y,z,theta_x,theta_y,theta_z\n0,0,0,1,0,0,0\n0,0,0,1,0,0,0\n', 'increase'),
    ('t,x,y,z,theta_x,theta_y,theta_z\n0,0,0,1,0,0\n', '7 numbers'),
    ('t,x,y,z,theta_x,theta_y,theta_z\n0,0,0,nan,0,0,0\n', 'NaN'),
])
def test_bad_reference_files_are_refused(mech, tmp_path, text, problem):
    path = tmp_path / 'ref.csv'
    path.write_text(text)
    with pytest.raises(ReferenceError, match=problem):
        load_reference(mech, path)


# -- the interface: user laws, failures, gains --------------------------------------------------
def test_user_law_example_equals_pd_with_the_same_gains(setup, mech, dyn):
    ref = Reference.from_poses(mech, *six_axis_reference(setup, duration=1.0))
    pd = run_sampled(setup, 0.3, RATE, dyn=dyn, controller=Controller(setup, law='pd',
                                                                     reference=ref))
    user = Controller(setup, {'legpd_kp': setup.gains.kp, 'legpd_kv': setup.gains.kv},
                      law='stewart63_ros.examples.my_law:LegPD', reference=ref)
    mine = run_sampled(setup, 0.3, RATE, dyn=dyn, controller=user)
    assert np.allclose(mine.forces, pd.forces, rtol=0, atol=1e-9)
    user.set_parameter('legpd_kp', [1.0] * 6)
    with pytest.raises(ParameterError):
        user.set_parameter('legpd_kp', [1.0] * 5)


def test_a_failing_law_raises_law_error(setup, mech, dyn):
    y = initial_state(setup.task)
    lengths, rates = dyn.lengths_and_rates(y)
    failing = Controller(setup, {'failing_after': 0.5}, law='stewart63_ros.examples.my_law:Failing')
    assert np.all(np.isfinite(failing(lengths, rates, 0.0)))
    with pytest.raises(LawError, match='fails on purpose'):
        failing(lengths, rates, 0.6)
    nan = Controller(setup, law='pd')
    nan.law = lambda t, L, Ld, ref: np.full(6, np.nan)
    with pytest.raises(LawError, match='six finite'):
        nan(lengths, rates, 0.0)


@pytest.mark.parametrize('name,value', [
    ('kp', [np.nan] * 6), ('kp', [1.0] * 5), ('kv', [-1.0] + [1.0] * 5),
    ('ct_kp', [1.0] * 7), ('ct_kd', [-2.0] * 6)])
def test_bad_gains_are_refused_and_change_nothing(setup, mech, dyn, name, value):
    y = initial_state(setup.task)
    lengths, rates = dyn.lengths_and_rates(y)
    for law in ('pd', 'computed_torque'):
        ctl = Controller(setup, law=law)
        before = ctl(lengths, rates, 0.0)
        with pytest.raises(ParameterError):
            ctl.set_parameter(name, value)
        assert np.array_equal(ctl(lengths, rates, 0.0), before)


def test_unknown_law_is_refused(setup, mech):
    for name in ('nope', 'no_such_module:Law', 'stewart63_ros.examples.my_law:Nope', ''):
        with pytest.raises(ParameterError, match='control_law'):
            Controller(setup, law=name)


def test_a_new_gain_takes_effect_at_the_next_force(setup, mech, dyn):
    y = initial_state(setup.task)
    lengths, rates = dyn.lengths_and_rates(y)
    ctl = Controller(setup, law='pd')
    ctl.set_parameter('kp', [1000.0] * 6)
    expected = 1000.0 * (setup.task.setpoint_lengths - lengths) - setup.gains.kv * rates
    assert np.allclose(ctl(lengths, rates, 0.0), np.clip(expected, -3000, 3000), atol=1e-9)


def test_quaternion_helper_consistency(setup, mech):
    q = quaternion_from_euler(setup.task.initial_orientation)
    assert np.allclose(Rotation.from_quat(q).as_matrix(),
                       rotation_from_euler(setup.task.initial_orientation))


# -- sim and plot ---------------------------------------------------------------------------------
@pytest.mark.slow      # sim and plot end to end: a run, two CSVs and a figure
def test_sim_follows_a_reference_and_plot_draws_it(setup, mech, tmp_path, capsys):
    from stewart63_ros.tools import plot, sim
    ref_csv = tmp_path / 'ref.csv'
    write_reference_csv(ref_csv, *six_axis_reference(setup, duration=3.0))
    out = tmp_path / 'out'
    assert sim.main(['--duration', '2', '--out', str(out), '--control', 'sampled',
                     '--control-law', 'computed_torque', '--reference', str(ref_csv)]) == 0
    text = capsys.readouterr().out
    line = [ln for ln in text.splitlines() if ln.startswith('tracking error after 1s')]
    assert line, text
    print('\n' + line[0])
    assert (out / 'reference.csv').is_file() and (out / 'figure.png').is_file()
    assert plot.main([str(out / 'trajectory.csv'), '--out', str(tmp_path / 'fig.png')]) == 0
    assert (tmp_path / 'fig.png').stat().st_size > 10000


def test_sim_refuses_a_bad_reference_in_one_line(setup, mech, tmp_path, capsys):
    from stewart63_ros.tools import sim
    ref_csv = tmp_path / 'ref.csv'
    centre = np.concatenate([setup.task.initial_position, setup.task.initial_orientation])
    write_reference_csv(ref_csv, [0.0, 1.0], [centre, centre + [0, 0, 2.0, 0, 0, 0]])
    assert sim.main(['--duration', '1', '--out', str(tmp_path / 'o'),
                     '--reference', str(ref_csv)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count('\n') == 0 and 'outside the stroke' in err and 'leg_' in err, err
