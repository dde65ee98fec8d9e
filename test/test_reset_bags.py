"""A bag that spans a ``~/reset`` is drawn run by run, never spliced.

The bags here are written with rosbags and hold what the plant publishes
across a reset (checked against real rig bags, lockstep and realtime): per
sample ``leg_lengths``, ``ground_truth/pose`` and the controller's
``leg_forces`` with the sample's stamp; the plant's status on /diagnostics
with ``run`` and ``run_number`` and each fault's state. A reset: the status
``run: reset`` with the new ``run_number``, a quiet second, then the new
run from sample 0, its stamps from 0 again in lockstep and going on in
realtime.

- ``bagruns.bag_runs`` finds the runs; ``trajectory_from_bag`` reads one
  (default the last), never a sample of another;
- ``plot`` draws the last run to figure.png and run 1 to figure_run1.png,
  each titled with its run, faults shaded per run; ``--run 1`` draws run 1
  alone;
- ``view``'s replay and ``plot --animate`` take one run the same way;
- ``plot --animate`` of a run with a dropout draws the legs with gaps, no
  empty panel, no warning.
"""
from __future__ import annotations

import contextlib
import io
import warnings
from pathlib import Path

import numpy as np
import pytest

from stewart63_ros import bagio, bagruns
from stewart63_ros.core.mechanics.kinematics import leg_lengths
from stewart63_ros.core.plumbing.params import LEG_NAMES, load_setup

REPO = Path(__file__).resolve().parents[1]
SETUP = load_setup(REPO / 'config' / 'stewart63.yaml')
MECH = SETUP.mechanism
RATE = 100.0
FAULT = 'actuator_dead:leg_2@0.1-0.2'


def write_reset_bag(path, mode='lockstep', runs=((0.6, 1.2), (0.3, 1.1)), dropout=()):
    """A bag of len(runs) runs of (seconds, height the platform rises to): the
    platform rises linearly from z = 1.0 in each; the plant's statuses as it
    sends them (once per 0.1 s, and at once on a change of ``run``); a reset
    between runs. ``dropout``: samples of the last run whose leg 5 is NaN."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    ts = bagio.typestore()
    T = ts.types
    JS, PS = 'sensor_msgs/msg/JointState', 'geometry_msgs/msg/PoseStamped'
    DA = 'diagnostic_msgs/msg/DiagnosticArray'
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    conns = {topic: writer.add_connection(topic, msgtype, typestore=ts) for topic, msgtype in (
        ('/leg_lengths', JS), ('/ground_truth/pose', PS), ('/leg_forces', JS),
        ('/diagnostics', DA))}

    def header(stamp_ns):
        return T['std_msgs/msg/Header'](stamp=T['builtin_interfaces/msg/Time'](
            sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000),
            frame_id='base')

    def status(stamp_ns, when, run, number, sample, fault_state):
        values = [T['diagnostic_msgs/msg/KeyValue'](key=k, value=v) for k, v in (
            ('run', run), ('run_number', str(number)), ('sample', str(sample)),
            ('fault: ' + FAULT, fault_state))]
        st = T['diagnostic_msgs/msg/DiagnosticStatus'](
            level=0, name='stewart63/plant', message='ok', hardware_id='', values=values)
        writer.write(conns['/diagnostics'], when,
                     ts.serialize_cdr(T[DA](header=header(stamp_ns), status=[st]), DA))

    wall = 1_800_000_000_000_000_000        # recording time [ns]
    period = int(1e9 / RATE)
    for r, (seconds, top) in enumerate(runs):
        number = r + 1
        n = int(round(seconds * RATE)) + 1
        base = 0 if mode == 'lockstep' else wall        # realtime stamps: wall time
        for k in range(n):
            t = k / RATE
            stamp = base + k * period
            if k % 10 == 0:
                state = ('scheduled from 0.1 s to 0.2 s' if t < 0.1 else
                         'active since 0.100000 s (until 0.2 s)' if t < 0.2 else
                         'ended: active 0.100000-0.200000 s')
                status(stamp, wall, 'running', number, k, state)
            z = 1.0 + (top - 1.0) * t / seconds
            lengths = leg_lengths(MECH, np.array([0.0, 0.0, z]), np.eye(3))
            if r == len(runs) - 1 and k in dropout:
                lengths = np.where(np.arange(6) == 4, np.nan, lengths)
            h = header(stamp)
            writer.write(conns['/leg_lengths'], wall + 1000, ts.serialize_cdr(T[JS](
                header=h, name=list(LEG_NAMES), position=np.asarray(lengths, float),
                velocity=np.zeros(6), effort=np.array([], float)), JS))
            pose = T[PS](header=h, pose=T['geometry_msgs/msg/Pose'](
                position=T['geometry_msgs/msg/Point'](x=0.0, y=0.0, z=z),
                orientation=T['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0)))
            writer.write(conns['/ground_truth/pose'], wall + 2000, ts.serialize_cdr(pose, PS))
            writer.write(conns['/leg_forces'], wall + 300_000, ts.serialize_cdr(T[JS](
                header=h, name=list(LEG_NAMES), position=np.array([], float),
                velocity=np.array([], float), effort=np.full(6, 100.0 * number)), JS))
            wall += period
        if r + 1 < len(runs):
            # ~/reset after the last sample: the new run's number at once, a quiet second
            status(base + (n - 1) * period, wall, 'reset', number + 1, n,
                   'scheduled from 0.1 s to 0.2 s')
            wall += 1_000_000_000
    writer.close()
    return Path(path)


@pytest.fixture(params=['lockstep', 'realtime'])
def reset_bag(request, tmp_path):
    return write_reset_bag(tmp_path / ('bag_' + request.param), request.param)


def test_the_runs_of_a_bag_are_found_and_read_apart(reset_bag):
    runs = bagruns.bag_runs(reset_bag)
    assert [(r.index, r.number, r.samples, r.count) for r in runs] == [(1, 1, 61, 2),
                                                                      (2, 2, 31, 2)]
    assert [r.name for r in runs] == ['run 1', 'run 2']
    last = bagruns.trajectory_from_bag(reset_bag)     # the default: the last run only
    first = bagruns.trajectory_from_bag(reset_bag, run=runs[0])
    for cols, seconds, top, force in ((first, 0.6, 1.2, 100.0), (last, 0.3, 1.1, 200.0)):
        n = int(round(seconds * RATE)) + 1
        assert np.allclose(cols['t'], np.arange(n) / RATE, atol=1e-9)
        # the platform rose from 1.0 in each run: nothing of the other run in it
        assert cols['z'][0] == pytest.approx(1.0) and cols['z'][-1] == pytest.approx(top)
        assert np.all(np.diff(cols['z']) > 0)
        assert np.all(cols['F1'] == force)
    assert np.array_equal(bagruns.trajectory_from_bag(reset_bag, run=runs[1])['z'], last['z'])
    assert bagruns.select_run(runs, 1) is runs[0]
    with pytest.raises(bagio.BagError, match='no run 3 in the bag'):
        bagruns.select_run(runs, 3)


def test_plot_of_a_reset_bag_draws_each_run_on_its_own(reset_bag, tmp_path, monkeypatch):
    from stewart63_ros.tools import plot
    drawn = {}

    def spy(columns, out_path, title='', reference=None, setpoint=None, faults=None, layout='6-3'):
        drawn[Path(out_path).name] = (title, columns['t'].copy(), columns['z'].copy(), faults)
        return out_path
    monkeypatch.setattr(plot, 'draw_figure', spy)
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert plot.main([str(reset_bag), '--out', str(tmp_path / 'figure.png')]) == 0
    assert sorted(drawn) == ['figure.png', 'figure_run1.png']
    title, t, z, faults = drawn['figure.png']
    assert 'run 2, 2 of 2 in the bag, 0.3 s, 31 samples' in title
    assert t[-1] == pytest.approx(0.3) and np.all(np.diff(t) > 0) and z[0] == pytest.approx(1.0)
    # the shading of run 2: its fault as run 2's statuses left it, not run 1's
    assert [(f['fault'], f['active_from_s']) for f in faults] == [(FAULT, 0.1)]
    title, t, z, _ = drawn['figure_run1.png']
    assert 'run 1, 1 of 2 in the bag, 0.6 s, 61 samples' in title
    assert t[-1] == pytest.approx(0.6) and np.all(np.diff(t) > 0)
    assert 'figure_run1.png' in printed.getvalue() and 'figure.png' in printed.getvalue()
    drawn.clear()
    with contextlib.redirect_stdout(io.StringIO()):
        assert plot.main([str(reset_bag), '--run', '1', '--out', str(tmp_path / 'one.png')]) == 0
    assert list(drawn) == ['one.png'] and drawn['one.png'][1][-1] == pytest.approx(0.6)


def test_plot_writes_one_figure_per_run(reset_bag, tmp_path):
    from stewart63_ros.tools import plot
    with contextlib.redirect_stdout(io.StringIO()):
        assert plot.main([str(reset_bag)]) == 0
    assert (reset_bag / 'figure.png').stat().st_size > 10000
    assert (reset_bag / 'figure_run1.png').stat().st_size > 10000


def test_view_replays_one_run_of_a_reset_bag(reset_bag):
    from stewart63_ros.tools.view_sources import BagRun
    last = BagRun(reset_bag, SETUP)
    assert last.t[-1] == pytest.approx(0.3) and np.all(np.diff(last.t) > 0)
    assert last.position[0][2] == pytest.approx(1.0)
    assert 'run 2 of the bag (2 of 2; the others: --run 1)' == last.describe()
    first = BagRun(reset_bag, SETUP, 1)
    assert first.t[-1] == pytest.approx(0.6) and first.position[-1][2] == pytest.approx(1.2)
    with pytest.raises(bagio.BagError, match='no run 5'):
        BagRun(reset_bag, SETUP, 5)


def test_animate_of_a_reset_bag_takes_each_run_apart(tmp_path):
    from stewart63_ros.tools import plot
    bag = write_reset_bag(tmp_path / 'bag', 'lockstep', runs=((0.2, 1.05), (0.2, 1.1)))
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert plot.main(['--animate', str(bag), '--fps', '5',
                          '--out', str(tmp_path / 'run.gif')]) == 0
    assert (tmp_path / 'run.gif').is_file() and (tmp_path / 'run_run1.gif').is_file()
    assert 'run 1 of the bag' in printed.getvalue() and 'run 2 of the bag' in printed.getvalue()


def test_animation_of_a_dropout_draws_the_legs_with_gaps(tmp_path):
    from stewart63_ros.tools.animate import Animator
    bag = write_reset_bag(tmp_path / 'bag', 'lockstep', runs=((1.0, 1.1),),
                          dropout=range(40, 46))
    columns = bagruns.trajectory_from_bag(bag)
    assert np.isnan(columns['L5'][40:46]).all()
    with warnings.catch_warnings():
        warnings.simplefilter('error')      # no "No artists with labels" and the like
        anim = Animator(columns, MECH, title='dropout')
        anim.save_frame(0.42, tmp_path / 'frame.png')
    lines = anim.axL.get_lines()
    legs = [line for line in lines if line.get_label().startswith('$L_')]
    assert len(legs) == 6
    leg5 = np.asarray(legs[4].get_ydata(), float)
    assert np.isnan(leg5[40:46]).all() and np.isfinite(leg5[:40]).all()
    assert anim.axL.get_xlim() == pytest.approx((0.0, 1.0))
    low, high = anim.axL.get_ylim()
    assert low < np.nanmin(columns['L3']) and high > np.nanmax(columns['L1'])
