"""Nothing lost under load: lockstep flow control, losses counted, stops that stop.

- A lockstep rig whose fk, then recorder, is starved of CPU for a while
  (its main thread, while its middleware threads receive on): the plant
  waits for them (``lockstep_peers``), nothing is lost, the run equals the
  offline one.
- A lockstep rig beside a process that keeps a core busy: every sample is
  answered, posed and recorded, and the run equals the offline one.
- ``rig`` stopped by SIGINT or SIGTERM at random moments of its start-up
  stops within 5 s, exit 0, no child left.
- The pieces on their own: gaps in sequence numbers are counted, the
  recorder reads a sample's stamp from its bytes, a stop signal during a
  child's start is held until the child is known, dead processes' Fast DDS
  files are cleaned and live ones kept.
"""
from __future__ import annotations

import contextlib
import fcntl
import os
import random
import signal
import subprocess
import threading
import time

import numpy as np
import test_rig
from ros_harness import PYTHON, clean_dead_shm_segments, logs_of, rig_env, wait_until
from test_rig import (
    PARAMS,
    RATE,
    assert_every_published_message_is_in_the_bag,
    by_stamp,
    children_of,
    ended,
    kill_leftovers,
    read_log,
    rig_command,
)

from stewart63_ros.core.controllers.simulate import run_sampled, sensor_reading
from stewart63_ros.core.mechanics.dynamics import Dynamics
from stewart63_ros.recording.recorder import header_stamp_ns
from stewart63_ros.runtime.checks import SkipCounter
from stewart63_ros.runtime.launcher import signals_deferred
from stewart63_ros.tools.rig_process import Rig

# test_rig's module fixtures: the mechanism, the kernels compiled once
mech, warm_kernels = test_rig.mech, test_rig.warm_kernels
DURATION = 5.0          # simulated s
RUN_TIMEOUT = 150.0


# ---------------------------------------------------------------- the pieces
def test_gaps_in_a_publishers_sequence_numbers_are_counted_per_publisher():
    counter = SkipCounter()
    a, b = b'a' * 16, b'b' * 16
    assert [counter.note(a, {'publication_sequence_number': n}) for n in (1, 2, 5, 6)] == [
        0, 0, 2, 0]
    # another publisher starts its own count; a reader that joined late
    # (first number 40) has lost nothing
    assert counter.note(b, {'publication_sequence_number': 40}) == 0
    assert counter.note(b, {'publication_sequence_number': 43}) == 2
    assert counter.note(a, {'publication_sequence_number': 7}) == 0
    assert counter.skipped == 4
    assert counter.note(a, {}) == 0 and counter.note(None, {'publication_sequence_number': 9}) == 0


def test_the_recorder_reads_a_samples_stamp_from_its_bytes():
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState
    msg = JointState()
    msg.header.stamp.sec, msg.header.stamp.nanosec = 12, 345_000_000
    msg.position = [1.0] * 6
    assert header_stamp_ns(serialize_message(msg)) == 12_345_000_000
    assert header_stamp_ns(b'\x00\x01') == -1


def test_a_stop_signal_while_a_child_starts_is_acted_on_once_it_is_known():
    seen = []

    def handler(signum, frame):
        seen.append(signum)
    old = signal.signal(signal.SIGTERM, handler)
    try:
        with signals_deferred():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
            assert seen == []               # held while the child is started
        assert seen == [signal.SIGTERM]     # and handed over after
    finally:
        signal.signal(signal.SIGTERM, old)


def test_dead_processes_fast_dds_files_are_removed_and_live_ones_kept(tmp_path):
    for name in ('fastdds_dead', 'fastdds_dead_el', 'fastdds_portX', 'fastdds_portX_el',
                 'sem.fastdds_portX_mutex', 'fastdds_live', 'fastdds_live_el'):
        (tmp_path / name).write_bytes(b'')
    live = os.open(tmp_path / 'fastdds_live_el', os.O_RDWR)
    try:
        # its owner lives (flock: another open file, even in this process, is refused)
        fcntl.flock(live, fcntl.LOCK_EX | fcntl.LOCK_NB)
        assert clean_dead_shm_segments(tmp_path) == 5
    finally:
        os.close(live)
    assert sorted(p.name for p in tmp_path.iterdir()) == ['fastdds_live', 'fastdds_live_el']
    assert clean_dead_shm_segments(tmp_path) == 2


# ------------------------------------------------------------ the rig, loaded
def run_lockstep(ros, monkeypatch, tmp_path, during=None, duration=DURATION):
    """A recorded lockstep ``Rig`` of ``duration``; ``during(rig)`` runs in
    a thread once the plant has started its samples. Returns (bag, plant
    summary, fk summary, logs)."""
    rig_env(ros, monkeypatch)
    bag, log_dir = tmp_path / 'bag', tmp_path / 'rig'
    rig = Rig(PARAMS, mode='lockstep', duration=duration, record=bag, log_dir=log_dir)
    thread, errors = None, []
    ok = False
    try:
        rig.start()
        if during is not None:
            def target():
                try:
                    plant_log = log_dir / 'plant.log'
                    assert wait_until(lambda: 'lockstep at' in read_log(plant_log), 90)
                    during(rig)
                except BaseException as exc:  # noqa: BLE001 - reported by the test
                    errors.append(exc)
            thread = threading.Thread(target=target, daemon=True)
            thread.start()
        ok = rig.wait(timeout=RUN_TIMEOUT)
    finally:
        if thread is not None:
            thread.join(30)
        for proc in rig.procs.values():        # never leave one frozen
            with contextlib.suppress(ProcessLookupError):
                os.kill(proc.pid, signal.SIGCONT)
        codes = rig.stop()
    logs = logs_of(log_dir)
    assert not errors, errors
    assert ok, 'the rig did not finish its run: %s\n%s' % (codes, logs)
    assert codes == {'record': 0, 'controller': 0, 'fk': 0, 'plant': 0}, logs
    return bag, rig.summary(), rig.summary('fk'), logs


def assert_whole_and_equal_to_the_offline_run(bag, summary, fk, setup, logs):
    duration = summary['sim_time_s']
    n = int(round(duration * RATE)) + 1
    assert summary['samples'] == n, summary
    assert summary['force_timeouts'] == 0, summary
    assert not summary.get('skipped'), summary
    assert 'LOST' not in logs, logs
    assert 'XMLPARSER' not in logs, logs     # config/fastdds.xml loaded cleanly
    assert fk['received']['leg_lengths'] == n, fk
    assert fk['published']['platform_pose'] == n, fk
    assert not fk.get('skipped'), fk
    counts = assert_every_published_message_is_in_the_bag(bag, summary)
    assert counts['platform_pose'] == n, counts
    ref = run_sampled(setup, duration, RATE)
    lengths, n_lengths = by_stamp(bag, 'leg_lengths')
    assert n_lengths == n
    dyn = Dynamics(setup.mechanism)
    worst = max(float(np.max(np.abs(np.asarray(lengths[k * 1_000_000].position)
                                    - sensor_reading(dyn, ref.states[k])[0])))
                for k in range(0, n, 97))
    assert worst <= 1e-9, 'leg lengths differ from the offline run by %g m\n%s' % (worst, logs)
    return counts


@contextlib.contextmanager
def busy_cores(n: int, nice: int = 0):
    """``n`` processes that each keep a core busy (at ``nice``), for the block."""
    procs = [subprocess.Popen([PYTHON, '-c', 'import os; os.nice(%d)\nwhile True: pass' % nice])
             for _ in range(n)]
    try:
        yield
    finally:
        for proc in procs:
            proc.kill()
            proc.wait(10)


def starve_main_thread(pid: int, seconds: float) -> None:
    """Keep the main thread of process ``pid`` off the CPU for ``seconds``
    while its middleware threads run on: the main thread runs SCHED_IDLE
    (only when no other thread wants a core) and two busy processes fill
    both cores at the lowest nice level (so the plant and the controller
    keep their pace). What a loaded machine does to a node, only more so:
    its reader queue fills while it takes nothing."""
    os.sched_setscheduler(pid, os.SCHED_IDLE, os.sched_param(0))   # the thread id = pid
    try:
        with busy_cores(2, nice=19):
            time.sleep(seconds)
    finally:
        os.sched_setscheduler(pid, os.SCHED_OTHER, os.sched_param(0))


def test_starved_fk_and_recorder_hold_the_lockstep_plant_and_lose_nothing(
        ros, monkeypatch, tmp_path, setup, warm_kernels):
    """fk's, then the recorder's, main thread starved for 5 s each mid-run:
    without flow control the plant runs thousands of samples ahead and
    they are lost (measured here: fk received 9988 of 10001, the recorder
    lost a pose)."""
    def starve(rig):
        for name in ('fk', 'record'):
            time.sleep(0.2)
            starve_main_thread(rig.procs[name].pid, 5.0)
    bag, summary, fk, logs = run_lockstep(ros, monkeypatch, tmp_path, starve, duration=10.0)
    peers = summary['lockstep_peers']
    print('\nstarved peers: the plant held %d times, %.2f s in all; window %d samples'
          % (peers['held_samples'], peers['held_s'], peers['window']))
    assert not peers['dropped'], peers
    assert peers['held_samples'] > 0, peers
    assert_whole_and_equal_to_the_offline_run(bag, summary, fk, setup, logs)


def test_a_lockstep_rig_beside_a_busy_core_answers_poses_and_records_every_sample(
        ros, monkeypatch, tmp_path, setup, warm_kernels):
    with busy_cores(1):
        bag, summary, fk, logs = run_lockstep(ros, monkeypatch, tmp_path)
    counts = assert_whole_and_equal_to_the_offline_run(bag, summary, fk, setup, logs)
    print('\nbeside a busy core: %d samples in %.2f s wall, final error %.4f %%, held %.2f s; '
          'bag %s' % (summary['samples'], summary['wall_time_s'],
                      summary['positioning_error_percent'],
                      summary['lockstep_peers']['held_s'], counts))


def test_rig_stops_within_5_s_of_a_signal_at_random_moments_of_start_up(
        ros, tmp_path, warm_kernels):
    seed = int(os.environ.get('STEWART63_STOP_SEED', random.randrange(1 << 30)))
    rng = random.Random(seed)
    print('\nseed %d (STEWART63_STOP_SEED to repeat)' % seed)
    for i in range(3):
        sig = rng.choice([signal.SIGINT, signal.SIGTERM])
        delay = rng.uniform(0.0, 6.0) if i else rng.uniform(0.0, 1.0)
        log_dir = tmp_path / ('rig%d' % i)
        proc = ros.spawn(rig_command() + ['--mode', 'lockstep', '--duration', '30',
                                          '--record', str(tmp_path / ('bag%d' % i)),
                                          '--log-dir', str(log_dir)], name='rig%d' % i)
        children: dict[int, str] = {}
        try:
            end = time.monotonic() + delay
            while time.monotonic() < end:      # who it started so far, to check after
                children.update(children_of(proc.pid))
                time.sleep(0.01)
            children.update(children_of(proc.pid))
            os.kill(proc.pid, sig)
            sent = time.monotonic()
            code = proc.wait(10)
            took = time.monotonic() - sent
            gone = wait_until(lambda: all(ended(p, c) for p, c in children.items()),
                              max(0.1, 5.0 - took))
            print('%s after %.2f s of start-up: rig exit %s in %.2f s, %d children'
                  % (sig.name, delay, code, took, len(children)))
            # Before Python has run the rig's first line there is no handler
            # (and no child): the signal's default action ends it at once.
            assert code == 0 or (code == -sig and not children), proc.describe()
            assert took <= 5.0, 'rig took %.2f s to stop\n%s' % (took, proc.describe())
            assert gone, ({p: c for p, c in children.items() if not ended(p, c)},
                          proc.describe())
        finally:
            ros.stop(proc)
            kill_leftovers(children)

