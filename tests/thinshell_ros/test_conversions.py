"""Round trips NumPy -> rclpy message -> (CDR ->) NumPy for every thinshell message type."""

from __future__ import annotations

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import Marker

from thinshell_ros import conversions as cv


def _cdr_round_trip(msg):
    return deserialize_message(serialize_message(msg), type(msg))


def test_stamp_round_trip_and_validation():
    for t_ns in (0, 1, 999_999_999, 1_000_000_000, 12_345_678_901_234):
        stamp = cv.stamp_from_ns(t_ns)
        assert 0 <= stamp.nanosec < 1_000_000_000
        assert cv.ns_from_stamp(stamp) == t_ns
    assert cv.clock_from_msg(_cdr_round_trip(cv.clock_msg(5_000_000))) == 5_000_000
    assert cv.seconds_to_ns(0.005) == 5_000_000
    with pytest.raises(ValueError, match="non-negative integer"):
        cv.stamp_from_ns(-1)
    with pytest.raises(ValueError, match="integer nanoseconds"):
        cv.stamp_from_ns(1.5)


def test_pose_twist_wrench_round_trip():
    rng = np.random.default_rng(0)
    q = rng.normal(size=4)
    pose = np.concatenate([rng.normal(size=3), q / np.linalg.norm(q)])
    t, back = cv.pose_from_msg(_cdr_round_trip(cv.pose_to_msg(pose, 42, "world")))
    assert t == 42 and np.array_equal(back, pose)
    twist = rng.normal(size=6)
    msg = cv.twist_to_msg(twist, 7)
    assert msg.header.frame_id == "world"
    assert np.array_equal(cv.twist_from_msg(_cdr_round_trip(msg))[1], twist)
    wrench = rng.normal(size=6)
    msg = _cdr_round_trip(cv.wrench_to_msg(wrench, 9, "tactile"))
    assert msg.header.frame_id == "tactile" and msg.wrench.force.z == wrench[2] and msg.wrench.torque.x == wrench[3]
    assert np.array_equal(cv.wrench_from_msg(msg)[1], wrench)
    with pytest.raises(ValueError, match="pose must have 7 entries"):
        cv.pose_to_msg(np.zeros(6), 0)


def test_marker_cloud_round_trip_float32_layout():
    rng = np.random.default_rng(1)
    xyz, uv = rng.normal(size=(63, 3)) * 0.01, rng.uniform(0, 320, size=(63, 2))
    msg = _cdr_round_trip(cv.markers_to_msg(xyz, uv, 1_000, "tactile"))
    assert [f.name for f in msg.fields] == ["x", "y", "z", "u", "v"]
    assert [f.offset for f in msg.fields] == [0, 4, 8, 12, 16]
    assert msg.point_step == 20 and msg.row_step == 20 * 63 and msg.width == 63 and msg.height == 1
    t, values = cv.cloud_from_msg(msg, ("x", "y", "z", "u", "v"))
    assert t == 1_000
    np.testing.assert_array_equal(values[:, :3], xyz.astype(np.float32).astype(float))
    np.testing.assert_array_equal(values[:, 3:], uv.astype(np.float32).astype(float))
    # a subset of fields, in another order, is read through the offsets
    _, vz = cv.cloud_from_msg(msg, ("v", "z"))
    np.testing.assert_array_equal(vz, values[:, [4, 2]])


def test_cloud_readable_by_rosbags_typestore():
    from rosbags.typesys import Stores, get_typestore

    pts = np.arange(12, dtype=float).reshape(4, 3) * 0.001
    raw = serialize_message(cv.points_to_msg(pts, 3_000_000_000))
    msg = get_typestore(Stores.ROS2_JAZZY).deserialize_cdr(raw, "sensor_msgs/msg/PointCloud2")
    assert msg.header.stamp.sec == 3 and msg.width == 4
    np.testing.assert_array_equal(np.frombuffer(msg.data.tobytes(), "<f4").reshape(4, 3), pts.astype(np.float32))


def test_cloud_errors_name_the_field():
    msg = cv.points_to_msg(np.zeros((2, 3)), 0)
    with pytest.raises(ValueError, match="no field 'u'"):
        cv.cloud_from_msg(msg, ("x", "u"))
    with pytest.raises(ValueError, match=r"shape \(k, 3\)"):
        cv.points_to_msg(np.zeros((2, 2)), 0)
    short = PointCloud2(fields=msg.fields, width=5, height=1, point_step=12, data=bytes(12))
    with pytest.raises(ValueError, match="expected 60"):
        cv.cloud_from_msg(short, ("x",))
    assert not cv.points_to_msg(np.array([[np.nan, 0, 0]]), 0).is_dense


def test_image_round_trip_and_padded_rows():
    img = np.random.default_rng(2).integers(0, 256, size=(24, 32), dtype=np.uint8)
    t, back = cv.image_from_msg(_cdr_round_trip(cv.image_to_msg(img, 5, "tactile")))
    assert t == 5 and np.array_equal(back, img)
    msg = cv.image_to_msg(img, 5, "tactile")
    padded = np.zeros((24, 40), np.uint8)
    padded[:, :32] = img
    msg.step, msg.data = 40, padded.tobytes()
    assert np.array_equal(cv.image_from_msg(msg)[1], img)
    with pytest.raises(ValueError, match="uint8"):
        cv.image_to_msg(img.astype(float), 0, "tactile")
    msg.encoding = "rgb8"
    with pytest.raises(ValueError, match="not mono8"):
        cv.image_from_msg(msg)


def test_mesh_marker_triangle_soup():
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.5]], dtype=float)
    tris = np.array([[0, 1, 2], [1, 3, 2]])
    msg = _cdr_round_trip(cv.mesh_to_marker(pts, tris, 11))
    assert msg.type == Marker.TRIANGLE_LIST and msg.header.frame_id == "world" and msg.pose.orientation.w == 1.0
    t, corners = cv.marker_to_triangles(msg)
    assert t == 11 and np.array_equal(corners, pts[tris])
    with pytest.raises(ValueError, match=r"indices must be in \[0, 4\)"):
        cv.mesh_to_marker(pts, np.array([[0, 1, 4]]), 0)
