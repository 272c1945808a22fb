"""A "robot" for DDS tests that publishes no ``/clock``: the kinematic FakeSimulation stepped on wall time.

Like a real cell: it subscribes ``<ns>/ee/pose_cmd`` (rate-limited by the sim node's
:class:`~thinshell_ros.commands.CommandArbiter`), steps every ``dt`` of wall time (steady timer) and
publishes ``ee/pose``, ``tactile/wrench`` and ``sheet/points`` stamped with wall time.
"""

from __future__ import annotations

from geometry_msgs.msg import PoseStamped, WrenchStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2

from tests.thinshell_ros.fake_sim import FakeSimulation
from thinshell_ros import conversions as cv
from thinshell_ros.commands import CommandArbiter, CommandLimits
from thinshell_ros.runtime import COMMAND_QOS, SENSOR_QOS


class WallRobot(Node):
    """Kinematic robot on wall time, no ``/clock`` (module docstring)."""

    def __init__(self, context, namespace: str = "/thinshell", **sim_kwargs) -> None:
        super().__init__("wall_robot", namespace=namespace, context=context)
        self.sim = FakeSimulation(**sim_kwargs)
        self.arbiter = CommandArbiter({"ee": CommandLimits(timeout=0.0)})
        self.rejected: list[str] = []
        self.pub_pose = self.create_publisher(PoseStamped, "ee/pose", SENSOR_QOS)
        self.pub_wrench = self.create_publisher(WrenchStamped, "tactile/wrench", SENSOR_QOS)
        self.pub_points = self.create_publisher(PointCloud2, "sheet/points", SENSOR_QOS)
        self.create_subscription(PoseStamped, "ee/pose_cmd", self._on_cmd, COMMAND_QOS)
        self.create_timer(self.sim.dt, self._step, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def _on_cmd(self, msg: PoseStamped) -> None:
        res = self.arbiter.submit_pose("ee", cv.pose_from_msg(msg)[1], self.sim.t, msg.header.frame_id)
        if not res.accepted:
            self.rejected.append(res.reason)

    def _step(self) -> None:
        targets = self.arbiter.step_targets(self.sim.t, self.sim.dt, self.sim.state.effector_pose)
        control = self.sim.model.control()
        control.effector_pose_target.update(targets.effector_pose_target)
        self.sim.step(control)
        obs = self.sim.observe()
        stamp = self.get_clock().now().nanoseconds
        self.pub_pose.publish(cv.pose_to_msg(obs.effector_pose["ee"], stamp, "world"))
        self.pub_wrench.publish(cv.wrench_to_msg(obs.tactile["tactile"].wrench, stamp, "tactile"))
        self.pub_points.publish(cv.points_to_msg(obs.sheet_points, stamp, "world"))
