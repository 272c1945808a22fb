"""Command validation, limiting, twist integration and staleness (thinshell_ros.commands)."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.transforms import quat_from_rotvec, quat_multiply, quat_to_rotvec
from thinshell_ros.commands import (
    CommandArbiter,
    CommandLimits,
    Workspace,
    check_gripper,
    check_pose,
    integrate_twist,
    split_command_topic,
    unknown_effector_topics,
)

HOME = np.array([0.06, 0.0, 0.004, 1.0, 0.0, 0.0, 0.0])
DT = 0.005


def _arbiter(**kw) -> CommandArbiter:
    return CommandArbiter({"ee": CommandLimits(**kw)})


def test_check_pose_reasons():
    assert check_pose(HOME) is None
    assert "non-finite" in check_pose(np.r_[np.nan, HOME[1:]])
    assert "non-finite" in check_pose(np.r_[HOME[:6], np.inf])
    assert "quaternion norm 2" in check_pose(np.r_[HOME[:3], 2.0, 0, 0, 0])
    assert "quaternion norm 0" in check_pose(np.r_[HOME[:3], 0, 0, 0, 0])
    assert "frame_id 'map'" in check_pose(HOME, "map")
    assert check_pose(HOME, "") is None
    assert "7 entries" in check_pose(HOME[:6])
    assert "outside [0, 0.1]" in check_gripper(0.2, 0.1)
    assert "not finite" in check_gripper(float("nan"), 0.1)


def test_workspace_rejects_far_poses_and_stops_twists_at_the_boundary():
    ws = Workspace((0.0, -0.05, -0.01), (0.1, 0.05, 0.05))
    assert check_pose(HOME, workspace=ws) is None
    reason = check_pose(HOME + np.r_[1e9, 0, 0, 0, 0, 0, 0], workspace=ws)
    assert "outside the workspace [0.0, -0.05, -0.01] .. [0.1, 0.05, 0.05] m" in reason
    arb = _arbiter(workspace=ws)
    arb.step_targets(0.0, DT, {"ee": HOME})
    res = arb.submit_pose("ee", HOME + np.r_[0, 0, -1.0, 0, 0, 0, 0], 0.0)
    assert not res.accepted and res.reason.startswith("ee/pose_cmd rejected: position") and "outside the workspace" in res.reason
    assert arb.submit_twist("ee", np.r_[0.0, 0.0, 1.0, 0, 0, 0], 0.0).accepted  # 5 mm per step, limited to 1 mm
    events = []
    for k in range(60):
        out = arb.step_targets(k * DT, DT, {"ee": HOME})
        events += out.events
    assert out.effector_pose_target["ee"][2] == pytest.approx(0.05)  # stopped at the top face
    assert sum("workspace boundary" in e for e in events) == 1
    with pytest.raises(ValueError, match="low < high"):
        Workspace((0, 0, 0), (1, 0, 1))
    with pytest.raises(ValueError, match="3 finite numbers"):
        Workspace((0, 0, np.nan), (1, 1, 1))


def test_rejected_command_keeps_previous_target():
    arb = _arbiter()
    assert arb.submit_pose("ee", HOME + np.r_[0, 0, -5e-4, 0, 0, 0, 0], now=0.0).accepted
    res = arb.submit_pose("ee", np.r_[np.nan, HOME[1:]], now=0.0)
    assert not res.accepted and res.reason.startswith("ee/pose_cmd rejected: pose has non-finite")
    res = arb.submit_pose("ee", np.r_[HOME[:3], 0.3, 0.3, 0.3, 0.3], now=0.0)
    assert not res.accepted and "quaternion norm 0.6" in res.reason
    out = arb.step_targets(0.0, DT, {"ee": HOME})
    np.testing.assert_allclose(out.effector_pose_target["ee"][2], HOME[2] - 5e-4)


def test_unknown_effector_is_reported_with_known_names():
    res = _arbiter().submit_pose("left", HOME, now=0.0)
    assert not res.accepted and res.reason == "unknown effector 'left' (known: ['ee'])"
    assert not _arbiter().submit_twist("left", np.zeros(6), now=0.0).accepted
    assert not _arbiter().submit_gripper("left", 0.01).accepted
    topics = ["/thinshell/ee/pose_cmd", "/thinshell/left/pose_cmd", "/thinshell/left/twist_cmd",
              "/thinshell/tactile/markers", "/other/x/pose_cmd", "/thinshell/a/b/pose_cmd"]
    assert unknown_effector_topics(topics, "/thinshell", ["ee"]) == [
        ("/thinshell/left/pose_cmd", "left"), ("/thinshell/left/twist_cmd", "left")]
    assert split_command_topic("/thinshell/ee/gripper_cmd", "/thinshell/") == ("ee", "gripper_cmd")


def test_far_target_is_approached_at_the_limit_and_reported_once():
    arb = _arbiter(max_translation_per_step=1e-3, max_rotation_per_step=0.02, timeout=0.0)
    target = HOME + np.r_[0.0105, 0, 0, 0, 0, 0, 0]
    assert arb.submit_pose("ee", target, now=0.0).accepted
    xs, events = [], []
    for k in range(12):
        out = arb.step_targets(k * DT, DT, {"ee": HOME})
        xs.append(out.effector_pose_target["ee"][0])
        events += out.events
    steps = np.diff(np.r_[HOME[0], xs])
    np.testing.assert_allclose(steps[:10], 1e-3, rtol=1e-12)
    np.testing.assert_allclose(xs[-1], target[0], rtol=0, atol=1e-15)
    assert len(events) == 1 and "exceeds the per-step limit" in events[0]
    # a new command re-arms the report
    arb.submit_pose("ee", HOME, now=0.1)
    assert any("per-step limit" in e for e in arb.step_targets(0.1, DT, {"ee": HOME}).events)


def test_rotation_is_limited_per_step():
    arb = _arbiter(max_rotation_per_step=0.02, timeout=0.0)
    q_goal = quat_multiply(quat_from_rotvec([0, 0, 0.1]), HOME[3:])
    arb.submit_pose("ee", np.r_[HOME[:3], q_goal], now=0.0)
    q1 = arb.step_targets(0.0, DT, {"ee": HOME}).effector_pose_target["ee"][3:]
    q_rel = quat_multiply(q1, HOME[3:] * np.r_[-1, -1, -1, 1])
    np.testing.assert_allclose(quat_to_rotvec(q_rel), [0, 0, 0.02], atol=1e-12)


def test_twist_integration_matches_constant_velocity_motion():
    w = np.array([0.0, 0.0, 2.0])
    pose = integrate_twist(HOME, np.r_[0.1, -0.2, 0.0, w], 0.01)
    np.testing.assert_allclose(pose[:3], HOME[:3] + [0.001, -0.002, 0.0])
    q_rel = quat_multiply(pose[3:], HOME[3:] * np.r_[-1, -1, -1, 1])
    np.testing.assert_allclose(quat_to_rotvec(q_rel), w * 0.01, atol=1e-12)
    # through the arbiter: 20 steps of 0.05 m/s along y, below the limit
    arb = _arbiter(timeout=1.0)
    arb.submit_twist("ee", [0, 0.05, 0, 0, 0, 0], now=0.0)
    for k in range(20):
        out = arb.step_targets(k * DT, DT, {"ee": HOME})
    np.testing.assert_allclose(out.effector_pose_target["ee"][1], 20 * DT * 0.05, rtol=1e-12)
    assert not out.events


def test_stale_command_holds_position():
    arb = _arbiter(max_translation_per_step=1e-4, timeout=0.02)
    arb.submit_pose("ee", HOME + np.r_[0, 0, 0.01, 0, 0, 0, 0], now=0.0)
    zs, events = [], []
    for k in range(10):
        out = arb.step_targets(k * DT, DT, {"ee": HOME})
        zs.append(out.effector_pose_target["ee"][2])
        events += out.events
    # moves while fresh (t <= 0.02 s: 5 steps), then holds where it is
    np.testing.assert_allclose(np.diff(np.r_[HOME[2], zs])[:5], 1e-4, rtol=1e-9)
    assert np.all(np.diff(zs)[5:] == 0.0)
    assert sum("stale" in e for e in events) == 1
    # a stale twist stops as well
    arb.submit_twist("ee", [0, 0, 0.01, 0, 0, 0], now=1.0)
    z_a = arb.step_targets(1.0, DT, {"ee": HOME}).effector_pose_target["ee"][2]
    z_b = arb.step_targets(1.5, DT, {"ee": HOME}).effector_pose_target["ee"][2]
    assert z_b == z_a


def test_reached_target_is_not_reported_stale_and_gripper_is_kept():
    arb = _arbiter(timeout=0.01)
    arb.submit_pose("ee", HOME, now=0.0)
    assert arb.submit_gripper("ee", 0.02).accepted
    events = []
    for k in range(10):
        out = arb.step_targets(k * DT, DT, {"ee": HOME})
        events += out.events
    assert events == [] and out.gripper_target == {"ee": 0.02}
    arb.reset()
    assert arb.step_targets(0.0, DT, {"ee": HOME}).gripper_target == {}


def test_limits_validate():
    with pytest.raises(ValueError, match="max_translation_per_step must be finite and > 0"):
        CommandLimits(max_translation_per_step=0.0)
    with pytest.raises(ValueError, match="needs at least one effector"):
        CommandArbiter({})
