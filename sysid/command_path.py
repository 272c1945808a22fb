"""The path along which the effector was commanded, as a robot took its commands, and the replay step it needs.

A recording's ``pose_cmd`` channel carries each command's header stamp (when the commander meant it for) and, in
``Evidence.pose_cmd_taken``, its log time (when the robot took it). A robot that steps faster than its commander, or
back to back without waiting for it (the sim node in ``fast`` mode on a loaded machine), takes a command a step or
more after its header stamp, several at once when it falls behind; its path is then a staircase of the commands held
from their log times, which the commands interpolated between their header stamps miss by a step's travel.
:func:`commanded_path` reads the commands the way the effector followed them (the score stage's replay,
:func:`sysid.diagnose.noise.denoise_controls`); :func:`anchor_path` takes that reading for the drive's calibration
(:func:`sysid.drive_calibration.fit_drive`) and anchor (``ObservationModel.commands``) where the recording holds the
robot's timing (commands logged after their header stamps). :func:`replay_step` is the
simulation step at which a replay follows such a path: a replay steps the effector linearly from one step end to the
next, so a held path that jumps inside a replay step is replayed at the robot's own step.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from sysid.evidence import resample_pose
from sysid.replay_time import held as zero_order_hold


def commanded_path(ev: Any, at_ns: np.ndarray | None = None) -> tuple[np.ndarray, bool]:
    """The commanded pose at each of ``at_ns`` (default the ``pose`` stamps), as the effector was commanded.

    Two readings of the recorded commands:

    - held: a robot that takes a command between two steps (logged then: ``Evidence.pose_cmd_taken``)
      reaches it at the end of the next step, so the pose stamped ``t`` follows the last command taken
      at or before ``t - T/2`` (``T`` the pose stream's median period, the robot's step; the stamps rounded
      to the ns), and its recorded start pose before the first command (zero-order hold, as a task scene's
      replay holds its commands, ``sysid.observation``);
    - interpolated: the commands' header stamps, linearly (a robot that tracks a continuous reference).

    The reading whose tracking error ``pose - command`` at the pose stamps has the smaller energy over the
    positions is taken: on the sim node's own recordings the held one is exact (the error is the pose noise
    alone), whatever the commander's timing; where the log times say nothing of when the robot took a command
    (a recorder that logs on arrival), the interpolation is kept. The rule reads a kinematic arm's timing (the
    score stage's premise); of an arm that lags its command (a compliant drive) the older command always lies
    closer, whatever the timing: the drive's calibration and anchor read :func:`anchor_path`.

    Args:
        ev: ``Evidence`` (or any object with its ``t_ns``, ``pose``, ``pose_cmd``, ``pose_cmd_taken``) with
            ``pose`` and ``pose_cmd`` channels.
        at_ns: stamps ``(M,)`` int64 ns at which to read the path (default the ``pose`` stamps); outside the
            commands' span the interpolated reading is clamped to the first and last command.

    Returns:
        ``(commanded poses (M, 7), True when held)``.
    """
    t_pose = np.asarray(ev.t_ns["pose"], dtype=np.int64)
    at = t_pose if at_ns is None else np.asarray(at_ns, dtype=np.int64)
    pose = np.asarray(ev.pose, dtype=float)
    t_cmd = np.asarray(ev.t_ns["pose_cmd"])
    lin = resample_pose(t_cmd, ev.pose_cmd, t_pose, outside="clamp")
    taken = ev.pose_cmd_taken
    if taken is None or t_pose.shape[0] < 2 or len(taken[0]) == 0:
        return (lin if at_ns is None else resample_pose(t_cmd, ev.pose_cmd, at, outside="clamp")), False
    period = robot_step_ns(ev)
    hold = zero_order_hold(taken[0], taken[1], t_pose - period, period, pose[0])
    e_lin = float(np.sum((pose[:, :3] - lin[:, :3]) ** 2))
    e_hold = float(np.sum((pose[:, :3] - hold[:, :3]) ** 2))
    if e_hold < e_lin:
        return (hold if at_ns is None else zero_order_hold(taken[0], taken[1], at - period, period, pose[0])), True
    return (lin if at_ns is None else resample_pose(t_cmd, ev.pose_cmd, at, outside="clamp")), False


def anchor_path(ev: Any, at_ns: np.ndarray) -> np.ndarray:
    """The commanded pose at ``at_ns`` ``(M,)`` ns that an arm's drive is anchored at: the robot's own timing
    where the recording holds it, else the commands interpolated between their header stamps. ``(M, 7)``.

    Where some command was logged after its header stamp (:func:`logged_at_stamps` False: the robot took it
    late, as the sim node logs a command a lagging commander's robot takes a step or more after its stamp),
    the log times say when the robot took each command, and :func:`commanded_path`'s reading is taken (held on
    such a robot's recordings). Where every command was logged at its own header stamp, they say nothing the
    stamps do not, and the tracking-error rule cannot choose for a compliant arm, whose pose always lies closer
    to the older command: the interpolation is kept (a kinematic arm's lag is then at most the commands' one-step
    lead, which no load follows).

    Args:
        ev: ``Evidence`` with ``pose`` and ``pose_cmd`` channels.
        at_ns: stamps, int64 ns.
    """
    taken = ev.pose_cmd_taken
    if taken is None or len(taken[0]) == 0 or logged_at_stamps(taken[0], ev.t_ns["pose_cmd"]):
        return resample_pose(np.asarray(ev.t_ns["pose_cmd"]), ev.pose_cmd, np.asarray(at_ns, dtype=np.int64),
                             outside="clamp")
    return commanded_path(ev, at_ns)[0]


def logged_at_stamps(t_log: np.ndarray, t_stamp: np.ndarray) -> bool:
    """Whether every command was logged at its own header stamp: the log times ``(N,)`` within the stamps' span
    equal the header stamps ``(M,)`` (ns), one for one (the log times cover the whole recording, the stamps may be
    a window of it)."""
    t_log, t_stamp = np.asarray(t_log, dtype=np.int64), np.asarray(t_stamp, dtype=np.int64)
    if t_stamp.size == 0:
        return False
    inside = t_log[(t_log >= t_stamp[0]) & (t_log <= t_stamp[-1])]
    return inside.shape == t_stamp.shape and bool(np.array_equal(inside, t_stamp))


def robot_step_ns(ev: Any) -> int:
    """The robot's step, ns: the median period of the ``pose`` stream (at least 2 samples)."""
    return int(np.median(np.diff(np.asarray(ev.t_ns["pose"], dtype=np.int64))))


def held_path_jumps_inside(ev: Any, dt_ns: int, tol_velocity: float, start_ns: int | None = None) -> int:
    """How many replay steps of ``dt_ns`` the held command path leaves the straight line between their ends in.

    A replay drives the effector to a target at each step end ``t_k = t_0 + k dt`` and moves it linearly
    in between (``sim_core.effector``); its observations at stamps inside a step are interpolated between
    the step ends (:mod:`sysid.observation`). A robot stepping at ``T < dt`` that holds a command and then
    jumps to the next one (a command taken a step or more late, several at once) inside one replay step
    follows a path the replay cannot. A step counts where, at a ``pose`` stamp strictly inside it, the held
    path (:func:`commanded_path`) leaves the line between its values at the step's ends by more than both the
    replay's own position resolution, ``tol_velocity * dt`` (the Newton tolerance a replay step is solved to,
    ``sysid.observation.REPLAY_TOL_VELOCITY``: 1 nm at 10 ms), and the measured pose's scatter about the held
    path (:func:`white_level`: zero on the sim node's exact poses, the pose noise on a measured arm's): the
    straight-line cut of a smooth path's curvature that the recording's own pose cannot resolve does not count.

    Args:
        ev: ``Evidence`` with ``pose`` and ``pose_cmd`` channels.
        dt_ns: the replay step, ns.
        tol_velocity: the replay's Newton tolerance, m/s.
        start_ns: the replay's first step time (default the first ``pose`` stamp).

    Returns:
        0 where the commands are read interpolated (:func:`commanded_path`), the robot's step is not shorter
        than ``dt_ns``, or no command was recorded; else the number of such steps.
    """
    if "pose_cmd" not in ev.channels_present or ev.pose_cmd is None or ev.pose_cmd_taken is None:
        return 0
    t_pose = np.asarray(ev.t_ns["pose"], dtype=np.int64)
    if t_pose.shape[0] < 3 or robot_step_ns(ev) >= dt_ns:
        return 0
    path, is_held = commanded_path(ev)
    if not is_held:
        return 0
    t0 = int(t_pose[0]) if start_ns is None else int(start_ns)
    k = (t_pose - t0) // dt_ns  # the step each stamp lies in (its start t_0 + k dt)
    inside = (t_pose - t0) % dt_ns != 0
    ends = t0 + dt_ns * np.stack([k, k + 1], axis=1)
    at_ends = commanded_path(ev, ends.reshape(-1))[0][:, :3].reshape(-1, 2, 3)
    w = ((t_pose - t0 - k * dt_ns) / dt_ns)[:, None]
    line = (1.0 - w) * at_ends[:, 0] + w * at_ends[:, 1]
    scatter = white_level(np.asarray(ev.pose, dtype=float)[:, :3] - path[:, :3])
    off = np.linalg.norm(path[:, :3] - line, axis=1) > max(tol_velocity * dt_ns * 1e-9, scatter)
    return int(np.unique(k[inside & off]).size)


def replay_step(ev: Any, dt: float, tol_velocity: float) -> float:
    """The step (s) at which to replay ``ev`` asked for at ``dt``: the robot's own step (the ``pose`` stream's
    period) where the held command path jumps inside a replay step of ``dt`` (:func:`held_path_jumps_inside`),
    else ``dt``.

    Args:
        ev: ``Evidence``.
        dt: the asked replay step, s (> 0).
        tol_velocity: the replay's Newton tolerance, m/s (``sysid.observation.REPLAY_TOL_VELOCITY``).
    """
    dt_ns = int(round(dt * 1e9))
    if held_path_jumps_inside(ev, dt_ns, tol_velocity) == 0:
        return dt
    return robot_step_ns(ev) * 1e-9


def white_level(err: np.ndarray) -> float:
    """The white-noise level (m) of a tracking error ``(N, 3)``: the norm over the axes of each axis's
    ``1.4826 MAD(e_t - e_{t-1}) / sqrt(2)`` (first differences cancel a smooth error, the median ignores a sparse
    sharp one; the estimator of :func:`sysid.diagnose.noise.raise_to_white_residual`); 0 for fewer than 3 samples."""
    e = np.asarray(err, dtype=float)
    if e.shape[0] < 3:
        return 0.0
    d = np.diff(e, axis=0)
    mad = np.median(np.abs(d - np.median(d, axis=0)), axis=0)
    return float(np.linalg.norm(1.4826 * mad / np.sqrt(2.0)))
