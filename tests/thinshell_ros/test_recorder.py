"""Recording live DDS traffic into a bag readable by rosbags and mcap_ros2."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Float64, String

from tests.thinshell_ros.conftest import PYTHON, REPO, spin_until
from thinshell_ros import conversions as cv
from thinshell_ros.recorder import BagRecorder, RecorderNode, interface_type, message_class, msgtype_of
from thinshell_ros.runtime import COMMAND_QOS, SENSOR_QOS

pytestmark = pytest.mark.ros
SCENE = REPO / "config" / "scenes" / "press_slide.yaml"


def read_with_rosbags(bag: Path) -> dict[str, list]:
    from rosbags.highlevel import AnyReader

    out: dict[str, list] = {}
    with AnyReader([bag]) as reader:
        for conn, t_ns, raw in reader.messages():
            out.setdefault(conn.topic, []).append((conn.msgtype, t_ns, reader.deserialize(raw, conn.msgtype)))
    return out


def read_with_mcap(bag: Path) -> dict[str, list]:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    (mcap_file,) = bag.glob("*.mcap")
    out: dict[str, list] = {}
    with open(mcap_file, "rb") as fh:
        for _schema, channel, _message, decoded in make_reader(fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            out.setdefault(channel.topic, []).append(decoded)
    return out


def test_topic_classification_and_types():
    assert interface_type("/thinshell/ee/pose_cmd", "/thinshell") == "geometry_msgs/msg/PoseStamped"
    assert interface_type("/thinshell/tactile/markers", "/thinshell/") == "sensor_msgs/msg/PointCloud2"
    assert interface_type("/thinshell/sheet/mesh", "/thinshell") == "visualization_msgs/msg/Marker"
    assert interface_type("/clock", "/thinshell") == "rosgraph_msgs/msg/Clock"
    assert interface_type("/thinshell/ee/unknown", "/thinshell") is None
    assert interface_type("/other/ee/pose", "/thinshell") is None
    assert msgtype_of(PoseStamped()) == "geometry_msgs/msg/PoseStamped" and msgtype_of(Clock) == "rosgraph_msgs/msg/Clock"
    assert message_class("sensor_msgs/PointCloud2") is PointCloud2
    from sim_core.errors import ConfigError

    with pytest.raises(ConfigError, match="'nope_msgs/msg/X' is not available"):
        message_class("nope_msgs/msg/X")


def test_recorder_node_records_live_traffic(ros_context, tmp_path):
    bag = tmp_path / "live"
    recorder = BagRecorder(bag, scene=SCENE)
    rec = RecorderNode(recorder, namespace="/thinshell", context=ros_context, discovery_period=0.05)
    talker = Node("talker", context=ros_context)
    pub_cmd = talker.create_publisher(PoseStamped, "/thinshell/ee/pose_cmd", COMMAND_QOS)
    pub_mk = talker.create_publisher(PointCloud2, "/thinshell/tactile/markers", SENSOR_QOS)
    pub_grip = talker.create_publisher(Float64, "/thinshell/ee/gripper_cmd", COMMAND_QOS)
    pub_other = talker.create_publisher(String, "/thinshell/chatter", 10)
    pub_wrong = talker.create_publisher(String, "/thinshell/tactile/wrench", 10)  # wrong type: skipped
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(rec)
    ex.add_node(talker)
    wanted = {"/thinshell/ee/pose_cmd", "/thinshell/tactile/markers", "/thinshell/ee/gripper_cmd"}
    assert spin_until(ex, lambda: wanted <= set(rec.subscribed_topics), timeout=10.0), rec.subscribed_topics
    assert "/thinshell/chatter" not in rec.subscribed_topics
    xyz = np.arange(189, dtype=float).reshape(63, 3) * 1e-4
    uv = np.ones((63, 2)) * 7.0
    n = 5
    for k in range(n):
        pub_cmd.publish(cv.pose_to_msg([0.06, 0, 0.004 - 1e-4 * k, 1, 0, 0, 0], 1000 * k))
        pub_mk.publish(cv.markers_to_msg(xyz + k, uv, 1000 * k, "tactile"))
        pub_grip.publish(Float64(data=0.01 * k))
        pub_other.publish(String(data="x"))
        pub_wrong.publish(String(data="x"))
        spin_until(ex, lambda: False, timeout=0.05)
    assert spin_until(ex, lambda: all(recorder.message_counts.get(t, 0) == n for t in wanted), timeout=10.0), \
        recorder.message_counts
    recorder.close()
    ex.shutdown(timeout_sec=0)
    msgs = read_with_rosbags(bag)
    assert set(msgs) == wanted
    assert [m[2].pose.position.z for m in msgs["/thinshell/ee/pose_cmd"]] == pytest.approx([0.004 - 1e-4 * k for k in range(n)])
    last_cloud = msgs["/thinshell/tactile/markers"][-1][2]
    np.testing.assert_array_equal(np.frombuffer(last_cloud.data.tobytes(), "<f4").reshape(63, 5)[:, :3],
                                  (xyz + n - 1).astype(np.float32))
    t_log = [m[1] for m in msgs["/thinshell/ee/gripper_cmd"]]
    assert t_log == sorted(t_log) and t_log[0] > 1_000_000_000  # wall-clock receive times
    decoded = read_with_mcap(bag)
    assert [m.data for m in decoded["/thinshell/ee/gripper_cmd"]] == pytest.approx([0.01 * k for k in range(n)])
    assert (bag / "scene.yaml").read_text() == SCENE.read_text()


def test_record_cli_closes_bag_on_sigint(ros_env, tmp_path):
    """``thinshell record`` in a subprocess: SIGINT while messages flow leaves a complete bag."""
    import rclpy
    from rclpy.context import Context

    bag = tmp_path / "cli"
    proc = subprocess.Popen([PYTHON, "-m", "thinshell_ros.cli", "record", "--out", str(bag), "--scene", str(SCENE)],
                            cwd=REPO, env=ros_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(ros_env["ROS_DOMAIN_ID"]))
    try:
        talker = Node("talker", context=ctx)
        pub = talker.create_publisher(Clock, "/clock", 10)
        deadline = time.monotonic() + 20.0
        while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert pub.get_subscription_count() > 0, "recorder did not subscribe to /clock"
        for k in range(20):
            pub.publish(cv.clock_msg(k * 5_000_000))
            time.sleep(0.01)
        time.sleep(0.3)
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
        ctx.try_shutdown()
    assert proc.returncode == 0, out
    clocks = read_with_rosbags(bag)["/clock"]
    assert [cv.ns_from_stamp(m[2].clock) for m in clocks] == [k * 5_000_000 for k in range(20)]
    assert "closed: 20 messages" in out
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".")], "staging directory left behind"
