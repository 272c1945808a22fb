"""A real cell's side of the deploy node, free of rclpy: frames, command interfaces, wrench guard, abort.

- :class:`CellFrames`: where thinshell's ``world`` sits in the robot's base frame and where the tactile
  sensor sits on the robot's tool link; turns an effector pose in ``world`` (what a trajectory holds)
  into the pose of the tool link in the base frame (what a Cartesian controller's target takes) and back.
- :func:`servo_twist`: the twist command of the ``twist`` interface (feed-forward from the trajectory's
  finite differences plus a proportional pose-error term, limited).
- :func:`wrench_in_sensor`, :class:`WrenchTare`, :class:`WrenchGuard`: a measured wrench carried into
  the sensor frame (moment moved with the lever arm), its tare, and the normal / shear / torque limits.
- :class:`Watchdog`: the age of the newest message of every monitored stream.
- :class:`RetractPlan`: the lift along the sensor normal after an abort, inside the workspace.

Frames (poses ``[x y z qx qy qz qw]``, ``T_a_b`` = frame ``b`` in frame ``a``)::

    T_base_tool = T_base_world . T_world_effector . T_effector_sensor . T_tool_sensor^-1

with ``T_base_world`` = ``world_in_base``, ``T_effector_sensor`` = the scene's ``sensors.<name>.mount``
and ``T_tool_sensor`` = ``sensor_in_tool`` (deploy node parameters).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from sim_core.errors import ConfigError
from sim_core.transforms import (compose_poses, matrix_to_pose, pose_to_matrix, quat_from_rotvec, quat_multiply,
                                 quat_normalize, quat_to_matrix, quat_to_rotvec)
from thinshell_ros.commands import Workspace

COMMAND_INTERFACES = ("thinshell", "pose_target", "twist")
ABORT_ACTIONS = ("hold", "retract")
IDENTITY = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
_CONJ = np.array([-1.0, -1.0, -1.0, 1.0])


def checked_pose(value: Sequence[float], name: str) -> np.ndarray:
    """A parameter's pose ``[x y z qx qy qz qw]`` (m, unit quaternion) as ``(7,)``, quaternion normalised.

    Raises:
        ConfigError: not 7 finite numbers or a quaternion whose norm is off 1 by more than 1e-3, naming ``name``.
    """
    p = np.asarray(list(value), dtype=float).reshape(-1)
    if p.shape != (7,) or not np.all(np.isfinite(p)):
        raise ConfigError(f"parameter {name!r} must be 7 finite numbers [x, y, z, qx, qy, qz, qw] (m, unit "
                          f"quaternion), got {list(value)!r}")
    return np.concatenate([p[:3], quat_normalize(p[3:], f"parameter {name!r}")])


def invert_pose(pose: np.ndarray) -> np.ndarray:
    """The inverse transform of ``pose`` ``(7,)``."""
    return matrix_to_pose(np.linalg.inv(pose_to_matrix(pose)))


@dataclass(frozen=True)
class CellFrames:
    """The cell's fixed transforms (deploy node parameters).

    Attributes:
        world_frame: name of thinshell's ``world`` on the cell (frame_id of ``thinshell`` commands and of
            measured effector poses).
        base_frame: the robot's base frame (frame_id of ``pose_target`` and ``twist`` commands).
        tool_link: the link the controller moves (FZI ``end_effector_link``, MoveIt Servo ``ee_frame``).
        world_in_base: ``T_base_world``, pose of ``world`` in the base frame, ``(7,)``.
        sensor_in_tool: ``T_tool_sensor``, pose of the tactile sensor frame in the tool link, ``(7,)``.
        sensor_mount: ``T_effector_sensor``, the scene's mount of the sensor on its effector, ``(7,)``.
    """

    world_frame: str = "world"
    base_frame: str = "base_link"
    tool_link: str = "tool0"
    world_in_base: np.ndarray = field(default_factory=lambda: np.array(IDENTITY))
    sensor_in_tool: np.ndarray = field(default_factory=lambda: np.array(IDENTITY))
    sensor_mount: np.ndarray = field(default_factory=lambda: np.array(IDENTITY))

    def __post_init__(self) -> None:
        for name in ("world_frame", "base_frame", "tool_link"):
            if not getattr(self, name) or any(c.isspace() for c in getattr(self, name)):
                raise ConfigError(f"parameter {name!r} must be a frame name without spaces, got {getattr(self, name)!r}")
        for name in ("world_in_base", "sensor_in_tool", "sensor_mount"):
            object.__setattr__(self, name, checked_pose(getattr(self, name), name))
        # T_effector_tool = T_effector_sensor . T_tool_sensor^-1
        object.__setattr__(self, "_effector_tool", compose_poses(self.sensor_mount, invert_pose(self.sensor_in_tool)))

    def tool_in_base(self, effector_in_world: np.ndarray) -> np.ndarray:
        """``T_base_tool`` of an effector pose in ``world`` ``(7,)`` (the module's chain)."""
        return compose_poses(compose_poses(self.world_in_base, effector_in_world), self._effector_tool)

    def effector_in_world(self, tool_in_base: np.ndarray) -> np.ndarray:
        """The inverse of :meth:`tool_in_base`: ``T_world_effector`` of the tool link's pose in the base frame."""
        return compose_poses(compose_poses(invert_pose(self.world_in_base), tool_in_base),
                             invert_pose(self._effector_tool))

    def sensor_normal_in_world(self, effector_in_world: np.ndarray) -> np.ndarray:
        """Unit z axis of the sensor frame in ``world`` ``(3,)`` (points from the gel into what it touches)."""
        sensor = compose_poses(effector_in_world, self.sensor_mount)
        return quat_to_matrix(sensor[3:])[:, 2]

    def vector_to_base(self, v_world: np.ndarray) -> np.ndarray:
        """A free vector ``(3,)`` of ``world`` expressed in the base frame."""
        return quat_to_matrix(self.world_in_base[3:]) @ np.asarray(v_world, float)


def servo_twist(target: np.ndarray, target_next: np.ndarray, dt: float, measured: np.ndarray | None, gain: float,
                max_linear_speed: float, max_angular_speed: float) -> np.ndarray:
    """Twist ``[vx vy vz wx wy wz]`` (m/s, rad/s) that moves a frame along a pose trajectory.

    ``v = (p(t+dt) - p(t)) / dt + gain (p(t) - p_meas)``,
    ``w = rotvec(q(t+dt) q(t)^-1) / dt + gain rotvec(q(t) q_meas^-1)``, every pose in one frame (the
    twist is in that frame: angular velocity about its axes, linear velocity of the moving frame's
    origin); each part scaled down to its speed limit when above it.

    Args:
        target, target_next: the frame's poses at the command's time and one period later, ``(7,)``.
        dt: the period, s (> 0).
        measured: the frame's measured pose ``(7,)``, or None (no feedback term).
        gain: proportional gain, 1/s (>= 0).
        max_linear_speed: m/s; max_angular_speed: rad/s.
    """
    target, target_next = np.asarray(target, float), np.asarray(target_next, float)
    v = (target_next[:3] - target[:3]) / dt
    w = quat_to_rotvec(quat_multiply(target_next[3:], target[3:] * _CONJ)) / dt
    if measured is not None:
        measured = np.asarray(measured, float)
        v = v + gain * (target[:3] - measured[:3])
        w = w + gain * quat_to_rotvec(quat_multiply(target[3:], measured[3:] * _CONJ))
    for part, limit in ((v, max_linear_speed), (w, max_angular_speed)):
        n = float(np.linalg.norm(part))
        if n > limit:
            part *= limit / n
    return np.concatenate([v, w])


def wrench_in_sensor(wrench: np.ndarray, ft_in_sensor: np.ndarray) -> np.ndarray:
    """A wrench measured in an F/T frame, carried to the sensor frame.

    ``f_s = R f``, ``tau_s = R tau + p x f_s`` with ``(p, R)`` the F/T frame's pose in the sensor frame
    (the moment about the sensor frame's origin).

    Args:
        wrench: ``[fx fy fz tx ty tz]`` (N, N*m) in the F/T frame.
        ft_in_sensor: the F/T frame's pose in the sensor frame ``(7,)``.
    """
    wrench, ft_in_sensor = np.asarray(wrench, float), np.asarray(ft_in_sensor, float)
    R = quat_to_matrix(ft_in_sensor[3:])
    f = R @ wrench[:3]
    return np.concatenate([f, R @ wrench[3:] + np.cross(ft_in_sensor[:3], f)])


class WrenchTare:
    """Mean of a wrench stream over a window, subtracted afterwards (the sensor's offset out of contact).

    Args:
        max_offset: N; a tare whose force exceeds it is refused (the gel is in contact, or the sensor is off).
    """

    def __init__(self, max_offset: float) -> None:
        self.max_offset = float(max_offset)
        self._samples: dict[str, list[np.ndarray]] = {}
        self.offset: dict[str, np.ndarray] = {}

    def add(self, topic: str, wrench: np.ndarray) -> None:
        """One sample ``(6,)`` of ``topic`` inside the window."""
        self._samples.setdefault(topic, []).append(np.asarray(wrench, float).copy())

    def finish(self, topics: Sequence[str]) -> dict[str, np.ndarray]:
        """Fix the offsets ``topic -> (6,)`` from the samples taken.

        Raises:
            ConfigError: a topic without a sample, non-finite samples, or an offset force above ``max_offset``.
        """
        for topic in topics:
            samples = self._samples.get(topic)
            if not samples:
                raise ConfigError(f"wrench tare: no sample on {topic} within the tare window")
            mean = np.mean(samples, axis=0)
            force = float(np.linalg.norm(mean[:3]))
            if not np.all(np.isfinite(mean)) or force > self.max_offset:
                raise ConfigError(f"wrench tare: mean force {force:.4g} N on {topic} over {len(samples)} samples exceeds "
                                  f"tare_max_force {self.max_offset:g} N (in contact before the start, or a sensor "
                                  "offset to correct first)")
            self.offset[topic] = mean
        return self.offset

    def apply(self, topic: str, wrench: np.ndarray) -> np.ndarray:
        """``wrench`` minus the topic's offset (unchanged before :meth:`finish`)."""
        off = self.offset.get(topic)
        return np.asarray(wrench, float) if off is None else np.asarray(wrench, float) - off


@dataclass(frozen=True)
class WrenchGuard:
    """Force and torque limits on a wrench in the sensor frame (``inf``: that limit is off).

    Attributes:
        force_norm: N, on ``|f|``; normal_force: N, on ``|f_z|`` (along the sensor normal);
        shear_force: N, on ``sqrt(f_x^2 + f_y^2)``; torque: N*m, on ``|tau|`` about the sensor origin.

    Raises:
        ConfigError: a limit that is not > 0 (``inf`` allowed).
    """

    force_norm: float = 20.0
    normal_force: float = math.inf
    shear_force: float = math.inf
    torque: float = math.inf

    def __post_init__(self) -> None:
        for name in ("force_norm", "normal_force", "shear_force", "torque"):
            value = getattr(self, name)
            if math.isnan(value) or value <= 0:
                raise ConfigError(f"wrench limit {name} must be > 0, got {value}")

    def _figures(self, wrench: np.ndarray) -> tuple[tuple[str, float, float, str, str], ...]:
        w = np.asarray(wrench, float)
        return (("force", float(np.linalg.norm(w[:3])), self.force_norm, "wrench_limit", "N"),
                ("normal force", abs(float(w[2])), self.normal_force, "normal_force_limit", "N"),
                ("shear force", float(np.hypot(w[0], w[1])), self.shear_force, "shear_force_limit", "N"),
                ("torque", float(np.linalg.norm(w[3:6])), self.torque, "torque_limit", "N*m"))

    def margins(self, wrench: np.ndarray) -> dict[str, float]:
        """Parameter name -> limit minus the measured value (N or N*m) of every limit that is on."""
        return {name: limit - value for _, value, limit, name, _ in self._figures(wrench) if math.isfinite(limit)}

    def check(self, topic: str, wrench: np.ndarray) -> str | None:
        """Reason to abort when ``wrench`` ``[fx fy fz tx ty tz]`` (sensor frame) breaks a limit, else None."""
        for what, value, limit, name, unit in self._figures(wrench):
            if not math.isfinite(value) or value > limit:
                return f"measured {what} {value:.4g} {unit} on {topic} exceeds {name} {limit:g} {unit}"
        return None


class Watchdog:
    """The newest message's arrival per stream, on the robot's clock and on a steady clock.

    A stream is stale when its newest message is older than the timeout on both clocks: on a cell the
    robot's clock is wall time and the two agree; in simulation (``/clock``) a simulator slower than
    real time is not taken for a dead sensor (robot clock), nor a jump of ``/clock`` taken before the
    messages queued behind it (steady clock).

    Args:
        timeout: s; a stream whose newest message is older than this is stale.
    """

    def __init__(self, timeout: float) -> None:
        if not (math.isfinite(timeout) and timeout > 0):
            raise ConfigError(f"sensor_timeout must be finite and > 0, got {timeout}")
        self.timeout = float(timeout)
        self.last: dict[str, float] = {}
        self._last_steady: dict[str, float] = {}
        self._resumed = -math.inf

    def seen(self, stream: str, now: float, steady: float | None = None) -> None:
        """A message of ``stream`` arrived at robot clock reading ``now`` and steady clock reading ``steady`` (s;
        default: ``now``)."""
        self.last[stream] = float(now)
        self._last_steady[stream] = float(now if steady is None else steady)

    def resumed(self, steady: float) -> None:
        """The watching process itself stalled until steady clock reading ``steady`` (s): the steady ages count
        from there (what arrived meanwhile may still wait in its queue, what was not sent could not be)."""
        self._resumed = float(steady)

    def stale(self, streams: Sequence[str], now: float, steady: float | None = None) -> str | None:
        """Reason to abort when a stream of ``streams`` has no message, or its newest is older than the timeout on
        the robot's clock (``now``) and on the steady clock (``steady``, default ``now``; counted from the last
        :meth:`resumed` at most)."""
        steady = now if steady is None else steady
        for s in streams:
            t = self.last.get(s)
            if t is None:
                return f"no message on {s} (sensor_timeout {self.timeout:g} s)"
            if now - t > self.timeout and steady - max(self._last_steady[s], self._resumed) > self.timeout:
                return f"the newest message on {s} is {now - t:.3g} s old (> sensor_timeout {self.timeout:g} s)"
        return None


class RetractPlan:
    """A straight lift from a start pose at constant speed, orientation held.

    ``p(t) = p0 + d min(speed (t - t0), reach)``, with ``reach`` the planned distance shortened to
    stay inside the workspace.

    Args:
        start: effector pose in ``world`` at the abort ``(7,)``.
        direction: unit vector in ``world`` ``(3,)`` (minus the sensor normal: away from what it touches).
        speed: m/s (> 0).
        distance: m (>= 0).
        t0: clock reading of the abort, s.
        workspace: the allowed positions, or None.
    """

    def __init__(self, start: np.ndarray, direction: np.ndarray, speed: float, distance: float, t0: float,
                 workspace: Workspace | None = None) -> None:
        self.start = np.asarray(start, float).copy()
        self.direction = np.asarray(direction, float) / np.linalg.norm(direction)
        self.speed, self.t0 = float(speed), float(t0)
        reach = float(distance)
        if workspace is not None:
            p0 = workspace.clip(self.start[:3])
            for axis in range(3):
                d = self.direction[axis]
                if d > 1e-12:
                    reach = min(reach, (workspace.high[axis] - p0[axis]) / d)
                elif d < -1e-12:
                    reach = min(reach, (workspace.low[axis] - p0[axis]) / d)
        self.reach = max(0.0, reach)

    @property
    def duration(self) -> float:
        """s from the abort to the end of the lift."""
        return self.reach / self.speed

    def pose(self, now: float) -> np.ndarray:
        """Effector pose in ``world`` ``(7,)`` at clock reading ``now``."""
        s = min(max(0.0, now - self.t0) * self.speed, self.reach)
        return np.concatenate([self.start[:3] + s * self.direction, self.start[3:]])

    def velocity(self, now: float) -> np.ndarray:
        """Linear velocity in ``world`` ``(3,)`` at ``now`` (zero once lifted)."""
        return self.direction * self.speed if now - self.t0 < self.duration else np.zeros(3)


def scene_mount(scene_path: str | None) -> tuple[np.ndarray, str]:
    """The mount of the scene's first tactile sensor ``(7,)`` and where it came from.

    Args:
        scene_path: the trajectory's scene file (a version-1 scene or a task scene), or None.

    Raises:
        ConfigError: a missing or unreadable scene file (named).
    """
    if not scene_path:
        return np.array(IDENTITY), "identity (the trajectory names no scene)"
    from sim_core.scenes.task_file import load_any_scene_file

    scene = load_any_scene_file(scene_path)
    for name, spec in scene.sensors.items():
        if spec.mount is not None:
            return checked_pose(spec.mount, f"{scene_path}: sensors.{name}.mount"), f"{scene_path}: sensors.{name}.mount"
        return np.array(IDENTITY), f"{scene_path}: sensors.{name} (no mount: identity)"
    return np.array(IDENTITY), f"identity ({scene_path} has no tactile sensor)"


def integrate_twist_in_frame(pose: np.ndarray, twist: np.ndarray, dt: float) -> np.ndarray:
    """Pose ``(7,)`` after a constant twist ``[v w]`` in the pose's parent frame for ``dt`` s (``q' = exp(w dt) q``)."""
    q = quat_multiply(quat_from_rotvec(np.asarray(twist[3:], float) * dt), np.asarray(pose[3:], float))
    return np.concatenate([np.asarray(pose[:3], float) + np.asarray(twist[:3], float) * dt, q / np.linalg.norm(q)])
