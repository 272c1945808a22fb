"""A task's reward measured on recorded (or predicted) sheet points: the reward a robot achieved.

A ThinShellLab task's reward (:mod:`sim_core.tasks.task_rewards`) is a function of the final state.
A recording holds the tracked sheet points (``sheet/points``: ``Model.tracked_sheet_vertices``), not
the whole state, so the reward is evaluated on the task model's initial state with the tracked
vertices moved to the given points. That is the reward itself only when it reads nothing else:
:func:`reward_on_points` checks it by perturbing every other vertex and every rest angle (a reward
that reads rest angles, such as Folding's crease rewards, or a body that is not recorded, such as
Lifting's block, is refused with an error naming the reward).

The time of the reward is the end of the commanded motion: :func:`reward_sample_index` picks the
first ``sheet/points`` sample stamped after the last ``<effector>/pose_cmd`` of the recording (the
state the last command produced), so a robot that holds its pose after the motion is scored at the
task's horizon, not at the end of the bag.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from sim_core.errors import ConfigError

PERTURBATION = 1e-3
"""m (positions) and rad (rest angles) of the check that the reward reads only the tracked points."""


class TaskRewardProbe:
    """A task's reward as a function of the tracked sheet points.

    Args:
        task: a :class:`sim_core.tasks.spec.TaskSpec` (its ``scene`` builds the model whose body
            layout the points follow; its ``reward`` closure, with its target, is evaluated).

    Raises:
        ConfigError: the reward reads more than the tracked sheet points (named).
    """

    def __init__(self, task: Any) -> None:
        from sim_core.scenes.task_scene import build_task_scene

        self.task = task
        self.model = build_task_scene(dict(task.scene))
        self.tracked = self.model.tracked_sheet_vertices()
        self._check()

    def _state(self, points: np.ndarray):
        state = self.model.state()
        state.x[self.tracked] = points
        return state

    def _check(self) -> None:
        state = self.model.state()
        base = float(self.task.reward(self.model, state))
        rng = np.random.default_rng(0)
        other = np.setdiff1d(np.arange(self.model.vertex_count), self.tracked)
        state.x[other] += PERTURBATION * rng.standard_normal((other.size, 3))
        for name, theta_bar in state.hinge_theta_bar.items():
            state.hinge_theta_bar[name] = theta_bar + PERTURBATION * rng.standard_normal(theta_bar.shape)
        moved = float(self.task.reward(self.model, state))
        if moved != base:
            raise ConfigError(f"task {self.task.name}: reward {self.task.reward_name!r} reads more than the recorded "
                              "sheet points (rest angles or another body); it cannot be measured on a recording")

    def __call__(self, points: np.ndarray) -> float:
        """The reward (unit ``task.reward_units``) with the tracked sheet points at ``points``.

        Args:
            points: tracked sheet points in m, ``world``, shape ``(p, 3)``.

        Raises:
            ConfigError: ``points`` of another shape than the task's tracked points.
        """
        points = np.asarray(points, dtype=float)
        if points.shape != (self.tracked.size, 3):
            raise ConfigError(f"task {self.task.name}: {points.shape[0] if points.ndim else 0} sheet points, the task's "
                              f"scene tracks {self.tracked.size}")
        return float(self.task.reward(self.model, self._state(points)))


def reward_sample_index(evidence: Any, sheet_t_ns: np.ndarray) -> int:
    """Index of the first ``sheet/points`` sample stamped after the recording's last pose command.

    Args:
        evidence: :class:`sysid.evidence.Evidence` of a task-scene recording (``effectors``).
        sheet_t_ns: stamps of the sheet-point samples in use, ns, shape ``(n,)``.

    Raises:
        ConfigError: no pose command recorded, or no sheet sample after the last one.
    """
    stamps = [int(streams["pose_cmd"][0][-1]) for streams in evidence.effectors.values()
              if "pose_cmd" in streams and len(streams["pose_cmd"][0])]
    if not stamps:
        raise ConfigError(f"{evidence.source.bag_path}: no <effector>/pose_cmd recorded; the end of the motion is unknown")
    after = np.flatnonzero(np.asarray(sheet_t_ns) > max(stamps))
    if after.size == 0:
        raise ConfigError(f"{evidence.source.bag_path}: no sheet/points sample after the last pose command "
                          f"(t = {max(stamps) * 1e-9:.4f} s)")
    return int(after[0])
