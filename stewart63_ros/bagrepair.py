"""Repairing a bag whose recorder was killed hard (no MCAP summary or footer,
no ``metadata.yaml``): :func:`recover_bag` (``record --recover``).

Works without rclpy, as ``bagio``.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

from stewart63_ros.bagio import (
    BagError,
    _describe,
    _mcap_files,
    typestore,
)


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
