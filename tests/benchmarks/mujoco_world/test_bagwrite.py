"""The MuJoCo generator's bag writer: a written bag reads back with the contract's topics, frames and fields."""

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from benchmarks.mujoco_world.bagwrite import write_bag
from benchmarks.mujoco_world.observe import SENSOR_QUAT_XYZW, Streams


def _streams(n_fast=11):
    rng = np.random.default_rng(3)
    n_slow = (n_fast + 1) // 2
    return Streams(np.arange(n_fast, dtype=np.int64) * 5_000_000, np.arange(n_slow, dtype=np.int64) * 10_000_000,
                   rng.normal(size=(n_fast, 3)), rng.normal(size=(n_fast, 3)), rng.normal(size=(n_fast, 6)),
                   rng.normal(size=(n_slow, 63, 5)).astype(np.float32), rng.normal(size=(n_slow, 273, 3)))


def test_bag_round_trip(tmp_path):
    s = _streams()
    counts = write_bag(tmp_path / "bag", s, SENSOR_QUAT_XYZW)
    assert counts == {"/thinshell/ee/pose": 11, "/thinshell/ee/pose_cmd": 11, "/thinshell/tactile/wrench": 11,
                      "/clock": 11, "/thinshell/tactile/markers": 6, "/thinshell/sheet/points": 6}
    got: dict[str, list] = {}
    with AnyReader([tmp_path / "bag"]) as reader:
        for conn, t, raw in reader.messages():
            got.setdefault(conn.topic, []).append((t, reader.deserialize(raw, conn.msgtype)))
    t, w = got["/thinshell/tactile/wrench"][3]
    assert t == 15_000_000 and w.header.frame_id == "tactile"
    assert (w.header.stamp.sec, w.header.stamp.nanosec) == (0, 15_000_000)
    assert [w.wrench.force.x, w.wrench.force.y, w.wrench.torque.z] == pytest.approx(s.wrench[3, [0, 1, 5]])
    _, p = got["/thinshell/ee/pose"][2]
    assert p.header.frame_id == "world" and [p.pose.orientation.x, p.pose.orientation.w] == [1.0, 0.0]
    assert [p.pose.position.x, p.pose.position.z] == pytest.approx(s.pose[2, [0, 2]])
    t, m = got["/thinshell/tactile/markers"][4]
    assert t == 40_000_000 and m.header.frame_id == "tactile" and m.width == 63 and m.point_step == 20
    assert [f.name for f in m.fields] == ["x", "y", "z", "u", "v"]
    np.testing.assert_array_equal(np.frombuffer(bytes(m.data), dtype="<f4").reshape(63, 5), s.markers[4])
    _, sh = got["/thinshell/sheet/points"][1]
    assert sh.header.frame_id == "world" and sh.width == 273 and [f.name for f in sh.fields] == ["x", "y", "z"]
    with pytest.raises(FileExistsError, match="refusing to overwrite"):
        write_bag(tmp_path / "bag", s, SENSOR_QUAT_XYZW)
