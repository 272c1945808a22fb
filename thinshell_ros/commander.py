"""A scripted commander: press, slide and lift the tactile sensor over DDS, on the robot's clock (wall or sim time).

The commander is a client of the simulator node (INTERFACES.md): it waits for the first measured
``<effector>/pose`` and ``sheet/points``, plans a scripted trajectory from that geometry
(:func:`thinshell_ros.trajectory.scripted_trajectory`: approach along the sensor's outward normal
until the gel touches the top of the sheet, press ``depth`` further, hold, slide ``slide`` along
world +x, lift back to the start height), and publishes ``<effector>/pose_cmd`` at a fixed rate of
the node's clock: at every tick ``t`` at or past the next publication time it sends the trajectory's
pose at ``t - t0 + 1/rate`` (one period of look-ahead, as the simulator moves towards the latest
target during the next period). ``t0`` is the clock reading the plan was made at.

The clock is the ROS one: with ``use_sim_time`` the ticks are the ``/clock`` messages (sim time, as
the simulator steps: fast or slow); without it (a real cell, which publishes no ``/clock``) a steady
timer at ``rate`` reads wall time, and the commander never waits for a ``/clock``.

Pure parts (planning, scheduling) are free of rclpy: :func:`plan_from_observation`,
:class:`CommandSchedule`. :class:`CommanderNode` wires them to topics; :func:`main` runs it
standalone (``python -m thinshell_ros.commander --ros-args -p scene:=...``).
"""

from __future__ import annotations

import math
import sys
import threading
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from rclpy.clock import Clock as RosClock, ClockType
from rclpy.node import Node

from sim_core.errors import ConfigError, ThinShellError
from sim_core.scenes.scene_file import SceneFile, load_scene_file
from sim_core.transforms import compose_poses, quat_to_matrix
from thinshell_ros import conversions as cv
from thinshell_ros.paths import bundled_scene
from thinshell_ros.runtime import CLOCK_QOS, COMMAND_QOS, SENSOR_QOS, ros_session, spin_until_stopped, topic_namespace
from thinshell_ros.trajectory import SCRIPTED, Trajectory, scripted_trajectory

DEFAULT_SCRIPT = "press_slide_lift"


def plan_from_observation(scene: SceneFile, effector_pose: np.ndarray, sheet_points: np.ndarray,
                          name: str = DEFAULT_SCRIPT, sensor: str | None = None, *, depth: float = 1.0e-3,
                          slide: float = 0.015, approach_speed: float = 0.02, press_speed: float = 0.005,
                          slide_speed: float = 0.02, hold: float = 0.05, release: float = 5.0e-4) -> Trajectory:
    """Scripted trajectory from the measured effector pose and sheet points.

    The sensor frame is the effector pose composed with the sensor's ``mount`` (identity when the
    scene has none); the sheet top is the highest measured sheet point (mid-surface) plus half the
    sheet thickness of the scene. ``press_slide`` is :func:`scripted_trajectory`'s (approach at
    ``approach_speed`` until the gel touches the sheet top, press ``depth`` at ``press_speed``, hold,
    slide along world +x at ``slide_speed``); ``press_slide_lift`` then releases the contact the way
    it was made (back along the sensor normal by ``depth + release`` at ``press_speed``: pulling the
    stuck gel off the card faster makes the implicit solver's line search fail) and lifts to the
    start height at ``approach_speed``.

    Args:
        scene: the scene the simulator runs.
        effector_pose: measured effector pose ``(7,)`` ``[x y z qx qy qz qw]`` in ``world``.
        sheet_points: measured sheet points ``(p, 3)`` in ``world``, m.
        name: ``press_slide`` or ``press_slide_lift``.
        sensor: tactile sensor name (None: the scene's first sensor).
        depth, slide, release: m.  approach_speed, press_speed, slide_speed: m/s (> 0).  hold: s.

    Returns:
        the trajectory of the sensor's effector, starting at ``t = 0``.

    Raises:
        ConfigError: no sensor / unknown sensor, no sheet points, non-finite input, a speed <= 0, or
            a geometry :func:`scripted_trajectory` rejects.
    """
    if not scene.sensors:
        raise ConfigError(f"{scene.source}: the commander needs a tactile sensor in the scene")
    sensor = sensor or next(iter(scene.sensors))
    if sensor not in scene.sensors:
        raise ConfigError(f"{scene.source}: no sensor {sensor!r} (sensors: {list(scene.sensors)})")
    if name not in SCRIPTED:
        raise ConfigError(f"unknown scripted trajectory {name!r} (known: {list(SCRIPTED)})")
    speeds = {"approach_speed": approach_speed, "press_speed": press_speed, "slide_speed": slide_speed}
    for key, value in speeds.items():
        if not (math.isfinite(value) and value > 0):
            raise ConfigError(f"{key} must be finite and > 0 m/s, got {value}")
    spec = scene.sensors[sensor]
    pose = np.asarray(effector_pose, dtype=float).reshape(7)
    points = np.asarray(sheet_points, dtype=float).reshape(-1, 3)
    if not len(points):
        raise ConfigError("the commander needs at least one sheet point to find the sheet's top")
    if not (np.all(np.isfinite(pose)) and np.all(np.isfinite(points))):
        raise ConfigError("the commander got a non-finite effector pose or sheet point")
    mount = np.asarray(spec.mount if spec.mount is not None else (0, 0, 0, 0, 0, 0, 1), dtype=float)
    sensor_pose = compose_poses(pose, mount)
    top = float(points[:, 2].max()) + 0.5 * scene.sheet.thickness
    base = scripted_trajectory("press_slide", pose, sensor_pose, top, depth=depth, slide=slide, hold=hold,
                               effector=spec.effector, **speeds)
    if name == "press_slide":
        return base
    n = quat_to_matrix(sensor_pose[3:7])[:, 2]
    t, poses = list(base.t), list(base.poses)
    released = poses[-1].copy()
    released[:3] -= (depth + release) * n
    t.append(t[-1] + (depth + release) / press_speed)
    poses.append(released)
    if pose[2] > released[2] + 1e-9:
        lifted = released.copy()
        lifted[2] = pose[2]
        t.append(t[-1] + (pose[2] - released[2]) / approach_speed)
        poses.append(lifted)
    return Trajectory(spec.effector, np.asarray(t), np.asarray(poses))


class CommandSchedule:
    """When to publish which pose: a trajectory sampled at a fixed rate of sim time.

    Args:
        trajectory: the plan (time 0 = ``t0``).
        t0: sim time at which the plan starts, s.
        rate: publication rate, Hz of sim time (> 0).
        settle: s after the trajectory's end during which its final pose is still sent.

    Raises:
        ConfigError: ``rate`` not finite and > 0, or ``settle`` < 0.
    """

    def __init__(self, trajectory: Trajectory, t0: float, rate: float, settle: float = 0.05) -> None:
        if not (math.isfinite(rate) and rate > 0):
            raise ConfigError(f"commander rate must be finite and > 0 Hz, got {rate}")
        if not (math.isfinite(settle) and settle >= 0):
            raise ConfigError(f"commander settle time must be >= 0 s, got {settle}")
        self.trajectory = trajectory
        self.t0 = float(t0)
        self.period = 1.0 / float(rate)
        self.settle = float(settle)
        self._next = self.t0
        self.sent = 0

    @property
    def end(self) -> float:
        """Sim time after which the schedule is finished, s."""
        return self.t0 + self.trajectory.duration + self.settle

    def progress(self, t: float) -> float:
        """Fraction of the schedule done at sim time ``t`` (0..1)."""
        span = self.end - self.t0
        return 1.0 if span <= 0 else float(min(1.0, max(0.0, (t - self.t0) / span)))

    def finished(self, t: float) -> bool:
        """True once sim time ``t`` is past :attr:`end`."""
        return t >= self.end - 1e-12

    def due(self, t: float) -> np.ndarray | None:
        """The pose ``(7,)`` to publish at sim time ``t``, or None when no publication is due.

        A publication is due when ``t`` reached the next publication time; the next one is then one
        period after ``t`` (a clock that jumps over several periods yields one command, not a burst).
        The pose is the trajectory at ``t - t0 + period`` (one period of look-ahead).
        """
        if t < self._next - 1e-12:
            return None
        self._next = t + self.period
        self.sent += 1
        return self.trajectory.sample(t - self.t0 + self.period)


class CommanderNode(Node):
    """ROS 2 node publishing a scripted ``<effector>/pose_cmd`` on its clock (``/clock`` with ``use_sim_time``, else wall time).

    Parameters (``--ros-args -p name:=value``): ``scene`` (path; default the bundled scene),
    ``script`` (``press_slide_lift`` | ``press_slide``), ``depth``, ``slide``, ``release`` (m),
    ``approach_speed`` (also the lift), ``press_speed`` (also the release), ``slide_speed`` (m/s),
    ``hold`` (s), ``rate`` (Hz of the node's clock; 0: one command per scene ``dt``), ``namespace``
    (``/thinshell``; a node given a ROS namespace, ``-r __ns:=/robot``, uses relative topic names in it:
    :func:`thinshell_ros.runtime.topic_namespace`), ``use_sim_time`` (ticks from ``/clock``; else a wall-time timer). Geometry and speeds: :func:`plan_from_observation`.

    Args:
        node_name: ROS node name.
        **kwargs: passed to ``rclpy.node.Node`` (``context``, ``parameter_overrides``, ...).

    Raises:
        ConfigError: bad parameter or scene.
    """

    def __init__(self, node_name: str = "thinshell_commander", **kwargs: Any) -> None:
        from geometry_msgs.msg import PoseStamped  # optional heavy dependency: ROS 2 (rclpy), for ROS commands only
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import PointCloud2

        super().__init__(node_name, **kwargs)
        self._cv = cv
        scene_path = str(self.declare_parameter("scene", "").value) or str(bundled_scene())
        self.script = str(self.declare_parameter("script", DEFAULT_SCRIPT).value)
        defaults = {"depth": 1.0e-3, "slide": 0.015, "release": 5.0e-4, "approach_speed": 0.02,
                    "press_speed": 0.005, "slide_speed": 0.02, "hold": 0.05}
        self.plan_kwargs = {k: float(self.declare_parameter(k, v).value) for k, v in defaults.items()}
        rate = float(self.declare_parameter("rate", 0.0).value)
        self.namespace, prefix = topic_namespace(self, str(self.declare_parameter("namespace", "/thinshell").value))
        if self.script not in SCRIPTED:
            raise ConfigError(f"parameter 'script' must be one of {list(SCRIPTED)}, got {self.script!r}")
        for key, value in self.plan_kwargs.items():
            positive = key.endswith("_speed")
            if not (math.isfinite(value) and (value > 0 if positive else value >= 0)):
                raise ConfigError(f"parameter {key!r} must be finite and {'> 0' if positive else '>= 0'}, got {value}")
        self.scene = load_scene_file(Path(scene_path))
        self.rate = rate if rate > 0 else 1.0 / self.scene.dt
        if not math.isfinite(self.rate):
            raise ConfigError(f"parameter 'rate' must be finite, got {rate}")
        if not self.scene.sensors:
            raise ConfigError(f"{scene_path}: the commander needs a tactile sensor in the scene")
        self.effector = next(iter(self.scene.sensors.values())).effector
        self.schedule: CommandSchedule | None = None
        self.sim_time: float | None = None
        self.done = threading.Event()
        self._pose: np.ndarray | None = None
        self._points: np.ndarray | None = None
        ns = self.namespace
        self._pub = self.create_publisher(PoseStamped, f"{prefix}{self.effector}/pose_cmd", COMMAND_QOS)
        self.create_subscription(PoseStamped, f"{prefix}{self.effector}/pose", self._on_pose, SENSOR_QOS)
        self.create_subscription(PointCloud2, f"{prefix}sheet/points", self._on_points, SENSOR_QOS)
        if bool(self.get_parameter("use_sim_time").value):
            self.create_subscription(Clock, "/clock", self._on_clock, CLOCK_QOS)
        else:
            self.create_timer(1.0 / self.rate, self._on_wall_tick, clock=RosClock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(f"commander: {self.script} for {self.effector!r} at {self.rate:g} Hz of sim time, "
                               f"scene {scene_path}; waiting for {ns}/{self.effector}/pose and {ns}/sheet/points")

    @property
    def subscriber_count(self) -> int:
        """Subscriptions matched by the ``pose_cmd`` publisher."""
        return self._pub.get_subscription_count()

    def progress(self) -> float:
        """Fraction of the scripted motion done (0 before the plan exists)."""
        if self.schedule is None or self.sim_time is None:
            return 0.0
        return self.schedule.progress(self.sim_time)

    def _on_pose(self, msg: Any) -> None:
        self._pose = self._cv.pose_from_msg(msg)[1]

    def _on_points(self, msg: Any) -> None:
        self._points = self._cv.cloud_from_msg(msg, self._cv.POINT_FIELDS)[1]

    def _on_clock(self, msg: Any) -> None:
        self._tick(self._cv.clock_from_msg(msg) * 1e-9)

    def _on_wall_tick(self) -> None:
        self._tick(self.get_clock().now().nanoseconds * 1e-9)

    def _tick(self, t: float) -> None:
        """Plan on the first tick with a measured pose and sheet, then publish what is due at clock ``t`` (s)."""
        self.sim_time = t
        if self.done.is_set():
            return
        if self.schedule is None:
            if self._pose is None or self._points is None or self.subscriber_count == 0:
                return
            try:
                traj = plan_from_observation(self.scene, self._pose, self._points, self.script, **self.plan_kwargs)
            except ConfigError as err:
                self.get_logger().error(f"cannot plan the {self.script} motion: {err}")
                self.done.set()
                return
            self.schedule = CommandSchedule(traj, t, self.rate)
            self.get_logger().info(f"plan from t={t:.3f} s: {traj.duration:.3f} s of motion, "
                                   f"waypoints at {np.round(traj.t, 3).tolist()} s")
        pose = self.schedule.due(t)
        if pose is not None:
            self._pub.publish(self._cv.pose_to_msg(pose, self._cv.seconds_to_ns(t), "world"))
        if self.schedule.finished(t):
            self.get_logger().info(f"motion done at t={t:.3f} s ({self.schedule.sent} commands)")
            self.done.set()


def main(argv: Sequence[str] | None = None) -> int:
    """Run the commander until its motion is done or SIGINT/SIGTERM; returns the exit code."""
    args = list(sys.argv) if argv is None else ["thinshell-commander", *argv]
    with ros_session(args) as stop:
        try:
            node = CommanderNode()
        except (ThinShellError, FileNotFoundError) as err:
            print(f"thinshell commander: error: {err}", file=sys.stderr)
            return 1
        node.create_timer(0.1, lambda: stop.set() if node.done.is_set() else None)
        try:
            spin_until_stopped(node, stop)
        finally:
            node.destroy_node()
    return 0


if __name__ == "__main__":
    sys.exit(main())
