"""Corrections of the diagnosis's data model: denoised replay controls and white-noise levels.

The replay is driven by the *measured* effector pose, whose noise propagates into every prediction
(errors in variables), and the declared sensor noise leaves that propagated noise out. Two fixes,
applied by :mod:`sysid.diagnose.engine` before any test: :func:`denoise_controls` replaces the
replayed positions by a denoised estimate, :func:`raise_to_white_residual` raises each channel's
noise level to the white part of the nominal residual.
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

import numpy as np


def replay_model(evidence: Any, dt: float, window: int, **options: Any) -> tuple[Any, list[str]]:
    """The score stage's ``ObservationModel`` of ``evidence`` at ``dt``, controls denoised, and notes for the report.

    Where the path the robot held (:func:`sysid.command_path.commanded_path`) jumps inside a replay step of ``dt``
    (:func:`sysid.command_path.held_path_jumps_inside`: a robot stepping faster than the replay that holds a
    command and then takes the next ones at once, under a commander that falls behind it), a replay moving
    linearly between its step ends misses that staircase by up to a robot step's travel at the stamps inside the
    step; a note says how many steps and the step that would follow it (the ``pose`` stream's period,
    :func:`sysid.command_path.robot_step_ns`, as :func:`sysid.command_path.replay_step` chooses it). The replay
    keeps ``dt`` (docs/benchmarks_log.md "2026-11-28 (session 60, 49demo2)" measured the robot's step as the
    default). Then :func:`denoise_controls` with ``window`` (0: the measured pose replayed as recorded).

    Args:
        evidence: the recording's ``Evidence``.
        dt: the replay step, s.
        window: :func:`denoise_controls`'s window in pose samples (0: none).
        **options: ``ObservationModel``'s ``t_max``, ``simulation``, ``arch``.

    Returns:
        ``(model, notes for the report)``.

    Raises:
        CalibrationError: as ``ObservationModel``.
    """
    from sysid.command_path import held_path_jumps_inside, robot_step_ns
    from sysid.observation import REPLAY_TOL_VELOCITY, ObservationModel

    notes = []
    jumps = held_path_jumps_inside(evidence, int(round(dt * 1e9)), REPLAY_TOL_VELOCITY)
    step = robot_step_ns(evidence) * 1e-9 if jumps else dt  # sysid.command_path.replay_step's choice
    if step != dt:
        notes.append(f"the path the robot held (its commands from when it took each) jumps inside {jumps} replay "
                     f"steps of {dt * 1e3:g} ms, which the replay moves through linearly; --dt {step:g} replays it "
                     "at the robot's step")
    model = ObservationModel(evidence, dt=dt, **options)
    if window:
        note = denoise_controls(model, window)
        if note:
            notes.append(note)
    return model, notes


def denoise_controls(model: Any, window: int) -> str | None:
    """Replace the replayed effector positions by a denoised estimate (errors in variables).

    The replay is driven by the *measured* effector pose; its noise (5 um) propagates through the
    gel (a 2e4 N/m contact) and the stick/slip history into every predicted channel -- on a nominal
    recording it alone left a whitened RMS of 1.1-1.6 in markers and wrench. When the commanded pose
    is recorded, the tracking error ``pose - command`` (smooth: an impedance response) is smoothed
    with a Savitzky-Golay filter (order 2, ``window`` samples of the pose stream, made odd; Savitzky &
    Golay 1964) and added back to the exact command, so the command's corners stay sharp; a tracking
    error that is white (:func:`tracking_error_is_white`: measurement noise only) is not added back.

    The command path is the one the effector followed (:func:`sysid.command_path.commanded_path`): the commands held as
    the robot held them, from the time it took each (zero-order hold on the log times,
    ``Evidence.pose_cmd_taken``), or the commands interpolated linearly between their header stamps,
    whichever leaves the smaller tracking error. A robot that steps faster than its commander takes a
    command a step or more after its header stamp, several at once when it falls behind (a loaded
    machine); its path is then a staircase that the interpolated commands miss by a step's travel
    (up to 0.4 mm at the demo's 40 mm/s approach), which no smoothing of the tracking error restores.
    Without ``pose_cmd`` (or with fewer than ``window + 2`` pose samples) the controls are left as
    recorded.

    Args:
        model: an ``ObservationModel`` (its ``controls``, initial effector pose and cached simulation
            are replaced).
        window: filter window in pose samples.

    Returns:
        a note for the report when the controls were replaced, else None.
    """
    from scipy.signal import savgol_filter

    from sysid.command_path import commanded_path
    from sysid.evidence import resample_pose

    ev = model.evidence
    if "pose_cmd" not in ev.channels_present or ev.pose_cmd is None:
        return None
    w = int(window) | 1
    t_pose = np.asarray(ev.t_ns["pose"])
    if t_pose.shape[0] < w + 2:
        return None
    cmd, held = commanded_path(ev)
    err = np.asarray(ev.pose, dtype=float)[:, :3] - cmd[:, :3]
    smooth = np.array(ev.pose, dtype=float)
    white = tracking_error_is_white(err)
    smooth[:, :3] = cmd[:, :3] + (0.0 if white else savgol_filter(err, w, 2, axis=0, mode="interp"))
    model.controls = resample_pose(t_pose, smooth, model.step_times_ns, outside="clamp")
    model.scene["effectors"][model.effector]["initial_pose"] = [float(v) for v in model.controls[0]]
    model._sim = None
    path = "held from when the robot took each command" if held else "interpolated between the commands' stamps"
    if white:
        return f"replayed effector positions = pose_cmd, {path} (the tracking error is white: measurement noise only)"
    return f"replayed effector positions denoised (pose_cmd, {path}, + Savitzky-Golay({w}, 2) of the tracking error)"


WHITE_Z = 3.09
"""One-sided normal quantile (p = 0.001) of :func:`tracking_error_is_white`'s von Neumann test."""


def tracking_error_is_white(err: np.ndarray, z: float = WHITE_Z) -> bool:
    """Whether a tracking error ``pose - pose_cmd`` is zero-mean white noise (no motion to replay).

    Von Neumann's ratio without centring, pooled over the axes:
    ``eta = sum_t |e_t - e_{t-1}|^2 / sum_t |e_t|^2`` is about 2 for zero-mean white noise (standard
    deviation about ``2 / sqrt(N)``, ``N`` samples x axes) and falls towards 0 for a smooth error or an
    offset (von Neumann 1941, "Distribution of the ratio of the mean square successive difference to
    the variance"). White when ``eta >= 2 - z 2 / sqrt(N)``: then the command is the best estimate of
    the effector's path and smoothing the noise would only add a smooth error of its own (a
    Savitzky-Golay filter of 11 samples keeps about 20 % of the noise's variance, correlated over the
    window, which the replay turns into a systematic residual).

    Args:
        err: tracking error ``(samples, axes)`` [m].
        z: one-sided normal quantile of the test.

    Returns:
        False for fewer than 3 samples; True for an error that is exactly zero.
    """
    e = np.asarray(err, dtype=float)
    if e.ndim != 2 or e.shape[0] < 3:
        return False
    energy = float(np.sum(e ** 2))
    if energy == 0.0:
        return True
    eta = float(np.sum(np.diff(e, axis=0) ** 2)) / energy
    return eta >= 2.0 - z * 2.0 / math.sqrt(e.size)


def raise_to_white_residual(model: Any, channels: Sequence[str], prediction: Mapping[str, np.ndarray]) -> None:
    """Raise each channel axis's noise level (``model.sigma``) to the white part of the residual.

    The white part is estimated from first differences in time, robustly:
    ``sigma_w = 1.4826 MAD(r_t - r_{t-1}) / sqrt(2)`` (a smooth model error cancels in the
    differences; a sparse sharp one does not move the median). It holds the sensor noise plus the
    noise the replay inherits from the *measured* effector poses it is driven by (errors in
    variables: 5 um of pose noise moves a 2e4 N/m gel by 0.1 N), which the declared sensor noise
    leaves out and which would otherwise read as a smooth-less but real excess. Channels with fewer
    than 9 samples are left as they are.
    """
    for ch in channels:
        r = model.data(ch) - prediction[ch]
        axes = r.shape[-1]
        d = np.diff(r.reshape(r.shape[0], -1, axes), axis=0).reshape(-1, axes)
        if d.shape[0] < 8:
            continue
        mad = np.median(np.abs(d - np.median(d, axis=0)), axis=0)
        white = 1.4826 * mad / math.sqrt(2.0)
        model.sigma[ch] = np.maximum(model.sigma[ch], white)
