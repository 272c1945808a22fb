"""Kinematic effectors: rate-limited SE(3) targets and the driven vertex positions they imply.

ThinShellLab's action space is a per-step translation + rotation of at most 1 mm (2 mm); here a
target pose is approached at a configurable per-step limit (DESIGN.md "Boundaries").
"""

from __future__ import annotations

import numpy as np

from sim_core.errors import ConfigError
from sim_core.model import Effector
from sim_core.transforms import quat_from_rotvec, quat_multiply, quat_normalize, quat_to_matrix, quat_to_rotvec


def limit_pose_step(
    current: np.ndarray, target: np.ndarray, max_translation: float, max_rotation: float
) -> tuple[np.ndarray, bool]:
    """Move ``current`` toward ``target`` by at most the given translation and rotation.

    Args:
        current: pose ``[x y z qx qy qz qw]``.
        target: pose ``[x y z qx qy qz qw]``; must be finite with a unit quaternion.
        max_translation: m per step (> 0).
        max_rotation: rad per step (> 0).

    Returns:
        ``(pose, limited)``: the next pose and whether the limit was active.

    Raises:
        ConfigError: non-finite target or non-unit quaternion.
    """
    target = np.asarray(target, dtype=float)
    if target.shape != (7,) or not np.all(np.isfinite(target)):
        raise ConfigError(f"effector target pose must be 7 finite numbers, got {np.asarray(target).tolist()}")
    q_t = quat_normalize(target[3:], "effector target")
    p_c, q_c = np.asarray(current[:3], dtype=float), np.asarray(current[3:], dtype=float)
    dp = target[:3] - p_c
    dist = float(np.linalg.norm(dp))
    limited = False
    if dist > max_translation:
        dp *= max_translation / dist
        limited = True
    # relative rotation q_rel = q_t * q_c^-1 (world frame)
    q_c_inv = np.array([-q_c[0], -q_c[1], -q_c[2], q_c[3]])
    r = quat_to_rotvec(quat_multiply(q_t, q_c_inv))
    ang = float(np.linalg.norm(r))
    if ang > max_rotation:
        r *= max_rotation / ang
        limited = True
        q_new = quat_multiply(quat_from_rotvec(r), q_c)
    else:
        q_new = q_t
    q_new = q_new / np.linalg.norm(q_new)
    return np.concatenate([p_c + dp, q_new]), limited


def driven_positions(effector: Effector, pose: np.ndarray, opening: float) -> np.ndarray:
    """World positions of the effector's driven vertices.

    ``x_i = R (p_i + s_i (opening - opening_0)/2 a) + t`` with ``p_i`` the local points, ``s_i`` the
    finger sign, ``a`` the finger axis.

    Args:
        effector: the effector.
        pose: ``[x y z qx qy qz qw]``.
        opening: finger opening in m.

    Returns:
        shape ``(k, 3)``.
    """
    local = np.array(effector.local_points, dtype=float)
    if effector.finger_sign is not None:
        local = local + np.outer(effector.finger_sign * 0.5 * (opening - effector.initial_opening), effector.finger_axis)
    R = quat_to_matrix(np.asarray(pose[3:7], dtype=float))
    return local @ R.T + np.asarray(pose[:3], dtype=float)
