"""ROS conventions of the nodes over real DDS (issue 50 item 6): the sim node's ``camera_info`` (the
bundled scene's tactile camera), ``~/step`` taking ``step_count`` steps and ``~/step_n`` (std_msgs/UInt32),
its 1 Hz runtime status on ``/diagnostics``; the sysid node's 1 Hz progress status."""

from __future__ import annotations

import threading

import numpy as np
import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rcl_interfaces.srv import SetParameters
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import UInt32
from std_srvs.srv import Trigger

from tests.thinshell_ros.conftest import spin_until
from thinshell_ros import conversions as cv
from thinshell_ros.paths import bundled_scene
from thinshell_ros.runtime import CAMERA_INFO_QOS, COMMAND_QOS, DIAGNOSTICS_TOPIC, SENSOR_QOS
from thinshell_ros.sim_node import SimNode
from thinshell_ros.sysid_node import FitRequest, SysidNode

pytestmark = pytest.mark.ros


def _values(status: DiagnosticStatus) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values}


def _call(ex, node: Node, srv_type, name: str, request):
    cli = node.create_client(srv_type, name)
    assert cli.wait_for_service(timeout_sec=5.0), name
    fut = cli.call_async(request)
    assert spin_until(ex, fut.done, 60.0), name
    return fut.result()


def test_sim_node_camera_info_stepping_by_n_and_runtime_status(ros_context):
    camera = yaml.safe_load(bundled_scene().read_text())["sensors"]["tactile"]["camera"]
    node = SimNode(context=ros_context, parameter_overrides=[
        Parameter("mode", value="stepped"), Parameter("backend", value="numpy"), Parameter("mesh_rate", value=0.0),
        Parameter("publish_image", value=True)])
    client = Node("conventions_client", context=ros_context)
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(node)
    ex.add_node(client)
    try:
        # a late subscriber gets the calibration published at start-up (transient local)
        infos: list[CameraInfo] = []
        images: list[Image] = []
        statuses: list[DiagnosticStatus] = []
        client.create_subscription(CameraInfo, "/thinshell/tactile/camera_info", infos.append,
                                   CAMERA_INFO_QOS)  # a late joiner asks for the kept samples
        client.create_subscription(Image, "/thinshell/tactile/image", images.append, SENSOR_QOS)
        client.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC,
                                   lambda m: statuses.extend(s for s in m.status if s.name == "thinshell_sim: status"),
                                   10)
        assert spin_until(ex, lambda: bool(infos), 10.0)
        info = infos[0]
        assert (info.width, info.height, info.header.frame_id) == (camera["width"], camera["height"], "tactile")
        K = [[camera["fx"], 0, camera["cx"]], [0, camera["fy"], camera["cy"]], [0, 0, 1]]
        assert np.allclose(np.reshape(info.k, (3, 3)), K)
        assert info.distortion_model == "plumb_bob" and np.allclose(info.d, [camera.get("k1", 0.0),
                                                                             camera.get("k2", 0.0), 0, 0, 0])
        # what a recording of it gives the bag reader (sysid.bagio, a recorded camera_info) is the scene's camera
        from rclpy.serialization import serialize_message

        from sysid.bagio.codec import deserialize
        from sysid.bagio.images import parse_camera_info
        read = parse_camera_info(deserialize(serialize_message(info), "sensor_msgs/msg/CameraInfo"))
        assert {k: read[k] for k in ("fx", "fy", "cx", "cy", "width", "height")} == \
            {k: camera[k] for k in ("fx", "fy", "cx", "cy", "width", "height")}
        assert (read.get("k1", 0.0), read.get("k2", 0.0)) == (camera.get("k1", 0.0), camera.get("k2", 0.0))
        # the calibration projects as the simulator's camera does (the camera centre at z = -distance of the
        # sensor frame): points of the gel, 0-2 mm deep, seen through P
        points = np.array([[0.0, 0.0, 0.0], [1e-3, -2e-3, 0.0], [-4e-3, 3e-3, -2e-3]])
        uvw = (np.reshape(info.p, (3, 4)) @ np.c_[points + [0.0, 0.0, camera["distance"]], np.ones(3)].T).T
        assert np.allclose(uvw[:, :2] / uvw[:, 2:], node.sim.model.sensors["tactile"].camera.project(points),
                           rtol=0, atol=1e-9)

        # ~/step takes step_count steps; a bad count is refused
        dt = node.dt
        t0 = node.sim.t
        set_params = lambda *ps: _call(ex, client, SetParameters, "/thinshell_sim/set_parameters",  # noqa: E731
                                       SetParameters.Request(parameters=[p.to_parameter_msg() for p in ps]))
        assert set_params(Parameter("step_count", value=3)).results[0].successful
        bad = set_params(Parameter("step_count", value=0)).results[0]
        assert not bad.successful and "1..100000" in bad.reason and node.step_count == 3
        res = _call(ex, client, Trigger, "/thinshell_sim/step", Trigger.Request())
        assert res.success and res.message.endswith(" s after 3 steps") and node.sim.t == pytest.approx(t0 + 3 * dt)
        # every image comes with its calibration, same stamp
        assert spin_until(ex, lambda: len(images) >= 3 and len(infos) >= 4, 10.0), (len(images), len(infos))
        assert [i.header.stamp for i in infos[-3:]] == [i.header.stamp for i in images[-3:]]

        # ~/step_n (std_msgs/UInt32): N steps in one message
        step_n = client.create_publisher(UInt32, "/thinshell_sim/step_n", COMMAND_QOS)
        assert spin_until(ex, lambda: step_n.get_subscription_count() > 0, 5.0)
        step_n.publish(UInt32(data=4))
        assert spin_until(ex, lambda: node.sim.t >= t0 + 7 * dt - 1e-12, 60.0)
        ex.spin_once(timeout_sec=0.1)
        assert node.sim.t == pytest.approx(t0 + 7 * dt)

        # the 1 Hz status: the steps of its period, their p95, nothing rejected
        n = len(statuses)
        assert spin_until(ex, lambda: len(statuses) >= n + 2, 10.0)
        steps = sum(int(_values(s)["steps"]) for s in statuses)
        assert steps == 7, [_values(s) for s in statuses]
        busy = [_values(s) for s in statuses if int(_values(s)["steps"])]
        assert all(float(v["step_p95_ms"]) > 0 and float(v["step_max_ms"]) >= float(v["step_p95_ms"]) for v in busy)
        last = statuses[-1]
        assert last.level == DiagnosticStatus.OK and _values(last)["rejected_commands"] == "0"
        assert _values(last)["mode"] == "stepped" and _values(last)["paused"] == "true"
    finally:
        ex.shutdown(timeout_sec=0)
        client.destroy_node()
        node.destroy_node()


def test_sysid_node_progress_status(ros_context, tmp_path):
    release = threading.Event()

    def runner(job: FitRequest) -> dict:
        assert release.wait(20.0)
        raise RuntimeError("replay diverged")

    node = SysidNode(runner=runner, context=ros_context,
                     parameter_overrides=[Parameter("bag", value=str(tmp_path)), Parameter("max_time", value=100.0)])
    client = Node("progress_client", context=ros_context)
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(node)
    ex.add_node(client)
    got: list[DiagnosticStatus] = []
    client.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC,
                               lambda m: got.extend(s for s in m.status if s.name == "thinshell_sysid: progress"), 10)
    try:
        assert spin_until(ex, lambda: bool(got), 5.0)
        assert _values(got[-1])["state"] == "idle" and got[-1].message == "idle; no fit yet"
        assert _call(ex, client, Trigger, "/thinshell_sysid/fit", Trigger.Request()).success
        n = len(got)
        assert spin_until(ex, lambda: len(got) > n and _values(got[-1])["state"] == "fitting", 5.0)
        v = _values(got[-1])
        assert v["bag"] == str(tmp_path) and v["budget_s"] == "100" and 0 < float(v["budget_fraction"]) < 0.1
        release.set()
        assert spin_until(ex, lambda: _values(got[-1])["state"] == "idle" and _values(got[-1])["fits_done"] == "1",
                          10.0)
        assert got[-1].level == DiagnosticStatus.ERROR and _values(got[-1])["fits_failed"] == "1"
        assert "replay diverged" in _values(got[-1])["last"]
    finally:
        release.set()
        ex.shutdown(timeout_sec=0)
        client.destroy_node()
        node.destroy_node()
