"""ThinShellLab-style tasks: task specifications, rewards as pure functions of the state, rollouts,
Gymnasium environments and benchmark trajectories.

Modules: :mod:`~sim_core.tasks.spec` (``TaskSpec``, action rows), :mod:`~sim_core.tasks.registry`
(``load_task``, ``task_names``: ``config/tasks/*.yaml``), :mod:`~sim_core.tasks.rewards` (formulas),
:mod:`~sim_core.tasks.task_rewards` (bindings), :mod:`~sim_core.tasks.rollout` (``rollout``,
``build_task_simulation``, ``TaskEpisode``), :mod:`~sim_core.tasks.env` (the Gymnasium environment, imported on
demand; importing this package registers the ids ``thinshell/<Task>-v0``, :mod:`~sim_core.tasks.gym_ids`), :mod:`~sim_core.tasks.bench` (``thinshell bench tasks``). Scenes live in ``config/scenes``
(``kind: task``, built by :mod:`sim_core.scenes.task_scene`).
"""

from __future__ import annotations

from sim_core.tasks.gym_ids import gymnasium_installed, register_envs
from sim_core.tasks.rewards import crease_columns, folding_reward, forming_reward
from sim_core.tasks.trajectories import forming_benchmark_offsets, pose_targets

__all__ = ["crease_columns", "folding_reward", "forming_reward", "forming_benchmark_offsets", "pose_targets"]

if gymnasium_installed():  # the environments' ids, where Gymnasium is there to make them
    register_envs()
