"""The TF buffer of sysid.bagio.tf_buffer: pose algebra, per-edge interpolation, chains, wrench transport."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.errors import BagReadError
from sim_core.transforms import pose_to_matrix, quat_from_rotvec
from sysid.bagio.tf_buffer import TFBuffer, pose_compose, pose_inverse, quat_slerp, wrench_transform


def _pose(rotvec, t) -> np.ndarray:
    return np.concatenate([np.asarray(t, dtype=float), quat_from_rotvec(np.asarray(rotvec, dtype=float))])


def _same_pose(a, b, atol=1e-12):
    np.testing.assert_allclose(pose_to_matrix(a), pose_to_matrix(b), rtol=0, atol=atol)


def test_compose_and_inverse_match_homogeneous_matrices():
    a, b = _pose([0.3, -0.2, 0.9], [0.1, 0.2, -0.3]), _pose([-1.1, 0.4, 0.2], [0.05, -0.4, 0.7])
    np.testing.assert_allclose(pose_to_matrix(pose_compose(a, b)), pose_to_matrix(a) @ pose_to_matrix(b), atol=1e-14)
    np.testing.assert_allclose(pose_to_matrix(pose_inverse(a)), np.linalg.inv(pose_to_matrix(a)), atol=1e-14)


def test_slerp_turns_at_constant_rate_about_one_axis():
    axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    q0, q1 = quat_from_rotvec(0.2 * axis), quat_from_rotvec(1.4 * axis)
    w = np.array([0.0, 0.25, 0.5, 1.0])
    got = quat_slerp(np.tile(q0, (4, 1)), np.tile(-q1, (4, 1)), w)  # -q1: the shortest arc is still taken
    expected = np.stack([quat_from_rotvec((0.2 + 1.2 * x) * axis) for x in w])
    np.testing.assert_allclose(got * np.sign(got[:, 3:]), expected * np.sign(expected[:, 3:]), atol=1e-14)
    np.testing.assert_array_equal(got[0], q0)  # exactly the sample at w = 0


def test_lookup_interpolates_each_edge_and_composes_the_chain():
    mount = _pose([0.0, 0.5, 0.0], [0.0, 0.0, 0.06])
    tf = TFBuffer("bag")
    tf.add("link", "tool0", 0, mount, static=True)
    a0, a1 = _pose([0, 0, 0.1], [0.0, 0.0, 0.1]), _pose([0, 0, 0.7], [0.2, 0.0, 0.1])
    tf.add("base", "link", 1_000, a0, static=False)
    tf.add("base", "link", 3_000, a1, static=False)
    got = tf.lookup("base", "tool0", np.array([1_000, 2_000, 3_000]))
    mid = _pose([0, 0, 0.4], [0.1, 0.0, 0.1])  # half-way: lerp of position, slerp of the z rotation
    for pose_link, row in zip((a0, mid, a1), got):
        _same_pose(row, pose_compose(pose_link, mount))
    # the inverse direction and a path through the common ancestor
    tf.add("base", "camera", 0, _pose([0.3, 0, 0], [1.0, 0, 0]), static=True)
    back = tf.lookup("camera", "tool0", np.array([2_000]))[0]
    _same_pose(back, pose_compose(pose_inverse(_pose([0.3, 0, 0], [1.0, 0, 0])), pose_compose(mid, mount)))


def test_lookup_errors_name_the_frames():
    tf = TFBuffer("cell.bag")
    tf.add("base", "link", 0, _pose([0, 0, 0], [0, 0, 0]), static=False)
    tf.add("base", "link", 10, _pose([0, 0, 0], [0, 0, 0]), static=False)
    with pytest.raises(BagReadError, match=r"cell.bag: frame gel is not in /tf or /tf_static \(frames: base, link\)"):
        tf.lookup("base", "gel", np.array([0]))
    with pytest.raises(BagReadError, match=r"transform base -> link is needed at 11 ns, outside its samples \[0, 10\]"):
        tf.lookup("base", "link", np.array([11]))
    with pytest.raises(BagReadError, match="frame link has two parents in the TF tree"):
        tf.add("odom", "link", 0, _pose([0, 0, 0], [0, 0, 0]), static=True)
    tf.add("world", "table", 0, _pose([0, 0, 0], [0, 0, 0]), static=True)
    with pytest.raises(BagReadError, match="frames base and table are not connected"):
        tf.lookup("base", "table", np.array([0]))


def test_wrench_transport_keeps_the_moment_about_every_point():
    """A force F applied at point r: the transported wrench equals the one computed directly in frame a."""
    pose_ab = _pose([0.4, -0.7, 1.2], [0.02, -0.05, 0.11])
    rng = np.random.default_rng(3)
    r_b, f_b = rng.normal(size=3) * 0.05, rng.normal(size=3)
    wrench_b = np.concatenate([f_b, np.cross(r_b, f_b)])
    T = pose_to_matrix(pose_ab)
    r_a, f_a = T[:3, :3] @ r_b + T[:3, 3], T[:3, :3] @ f_b
    np.testing.assert_allclose(wrench_transform(pose_ab, wrench_b), np.concatenate([f_a, np.cross(r_a, f_a)]),
                               atol=1e-15)
