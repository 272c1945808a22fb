"""Batched pose checks, CDR pose reading and the error throttle of the sim node's command intake."""

from __future__ import annotations

import numpy as np
import pytest
from rclpy.serialization import serialize_message

from thinshell_ros import conversions as cv
from thinshell_ros.command_intake import POSE_REJECTION_KINDS, ErrorThrottle, PoseBatch, pose_from_cdr, pose_rejections
from thinshell_ros.commands import Workspace, check_pose

WS = Workspace((-0.1, -0.1, -0.1), (0.1, 0.1, 0.1))
REASON_WORDS = {"non_finite": "non-finite", "frame": "frame_id", "quaternion": "quaternion norm",
                "workspace": "outside the workspace"}


def _mixed_batch(n: int, seed: int = 3) -> tuple[np.ndarray, list[str]]:
    """``n`` poses with every kind of fault, alone and combined (so the precedence matters)."""
    rng = np.random.default_rng(seed)
    poses = np.zeros((n, 7))
    poses[:, :3] = rng.uniform(-0.15, 0.15, (n, 3))  # about 30 % outside the box
    q = rng.normal(size=(n, 4))
    poses[:, 3:] = q / np.linalg.norm(q, axis=1, keepdims=True)
    poses[rng.random(n) < 0.2, 3:] *= 1.01  # norm off by 1e-2
    poses[rng.random(n) < 0.1, 3:] = 0.0
    poses[rng.random(n) < 0.1, rng.integers(0, 7)] = np.nan
    poses[rng.random(n) < 0.05, 2] = -np.inf
    frames = [("world", "", "base_link", "map")[k] for k in rng.choice(4, n, p=[0.6, 0.2, 0.1, 0.1])]
    return poses, frames


def test_batched_check_agrees_with_check_pose_one_by_one():
    poses, frames = _mixed_batch(2000)
    codes = pose_rejections(poses, frames, 1e-3, WS)
    for pose, frame, code in zip(poses, frames, codes):
        reason = check_pose(pose, frame, 1e-3, WS)
        kind = POSE_REJECTION_KINDS[code]
        assert (reason is None) == (kind == "valid"), (pose, frame, kind, reason)
        if reason is not None:
            assert REASON_WORDS[kind] in reason, (kind, reason)
    assert set(np.unique(codes)) == set(range(len(POSE_REJECTION_KINDS)))  # every kind occurred
    assert np.array_equal(pose_rejections(poses, frames, 1e-3, None) == 4, np.zeros(len(poses), bool))
    with pytest.raises(ValueError, match=r"\(n, 7\) with n frames"):
        pose_rejections(poses[:, :6], frames)


def test_cdr_pose_reading_matches_the_message_for_any_frame_length():
    for frame in ("", "w", "world", "tool0_flange_link", "x" * 61):
        pose = np.array([0.1, -0.2, 0.3, 0.0, 0.6, 0.0, 0.8])
        cdr = serialize_message(cv.pose_to_msg(pose, 123_456_789_012, frame or "world")) if frame else None
        if cdr is None:
            msg = cv.pose_to_msg(pose, 0, "world")
            msg.header.frame_id = ""
            cdr = serialize_message(msg)
        got, got_frame = pose_from_cdr(cdr)
        assert got == tuple(pose) and got_frame == frame
    with pytest.raises(ValueError, match="too short"):
        pose_from_cdr(cdr[:-8])
    with pytest.raises(ValueError, match="not a plain CDR PoseStamped"):
        pose_from_cdr(b"\x00\x03\x00\x00" + cdr[4:])


def test_batch_takes_in_arrival_order_and_empties():
    batch = PoseBatch()
    for k in range(3):
        batch.add((k, 0, 0, 0, 0, 0, 1), "world", 0.5 * k)
    poses, frames = batch.take()
    assert poses[:, 0].tolist() == [0, 1, 2] and frames == ["world"] * 3 and batch.received == 1.0
    assert len(batch) == 0 and batch.take()[0].shape == (0, 7)


def test_throttle_logs_one_line_per_kind_per_period_counting_the_rest():
    now = [0.0]
    throttle = ErrorThrottle(1.0, lambda: now[0])
    out = []
    for k in range(1000):  # 1000 errors of kind a and 10 of kind b over 2.5 s
        now[0] = 2.5 * k / 1000
        out.append(throttle.report("a", f"a {k}"))
        if k % 100 == 0:
            out.append(throttle.report("b", f"b {k}", count=3))
        out.extend(throttle.flush())
    lines = [line for line in out if line]
    a_lines = [line for line in lines if line.startswith("a")]
    assert a_lines[0] == "a 0" and len(a_lines) == 3  # at 0, 1.0 and 2.0 s
    counted = sum(int(line.split("(")[1].split()[0]) if "(" in line else 1 for line in a_lines)
    now[0] = 10.0
    rest = throttle.flush()
    counted += sum(int(line.split("(")[1].split()[0]) for line in rest if line.startswith("a"))
    assert counted == 1000 == throttle.reported["a"]
    assert lines[1] == "b 0 (3 of this kind at once)" and throttle.reported["b"] == 30
    assert throttle.lines == len(lines) + len(rest)
    with pytest.raises(ValueError, match="period"):
        ErrorThrottle(0.0, lambda: 0.0)
