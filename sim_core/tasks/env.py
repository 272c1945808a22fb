"""Gymnasium environments of the ThinShellLab tasks (ids ``thinshell/<Task>-v0``, e.g. ``thinshell/Lifting-v0``).

* Observation (float32 vector): the sampled vertex positions of every sheet (m, world; at most
  ``sheet_samples`` per sheet, evenly strided in vertex order), then per tactile effector (a gel that
  deforms) the displacements of ``marker_count`` markers (its surface vertices that are not driven,
  evenly strided) in the effector frame from their rest positions (m), then per effector its pose
  ``[x y z qx qy qz qw]`` and the net contact wrench on its body ``[fx fy fz tx ty tz]`` (N, N m).
* Action: one row of the task's action layout (:mod:`sim_core.tasks.spec`): per-step SE(3)
  increments of the effectors (+ gripper opening increments) within the task's bounds; values outside
  are clipped.
* Reward: 0 until the episode ends; at its end (horizon reached, or an infeasible state) the task's
  reward of the final state, minus ``infeasible_penalty`` when infeasible (ThinShellLab's early-stopped
  rollouts lose their success bonus, ``code/training/run_cmaes_all.py``).
* Termination: an infeasible state (:class:`sim_core.tasks.rollout.TaskEpisode`: solver failure, a
  force above the limit, lost contact); truncation: the horizon.
* ``render()``: an RGB frame (matplotlib Agg) of the sheets and effector bodies, ``(H, W, 3)`` uint8.

A task without effectors (Bouncing) has a zero-width action box: its episodes replay the passive motion.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
from gymnasium import spaces
import numpy as np

from sim_core.errors import ConfigError
from sim_core.tasks.registry import load_task
from sim_core.tasks.rollout import TaskEpisode
from sim_core.tasks.spec import TaskSpec
from sim_core.transforms import inverse_transform_points

def _strided(n: int, count: int) -> np.ndarray:
    return np.unique(np.linspace(0, n - 1, min(n, count)).round().astype(np.int64))


class ThinShellTaskEnv(gym.Env):
    """A task as a Gymnasium environment (module docstring).

    Args:
        task: a TaskSpec, a task name (``"lifting"``) or a task file path.
        horizon: episode length in steps (default: the task's; at most the task's).
        backend: solver backend.
        render_mode: None or ``"rgb_array"``.
        sheet_samples: sampled vertices per sheet.
        marker_count: markers per tactile effector.
        infeasible_penalty: subtracted from the final reward of an infeasible episode.

    Raises:
        ConfigError: unknown task, horizon out of range.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(self, task: TaskSpec | str, horizon: int | None = None, backend: str = "numpy",
                 render_mode: str | None = None, sheet_samples: int = 64, marker_count: int = 16,
                 infeasible_penalty: float = 1.0) -> None:
        self.task = task if isinstance(task, TaskSpec) else load_task(task)
        self.horizon = int(horizon or self.task.horizon)
        if not 1 <= self.horizon <= self.task.horizon:
            raise ConfigError(f"env {self.task.name}: horizon must be in [1, {self.task.horizon}], got {horizon}")
        if render_mode not in (None, "rgb_array"):
            raise ConfigError(f"env {self.task.name}: render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        self.infeasible_penalty = float(infeasible_penalty)
        self._episode = TaskEpisode(self.task, backend=backend)
        model = self._episode.sim.model
        self._sheets = [(b.vertex_start + _strided(b.vertex_stop - b.vertex_start, sheet_samples))
                        for b in model.bodies.values() if b.kind == "sheet"]
        self._effectors = list(model.effectors)
        state0 = self._episode.sim.state
        self._markers = {}
        for name in model.meta.get("tactile_effectors", []):
            body = model.bodies[model.meta["effector_bodies"][name]]
            free = np.setdiff1d(body.vertices, model.effectors[name].vertices)
            free = np.intersect1d(free, np.unique(body.triangles))  # surface vertices
            idx = free[_strided(free.size, marker_count)] if free.size else free
            self._markers[name] = (idx, inverse_transform_points(state0.effector_pose[name], state0.x[idx]))
        self.action_space = spaces.Box(self.task.action_low.astype(np.float32), self.task.action_high.astype(np.float32),
                                       dtype=np.float32)
        n_obs = self._observation().shape[0]
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(n_obs,), dtype=np.float32)

    def _observation(self) -> np.ndarray:
        ep = self._episode
        state = ep.sim.state
        parts = [state.x[idx].ravel() for idx in self._sheets]
        for name, (idx, rest_local) in self._markers.items():
            parts.append((inverse_transform_points(state.effector_pose[name], state.x[idx]) - rest_local).ravel())
        wrench = ep.wrenches()
        for name in self._effectors:
            parts += [state.effector_pose[name], wrench[name]]
        return np.concatenate(parts).astype(np.float32) if parts else np.zeros(0, np.float32)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Back to the task's initial state (deterministic: the seed only seeds ``np_random``)."""
        super().reset(seed=seed)
        self._episode.reset()
        return self._observation(), {"steps_done": 0}

    def step(self, action):
        """One step; returns ``(observation, reward, terminated, truncated, info)`` (module docstring).

        ``info``: ``steps_done``, ``infeasible`` (reason or None) and, at the end, ``task_reward``.
        """
        a = np.clip(np.asarray(action, dtype=float).reshape(self.task.action_dim), self.task.action_low,
                    self.task.action_high)
        ep = self._episode
        ep.step(a)
        terminated = ep.infeasible is not None
        truncated = not terminated and ep.steps_done >= self.horizon
        info: dict[str, Any] = {"steps_done": ep.steps_done, "infeasible": ep.infeasible}
        reward = 0.0
        if terminated or truncated:
            info["task_reward"] = ep.reward()
            reward = info["task_reward"] - (self.infeasible_penalty if terminated else 0.0)
        return self._observation(), float(reward), terminated, truncated, info

    def render(self) -> np.ndarray | None:
        """An RGB frame ``(480, 640, 3)`` uint8 of the sheets (grey) and effector bodies (green), or None
        when ``render_mode`` is None."""
        if self.render_mode is None:
            return None
        # optional heavy dependency: matplotlib, for plots only
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        model, state = self._episode.sim.model, self._episode.sim.state
        fig = Figure(figsize=(6.4, 4.8), dpi=100)
        canvas = FigureCanvasAgg(fig)
        ax = fig.add_subplot(projection="3d")
        for body in model.bodies.values():
            if body.kind == "sheet":
                ax.plot_trisurf(*state.x[:, :].T, triangles=body.triangles, color="0.7", linewidth=0.1)
            elif body.name in model.meta.get("effector_bodies", {}).values():
                p = state.x[body.vertex_start:body.vertex_stop]
                ax.scatter(*p.T, s=1, c="tab:green")
        ax.set_title(f"{self.task.name}  step {self._episode.steps_done}")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        canvas.draw()
        return np.asarray(canvas.buffer_rgba())[..., :3].copy()
