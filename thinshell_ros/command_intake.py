"""The sim node's intake of commands, cheap under bursts: batched pose checks and throttled error lines.

A node on a real network gets bursts (issue 50 item 7: 7.3k pose commands/s, a fifth of them bad).
The sim node therefore does not check and log each pose command as it arrives; it takes it as CDR
bytes (a raw subscription: no Python message is built, the bytes are what it records), reads the
header frame and the pose out of them (:func:`pose_from_cdr`), queues them (:class:`PoseBatch`, one
per effector), and
before a step, or once it has drained its subscriptions, checks the whole batch at once
(:func:`pose_rejections`, vectorised over the batch: the same rules and precedence as
:func:`thinshell_ros.commands.check_pose`) and submits only the newest valid one (earlier ones would be
overwritten by it before any step reads them). Every command is still checked and counted; each
rejected one is reported through an :class:`ErrorThrottle`: one line per kind per period, carrying
the count of the lines it stood for. :class:`CommandIntake` puts these together for the node's
command topics (free of rclpy: the node hands it the messages it takes).
"""

from __future__ import annotations

import struct
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from thinshell_ros import conversions as cv
from thinshell_ros.commands import ACCEPTED_FRAMES, CommandArbiter, CommandLimits, Workspace, check_pose

POSE_REJECTION_KINDS = ("valid", "non_finite", "frame", "quaternion", "workspace")
"""Codes of :func:`pose_rejections` (index = code), in :func:`~thinshell_ros.commands.check_pose`'s order."""


PoseTuple = tuple[float, float, float, float, float, float, float]


def pose_from_cdr(cdr: bytes) -> tuple[PoseTuple, str]:
    """``((x, y, z, qx, qy, qz, qw), frame_id)`` of a serialised ``geometry_msgs/PoseStamped``.

    The layout of the OMG CDR (XCDR1) encoding rclpy serialises to: a 4-byte encapsulation header
    (byte 1: 1 little endian, 0 big endian), then, aligned from the byte after it, ``stamp.sec``
    (int32), ``stamp.nanosec`` (uint32), ``frame_id`` (uint32 length with the terminating NUL, the
    bytes), padding to 8 and the 7 float64 of the pose.

    Raises:
        ValueError: fewer bytes than the layout needs, or an encapsulation other than plain CDR.
    """
    if len(cdr) < 16 or cdr[0] != 0 or cdr[1] not in (0, 1):
        raise ValueError(f"not a plain CDR PoseStamped ({len(cdr)} bytes, header {bytes(cdr[:4]).hex()})")
    order = "<" if cdr[1] == 1 else ">"
    (length,) = struct.unpack_from(order + "I", cdr, 12)
    offset = 4 + ((12 + length + 7) & ~7)
    if length < 1 or len(cdr) < offset + 56:
        raise ValueError(f"PoseStamped of {len(cdr)} bytes is too short for a frame_id of {length} bytes and a pose")
    frame = bytes(cdr[16:16 + length - 1]).decode("utf-8", errors="replace")
    return struct.unpack_from(order + "7d", cdr, offset), frame


def pose_rejections(poses: np.ndarray, frames: Sequence[str], quaternion_tolerance: float = 1e-3,
                    workspace: Workspace | None = None, accepted_frames: Sequence[str] = ACCEPTED_FRAMES) -> np.ndarray:
    """Why each pose command of a batch is unusable, as codes into :data:`POSE_REJECTION_KINDS`.

    The rules of :func:`thinshell_ros.commands.check_pose`, evaluated for the whole batch at once, and
    the first failing rule names the code: a non-finite entry, a frame other than ``world`` (or
    empty), a quaternion norm off 1 by more than ``quaternion_tolerance``, a position outside
    ``workspace`` (boundary included).

    Args:
        poses: ``[x y z qx qy qz qw]`` per command, shape ``(n, 7)``.
        frames: the header ``frame_id`` per command, length ``n``.
        quaternion_tolerance: accepted ``| |q| - 1 |``.
        workspace: allowed positions (m in ``world``), or None.
        accepted_frames: the header frames meaning ``world``.

    Returns:
        int codes, shape ``(n,)``; 0: valid.

    Raises:
        ValueError: ``poses`` not ``(n, 7)`` or ``frames`` not of length ``n``.
    """
    poses = np.asarray(poses, dtype=float)
    if poses.ndim != 2 or poses.shape[1] != 7 or len(frames) != poses.shape[0]:
        raise ValueError(f"pose batch must be (n, 7) with n frames, got {poses.shape} and {len(frames)} frames")
    codes = np.zeros(poses.shape[0], dtype=np.int8)
    if workspace is not None:
        inside = np.all((poses[:, :3] >= workspace.low) & (poses[:, :3] <= workspace.high), axis=1)
        codes[~inside] = 4
    with np.errstate(invalid="ignore", over="ignore"):
        norm = np.sqrt(np.einsum("ij,ij->i", poses[:, 3:], poses[:, 3:]))
        codes[~(np.abs(norm - 1.0) <= quaternion_tolerance)] = 3
    accepted = frozenset(accepted_frames)
    codes[np.fromiter((f not in accepted for f in frames), dtype=bool, count=len(frames))] = 2
    codes[~np.all(np.isfinite(poses), axis=1)] = 1
    return codes


class PoseBatch:
    """The pose commands of one effector received since its last check (arrival order).

    Attributes:
        received: sim time (s) of the newest command's arrival.
    """

    def __init__(self) -> None:
        self._poses: list[PoseTuple] = []
        self._frames: list[str] = []
        self.received = 0.0

    def __len__(self) -> int:
        return len(self._poses)

    def add(self, pose: PoseTuple, frame_id: str, now: float) -> None:
        """Queue ``pose`` ``(x, y, z, qx, qy, qz, qw)`` received in ``frame_id`` at sim time ``now`` (s)."""
        self._poses.append(pose)
        self._frames.append(frame_id)
        self.received = now

    def take(self) -> tuple[np.ndarray, list[str]]:
        """The queued commands, ``(poses (n, 7), frames)``, and an empty batch."""
        poses = np.array(self._poses, dtype=float).reshape(-1, 7)
        frames = self._frames
        self._poses, self._frames = [], []
        return poses, frames


class ErrorThrottle:
    """At most one error line per kind per ``period`` s, each carrying the count of the lines it stands for.

    The first line of a kind is logged at once; later ones of that kind within ``period`` are
    counted and held back (the newest kept); the next one after the period, or :meth:`flush` once
    the period has passed, logs the newest held-back line with ``(N of this kind in the last T s)``.

    Args:
        period: s of ``clock`` time between two lines of one kind (> 0).
        clock: the clock, s (``time.monotonic`` in the node).
    """

    def __init__(self, period: float, clock: Callable[[], float]) -> None:
        if not np.isfinite(period) or period <= 0:
            raise ValueError(f"ErrorThrottle.period must be finite and > 0 s, got {period}")
        self.period = float(period)
        self._clock = clock
        self._kinds: dict[str, list] = {}  # kind -> [t of the last line, held-back count, newest held-back line]
        self.lines = 0
        self.reported: dict[str, int] = {}

    def report(self, kind: str, line: str, count: int = 1) -> str | None:
        """Count ``count`` errors of ``kind`` (``line`` the newest); returns the line to log now, or None."""
        now = self._clock()
        self.reported[kind] = self.reported.get(kind, 0) + count
        state = self._kinds.get(kind)
        if state is None or now - state[0] >= self.period:
            held = state[1] if state is not None else 0
            since = now - state[0] if state is not None else 0.0
            self._kinds[kind] = [now, 0, ""]
            return self._line(line, held + count, since)
        state[1] += count
        state[2] = line
        return None

    def flush(self) -> list[str]:
        """Lines for the kinds whose held-back errors are a period old (call it periodically)."""
        now = self._clock()
        out = []
        for state in self._kinds.values():
            if state[1] and now - state[0] >= self.period:
                out.append(self._line(state[2], state[1], now - state[0]))
                state[:] = [now, 0, ""]
        return out

    def _line(self, line: str, count: int, since: float) -> str:
        self.lines += 1
        if count <= 1:
            return line
        return f"{line} ({count} of this kind " + (f"in the last {since:.2g} s)" if since > 0 else "at once)")


class CommandIntake:
    """The sim node's command topics: each message recorded, checked and submitted to the arbiter,
    each rejection counted and reported through an :class:`ErrorThrottle`.

    Pose commands (CDR bytes, :meth:`on_pose`) are queued per effector and checked as a batch by
    :meth:`submit_poses` (the node calls :meth:`submit_all` once it has taken every queued message,
    and before each step); twist and gripper commands (rclpy messages) are checked one by one, a
    twist after the pose commands queued before it.

    Args:
        arbiter: the node's :class:`~thinshell_ros.commands.CommandArbiter`.
        limits: effector -> its :class:`~thinshell_ros.commands.CommandLimits` (the arbiter's).
        sim_time: the simulation's time now, s (when a command is taken).
        record: ``(effector, suffix, message or CDR bytes) -> None``: records a taken command.
        log_error: logs one error line.
        throttle: the node's error throttle.
    """

    def __init__(self, arbiter: CommandArbiter, limits: Mapping[str, CommandLimits], sim_time: Callable[[], float],
                 record: Callable[[str, str, Any], None], log_error: Callable[[str], None],
                 throttle: ErrorThrottle) -> None:
        self.arbiter, self.limits = arbiter, dict(limits)
        self._sim_time, self._record, self._log_error, self.throttle = sim_time, record, log_error, throttle
        self._batches = {e: PoseBatch() for e in self.limits}
        self.rejected_commands = 0
        self.rejected_by_kind: dict[str, int] = {}

    def reject(self, kind: str, reason: str, count: int = 1) -> None:
        """Count ``count`` rejected commands of ``kind`` (``<effector>/<suffix> <why>``) and report
        ``reason`` (the newest one's) through the throttle."""
        self.rejected_commands += count
        self.rejected_by_kind[kind] = self.rejected_by_kind.get(kind, 0) + count
        line = self.throttle.report(kind, reason, count)
        if line is not None:
            self._log_error(line)

    def handler(self, effector: str, suffix: str) -> Callable[[Any], None]:
        """The handler of ``<effector>/<suffix>`` (``pose_cmd``: CDR bytes; ``twist_cmd``, ``gripper_cmd``:
        rclpy messages); it never raises."""
        handle = {"pose_cmd": self._on_pose, "twist_cmd": self._on_twist, "gripper_cmd": self._on_gripper}[suffix]

        def on_message(msg: Any) -> None:
            try:
                self._record(effector, suffix, msg)
                handle(effector, msg)
            except Exception as err:  # noqa: BLE001 - never die on input
                self.reject(f"{effector}/{suffix} unusable", f"{effector}/{suffix}: unusable message: {err}")
        return on_message

    def _on_pose(self, effector: str, cdr: bytes) -> None:
        pose, frame = pose_from_cdr(cdr)
        self._batches[effector].add(pose, frame, self._sim_time())

    def _on_twist(self, effector: str, msg: Any) -> None:
        self.submit_poses(effector)  # the pose commands that came before it first
        res = self.arbiter.submit_twist(effector, cv.twist_from_msg(msg)[1], self._sim_time(), msg.header.frame_id)
        if not res.accepted:
            self.reject(f"{effector}/twist_cmd invalid", res.reason)

    def _on_gripper(self, effector: str, msg: Any) -> None:
        res = self.arbiter.submit_gripper(effector, msg.data)
        if not res.accepted:
            self.reject(f"{effector}/gripper_cmd invalid", res.reason)

    def submit_poses(self, effector: str) -> None:
        """Check the effector's queued pose commands at once (:func:`pose_rejections`), count and report
        the rejected ones (one throttled line per kind, the newest one's reason as
        :func:`~thinshell_ros.commands.check_pose` words it) and submit the newest valid one to the
        arbiter (the earlier ones would be replaced by it before any step reads them)."""
        batch = self._batches[effector]
        if not len(batch):
            return
        received = batch.received
        poses, frames = batch.take()
        lim = self.limits[effector]
        codes = pose_rejections(poses, frames, lim.quaternion_tolerance, lim.workspace)
        for code in np.unique(codes[codes > 0]):
            where = np.flatnonzero(codes == code)
            i = int(where[-1])
            reason = check_pose(poses[i], frames[i], lim.quaternion_tolerance, lim.workspace)
            self.reject(f"{effector}/pose_cmd {POSE_REJECTION_KINDS[code]}", f"{effector}/pose_cmd rejected: {reason}",
                        len(where))
        valid = np.flatnonzero(codes == 0)
        if valid.size:
            res = self.arbiter.submit_pose(effector, poses[valid[-1]], received, frames[valid[-1]])
            if not res.accepted:
                self.reject(f"{effector}/pose_cmd invalid", res.reason)

    def submit_all(self) -> None:
        """:meth:`submit_poses` for every effector."""
        for effector in self._batches:
            self.submit_poses(effector)
