"""Kinematic effectors: the per-step translation/rotation limit and the two-finger gripper opening."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.effector import driven_positions, limit_pose_step
from sim_core.errors import ConfigError
from sim_core.model import Effector
from sim_core.transforms import quat_from_rotvec, quat_multiply, quat_to_rotvec

START = np.array([0.1, 0.0, 0.03, 0.0, 0.0, 0.0, 1.0])


def _with_quat(p, q):
    return np.concatenate([p, q])


def test_translation_is_limited_along_the_straight_line():
    target = START.copy()
    target[:3] += [0.003, 0.004, 0.0]  # 5 mm away
    pose, limited = limit_pose_step(START, target, 1e-3, 0.02)
    assert limited
    np.testing.assert_allclose(pose[:3] - START[:3], [0.0006, 0.0008, 0.0], atol=1e-15)
    pose, limited = limit_pose_step(START, _with_quat(START[:3] + [0.0, 0.0, -5e-4], START[3:]), 1e-3, 0.02)
    assert not limited and np.allclose(pose, _with_quat(START[:3] + [0.0, 0.0, -5e-4], START[3:]))


def test_rotation_is_limited_about_the_same_axis():
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    q_target = quat_from_rotvec(0.1 * axis)
    pose, limited = limit_pose_step(START, _with_quat(START[:3], q_target), 1e-3, 0.02)
    assert limited
    q_rel = quat_multiply(pose[3:], np.array([-START[3], -START[4], -START[5], START[6]]))
    np.testing.assert_allclose(quat_to_rotvec(q_rel), 0.02 * axis, atol=1e-12)
    assert np.linalg.norm(pose[3:]) == pytest.approx(1.0)
    # repeated steps reach the target in ceil(0.1 / 0.02) = 5 steps
    for _ in range(4):
        pose, limited = limit_pose_step(pose, _with_quat(START[:3], q_target), 1e-3, 0.02)
    assert not limited
    assert np.allclose(pose[3:], q_target) or np.allclose(pose[3:], -q_target)


def test_bad_targets_are_named():
    with pytest.raises(ConfigError, match="7 finite numbers"):
        limit_pose_step(START, START * np.nan, 1e-3, 0.02)


def test_gripper_opening_moves_the_fingers_along_the_rotated_axis():
    local = np.array([[-0.01, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.0, 0.02]])
    eff = Effector(name="ee", vertices=np.arange(3), local_points=local, initial_pose=START,
                   finger_sign=np.array([-1.0, 1.0, 0.0]), finger_axis=np.array([1.0, 0.0, 0.0]),
                   initial_opening=0.02)
    pose = _with_quat(np.array([0.1, 0.2, 0.3]), quat_from_rotvec([0.0, 0.0, np.pi / 2]))  # x -> y
    x = driven_positions(eff, pose, opening=0.03)  # 1 cm wider: each finger 5 mm out
    np.testing.assert_allclose(x[0], [0.1, 0.2 - 0.015, 0.3], atol=1e-12)
    np.testing.assert_allclose(x[1], [0.1, 0.2 + 0.015, 0.3], atol=1e-12)
    np.testing.assert_allclose(x[2], [0.1, 0.2, 0.32], atol=1e-12)  # the palm does not move
    np.testing.assert_allclose(np.linalg.norm(x[1] - x[0]), 0.03, atol=1e-12)
    # a single pad (no finger signs) ignores the opening
    pad = Effector(name="ee", vertices=np.arange(3), local_points=local, initial_pose=START)
    np.testing.assert_allclose(driven_positions(pad, pose, 0.05), driven_positions(pad, pose, 0.0))
