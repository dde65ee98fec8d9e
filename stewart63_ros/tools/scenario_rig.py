"""A scenario on the rig (``run: lockstep`` or ``realtime``): a ROS domain
leased for it, its parameter file written, ``rig`` started with a bag and a
summary in a temporary folder, and the ``Trace`` built from what it left.
"""
from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

from stewart63_ros.paths import try_lock_domain

#: Bound on a rig's start-up (loading or compiling the kernels, discovery) [s].
RIG_START_BOUND = 240.0


def domain_range() -> list[int]:
    text = os.environ.get('STEWART63_SCENARIO_DOMAINS', '1-100')
    match = re.fullmatch(r'\s*(\d+)\s*(?:-\s*(\d+))?\s*', text)
    if not match:
        raise ValueError('STEWART63_SCENARIO_DOMAINS: expected LO-HI or one id, got %r' % text)
    lo = int(match.group(1))
    hi = int(match.group(2) or lo)
    return list(range(lo, hi + 1))


@contextlib.contextmanager
def leased_domain(fixed: int | None = None, wait: float = 120.0):
    """A ROS domain id no other process on this machine holds while the block
    runs (``fixed``: that id, unleased: the caller vouches for it)."""
    if fixed is not None:
        yield fixed
        return
    ids = domain_range()
    deadline = time.monotonic() + wait
    start = (os.getpid() * 7) % len(ids)
    while True:
        for k in range(len(ids)):
            domain = ids[(start + k) % len(ids)]
            fd = try_lock_domain(domain)
            if fd is None:
                continue
            try:
                yield domain
            finally:
                os.close(fd)
            return
        if time.monotonic() > deadline:
            raise RuntimeError('no free ROS domain id in %s' % ids)
        time.sleep(0.5)


# -- a rig scenario --------------------------------------------------------------
def write_parameter_file(scenario, path: Path) -> None:
    """The scenario's parameter file: its ``params_file`` with each override set in
    every section that has the key (the wildcard section when none has it)."""
    import yaml  # lazy: yaml costs 76 ms; --help answers without it
    doc = yaml.safe_load(Path(scenario.params_file).read_text())
    sections = [s['ros__parameters'] for s in doc.values()
                if isinstance(s, dict) and isinstance(s.get('ros__parameters'), dict)]
    wildcard = next((doc[k]['ros__parameters'] for k in doc if str(k).strip() in ('/**', '**')),
                    sections[0])
    for key, value in scenario.params.items():
        for section in [s for s in sections if key in s] or [wildcard]:
            section[key] = value
    path.write_text(yaml.safe_dump(doc, sort_keys=False))


def trace_from_rig(scenario, bag: Path, summary: dict, trips: list | None = None):
    """The ``Trace`` of a rig run from its bag (ground truth, leg_lengths,
    leg_forces), the plant's summary and the supervisor's trips (its summary's
    ``trips``: cause, sample, latency_samples, detail)."""
    # lazy: numpy and the core cost 692 ms; only a rig run needs them
    import numpy as np

    from stewart63_ros.bagio import header_stamp_ns, read_messages
    from stewart63_ros.core.analysis.sweep import leg_lengths_of_states
    from stewart63_ros.core.mechanics.dynamics import Dynamics
    from stewart63_ros.core.scenarios.running import (
        build_controller,
        build_plant,
        reference_lengths,
    )
    from stewart63_ros.core.scenarios.scenario import Trace, TripRecord
    lengths_msgs, poses, forces = {}, {}, {}
    for topic, _, msg in read_messages(bag, ['leg_lengths', 'leg_forces', 'ground_truth/pose']):
        stamp = header_stamp_ns(msg)
        if topic.endswith('ground_truth/pose'):
            p, q = msg.pose.position, msg.pose.orientation
            poses[stamp] = (p.x, p.y, p.z, q.x, q.y, q.z, q.w)
        elif topic.endswith('leg_lengths'):
            lengths_msgs[stamp] = np.asarray(msg.position, float)
        else:
            forces[stamp] = np.asarray(msg.effort, float)
    stamps = sorted(s for s in lengths_msgs if s in poses)
    if not stamps:
        raise RuntimeError('the bag %s has no sample with both leg_lengths and '
                           'ground_truth/pose' % bag)
    plant = build_plant(scenario)
    mech = plant.mechanism
    dyn = Dynamics(mech)
    states = np.zeros((len(stamps), 13))
    states[:, :7] = [poses[s] for s in stamps]
    lengths = leg_lengths_of_states(dyn.base_points, dyn.leg_points, states)
    held = np.zeros(6)          # the plant holds zero until the first answer
    rows = np.empty((len(stamps), 6))
    withheld = np.zeros(len(stamps), bool)
    for k, s in enumerate(stamps):
        if s in forces:
            held = forces[s]
        elif np.all(np.isfinite(lengths_msgs[s])):
            withheld[k] = True
        rows[k] = held
    # Sample k's stamp is k periods after the first: k / rate, as sim's times.
    rate = float(summary.get('rate_hz') or 0.0)
    times = (np.array(stamps, dtype=np.int64) - stamps[0]) * 1e-9
    if rate > 0:
        times = np.round(times * rate) / rate
    _, reference = build_controller(scenario)
    expected = int(summary.get('samples', len(stamps)))
    lost = sum(int(v) for v in (summary.get('skipped') or {}).values())
    lost += max(0, expected - len(lengths_msgs))
    missed = int(summary.get('missed_cycles', 0)) + int(summary.get('force_timeouts', 0))
    if rate <= 0:
        rate = float(plant.setting('sensor_rate'))
    records = tuple(TripRecord(t['cause'], int(t['sample']), t.get('latency_samples'),
                               t.get('detail', '')) for t in trips or ())
    return Trace(times, lengths, reference_lengths(scenario, reference, times), rows, withheld,
                 (mech.leg_length_min, mech.leg_length_max), missed, lost,
                 rate, records)


def _stop_group(proc: subprocess.Popen) -> None:
    """SIGINT to the rig's process group (it stops its nodes), then SIGKILL."""
    for sig, wait in ((signal.SIGINT, 20.0), (signal.SIGKILL, 5.0)):
        if proc.poll() is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, sig)
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(wait)


def rig_reference(reference: str, workdir: Path) -> str:
    """The reference CSV ``rig --reference`` takes: the scenario's, or a topic
    file's poses written as one (a trajectory with velocities is refused when
    the scenario is read)."""
    if not os.path.isdir(reference):
        return reference
    # lazy: bagio costs 197 ms; only a rig run needs it
    from stewart63_ros.bagruns import reference_points_from_bag
    from stewart63_ros.core.controllers.reference_files import write_reference_csv
    points = reference_points_from_bag(reference)
    path = workdir / 'reference.csv'
    write_reference_csv(path, points['times'], points['poses'])
    return str(path)


def run_rig(scenario, workdir: Path, domain: int | None = None):
    """Run a scenario with ``rig --mode lockstep|realtime`` on a leased ROS domain.

    ``domain``: run on that id instead of a leased one. Returns its
    ``Trace``; RuntimeError when the rig fails (its log's tail)."""
    params = workdir / 'params.yaml'
    write_parameter_file(scenario, params)
    bag, logs = workdir / 'bag', workdir / 'logs'
    cmd = [sys.executable, '-m', 'stewart63_ros.tools.rig', '--params', str(params),
           '--mode', scenario.run, '--duration', repr(scenario.duration),
           '--record', str(bag), '--log-dir', str(logs),
           # no fk: the verdicts read the plant's ground truth, not its pose
           '--nodes', 'plant,controller']
    if scenario.control_law:
        cmd += ['--control-law', scenario.control_law]
    if scenario.reference:
        cmd += ['--reference', rig_reference(scenario.reference, workdir)]
    for fault in scenario.faults:
        cmd += ['--fault', fault]
    if scenario.supervised:
        cmd += ['--supervisor']
    if scenario.bus:
        cmd += ['--bus', scenario.bus]
    bound = RIG_START_BOUND + 60.0 * scenario.duration
    with leased_domain(domain) as domain:
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1',
                   ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
        env.pop('ROS_LOCALHOST_ONLY', None)
        with open(workdir / 'rig.log', 'w') as log:
            proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env,
                                    start_new_session=True)
            try:
                code = proc.wait(bound)
            except subprocess.TimeoutExpired:
                code = None
            finally:
                _stop_group(proc)
    tail = ' | '.join((workdir / 'rig.log').read_text().strip().splitlines()[-3:])
    if code is None:
        raise RuntimeError('the rig did not finish within %.0f s: %s' % (bound, tail))
    summary_path = logs / 'plant_summary.json'
    if code != 0 or not summary_path.exists():
        raise RuntimeError('the rig failed (exit %s): %s' % (code, tail))
    trips = None
    if scenario.supervised:
        supervisor = logs / 'supervisor_summary.json'
        if not supervisor.exists():
            raise RuntimeError('the rig wrote no supervisor summary: %s' % tail)
        trips = json.loads(supervisor.read_text()).get('trips') or []
    return trace_from_rig(scenario, bag, json.loads(summary_path.read_text()), trips)
