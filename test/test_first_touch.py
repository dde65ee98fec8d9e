"""What a new user meets first: parameters, mistakes, start-up, the README's examples.

- a recorder started before the rig records every message of the run, from
  the first (lockstep and realtime);
- ``-p name:=value`` wins over the parameter file; the files given are the
  whole model; unknown keys are named, with a "did you mean";
- every mistake gets one line and exit status 2, never a traceback;
- a normal realtime run leaves no ERROR line in any log;
- every example command of the README runs (``test_readme_examples_are_all_tested``
  keeps this list and the README's in step).
"""
from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from ros_harness import PYTHON, wait_line, wait_until
from test_rig import assert_every_published_message_is_in_the_bag

REPO = Path(__file__).resolve().parents[1]
PARAMS = REPO / 'config' / 'stewart63.yaml'
README = REPO / 'README.md'
BIN = Path(PYTHON).parent
NODES = ('plant', 'controller', 'fk')


def exe(name: str) -> str:
    path = BIN / name
    assert path.exists(), '%s is not installed in this venv (make venv)' % path
    return str(path)


def run(args, timeout=120, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run([str(a) for a in args], capture_output=True, text=True,
                          timeout=timeout, **kwargs)


def variant(tmp_path, name, old, new) -> Path:
    text = PARAMS.read_text()
    assert old in text
    path = tmp_path / name
    path.write_text(text.replace(old, new, 1))
    return path


def wait_text(proc, text: str, timeout: float, stream: str = 'stderr') -> bool:
    """Until ``text`` appears anywhere in the process's stdout or stderr."""
    read = proc.stderr if stream == 'stderr' else proc.stdout
    return wait_until(lambda: text in read() or proc.returncode is not None, timeout) and (
        text in read())


def assert_no_error_but_starvation(logs: dict) -> None:
    """No ERROR line in any log, but for a watchdog trip in mid-run that the
    next sample ends ("samples are back"): a controller starved of CPU for
    more than watchdog_timeout on a loaded machine, which is a real fault.
    The end of a run, or a Ctrl-C, is never an ERROR."""
    for name, text in logs.items():
        lines = text.splitlines()
        for i, line in enumerate(lines):
            if 'ERROR' not in line:
                continue
            resumed = any('samples are back' in later for later in lines[i + 1:])
            assert name == 'controller.log' and 'watchdog' in line and resumed, (
                '%s:\n%s' % (name, text))


def one_error_line(text: str) -> str:
    """The stderr of a refused command: no traceback, exactly one error line."""
    assert 'Traceback' not in text, text
    errors = [s for s in text.splitlines() if 'error' in s.lower()]
    assert len(errors) == 1, text
    return errors[0]


# -- 1. a recorder started before the rig -------------------------------------------
@pytest.mark.parametrize('mode,duration', [('lockstep', 1.0), ('realtime', 5.0)])
def test_a_recorder_started_first_records_every_message(ros, tmp_path, mode, duration):
    """``record`` in one terminal, ``rig`` (without --record) in another: the
    bag holds the run from its first sample (the plant's, the controller's and
    fk's first answers) and every message each node says it published (its
    last /diagnostics), on every topic, in lockstep and in realtime. The
    realtime run of 5 s also leaves no ERROR line in any log (its end is not
    an error)."""
    from stewart63_ros import bagio
    bag = tmp_path / 'bag'
    rec = ros.spawn([exe('record'), str(bag)], name='record')
    assert wait_line(rec, 'READY', 60), rec.describe()
    log_dir = tmp_path / 'logs'
    rig = ros.spawn([exe('rig'), '--mode', mode, '--duration', str(duration),
                     '--log-dir', str(log_dir)], name='rig')
    code = rig.wait(240)
    logs = {p.name: p.read_text(errors='replace') for p in sorted(log_dir.glob('*.log'))}
    assert code == 0, rig.describe() + '\n'.join('--- %s\n%s' % kv for kv in logs.items())
    assert ros.stop(rec) == 0, rec.describe()
    summary = json.loads((log_dir / 'plant_summary.json').read_text())
    assert summary['samples'] == int(round(duration * 1000)) + 1
    # The start: the first and the last sample of the plant are in the bag,
    # and (lockstep) the controller's answer to sample 0; in realtime the
    # controller answers the newest sample it finds, so its first answer may
    # be to sample 1 (every force it published is in the bag: checked below).
    first = {}
    for topic in ('leg_lengths', 'ground_truth/pose') + (
            ('leg_forces',) if mode == 'lockstep' else ()):
        stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
                  for _, _, m in bagio.read_messages(bag, [topic])]
        first[topic] = stamps[0]
        if topic == 'leg_lengths':
            assert abs(stamps[-1] - stamps[0] - duration * 1e9) < 1e4, (stamps[0], stamps[-1])
    assert len(set(first.values())) == 1, first
    counts = assert_every_published_message_is_in_the_bag(bag, summary)
    print('\nrecorder started first, %s: published = recorded: %s' % (mode, counts))
    waits = [s for s in logs['plant.log'].splitlines() if 'waiting' in s or 'matched' in s]
    print('plant: %s' % waits)
    if mode == 'realtime':
        assert_no_error_but_starvation(logs)
        # The controller tells the end of the run from a lost sensor, or was
        # stopped by rig (within ms of the plant's exit) before its watchdog
        # could take the end for a fault: no watchdog line after the last
        # resumption either way.
        ctl = logs['controller.log']
        assert ('the plant ended its run' in ctl
                or 'watchdog' not in ctl.split('samples are back')[-1]), ctl


def test_a_publisher_waits_for_a_subscription_the_graph_shows(ros, tmp_path):
    """A subscriber made before the plant starts gets sample 0 (the plant
    waits for it, saying so in its log); here in realtime at 500 Hz,
    through the README's own command with -p overrides."""
    from sensor_msgs.msg import JointState

    from stewart63_ros import topics
    node = ros.node('probe')
    stamps = []
    node.create_subscription(
        JointState, '/rig2/leg_lengths',
        lambda m: stamps.append(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec),
        topics.RECORD_SUB)
    summary_file = tmp_path / 'summary.json'
    # The README's example, plus what makes it end by itself.
    plant = ros.spawn([exe('plant'), '--ros-args', '--params-file', str(PARAMS),
                       '-r', '__ns:=/rig2', '-p', 'sensor_rate:=500.0',
                       '-p', 'clock_mode:=realtime', '-p', 'duration:=1.0',
                       '-p', 'summary_file:=%s' % summary_file,
                       # discovery has taken up to 3.5 s on a loaded machine
                       '-p', 'discovery_settle:=5.0'], name='plant')
    assert ros.spin_until(lambda: plant.returncode is not None, 60), plant.describe()
    assert plant.returncode == 0, plant.describe()
    assert ros.spin_until(lambda: len(stamps) >= 501, 10), (len(stamps), plant.describe())
    summary = json.loads(summary_file.read_text())
    assert summary['rate_hz'] == 500.0 and summary['clock_mode'] == 'realtime', summary
    assert summary['samples'] == 501
    gaps = np.diff(np.array(stamps, dtype=np.int64))
    # wall-clock stamps t0 + k / rate: exact to the rounding of a double (~256 ns)
    assert len(stamps) == 501 and np.all(np.abs(gaps - 2_000_000) < 1000), set(gaps.tolist())
    print('\nplant -p sensor_rate:=500.0 -p clock_mode:=realtime: %d samples, every 2 ms, '
          'the first included' % len(stamps))


def test_a_node_starts_only_when_a_recorder_says_it_has_matched_it(ros):
    """Each side of a DDS match discovers the other on its own: a recorder
    still drops what fk sends while fk already counts it as matched. So the
    recorder names on /diagnostics the nodes whose publishers it has matched,
    and fk waits (saying so) for its own name before its first message."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from geometry_msgs.msg import PoseStamped

    from stewart63_ros import topics
    node = ros.node('fake_recorder', namespace='/rw')
    node.create_subscription(PoseStamped, '/rw/platform_pose', lambda m: None,
                             topics.RECORD_SUB)
    status_pub = node.create_publisher(DiagnosticArray, '/diagnostics',
                                       topics.DIAGNOSTICS_QOS)

    def say_matched(names, seconds, until=lambda: False):
        """The fake recorder's status, every 0.2 s for ``seconds`` or ``until()``."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline and not until():
            status = DiagnosticStatus(name='stewart63/rw/fake_recorder', values=[
                KeyValue(key='matched_publishers', value=names)])
            status_pub.publish(DiagnosticArray(status=[status]))
            ros.spin_until(until, 0.2)
        return until()
    # a recorder the run does not name: discovery_settle gives the graph
    # time to show it (4 s: one lost DDS announcement)
    fk = ros.spawn([exe('fk'), '--ros-args', '-r', '__ns:=/rw',
                    '-p', 'discovery_timeout:=60.0', '-p', 'discovery_settle:=4.0'], name='fk')
    waits_for_it = "fake_recorder to match /rw/fk's publishers"
    assert say_matched('/rw/other', 60, lambda: waits_for_it in fk.stderr()
                       or fk.returncode is not None), fk.describe()
    assert not say_matched('/rw/other', 2.0, lambda: 'matched after' in fk.stderr()), \
        fk.describe()
    assert say_matched('/rw/other,/rw/fk', 15, lambda: 'matched after' in fk.stderr()), \
        fk.describe()
    assert ros.stop(fk) == 0, fk.describe()


def test_the_recorder_names_the_nodes_it_has_matched(ros, tmp_path):
    """The other side of the test above: the package's recorder says on
    /diagnostics which nodes' publishers its own subscriptions have matched."""
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import JointState

    from stewart63_ros import topics
    from stewart63_ros.recording.recorder import Recorder
    rec = Recorder(tmp_path / 'bag', ['leg_lengths'], domain_id=ros.domain_id).start()
    try:
        node = ros.node('talker', namespace='/rn')
        said = []

        def on_status(msg):
            for status in msg.status:
                if status.name == 'stewart63/record':
                    values = {kv.key: kv.value for kv in status.values}
                    if 'matched_publishers' in values:
                        said.append(values['matched_publishers'].split(','))
        node.create_subscription(DiagnosticArray, '/diagnostics', on_status,
                                 topics.DIAGNOSTICS_QOS)
        assert ros.spin_until(lambda: said, 15), 'no status from the recorder'
        assert '/rn/talker' not in said[-1], said
        node.create_publisher(JointState, '/leg_lengths', topics.STREAM_PUB)
        assert ros.spin_until(lambda: '/rn/talker' in said[-1], 15), said
        assert rec.publisher_counts(['leg_lengths'])['/leg_lengths'] >= 1
    finally:
        rec.stop()


def test_the_graph_count_agrees_with_the_middlewares_matching(ros):
    """What a node waits for before its first message: the subscriptions the
    ROS graph shows that can match its publisher (``topics.can_match``) are
    exactly those the publisher does match, for every kind the rig meets (the
    first version counted none: rclpy's own check calls every profile the
    graph returns incompatible)."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState

    from stewart63_ros import topics
    kinds = {'recorder': topics.RECORD_SUB, 'controller': topics.LATEST_SUB,
             'latched_reader': QoSProfile(depth=10,
                                          durability=DurabilityPolicy.TRANSIENT_LOCAL),
             'fk': topics.EVERY_SUB, 'echo': QoSProfile(depth=10),
             'best_effort': QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)}
    offered = {'stream': topics.STREAM_PUB, 'latched': topics.SETPOINT_QOS,
               'volatile_driver': QoSProfile(depth=10, durability=DurabilityPolicy.VOLATILE),
               'best_effort_driver': QoSProfile(
                   depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)}
    publisher_node, subscriber_node = ros.node('pubs'), ros.node('subs')
    for name, qos in kinds.items():
        subscriber_node.create_subscription(JointState, 'only_' + name, lambda m: None, qos)
    for pub_name, pub_qos in offered.items():
        for name in kinds:
            pub = publisher_node.create_publisher(JointState, 'only_' + name, pub_qos)
            infos = []
            assert ros.spin_until(lambda: bool(infos.extend(
                publisher_node.get_subscriptions_info_by_topic(pub.topic_name)) or infos), 15)
            predicted = topics.can_match(pub.qos_profile, infos[0].qos_profile)
            if predicted:
                assert ros.spin_until(lambda: pub.get_subscription_count() == 1, 15), (
                    pub_name, name)
            else:      # a match that should not be: give it as long as one that is took
                ros.rc.spin_for(0.5)
                assert pub.get_subscription_count() == 0, (pub_name, name)
            publisher_node.destroy_publisher(pub)


def test_the_plant_waits_for_a_late_peer_even_when_a_recorder_fills_the_count(ros, tmp_path):
    """A recorder started first fills ``lengths_subscribers`` while fk, still
    loading, has no subscription yet: the plant waits for the peers it is told
    by name (``lengths_peers``, as ``rig`` sets them), says so, and fk started
    late still gets every sample (a fresh-clone run lost all of fk's poses)."""
    from sensor_msgs.msg import JointState

    from stewart63_ros import topics
    node = ros.node('early_recorder')
    stamps = []
    recorder = node.create_subscription(JointState, '/leg_lengths',
                                        lambda m: stamps.append(m), topics.RECORD_SUB)
    plant_summary, fk_summary = tmp_path / 'plant.json', tmp_path / 'fk.json'
    plant = ros.spawn([exe('plant'), '--ros-args', '--params-file', str(PARAMS),
                       '-p', 'clock_mode:=realtime', '-p', 'duration:=0.5',
                       '-p', 'lengths_subscribers:=1', '-p', 'lengths_peers:=[fk]',
                       '-p', 'discovery_timeout:=60.0',
                       '-p', 'summary_file:=%s' % plant_summary], name='plant')
    try:
        assert wait_text(plant, 'no subscription from /fk yet (lengths_peers)', 60), (
            plant.describe())
        # The case is a count the recorder fills: it must have matched before
        # fk comes (a loaded CI run matched fk first, and the recorder got nothing).
        assert ros.spin_until(lambda: recorder.get_publisher_count() >= 1, 30), (
            plant.describe())
        fk = ros.spawn([exe('fk'), '--ros-args', '--params-file', str(PARAMS),
                        '-p', 'summary_file:=%s' % fk_summary], name='fk')
        assert ros.spin_until(lambda: plant.returncode is not None, 90), plant.describe()
        assert plant.returncode == 0, plant.describe()
        assert wait_until(lambda: plant_summary.exists(), 5)
        samples = json.loads(plant_summary.read_text())['samples']
        assert samples == 501
        assert ros.spin_until(lambda: len(stamps) >= samples, 10), len(stamps)
    finally:
        ros.stop(plant)
    assert ros.stop(fk) == 0, fk.describe()
    received = json.loads(fk_summary.read_text())['received']
    assert received.get('leg_lengths') == samples, (received, fk.describe())
    print('\nrecorder first, fk late: fk received %d of %d samples' % (
        received['leg_lengths'], samples))


def test_lockstep_plant_alone_says_what_it_waits_for(ros, tmp_path):
    plant = ros.spawn([exe('plant'), '--ros-args', '-p', 'discovery_timeout:=60.0'],
                      name='plant')
    try:
        assert wait_text(plant, 'waiting', 60), plant.describe()
        started = time.monotonic()
        line = next(s for s in plant.stderr().splitlines() if 'waiting' in s)
        assert 'leg_forces publisher' in line and 'discovery_timeout' in line, line
        # and again every 5 s
        assert wait_until(lambda: plant.stderr().count('waiting') >= 2, 10), plant.describe()
        assert time.monotonic() - started < 9
        print('\n' + line)
    finally:
        ros.stop(plant)


# -- 2. -p wins over the file; the files given are the whole model -----------------
def test_p_override_wins_over_the_files_node_section(ros, tmp_path):
    """The shipped file says sensor_rate: 1000 under /**/plant (and
    clock_mode: lockstep under /**); -p says 500 and realtime: the plant runs
    realtime at 500 Hz (alone: a lockstep plant would wait for a controller)."""
    summary_file = tmp_path / 's.json'
    plant = ros.spawn([exe('plant'), '--ros-args', '--params-file', str(PARAMS),
                       '-p', 'clock_mode:=realtime', '-p', 'duration:=0.2',
                       '-p', 'sensor_rate:=500.0',
                       '-p', 'summary_file:=%s' % summary_file], name='plant')
    assert plant.wait(60) == 0, plant.describe()
    summary = json.loads(summary_file.read_text())
    assert summary['clock_mode'] == 'realtime' and summary['rate_hz'] == 500.0, summary


def test_parameter_loading_order(tmp_path):
    from stewart63_ros.runtime.parameters import load_parameters
    second = tmp_path / 'second.yaml'
    second.write_text('/**:\n  ros__parameters:\n    clock_mode: realtime\n'
                      '/**/controller:\n  ros__parameters:\n    watchdog_timeout: 0.5\n')
    argv = ['plant', '--ros-args', '--params-file', str(PARAMS), '--params-file', str(second)]
    name, params = load_parameters('plant', argv)
    assert name == 'plant' and params['clock_mode'] == 'realtime'   # the later file wins
    assert params['platform_mass'] == 15.0 and 'watchdog_timeout' not in params
    _, params = load_parameters('plant', argv + ['-p', 'clock_mode:=lockstep',
                                                 '-p', 'kp:=[1, 2.5, 3, 4, 5, 6]'])
    assert params['clock_mode'] == 'lockstep' and params['kp'] == [1, 2.5, 3, 4, 5, 6]
    _, params = load_parameters('plant', ['x', '--ros-args', '-r', '__node:=plant2',
                                          '-p', 'plant:sensor_rate:=9.0'])
    # renamed: neither the file's /**/plant section nor a -p for plant applies
    assert 'sensor_rate' not in params and params['platform_mass'] == 15.0
    name, params = load_parameters('plant', ['x', '--ros-args', '-r', '__node:=plant2',
                                             '-p', 'plant2:sensor_rate:=9.0'])
    assert name == 'plant2' and params['sensor_rate'] == 9.0
    # a file given is the whole model: nothing from the packaged file
    only = tmp_path / 'only.yaml'
    only.write_text('/**:\n  ros__parameters:\n    platform_mass: 3.0\n')
    _, params = load_parameters('plant', ['x', '--ros-args', '--params-file', str(only)])
    assert params == {'platform_mass': 3.0}


# -- 3. typos ------------------------------------------------------------------------
def test_a_misspelt_key_stops_every_executable(ros, tmp_path):
    bad = variant(tmp_path, 'typo.yaml', 'platform_mass:', 'platfrom_mass:')
    commands = {exe_: [exe(exe_), '--ros-args', '--params-file', bad,
                       '-r', '__ns:=/typo%d' % i] for i, exe_ in enumerate(NODES)}
    commands['sim'] = [exe('sim'), '--params', bad, '--out', tmp_path / 'sim']
    commands['rig'] = [exe('rig'), '--params', bad, '--log-dir', tmp_path / 'rig']
    commands['fk --solve'] = [exe('fk'), '--solve', 1.9, 1.9, 1.6, 1.6, 1.6, 1.6,
                              '--params', bad]
    procs = {name: ros.spawn(cmd, name=name.split()[0]) for name, cmd in commands.items()}
    for name, proc in procs.items():
        assert proc.wait(90) == 2, proc.describe()
        line = one_error_line(proc.stderr())
        assert 'platform_mass: missing' in line and 'platfrom_mass' in line, (name, line)
        print('\n%-11s exit 2: %s' % (name, line))
    assert not (tmp_path / 'sim').exists()


def test_an_unknown_key_is_named_and_refused_when_strict(ros, tmp_path):
    # in the wildcard section: every node reads it
    extra = variant(tmp_path, 'extra.yaml', '    platform_mass: 15.0',
                    '    platform_mass: 15.0\n    sensor_rat: 500.0')
    hint = 'sensor_rat: unknown parameter (did you mean sensor_rate?)'
    # command lines: a warning, and the run goes on
    for cmd in ([exe('sim'), '--params', extra, '--out', tmp_path / 'sim', '--duration', 0.1,
                 '--no-figure'],
                [exe('fk'), '--solve', 1.9, 1.9, 1.6, 1.6, 1.6, 1.6, '--params', extra]):
        done = run(cmd)
        assert done.returncode == 0 and hint in done.stderr, done
        strict = run(cmd + ['--strict'])
        assert strict.returncode == 2 and hint in strict.stderr, strict
        assert 'Traceback' not in strict.stderr
    strict = run([exe('rig'), '--params', extra, '--strict', '--log-dir', tmp_path / 'r'])
    assert strict.returncode == 2 and hint in strict.stderr, strict
    # nodes: a warning in the log; strict_parameters:=true refuses
    procs = {}
    for i, name in enumerate(NODES):
        args = [exe(name), '--ros-args', '--params-file', extra, '-r', '__ns:=/x%d' % i]
        procs[name] = ros.spawn(args, name=name)
        procs[name + ' strict'] = ros.spawn(args + ['-p', 'strict_parameters:=true'],
                                            name=name + '_strict')
    for name, proc in procs.items():
        if name.endswith('strict'):
            assert proc.wait(90) == 2, proc.describe()
            line = one_error_line(proc.stderr())
            assert 'sensor_rat' in line and 'strict_parameters' in line, line
        else:
            assert wait_text(proc, hint, 90), proc.describe()
            assert proc.returncode is None, proc.describe()
            ros.stop(proc)
    # rig without --strict: the warning, then a normal run
    done = run([exe('rig'), '--params', extra, '--duration', 0.05, '--log-dir', tmp_path / 'rig'],
               timeout=240, env=ros.env())
    assert done.returncode == 0 and hint in done.stderr, done


# -- 4. mistakes: one line, exit 2 ---------------------------------------------------
def test_a_missing_parameter_file_is_one_line_and_exit_2(ros, tmp_path):
    nope = tmp_path / 'nope.yaml'
    commands = {name: [exe(name), '--ros-args', '--params-file', nope] for name in NODES}
    commands['plant -p'] = [exe('plant'), '--ros-args', '-p', 'sensor_rate']
    commands['sim'] = [exe('sim'), '--params', nope, '--out', tmp_path / 'o']
    commands['rig'] = [exe('rig'), '--params', nope, '--log-dir', tmp_path / 'r']
    commands['fk --solve'] = [exe('fk'), '--solve', 1, 1, 1, 1, 1, 1, '--params', nope]
    procs = {name: ros.spawn(cmd, name=name.split()[0]) for name, cmd in commands.items()}
    for name, proc in procs.items():
        assert proc.wait(90) == 2, proc.describe()
        line = one_error_line(proc.stderr())
        assert ('nope.yaml' in line or 'sensor_rate' in line), (name, line)
        print('\n%-11s exit 2: %s' % (name, line))


def test_plot_refuses_a_folder_that_is_not_a_bag_and_draws_a_sim_folder(tmp_path):
    folder = tmp_path / 'not_a_bag'
    folder.mkdir()
    (folder / 'notes.txt').write_text('hello')
    done = run([exe('plot'), folder])
    assert done.returncode == 2, done
    assert 'not a bag' in one_error_line(done.stderr)
    out = tmp_path / 'sim'
    assert run([exe('sim'), '--duration', 1, '--out', out, '--no-figure']).returncode == 0
    done = run([exe('plot'), out])
    assert done.returncode == 0, done
    assert done.stdout.strip() == str(out / 'figure.png') and (out / 'figure.png').stat().st_size
    from stewart63_ros.tools.plot import load_columns, run_title
    columns = load_columns(out)
    assert len(columns['t']) == 101
    assert run_title(out, columns).startswith(str(out) + ' (trajectory, 1 s')


def test_usage_errors_exit_2(tmp_path):
    for cmd in ([exe('play'), tmp_path / 'nothing_here'],
                [exe('fk'), '--solve', 0.1, 3.2, 1.6, 1.6, 1.6, 1.6],
                [exe('rig'), '--duration', -1],
                [exe('record'), '--recover', tmp_path]):
        done = run(cmd)
        assert done.returncode == 2, done
        assert 'Traceback' not in done.stderr, done


# -- 6. output -------------------------------------------------------------------------
def test_rig_help_shows_every_default():
    text = run([exe('rig'), '--help']).stdout
    flat = ' '.join(text.split())
    for option, default in (('--mode', 'default: lockstep'), ('--realtime-priority', 'default: 0'),
                            ('--params', 'default: the packaged'),
                            ('--duration', 'default: run until Ctrl-C'),
                            ('--log-dir', 'default: DIR.logs beside the bag'),
                            ('--namespace', 'default: the root namespace'),
                            ('--record', 'default: no recording')):
        assert option in flat and default in flat, (option, default, text)


def test_fk_solve_names_lengths_outside_the_stroke():
    done = run([exe('fk'), '--solve', 2.35, 2.35, 1.9, 1.9, 1.9, 1.9])
    assert done.returncode == 0, done
    out = json.loads(done.stdout)
    assert out['outside_stroke'] == ['leg_1: 2.35 m is outside the stroke [1.2, 2.3]',
                                     'leg_2: 2.35 m is outside the stroke [1.2, 2.3]']
    assert 'position' in out
    inside = json.loads(run([exe('fk'), '--solve', 1.9, 1.9, 1.6, 1.6, 1.6, 1.6]).stdout)
    assert 'outside_stroke' not in inside


def test_known_keys_come_from_one_place():
    """Every key of the packaged file and of docs/interface.md's node keys is known."""
    from stewart63_ros.core.plumbing.params import file_parameters, known_keys, unknown_keys
    assert unknown_keys(file_parameters(PARAMS)) == []
    text = (REPO / 'docs' / 'interface.md').read_text()
    section = text[text.index('### Node-specific keys'):text.index('## Frames')]
    table = re.findall(r'^\| `([a-z_]+)`(?:, `([a-z_]+)`)? \| (?:plant|controller|fk|all)',
                       section, re.M)
    keys = {k for row in table for k in row if k}
    assert {'sensor_rate', 'watchdog_timeout', 'singularity_threshold'} <= keys
    assert keys <= known_keys(), keys - known_keys()
    assert unknown_keys(['platfrom_mass', 'zzz']) == [
        'platfrom_mass: unknown parameter (did you mean platform_mass?)',
        'zzz: unknown parameter, read by no executable']
    # a user's control law brings the keys it lists
    law = {'control_law': 'stewart63_ros.examples.my_law:LegPD', 'legpd_kp': [1.0] * 6}
    assert unknown_keys(law) == []
    assert unknown_keys({'legpd_kp': [1.0] * 6}) != []


def test_every_key_the_code_reads_is_known():
    """The declarations (core/plumbing/node_parameters.py) and Mechanism cover every
    parameter the code reads (found as docs/interface.md's test finds them)."""
    from test_interface_doc import parameters_read

    from stewart63_ros.core.plumbing.params import known_keys
    examples = {'legpd_kp', 'legpd_kv', 'failing_after',     # the example laws' own keys
                'fd_window', 'fd_threshold'}
    # node names (rig's extra, files)
    examples |= {'plant', 'controller', 'fk', 'canopen_bridge', 'supervisor'}
    missing = {k: where for k, where in parameters_read().items()
               if k not in known_keys() and k not in examples}
    assert missing == {}, 'declare these in core/plumbing/node_parameters.py: %s' % missing


# -- 7. the README's examples ---------------------------------------------------------
#: Every example command of the README (its first two ``sh`` blocks, comments
#: dropped) and the test that runs it.
README_EXAMPLES = {
    'make demo': 'not run here: it builds the venv the tests run in, then runs rig '
                 '--record, plot and the summary, which the tests below run',
    'make test': 'not run here: it is the test suite itself',
    'plant --ros-args --params-file config/stewart63.yaml -r __ns:=/rig2 -p sensor_rate:=500.0':
        'test_a_publisher_waits_for_a_subscription_the_graph_shows',
    'rig --mode lockstep --duration 10 --record out/run1': 'test_readme_rig_plot_play',
    'rig --mode realtime --namespace /rig2': 'test_readme_realtime_rig_until_ctrl_c',
    'rig --compose --duration 10 --record out/run2': 'test_readme_composed_rig',
    'sim --duration 10 --out out/sim --control sampled --rate 100': 'test_readme_sim_and_fk',
    'plot out/run1': 'test_readme_rig_plot_play',
    'play out/run1 --topics leg_lengths & fk': 'test_readme_rig_plot_play',
    'fk --solve 1.9 1.9 1.6 1.6 1.6 1.6 --all': 'test_readme_sim_and_fk',
}


def readme_examples() -> list[str]:
    text = README.read_text()
    blocks = re.findall(r'```sh\n(.*?)```', text, re.S)[:2]
    inline = re.findall(r'`(plant --ros-args[^`]*)`', text)
    commands = []
    for block in blocks:
        for line in block.splitlines():
            command = line.split('#', 1)[0].strip()
            if command:
                commands.append(' '.join(command.split()))
    return commands + inline


def test_readme_examples_are_all_tested():
    assert sorted(readme_examples()) == sorted(README_EXAMPLES), (
        'README examples and their tests differ: %s' % sorted(
            set(readme_examples()) ^ set(README_EXAMPLES)))
    this = Path(__file__).read_text()
    for command, how in README_EXAMPLES.items():
        assert how.startswith('not run here') or 'def %s(' % how in this, (command, how)


def _readme_cwd(tmp_path) -> Path:
    cwd = tmp_path / 'work'
    (cwd / 'config').mkdir(parents=True)
    (cwd / 'config' / 'stewart63.yaml').write_text(PARAMS.read_text())
    return cwd


def _command(line: str) -> list[str]:
    words = line.split()
    return [exe(words[0])] + words[1:]


def test_readme_sim_and_fk(tmp_path):
    cwd = _readme_cwd(tmp_path)
    done = run(_command('sim --duration 10 --out out/sim --control sampled --rate 100'), cwd=cwd)
    assert done.returncode == 0, done
    assert 'positioning_error_percent    0.93' in done.stdout, done.stdout
    assert '"out/sim/figure.png"' in done.stdout and (cwd / 'out/sim/figure.png').exists()
    done = run(_command('fk --solve 1.9 1.9 1.6 1.6 1.6 1.6 --all'), cwd=cwd)
    assert done.returncode == 0 and json.loads(done.stdout)['count'] == 8, done


def test_readme_rig_plot_play(ros, tmp_path):
    from geometry_msgs.msg import PoseStamped

    from stewart63_ros import bagio, topics
    cwd = _readme_cwd(tmp_path)
    rig = ros.spawn(_command('rig --mode lockstep --duration 10 --record out/run1'), cwd=cwd,
                    name='rig')
    assert rig.wait(300) == 0, rig.describe()
    assert 'bag: out/run1' in rig.stdout() and (cwd / 'out/run1.logs/plant.log').exists()
    assert 'logs in out/run1.logs' in rig.stdout(), rig.stdout()
    done = run(_command('plot out/run1'), cwd=cwd)
    assert done.returncode == 0 and (cwd / 'out/run1/figure.png').exists(), done
    # play out/run1 --topics leg_lengths & fk: fk answers every recorded sample
    node = ros.node('probe')
    poses = []
    node.create_subscription(PoseStamped, 'platform_pose', poses.append, topics.RECORD_SUB)
    fk = ros.spawn([exe('fk')], cwd=cwd, name='fk')
    play = ros.spawn(_command('play out/run1 --topics leg_lengths'), cwd=cwd, name='play')
    assert ros.spin_until(lambda: play.returncode is not None, 120), play.describe()
    assert play.returncode == 0, play.describe()
    ros.spin_until(lambda: False, 2.0)          # the last poses in flight
    ros.stop(fk)
    truth = {m.header.stamp.sec * 10**9 + m.header.stamp.nanosec: m.pose.position
             for _, _, m in bagio.read_messages(cwd / 'out/run1', ['ground_truth/pose'])}
    assert len(truth) == 10001
    # A lockstep bag replays at its recorded pace, ~3x real time here: fk
    # (queue depth 100) answers what it keeps up with; each answer is exact.
    assert len(poses) >= 1000, (len(poses), fk.describe())
    worst = max(abs(p.pose.position.z - truth[p.header.stamp.sec * 10**9
                                               + p.header.stamp.nanosec].z) for p in poses)
    assert worst < 1e-9, worst
    print('\nplay out/run1 --topics leg_lengths & fk: %d of 10001 samples answered, '
          'max |z - truth| %.2g m' % (len(poses), worst))


def test_readme_composed_rig(ros, tmp_path):
    from stewart63_ros import bagio
    cwd = _readme_cwd(tmp_path)
    rig = ros.spawn(_command('rig --compose --duration 10 --record out/run2'), cwd=cwd,
                    name='rig')
    assert rig.wait(300) == 0, rig.describe()
    assert 'final positioning error: 0.93' in rig.stdout(), rig.stdout()
    n = sum(1 for _ in bagio.read_messages(cwd / 'out/run2', ['leg_lengths']))
    assert n == 10001, n


def test_readme_realtime_rig_until_ctrl_c(ros, tmp_path):
    env = ros.env({'ROS_HOME': tmp_path / 'ros_home'})
    rig = ros.spawn(_command('rig --mode realtime --namespace /rig2'), env=env, name='rig')
    log_dir = tmp_path / 'ros_home' / 'stewart63' / 'rig_logs' / 'rig2'
    assert wait_text(rig, 'logs in %s' % log_dir, 120, stream='stdout'), rig.describe()
    assert wait_until(lambda: 'realtime at' in (log_dir / 'plant.log').read_text(), 60), (
        rig.describe())
    time.sleep(2.0)      # let it run
    rig.popen.send_signal(signal.SIGINT)
    assert rig.wait(60) == 0, rig.describe()
    assert_no_error_but_starvation({p.name: p.read_text() for p in log_dir.glob('*.log')})
    assert 'Traceback' not in rig.stderr() + rig.stdout()


if __name__ == '__main__':
    sys.exit(pytest.main([__file__, '-v', '-s']))


def test_no_node_logs_through_the_deprecated_warn():
    """rclpy's ``Logger.warn`` is a deprecation wrapper: every call through it
    looks like one call site to rclpy's log filters, so a node that logged a
    throttled warning (a rejected input) and then any other warning died with
    "Requested logging filters cannot be changed between calls" (a plant in
    the two-rigs test, at its first 'new run of its source'). ``warning`` it is."""
    import ast
    offenders = []
    for path in sorted((REPO / 'stewart63_ros').rglob('*.py')):
        for node in ast.walk(ast.parse(path.read_text())):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                    and node.func.attr == 'warn'
                    and not (isinstance(node.func.value, ast.Name)
                             and node.func.value.id == 'warnings')):
                offenders.append('%s:%d' % (path.relative_to(REPO), node.lineno))
    assert not offenders, offenders
