"""Reading (and repairing) the rosbag2 directories that ``record`` writes.

Everything here works without rclpy: ``plot``, the tests and ``play`` use it.

- :func:`read_messages` yields ``(topic, timestamp_ns, message)`` decoded with
  rosbags' Kilted type store (or the definitions stored in the bag).
- :func:`read_raw` yields the CDR bytes unchanged, for replay.
- :func:`bag_runs` finds the plant's runs in a recording that spans a reset;
- :func:`trajectory_from_bag` builds the columns of the trajectory CSV
  (docs/interface.md) from a recording, one run at a time.
- :func:`recover_bag` repairs a bag whose recorder was killed hard (no MCAP
  summary/footer, no ``metadata.yaml``).

Every failure to read a bag (not a bag, truncated, corrupt, a topic that is not
in it) raises :class:`BagError`; the command-line tools turn it into a one-line
message and a non-zero exit.
"""
from __future__ import annotations

import dataclasses
import functools
import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from stewart63_ros.core.plumbing.stamps import stamp_ns
from stewart63_ros.core.plumbing.trajectory import COLUMNS

#: Key of ``metadata.yaml``'s ``custom_data`` holding the namespace a bag was
#: recorded in (``/`` when none): ``play --namespace`` re-roots topics from it.
NAMESPACE_KEY = 'stewart63_ros.namespace'

#: Topics whose names stay absolute whatever the namespace.
ABSOLUTE_TOPICS = ('/clock', '/diagnostics')


class BagError(Exception):
    """A path that is not a readable bag, a damaged bag, or a missing topic."""


@functools.lru_cache(maxsize=1)
def typestore():
    """rosbags' type store for ROS 2 Kilted (the distro of the wheels)."""
    # lazy: rosbags.typesys costs 74 ms; plot of a CSV needs no bag
    from rosbags.typesys import Stores, get_typestore
    store = getattr(Stores, 'ROS2_KILTED', None) or Stores.LATEST
    return get_typestore(store)


# --------------------------------------------------------------------------
# Opening


def _mcap_files(path: Path) -> list[Path]:
    return sorted(p for p in path.glob('*.mcap') if p.is_file())


def check_bag_dir(bag_dir) -> Path:
    """The bag directory as a Path, or :class:`BagError` saying why it is not one."""
    path = Path(bag_dir)
    if not path.exists():
        raise BagError(f'{path}: no such bag directory')
    if not path.is_dir():
        raise BagError(f'{path}: not a bag (a rosbag2 bag is a directory with metadata.yaml)')
    if not (path / 'metadata.yaml').is_file():
        if _mcap_files(path):
            raise BagError(f'{path}: metadata.yaml is missing (was the recorder killed?); '
                           f'repair it with: record --recover {path}')
        raise BagError(f'{path}: not a bag (no metadata.yaml)')
    return path


def open_reader(bag_dir):
    """An opened rosbags ``AnyReader`` on ``bag_dir``; close it (or use ``with``)."""
    # lazy: rosbags.highlevel costs 181 ms; plot of a CSV needs no bag
    from rosbags.highlevel import AnyReader
    path = check_bag_dir(bag_dir)
    reader = AnyReader([path], default_typestore=typestore())
    try:
        reader.open()
    except Exception as exc:  # rosbags raises several types; one for our callers
        raise BagError(f'{path}: cannot read bag: {_describe(exc)}') from exc
    return reader


def _describe(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0]


def bag_namespace(reader) -> str:
    """The namespace the bag was recorded in (``/`` if not recorded by ``record``)."""
    for path in getattr(reader, 'paths', []):
        try:
            # lazy: ruamel.yaml costs 54 ms; only a bag's metadata needs it
            from ruamel.yaml import YAML, YAMLError
            meta = YAML(typ='safe').load((Path(path) / 'metadata.yaml').read_text())
            custom = meta['rosbag2_bagfile_information'].get('custom_data') or {}
        except (OSError, YAMLError, KeyError, TypeError, AttributeError):
            continue
        if custom.get(NAMESPACE_KEY):
            return str(custom[NAMESPACE_KEY])
    return '/'


def resolve_bag_topics(reader, topics: Iterable[str] | None) -> list[str]:
    """Full bag topic names for ``topics`` (relative names resolve under the
    namespace the bag was recorded in; then under ``/``; then as the unique bag
    topic ending in ``/name``). ``None`` means every topic. Unknown topics raise
    :class:`BagError`, naming the topics the bag has."""
    available = sorted({c.topic for c in reader.connections})
    if topics is None:
        return available
    ns = bag_namespace(reader).rstrip('/')
    out = []
    for name in topics:
        found = None
        if name.startswith('/'):
            found = name if name in available else None
        else:
            for cand in (f'{ns}/{name}', f'/{name}'):
                if cand in available:
                    found = cand
                    break
            if found is None:
                ends = [t for t in available if t.endswith('/' + name)]
                if len(ends) == 1:
                    found = ends[0]
        if found is None:
            raise BagError(f'topic {name!r} is not in the bag '
                           f'(it has: {", ".join(available) or "no topics"})')
        if found not in out:
            out.append(found)
    return out


# --------------------------------------------------------------------------
# Reading


def read_raw(bag_dir, topics: Iterable[str] | None = None, start_ns: int | None = None
             ) -> Iterator[tuple[str, str, int, bytes]]:
    """Yield ``(topic, msgtype, timestamp_ns, cdr_bytes)`` in timestamp order."""
    reader = open_reader(bag_dir)
    try:
        names = set(resolve_bag_topics(reader, topics))
        conns = [c for c in reader.connections if c.topic in names]
        if not conns:
            return
        try:
            for conn, stamp, data in reader.messages(connections=conns, start=start_ns):
                yield conn.topic, conn.msgtype, stamp, data
        except Exception as exc:
            raise BagError(f'{bag_dir}: damaged bag: {_describe(exc)}') from exc
    finally:
        reader.close()


def read_messages(bag_dir, topics: Iterable[str] | None = None, run: BagRun | None = None
                  ) -> Iterator[tuple[str, int, object]]:
    """Yield ``(topic, timestamp_ns, message)`` decoded, in timestamp order.

    ``topics`` are bag topic names (``/leg_lengths``) or relative names
    (``leg_lengths``); ``None`` reads every topic. ``run``: only the messages
    recorded during that run (:func:`bag_runs`). Messages are rosbags
    dataclasses (``msg.header.stamp.sec``, ``msg.position`` as a numpy array).
    """
    reader = open_reader(bag_dir)
    try:
        names = set(resolve_bag_topics(reader, topics))
        conns = [c for c in reader.connections if c.topic in names]
        if not conns:
            return
        window = {} if run is None else {'start': run.start_ns, 'stop': run.stop_ns}
        try:
            for conn, stamp, data in reader.messages(connections=conns, **window):
                yield conn.topic, stamp, reader.deserialize(data, conn.msgtype)
        except Exception as exc:
            raise BagError(f'{bag_dir}: damaged bag: {_describe(exc)}') from exc
    finally:
        reader.close()


def bag_info(bag_dir) -> dict:
    """``{'topics': {topic: (msgtype, count)}, 'start_ns', 'end_ns', 'message_count',
    'namespace'}`` from the bag's metadata."""
    reader = open_reader(bag_dir)
    try:
        topics = {}
        for conn in reader.connections:
            msgtype, count = topics.get(conn.topic, (conn.msgtype, 0))
            topics[conn.topic] = (msgtype, count + conn.msgcount)
        return {'topics': topics, 'start_ns': reader.start_time, 'end_ns': reader.end_time,
                'message_count': reader.message_count, 'namespace': bag_namespace(reader)}
    finally:
        reader.close()


def header_stamp_ns(msg) -> int:
    """A stamped message's ``header.stamp`` in integer nanoseconds."""
    return stamp_ns(msg.header.stamp)


# --------------------------------------------------------------------------
# Runs: a bag that spans a reset (or a restarted plant) holds several


@dataclasses.dataclass(frozen=True)
class BagRun:
    """One run of the plant in a recording (docs/faults.md, "Reset").

    Attributes:
        index: 1, 2, ... in the order recorded.
        count: how many runs the bag holds.
        number: the plant's ``run_number`` (its /diagnostics status) during
            the run, or None when the bag has no plant status.
        start_ns, stop_ns: the recording times (bag timestamps) the run
            covers: from its first sample to the next run's first sample
            (None: to the end of the bag).
        samples: its samples (``leg_lengths``, else poses).
    """
    index: int
    count: int
    number: int | None
    start_ns: int
    stop_ns: int | None
    samples: int

    @property
    def name(self) -> str:
        """How the tools name the run: ``run 2`` (the plant's number), else ``run 2 of 3``
        of the bag's order."""
        if self.number is not None:
            return 'run %d' % self.number
        return 'run %d of %d' % (self.index, self.count)

    @property
    def label(self) -> str:
        """The run in a file name: ``run2`` (the plant's number, else the index)."""
        return 'run%d' % (self.number if self.number is not None else self.index)


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


# --------------------------------------------------------------------------
# Recovery after a hard kill


def recover_bag(bag_dir) -> dict[str, int]:
    """Repair a bag whose recorder died without closing it.

    What such a bag holds: the MCAP file up to the last chunk the recorder
    flushed (it flushes every ``flush_period``), then possibly a partly written
    chunk, and no summary, footer or ``metadata.yaml``. This reads every
    complete record (schemas, channels with their offered QoS, messages), writes
    a new, complete MCAP file and ``metadata.yaml`` in ``bag_dir``, and keeps
    the damaged file beside it as ``<name>.mcap.orig``. A bag that is already
    complete is re-indexed the same way (its messages are all kept).

    Returns the number of messages recovered per topic. Raises :class:`BagError`
    if ``bag_dir`` holds no MCAP file or nothing readable.
    """
    # lazy: mcap and rosbags.rosbag2 cost 182 ms; only record --recover needs them
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader
    from rosbags.rosbag2 import ReaderError, StoragePlugin, Writer
    from rosbags.rosbag2.metadata import parse_qos
    from rosbags.typesys import Stores, get_types_from_msg
    from rosbags.typesys import get_typestore as _get_typestore

    path = Path(bag_dir)
    if not path.is_dir():
        raise BagError(f'{path}: not a bag directory')
    files = [p for p in _mcap_files(path)]
    if not files:
        raise BagError(f'{path}: no .mcap file to recover')
    if len(files) > 1:
        raise BagError(f'{path}: several .mcap files ({", ".join(p.name for p in files)}); '
                       'recover handles one')
    src = files[0]
    orig = src.with_name(src.name + '.orig')
    if orig.exists():
        raise BagError(f'{orig} exists already (an earlier recovery?); not overwriting it')

    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    messages: list[tuple[int, int, bytes]] = []
    damaged = None
    try:
        with src.open('rb') as fh:
            for rec in StreamReader(fh, record_size_limit=2**31).records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Message):
                    messages.append((rec.channel_id, rec.log_time, bytes(rec.data)))
    except Exception as exc:  # noqa: BLE001 - any damage in the tail of a killed recording
        damaged = _describe(exc)
    if not channels:
        raise BagError(f'{src}: no readable MCAP records'
                       + (f' ({damaged})' if damaged else ''))

    kilted = typestore()
    custom = {}
    meta_path = path / 'metadata.yaml'
    if meta_path.is_file():
        try:
            # lazy: ruamel.yaml costs 54 ms; only a bag's metadata needs it
            from ruamel.yaml import YAML, YAMLError
            meta = YAML(typ='safe').load(meta_path.read_text())
            custom = dict(meta['rosbag2_bagfile_information'].get('custom_data') or {})
        except (OSError, YAMLError, KeyError, TypeError, AttributeError, ValueError):
            custom = {}

    tmp_parent = Path(tempfile.mkdtemp(prefix='.recover-', dir=path.parent))
    try:
        out_dir = tmp_parent / path.name
        writer = Writer(out_dir, version=9, storage_plugin=StoragePlugin.MCAP)
        for key, value in custom.items():
            writer.set_custom_data(str(key), str(value))
        writer.open()
        conns = {}
        counts: dict[str, int] = {}
        for cid, chan in sorted(channels.items()):
            schema = schemas.get(chan.schema_id)
            msgtype = schema.name if schema else ''
            if msgtype in kilted.fielddefs:
                store = kilted
            else:
                store = _get_typestore(Stores.EMPTY)
                if schema is None or schema.encoding != 'ros2msg':
                    raise BagError(f'{src}: no usable definition of type {msgtype!r}')
                store.register(get_types_from_msg(schema.data.decode(), msgtype))
            try:
                qos = parse_qos(chan.metadata.get('offered_qos_profiles', ''))
            except (ReaderError, KeyError, TypeError, ValueError, AttributeError):
                qos = []
            conns[cid] = writer.add_connection(
                chan.topic, msgtype, typestore=store,
                serialization_format=chan.message_encoding or 'cdr',
                offered_qos_profiles=qos)
            counts[chan.topic] = 0
        for cid, stamp, data in sorted(messages, key=lambda m: m[1]):
            conn = conns.get(cid)
            if conn is None:
                continue
            writer.write(conn, stamp, data)
            counts[conn.topic] += 1
        writer.close()
        # Swap in: keep the damaged file, then move the new files in.
        os.replace(src, orig)
        for item in out_dir.iterdir():
            if item.name == 'metadata.yaml':
                continue
            os.replace(item, path / item.name)
        os.replace(out_dir / 'metadata.yaml', meta_path)
    finally:
        shutil.rmtree(tmp_parent, ignore_errors=True)
    return counts

