"""Rigid transforms: quaternions (x y z w, REP 103) and poses ``[x y z qx qy qz qw]``.

Pure functions on NumPy arrays; units metres and radians.
"""

from __future__ import annotations

import numpy as np

from sim_core.errors import ConfigError


def quat_normalize(q: np.ndarray, where: str = "quaternion", tol: float = 1e-3) -> np.ndarray:
    """Return ``q / |q|`` after checking it is finite and close to unit norm.

    Args:
        q: shape ``(4,)`` as ``x y z w``.
        where: name used in the error message (e.g. a topic or YAML key).
        tol: accepted deviation of ``|q|`` from 1.

    Raises:
        ConfigError: NaN/inf entries or ``| |q| - 1 | > tol``.
    """
    q = np.asarray(q, dtype=float).reshape(4)
    if not np.all(np.isfinite(q)):
        raise ConfigError(f"{where}: quaternion has non-finite entries {q.tolist()}")
    n = float(np.linalg.norm(q))
    if abs(n - 1.0) > tol:
        raise ConfigError(f"{where}: quaternion norm {n:.6g} is not 1 (x y z w = {q.tolist()})")
    return q / n


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of unit quaternion(s) ``q`` (x y z w), shape ``(..., 4)`` -> ``(..., 3, 3)``."""
    q = np.asarray(q, dtype=float)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - z * w)
    R[..., 0, 2] = 2 * (x * z + y * w)
    R[..., 1, 0] = 2 * (x * y + z * w)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - x * w)
    R[..., 2, 0] = 2 * (x * z - y * w)
    R[..., 2, 1] = 2 * (y * z + x * w)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x y z w, w >= 0) of a rotation matrix ``R`` of shape ``(3, 3)``."""
    R = np.asarray(R, dtype=float)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = np.array([(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s])
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = np.zeros(4)
        q[i] = 0.25 * s
        q[j] = (R[j, i] + R[i, j]) / s
        q[k] = (R[k, i] + R[i, k]) / s
        q[3] = (R[k, j] - R[j, k]) / s
    q /= np.linalg.norm(q)
    return q if q[3] >= 0 else -q


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b`` of quaternions (x y z w)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ]
    )


def quat_from_rotvec(r: np.ndarray) -> np.ndarray:
    """Quaternion (x y z w) of rotation vector ``r`` (axis * angle, rad), shape ``(3,)``."""
    r = np.asarray(r, dtype=float)
    angle = float(np.linalg.norm(r))
    if angle < 1e-12:
        return np.array([0.5 * r[0], 0.5 * r[1], 0.5 * r[2], 1.0]) / np.sqrt(1 + 0.25 * angle**2)
    axis = r / angle
    return np.concatenate([axis * np.sin(0.5 * angle), [np.cos(0.5 * angle)]])


def quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle, angle in [0, pi]) of unit quaternion ``q`` (x y z w)."""
    q = np.asarray(q, dtype=float)
    if q[3] < 0:
        q = -q
    s = float(np.linalg.norm(q[:3]))
    if s < 1e-12:
        return 2.0 * q[:3]
    angle = 2.0 * np.arctan2(s, q[3])
    return q[:3] / s * angle


def pose_to_matrix(pose: np.ndarray) -> np.ndarray:
    """4x4 homogeneous matrix of a pose ``[x y z qx qy qz qw]``."""
    pose = np.asarray(pose, dtype=float)
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(pose[3:7])
    T[:3, 3] = pose[:3]
    return T


def matrix_to_pose(T: np.ndarray) -> np.ndarray:
    """Pose ``[x y z qx qy qz qw]`` of a 4x4 homogeneous matrix."""
    return np.concatenate([T[:3, 3], matrix_to_quat(T[:3, :3])])


def compose_poses(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pose of ``a * b`` (frame b expressed in a's parent), both ``[x y z qx qy qz qw]``."""
    return matrix_to_pose(pose_to_matrix(a) @ pose_to_matrix(b))


def transform_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map points ``(k, 3)`` from a frame to its parent: ``R p + t``."""
    R = quat_to_matrix(np.asarray(pose)[3:7])
    return np.asarray(points) @ R.T + np.asarray(pose)[:3]


def inverse_transform_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map points ``(k, 3)`` from the parent frame into the frame of ``pose``: ``R^T (p - t)``."""
    R = quat_to_matrix(np.asarray(pose)[3:7])
    return (np.asarray(points) - np.asarray(pose)[:3]) @ R
