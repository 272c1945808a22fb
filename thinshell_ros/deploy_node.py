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
one control period of its arrival; nothing is published after an abort). ``~/abort``
(``std_srvs/Trigger``) aborts on request. ``dry_run`` checks and reports without publishing commands.

Status: ``~/status`` (``std_msgs/String``, JSON, reliable + transient local, 10 Hz and at every
change): ``state`` (``waiting`` | ``running`` | ``completed`` | ``aborted`` | ``refused``), ``progress``
(0..1), ``tick``/``ticks``, ``reason``, ``trajectory``, and at the end ``timing_error_p95_s``. The
same transitions go to the log.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from geometry_msgs.msg import PoseStamped, WrenchStamped
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64, String
from std_srvs.srv import Trigger

from sim_core.errors import ConfigError, ThinShellError
from sim_core.trajectory_file import Trajectory, read_trajectory
from thinshell_ros import conversions as cv
from thinshell_ros.commands import Workspace
from thinshell_ros.deploy_plan import (DeployLimits, DeploySchedule, SafetyMonitor, approach_trajectory,
                                       check_trajectory, start_pose_error, trajectory_from_bag)
from thinshell_ros.runtime import COMMAND_QOS, SENSOR_QOS, ros_session, spin_until_stopped

DEFAULT_NAMESPACE = "/thinshell"
STATES = ("waiting", "running", "completed", "aborted", "refused")
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
        ConfigError: invalid parameter, or no trajectory. A trajectory that breaks the limits does not
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
        ws_min = list(self.declare_parameter("workspace_min", [-0.5, -0.5, -0.1], _descriptor(
            "[x, y, z] lower corner of the allowed effector positions, m in world")).value)
        ws_max = list(self.declare_parameter("workspace_max", [0.5, 0.5, 0.5], _descriptor(
            "[x, y, z] upper corner of the allowed effector positions, m in world")).value)
        self.wrench_topics = list(self.declare_parameter("wrench_topics", ["tactile/wrench"], _descriptor(
            "WrenchStamped topics monitored against wrench_limit (relative names follow the namespace)")).value)
        self.require_wrench = bool(self.declare_parameter("require_wrench", True, _descriptor(
            "wait for a measured wrench on every wrench_topics topic before starting (false: a cell without "
            "force sensing, wrench_limit not enforced)")).value)
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
        self.rate, self.time_scale = p["rate"], p["time_scale"]
        self.approach_speed, self.approach_angular_speed = p["approach_speed"], p["approach_angular_speed"]
        self.start_timeout = p["start_timeout"]
        if trajectory is None:
            if not source:
                raise ConfigError("parameter 'trajectory' (a trajectory.yaml or a bag) is required")
            trajectory = load_deploy_source(source, recording_map or None)
        self.source = source or "<given>"
        self.trajectory = trajectory
        self.state = "waiting"
        self.reason = ""
        self.done = threading.Event()
        self.schedule: DeploySchedule | None = None
        self.monitor = SafetyMonitor(self.limits)
        self.published = 0
        self._measured: dict[str, np.ndarray] = {}
        self._wrench_seen: set[str] = set()
        self._warned_no_wrench = False
        self._wall0 = time.monotonic()
        self._last_status = 0.0

        effectors = trajectory.effectors
        self._pub_pose = {e: self.create_publisher(PoseStamped, f"{e}/pose_cmd", COMMAND_QOS) for e in effectors}
        self._pub_grip = {e: self.create_publisher(Float64, f"{e}/gripper_cmd", COMMAND_QOS) for e in trajectory.gripper}
        self._pub_status = self.create_publisher(String, "~/status", STATUS_QOS)
        for e in effectors:
            self.create_subscription(PoseStamped, f"{e}/pose", self._pose_callback(e), SENSOR_QOS)
        for topic in self.wrench_topics:
            self.create_subscription(WrenchStamped, topic, self._wrench_callback(topic), SENSOR_QOS)
        self.create_service(Trigger, "~/abort", self._on_abort)
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(1.0 / self.rate, self._on_tick, clock=self._steady)

        try:
            self.trajectory = check_trajectory(trajectory, self.limits, self.time_scale, self.source)
        except ConfigError as err:
            self._finish("refused", str(err))
            return
        msg = (f"deploy {self.source}: {len(effectors)} effector(s) {effectors}, {trajectory.waypoint_count} waypoints, "
               f"{trajectory.duration * self.time_scale:.3f} s at {self.rate:g} Hz (time_scale {self.time_scale:g}), "
               f"clock {'sim (/clock)' if self._use_sim_time else 'wall'}, topics under {self.get_namespace()}")
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

    def status(self) -> dict[str, Any]:
        """The status document published on ``~/status``."""
        doc: dict[str, Any] = {"state": self.state, "trajectory": self.source, "reason": self.reason,
                               "published": self.published, "dry_run": self.dry_run}
        if self.schedule is not None:
            doc.update(progress=self.schedule.progress(), tick=self.schedule.next_tick, ticks=self.schedule.tick_count)
            if self.schedule.lateness:
                late = np.abs(np.asarray(self.schedule.lateness))
                doc.update(timing_error_p95_s=float(np.percentile(late, 95)), timing_error_max_s=float(late.max()))
        else:
            doc["progress"] = 1.0 if self.state == "completed" else 0.0
        return doc

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
        """Stop publishing at once and report ``aborted`` with ``reason`` (no-op once finished)."""
        self._finish("aborted", reason)

    # ------------------------------------------------------------------------------ callbacks
    def _on_abort(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if self.done.is_set():
            response.success, response.message = False, f"nothing to abort: {self.state}"
        else:
            self.abort("abort requested on ~/abort")
            response.success, response.message = True, "aborted"
        return response

    def _pose_callback(self, effector: str):
        def on_pose(msg: PoseStamped) -> None:
            pose = cv.pose_from_msg(msg)[1]
            self._measured[effector] = pose
            if self.state == "running":
                now = self._now()
                reason = None if now is None else self.monitor.check_pose(effector, now, pose)
                if reason:
                    self.abort(reason)
        return on_pose

    def _wrench_callback(self, topic: str):
        def on_wrench(msg: WrenchStamped) -> None:
            self._wrench_seen.add(topic)
            if self.state == "running":
                reason = self.monitor.check_wrench(topic, cv.wrench_from_msg(msg)[1])
                if reason:
                    self.abort(reason)
        return on_wrench

    def _on_tick(self) -> None:
        if self.done.is_set():
            return
        try:
            if self.state == "waiting":
                self._try_start()
            if self.state == "running":
                self._publish_due()
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
            for e, pose in poses.items():
                self._pub_pose[e].publish(cv.pose_to_msg(pose, stamp, "world"))
                self.monitor.commanded(e, now, pose)
            for e, g in grippers.items():
                self._pub_grip[e].publish(Float64(data=float(g)))
            self.published += 1
        if self.schedule.finished:
            self._finish("completed", f"{self.published} commands published over "
                                      f"{self.schedule.end - self.schedule.t0:.3f} s")


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
