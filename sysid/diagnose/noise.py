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


def denoise_controls(model: Any, window: int) -> str | None:
    """Replace the replayed effector positions by a denoised estimate (errors in variables).

    The replay is driven by the *measured* effector pose; its noise (5 um) propagates through the
    gel (a 2e4 N/m contact) and the stick/slip history into every predicted channel -- on a nominal
    recording it alone left a whitened RMS of 1.1-1.6 in markers and wrench. When the commanded pose
    is recorded, the tracking error ``pose - pose_cmd`` (smooth: an impedance response) is smoothed
    with a Savitzky-Golay filter (order 2, ``window`` samples of the pose stream, made odd; Savitzky &
    Golay 1964) and added back to the exact command, so the command's corners stay sharp.
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

    from sysid.evidence import resample_pose

    ev = model.evidence
    if "pose_cmd" not in ev.channels_present or ev.pose_cmd is None:
        return None
    w = int(window) | 1
    t_pose = np.asarray(ev.t_ns["pose"])
    if t_pose.shape[0] < w + 2:
        return None
    cmd = resample_pose(np.asarray(ev.t_ns["pose_cmd"]), ev.pose_cmd, t_pose, outside="clamp")
    err = np.asarray(ev.pose, dtype=float)[:, :3] - cmd[:, :3]
    smooth = np.array(ev.pose, dtype=float)
    smooth[:, :3] = cmd[:, :3] + savgol_filter(err, w, 2, axis=0, mode="interp")
    model.controls = resample_pose(t_pose, smooth, model.step_times_ns, outside="clamp")
    model.scene["effectors"][model.effector]["initial_pose"] = [float(v) for v in model.controls[0]]
    model._sim = None
    return f"replayed effector positions denoised (pose_cmd + Savitzky-Golay({w}, 2) of the tracking error)"


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
