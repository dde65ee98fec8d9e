"""The recorder's batch writes give the bag rosbags' own writer gives (no DDS)."""
from __future__ import annotations

import numpy as np

from stewart63_ros import bagio
from stewart63_ros.recording.recorder import BatchWriter


def _bag(path, batched, topics):
    from rosbags.rosbag2 import StoragePlugin, Writer
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    conns = {topic: writer.add_connection(topic, type_name, typestore=bagio.typestore())
             for topic, (type_name, _) in topics.items()}
    batch = BatchWriter(writer)
    assert batch.direct or not batched          # this rosbags: the direct path
    for round_ in range(3):
        for topic, (_, messages) in topics.items():
            part = messages[round_::3]
            if batched:
                batch.write(conns[topic], part)
            else:
                for stamp, data in part:
                    writer.write(conns[topic], stamp, data)
    writer.close()
    return path


def test_batch_writes_equal_rosbags_writes_byte_for_byte(tmp_path):
    """Over more than one MCAP chunk (1 MiB), two topics interleaved in
    batches: the .mcap file and metadata.yaml equal those of
    ``Writer.write`` message by message."""
    rng = np.random.default_rng(3)
    topics = {}
    for k, (topic, type_name) in enumerate((('/leg_lengths', 'sensor_msgs/msg/JointState'),
                                            ('/clock', 'rosgraph_msgs/msg/Clock'))):
        stamps = np.cumsum(rng.integers(1, 10**6, size=3000)) + 10**18 + k
        topics[topic] = (type_name, [(int(t), rng.bytes(int(rng.integers(8, 700))))
                                     for t in stamps])
    direct = tmp_path / 'direct'
    each = tmp_path / 'each'
    direct.mkdir()
    each.mkdir()
    a = _bag(direct / 'bag', True, topics)
    b = _bag(each / 'bag', False, topics)
    mcap_a, mcap_b = (p / 'bag.mcap' for p in (a, b))
    assert mcap_a.stat().st_size > 2 * 2**20           # three chunks at least
    assert mcap_a.read_bytes() == mcap_b.read_bytes()
    assert (a / 'metadata.yaml').read_text() == (b / 'metadata.yaml').read_text()
    assert sum(1 for _ in bagio.read_raw(a)) == 6000
    print('\nbatch writer: %d messages, %.1f MiB, identical to rosbags Writer.write'
          % (6000, mcap_a.stat().st_size / 2**20))
