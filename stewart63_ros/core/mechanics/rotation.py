"""Orientation conventions (docs/interface.md), and every conversion, in one place.

theta = (theta_x, theta_y, theta_z) with R = Rz(theta_z) Ry(theta_y) Rx(theta_x),
i.e. extrinsic x-y-z ("roll, pitch, yaw about fixed axes"): scipy's ``'xyz'``.
Quaternions are (x, y, z, w), scalar last, as in geometry_msgs and scipy.
Euler angles appear only at the edges (parameters, CSV, plots); the model
carries a unit quaternion, free of singularities.

The conversions are scipy's ``Rotation``, except on the compiled hot paths,
where its object overhead (about 10 us a call) would dominate: there, and
only there, quaternion -> matrix is ``rotation_rows`` (the right-hand side of
the dynamics; ``matrix_from_quaternion`` is it as an array) and matrix ->
quaternion is ``quaternion_of_matrix`` (the fk node's pose at 1 kHz), each
written once. No other module converts (test/test_imports.py).
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from stewart63_ros.core.plumbing._jit import njit, njit_kernel

EULER_SEQ = 'xyz'  # lower case = extrinsic: R = Rz Ry Rx


def rotation_from_euler(theta: ArrayLike) -> np.ndarray:
    """R = Rz(theta_z) Ry(theta_y) Rx(theta_x).

    Args:
        theta: (3,) or (N, 3) angles [rad].

    Returns:
        (3, 3) or (N, 3, 3), platform to base.
    """
    return Rotation.from_euler(EULER_SEQ, np.asarray(theta, dtype=float)).as_matrix()


def quaternion_from_euler(theta: ArrayLike) -> np.ndarray:
    """The unit quaternion (x, y, z, w) of R = Rz Ry Rx.

    Args:
        theta: (3,) or (N, 3) angles [rad].

    Returns:
        (4,) or (N, 4).
    """
    return Rotation.from_euler(EULER_SEQ, np.asarray(theta, dtype=float)).as_quat()


def euler_from_quaternion(quat: ArrayLike) -> np.ndarray:
    """theta of a quaternion (normalised first).

    Args:
        quat: (4,) or (N, 4), (x, y, z, w).

    Returns:
        (3,) or (N, 3) angles [rad], each in scipy's range for ``'xyz'``.
    """
    return Rotation.from_quat(np.asarray(quat, dtype=float)).as_euler(EULER_SEQ)


def euler_from_matrix(rot: ArrayLike) -> np.ndarray:
    """theta of R.

    Args:
        rot: (3, 3) or (N, 3, 3) rotation matrices.

    Returns:
        (3,) or (N, 3) angles [rad].
    """
    return Rotation.from_matrix(np.asarray(rot, dtype=float)).as_euler(EULER_SEQ)


def rotation_from_quaternion(quat: ArrayLike) -> np.ndarray:
    """R from unit quaternions (x, y, z, w), normalised first (scipy).

    Args:
        quat: (4,) or (N, 4), any non-zero length.

    Returns:
        (3, 3) or (N, 3, 3), platform to base.
    """
    return Rotation.from_quat(np.asarray(quat, dtype=float)).as_matrix()


def quaternion_from_rotation(rot: ArrayLike) -> np.ndarray:
    """The unit quaternion (x, y, z, w) of R (scipy: its sign as scipy picks it).

    Args:
        rot: (3, 3) or (N, 3, 3) rotation matrices.

    Returns:
        (4,) or (N, 4).
    """
    return Rotation.from_matrix(np.asarray(rot, dtype=float)).as_quat()


def rotation_angle_between(rot_ref: ArrayLike, quat: ArrayLike) -> np.ndarray:
    """The angle of R_ref R^T: how far R (as a quaternion) is from R_ref.

    Args:
        rot_ref: (N, 3, 3) the reference rotations.
        quat: (N, 4) the actual orientations, quaternions (x, y, z, w).

    Returns:
        (N,) angles [rad], in [0, pi].
    """
    rel = Rotation.from_matrix(np.asarray(rot_ref, dtype=float)) * Rotation.from_quat(
        np.asarray(quat, dtype=float)).inv()
    return np.linalg.norm(rel.as_rotvec(), axis=-1)


def rotvec_from_rotation(rot: ArrayLike) -> np.ndarray:
    """The rotation vector (axis times angle) of R.

    Args:
        rot: (3, 3) or (N, 3, 3) rotation matrices.

    Returns:
        (3,) or (N, 3) [rad].
    """
    return Rotation.from_matrix(np.asarray(rot, dtype=float)).as_rotvec()


def quaternion_of_rotvec_times(rotvec: ArrayLike, rot: ArrayLike) -> np.ndarray:
    """The unit quaternion (x, y, z, w) of exp([phi]x) R: R turned further by phi.

    Args:
        rotvec: phi (3,) [rad], base frame; rot: R (3, 3).

    Returns:
        (4,).
    """
    return (Rotation.from_rotvec(np.asarray(rotvec, dtype=float))
            * Rotation.from_matrix(np.asarray(rot, dtype=float))).as_quat()


def rotvec_between(quat: ArrayLike, rot_ref: ArrayLike) -> np.ndarray:
    """The rotation vector phi = log(R R_ref^T): how far R (as a quaternion) is
    turned from R_ref, in the base frame.

    Args:
        quat: (4,) or (N, 4) quaternions (x, y, z, w) of R.
        rot_ref: (3, 3) R_ref.

    Returns:
        (3,) or (N, 3) [rad].
    """
    return (Rotation.from_quat(np.asarray(quat, dtype=float))
            * Rotation.from_matrix(np.asarray(rot_ref, dtype=float)).inv()).as_rotvec()


@njit
def matrix_from_quaternion(q: np.ndarray) -> np.ndarray:
    """R from a unit quaternion (x, y, z, w), not normalised here: ``rotation_rows``
    as an array, compiled (about 30 times cheaper a call than scipy's Rotation).

    Args:
        q: (4,) float array, a unit quaternion (x, y, z, w).

    Returns:
        (3, 3) R.
    """
    rows = rotation_rows(q[0], q[1], q[2], q[3])
    rot = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            rot[i, j] = rows[i][j]
    return rot


@njit_kernel
def rotation_rows(x: float, y: float, z: float, w: float) -> tuple:
    """R of the unit quaternion (x, y, z, w), as a tuple of its three rows
    (tuples of floats): the compiled right-hand side's conversion, where
    scipy's Rotation (about 10 us a call) cannot go.

    Args:
        x, y, z, w: the unit quaternion (not normalised here).

    Returns:
        ((R00, R01, R02), (R10, R11, R12), (R20, R21, R22)).
    """
    return ((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
            (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
            (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)))



@njit
def quaternion_of_matrix(rot: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w), w >= 0, of a rotation matrix.

    Shepperd's method (J. Guidance and Control 1(3), 1978): take the square
    root of the largest of 1 + trace, 1 + 2 R_ii - trace, so it never divides
    by a small number. scipy's Rotation does the same but costs ~100x more
    per call, which matters at 1 kHz (the fk node's pose).

    Args:
        rot: (3, 3) a rotation matrix.

    Returns:
        (4,) the unit quaternion (x, y, z, w), w >= 0.
    """
    tr = rot[0, 0] + rot[1, 1] + rot[2, 2]
    q = np.empty(4)
    if tr >= rot[0, 0] and tr >= rot[1, 1] and tr >= rot[2, 2]:
        s = 2.0 * np.sqrt(1.0 + tr)
        q[3], q[0] = 0.25 * s, (rot[2, 1] - rot[1, 2]) / s
        q[1], q[2] = (rot[0, 2] - rot[2, 0]) / s, (rot[1, 0] - rot[0, 1]) / s
    elif rot[0, 0] >= rot[1, 1] and rot[0, 0] >= rot[2, 2]:
        s = 2.0 * np.sqrt(1.0 + 2.0 * rot[0, 0] - tr)
        q[3], q[0] = (rot[2, 1] - rot[1, 2]) / s, 0.25 * s
        q[1], q[2] = (rot[0, 1] + rot[1, 0]) / s, (rot[0, 2] + rot[2, 0]) / s
    elif rot[1, 1] >= rot[2, 2]:
        s = 2.0 * np.sqrt(1.0 + 2.0 * rot[1, 1] - tr)
        q[3], q[0] = (rot[0, 2] - rot[2, 0]) / s, (rot[0, 1] + rot[1, 0]) / s
        q[1], q[2] = 0.25 * s, (rot[1, 2] + rot[2, 1]) / s
    else:
        s = 2.0 * np.sqrt(1.0 + 2.0 * rot[2, 2] - tr)
        q[3], q[0] = (rot[1, 0] - rot[0, 1]) / s, (rot[0, 2] + rot[2, 0]) / s
        q[1], q[2] = (rot[1, 2] + rot[2, 1]) / s, 0.25 * s
    if q[3] < 0.0:
        for i in range(4):
            q[i] = -q[i]
    return q


def quaternion_rate(q: ArrayLike, omega: ArrayLike) -> np.ndarray:
    """dq/dt for a base-frame angular velocity omega: q' = 1/2 [omega, 0] (x) q.

    Args:
        q: (4,) the quaternion (x, y, z, w); omega: (3,) [rad/s], base frame.

    Returns:
        (4,) dq/dt [1/s].
    """
    x, y, z, w = q
    ox, oy, oz = omega
    return 0.5 * np.array([
        ox * w + oy * z - oz * y,
        -ox * z + oy * w + oz * x,
        ox * y - oy * x + oz * w,
        -ox * x - oy * y - oz * z])


def euler_rate_matrix(theta: ArrayLike) -> np.ndarray:
    """E(theta) with omega = E(theta) dtheta/dt (base frame) for R = Rz Ry Rx.

    omega = dtz * z + Rz dty * y + Rz Ry dtx * x.

    Args:
        theta: (3,) angles [rad].

    Returns:
        (3, 3) E.
    """
    _, ty, tz = theta
    cy, sy, cz, sz = np.cos(ty), np.sin(ty), np.cos(tz), np.sin(tz)
    return np.array([[cy * cz, -sz, 0.0],
                     [cy * sz, cz, 0.0],
                     [-sy, 0.0, 1.0]])
