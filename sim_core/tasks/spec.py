"""TaskSpec: one ThinShellLab task (scene, horizon, action space, optimiser settings, reward) as data.

A task is read from ``config/tasks/<name>.yaml`` by :func:`sim_core.tasks.registry.load_task`; the
file format is documented in ``docs/task_format.md``.

Action space (per step, world frame): for every ``(effector, "pose")`` entry of ``action_layout``
six values ``[dx dy dz rx ry rz]``: a translation increment in m and a rotation vector in rad applied
to the effector's commanded pose (``p <- p + d``, ``q <- exp(r) q``: a rotation about the effector
frame's origin, axes in world); for every ``(effector, "gripper")`` entry one value, the increment of
the commanded finger opening in m. This is ThinShellLab's ``delta_pos`` / ``delta_rot`` per frame
(``code/agent/traj_opt_single.py``), with the gripper opening as an extra column.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from sim_core.errors import ConfigError
from sim_core.model import Model
from sim_core.state import State
from sim_core.transforms import quat_from_rotvec, quat_multiply

ACTION_KINDS = ("pose", "gripper")
"""Kinds of action blocks: 6 values per ``pose`` (m, rad), 1 per ``gripper`` (m)."""

ACTION_WIDTH = {"pose": 6, "gripper": 1}

RewardFn = Callable[[Model, State], float]


@dataclass(frozen=True)
class Infeasibility:
    """When a rollout stops early (ThinShellLab ``check_early_stop``).

    Attributes:
        max_force_N: a component of the net contact force on an effector's body above this (N) is
            infeasible (the original: 10 N); None disables the check.
        min_contact_force_N: after ``contact_after_step`` steps, an effector whose net contact force
            is below this (N) has lost contact (the original: 0.2 N); None disables the check.
        contact_after_step: first step (1-based) at which the contact check applies.
        contact_effectors: effectors the contact check applies to (empty: all pose effectors).
    """

    max_force_N: float | None = 10.0
    min_contact_force_N: float | None = None
    contact_after_step: int = 10
    contact_effectors: tuple[str, ...] = ()


@dataclass(frozen=True)
class TaskSpec:
    """One task: the scene document, the episode and action space, optimiser settings and the reward.

    Attributes:
        name: task name as in the paper (``"Lifting"``).
        kind: ``"manipulation"`` or ``"inverse"``.
        scene: the scene document (``kind: task``, version 1 or 2), already validated.
        horizon: steps per episode.
        dt: time step in s.
        action_layout: ``((effector, "pose" | "gripper"), ...)``: the blocks of one action row.
        action_low: per-step lower bounds, shape ``(action_dim,)`` (m, rad, m).
        action_high: per-step upper bounds, shape ``(action_dim,)``.
        control_points: CMA-ES control points per episode (the original's ``abs_step``).
        cma_sigma: CMA-ES initial step in the original's units (``run_cmaes_all.py`` decodes
            ``(x - 5) 0.0003 / 5``: 1.0 = 6e-5 m of translation, 2e-3 rad of rotation per step;
            :mod:`sim_core.optim.actions`).
        cma_population: CMA-ES population size.
        cma_generations: CMA-ES generations.
        cma_start: what the CMA-ES control points are added to: ``"zero"`` (the zero trajectory, as
            the original) or ``"reference"`` (the human-designed ``reference_actions``: a warm start,
            :class:`sim_core.optim.search.ActionSpace`).
        reward: pure function ``reward(model, state) -> float`` of the final state (units in
            ``reward_units``; larger is better).
        success_score: Table A's success threshold, or None.
        human_score: Table A's human-designed score, or None.
        reference_actions: the human-designed trajectory, shape ``(horizon, action_dim)``, or None.
        identify: inverse tasks: global parameter names to identify (``Model.parameter_names``).
        source: where the facts come from (ThinShellLab file paths).
        reward_name: the reward's registered name (``sim_core.tasks.task_rewards``).
        reward_units: the reward's unit (``"m^2"``, ``"rad"`` ...).
        oracle_score: Table A's oracle score, or None.
        infeasible: the early-stop rules.
        true_parameters: inverse tasks: the parameter values that produced the observed motion.
        tied: inverse tasks: ``{follower: leader}`` among ``identify``; a follower always takes its
            leader's value (one physical parameter set on several scene entries), so it is not searched.
        path: the task file, or None for a task built in memory.
    """

    name: str
    kind: str
    scene: dict
    horizon: int
    dt: float
    action_layout: tuple[tuple[str, str], ...]
    action_low: np.ndarray
    action_high: np.ndarray
    control_points: int
    cma_sigma: float
    cma_population: int
    cma_generations: int
    reward: RewardFn
    cma_start: str = "zero"
    success_score: float | None = None
    human_score: float | None = None
    reference_actions: np.ndarray | None = None
    identify: tuple[str, ...] = ()
    source: str = ""
    reward_name: str = ""
    reward_units: str = ""
    oracle_score: float | None = None
    infeasible: Infeasibility = field(default_factory=Infeasibility)
    true_parameters: dict = field(default_factory=dict)
    tied: dict = field(default_factory=dict)
    path: str | None = None

    @property
    def action_dim(self) -> int:
        """Values per action row: 6 per pose block, 1 per gripper block."""
        return sum(ACTION_WIDTH[k] for _, k in self.action_layout)

    def action_slices(self) -> list[tuple[str, str, slice]]:
        """``(effector, kind, columns)`` of each block of an action row, in layout order."""
        out, start = [], 0
        for eff, kind in self.action_layout:
            width = ACTION_WIDTH[kind]
            out.append((eff, kind, slice(start, start + width)))
            start += width
        return out

    def check_actions(self, actions: np.ndarray, *, steps: int | None = None) -> np.ndarray:
        """Validate an action sequence.

        Args:
            actions: shape ``(k, action_dim)`` with ``k <= horizon`` (``k == steps`` when given).
            steps: required row count, or None.

        Returns:
            the actions as float64.

        Raises:
            ConfigError: wrong shape, non-finite entries, or a value outside the per-step bounds
                (naming the step and column).
        """
        a = np.asarray(actions, dtype=float)
        if a.ndim != 2 or a.shape[1] != self.action_dim:
            raise ConfigError(f"task {self.name}: actions must have shape (steps, {self.action_dim}), got {a.shape}")
        if a.shape[0] > self.horizon or (steps is not None and a.shape[0] != steps):
            raise ConfigError(f"task {self.name}: {a.shape[0]} action rows for a horizon of {self.horizon}")
        bad = ~np.isfinite(a)
        tol = 1e-12
        bad |= (a < self.action_low - tol) | (a > self.action_high + tol)
        if bad.any():
            step, col = (int(v) for v in np.argwhere(bad)[0])
            raise ConfigError(f"task {self.name}: action[{step}][{col}] = {a[step, col]!r} is not finite or outside "
                              f"[{self.action_low[col]:g}, {self.action_high[col]:g}]")
        return a


def apply_action(task: TaskSpec, row: np.ndarray, pose_targets: dict[str, np.ndarray],
                 gripper_targets: dict[str, float]) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Commanded effector poses and openings after one action row.

    Args:
        task: the task.
        row: one action row, shape ``(action_dim,)``.
        pose_targets: effector -> commanded pose ``[x y z qx qy qz qw]`` before the row.
        gripper_targets: effector -> commanded opening in m before the row.

    Returns:
        ``(poses, openings)``: new dictionaries (the inputs are not modified). A pose moves by
        ``p + d`` and ``q <- quat(r) q`` (world-frame rotation vector ``r``); an opening by ``+ d``.
    """
    poses = {k: np.array(v, dtype=float) for k, v in pose_targets.items()}
    openings = dict(gripper_targets)
    for eff, kind, cols in task.action_slices():
        values = np.asarray(row[cols], dtype=float)
        if kind == "pose":
            p = poses[eff]
            p[:3] += values[:3]
            if np.any(values[3:]):
                q = quat_multiply(quat_from_rotvec(values[3:]), p[3:])
                p[3:] = q / np.linalg.norm(q)
        else:
            openings[eff] = float(openings[eff] + values[0])
    return poses, openings
