"""A reference from outside: the reference CSV (``t,x,y,z,theta_x,theta_y,theta_z``,
docs/interface.md) read and written, and a ``trajectory_msgs`` message's
points turned into poses (the controller's ``~/reference`` topic). Both
become a ``reference.Reference``.
"""
from __future__ import annotations

import csv
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from stewart63_ros.core.mechanics.rotation import (
    euler_from_quaternion,
    euler_rate_matrix,
)

if TYPE_CHECKING:
    from stewart63_ros.core.mechanics.mechanism import Mechanism
from stewart63_ros.core.controllers.reference import (
    CSV_COLUMNS,
    MessageError,
    Reference,
    ReferenceError,
)


def read_reference_csv(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a reference CSV ``t,x,y,z,theta_x,theta_y,theta_z``.

    Args:
        path: the file.

    Returns:
        (times (N,) [s], poses (N, 6) [m, rad]).

    Raises:
        ReferenceError: the file cannot be read, or is not such a CSV.
    """
    path = Path(path)
    try:
        with open(path, newline='') as stream:
            rows = list(csv.reader(stream))
    except OSError as exc:
        raise ReferenceError('cannot read %s: %s' % (path, exc.strerror)) from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise ReferenceError('%s is not a reference CSV: %s' % (path, exc)) from None
    rows = [r for r in rows if r and any(c.strip() for c in r)]
    if not rows or tuple(c.strip() for c in rows[0]) != CSV_COLUMNS:
        raise ReferenceError('%s: the header must be %s' % (path, ','.join(CSV_COLUMNS)))
    if len(rows) < 2:
        raise ReferenceError('%s holds no poses' % path)
    try:
        table = np.array([[float(c) for c in r] for r in rows[1:]])
    except ValueError:
        raise ReferenceError('%s: every row must hold 7 numbers' % path) from None
    if table.ndim != 2 or table.shape[1] != 7:
        raise ReferenceError('%s: every row must hold 7 numbers' % path)
    return table[:, 0], table[:, 1:]


def load_reference(mech: Mechanism, path: str | os.PathLike, max_leg_speed: float = 0.0,
                   max_leg_acceleration: float = 0.0) -> Reference:
    """A checked reference from a reference CSV.

    Args:
        mech: the mechanism; path: the CSV file.
        max_leg_speed, max_leg_acceleration: as for ``Reference.check``.

    Returns:
        The reference, checked.

    Raises:
        ReferenceError: naming the file, as ``read_reference_csv``,
            ``Reference.from_poses`` and ``Reference.check``.
    """
    times, poses = read_reference_csv(path)
    try:
        ref = Reference.from_poses(mech, times, poses)
        ref.check(max_leg_speed, max_leg_acceleration)
    except ReferenceError as exc:
        raise ReferenceError('%s: %s' % (path, exc)) from None
    return ref


#: The one joint of a pose_trajectory.
PLATFORM_JOINT = 'platform'


def _finite(values, size: int, field: str) -> np.ndarray:
    arr = np.asarray(values, dtype=float)
    if arr.shape != (size,) or not np.all(np.isfinite(arr)):
        raise MessageError('non_finite' if arr.shape == (size,) else 'wrong_size',
                           '%s must be %d finite numbers' % (field, size))
    return arr


def message_quaternion(q: Any, field: str) -> np.ndarray:
    """(4,) x, y, z, w of a message's quaternion ``q`` (fields x, y, z, w),
    normalised; MessageError unless finite with a norm within 10 % of 1."""
    quat = _finite([q.x, q.y, q.z, q.w], 4, field)
    norm = np.linalg.norm(quat)
    if not 0.9 < norm < 1.1:
        raise MessageError('bad_quaternion', '%s is not a unit quaternion (norm %.3g)'
                           % (field, norm))
    return quat / norm


def trajectory_points(msg: Any) -> tuple:
    """The points of a ``MultiDOFJointTrajectory`` of the one joint ``platform``
    (the controller's ``pose_trajectory``, or one a topic file holds: only the
    message's fields are read, so rclpy's and rosbags' messages alike).

    Points: ``transforms[0]`` (base frame) at ``time_from_start``; velocities
    (twist, base frame) where every point has one, accelerations where every
    point has velocities and one acceleration.

    Returns:
        (times (N,) [s], translations (N, 3) [m], quaternions (N, 4) x, y, z, w,
        twists (N, 6) or None, accelerations (N, 6) or None), for
        ``trajectory_poses``.

    Raises:
        MessageError: another joint, no point, a point without one transform,
            a number that is not finite, a quaternion far from unit length.
    """
    if list(msg.joint_names) != [PLATFORM_JOINT]:
        raise MessageError('unknown_joint_names', 'joint_names must be [%r], got %s'
                           % (PLATFORM_JOINT, list(msg.joint_names)))
    points = msg.points
    if not points:
        raise MessageError('empty_trajectory', 'the trajectory has no points')
    n = len(points)
    times = np.empty(n)
    translations = np.empty((n, 3))
    quats = np.empty((n, 4))
    twists = np.empty((n, 6)) if all(len(p.velocities) == 1 for p in points) else None
    accels = (np.empty((n, 6)) if twists is not None
              and all(len(p.accelerations) == 1 for p in points) else None)
    for k, p in enumerate(points):
        if len(p.transforms) != 1:
            raise MessageError('wrong_size', 'point %d has %d transforms, expected 1'
                               % (k, len(p.transforms)))
        tr = p.transforms[0]
        times[k] = p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec
        translations[k] = _finite([tr.translation.x, tr.translation.y, tr.translation.z], 3,
                                  'point %d translation' % k)
        quats[k] = message_quaternion(tr.rotation, 'point %d rotation' % k)
        for arr, items in ((twists, p.velocities), (accels, p.accelerations)):
            if arr is not None:
                lin, ang = items[0].linear, items[0].angular
                arr[k] = _finite([lin.x, lin.y, lin.z, ang.x, ang.y, ang.z], 6,
                                 'point %d twist' % k)
    return times, translations, quats, twists, accels


def trajectory_poses(translations: ArrayLike, quaternions: ArrayLike,
                     twists: ArrayLike | None = None, accelerations: ArrayLike | None = None
                     ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """The pose coordinates of a trajectory's points (a ``pose_trajectory``
    message's, a topic file's), for ``Reference.from_poses``.

    theta is continuous from point to point (unwrapped: no 2 pi jumps); with
    twists, dtheta/dt = E(theta)^-1 omega; with accelerations too,
    d2theta/dt2 = E^-1 (alpha - dE/dt dtheta/dt) (dE/dt by a forward difference).

    Args:
        translations: (N, 3) [m], base frame.
        quaternions: (N, 4) unit quaternions x, y, z, w.
        twists: (N, 6) linear [m/s] and angular [rad/s] velocities, base frame, or None.
        accelerations: (N, 6) their derivatives (with ``twists``), or None.

    Returns:
        (poses (N, 6), their rates (N, 6) or None, their second derivatives or None).
    """
    translations = np.asarray(translations, float).reshape(-1, 3)
    poses = np.empty((len(translations), 6))
    poses[:, :3] = translations
    poses[:, 3:] = np.unwrap(euler_from_quaternion(np.asarray(quaternions, float)), axis=0)
    if twists is None:
        return poses, None, None
    rates = np.array(twists, float)
    accs = None if accelerations is None else np.array(accelerations, float)
    for k in range(len(poses)):
        e = euler_rate_matrix(poses[k, 3:])
        rates[k, 3:] = np.linalg.solve(e, np.asarray(twists, float)[k, 3:])
        if accs is not None:
            h = 1e-7
            de = (euler_rate_matrix(poses[k, 3:] + h * rates[k, 3:]) - e) / h
            accs[k, 3:] = np.linalg.solve(e, np.asarray(accelerations, float)[k, 3:]
                                          - de @ rates[k, 3:])
    return poses, rates, accs


def write_reference_csv(path: str | os.PathLike, times: ArrayLike, poses: ArrayLike) -> None:
    """Write times (N,) [s] and poses (N, 6) [m, rad] as a reference CSV (full precision)."""
    with open(path, 'w', newline='') as stream:
        writer = csv.writer(stream)
        writer.writerow(CSV_COLUMNS)
        writer.writerows([[repr(float(t))] + [repr(float(v)) for v in p]
                          for t, p in zip(times, poses)])
