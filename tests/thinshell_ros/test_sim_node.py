"""SimNode plumbing over real DDS (in-process), with the kinematic FakeSimulation behind it."""

from __future__ import annotations

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped, WrenchStamped
from rcl_interfaces.srv import SetParameters
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Image, PointCloud2
from std_srvs.srv import SetBool, Trigger
from visualization_msgs.msg import Marker

from tests.thinshell_ros.conftest import spin_until
from tests.thinshell_ros.fake_sim import HOME, FakeSimulation
from tests.thinshell_ros.test_recorder import read_with_mcap, read_with_rosbags
from thinshell_ros import conversions as cv
from thinshell_ros.runtime import CLOCK_QOS, COMMAND_QOS, SENSOR_QOS
from thinshell_ros.sim_node import SimNode
from sim_core.errors import SimulationDivergedError

pytestmark = pytest.mark.ros


class Client:
    """Test-side node: command publishers, output subscribers, service clients."""

    def __init__(self, ctx, node: SimNode) -> None:
        self.node = node
        self.n = Node("client", context=ctx)
        self.pose_cmd = self.n.create_publisher(PoseStamped, "/thinshell/ee/pose_cmd", COMMAND_QOS)
        self.got = {"pose": [], "wrench": [], "markers": [], "clock": [], "image": [], "points": [], "mesh": []}
        self.n.create_subscription(PoseStamped, "/thinshell/ee/pose", lambda m: self.got["pose"].append(cv.pose_from_msg(m)), SENSOR_QOS)
        self.n.create_subscription(WrenchStamped, "/thinshell/tactile/wrench", lambda m: self.got["wrench"].append(cv.wrench_from_msg(m)), SENSOR_QOS)
        self.n.create_subscription(PointCloud2, "/thinshell/tactile/markers",
                                   lambda m: self.got["markers"].append(cv.cloud_from_msg(m, cv.MARKER_FIELDS)), SENSOR_QOS)
        self.n.create_subscription(Clock, "/clock", lambda m: self.got["clock"].append(cv.clock_from_msg(m)), CLOCK_QOS)
        self.n.create_subscription(Image, "/thinshell/tactile/image", lambda m: self.got["image"].append(m), SENSOR_QOS)
        self.n.create_subscription(PointCloud2, "/thinshell/sheet/points", lambda m: self.got["points"].append(m), SENSOR_QOS)
        self.n.create_subscription(Marker, "/thinshell/sheet/mesh", lambda m: self.got["mesh"].append(m), 10)
        self.ex = SingleThreadedExecutor(context=ctx)
        self.ex.add_node(node)
        self.ex.add_node(self.n)
        assert spin_until(self.ex, lambda: self.pose_cmd.get_subscription_count() > 0 and self.got["clock"], 10.0)

    def send_pose(self, pose) -> None:
        self.pose_cmd.publish(cv.pose_to_msg(np.asarray(pose, float), 0))

    def call(self, srv_type, name: str, request):
        cli = self.n.create_client(srv_type, name)
        assert cli.wait_for_service(timeout_sec=5.0), name
        fut = cli.call_async(request)
        assert spin_until(self.ex, fut.done, 5.0), name
        return fut.result()

    def spin(self, seconds: float) -> None:
        spin_until(self.ex, lambda: False, seconds)


def _node(ctx, sim=None, **params) -> SimNode:
    overrides = [Parameter(k, value=v) for k, v in {"mode": "fast", **params}.items()]
    return SimNode(sim=sim or FakeSimulation(), context=ctx, parameter_overrides=overrides)


def test_pressing_raises_normal_force_and_moves_markers(ros_context):
    node = _node(ros_context, publish_image=True)
    c = Client(ros_context, node)
    c.send_pose(HOME + np.r_[0, 0, -0.0045, 0, 0, 0, 0])  # 0.8 mm into the plane at z = 0.3 mm
    assert spin_until(c.ex, lambda: c.got["wrench"] and c.got["markers"] and c.got["pose"]
                      and c.got["wrench"][-1][1][2] < -0.79 and c.got["markers"][-1][1][0, 2] < -0.00079
                      and c.got["pose"][-1][1][2] < HOME[2] - 0.00449, 10.0)
    _, z = c.got["pose"][-1]
    assert z[2] == pytest.approx(HOME[2] - 0.0045)
    assert c.got["markers"][-1][1][:, 2] == pytest.approx(-0.0008) and c.got["markers"][0][1][:, 2] == pytest.approx(0.0)
    steps = np.diff([p[1][2] for p in c.got["pose"]])
    assert steps.min() >= -1e-3 - 1e-12  # approached at the per-step limit
    clock = c.got["clock"]
    assert clock == sorted(clock) and clock[-1] >= 5 * 5_000_000
    assert c.got["image"] and c.got["image"][-1].encoding == "mono8"
    assert spin_until(c.ex, lambda: c.got["mesh"], 5.0)  # 10 Hz of sim time
    assert c.got["points"] and c.got["mesh"][0].type == Marker.TRIANGLE_LIST
    stamps = {t for t, _ in c.got["pose"]}
    assert {t for t, _ in c.got["wrench"]} & stamps  # outputs stamped with sim time: multiples of dt
    assert all(t % 5_000_000 == 0 for t in stamps | set(clock))
    node.destroy_node()


def test_bad_input_is_rejected_and_node_keeps_publishing(ros_context):
    node = _node(ros_context)
    c = Client(ros_context, node)
    bad = [np.r_[np.nan, HOME[1:]], np.r_[HOME[:3], 0.5, 0.5, 0.5, 0.6], np.r_[HOME[:3], 0, 0, 0, 0]]
    for pose in bad:
        c.send_pose(pose)
        c.spin(0.1)
    msg = cv.pose_to_msg(HOME, 0, "map")
    c.pose_cmd.publish(msg)
    wrong = c.n.create_publisher(PoseStamped, "/thinshell/left_arm/pose_cmd", COMMAND_QOS)
    wrong.publish(cv.pose_to_msg(HOME, 0))
    assert spin_until(c.ex, lambda: node.rejected_commands == 4, 5.0), node.rejected_commands
    n_clock = len(c.got["clock"])
    c.spin(1.2)  # the graph check runs once a second
    assert "/thinshell/left_arm/pose_cmd" in node._warned_topics
    assert len(c.got["clock"]) > n_clock + 10
    assert np.array_equal(c.got["pose"][-1][1], HOME)
    # a huge jump is approached at the limit, never teleported
    c.send_pose(HOME + np.r_[0.05, 0, 0, 0, 0, 0, 0])
    c.spin(0.3)
    xs = [p[1][0] for p in c.got["pose"]]
    assert np.diff(xs).max() <= 1e-3 + 1e-12 and xs[-1] > HOME[0]
    node.destroy_node()


def test_pose_outside_the_workspace_is_rejected_like_nan(ros_context):
    # default workspace: effector start + sheet bounding box grown by 0.1 m
    node = _node(ros_context)
    assert node.workspace.low == pytest.approx((-0.1, -0.13, -0.0997)) and node.workspace.high == pytest.approx((0.2, 0.13, 0.104))
    c = Client(ros_context, node)
    c.send_pose(HOME + np.r_[1e9, 0, 0, 0, 0, 0, 0])
    assert spin_until(c.ex, lambda: node.rejected_commands == 1, 5.0)
    c.spin(0.2)
    assert np.array_equal(c.got["pose"][-1][1], HOME)  # the effector did not move towards it
    node.destroy_node()
    # a declared box
    node = _node(ros_context, workspace_min=[0.0, -0.01, 0.0], workspace_max=[0.07, 0.01, 0.01])
    logged = []
    node.get_logger().error = lambda msg, **kw: logged.append(msg)
    c = Client(ros_context, node)
    c.send_pose(HOME + np.r_[0.02, 0, 0, 0, 0, 0, 0])
    c.spin(0.1)
    c.send_pose(HOME + np.r_[0.005, 0, 0, 0, 0, 0, 0])
    assert spin_until(c.ex, lambda: c.got["pose"] and c.got["pose"][-1][1][0] == pytest.approx(0.065), 5.0)
    assert node.rejected_commands == 1
    assert "ee/pose_cmd rejected: position [0.08, 0.0, 0.004] m is outside the workspace [0.0, -0.01, 0.0] .. " \
           "[0.07, 0.01, 0.01] m" in logged[0]
    node.destroy_node()
    from sim_core.errors import ConfigError

    with pytest.raises(ConfigError, match="workspace_min.*low < high"):
        _node(ros_context, workspace_min=[0.0, 0.0, 0.0], workspace_max=[0.07, 0.0, 0.01])


def test_measurement_noise_is_white_with_the_declared_sigma(ros_context):
    node = _node(ros_context, noise_force=0.2, noise_markers=1e-5, noise_seed=3)
    c = Client(ros_context, node)
    assert spin_until(c.ex, lambda: len(c.got["wrench"]) > 300 and len(c.got["markers"]) > 5, 10.0)
    f = np.array([w for _, w in c.got["wrench"]])
    assert np.std(f[:, :3]) == pytest.approx(0.2, rel=0.1) and abs(np.mean(f[:, :3])) < 0.05  # no contact: F = 0
    assert np.all(f[:, 3:] == 0.0)  # noise_torque = 0
    xyz = np.array([m[1][:, :3] for m in c.got["markers"]])
    assert np.std(xyz[..., 2]) == pytest.approx(1e-5, rel=0.2)
    assert np.array_equal(c.got["pose"][-1][1], HOME)  # the pose stays exact
    node.destroy_node()
    from sim_core.errors import ConfigError

    with pytest.raises(ConfigError, match="noise parameters must be finite and >= 0"):
        _node(ros_context, noise_pixels=-1.0)


def test_topics_follow_the_ros_namespace_and_remapping(ros_context):
    node = SimNode(sim=FakeSimulation(), context=ros_context, cli_args=[
        "--ros-args", "-r", "__ns:=/robot", "-r", "tactile/wrench:=force_torque"],
        parameter_overrides=[Parameter("mode", value="fast")])
    assert node.namespace == "/robot"
    names = {n for n, _ in node.get_publisher_names_and_types_by_node("thinshell_sim", "/robot")}
    assert {"/robot/ee/pose", "/robot/force_torque", "/robot/sheet/points", "/clock"} <= names
    assert not any(n.startswith("/thinshell/") for n in names)
    c = Node("client_ns", context=ros_context)
    got = []
    c.create_subscription(WrenchStamped, "/robot/force_torque", lambda m: got.append(m), SENSOR_QOS)
    cmd = c.create_publisher(PoseStamped, "/robot/ee/pose_cmd", COMMAND_QOS)
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(node)
    ex.add_node(c)
    assert spin_until(ex, lambda: got and cmd.get_subscription_count() > 0, 5.0)
    cmd.publish(cv.pose_to_msg(HOME + np.r_[0.002, 0, 0, 0, 0, 0, 0], 0))
    assert spin_until(ex, lambda: abs(node.sim.state.effector_pose["ee"][0] - HOME[0] - 0.002) < 1e-12, 5.0)
    ex.shutdown(timeout_sec=0)
    c.destroy_node()
    node.destroy_node()


def test_failed_step_holds_and_keeps_publishing(ros_context):
    node = _node(ros_context, sim=FakeSimulation(fail_below=0.0035))
    c = Client(ros_context, node)
    c.send_pose(HOME + np.r_[0, 0, -0.002, 0, 0, 0, 0])
    assert spin_until(c.ex, lambda: node.failed_steps > 0, 5.0)
    n = len(c.got["clock"])
    c.spin(0.3)
    assert len(c.got["clock"]) > n
    assert c.got["pose"][-1][1][2] >= 0.0035  # the state before the failing step is kept
    node.destroy_node()


def test_services_pause_step_reset(ros_context):
    node = _node(ros_context, mode="stepped")
    c = Client(ros_context, node)
    c.spin(0.2)
    assert node.sim.t == 0.0
    for _ in range(3):
        assert c.call(Trigger, "/thinshell_sim/step", Trigger.Request()).success
    assert node.sim.t == pytest.approx(0.015)
    assert spin_until(c.ex, lambda: c.got["clock"][-1] == 15_000_000, 2.0)
    res = c.call(SetBool, "/thinshell_sim/pause", SetBool.Request(data=False))
    assert not res.success and "stepped mode" in res.message
    res = c.call(Trigger, "/thinshell_sim/reset", Trigger.Request())
    assert res.success and node.sim.t == 0.0
    node.destroy_node()
    node = _node(ros_context, sim=FakeSimulation())
    node2 = Client(ros_context, node)
    assert node2.call(SetBool, "/thinshell_sim/pause", SetBool.Request(data=True)).success
    node2.spin(0.05)
    t_paused = node.sim.t
    node2.spin(0.2)
    assert node.sim.t == t_paused
    assert node2.call(SetBool, "/thinshell_sim/pause", SetBool.Request(data=False)).message == "running"
    node2.spin(0.2)
    assert node.sim.t > t_paused
    node.destroy_node()


def test_material_parameters_validated_and_applied(ros_context):
    node = _node(ros_context, **{"sheet.youngs_modulus": 2.0e9})
    assert node.sim.get_parameter("sheet.youngs_modulus") == 2.0e9
    c = Client(ros_context, node)
    req = SetParameters.Request(parameters=[Parameter("sheet.youngs_modulus", value=4.0e9).to_parameter_msg()])
    assert c.call(SetParameters, "/thinshell_sim/set_parameters", req).results[0].successful
    assert node.sim.get_parameter("sheet.youngs_modulus") == 4.0e9
    req = SetParameters.Request(parameters=[Parameter("sheet.youngs_modulus", value=-1.0).to_parameter_msg()])
    res = c.call(SetParameters, "/thinshell_sim/set_parameters", req).results[0]
    assert not res.successful and "must be > 0" in res.reason
    req = SetParameters.Request(parameters=[Parameter("contact.stiffness", value="soft").to_parameter_msg()])
    res = c.call(SetParameters, "/thinshell_sim/set_parameters", req).results[0]
    assert not res.successful and "must be a number" in res.reason
    assert node.sim.get_parameter("sheet.youngs_modulus") == 4.0e9
    node.destroy_node()
    from sim_core.errors import ConfigError

    with pytest.raises(ConfigError, match="mode.*got 'turbo'"):
        _node(ros_context, mode="turbo")


def test_recording_holds_inputs_and_outputs(ros_context, tmp_path):
    bag = tmp_path / "rec"
    node = _node(ros_context, record=str(bag))
    c = Client(ros_context, node)
    c.send_pose(HOME + np.r_[0, 0, -0.004, 0, 0, 0, 0])
    assert spin_until(c.ex, lambda: node.sim.t > 0.05, 5.0)
    node.close()
    node.destroy_node()
    msgs = read_with_rosbags(bag)
    assert {"/thinshell/ee/pose_cmd", "/thinshell/ee/pose", "/thinshell/tactile/markers", "/thinshell/tactile/wrench",
            "/thinshell/sheet/points", "/thinshell/sheet/mesh", "/clock"} <= set(msgs)
    t_clock = [t for _, t, _ in msgs["/clock"]]
    assert t_clock == sorted(t_clock) and t_clock[1] - t_clock[0] == 5_000_000
    fz = [m.wrench.force.z for _, _, m in msgs["/thinshell/tactile/wrench"]]
    assert fz[0] == 0.0 and fz[-1] == pytest.approx(-0.3)  # 0.3 mm into the plane, k = 1000 N/m
    assert len(read_with_mcap(bag)["/thinshell/tactile/wrench"]) == len(fz)


class _StuckSimulation(FakeSimulation):
    """Every step fails once the first one has (a state the solver cannot leave)."""

    def __init__(self, **kw) -> None:
        super().__init__(**kw)
        self.stuck = False

    def step(self, control=None):
        if self.stuck:
            raise SimulationDivergedError(f"step at t = {self.t:.3f} s: still stuck")
        try:
            return super().step(control)
        except SimulationDivergedError:
            self.stuck = True
            raise

    def reset(self) -> None:
        super().reset()
        self.stuck = False


def test_repeated_failures_pause_the_node_until_reset(ros_context):
    from thinshell_ros.sim_node import MAX_CONSECUTIVE_FAILURES

    node = _node(ros_context, sim=_StuckSimulation(fail_below=0.0035))
    c = Client(ros_context, node)
    c.send_pose(HOME + np.r_[0, 0, -0.002, 0, 0, 0, 0])
    assert spin_until(c.ex, lambda: node.paused, 5.0)
    assert node.consecutive_failures == MAX_CONSECUTIVE_FAILURES
    failed = node.failed_steps
    c.spin(0.3)
    assert node.failed_steps == failed  # paused: no more retries of the hopeless step
    response = node._on_reset(Trigger.Request(), Trigger.Response())
    assert response.success and node.consecutive_failures == 0
    node.destroy_node()


def test_executor_parameter_makes_that_executor_or_is_rejected(ros_context):
    from sim_core.errors import ConfigError

    for name, kind in (("single", "SingleThreadedExecutor"), ("events", "EventsExecutor")):
        node = _node(ros_context, executor=name)
        executor = node.make_executor()
        assert type(executor).__name__ == kind
        executor.shutdown(timeout_sec=0)
        node.destroy_node()
    with pytest.raises(ConfigError, match="parameter 'executor' must be one of .*'threads'"):
        _node(ros_context, executor="threads")
