"""A 6-6 test geometry for the tests of the mechanism's consumers.

The packaged 6-3 with each platform vertex p_k split into two joints, one per
leg of its pair, ``split`` metres apart along the vertex circle's tangent
(leg 2k-1 on the side of its base point b_{2k-1}), and the base turned by
``base_turn`` radians about z: a semi-regular 6-6 close to the packaged 6-3, so
the paper's setpoint and start pose still fit its stroke. A plain module (not a
fixture) so that any test file can build one with its own split.
"""
from __future__ import annotations

import numpy as np

from stewart63_ros.core.mechanics.setup import Setup
from stewart63_ros.core.plumbing.legs import LEG_VERTEX


def split_platform_points(platform_points, split: float) -> np.ndarray:
    """(3, 3) vertices of a 6-3 -> (6, 3) joints of a 6-6, each pair ``split`` m apart.

    Leg 2k-1 (0-based even) goes to the clockwise side, leg 2k to the
    counter-clockwise side, as their base points lie (azimuth -55 / +55 deg).
    """
    plat = np.asarray(platform_points, float).reshape(3, 3)
    joints = np.empty((6, 3))
    for leg in range(6):
        p = plat[LEG_VERTEX[leg]]
        tangent = np.array([-p[1], p[0], 0.0]) / np.hypot(p[0], p[1])
        joints[leg] = p + (0.5 if leg % 2 else -0.5) * split * tangent
    return joints


def turned_z(points, angle: float) -> np.ndarray:
    """``points`` (n, 3) turned by ``angle`` [rad] about z."""
    c, s = np.cos(angle), np.sin(angle)
    return np.asarray(points, float) @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T


def setup66(setup63: Setup, split: float = 0.06, base_turn: float = np.radians(1.0)) -> Setup:
    """The 6-6 of ``setup63``'s 6-3 (module docstring), its gains, task and settings.

    Args:
        setup63: a 6-3 setup (the packaged one).
        split: the distance between a pair's two platform joints [m].
        base_turn: the base's turn about z [rad].

    Returns:
        The validated 6-6 setup (its ``mechanism.layout`` is '6-6').
    """
    mech = setup63.mechanism
    return setup63.replace(platform_points=split_platform_points(mech.platform_points, split),
                           base_points=turned_z(mech.base_points, base_turn))
