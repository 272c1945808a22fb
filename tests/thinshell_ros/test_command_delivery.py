"""Every command reaches a busy sim node (issue 27): the deploy node in sim time against a ``fast`` sim
node whose steps take longer than the deploy node's period, over real DDS, recorded into a real bag."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter

from sim_core.trajectory_file import Trajectory
from tests.thinshell_ros.conftest import spin_until
from tests.thinshell_ros.fake_sim import HOME, FakeSimulation
from tests.thinshell_ros.test_recorder import read_with_rosbags
from thinshell_ros import conversions as cv
from thinshell_ros.deploy_node import DeployNode
from thinshell_ros.runtime import COMMAND_QOS
from thinshell_ros.sim_node import SimNode

pytestmark = pytest.mark.ros
DT = 0.005  # s, FakeSimulation's step


class _SlowSimulation(FakeSimulation):
    """FakeSimulation whose step takes ``step_wall`` s of wall time (a solver busier than the commander)."""

    def __init__(self, step_wall: float) -> None:
        super().__init__()
        self.step_wall = step_wall

    def step(self, control=None):
        time.sleep(self.step_wall)
        return super().step(control)


def _spin_in_thread(ctx, node: Node, executor_name: str = "single"):
    """Spin ``node`` in its own executor on a thread (a robot that does not share the test's executor)."""
    executor = node.make_executor() if executor_name != "single" else SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.02)
    thread = threading.Thread(target=spin, daemon=True)
    thread.start()

    def close() -> None:
        stop.set()
        thread.join(timeout=5.0)
        executor.shutdown(timeout_sec=0)
    return close


@pytest.mark.parametrize("executor_name", ["single", "events"])
def test_every_deployed_command_is_recorded_by_a_busy_fast_sim_node(ros_context, tmp_path, executor_name):
    bag = tmp_path / "robot"
    robot = SimNode(sim=_SlowSimulation(step_wall=0.02), context=ros_context, parameter_overrides=[
        Parameter("mode", value="fast"), Parameter("mesh_rate", value=0.0), Parameter("executor", value=executor_name),
        Parameter("record", value=str(bag))])
    close_robot = _spin_in_thread(ros_context, robot, executor_name)
    n = 21  # 0.1 s at 200 Hz: a 0.2 mm line (2 mm/s)
    a = np.linspace(0.0, 1.0, n)[:, None]
    poses = np.tile(HOME, (n, 1))
    poses[:, 0] += a[:, 0] * 2e-4
    traj = Trajectory(t=np.linspace(0.0, 0.1, n), poses={"ee": poses}, scene_name="fake")
    deploy = DeployNode(trajectory=traj, context=ros_context, parameter_overrides=[
        Parameter("use_sim_time", value=True), Parameter("rate", value=1.0 / DT), Parameter("start_timeout", value=10.0)])
    probe = Node("probe", context=ros_context)  # what the deploy node published, as a second reader sees it
    sent: list[int] = []
    probe.create_subscription(PoseStamped, "/thinshell/ee/pose_cmd",
                              lambda m: sent.append(cv.ns_from_stamp(m.header.stamp)), COMMAND_QOS)
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(deploy)
    ex.add_node(probe)
    try:
        assert spin_until(ex, deploy.done.is_set, 20.0), deploy.status()
        assert deploy.state == "completed", deploy.reason
        t_end = deploy.schedule.end
        assert spin_until(ex, lambda: robot.sim.t > t_end + 3 * DT and len(sent) == deploy.published, 5.0)
    finally:
        close_robot()
        robot.close()
        ex.shutdown(timeout_sec=0)
        for n_ in (deploy, probe, robot):
            n_.destroy_node()
    # each robot step (20 ms wall) is four deploy periods: the deploy node sees (nearly) every sim tick
    grid = {cv.seconds_to_ns(deploy.schedule.t0 + k * DT) for k in range(n)}
    assert deploy.published == len(sent) >= n - 2 and set(sent) <= grid, (deploy.published, sent)
    cmds = read_with_rosbags(bag)["/thinshell/ee/pose_cmd"]
    stamps = [cv.ns_from_stamp(m.header.stamp) for _, _, m in cmds]
    assert stamps == sent  # the robot recorded every command, in order, none twice
    # taken before the step after the one it arrived in: recorded one step after its stamp, no lag building up
    # (a depth-1 queue loses every second command here; a deep queue without the take before each step: 2 steps)
    lag = np.array([t_rec - s for (_, t_rec, _), s in zip(cmds, stamps)]) * 1e-9
    assert lag.min() >= 0.0 and np.median(lag) <= DT + 1e-9 and lag.max() <= 3 * DT + 1e-9, lag


def test_a_step_takes_every_queued_command_and_the_newest_controls_it(ros_context, tmp_path):
    bag = tmp_path / "robot"
    robot = SimNode(sim=FakeSimulation(), context=ros_context, parameter_overrides=[
        Parameter("mode", value="stepped"), Parameter("mesh_rate", value=0.0), Parameter("record", value=str(bag))])
    client = Node("client", context=ros_context)
    pub = client.create_publisher(PoseStamped, "/thinshell/ee/pose_cmd", COMMAND_QOS)
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(client)  # the robot is not spun: its commands queue up on its subscription
    try:
        assert spin_until(ex, lambda: pub.get_subscription_count() > 0, 10.0)
        targets = [HOME + np.r_[1e-4 * (i + 1), 0, 0, 0, 0, 0, 0] for i in range(5)]
        for i, pose in enumerate(targets):
            pub.publish(cv.pose_to_msg(pose, (i + 1) * 1_000_000))
        time.sleep(0.3)  # delivered into the robot's reader, not taken yet
        assert robot.advance()
        assert robot.take_pending_commands() == 0  # all five were taken by the step
        np.testing.assert_allclose(robot.sim.state.effector_pose["ee"], targets[-1], atol=1e-12)
    finally:
        robot.close()
        ex.shutdown(timeout_sec=0)
        client.destroy_node()
        robot.destroy_node()
    cmds = read_with_rosbags(bag)["/thinshell/ee/pose_cmd"]
    assert [cv.ns_from_stamp(m.header.stamp) for _, _, m in cmds] == [(i + 1) * 1_000_000 for i in range(5)]
