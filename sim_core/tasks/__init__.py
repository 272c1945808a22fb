"""ThinShellLab-style tasks: benchmark trajectories and rewards as pure functions of the state.

Scenes live in ``config/scenes`` (``kind: task``, built by :mod:`sim_core.scenes.task_scene`).
"""

from __future__ import annotations

from sim_core.tasks.rewards import crease_columns, folding_reward, forming_reward
from sim_core.tasks.trajectories import forming_benchmark_offsets, pose_targets

__all__ = ["crease_columns", "folding_reward", "forming_reward", "forming_benchmark_offsets", "pose_targets"]
