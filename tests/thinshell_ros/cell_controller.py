"""A real cell's controller for DDS tests of the deploy node: the kinematic FakeSimulation behind the
interfaces of a robot arm, on wall time (no ``/clock``).

The cell's geometry is its own ground truth, written with explicit 4x4 matrices (not with
:class:`thinshell_ros.deploy_cell.CellFrames`, which the deploy node uses): the robot's base frame
``base_link`` holds thinshell's ``world`` at :data:`T_BASE_WORLD`; the gel (sensor frame = effector
frame of the fake, mount identity) sits on the tool link ``tool0`` at :data:`T_TOOL_SENSOR`.

Inputs, as the real controllers take them:
- ``/cartesian_motion_controller/target_frame`` (``PoseStamped`` of ``tool0`` in ``base_link``, the FZI
  ``cartesian_motion_controller``): the effector goes to ``T_world_ee = T_base_world^-1 T_base_tool T_tool_sensor``;
- ``/servo_node/delta_twist_cmds`` (``TwistStamped`` of ``tool0`` in ``base_link``, MoveIt Servo): the twist
  is held until the next one (integrated every step over the wall time since the previous step);
- ``<ns>/ee/pose_cmd`` (``PoseStamped`` in ``world``, thinshell's own interface).
A command in another frame is not executed and is kept in :attr:`wrong_frames`.

Outputs: ``<ns>/ee/pose`` (the tool link in ``base_link`` with ``pose_in_base``, else the effector in
``world``) and ``<ns>/tactile/wrench`` (sensor frame, plus ``wrench_offset``); either stream stops while
:attr:`publish_pose` / :attr:`publish_wrench` is False (a sensor that dies).
"""

from __future__ import annotations

import time

import numpy as np
from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from sim_core.transforms import matrix_to_pose, pose_to_matrix
from tests.thinshell_ros.fake_sim import FakeSimulation
from thinshell_ros import conversions as cv
from thinshell_ros.commands import CommandArbiter, CommandLimits
from thinshell_ros.runtime import COMMAND_QOS, SENSOR_QOS

S = np.sqrt(0.5)
# world in base_link: rotated +90 deg about z (world x = base y), origin at (0.4, -0.1, 0.2) m
T_BASE_WORLD = np.array([[0.0, -1.0, 0.0, 0.4], [1.0, 0.0, 0.0, -0.1], [0.0, 0.0, 1.0, 0.2], [0.0, 0.0, 0.0, 1.0]])
WORLD_IN_BASE = [0.4, -0.1, 0.2, 0.0, 0.0, S, S]
# the gel on the tool link: rotated +90 deg about y (sensor z = tool -x), 5 cm out along the tool's z, 1 cm along x
T_TOOL_SENSOR = np.array([[0.0, 0.0, 1.0, 0.01], [0.0, 1.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 0.05], [0.0, 0.0, 0.0, 1.0]])
SENSOR_IN_TOOL = [0.01, 0.0, 0.05, 0.0, S, 0.0, S]
FZI_TOPIC = "/cartesian_motion_controller/target_frame"
SERVO_TOPIC = "/servo_node/delta_twist_cmds"


def tool_in_base_truth(effector_in_world: np.ndarray) -> np.ndarray:
    """The cell's ``T_base_tool`` of an effector pose in world (mount identity)."""
    return T_BASE_WORLD @ pose_to_matrix(effector_in_world) @ np.linalg.inv(T_TOOL_SENSOR)


def effector_in_world_truth(tool_in_base: np.ndarray) -> np.ndarray:
    """The effector pose ``(7,)`` in world of a tool link pose ``(7,)`` in base_link."""
    return matrix_to_pose(np.linalg.inv(T_BASE_WORLD) @ pose_to_matrix(tool_in_base) @ T_TOOL_SENSOR)


class CellController(Node):
    """The cell (module docstring)."""

    def __init__(self, context, namespace: str = "/thinshell", pose_in_base: bool = False,
                 wrench_offset: np.ndarray | None = None, **sim_kwargs) -> None:
        super().__init__("cell_controller", namespace=namespace, context=context)
        self.sim = FakeSimulation(**sim_kwargs)
        self.arbiter = CommandArbiter({"ee": CommandLimits(timeout=0.0)})
        self.pose_in_base = pose_in_base
        self.wrench_offset = np.zeros(6) if wrench_offset is None else np.asarray(wrench_offset, float)
        self.publish_pose = self.publish_wrench = True
        self.received: dict[str, list[tuple[str, np.ndarray, int]]] = {"pose_target": [], "twist": [], "thinshell": []}
        """interface -> (frame_id, pose (7,) or twist (6,), header stamp ns) of every command received"""
        self.wrong_frames: list[str] = []
        self.trace: list[np.ndarray] = []  # effector pose in world after every step
        self._wall: float | None = None
        self.pub_pose = self.create_publisher(PoseStamped, "ee/pose", SENSOR_QOS)
        self.pub_wrench = self.create_publisher(WrenchStamped, "tactile/wrench", SENSOR_QOS)
        self.create_subscription(PoseStamped, FZI_TOPIC, self._on_target, COMMAND_QOS)
        self.create_subscription(TwistStamped, SERVO_TOPIC, self._on_twist, COMMAND_QOS)
        self.create_subscription(PoseStamped, "ee/pose_cmd", self._on_pose_cmd, COMMAND_QOS)
        self.create_timer(self.sim.dt, self._step, clock=Clock(clock_type=ClockType.STEADY_TIME))

    @property
    def pose(self) -> np.ndarray:
        """The effector's pose in world now ``(7,)``."""
        return self.sim.state.effector_pose["ee"].copy()

    def _on_target(self, msg: PoseStamped) -> None:
        pose = cv.pose_from_msg(msg)[1]
        self.received["pose_target"].append((msg.header.frame_id, pose, cv.ns_from_stamp(msg.header.stamp)))
        if msg.header.frame_id != "base_link":
            self.wrong_frames.append(msg.header.frame_id)
            return
        self.arbiter.submit_pose("ee", effector_in_world_truth(pose), self.sim.t)

    def _on_twist(self, msg: TwistStamped) -> None:
        twist = cv.twist_from_msg(msg)[1]
        self.received["twist"].append((msg.header.frame_id, twist, cv.ns_from_stamp(msg.header.stamp)))
        if msg.header.frame_id != "base_link":
            self.wrong_frames.append(msg.header.frame_id)
            return
        R_wb = np.linalg.inv(T_BASE_WORLD)[:3, :3]
        w = R_wb @ twist[3:]
        ee = self.pose
        p_tool = (np.linalg.inv(T_BASE_WORLD) @ tool_in_base_truth(ee))[:3, 3]
        v_ee = R_wb @ twist[:3] + np.cross(w, ee[:3] - p_tool)  # the effector origin's velocity
        self.arbiter.submit_twist("ee", np.concatenate([v_ee, w]), self.sim.t)

    def _on_pose_cmd(self, msg: PoseStamped) -> None:
        pose = cv.pose_from_msg(msg)[1]
        self.received["thinshell"].append((msg.header.frame_id, pose, cv.ns_from_stamp(msg.header.stamp)))
        res = self.arbiter.submit_pose("ee", pose, self.sim.t, msg.header.frame_id)
        if not res.accepted:
            self.wrong_frames.append(msg.header.frame_id)

    def _step(self) -> None:
        # a twist moves the arm in real time (as a servo does): integrated over the wall time since the last step
        wall = time.monotonic()
        elapsed = min(wall - self._wall, 0.05) if self._wall is not None else self.sim.dt
        self._wall = wall
        targets = self.arbiter.step_targets(self.sim.t, elapsed, self.sim.state.effector_pose)
        control = self.sim.model.control()
        control.effector_pose_target.update(targets.effector_pose_target)
        self.sim.step(control)
        obs = self.sim.observe()
        self.trace.append(obs.effector_pose["ee"].copy())
        stamp = self.get_clock().now().nanoseconds
        if self.publish_pose:
            if self.pose_in_base:
                self.pub_pose.publish(cv.pose_to_msg(matrix_to_pose(tool_in_base_truth(obs.effector_pose["ee"])), stamp,
                                                     "base_link"))
            else:
                self.pub_pose.publish(cv.pose_to_msg(obs.effector_pose["ee"], stamp, "world"))
        if self.publish_wrench:
            self.pub_wrench.publish(cv.wrench_to_msg(obs.tactile["tactile"].wrench + self.wrench_offset, stamp, "tactile"))
