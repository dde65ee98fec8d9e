"""The rig's Fast DDS defaults (``config/fastdds.xml``), for every process of a rig.

Standard library only: called before rclpy creates a participant, and from
``rig`` before it starts its children.
"""
from __future__ import annotations

import os
from pathlib import Path

from stewart63_ros.paths import default_params_path

#: Fast DDS reads its default profiles from the file this names.
PROFILES_VARIABLE = 'FASTDDS_DEFAULT_PROFILES_FILE'


def rig_profile_path() -> Path:
    """Where the packaged ``config/fastdds.xml`` is (beside the parameter file)."""
    return default_params_path().parent / 'fastdds.xml'


def use_rig_profile(env: dict | None = None) -> str:
    """Point ``PROFILES_VARIABLE`` in ``env`` (default: this process's
    environment, read by Fast DDS when the first participant is made) at the
    rig's profile, unless it is set already: a user's own file wins (it
    should then carry the rig's heartbeat settings, docs/interface.md).
    Returns the file in force."""
    env = os.environ if env is None else env
    if not env.get(PROFILES_VARIABLE):
        try:
            path = rig_profile_path()
        except FileNotFoundError:
            return ''
        if path.is_file():
            env[PROFILES_VARIABLE] = str(path)
    return env.get(PROFILES_VARIABLE, '')
