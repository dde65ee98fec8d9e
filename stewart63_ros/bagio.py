"""Reading the rosbag2 directories that ``record`` writes.

Everything here works without rclpy: ``plot``, the tests and ``play`` use it.

- :func:`read_messages` yields ``(topic, timestamp_ns, message)`` decoded with
  rosbags' Kilted type store (or the definitions stored in the bag).
- :func:`read_raw` yields the CDR bytes unchanged, for replay.

The plant's runs in a recording (and the trajectory CSV from one) are
``bagruns``'; repairing a bag whose recorder was killed hard is ``bagrepair``'s.

Every failure to read a bag (not a bag, truncated, corrupt, a topic that is not
in it) raises :class:`BagError`; the command-line tools turn it into a one-line
message and a non-zero exit.
"""
from __future__ import annotations

import dataclasses
import functools
from collections.abc import Iterable, Iterator
from pathlib import Path

from stewart63_ros.core.plumbing.stamps import stamp_ns

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
