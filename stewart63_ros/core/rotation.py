"""Orientation conventions (docs/interface.md), in one place.

theta = (theta_x, theta_y, theta_z) with R = Rz(theta_z) Ry(theta_y) Rx(theta_x),
i.e. extrinsic x-y-z ("roll, pitch, yaw about fixed axes"): scipy's ``'xyz'``.
Quaternions are (x, y, z, w), scalar last, as in geometry_msgs and scipy.
Euler angles appear only at the edges (parameters, CSV, plots); the model
carries a unit quaternion, free of singularities.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

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


def matrix_from_quaternion(q: ArrayLike) -> np.ndarray:
    """R from a unit quaternion (x, y, z, w), not normalised here.

    Hand-written rather than scipy's Rotation because the dynamics call it on
    every right-hand-side evaluation, where Rotation's object overhead (~10 us)
    would dominate.

    Args:
        q: (4,) a unit quaternion (x, y, z, w).

    Returns:
        (3, 3) R.
    """
    x, y, z, w = q
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    return np.array([
        [1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)],
        [2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)],
        [2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)]])


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
