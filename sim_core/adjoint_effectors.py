"""The effector part of the adjoint (:mod:`sim_core.adjoint`): derivatives of the driven vertices with
respect to an effector's pose and finger opening, of the reached pose with respect to the command (and,
when rate limited, the previous pose), and one step's pullback through them."""

from __future__ import annotations

import numpy as np

from sim_core.control import Control
from sim_core.effector import limit_pose_step
from sim_core.model import Model
from sim_core.state import State
from sim_core.transforms import quat_to_matrix

LIMITED_POSE_FD_STEP = 1e-7
"""Central-difference step (m, and quaternion units) for the Jacobian of a rate-limited command."""


def rotation_derivative(q: np.ndarray) -> np.ndarray:
    """dR/dq of :func:`~sim_core.transforms.quat_to_matrix` (a quadratic form), shape ``(4, 3, 3)``.

    Exact: central differences of a quadratic polynomial carry no truncation error.
    """
    q = np.asarray(q, dtype=float)
    out = np.empty((4, 3, 3))
    for i in range(4):
        e = np.zeros(4)
        e[i] = 0.5
        out[i] = quat_to_matrix(q + e) - quat_to_matrix(q - e)
    return out


def driven_jacobian(eff, pose: np.ndarray, opening: float) -> tuple[np.ndarray, np.ndarray]:
    """Derivatives of :func:`~sim_core.effector.driven_positions`.

    Returns:
        ``(d x / d pose (k, 3, 7), d x / d opening (k, 3))`` for the ``k`` driven vertices.
    """
    local = np.array(eff.local_points, dtype=float)
    d_open = np.zeros_like(local)
    if eff.finger_sign is not None:
        local = local + np.outer(eff.finger_sign * 0.5 * (opening - eff.initial_opening), eff.finger_axis)
        d_open = np.outer(eff.finger_sign * 0.5, eff.finger_axis)
    R = quat_to_matrix(pose[3:7])
    dR = rotation_derivative(pose[3:7])
    J = np.zeros((local.shape[0], 3, 7))
    J[:, :, :3] = np.eye(3)
    J[:, :, 3:] = np.einsum("qij,kj->kiq", dR, local)
    return J, d_open @ R.T


def command_jacobian(eff, current: np.ndarray, target: np.ndarray, limited: bool) -> tuple[np.ndarray, np.ndarray]:
    """Jacobians of the reached pose w.r.t. the previous pose and the commanded target, ``(7, 7)`` each.

    Unlimited: pose = ``[t, q / |q|]`` (exact). Limited: central differences of
    :func:`~sim_core.effector.limit_pose_step` with step :data:`LIMITED_POSE_FD_STEP`.
    """
    target = np.asarray(target, dtype=float)
    if not limited:
        qn = np.linalg.norm(target[3:])
        qh = target[3:] / qn
        J = np.zeros((7, 7))
        J[:3, :3] = np.eye(3)
        J[3:, 3:] = (np.eye(4) - np.outer(qh, qh)) / qn
        return np.zeros((7, 7)), J
    h = LIMITED_POSE_FD_STEP
    lim = (eff.max_translation_per_step, eff.max_rotation_per_step)
    out = []
    for which in (0, 1):
        J = np.zeros((7, 7))
        for i in range(7):
            args_p = [np.array(current, dtype=float), target.copy()]
            args_m = [np.array(current, dtype=float), target.copy()]
            args_p[which][i] += h
            args_m[which][i] -= h
            J[:, i] = (limit_pose_step(*args_p, *lim)[0] - limit_pose_step(*args_m, *lim)[0]) / (2 * h)
        out.append(J)
    return out[0], out[1]



def effector_pullback(model: Model, rec, state: State, control: Control, a_fixed: np.ndarray,
                       apose: dict, aopen: dict, g_control: dict, g_gripper: dict) -> None:
    """One step's effectors: driven vertices -> reached pose -> command / previous pose. Updates the
    pose and opening adjoints ``apose``, ``aopen`` in place and fills the step's ``g_control``
    (effector -> dL/d target, shape ``(7,)``) and ``g_gripper`` (effector -> dL/d opening)."""
    for name, eff in model.effectors.items():
        pose = rec.effector_pose[name]
        opening = rec.gripper_opening[name]
        Jp, Jo = driven_jacobian(eff, pose, opening)
        a_v = a_fixed[eff.vertices]
        a_pose = apose[name] + np.einsum("kdq,kd->q", Jp, a_v)
        a_open = aopen[name] + float(np.sum(Jo * a_v))
        target = control.effector_pose_target.get(name)
        if target is None:
            g_control[name] = np.zeros(7)
            apose[name] = a_pose
        else:
            J_cur, J_tgt = command_jacobian(eff, state.effector_pose[name], target, name in rec.limited_effectors)
            g_control[name] = J_tgt.T @ a_pose
            apose[name] = J_cur.T @ a_pose
        if name in control.gripper_target:
            g_gripper[name] = a_open
            aopen[name] = 0.0
        else:
            g_gripper[name] = 0.0
            aopen[name] = a_open
