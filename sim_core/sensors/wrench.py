"""Net contact wrench on the gel, as a 6-axis force/torque reading in the sensor frame.

INTERFACES.md: the force is the one exerted ON the gel by everything it touches; the torque is
taken about the sensor frame origin; both are expressed in the sensor frame. With ``R, t`` the
sensor pose in ``world``:

    F_s = R^T sum_i f_i,        tau_s = R^T sum_i (p_i - t) x f_i.

Pressing the gel onto an object gives ``F_z < 0`` (the object pushes back into the gel, against the
sensor's outward normal +z).
"""

from __future__ import annotations

import numpy as np

from sim_core.transforms import quat_normalize, quat_to_matrix


def net_wrench(forces_world: np.ndarray, points_world: np.ndarray, sensor_pose: np.ndarray) -> np.ndarray:
    """Net force and torque of point forces, in the sensor frame.

    Args:
        forces_world: forces exerted ON the gel vertices, shape ``(k, 3)``, N, world frame.
        points_world: points of application (the gel vertices' positions), shape ``(k, 3)``, m, world.
        sensor_pose: sensor frame in ``world``, ``[x y z qx qy qz qw]``.

    Returns:
        ``[Fx Fy Fz Tx Ty Tz]`` in the sensor frame, N and N*m, torque about the sensor origin.

    Raises:
        ValueError: shapes of forces and points differ.
        ConfigError: the pose's quaternion is not unit norm.
    """
    f = np.asarray(forces_world, dtype=float).reshape(-1, 3)
    p = np.asarray(points_world, dtype=float).reshape(-1, 3)
    if f.shape != p.shape:
        raise ValueError(f"net_wrench: forces {f.shape} and points {p.shape} must have the same shape")
    pose = np.asarray(sensor_pose, dtype=float).reshape(7)
    R = quat_to_matrix(quat_normalize(pose[3:7], where="net_wrench: sensor_pose"))
    force_world = f.sum(axis=0)
    torque_world = np.cross(p - pose[:3], f).sum(axis=0)
    return np.concatenate([R.T @ force_world, R.T @ torque_world])
