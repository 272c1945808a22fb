"""What the deploy node checks and when it publishes, free of rclpy (unit-testable without DDS).

- :func:`check_trajectory` refuses, before anything is published, a trajectory that has NaN/inf,
  non-monotonic times, a zero quaternion, a waypoint outside the workspace, or a segment that breaks
  the linear / angular speed or acceleration limit (times scaled by ``time_scale``). Every refusal is
  a :class:`~sim_core.errors.ConfigError` naming the waypoint.
- :func:`approach_trajectory` prepends a slow straight-line approach from the measured pose to the
  trajectory's first pose; :func:`start_pose_error` measures how far the robot is from it.
- :class:`DeploySchedule` says which command is due at a clock reading: commands on a fixed grid of
  ``1 / rate`` s of the robot's clock, each the trajectory sampled at its grid time (so a late tick
  publishes the pose it was scheduled to, and the lateness is the timing error).
- :class:`SafetyMonitor` aborts on a measured wrench above the limit or a measured pose that lags
  every recent command by more than the tolerance.
- :func:`trajectory_from_bag` turns a recording's ``pose_cmd`` stream into a trajectory (replay).

Speeds of a segment ``i-1 -> i`` (duration ``dt_i = time_scale (t_i - t_{i-1})``):
``v_i = |p_i - p_{i-1}| / dt_i``, ``w_i = angle(q_{i-1}^-1 q_i) / dt_i``. Accelerations at waypoint
``i``: ``|v_{i+1} - v_i| / ((dt_i + dt_{i+1}) / 2)`` with the velocity vectors, the motion starting
and ending at rest (``v_0 = v_{T} = 0``, the end segments counted with their own duration).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

import numpy as np

from sim_core.errors import ConfigError
from sim_core.trajectory_file import Trajectory, validate_trajectory
from sim_core.transforms import quat_multiply, quat_to_rotvec
from sysid.bagio import open_bag
from thinshell_ros.commands import Workspace

_CONJ = np.array([-1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class DeployLimits:
    """The robot cell's limits (deploy node parameters).

    Attributes:
        workspace: allowed effector positions (m, ``world``), or None.
        max_linear_speed: m/s; max_angular_speed: rad/s.
        max_linear_acceleration: m/s^2; max_angular_acceleration: rad/s^2.
        wrench_limit: N, on the norm of the measured force of any sensor.
        start_tolerance: m between the measured pose and the trajectory's first pose.
        start_angle_tolerance: rad, the same for the orientation.
        pose_lag_tolerance: m between the measured position and the nearest recent command.
        pose_lag_window: s of commands the measured pose is compared with.

    Raises:
        ConfigError: a limit that is not finite and > 0.
    """

    workspace: Workspace | None = None
    max_linear_speed: float = 0.05
    max_angular_speed: float = 1.0
    max_linear_acceleration: float = 1.0
    max_angular_acceleration: float = 20.0
    wrench_limit: float = 20.0
    start_tolerance: float = 0.002
    start_angle_tolerance: float = 0.05
    pose_lag_tolerance: float = 0.005
    pose_lag_window: float = 0.1

    def __post_init__(self) -> None:
        for name in ("max_linear_speed", "max_angular_speed", "max_linear_acceleration", "max_angular_acceleration",
                     "wrench_limit", "start_tolerance", "start_angle_tolerance", "pose_lag_tolerance", "pose_lag_window"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"deploy limit {name} must be finite and > 0, got {value}")


def rotation_angle(q0: np.ndarray, q1: np.ndarray) -> float:
    """Angle (rad, in ``[0, pi]``) of the rotation from unit quaternion ``q0`` to ``q1`` (``[qx qy qz qw]``)."""
    return float(np.linalg.norm(quat_to_rotvec(quat_multiply(np.asarray(q1, float), np.asarray(q0, float) * _CONJ))))


def check_trajectory(traj: Trajectory, limits: DeployLimits, time_scale: float = 1.0,
                     where: str = "trajectory") -> Trajectory:
    """Validate a trajectory against the cell's limits before any command is published.

    Args:
        traj: the trajectory.
        limits: the cell's limits.
        time_scale: factor on the trajectory's times (2: twice as slow), > 0.
        where: prefix of error messages (the file).

    Returns:
        the validated trajectory (normalised quaternions).

    Raises:
        ConfigError: the first fault, naming the waypoint (index, time, effector) and the limit.
    """
    if not (math.isfinite(time_scale) and time_scale > 0):
        raise ConfigError(f"time_scale must be finite and > 0, got {time_scale}")
    traj = validate_trajectory(traj, where)
    t = traj.t * time_scale
    dt = np.diff(t)
    for eff, poses in traj.poses.items():
        ws = limits.workspace
        if ws is not None:
            for i, p in enumerate(poses):
                if not ws.contains(p[:3]):
                    raise ConfigError(f"{where}: waypoint {i} (t={traj.t[i]:g} s), effector {eff!r}: position "
                                      f"{np.round(p[:3], 6).tolist()} m is outside the workspace {ws.describe()}")
        if len(t) < 2:
            continue
        v = np.diff(poses[:, :3], axis=0) / dt[:, None]  # (T-1, 3) segment velocities
        w = np.array([quat_to_rotvec(quat_multiply(poses[i + 1, 3:], poses[i, 3:] * _CONJ))
                      for i in range(len(dt))]) / dt[:, None]
        for i in range(len(dt)):
            at = f"{where}: waypoint {i + 1} (t={traj.t[i + 1]:g} s), effector {eff!r}"
            speed, omega = float(np.linalg.norm(v[i])), float(np.linalg.norm(w[i]))
            if speed > limits.max_linear_speed * (1 + 1e-9):
                raise ConfigError(f"{at}: linear speed {speed:.4g} m/s from waypoint {i} exceeds max_linear_speed "
                                  f"{limits.max_linear_speed:g} m/s (time_scale {time_scale:g})")
            if omega > limits.max_angular_speed * (1 + 1e-9):
                raise ConfigError(f"{at}: angular speed {omega:.4g} rad/s from waypoint {i} exceeds max_angular_speed "
                                  f"{limits.max_angular_speed:g} rad/s (time_scale {time_scale:g})")
        zero = np.zeros((1, 3))
        vv, ww = np.vstack([zero, v, zero]), np.vstack([zero, w, zero])
        durations = np.concatenate([[dt[0]], dt, [dt[-1]]])
        for i in range(len(t)):
            span = 0.5 * (durations[i] + durations[i + 1])
            acc = float(np.linalg.norm(vv[i + 1] - vv[i])) / span
            alpha = float(np.linalg.norm(ww[i + 1] - ww[i])) / span
            at = f"{where}: waypoint {i} (t={traj.t[i]:g} s), effector {eff!r}"
            if acc > limits.max_linear_acceleration * (1 + 1e-9):
                raise ConfigError(f"{at}: linear acceleration {acc:.4g} m/s^2 exceeds max_linear_acceleration "
                                  f"{limits.max_linear_acceleration:g} m/s^2 (time_scale {time_scale:g})")
            if alpha > limits.max_angular_acceleration * (1 + 1e-9):
                raise ConfigError(f"{at}: angular acceleration {alpha:.4g} rad/s^2 exceeds max_angular_acceleration "
                                  f"{limits.max_angular_acceleration:g} rad/s^2 (time_scale {time_scale:g})")
    return traj


def start_pose_error(measured: np.ndarray, start: np.ndarray) -> tuple[float, float]:
    """``(distance m, angle rad)`` between a measured pose and the trajectory's first pose ``(7,)``."""
    measured, start = np.asarray(measured, float), np.asarray(start, float)
    return float(np.linalg.norm(measured[:3] - start[:3])), rotation_angle(measured[3:], start[3:])


def approach_trajectory(traj: Trajectory, measured: Mapping[str, np.ndarray], linear_speed: float,
                        angular_speed: float) -> Trajectory:
    """``traj`` preceded by a straight-line approach from the measured poses to its first poses.

    The approach takes ``max(distance / linear_speed, angle / angular_speed)`` over the effectors (at
    least 0.1 s, rest to rest: linear interpolation at constant speed), then the trajectory follows
    with its times shifted by that duration. Gripper openings are held at their first value.

    Args:
        traj: the trajectory.
        measured: effector -> measured pose ``(7,)``.
        linear_speed: m/s (> 0); angular_speed: rad/s (> 0).

    Raises:
        ConfigError: a measured pose missing for an effector of the trajectory.
    """
    missing = [e for e in traj.effectors if e not in measured]
    if missing:
        raise ConfigError(f"no measured pose for effectors {missing}")
    duration = 0.1
    for e in traj.effectors:
        dist, angle = start_pose_error(measured[e], traj.poses[e][0])
        duration = max(duration, dist / linear_speed, angle / angular_speed)
    t = np.concatenate([[0.0], traj.t - traj.t[0] + duration])
    poses = {e: np.vstack([np.asarray(measured[e], float)[None], p]) for e, p in traj.poses.items()}
    gripper = {e: np.concatenate([[g[0]], g]) for e, g in traj.gripper.items()}
    prov = dict(traj.provenance, approach_s=float(duration))
    return Trajectory(t=t, poses=poses, gripper=gripper, scene_path=traj.scene_path, scene_name=traj.scene_name,
                      parameters=dict(traj.parameters), prediction=dict(traj.prediction), provenance=prov)


class DeploySchedule:
    """Commands on a fixed grid of the robot's clock.

    Tick ``k`` is due at ``t0 + k / rate`` and commands the trajectory at time ``k / (rate * time_scale)``
    (trajectory seconds); the last tick is the first at or after the trajectory's end.

    Args:
        traj: the (checked) trajectory.
        t0: clock reading at which the motion starts, s.
        rate: command rate, Hz (> 0).
        time_scale: factor on the trajectory's times (> 0).

    Raises:
        ConfigError: rate or time_scale not finite and > 0.
    """

    def __init__(self, traj: Trajectory, t0: float, rate: float, time_scale: float = 1.0) -> None:
        if not (math.isfinite(rate) and rate > 0) or not (math.isfinite(time_scale) and time_scale > 0):
            raise ConfigError(f"rate and time_scale must be finite and > 0, got {rate}, {time_scale}")
        self.traj = traj
        self.t0 = float(t0)
        self.period = 1.0 / float(rate)
        self.time_scale = float(time_scale)
        self.tick_count = int(math.ceil(traj.duration * time_scale / self.period - 1e-9)) + 1
        self.next_tick = 0
        self.lateness: list[float] = []

    @property
    def end(self) -> float:
        """Clock time of the last tick, s."""
        return self.t0 + (self.tick_count - 1) * self.period

    @property
    def finished(self) -> bool:
        """True once every tick was published."""
        return self.next_tick >= self.tick_count

    def progress(self) -> float:
        """Fraction of the ticks published (0..1)."""
        return self.next_tick / self.tick_count

    def due(self, now: float) -> tuple[int, dict[str, np.ndarray], dict[str, float]] | None:
        """The command due at clock reading ``now`` (s), or None.

        A tick is due from half a period before its time (a timer of the same period that fires a
        little early must not skip it). When several ticks are overdue (a stalled executor), the latest
        one is returned and the skipped ones are dropped (never a burst of stale commands); the
        signed difference ``now - tick time`` of the returned tick and of every skipped one (whose
        command is superseded now) is appended to :attr:`lateness`, one entry per tick.

        Returns:
            ``(tick, effector -> pose (7,), effector -> gripper opening m)``.
        """
        if self.finished:
            return None
        k = int(math.floor((now - self.t0) / self.period + 0.5))
        if k < self.next_tick:
            return None
        k = min(k, self.tick_count - 1)
        for j in range(self.next_tick, k + 1):  # skipped ticks are superseded now: their error counts
            self.lateness.append(now - (self.t0 + j * self.period))
        self.next_tick = k + 1
        tau = k * self.period / self.time_scale
        poses = {e: self.traj.sample_pose(e, tau) for e in self.traj.effectors}
        grippers = {e: self.traj.sample_gripper(e, tau) for e in self.traj.gripper}
        return k, poses, grippers


class SafetyMonitor:
    """Abort conditions checked on every measurement.

    Args:
        limits: the cell's limits (``wrench_limit``, ``pose_lag_tolerance``, ``pose_lag_window``).
    """

    def __init__(self, limits: DeployLimits) -> None:
        self.limits = limits
        self._commands: dict[str, deque[tuple[float, np.ndarray]]] = {}

    def commanded(self, effector: str, now: float, pose: np.ndarray) -> None:
        """Remember a command published at clock reading ``now`` (s)."""
        self._commands.setdefault(effector, deque()).append((float(now), np.asarray(pose[:3], float).copy()))

    def check_wrench(self, sensor: str, wrench: np.ndarray) -> str | None:
        """Reason to abort when the force norm of ``wrench`` ``[fx fy fz tx ty tz]`` (N) exceeds the limit."""
        force = float(np.linalg.norm(np.asarray(wrench, float)[:3]))
        if not math.isfinite(force) or force > self.limits.wrench_limit:
            return f"measured force {force:.4g} N on {sensor} exceeds wrench_limit {self.limits.wrench_limit:g} N"
        return None

    def check_pose(self, effector: str, now: float, measured: np.ndarray) -> str | None:
        """Reason to abort when the measured position is farther than the tolerance from every command
        of the last ``pose_lag_window`` s (None while there is no command yet)."""
        cmds = self._commands.get(effector)
        if not cmds:
            return None
        while len(cmds) > 1 and cmds[1][0] <= now - self.limits.pose_lag_window:
            cmds.popleft()  # keep the newest command older than the window: the one in force at its start
        p = np.asarray(measured, float)[:3]
        lag = min(float(np.linalg.norm(p - c)) for _, c in cmds)
        if not math.isfinite(lag) or lag > self.limits.pose_lag_tolerance:
            return (f"measured pose of {effector} lags the command by {lag * 1e3:.3g} mm (> pose_lag_tolerance "
                    f"{self.limits.pose_lag_tolerance * 1e3:g} mm over the last {self.limits.pose_lag_window:g} s)")
        return None


def trajectory_from_bag(path: str | Path, recording_map: str | Path | None = None) -> Trajectory:
    """The ``pose_cmd`` stream of a recording as a trajectory (times from its first command).

    Args:
        path: rosbag2 directory or ``.mcap`` file (read by :func:`sysid.bagio.open_bag`; the effector
            named by its ``scene.yaml``).
        recording_map: recording map of a real cell's bag (its command topic and link, carried to the
            effector frame in ``world``; docs/recording_map.md); None: the bag's ``recording.yaml``, else
            the INTERFACES.md topics.

    Raises:
        BagReadError: unreadable bag. ConfigError: no ``pose_cmd`` messages, or bad poses (named).
    """
    bag = open_bag(path, skip_roles=("image", "markers", "sheet_points", "wrench", "clock", "pose"),
                   recording_map=recording_map)
    series = bag.series.get("pose_cmd")
    if series is None or len(series) == 0:
        raise ConfigError(f"{path}: no pose_cmd messages to replay (topic {bag.roles['pose_cmd']})")
    effector = bag.roles["pose_cmd"].rstrip("/").split("/")[-2]
    if bag.recording_map is not None:  # a map's command topic is the controller's; the scene names the effector
        sensors = list(bag.scene.sensors.values()) if bag.scene is not None else []
        if len(sensors) != 1:
            raise ConfigError(f"{path}: a recording map's pose_cmd needs a scene.yaml with one tactile sensor (whose "
                              "effector it commands)")
        effector = sensors[0].effector
    t = (series.t_ns - series.t_ns[0]) * 1e-9
    traj = Trajectory(t=t, poses={effector: np.array(series.values, dtype=float)},
                      scene_path=str(bag.scene_path) if bag.scene_path else None,
                      scene_name=bag.scene.name if bag.scene is not None else "",
                      provenance={"tool": "bag replay", "bag": str(bag.path), "bag_sha256": bag.sha256})
    return validate_trajectory(traj, str(path))
