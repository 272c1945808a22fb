"""Validation and limiting of effector commands, free of rclpy (unit-testable without DDS).

The simulator node feeds every received command to a :class:`CommandArbiter` and asks it, once per
step, for the pose targets of the step. The rules (INTERFACES.md topics ``<effector>/pose_cmd``,
``twist_cmd``, ``gripper_cmd``):

- a pose with NaN/inf entries, a quaternion whose norm is off 1 by more than a tolerance, a frame
  other than ``world``, or a position outside the effector's declared workspace (an axis-aligned box
  in ``world``, :class:`Workspace`) is rejected with a reason string (the node logs it; the last
  valid command stays in force);
- a target farther than the per-step translation / rotation limit is approached at the limit
  (ThinShellLab's bounded SE(3) action, DESIGN.md "Boundaries"), and the arbiter reports that once
  per command;
- a twist is integrated into a pose target each step: ``p += v dt``, ``q = exp(w dt) * q`` (angular
  velocity in ``world``); a twist that would leave the workspace stops at its boundary (reported once);
- a command older than ``timeout`` (sim seconds since it was received) is stale: a pose target not
  yet reached and a twist are dropped and the effector holds its pose (the commander may have died);
- a command for an effector the scene does not have is rejected, naming the known effectors.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Mapping, NamedTuple

import numpy as np

from sim_core.effector import limit_pose_step
from sim_core.transforms import quat_from_rotvec, quat_multiply

COMMAND_SUFFIXES = ("pose_cmd", "twist_cmd", "gripper_cmd")
ACCEPTED_FRAMES = ("world", "")


@dataclass(frozen=True)
class Workspace:
    """Axis-aligned box of allowed effector positions in ``world``.

    Attributes:
        low: ``[x y z]`` lower corner, m, shape ``(3,)``.
        high: ``[x y z]`` upper corner, m, shape ``(3,)``; ``high > low`` on every axis.

    Raises:
        ValueError: corners not 3 finite numbers each, or not ``low < high``.
    """

    low: tuple[float, float, float]
    high: tuple[float, float, float]

    def __post_init__(self) -> None:
        low = np.asarray(self.low, dtype=float).reshape(-1)
        high = np.asarray(self.high, dtype=float).reshape(-1)
        if low.shape != (3,) or high.shape != (3,) or not (np.all(np.isfinite(low)) and np.all(np.isfinite(high))):
            raise ValueError(f"workspace corners must be 3 finite numbers each, got {self.low!r} and {self.high!r}")
        if np.any(high <= low):
            raise ValueError(f"workspace must have low < high on every axis, got low {low.tolist()}, high {high.tolist()}")
        object.__setattr__(self, "low", tuple(float(v) for v in low))
        object.__setattr__(self, "high", tuple(float(v) for v in high))

    def contains(self, position: np.ndarray) -> bool:
        """True when ``position`` ``(3,)`` (m) lies in the box (boundary included)."""
        p = np.asarray(position, dtype=float)
        return bool(np.all(p >= self.low) and np.all(p <= self.high))

    def clip(self, position: np.ndarray) -> np.ndarray:
        """``position`` ``(3,)`` clamped into the box."""
        return np.clip(np.asarray(position, dtype=float), self.low, self.high)

    def describe(self) -> str:
        """``[low] .. [high] m`` for messages."""
        return f"{list(self.low)} .. {list(self.high)} m"


@dataclass(frozen=True)
class CommandLimits:
    """Per-effector command limits.

    Attributes:
        max_translation_per_step: m per step (> 0).
        max_rotation_per_step: rad per step (> 0).
        timeout: s of sim time after which an unfinished command is stale; <= 0 disables.
        quaternion_tolerance: accepted ``| |q| - 1 |``.
        max_gripper_opening: m; openings outside ``[0, max]`` are rejected.
        workspace: allowed positions (:class:`Workspace`), or None for no box.
    """

    max_translation_per_step: float = 1e-3
    max_rotation_per_step: float = 0.02
    timeout: float = 1.0
    quaternion_tolerance: float = 1e-3
    max_gripper_opening: float = 0.2
    workspace: Workspace | None = None

    def __post_init__(self) -> None:
        for name in ("max_translation_per_step", "max_rotation_per_step", "quaternion_tolerance", "max_gripper_opening"):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise ValueError(f"CommandLimits.{name} must be finite and > 0, got {value}")
        if not np.isfinite(self.timeout):
            raise ValueError(f"CommandLimits.timeout must be finite, got {self.timeout}")


class CommandResult(NamedTuple):
    """Outcome of submitting one command: ``accepted`` and, when rejected, the ``reason``."""

    accepted: bool
    reason: str = ""


class StepTargets(NamedTuple):
    """What the arbiter commands for one step.

    Attributes:
        effector_pose_target: effector -> pose ``[x y z qx qy qz qw]`` for this step.
        gripper_target: effector -> opening in m (only effectors that received a gripper command).
        events: human-readable notices to log once (limit active, command stale).
    """

    effector_pose_target: dict[str, np.ndarray]
    gripper_target: dict[str, float]
    events: list[str]


# ------------------------------------------------------------------------------------- checks
def check_pose(pose: np.ndarray, frame_id: str = "world", quaternion_tolerance: float = 1e-3,
               workspace: Workspace | None = None) -> str | None:
    """Reason why a pose command is unusable, or None when it is fine.

    Args:
        pose: ``[x y z qx qy qz qw]``.
        frame_id: header frame; ``world`` (or empty, meaning world) is accepted.
        quaternion_tolerance: accepted deviation of the quaternion norm from 1.
        workspace: allowed positions, or None.
    """
    pose = np.asarray(pose, dtype=float).reshape(-1)
    if pose.shape != (7,):
        return f"pose must have 7 entries, got {pose.size}"
    if not np.all(np.isfinite(pose)):
        return f"pose has non-finite entries {pose.tolist()}"
    if frame_id not in ACCEPTED_FRAMES:
        return f"frame_id {frame_id!r} is not 'world'"
    norm = float(np.linalg.norm(pose[3:]))
    if abs(norm - 1.0) > quaternion_tolerance:
        return f"quaternion norm {norm:.6g} is not 1 (tolerance {quaternion_tolerance:g}; x y z w = {pose[3:].tolist()})"
    if workspace is not None and not workspace.contains(pose[:3]):
        return f"position {pose[:3].tolist()} m is outside the workspace {workspace.describe()}"
    return None


def check_twist(twist: np.ndarray, frame_id: str = "world") -> str | None:
    """Reason why a twist command ``[vx vy vz wx wy wz]`` is unusable, or None."""
    twist = np.asarray(twist, dtype=float).reshape(-1)
    if twist.shape != (6,):
        return f"twist must have 6 entries, got {twist.size}"
    if not np.all(np.isfinite(twist)):
        return f"twist has non-finite entries {twist.tolist()}"
    if frame_id not in ACCEPTED_FRAMES:
        return f"frame_id {frame_id!r} is not 'world'"
    return None


def check_gripper(opening: float, max_opening: float) -> str | None:
    """Reason why a gripper opening (m) is unusable, or None."""
    opening = float(opening)
    if not np.isfinite(opening):
        return f"gripper opening {opening} is not finite"
    if not 0.0 <= opening <= max_opening:
        return f"gripper opening {opening:g} m is outside [0, {max_opening:g}] m"
    return None


def integrate_twist(pose: np.ndarray, twist: np.ndarray, dt: float) -> np.ndarray:
    """Pose after moving with a constant world-frame twist for ``dt`` seconds.

    ``p' = p + v dt``, ``q' = exp(w dt) q`` (left multiplication: angular velocity in ``world``).

    Args:
        pose: ``[x y z qx qy qz qw]``.
        twist: ``[vx vy vz wx wy wz]`` in m/s and rad/s.
        dt: s.

    Returns:
        the new pose, shape ``(7,)``, unit quaternion.
    """
    pose = np.asarray(pose, dtype=float)
    twist = np.asarray(twist, dtype=float)
    q = quat_multiply(quat_from_rotvec(twist[3:] * dt), pose[3:])
    return np.concatenate([pose[:3] + twist[:3] * dt, q / np.linalg.norm(q)])


def split_command_topic(topic: str, namespace: str) -> tuple[str, str] | None:
    """``(effector, suffix)`` if ``topic`` is ``<namespace>/<effector>/<pose|twist|gripper>_cmd``, else None."""
    prefix = namespace.rstrip("/") + "/"
    if not topic.startswith(prefix):
        return None
    parts = topic[len(prefix):].split("/")
    if len(parts) == 2 and parts[1] in COMMAND_SUFFIXES and parts[0]:
        return parts[0], parts[1]
    return None


def unknown_effector_topics(topics: Iterable[str], namespace: str, effectors: Iterable[str]) -> list[tuple[str, str]]:
    """Command topics in ``namespace`` addressed to effectors the scene does not have.

    Returns:
        sorted ``(topic, effector)`` pairs.
    """
    known = set(effectors)
    found = []
    for topic in topics:
        split = split_command_topic(topic, namespace)
        if split is not None and split[0] not in known:
            found.append((topic, split[0]))
    return sorted(found)


# ------------------------------------------------------------------------------------- arbiter
@dataclass
class _EffectorCommand:
    limits: CommandLimits
    setpoint: np.ndarray | None = None
    kind: str | None = None  # "pose" | "twist" | None (hold)
    target: np.ndarray | None = None
    twist: np.ndarray | None = None
    received: float = 0.0
    gripper: float | None = None
    limit_reported: bool = False
    stale_reported: bool = False
    boundary_reported: bool = False


class CommandArbiter:
    """Latest valid command per effector -> rate-limited per-step targets.

    Args:
        limits: effector name -> :class:`CommandLimits` (the scene's effectors).
    """

    def __init__(self, limits: Mapping[str, CommandLimits]) -> None:
        if not limits:
            raise ValueError("CommandArbiter needs at least one effector")
        self._cmd = {name: _EffectorCommand(lim) for name, lim in limits.items()}

    @property
    def effector_names(self) -> list[str]:
        """Known effector names."""
        return list(self._cmd)

    def _lookup(self, effector: str) -> _EffectorCommand | CommandResult:
        if effector not in self._cmd:
            return CommandResult(False, f"unknown effector {effector!r} (known: {sorted(self._cmd)})")
        return self._cmd[effector]

    def submit_pose(self, effector: str, pose: np.ndarray, now: float, frame_id: str = "world") -> CommandResult:
        """Set a pose target received at sim time ``now`` (s); returns whether it was accepted and why not."""
        cmd = self._lookup(effector)
        if isinstance(cmd, CommandResult):
            return cmd
        reason = check_pose(pose, frame_id, cmd.limits.quaternion_tolerance, cmd.limits.workspace)
        if reason:
            return CommandResult(False, f"{effector}/pose_cmd rejected: {reason}")
        pose = np.asarray(pose, dtype=float).reshape(7).copy()
        pose[3:] /= np.linalg.norm(pose[3:])
        cmd.kind, cmd.target, cmd.twist, cmd.received = "pose", pose, None, float(now)
        cmd.limit_reported = cmd.stale_reported = cmd.boundary_reported = False
        return CommandResult(True)

    def submit_twist(self, effector: str, twist: np.ndarray, now: float, frame_id: str = "world") -> CommandResult:
        """Set a velocity command received at sim time ``now`` (s)."""
        cmd = self._lookup(effector)
        if isinstance(cmd, CommandResult):
            return cmd
        reason = check_twist(twist, frame_id)
        if reason:
            return CommandResult(False, f"{effector}/twist_cmd rejected: {reason}")
        cmd.kind, cmd.twist, cmd.target, cmd.received = "twist", np.asarray(twist, float).reshape(6).copy(), None, float(now)
        cmd.limit_reported = cmd.stale_reported = cmd.boundary_reported = False
        return CommandResult(True)

    def submit_gripper(self, effector: str, opening: float) -> CommandResult:
        """Set a finger opening target in m."""
        cmd = self._lookup(effector)
        if isinstance(cmd, CommandResult):
            return cmd
        reason = check_gripper(opening, cmd.limits.max_gripper_opening)
        if reason:
            return CommandResult(False, f"{effector}/gripper_cmd rejected: {reason}")
        cmd.gripper = float(opening)
        return CommandResult(True)

    def reset(self) -> None:
        """Forget every command and setpoint (after a simulation reset)."""
        for name, cmd in self._cmd.items():
            self._cmd[name] = _EffectorCommand(cmd.limits)

    def hold(self, effector: str | None = None) -> None:
        """Drop the active pose/twist command (of one effector, or all): the effectors hold their setpoint."""
        for name, cmd in self._cmd.items():
            if effector is None or name == effector:
                cmd.kind, cmd.target, cmd.twist = None, None, None

    def step_targets(self, now: float, dt: float, measured: Mapping[str, np.ndarray]) -> StepTargets:
        """Targets for the step that starts at sim time ``now``.

        Args:
            now: sim time in s.
            dt: step in s (twist integration).
            measured: effector -> current pose; initialises the setpoint of an effector the first time.

        Returns:
            :class:`StepTargets` with a pose target for every known effector.
        """
        poses, grippers, events = {}, {}, []
        for name, cmd in self._cmd.items():
            if cmd.setpoint is None:
                cmd.setpoint = np.asarray(measured[name], dtype=float).copy()
            lim = cmd.limits
            if cmd.kind is not None and lim.timeout > 0 and now - cmd.received > lim.timeout:
                unfinished = cmd.kind == "twist" or not np.allclose(cmd.setpoint, cmd.target, atol=1e-12)
                if unfinished and not cmd.stale_reported:
                    events.append(f"{name}: {cmd.kind} command is stale ({now - cmd.received:.3g} s old > timeout "
                                  f"{lim.timeout:g} s); holding position")
                    cmd.stale_reported = True
                cmd.kind = None
            if cmd.kind is not None:
                goal = cmd.target if cmd.kind == "pose" else integrate_twist(cmd.setpoint, cmd.twist, dt)
                ws = lim.workspace
                if ws is not None and not ws.contains(goal[:3]):
                    goal = np.concatenate([ws.clip(goal[:3]), goal[3:]])
                    if not cmd.boundary_reported:
                        events.append(f"{name}: twist command reaches the workspace boundary {ws.describe()}; stopped there")
                        cmd.boundary_reported = True
                new, limited = limit_pose_step(cmd.setpoint, goal, lim.max_translation_per_step, lim.max_rotation_per_step)
                if limited and not cmd.limit_reported:
                    dist = float(np.linalg.norm(goal[:3] - cmd.setpoint[:3]))
                    events.append(f"{name}: {cmd.kind} command exceeds the per-step limit ({dist:.4g} m away); approaching at "
                                  f"{lim.max_translation_per_step:g} m and {lim.max_rotation_per_step:g} rad per step")
                    cmd.limit_reported = True
                cmd.setpoint = new
            poses[name] = cmd.setpoint.copy()
            if cmd.gripper is not None:
                grippers[name] = cmd.gripper
        return StepTargets(poses, grippers, events)
