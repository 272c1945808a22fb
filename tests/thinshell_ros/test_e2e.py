"""End to end: the sim node in a subprocess with the real Simulation, a client over real DDS.

One node process per test (its start-up dominates the cost). The client presses the gel onto the
card of the bundled scene, checks the physics (|F_z| grows, markers move into the gel, /clock
advances), throws bad input at the node, and finally interrupts it while it records.
"""

from __future__ import annotations

import signal
import subprocess
import time

import numpy as np
import pytest
import yaml
from geometry_msgs.msg import PoseStamped, WrenchStamped
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import PointCloud2

from tests.thinshell_ros.conftest import PYTHON, REPO, spin_until
from tests.thinshell_ros.test_recorder import read_with_mcap, read_with_rosbags
from thinshell_ros import conversions as cv
from thinshell_ros.runtime import CLOCK_QOS, COMMAND_QOS, SENSOR_QOS

pytestmark = pytest.mark.ros
SCENE = REPO / "config" / "scenes" / "press_slide.yaml"
START_TIMEOUT = 60.0
PHYSICS_TIMEOUT = 90.0


@pytest.fixture
def client(ros_env):
    """(context, node, executor, received dict) on the test's domain."""
    import rclpy

    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(ros_env["ROS_DOMAIN_ID"]))
    node = Node("e2e_client", context=ctx)
    got = {"clock": [], "pose": [], "wrench": [], "markers": []}
    node.create_subscription(Clock, "/clock", lambda m: got["clock"].append(cv.clock_from_msg(m)), CLOCK_QOS)
    node.create_subscription(PoseStamped, "/thinshell/ee/pose", lambda m: got["pose"].append(cv.pose_from_msg(m)), SENSOR_QOS)
    node.create_subscription(WrenchStamped, "/thinshell/tactile/wrench",
                             lambda m: got["wrench"].append(cv.wrench_from_msg(m)), SENSOR_QOS)
    node.create_subscription(PointCloud2, "/thinshell/tactile/markers",
                             lambda m: got["markers"].append(cv.cloud_from_msg(m, cv.MARKER_FIELDS)), SENSOR_QOS)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    yield ctx, node, ex, got
    ex.shutdown(timeout_sec=0)
    ctx.try_shutdown()


def _start_node(ros_env, tmp_path, *params: str) -> subprocess.Popen:
    args = [PYTHON, "-m", "thinshell_ros.sim_node", "--ros-args"]
    for p in ("mode:=fast", "mesh_rate:=0.0", *params):
        args += ["-p", p]
    log = open(tmp_path / "node.log", "w")
    return subprocess.Popen(args, cwd=REPO, env=ros_env, stdout=log, stderr=subprocess.STDOUT)


def _stop(proc: subprocess.Popen, sig: int = signal.SIGINT) -> int:
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            return proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode


def _press_target(depth: float) -> np.ndarray:
    """Effector pose putting the gel surface ``depth`` below the card's top (sensor mount is identity)."""
    scene = yaml.safe_load(SCENE.read_text())
    top = scene["sheet"]["origin"][2] + 0.5 * scene["sheet"]["thickness"]
    pose = np.array(scene["effectors"]["ee"]["initial_pose"], dtype=float)
    pose[2] = top - depth
    return pose


def test_press_bad_input_and_sigint_recording(ros_env, tmp_path, client):
    ctx, node, ex, got = client
    bag = tmp_path / "bag"
    proc = _start_node(ros_env, tmp_path, f"record:={bag}")
    try:
        cmd = node.create_publisher(PoseStamped, "/thinshell/ee/pose_cmd", COMMAND_QOS)
        assert spin_until(ex, lambda: proc.poll() is not None or (bool(got["clock"]) and bool(got["wrench"])
                                                                  and bool(got["markers"])
                                                                  and cmd.get_subscription_count() > 0), START_TIMEOUT)
        assert proc.poll() is None, (tmp_path / "node.log").read_text()
        fz0 = got["wrench"][-1][1][2]
        z0 = got["markers"][-1][1][:, 2].copy()
        # no contact at the start: the node starts from the settled scene (settle_steps_max), whose gel
        # hangs 0.15-0.18 um lower under its weight than the scene file's rest shape (+z of the sensor frame,
        # away from the pad; a press moves markers along -z), within one step's Newton tolerance
        # (tol_velocity dt = 1e-4 m/s x 5 ms = 0.5 um); the press below moves them by more than 10 um
        assert abs(fz0) < 1e-9 and np.allclose(z0, 0.0, atol=5e-7) and np.all(z0 >= 0.0)

        # press 0.5 mm into the card: the normal force ON the gel points along -z of the sensor frame
        target = _press_target(5e-4)
        cmd.publish(cv.pose_to_msg(target, 0))
        pressed = spin_until(ex, lambda: got["pose"] and abs(got["pose"][-1][1][2] - target[2]) < 1e-6
                             and got["wrench"][-1][1][2] < -0.05, PHYSICS_TIMEOUT)
        assert pressed, (got["wrench"][-1:], got["pose"][-1:], (tmp_path / "node.log").read_text()[-3000:])
        assert spin_until(ex, lambda: got["markers"][-1][1][:, 2].min() < -1e-5, 10.0)
        assert proc.poll() is None
        clock_mid = got["clock"][-1]

        # bad input: NaN, garbage quaternion, a 10 m jump, a topic of an effector that does not exist
        bad = [np.r_[np.nan, target[1:]], np.r_[target[:3], 0.3, 0.1, 0.9, 0.9], np.r_[target[:3], 0, 0, 0, 0]]
        expected = ["non-finite", "quaternion norm", "quaternion norm"]
        for pose, text in zip(bad, expected):  # commands are keep-last 1: wait until the node logged each
            log_path = tmp_path / "node.log"
            seen = log_path.read_text().count(text)

            def logged(text=text, seen=seen, pose=pose):
                if log_path.read_text().count(text) > seen:
                    return True
                cmd.publish(cv.pose_to_msg(pose, 0))  # re-send: a newer command may have replaced it
                return False

            cmd.publish(cv.pose_to_msg(pose, 0))
            assert spin_until(ex, logged, PHYSICS_TIMEOUT), log_path.read_text()[-2000:]
        wrong = node.create_publisher(PoseStamped, "/thinshell/left/pose_cmd", COMMAND_QOS)
        wrong.publish(cv.pose_to_msg(target, 0))
        jump = target + np.r_[0, 0, 10.0, 0, 0, 0, 0]
        cmd.publish(cv.pose_to_msg(jump, 0))
        n_pose = len(got["pose"])
        assert spin_until(ex, lambda: len(got["pose"]) > n_pose + 5, PHYSICS_TIMEOUT)
        assert proc.poll() is None, (tmp_path / "node.log").read_text()[-3000:]
        assert got["clock"][-1] > clock_mid
        zs = [p[2] for _, p in got["pose"][n_pose:]]
        assert np.all(np.diff(zs) <= 1e-3 + 1e-9) and zs[-1] < target[2] + 0.1  # approached at the limit
        log = (tmp_path / "node.log").read_text()
        assert "non-finite" in log and "quaternion norm" in log and "per-step limit" in log
    finally:
        rc = _stop(proc, signal.SIGINT)
    log = (tmp_path / "node.log").read_text()
    assert rc == 0, log[-3000:]
    assert "recording closed" in log
    msgs = read_with_rosbags(bag)
    for topic in ("/thinshell/ee/pose_cmd", "/thinshell/ee/pose", "/thinshell/tactile/markers",
                  "/thinshell/tactile/wrench", "/thinshell/sheet/points", "/clock"):
        assert msgs.get(topic), topic
    fz = [m.wrench.force.z for _, _, m in msgs["/thinshell/tactile/wrench"]]
    assert min(fz) < -0.05
    assert len(read_with_mcap(bag)["/clock"]) == len(msgs["/clock"])
    assert (bag / "scene.yaml").is_file()


@pytest.mark.parametrize("executor", ["single", "events"])
def test_sigterm_and_params_file(ros_env, tmp_path, client, executor):
    """The node reads the bundled params file, runs in stepped mode, serves its parameters and exits
    cleanly on SIGTERM, in either executor."""
    ctx, node, ex, got = client
    params = REPO / "config" / "nodes" / "sim_node.yaml"
    args = [PYTHON, "-m", "thinshell_ros.sim_node", "--ros-args", "--params-file", str(params), "-p", "mode:=stepped",
            "-p", f"executor:={executor}"]
    proc = subprocess.Popen(args, cwd=REPO, env=ros_env, stdout=open(tmp_path / "node.log", "w"), stderr=subprocess.STDOUT)
    try:
        from std_srvs.srv import Trigger

        cli = node.create_client(Trigger, "/thinshell_sim/step")
        deadline = time.monotonic() + START_TIMEOUT
        while not cli.service_is_ready() and time.monotonic() < deadline and proc.poll() is None:
            ex.spin_once(timeout_sec=0.05)
        assert cli.service_is_ready(), (tmp_path / "node.log").read_text()
        fut = cli.call_async(Trigger.Request())
        assert spin_until(ex, fut.done, PHYSICS_TIMEOUT)
        assert fut.result().success and fut.result().message == "t=0.005000 s"
        assert spin_until(ex, lambda: got["clock"] and got["clock"][-1] == 5_000_000, 5.0)
        # the node's parameter services through its executor: a material value set and read back, a bad
        # one rejected with the old value kept
        from rclpy.parameter import Parameter
        from rclpy.parameter_client import AsyncParameterClient

        params_client = AsyncParameterClient(node, "/thinshell_sim")
        assert params_client.wait_for_services(timeout_sec=10.0)
        for value, accepted in ((2.5e9, True), (-1.0, False)):
            fut = params_client.set_parameters([Parameter("sheet.youngs_modulus", value=value)])
            assert spin_until(ex, fut.done, 10.0)
            assert fut.result().results[0].successful is accepted, fut.result()
        fut = params_client.get_parameters(["sheet.youngs_modulus"])
        assert spin_until(ex, fut.done, 10.0)
        assert fut.result().values[0].double_value == 2.5e9
    finally:
        rc = _stop(proc, signal.SIGTERM)
    assert rc == 0, (tmp_path / "node.log").read_text()
