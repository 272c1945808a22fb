"""Effector trajectories of the ThinShellLab tasks.

The Forming benchmark trajectory (DESIGN.md "ThinShellLab tasks", the original's Forming initial
trajectory) gives the dome sensor's offset from its start pose, in metres, after step i (1-based):

* steps 1-19: ``z = -0.00011 i`` and x grows 0.00023 per step;
* steps 20-34: z falls 0.0002 and x grows 0.00027 per step;
* steps 35-49: z holds and x grows 0.0002 per step;

no rotation, y = 0.
"""

from __future__ import annotations

import numpy as np

from sim_core.errors import ConfigError
from sim_core.transforms import quat_normalize

FORMING_BENCHMARK_STEPS = 49
# (last step of the phase, dx per step, dz per step) in m
_FORMING_PHASES = ((19, 0.00023, -0.00011), (34, 0.00027, -0.0002), (49, 0.0002, 0.0))


def forming_benchmark_offsets(steps: int = FORMING_BENCHMARK_STEPS) -> np.ndarray:
    """Sensor offsets from the start pose after each step of the Forming benchmark.

    Args:
        steps: number of steps, 1 <= steps <= 49.

    Returns:
        offsets in m, shape ``(steps, 3)``; row ``i - 1`` is the offset after step ``i``.

    Raises:
        ConfigError: ``steps`` out of range.
    """
    if not 1 <= int(steps) <= FORMING_BENCHMARK_STEPS:
        raise ConfigError(f"forming benchmark trajectory has 1..{FORMING_BENCHMARK_STEPS} steps, asked for {steps}")
    delta = np.zeros((FORMING_BENCHMARK_STEPS, 3))
    first = 0
    for last, step_x, step_z in _FORMING_PHASES:
        delta[first:last, 0] = step_x
        delta[first:last, 2] = step_z
        first = last
    return np.cumsum(delta, axis=0)[: int(steps)]


def pose_targets(initial_pose: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """World pose targets ``initial_pose`` translated by each offset (orientation unchanged).

    Args:
        initial_pose: ``[x y z qx qy qz qw]``.
        offsets: world translations in m, shape ``(k, 3)``.

    Returns:
        poses, shape ``(k, 7)``.

    Raises:
        ConfigError: a pose that is not 7 finite numbers with a unit quaternion, or bad offsets.
    """
    pose = np.asarray(initial_pose, dtype=float)
    offsets = np.asarray(offsets, dtype=float)
    if pose.shape != (7,) or not np.all(np.isfinite(pose)):
        raise ConfigError(f"pose_targets: initial_pose must be 7 finite numbers, got {pose.tolist()}")
    if offsets.ndim != 2 or offsets.shape[1] != 3 or not np.all(np.isfinite(offsets)):
        raise ConfigError(f"pose_targets: offsets must be finite with shape (k, 3), got {offsets.shape}")
    q = quat_normalize(pose[3:], "pose_targets initial_pose")
    out = np.empty((offsets.shape[0], 7))
    out[:, :3] = pose[:3] + offsets
    out[:, 3:] = q
    return out
