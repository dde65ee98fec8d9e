"""The plant's runs in a recording (``bagio`` reads the bag): a bag that spans
a reset or a restarted plant holds several (docs/faults.md, "Reset").

- :func:`bag_runs` finds them, :func:`select_run` picks one;
- :func:`trajectory_from_bag` builds the columns of the trajectory CSV
  (docs/interface.md) from a recording, one run at a time;
- :func:`reference_from_bag` rebuilds the reference the controller followed.

Everything here works without rclpy, as ``bagio``.
"""
from __future__ import annotations

import numpy as np

from stewart63_ros.bagio import (
    BagError,
    BagRun,
    _describe,
    header_stamp_ns,
    open_reader,
    resolve_bag_topics,
)
from stewart63_ros.core.plumbing.trajectory import COLUMNS


def _plant_run_number(msg) -> int | None:
    """The plant's ``run_number`` in a DiagnosticArray, or None."""
    for status in msg.status:
        if status.name.endswith('/plant'):
            for kv in status.values:
                if kv.key == 'run_number':
                    try:
                        return int(kv.value)
                    except ValueError:
                        return None
    return None


def bag_runs(bag_dir) -> list[BagRun]:
    """The plant's runs a recording holds, in order.

    A new run begins at the first sample after the plant's ``run_number``
    changed on /diagnostics (a ``~/reset``: sent a quiet second before the new
    run's first sample, in realtime and lockstep alike), or at a sample whose
    stamp is before the previous sample's (a lockstep run's stamps start at 0
    again: a reset, or a plant started again, also without /diagnostics in
    the bag). The samples are ``leg_lengths`` (else ``ground_truth/pose``,
    else ``platform_pose``). Messages of other topics belong to the run whose
    window [start_ns, stop_ns) holds their recording time: a late answer to a
    run's last sample stays with that run.

    Args:
        bag_dir: the bag directory.

    Returns:
        One ``BagRun`` per run (one for a bag of one run; none for a bag
        without samples).

    Raises:
        BagError: not a readable bag.
    """
    reader = open_reader(bag_dir)
    try:
        def find(name):
            try:
                return resolve_bag_topics(reader, [name])[0]
            except BagError:
                return None
        sample_topic = find('leg_lengths') or find('ground_truth/pose') or find('platform_pose')
        if sample_topic is None:
            return []
        diagnostics = find('/diagnostics')
        conns = [c for c in reader.connections if c.topic in (sample_topic, diagnostics)]
        starts: list[list] = []         # [start_ns, plant number, samples]
        announced = None                # the run_number last seen on /diagnostics
        previous = None                 # the last sample's stamp
        pending = False                 # a new run_number: the next sample starts a run
        try:
            for conn, when, raw in reader.messages(connections=conns):
                msg = reader.deserialize(raw, conn.msgtype)
                if conn.topic == diagnostics:
                    number = _plant_run_number(msg)
                    if number is not None:
                        if starts and number != announced:
                            pending = True
                        if starts and starts[-1][1] is None:
                            starts[-1][1] = number      # recorded from the middle of a run
                        announced = number
                    continue
                stamp = header_stamp_ns(msg)
                if not starts or pending or (previous is not None and stamp < previous):
                    starts.append([when, announced, 0])
                    pending = False
                starts[-1][2] += 1
                previous = stamp
        except Exception as exc:
            raise BagError(f'{bag_dir}: damaged bag: {_describe(exc)}') from exc
    finally:
        reader.close()
    count = len(starts)
    return [BagRun(k + 1, count, number, start,
                   starts[k + 1][0] if k + 1 < count else None, samples)
            for k, (start, number, samples) in enumerate(starts)]


def select_run(runs: list[BagRun], number: int | None = None) -> BagRun:
    """The run ``number`` (the plant's number, else the bag's index) of ``runs``,
    or the last one.

    Args:
        runs: ``bag_runs``' list.
        number: the run asked for (``--run``), or None for the last.

    Returns:
        The run.

    Raises:
        BagError: no such run (naming those there are), or no run at all.
    """
    if not runs:
        raise BagError('the bag holds no samples')
    if number is None:
        return runs[-1]
    for run in runs:
        if (run.number if run.number is not None else run.index) == number:
            return run
    raise BagError('no run %d in the bag (it holds %s)'
                   % (number, ', '.join(r.name for r in runs)))


def trajectory_from_bag(bag_dir, *, relative_time: bool = True,
                        hold_forces: bool = False,
                        run: BagRun | None = None) -> dict[str, np.ndarray]:
    """The trajectory CSV's columns (:data:`COLUMNS`) from a recording, of one run.

    ``run``: the run (:func:`bag_runs`) to read; default the bag's last run
    (a bag that spans a reset holds several, whose stamps may overlap: they
    are never joined into one trajectory).
    One row per ``leg_lengths`` sample (per pose sample if the bag has no leg
    lengths). The pose and twist come from ``ground_truth/pose`` and
    ``ground_truth/twist`` when the bag has them, else from ``platform_pose``
    and ``platform_twist``; ``leg_forces`` gives F. Rows are joined on
    ``header.stamp`` (a pose's stamp is its sample's; ``leg_forces`` carries the
    stamp of the sample it answers); a value with no message of that stamp is
    NaN (a controller running slower than the sensor answers only some samples);
    with ``hold_forces`` each F row instead holds the last force received
    (zero-order hold, as the plant applies it).
    θ = ``core.mechanics.rotation.euler_from_quaternion(q)`` (R = Rz·Ry·Rx). ``t`` is the
    stamp in seconds, from the first row's stamp when ``relative_time``.
    """
    # lazy: core.mechanics.rotation costs 649 ms (numba, scipy); plot needs no core
    from stewart63_ros.core.mechanics.rotation import euler_from_quaternion

    if run is None:
        runs = bag_runs(bag_dir)
        run = runs[-1] if runs else None
    window = {} if run is None else {'start': run.start_ns, 'stop': run.stop_ns}
    reader = open_reader(bag_dir)
    try:
        available = {c.topic for c in reader.connections}

        def find(name):
            try:
                return resolve_bag_topics(reader, [name])[0]
            except BagError:
                return None
        pose_t, twist_t = find('ground_truth/pose'), find('ground_truth/twist')
        if pose_t is None:
            pose_t, twist_t = find('platform_pose'), find('platform_twist')
        legs_t, forces_t = find('leg_lengths'), find('leg_forces')
        if legs_t is None and pose_t is None:
            raise BagError(f'{bag_dir}: no leg_lengths, ground_truth/pose or platform_pose '
                           f'in the bag (it has: {", ".join(sorted(available)) or "no topics"})')
        wanted = [t for t in (pose_t, twist_t, legs_t, forces_t) if t]
        conns = [c for c in reader.connections if c.topic in wanted]
        data = {t: {} for t in wanted}
        try:
            for conn, _, raw in reader.messages(connections=conns, **window):
                msg = reader.deserialize(raw, conn.msgtype)
                topic = conn.topic
                stamp = header_stamp_ns(msg)
                if topic == pose_t:
                    p, q = msg.pose.position, msg.pose.orientation
                    data[topic][stamp] = (p.x, p.y, p.z, q.x, q.y, q.z, q.w)
                elif topic == twist_t:
                    v, w = msg.twist.linear, msg.twist.angular
                    data[topic][stamp] = (v.x, v.y, v.z, w.x, w.y, w.z)
                elif topic == legs_t:
                    data[topic][stamp] = (_six(msg.position), _six(msg.velocity))
                else:
                    data[topic][stamp] = _six(msg.effort)
        except BagError:
            raise
        except Exception as exc:
            raise BagError(f'{bag_dir}: damaged bag: {_describe(exc)}') from exc
    finally:
        reader.close()

    base = data[legs_t] if legs_t else data[pose_t]
    stamps = np.array(sorted(base), dtype=np.int64)
    n = len(stamps)
    cols = {name: np.full(n, np.nan) for name in COLUMNS}
    if n == 0:
        cols['t'] = np.zeros(0)
        return cols
    t0 = stamps[0] if relative_time else 0
    cols['t'] = (stamps - t0) * 1e-9

    if pose_t:
        pose = np.full((n, 7), np.nan)
        for i, s in enumerate(stamps):
            v = data[pose_t].get(int(s))
            if v is not None:
                pose[i] = v
        for k, name in enumerate(('x', 'y', 'z')):
            cols[name] = pose[:, k]
        ok = np.all(np.isfinite(pose[:, 3:]), axis=1) & (np.linalg.norm(
            np.nan_to_num(pose[:, 3:]), axis=1) > 0)
        if ok.any():
            euler = np.full((n, 3), np.nan)
            euler[ok] = euler_from_quaternion(pose[ok, 3:])
            for k, name in enumerate(('theta_x', 'theta_y', 'theta_z')):
                cols[name] = euler[:, k]
    if twist_t:
        for i, s in enumerate(stamps):
            v = data[twist_t].get(int(s))
            if v is not None:
                for k, name in enumerate(('vx', 'vy', 'vz', 'wx', 'wy', 'wz')):
                    cols[name][i] = v[k]
    if legs_t:
        for i, s in enumerate(stamps):
            pos, vel = data[legs_t][int(s)]
            for k in range(6):
                cols[f'L{k + 1}'][i] = pos[k]
                cols[f'Ldot{k + 1}'][i] = vel[k]
    if forces_t:
        for i, s in enumerate(stamps):
            f = data[forces_t].get(int(s))
            if f is not None:
                for k in range(6):
                    cols[f'F{k + 1}'][i] = f[k]
        if hold_forces:
            for k in range(6):
                col = cols[f'F{k + 1}']
                idx = np.where(np.isfinite(col), np.arange(n), 0)
                np.maximum.accumulate(idx, out=idx)
                cols[f'F{k + 1}'] = col[idx]   # rows before the first force stay NaN
    return cols


#: The topics a reference topic file holds, and their types (docs/scenarios.md).
REFERENCE_TOPICS = {'pose_trajectory': 'trajectory_msgs/msg/MultiDOFJointTrajectory',
                    'pose_setpoint': 'geometry_msgs/msg/PoseStamped'}


def reference_points_from_bag(bag_dir) -> dict[str, np.ndarray | None]:
    """A reference motion's points from a topic file (a rosbag2 directory).

    The bag holds either one ``pose_trajectory``
    (``trajectory_msgs/msg/MultiDOFJointTrajectory`` of the one joint
    ``platform``, as the controller follows it: its points at their
    ``time_from_start``, with velocities and accelerations where every point
    has them), or ``pose_setpoint`` messages (``geometry_msgs/msg/PoseStamped``:
    one point per message, at its header stamp from the first one's). Both, or
    several trajectories, are refused: which one would the run follow?

    Returns:
        {'times' (N,) [s], 'poses' (N, 6) [m, rad] (theta unwrapped),
        'rates' (N, 6) or None, 'accelerations' (N, 6) or None, 'topic'}.

    Raises:
        BagError: not a bag, none of the topics, both, a bad message.
    """
    # lazy: core.controllers.reference costs 570 ms (numba); plot needs no core
    from stewart63_ros.core.controllers.reference import MessageError
    from stewart63_ros.core.controllers.reference_files import (
        message_quaternion,
        trajectory_points,
        trajectory_poses,
    )
    reader = open_reader(bag_dir)
    try:
        found = {}
        for name in REFERENCE_TOPICS:
            try:
                found[name] = resolve_bag_topics(reader, [name])[0]
            except BagError:
                pass
        available = sorted({c.topic for c in reader.connections})
        if not found:
            raise BagError(f'{bag_dir}: no pose_trajectory or pose_setpoint in the bag '
                           f'(it has: {", ".join(available) or "no topics"})')
        if len(found) == 2:
            raise BagError(f'{bag_dir}: holds both pose_trajectory and pose_setpoint: a '
                           f'reference is one of them')
        name, topic = next(iter(found.items()))
        conns = [c for c in reader.connections if c.topic == topic]
        try:
            msgs = [reader.deserialize(raw, conn.msgtype)
                    for conn, _, raw in reader.messages(connections=conns)]
        except Exception as exc:
            raise BagError(f'{bag_dir}: damaged bag: {_describe(exc)}') from exc
    finally:
        reader.close()
    if not msgs:
        raise BagError(f'{bag_dir}: {topic} holds no message')
    twists = accels = None
    try:
        if name == 'pose_trajectory':
            if len(msgs) > 1:
                raise BagError(f'{bag_dir}: {topic} holds {len(msgs)} trajectories: a '
                               f'reference is one')
            times, translations, quats, twists, accels = trajectory_points(msgs[0])
        else:
            stamps = np.array([header_stamp_ns(m) for m in msgs], dtype=np.int64)
            times = (stamps - stamps[0]) * 1e-9
            translations = [[m.pose.position.x, m.pose.position.y, m.pose.position.z]
                            for m in msgs]
            quats = [message_quaternion(m.pose.orientation, 'message %d orientation' % k)
                     for k, m in enumerate(msgs)]
            if not np.all(np.isfinite(translations)):
                raise BagError(f'{bag_dir}: {topic}: a position holds NaN or Inf')
    except MessageError as exc:
        raise BagError(f'{bag_dir}: {topic}: {exc}') from None
    poses, rates, accs = trajectory_poses(translations, quats, twists, accels)
    return {'times': times, 'poses': poses, 'rates': rates, 'accelerations': accs,
            'topic': topic}


def reference_from_bag(mech, bag_dir, max_leg_speed: float = 0.0,
                       max_leg_acceleration: float = 0.0):
    """A checked ``core.controllers.reference.Reference`` from a topic file
    (:func:`reference_points_from_bag`), interpolated as a reference CSV is
    (clamped cubic through the poses; Hermite where velocities are given).

    Raises:
        ReferenceError: the bag cannot be read, or its motion is refused
            (``Reference.check``), naming the bag.
    """
    # lazy: core.controllers.reference costs 570 ms (numba); plot needs no core
    from stewart63_ros.core.controllers.reference import Reference, ReferenceError
    try:
        points = reference_points_from_bag(bag_dir)
    except BagError as exc:
        raise ReferenceError(str(exc)) from None
    try:
        ref = Reference.from_poses(mech, points['times'], points['poses'], points['rates'],
                                   points['accelerations'])
        ref.check(max_leg_speed, max_leg_acceleration)
    except ReferenceError as exc:
        raise ReferenceError('%s: %s' % (bag_dir, exc)) from None
    return ref


def _six(values) -> np.ndarray:
    out = np.full(6, np.nan)
    arr = np.asarray(values, dtype=float).ravel()[:6]
    out[:len(arr)] = arr
    return out
