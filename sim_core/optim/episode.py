"""One episode of a task: roll out per-step actions, score the final state, and differentiate the
reward with respect to every action (and to material parameters) through the adjoint.

The score the optimisers rank by is ThinShellLab's CMA-ES fitness (``code/training/run_cmaes_all.py``,
``evaluate``): ``0.1 steps_done / T`` plus, only when the episode ran to the end, ``reward + 5``.
An infeasible episode (the solver fails, a task check stops it early) therefore scores below every
feasible one whose reward exceeds -5, and a later stop scores above an earlier one.

Reward gradients: the task's reward is a pure function of the final state. When the reward object
has ``state_gradient(model, state) -> (dR/dx (n, 3), {sheet: dR/dtheta_bar (h,)})`` that is used;
otherwise the gradient is central differences of the reward over the final positions and rest
angles (step :data:`REWARD_FD_STEP`; exact up to rounding for the quadratic Forming and linear
Folding rewards). The reward must then depend on the state only through ``x`` and
``hinge_theta_bar``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Mapping, Sequence

import numpy as np

from sim_core import adjoint
from sim_core.errors import ConfigError, SimulationDivergedError
from sim_core.model import Model
from sim_core.optim.actions import action_gradient, actions_to_controls, check_actions
from sim_core.simulation import Simulation
from sim_core.solver_config import SolverConfig
from sim_core.state import State

PROGRESS_WEIGHT = 0.1
"""Score per completed fraction of the horizon (ThinShellLab ``stop_step / tot_timestep * 0.1``)."""
FEASIBLE_OFFSET = 5.0
"""Added to the reward of an episode that ran to the end (ThinShellLab ``reward + 5``)."""
REWARD_FD_STEP = 1e-6
"""Central-difference step of the fallback reward gradient (m for positions, rad for rest angles)."""


@dataclass
class EpisodeResult:
    """What one episode gave.

    Attributes:
        reward: task reward of the final state (NaN when infeasible).
        steps_done: steps completed (``horizon`` when feasible).
        horizon: steps asked for T.
        infeasible: why the episode stopped early, None when it ran to the end.
        effector_poses: effector -> reached poses ``(steps_done + 1, 7)`` (row 0 the initial pose).
        gripper: effector -> reached openings ``(steps_done + 1,)`` (two-finger effectors).
        final_state: the last state reached (None unless kept).
        states: every state (None unless kept).
    """

    reward: float
    steps_done: int
    horizon: int
    infeasible: str | None
    effector_poses: dict[str, np.ndarray] = field(default_factory=dict)
    gripper: dict[str, np.ndarray] = field(default_factory=dict)
    final_state: State | None = None
    states: list[State] | None = None

    @property
    def feasible(self) -> bool:
        """Ran to the end."""
        return self.infeasible is None

    @property
    def score(self) -> float:
        """ThinShellLab's fitness (module docstring); higher is better."""
        s = PROGRESS_WEIGHT * self.steps_done / self.horizon
        return s + self.reward + FEASIBLE_OFFSET if self.feasible else s

    def summary(self) -> "EpisodeResult":
        """A copy without states (what a worker sends back)."""
        return EpisodeResult(self.reward, self.steps_done, self.horizon, self.infeasible,
                             self.effector_poses, self.gripper)


def reward_state_gradient(reward: Callable[[Model, State], float], model: Model,
                          state: State) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """dR/dx and dR/dtheta_bar of a reward at ``state`` (module docstring).

    Returns:
        ``(dR/dx (n, 3), {sheet: dR/dtheta_bar (h,)})``.

    Raises:
        ConfigError: a ``state_gradient`` with wrong shapes.
    """
    if hasattr(reward, "state_gradient"):
        gx, gtb = reward.state_gradient(model, state)
        gx = np.asarray(gx, dtype=float)
        if gx.shape != state.x.shape:
            raise ConfigError(f"reward.state_gradient: dR/dx has shape {gx.shape}, expected {state.x.shape}")
        return gx, {k: np.asarray(v, dtype=float) for k, v in gtb.items()}
    probe = state.copy()
    h = REWARD_FD_STEP

    def central(arr: np.ndarray) -> np.ndarray:
        out = np.zeros(arr.shape)
        flat, grad = arr.reshape(-1), out.reshape(-1)
        for k in range(flat.size):
            keep = flat[k]
            flat[k] = keep + h
            up = reward(model, probe)
            flat[k] = keep - h
            down = reward(model, probe)
            flat[k] = keep
            grad[k] = (up - down) / (2.0 * h)
        return out

    gx = central(probe.x)
    gtb = {name: central(tb) for name, tb in probe.hinge_theta_bar.items()}
    return gx, {k: v for k, v in gtb.items() if np.any(v)}


class Episode:
    """A task's simulation, reset for every episode.

    Args:
        task: a task (``scene``, ``dt``, ``horizon``, ``action_layout``, ``reward``; the task contract).
        horizon: steps per episode (default ``task.horizon``).
        params: global parameter values to set on the model (e.g. the values an inverse task tries).
        solver_config: Newton settings (default: no dt halving, so every step has an implicit
            derivative and the score CMA-ES ranks is the one gradient descent differentiates).

    Raises:
        ConfigError: an invalid scene or parameter name.
    """

    def __init__(self, task, horizon: int | None = None, params: Mapping[str, float] | None = None,
                 solver_config: SolverConfig | None = None) -> None:
        from sim_core.scenes import load_scene
        from sim_core.scenes.task_scene import task_initial_state

        self.task = task
        self.horizon = int(horizon if horizon is not None else task.horizon)
        if self.horizon < 1:
            raise ConfigError(f"episode horizon must be >= 1, got {self.horizon}")
        model = load_scene(task.scene)
        self.sim = Simulation(model, dt=float(task.dt), solver_config=solver_config or SolverConfig(dt_halvings_on_failure=0))
        self.set_parameters(params or {})
        self._initial_state = task_initial_state(model)
        self.action_dim = int(task.action_dim)

    @property
    def model(self) -> Model:
        """The simulated model."""
        return self.sim.model

    def set_parameters(self, params: Mapping[str, float]) -> None:
        """Set global parameters (``Model.set_parameter``) for the following episodes.

        Raises:
            ConfigError: unknown name.
        """
        known = set(self.model.parameter_names)
        for name, value in params.items():
            if name not in known:
                raise ConfigError(f"episode: unknown parameter {name!r}; known: {sorted(known)}")
            self.sim.set_parameter(name, float(value))

    def reset(self) -> None:
        """Back to the task's initial state (solver caches cleared: runs are repeatable bit for bit)."""
        self.sim.reset()
        self.sim.state = self._initial_state.copy()

    def controls(self, actions: np.ndarray):
        """The per-step controls of ``actions`` from the initial state (:func:`actions_to_controls`)."""
        s = self._initial_state
        return actions_to_controls(actions, self.task.action_layout, s.effector_pose, s.gripper_opening)

    def run(self, actions: np.ndarray, keep_states: bool = False) -> EpisodeResult:
        """Roll out ``actions`` from the initial state.

        Args:
            actions: shape ``(horizon, action_dim)``.
            keep_states: keep every state (else only the final one).

        Returns:
            the :class:`EpisodeResult`; a solver failure makes it infeasible (naming the step).

        Raises:
            ConfigError: bad actions.
        """
        actions = check_actions(actions, self.horizon, self.action_dim)
        self.reset()
        states = [self.sim.state.copy()] if keep_states else None
        poses = {k: [np.array(v)] for k, v in self.sim.state.effector_pose.items()}
        grip = {k: [float(v)] for k, v in self.sim.state.gripper_opening.items()}
        infeasible, done = None, 0
        for i, c in enumerate(self.controls(actions)):
            try:
                self.sim.step(c)
            except SimulationDivergedError as err:
                infeasible = f"step {i}: {err}"
                break
            done = i + 1
            for k, v in self.sim.state.effector_pose.items():
                poses[k].append(np.array(v))
            for k, v in self.sim.state.gripper_opening.items():
                grip[k].append(float(v))
            if keep_states:
                states.append(self.sim.state.copy())
        reward = float(self.task.reward(self.model, self.sim.state)) if infeasible is None else float("nan")
        if infeasible is None and not np.isfinite(reward):
            infeasible = f"reward is {reward}"
        return EpisodeResult(reward, done, self.horizon, infeasible, {k: np.array(v) for k, v in poses.items()},
                             {k: np.array(v) for k, v in grip.items()}, self.sim.state.copy(), states)

    def reward_gradient(self, actions: np.ndarray, params: Sequence[str] = ()) -> tuple[EpisodeResult, np.ndarray, dict[str, float]]:
        """The episode's reward and its exact derivatives (adjoint, :mod:`sim_core.adjoint`).

        Args:
            actions: shape ``(horizon, action_dim)``.
            params: global parameter names to differentiate as well.

        Returns:
            ``(result, dR/d actions (horizon, action_dim), {param: dR/dp})``; zeros when infeasible.

        Raises:
            ConfigError: bad actions or parameter names.
        """
        actions = check_actions(actions, self.horizon, self.action_dim)
        self.reset()
        zero = np.zeros_like(actions)
        try:
            traj = adjoint.rollout(self.sim, self.controls(actions), record=True)
        except SimulationDivergedError as err:
            done = self.sim.state.step_index
            res = EpisodeResult(float("nan"), done, self.horizon, f"step {done}: {err}", final_state=self.sim.state.copy())
            return res, zero, {p: 0.0 for p in params}
        final = traj.states[-1]
        reward = float(self.task.reward(self.model, final))
        poses = {k: np.stack([s.effector_pose[k] for s in traj.states]) for k in final.effector_pose}
        grip = {k: np.array([s.gripper_opening[k] for s in traj.states]) for k in final.gripper_opening}
        res = EpisodeResult(reward, self.horizon, self.horizon, None, poses, grip, final)
        gx, gtb = reward_state_gradient(self.task.reward, self.model, final)
        dL_dx = np.zeros((self.horizon + 1,) + gx.shape)
        dL_dx[-1] = gx
        g = adjoint.rollout_gradient(self.sim, traj, dL_dx, params=params, dL_dtheta_bar=gtb)
        da = action_gradient(actions, self.task.action_layout, self._initial_state.effector_pose, g)
        return res, da, dict(g.params)
