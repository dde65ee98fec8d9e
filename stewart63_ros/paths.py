"""Where the package's files are, and the clock mode a rig runs in. Standard
library only: the launch files import it in a Python that may have ``launch``
but not numpy or scipy (and ``rig`` before its stop handlers are in place)."""
from __future__ import annotations

import fcntl
import os
import sys
from pathlib import Path

#: The clock mode a rig runs in unless told otherwise (``rig --mode``, ``demo
#: --mode``, the launch files' ``clock_mode:=``), written once. The packaged
#: file sets the same for every node (its ``/**`` section), so that a plant,
#: controller and fk each started by hand with it agree. A node given no
#: ``clock_mode`` runs in the declared default (core/plumbing/node_parameters.py),
#: ``realtime``: alone, it runs; in lockstep it would wait for a controller.
RIG_CLOCK_MODE = 'lockstep'


#: The packaged parameter file of each geometry (docs/geometry.md).
PACKAGED_GEOMETRIES = {'6-3': 'stewart63.yaml', '6-6': 'hexapod66.yaml'}


def packaged_params_path(geometry: str) -> Path:
    """The packaged parameter file of ``geometry`` ('6-3': the paper's,
    config/stewart63.yaml; '6-6': config/hexapod66.yaml), beside the default.

    Raises:
        ValueError: a geometry not packaged.
    """
    if geometry not in PACKAGED_GEOMETRIES:
        raise ValueError('geometry %r: packaged are %s'
                         % (geometry, ', '.join(PACKAGED_GEOMETRIES)))
    return default_params_path().parent / PACKAGED_GEOMETRIES[geometry]


def default_params_path() -> Path:
    """Where the packaged ``config/stewart63.yaml`` is, installed or in a checkout."""
    candidates = []
    try:  # a colcon / ROS install
        # lazy: optional, a ROS install only: ament_index_python costs 3 ms
        from ament_index_python.packages import get_package_share_directory
        candidates.append(Path(get_package_share_directory('stewart63_ros')) / 'config')
    except Exception:  # noqa: BLE001 - not a ROS install, or package not indexed
        pass
    candidates.append(Path(__file__).resolve().parents[1] / 'config')  # checkout / editable
    candidates.append(Path(sys.prefix) / 'share' / 'stewart63_ros' / 'config')  # pip install
    for folder in candidates:
        if (folder / 'stewart63.yaml').is_file():
            return folder / 'stewart63.yaml'
    raise FileNotFoundError('config/stewart63.yaml not found in %s' % [str(c) for c in candidates])


def domain_lock_dir() -> Path:
    """The lock files by which processes on this machine lease ROS domain ids
    (test/ros_harness.py, the benchmarks, ``scenario``)."""
    import tempfile  # lazy: tempfile costs 4 ms alone, 15 ms in rig's and record's start-up
    return Path(tempfile.gettempdir()) / 'stewart63_ros_domains'


def try_lock_domain(domain: int) -> int | None:
    """The open, exclusively locked lock file of ``domain`` (close it to
    release the id), or None when another process holds it."""
    folder = domain_lock_dir()
    folder.mkdir(parents=True, exist_ok=True)
    fd = os.open(folder / ('%d.lock' % domain), os.O_CREAT | os.O_RDWR, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return None
    return fd
