"""The deploy node: plays a trajectory on a robot (or the sim node) over DDS, with limits and an abort.

Reads a ``thinshell-trajectory`` file (``docs/trajectory_format.md``) or, for replay, a recording's
``pose_cmd`` stream (a bag directory or ``.mcap``), and publishes ``<effector>/pose_cmd``
(``geometry_msgs/PoseStamped``, frame ``world``, stamped with the command's scheduled time) and
``<effector>/gripper_cmd`` (``std_msgs/Float64``, m) at ``rate`` Hz of the robot's clock: the node's
ROS clock, i.e. wall time, or ``/clock`` when ``use_sim_time`` is set. The node's own loop runs on a
steady timer, so it never blocks on a ``/clock`` that does not come: with ``use_sim_time`` and no
clock after ``start_timeout`` s it aborts and says why.

Topic names are relative (``<effector>/pose_cmd``, ``<effector>/pose``, ``tactile/wrench``, ``~/status``)
and follow ROS namespacing and remapping (``--ros-args -r __ns:=/robot``); the default namespace is
``/thinshell``, where the sim node publishes.

Sequence: check the trajectory against the limits (:func:`thinshell_ros.deploy_plan.check_trajectory`;
a refusal names the waypoint and nothing is published) -> wait for the measured ``<effector>/pose``
and, with ``require_wrench`` (default), a measured wrench on every ``wrench_topics`` topic (a cell
that publishes no force cannot enforce ``wrench_limit``: the node aborts after ``start_timeout`` and
says so; ``require_wrench:=false`` deploys without force monitoring, logged as a warning) -> compare it with the first waypoint (``start_tolerance``, ``start_angle_tolerance``; with
``approach`` a slow approach at ``approach_speed`` is planned instead of refusing) -> publish the
commands on the clock grid -> ``completed``. During the motion every measured wrench whose force
exceeds ``wrench_limit`` and every measured pose farther than ``pose_lag_tolerance`` from all
commands of the last ``pose_lag_window`` s aborts at once (in the measurement's callback, so within
one control period of its arrival; no trajectory command follows an abort, ``on_abort`` does). ``~/abort``
(``std_srvs/Trigger``) aborts on request. ``dry_run`` checks and reports without publishing commands.

Status: ``~/status`` (``std_msgs/String``, JSON, reliable + transient local, 10 Hz and at every
change): ``state`` (``waiting`` | ``running`` | ``completed`` | ``aborted`` | ``refused``), ``progress``
(0..1), ``tick``/``ticks``, ``reason``, ``trajectory``, and at the end ``timing_error_p95_s``. The
same transitions go to the log.

Real controllers (``docs/deploy.md``): ``command_interface`` = ``thinshell`` (the above) | ``pose_target``
(``PoseStamped`` of ``tool_link`` in ``base_frame`` on ``command_topic``, default
``/cartesian_motion_controller/target_frame``, the FZI ``cartesian_motion_controller``'s target) | ``twist``
(``TwistStamped`` of ``tool_link`` in ``base_frame``, default ``/servo_node/delta_twist_cmds``, MoveIt
Servo): frames through :class:`thinshell_ros.deploy_cell.CellFrames` (``world_in_base``,
``sensor_in_tool``, the scene's mount or ``sensor_mount``). While running, a watchdog aborts when the
newest measured pose or (with ``require_wrench``) wrench is older than ``sensor_timeout`` s of the robot's
clock. An abort is followed by ``on_abort``: ``hold`` commands the measured pose at the abort (a zero twist)
for ``abort_hold_time`` s; ``retract`` lifts along minus the sensor normal at ``approach_speed`` by
``retract_distance`` (inside the workspace), then holds. ``tare_window`` > 0 tares every wrench stream
(mean over that window before the start, refused above ``tare_max_force``); wrenches are carried to the
sensor frame (``wrench_in_sensor``) and checked against ``wrench_limit`` (force norm),
``normal_force_limit``, ``shear_force_limit`` and ``torque_limit`` (0: off).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import threading
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64, String
from std_srvs.srv import Trigger

from sim_core.errors import ConfigError, ThinShellError
from sim_core.trajectory_file import Trajectory, read_trajectory
from thinshell_ros import conversions as cv
from thinshell_ros.commands import Workspace
from thinshell_ros.deploy_cell import (ABORT_ACTIONS, COMMAND_INTERFACES, IDENTITY, CellFrames, RetractPlan, Watchdog,
                                       WrenchGuard, WrenchTare, checked_pose, scene_mount, servo_twist, wrench_in_sensor)
from thinshell_ros.deploy_plan import (DeployLimits, DeploySchedule, SafetyMonitor, approach_trajectory,
                                       check_trajectory, start_pose_error, trajectory_from_bag)
from thinshell_ros.runtime import COMMAND_QOS, SENSOR_QOS, ros_session, spin_until_stopped

DEFAULT_NAMESPACE = "/thinshell"
STATES = ("waiting", "running", "completed", "aborted", "refused")
DIAGNOSTICS_TOPIC = "/diagnostics"
DIAGNOSTIC_LEVELS = {"waiting": DiagnosticStatus.OK, "running": DiagnosticStatus.OK, "completed": DiagnosticStatus.OK,
                     "aborted": DiagnosticStatus.ERROR, "refused": DiagnosticStatus.WARN}
DEFAULT_COMMAND_TOPICS = {"pose_target": "/cartesian_motion_controller/target_frame",
                          "twist": "/servo_node/delta_twist_cmds"}
"""Where the FZI cartesian_motion_controller takes its target (``<controller name>/target_frame``) and
MoveIt Servo its twists (``<servo node>/delta_twist_cmds``), for the default node names."""
STATUS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)

# name -> (default, description, low, high); ranges are enforced by rclpy (FloatingPointRange)
FLOAT_PARAMETERS: dict[str, tuple[float, str, float, float]] = {
    "rate": (100.0, "command rate, Hz of the robot's clock", 1.0, 1000.0),
    "time_scale": (1.0, "factor on the trajectory's times (2: twice as slow)", 0.1, 100.0),
    "max_linear_speed": (0.05, "maximum effector speed, m/s", 1e-6, 2.0),
    "max_angular_speed": (1.0, "maximum effector angular speed, rad/s", 1e-6, 10.0),
    "max_linear_acceleration": (1.0, "maximum effector acceleration, m/s^2", 1e-6, 50.0),
    "max_angular_acceleration": (20.0, "maximum effector angular acceleration, rad/s^2", 1e-6, 500.0),
    "wrench_limit": (20.0, "abort when a measured force norm exceeds this, N", 1e-6, 1000.0),
    "start_tolerance": (0.002, "maximum distance of the measured start pose from waypoint 0, m", 1e-6, 1.0),
    "start_angle_tolerance": (0.05, "maximum rotation of the measured start pose from waypoint 0, rad", 1e-6, 3.2),
    "pose_lag_tolerance": (0.005, "abort when the measured pose is farther than this from every recent command, m",
                           1e-6, 1.0),
    "pose_lag_window": (0.1, "s of recent commands the measured pose is compared with", 0.001, 10.0),
    "approach_speed": (0.005, "speed of the planned approach to the start pose, m/s", 1e-6, 1.0),
    "approach_angular_speed": (0.1, "angular speed of the planned approach, rad/s", 1e-6, 5.0),
    "start_timeout": (5.0, "s to wait for the measured pose (and /clock with use_sim_time)", 0.1, 600.0),
    "normal_force_limit": (0.0, "abort when |Fz| in the sensor frame exceeds this, N; 0 = off", 0.0, 1000.0),
    "shear_force_limit": (0.0, "abort when |(Fx, Fy)| in the sensor frame exceeds this, N; 0 = off", 0.0, 1000.0),
    "torque_limit": (0.0, "abort when the torque norm about the sensor origin exceeds this, N*m; 0 = off", 0.0, 100.0),
    "sensor_timeout": (0.2, "abort when the newest measured pose or wrench is older than this, s of the robot's clock",
                       0.001, 60.0),
    "tare_window": (0.0, "s of wrench averaged before the start and subtracted (out of contact); 0 = no tare",
                    0.0, 60.0),
    "tare_max_force": (5.0, "refuse a tare whose mean force exceeds this, N (in contact, or a sensor offset)",
                       1e-6, 1000.0),
    "retract_distance": (0.01, "on_abort retract: lift by this along minus the sensor normal, m", 0.0, 1.0),
    "abort_hold_time": (0.5, "s the abort's last command is repeated before the node exits", 0.0, 60.0),
    "twist_gain": (5.0, "command_interface twist: proportional gain on the pose error, 1/s", 0.0, 1000.0),
    "settle_tolerance": (0.0002, "command_interface twist: after the last waypoint, feedback twists until the "
                                 "measured position is this close to it, m", 1e-7, 0.1),
    "settle_angle_tolerance": (0.005, "command_interface twist: the same for the orientation, rad", 1e-6, 1.0),
}
STRING_PARAMETERS: dict[str, tuple[str, str]] = {
    "command_interface": ("thinshell", "thinshell (<effector>/pose_cmd in world_frame) | pose_target (PoseStamped "
                                       "of tool_link in base_frame) | twist (TwistStamped of tool_link in base_frame)"),
    "command_topic": ("", "topic of the commands; empty: <effector>/pose_cmd, "
                          + ", ".join(f"{k}: {v}" for k, v in DEFAULT_COMMAND_TOPICS.items())),
    "on_abort": ("hold", "hold (command the measured pose / a zero twist) | retract (lift along the sensor normal)"),
    "world_frame": ("world", "frame_id of thinshell's world on the cell (thinshell commands, measured effector poses)"),
    "base_frame": ("base_link", "the robot's base frame (FZI robot_base_link, MoveIt Servo planning frame)"),
    "tool_link": ("tool0", "the link the controller moves (FZI end_effector_link, MoveIt Servo ee_frame)"),
    "wrench_frame": ("", "expected frame_id of every measured wrench; empty: not checked"),
}
POSE_PARAMETERS: dict[str, str] = {
    "world_in_base": "[x, y, z, qx, qy, qz, qw] pose of world in base_frame (m, unit quaternion)",
    "sensor_in_tool": "[x, y, z, qx, qy, qz, qw] pose of the tactile sensor frame in tool_link",
    "wrench_in_sensor": "[x, y, z, qx, qy, qz, qw] pose of the measured wrench's frame in the sensor frame",
    "sensor_mount": "[x, y, z, qx, qy, qz, qw] the sensor frame in the effector frame; empty: the scene's mount",
}


def _descriptor(description: str, low: float | None = None, high: float | None = None,
                read_only: bool = True) -> ParameterDescriptor:
    desc = ParameterDescriptor(description=description, read_only=read_only)
    if low is not None:
        desc.floating_point_range = [FloatingPointRange(from_value=float(low), to_value=float(high), step=0.0)]
    return desc


def load_deploy_source(path: str | Path, recording_map: str | Path | None = None) -> Trajectory:
    """A trajectory file, or a bag's ``pose_cmd`` stream when ``path`` is a bag directory / ``.mcap``
    (a real cell's bag read through ``recording_map``, docs/recording_map.md).

    Raises:
        ConfigError: missing or invalid file (named). BagReadError: unreadable bag.
    """
    path = Path(path)
    if path.is_dir() or path.suffix == ".mcap":
        return trajectory_from_bag(path, recording_map)
    return read_trajectory(path)


class DeployNode(Node):
    """ROS 2 node publishing a checked trajectory's commands (module docstring).

    Args:
        trajectory: the trajectory to play; default: read from the ``trajectory`` parameter.
        node_name: ROS node name.
        namespace: default namespace (``__ns`` remapping overrides it).
        **kwargs: passed to ``rclpy.node.Node`` (``context``, ``parameter_overrides``, ...).

    Raises:
        ConfigError: invalid parameter (named), or no trajectory. A trajectory that breaks the limits does not
            raise: the node reports ``refused`` (status and log) and publishes nothing.
    """

    def __init__(self, trajectory: Trajectory | None = None, node_name: str = "thinshell_deploy",
                 namespace: str = DEFAULT_NAMESPACE, **kwargs: Any) -> None:
        super().__init__(node_name, namespace=namespace, **kwargs)
        source = str(self.declare_parameter("trajectory", "", _descriptor(
            "trajectory.yaml, or a bag (directory or .mcap) whose pose_cmd stream is replayed")).value)
        recording_map = str(self.declare_parameter("recording_map", "", _descriptor(
            "recording map of a real cell's bag given as trajectory (docs/recording_map.md); empty: the bag's "
            "recording.yaml, else the INTERFACES.md topics")).value).strip()
        p = {name: float(self.declare_parameter(name, default, _descriptor(desc, low, high)).value)
             for name, (default, desc, low, high) in FLOAT_PARAMETERS.items()}
        text = {name: str(self.declare_parameter(name, default, _descriptor(desc)).value)
                for name, (default, desc) in STRING_PARAMETERS.items()}
        poses = {name: list(self.declare_parameter(
            name, Parameter.Type.DOUBLE_ARRAY if name == "sensor_mount" else list(IDENTITY), _descriptor(desc)).value or [])
            for name, desc in POSE_PARAMETERS.items()}
        ws_min = list(self.declare_parameter("workspace_min", [-0.5, -0.5, -0.1], _descriptor(
            "[x, y, z] lower corner of the allowed effector positions, m in world")).value)
        ws_max = list(self.declare_parameter("workspace_max", [0.5, 0.5, 0.5], _descriptor(
            "[x, y, z] upper corner of the allowed effector positions, m in world")).value)
        self.wrench_topics = list(self.declare_parameter("wrench_topics", ["tactile/wrench"], _descriptor(
            "WrenchStamped topics monitored against the wrench limits (relative names follow the namespace)")).value)
        self.require_wrench = bool(self.declare_parameter("require_wrench", True, _descriptor(
            "wait for a measured wrench on every wrench_topics topic before starting and watch its age (false: a "
            "cell without force sensing, the wrench limits not enforced)")).value)
        self.dry_run = bool(self.declare_parameter("dry_run", False, _descriptor(
            "check the trajectory and report, publish no command")).value)
        self.approach = bool(self.declare_parameter("approach", False, _descriptor(
            "plan a slow approach from the measured pose to waypoint 0 instead of refusing a distant start")).value)
        try:
            workspace = Workspace(tuple(ws_min), tuple(ws_max))
        except ValueError as err:
            raise ConfigError(f"parameters 'workspace_min'/'workspace_max': {err}") from err
        self.limits = DeployLimits(
            workspace=workspace, max_linear_speed=p["max_linear_speed"], max_angular_speed=p["max_angular_speed"],
            max_linear_acceleration=p["max_linear_acceleration"], max_angular_acceleration=p["max_angular_acceleration"],
            wrench_limit=p["wrench_limit"], start_tolerance=p["start_tolerance"],
            start_angle_tolerance=p["start_angle_tolerance"], pose_lag_tolerance=p["pose_lag_tolerance"],
            pose_lag_window=p["pose_lag_window"])
        self.guard = WrenchGuard(p["wrench_limit"], *(p[k] or math.inf for k in (
            "normal_force_limit", "shear_force_limit", "torque_limit")))
        self.rate, self.time_scale = p["rate"], p["time_scale"]
        self.approach_speed, self.approach_angular_speed = p["approach_speed"], p["approach_angular_speed"]
        self.start_timeout = p["start_timeout"]
        self.interface, self.on_abort_action = text["command_interface"], text["on_abort"]
        if self.interface not in COMMAND_INTERFACES:
            raise ConfigError(f"parameter 'command_interface': {self.interface!r} is not one of {list(COMMAND_INTERFACES)}")
        if self.on_abort_action not in ABORT_ACTIONS:
            raise ConfigError(f"parameter 'on_abort': {self.on_abort_action!r} is not one of {list(ABORT_ACTIONS)}")
        self.watchdog = Watchdog(p["sensor_timeout"])
        self.tare = WrenchTare(p["tare_max_force"]) if p["tare_window"] > 0 else None
        self.tare_window, self.retract_distance = p["tare_window"], p["retract_distance"]
        self.abort_hold_time, self.twist_gain = p["abort_hold_time"], p["twist_gain"]
        self.settle_tolerance, self.settle_angle_tolerance = p["settle_tolerance"], p["settle_angle_tolerance"]
        self._settle_since: float | None = None
        self.wrench_frame = text["wrench_frame"]
        self.ft_in_sensor = checked_pose(poses["wrench_in_sensor"], "wrench_in_sensor")
        if trajectory is None:
            if not source:
                raise ConfigError("parameter 'trajectory' (a trajectory.yaml or a bag) is required")
            trajectory = load_deploy_source(source, recording_map or None)
        if poses["sensor_mount"]:
            mount, mount_from = checked_pose(poses["sensor_mount"], "sensor_mount"), "parameter sensor_mount"
        else:
            try:
                mount, mount_from = scene_mount(trajectory.scene_path)
            except ConfigError as err:
                if text["command_interface"] != "thinshell":  # the commanded tool pose depends on it
                    raise ConfigError(f"the sensor mount of the trajectory's scene: {err}; set parameter "
                                      "'sensor_mount'") from err
                mount, mount_from = np.array(IDENTITY), f"identity (the trajectory's scene is unreadable: {err})"
                self.get_logger().warning(f"sensor mount {mount_from}; on_abort retract lifts along the effector's "
                                          "-z; set parameter 'sensor_mount'")
        self.frames = CellFrames(world_frame=text["world_frame"], base_frame=text["base_frame"],
                                 tool_link=text["tool_link"], world_in_base=poses["world_in_base"],
                                 sensor_in_tool=poses["sensor_in_tool"], sensor_mount=mount)
        self.source = source or "<given>"
        self.trajectory = trajectory
        self.state = "waiting"
        self.reason = ""
        self.done = threading.Event()
        self.schedule: DeploySchedule | None = None
        self.monitor = SafetyMonitor(self.limits)
        self.published = 0
        self.abort_published = 0
        self.abort_action = ""  # "holding" | "retracting" once aborted while running
        self.aborted_at: float | None = None
        # (topic, header stamp in ns) of the measured wrench that tripped the wrench limit, when one did
        self.abort_measurement: tuple[str, int] | None = None
        self._last_tick: float | None = None
        self._measured: dict[str, np.ndarray] = {}
        self._wrench_seen: set[str] = set()
        self._warned_no_wrench = False
        self._wall0 = time.monotonic()
        self._last_status = 0.0
        self._tare_span: tuple[float, float] | None = None
        self._abort: dict[str, Any] | None = None

        effectors = trajectory.effectors
        if self.interface != "thinshell" and len(effectors) != 1:
            raise ConfigError(f"parameter 'command_interface' {self.interface!r} drives one tool link; the trajectory "
                              f"has {len(effectors)} effectors {effectors}")
        topic = text["command_topic"]
        if self.interface == "thinshell":
            if topic and len(effectors) != 1:
                raise ConfigError(f"parameter 'command_topic' names one topic; the trajectory has effectors {effectors}")
            self._pub_cmd = {e: self.create_publisher(PoseStamped, topic or f"{e}/pose_cmd", COMMAND_QOS)
                             for e in effectors}
        else:
            msg_type = PoseStamped if self.interface == "pose_target" else TwistStamped
            self._pub_cmd = {effectors[0]: self.create_publisher(
                msg_type, topic or DEFAULT_COMMAND_TOPICS[self.interface], COMMAND_QOS)}
        self._pub_grip = {e: self.create_publisher(Float64, f"{e}/gripper_cmd", COMMAND_QOS) for e in trajectory.gripper}
        self._pub_status = self.create_publisher(String, "~/status", STATUS_QOS)
        self._resolved = {t: self.resolve_topic_name(t) for t in [f"{e}/pose" for e in effectors] + self.wrench_topics}
        for e in effectors:
            self.create_subscription(PoseStamped, f"{e}/pose", self._pose_callback(e), SENSOR_QOS)
        for t in self.wrench_topics:
            self.create_subscription(WrenchStamped, t, self._wrench_callback(t), SENSOR_QOS)
        self.create_service(Trigger, "~/abort", self._on_abort)
        self._pub_diagnostics = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)
        self._wrench_now: dict[str, np.ndarray] = {}  # topic -> newest wrench in the sensor frame, tared
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(1.0 / self.rate, self._on_tick, clock=self._steady)
        self.create_timer(1.0, self._publish_diagnostics, clock=self._steady)

        try:
            self.trajectory = check_trajectory(trajectory, self.limits, self.time_scale, self.source)
        except ConfigError as err:
            self._finish("refused", str(err))
            return
        where = {"thinshell": f"pose_cmd in {self.frames.world_frame!r}",
                 "pose_target": f"{self.frames.tool_link!r} in {self.frames.base_frame!r}",
                 "twist": f"twist of {self.frames.tool_link!r} in {self.frames.base_frame!r}"}[self.interface]
        msg = (f"deploy {self.source}: {len(effectors)} effector(s) {effectors}, {trajectory.waypoint_count} waypoints, "
               f"{trajectory.duration * self.time_scale:.3f} s at {self.rate:g} Hz (time_scale {self.time_scale:g}), "
               f"clock {'sim (/clock)' if self._use_sim_time else 'wall'}, topics under {self.get_namespace()}; "
               f"command_interface {self.interface} ({where} on "
               f"{', '.join(pub.topic_name for pub in self._pub_cmd.values())}), sensor mount {mount_from}, "
               f"on_abort {self.on_abort_action}")
        if self.dry_run:
            self._finish("completed", f"dry run: trajectory within the limits; {msg}; no command published")
            return
        self.get_logger().info(msg + "; waiting for the measured pose")
        self._publish_status()

    # ------------------------------------------------------------------------------ helpers
    @property
    def _use_sim_time(self) -> bool:
        return bool(self.get_parameter("use_sim_time").value)

    def _now(self) -> float | None:
        """The robot clock in s, or None while ``use_sim_time`` is set and no ``/clock`` arrived."""
        clock = self.get_clock()
        ns = clock.now().nanoseconds
        if self._use_sim_time and ns == 0:
            return None
        return ns * 1e-9

    @property
    def _watched(self) -> list[str]:
        """Streams (resolved topic names) the watchdog watches while running: every effector's pose, every
        required wrench."""
        topics = [f"{e}/pose" for e in self.trajectory.effectors] + (list(self.wrench_topics) if self.require_wrench else [])
        return [self._resolved[t] for t in topics]

    def status(self) -> dict[str, Any]:
        """The status document published on ``~/status``."""
        doc: dict[str, Any] = {"state": self.state, "trajectory": self.source, "reason": self.reason,
                               "published": self.published, "dry_run": self.dry_run,
                               "command_interface": self.interface, "on_abort": self.on_abort_action,
                               "abort_action": self.abort_action, "abort_published": self.abort_published}
        now = self._now()
        if now is not None and self.watchdog.last:
            doc["sensor_age_s"] = {k: round(now - t, 4) for k, t in self.watchdog.last.items()}
        if self.schedule is not None:
            doc.update(progress=self.schedule.progress(), tick=self.schedule.next_tick, ticks=self.schedule.tick_count)
            if self.schedule.lateness:
                late = np.abs(np.asarray(self.schedule.lateness))
                doc.update(timing_error_p95_s=float(np.percentile(late, 95)), timing_error_max_s=float(late.max()))
        else:
            doc["progress"] = 1.0 if self.state == "completed" else 0.0
        return doc

    def diagnostic(self) -> DiagnosticStatus:
        """The node's ``diagnostic_msgs/DiagnosticStatus`` (1 Hz on ``/diagnostics``): ``OK`` while waiting,
        running or completed, ``WARN`` refused, ``ERROR`` aborted; the message is the state and reason; values
        ``state``, ``progress``, ``command_interface``, ``abort_action``, ``force_margin_N`` (the smallest
        margin of any wrench limit that is on, over the wrench topics: limit minus the newest tared value),
        ``force_margin_limit`` (which limit) and ``age_s <topic>`` per watched stream (robot clock)."""
        doc = self.status()
        status = DiagnosticStatus(name=f"{self.get_fully_qualified_name()}: deploy", hardware_id="thinshell",
                                  level=DIAGNOSTIC_LEVELS[self.state],
                                  message=self.state + (f": {self.reason}" if self.reason else ""))
        values = {"state": self.state, "progress": f"{doc['progress']:.4f}", "command_interface": self.interface,
                  "abort_action": self.abort_action}
        margins = [(m, name) for w in self._wrench_now.values() for name, m in self.guard.margins(w).items()]
        if margins:
            m, name = min(margins)
            values.update(force_margin_N=f"{m:.6g}", force_margin_limit=name)
        values.update({f"age_s {k}": f"{v:.4f}" for k, v in doc.get("sensor_age_s", {}).items()})
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        return status

    def _publish_diagnostics(self) -> None:
        msg = DiagnosticArray(status=[self.diagnostic()])
        msg.header.stamp = self.get_clock().now().to_msg()
        self._pub_diagnostics.publish(msg)

    def _publish_status(self) -> None:
        self._last_status = time.monotonic()
        self._pub_status.publish(String(data=json.dumps(self.status())))

    def _finish(self, state: str, reason: str) -> None:
        if self.done.is_set():
            return
        self.state, self.reason = state, reason
        log = self.get_logger()
        (log.info if state == "completed" else log.error)(f"deploy {state}: {reason}")
        self._publish_status()
        self.done.set()

    def abort(self, reason: str) -> None:
        """Abort with ``reason`` (no-op once finished or aborted).

        Before the motion started nothing was commanded: the node ends at once. While running, the
        trajectory stops and ``on_abort`` follows (the module docstring) until :attr:`done` is set.
        """
        if self.done.is_set() or self.state == "aborted":
            return
        now = self._now()
        if self.state != "running" or now is None:
            self._finish("aborted", reason)
            return
        self.state, self.reason = "aborted", reason
        self.aborted_at = time.monotonic()  # steady clock, s: when the abort was decided
        start = {e: self._measured.get(e, self.trajectory.sample_pose(e, 0.0)) for e in self.trajectory.effectors}
        plans: dict[str, RetractPlan] = {}
        if self.on_abort_action == "retract":
            speed = min(self.approach_speed, self.limits.max_linear_speed)  # inside the limits
            plans = {e: RetractPlan(p, -self.frames.sensor_normal_in_world(p), speed, self.retract_distance, now,
                                    self.limits.workspace) for e, p in start.items()}
        lift = max((plan.duration for plan in plans.values()), default=0.0)
        self._abort = {"t0": now, "start": start, "plans": plans, "end": now + lift + self.abort_hold_time,
                       "steady_end": time.monotonic() + lift + self.abort_hold_time + self.start_timeout}
        self.abort_action = "retracting" if plans else "holding"
        self.get_logger().error(
            f"deploy aborted: {reason}; on_abort {self.on_abort_action}: "
            + ("; ".join(f"{e}: lift {plan.reach * 1e3:.3g} mm along {np.round(plan.direction, 4).tolist()} in world "
                         f"at {plan.speed * 1e3:g} mm/s" for e, plan in plans.items())
               if plans else f"commanding the measured pose for {self.abort_hold_time:g} s"))
        self._publish_abort(now)
        self._publish_status()

    # ------------------------------------------------------------------------------ commands
    def _send(self, effector: str, pose: np.ndarray, stamp: int, tau: float | None = None,
              velocity: np.ndarray | None = None) -> None:
        """Publish the command that puts ``effector`` at ``pose`` (world) on the command interface.

        ``tau``: trajectory time of ``pose`` (the twist's feed-forward from the trajectory);
        ``velocity``: else the effector's linear velocity in world (m/s), zero when None.
        """
        pub = self._pub_cmd[effector]
        if self.interface == "thinshell":
            pub.publish(cv.pose_to_msg(pose, stamp, self.frames.world_frame))
        elif self.interface == "pose_target":
            pub.publish(cv.pose_to_msg(self.frames.tool_in_base(pose), stamp, self.frames.base_frame))
        else:
            target = self.frames.tool_in_base(pose)
            measured = self._measured.get(effector)
            measured_tool = None if measured is None else self.frames.tool_in_base(measured)
            if tau is not None:
                dt = 1.0 / self.rate
                nxt = self.frames.tool_in_base(self.trajectory.sample_pose(effector, tau + dt / self.time_scale))
                twist = servo_twist(target, nxt, dt, measured_tool, self.twist_gain, self.limits.max_linear_speed,
                                    self.limits.max_angular_speed)
            else:  # a pure translation (retract) or a stop: exactly zero angular velocity
                v = np.zeros(3) if velocity is None else self.frames.vector_to_base(velocity)
                speed = float(np.linalg.norm(v))
                if speed > self.limits.max_linear_speed:
                    v = v * (self.limits.max_linear_speed / speed)
                twist = np.concatenate([v, np.zeros(3)])
            pub.publish(cv.twist_to_msg(twist, stamp, self.frames.base_frame))

    def _publish_abort(self, now: float) -> None:
        """One command of the abort action at clock reading ``now``; the end of the abort when it is over."""
        a = self._abort
        stamp = cv.seconds_to_ns(now)
        for e, start in a["start"].items():
            plan = a["plans"].get(e)
            if plan is None:
                self._send(e, start, stamp)
            else:
                self._send(e, plan.pose(now), stamp, velocity=plan.velocity(now))
        self.abort_published += 1
        if a["plans"] and all(now - a["t0"] >= plan.duration for plan in a["plans"].values()):
            self.abort_action = "holding"
        if now >= a["end"] or time.monotonic() > a["steady_end"]:
            self.abort_action = "done"
            self.done.set()
            self._publish_status()
            self.get_logger().info(f"abort action {self.on_abort_action} done: {self.abort_published} commands")

    # ------------------------------------------------------------------------------ callbacks
    def _on_abort(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if self.done.is_set() or self.state == "aborted":
            response.success, response.message = False, f"nothing to abort: {self.state}"
        else:
            self.abort("abort requested on ~/abort")
            response.success, response.message = True, "aborted"
        return response

    def _reject(self, reason: str) -> None:
        """A measurement that cannot be used: refused before the start, an abort while running."""
        if self.state == "waiting":
            self._finish("refused", reason)
        else:
            self.abort(reason)

    def _pose_callback(self, effector: str):
        topic = f"{effector}/pose"

        def on_pose(msg: PoseStamped) -> None:
            if self.done.is_set():
                return
            frame, pose = msg.header.frame_id, cv.pose_from_msg(msg)[1]
            if frame == self.frames.base_frame and frame not in (self.frames.world_frame, ""):
                pose = self.frames.effector_in_world(pose)  # the tool link's pose in the robot's base frame
            elif frame not in (self.frames.world_frame, ""):
                self._reject(f"{self.resolve_topic_name(topic)}: frame_id {frame!r} is neither world_frame "
                             f"{self.frames.world_frame!r} nor base_frame {self.frames.base_frame!r}")
                return
            now = self._now()
            if now is not None:
                self.watchdog.seen(self._resolved[topic], now, time.monotonic())
            self._measured[effector] = pose
            if self.state == "running":
                reason = None if now is None else self.monitor.check_pose(effector, now, pose)
                if reason:
                    self.abort(reason)
        return on_pose

    def _wrench_callback(self, topic: str):
        def on_wrench(msg: WrenchStamped) -> None:
            if self.done.is_set():
                return
            if self.wrench_frame and msg.header.frame_id != self.wrench_frame:
                self._reject(f"{self.resolve_topic_name(topic)}: frame_id {msg.header.frame_id!r} is not wrench_frame "
                             f"{self.wrench_frame!r}")
                return
            now = self._now()
            if now is not None:
                self.watchdog.seen(self._resolved[topic], now, time.monotonic())
            self._wrench_seen.add(topic)
            stamp_ns, raw = cv.wrench_from_msg(msg)
            wrench = wrench_in_sensor(raw, self.ft_in_sensor)
            if self.tare is not None and self._tare_span is not None and now is not None \
                    and self._tare_span[0] <= now <= self._tare_span[1]:
                self.tare.add(topic, wrench)
            if self.tare is not None:
                wrench = self.tare.apply(topic, wrench)
            self._wrench_now[topic] = wrench
            if self.state == "running":
                reason = self.guard.check(self._resolved[topic], wrench)
                if reason:
                    self.abort_measurement = (self._resolved[topic], int(stamp_ns))
                    self.abort(reason)
        return on_wrench

    def _on_tick(self) -> None:
        if self.done.is_set():
            return
        steady = time.monotonic()
        # a tick late by half the timeout means this process stalled (the sensors' messages wait behind this tick,
        # or a robot in this process sent none): the watchdog's steady ages restart now
        stalled = self._last_tick is not None and steady - self._last_tick > 0.5 * self.watchdog.timeout
        self._last_tick = steady
        if stalled:
            self.watchdog.resumed(steady)
        try:
            if self.state == "waiting":
                self._try_start()
            if self.state == "running":
                now = self._now()
                reason = None if now is None or stalled else self.watchdog.stale(self._watched, now, steady)
                if reason:
                    self.abort(reason)
                else:
                    self._publish_due()
            if self.state == "aborted" and self._abort is not None and not self.done.is_set():
                now = self._now()
                self._publish_abort(now if now is not None else self._abort["t0"])
        except ThinShellError as err:
            self.abort(str(err))
        if not self.done.is_set() and time.monotonic() - self._last_status > 0.1:
            self._publish_status()

    def _try_start(self) -> None:
        waited = time.monotonic() - self._wall0
        now = self._now()
        missing = [e for e in self.trajectory.effectors if e not in self._measured]
        no_wrench = [t for t in self.wrench_topics if t not in self._wrench_seen] if self.require_wrench else []
        if now is None or missing or no_wrench:
            if waited > self.start_timeout:
                if now is None:
                    what = "no /clock (use_sim_time is set)"
                elif missing:
                    what = f"no measured pose on {[self.resolve_topic_name(f'{e}/pose') for e in missing]}"
                else:
                    what = (f"no measured wrench on {[self.resolve_topic_name(t) for t in no_wrench]} (wrench_limit "
                            f"{self.limits.wrench_limit:g} N cannot be enforced; require_wrench:=false deploys on a "
                            "cell without force sensing)")
                self.abort(f"{what} within start_timeout {self.start_timeout:g} s")
            return
        if self.tare is not None and not self.tare.offset:
            if self._tare_span is None:
                self._tare_span = (now, now + self.tare_window)
                self.get_logger().info(f"wrench tare: averaging {self.tare_window:g} s of "
                                       + ", ".join(self.resolve_topic_name(t) for t in self.wrench_topics))
                return
            if now < self._tare_span[1]:
                return
            try:
                offsets = self.tare.finish(sorted(self._wrench_seen) if not self.require_wrench else self.wrench_topics)
            except ConfigError as err:
                self._finish("refused", str(err))
                return
            # the newest wrenches were kept before there was an offset: tare them too
            self._wrench_now = {t: self.tare.apply(t, w) for t, w in self._wrench_now.items()}
            self.get_logger().info("wrench tare: " + "; ".join(
                f"{self.resolve_topic_name(t)} offset {np.round(w, 4).tolist()}" for t, w in offsets.items()))
        for topic, wrench in self._wrench_now.items():  # a cell already beyond a limit is not driven
            reason = self.guard.check(self._resolved[topic], wrench)
            if reason:
                self._finish("refused", f"before the start: {reason}")
                return
        if not self.require_wrench and not self._warned_no_wrench:
            self._warned_no_wrench = True
            self.get_logger().warning("require_wrench is false: the wrench limit is not enforced unless a wrench "
                                      "arrives on " + ", ".join(self.resolve_topic_name(t) for t in self.wrench_topics))
        traj = self.trajectory
        for e in traj.effectors:
            dist, angle = start_pose_error(self._measured[e], traj.poses[e][0])
            if dist > self.limits.start_tolerance or angle > self.limits.start_angle_tolerance:
                if not self.approach:
                    self._finish("refused", f"{self.source}: waypoint 0, effector {e!r}: the measured start pose is "
                                            f"{dist * 1e3:.3g} mm and {angle:.3g} rad away (start_tolerance "
                                            f"{self.limits.start_tolerance * 1e3:g} mm, {self.limits.start_angle_tolerance:g}"
                                            " rad); move the robot there or set approach:=true")
                    return
                traj = approach_trajectory(traj, self._measured, self.approach_speed, self.approach_angular_speed)
                try:
                    traj = check_trajectory(traj, self.limits, self.time_scale, f"{self.source} (with approach)")
                except ConfigError as err:
                    self._finish("refused", str(err))
                    return
                self.get_logger().info(f"approach of {traj.provenance['approach_s']:.3f} s planned from the measured pose")
                break
        self.trajectory = traj
        self.schedule = DeploySchedule(traj, now, self.rate, self.time_scale)
        for stream in self._watched:  # measured before the first /clock: its age counts from the start
            if stream not in self.watchdog.last:
                self.watchdog.seen(stream, now, time.monotonic())
        self.state = "running"
        self.get_logger().info(f"running: {self.schedule.tick_count} commands from t={now:.3f} s")
        self._publish_status()

    def _publish_due(self) -> None:
        now = self._now()
        if now is None:
            return
        due = self.schedule.due(now)
        if due is not None:
            k, poses, grippers = due
            stamp = cv.seconds_to_ns(self.schedule.t0 + k * self.schedule.period)
            tau = k * self.schedule.period / self.time_scale
            for e, pose in poses.items():
                self._send(e, pose, stamp, tau=tau)
                self.monitor.commanded(e, now, pose)
            for e, g in grippers.items():
                self._pub_grip[e].publish(Float64(data=float(g)))
            self.published += 1
        if self.schedule.finished:
            if self.interface == "twist" and not self._settled(now):
                return
            if self.interface == "twist":  # the end of the motion: stop (Servo would keep the last twist until its timeout)
                for e in self.trajectory.effectors:
                    self._send(e, self.trajectory.poses[e][-1], cv.seconds_to_ns(now))
            self._finish("completed", f"{self.published} commands published over "
                                      f"{self.schedule.end - self.schedule.t0:.3f} s")

    def _settled(self, now: float) -> bool:
        """Twist interface after the last tick: True once every measured pose is within the settle tolerances of
        the final pose; until then a feedback twist towards it (no feed-forward) each tick.

        Raises:
            ThinShellError: not settled within ``start_timeout`` s of steady time (the tick aborts).
        """
        if self._settle_since is None:
            self._settle_since = time.monotonic()
        far = []
        for e in self.trajectory.effectors:
            final, measured = self.trajectory.poses[e][-1], self._measured[e]
            dist, angle = start_pose_error(measured, final)
            if dist > self.settle_tolerance or angle > self.settle_angle_tolerance:
                far.append((e, dist, angle))
                tool = self.frames.tool_in_base(final)
                twist = servo_twist(tool, tool, 1.0, self.frames.tool_in_base(measured), self.twist_gain,
                                    self.limits.max_linear_speed, self.limits.max_angular_speed)
                self._pub_cmd[e].publish(cv.twist_to_msg(twist, cv.seconds_to_ns(now), self.frames.base_frame))
        if far and time.monotonic() - self._settle_since > self.start_timeout:
            e, dist, angle = far[0]
            raise ThinShellError(f"effector {e!r} did not settle at the final pose within start_timeout "
                                 f"{self.start_timeout:g} s: {dist * 1e3:.3g} mm and {angle:.3g} rad away "
                                 f"(settle_tolerance {self.settle_tolerance * 1e3:g} mm, settle_angle_tolerance "
                                 f"{self.settle_angle_tolerance:g} rad)")
        return not far


def deploy_main(argv: Sequence[str] | None = None) -> int:
    """``thinshell deploy TRAJECTORY [--dry-run] [--approach] [--time-scale X] [ROS args]``.

    Other node parameters go after ``--ros-args`` (``-p wrench_limit:=5.0``, ``-r __ns:=/robot``).
    Returns 0 when the motion completed, 1 when it was refused or aborted.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    ros_args = argv[argv.index("--ros-args"):] if "--ros-args" in argv else []
    own = argv[:len(argv) - len(ros_args)]
    parser = argparse.ArgumentParser(prog="thinshell deploy", description=(
        "play a trajectory.yaml (or a bag's pose_cmd stream) on the robot over DDS, with limits and an abort; "
        "node parameters after --ros-args"))
    parser.add_argument("trajectory", help="trajectory.yaml (docs/trajectory_format.md) or a bag to replay")
    parser.add_argument("--dry-run", action="store_true", help="check and report, publish nothing")
    parser.add_argument("--approach", action="store_true", help="plan a slow approach to the start pose")
    parser.add_argument("--time-scale", type=float, default=None, help="factor on the trajectory's times")
    parser.add_argument("--recording-map", metavar="FILE",
                        help="recording map of a real cell's bag given as trajectory (docs/recording_map.md)")
    args = parser.parse_args(own)
    params = ["-p", f"trajectory:={args.trajectory}"]
    if args.dry_run:
        params += ["-p", "dry_run:=true"]
    if args.approach:
        params += ["-p", "approach:=true"]
    if args.time_scale is not None:
        params += ["-p", f"time_scale:={args.time_scale}"]
    if args.recording_map is not None:
        params += ["-p", f"recording_map:={args.recording_map}"]
    ros = ros_args + params if ros_args else ["--ros-args", *params]
    return main(["thinshell-deploy-node", *ros])


def main(argv: Sequence[str] | None = None) -> int:
    """Run the deploy node until the motion ends or SIGINT/SIGTERM; 0 when it completed."""
    args = list(sys.argv) if argv is None else list(argv)
    with ros_session(args) as stop:
        try:
            node = DeployNode()
        except (ThinShellError, FileNotFoundError) as err:
            print(f"thinshell deploy: error: {err}", file=sys.stderr)
            return 1

        def check_done() -> None:
            if node.done.is_set():
                stop.set()
        node.create_timer(0.2, check_done)  # the final status has 0.2 s to reach subscribers
        try:
            spin_until_stopped(node, stop)
            if not node.done.is_set():
                node.abort("interrupted (SIGINT/SIGTERM)")
        finally:
            node.destroy_node()
        return 0 if node.state == "completed" else 1


if __name__ == "__main__":
    sys.exit(main())
