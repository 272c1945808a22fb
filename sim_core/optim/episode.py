"""One episode of a task: roll out per-step actions, score the final state, and differentiate the
reward with respect to every action (and to material parameters) through the adjoint.

Stepping, commanded targets and early stops are those of :class:`sim_core.tasks.rollout.TaskEpisode`
(ThinShellLab's ``check_early_stop``); this module keeps one simulation per :class:`Episode` and
reuses it for every episode, and records the solver's step records for the adjoint.

The score the optimisers rank by is ThinShellLab's CMA-ES fitness (``code/training/run_cmaes_all.py``,
``evaluate``): ``0.1 steps_done / T`` plus, only when the episode ran to the end, ``reward + 5``.
An infeasible episode (the solver fails, a task check stops it early) therefore scores below every
feasible one whose reward exceeds -5, and a later stop scores above an earlier one.

Reward gradients: the task's reward is a pure function of the final state (a closure of
:mod:`sim_core.tasks.task_rewards`); its gradient is central differences of the reward over the final positions and rest
angles (step :data:`REWARD_FD_STEP`; exact up to rounding for quadratic and linear rewards such
as Forming's and Folding's), body by body and sheet by sheet, skipping a body whose random
perturbation leaves the reward unchanged (a reward reads a few bodies). The reward must then
depend on the state only through ``x`` and ``hinge_theta_bar`` (true of every registered reward).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Mapping, Sequence

import numpy as np

from sim_core import adjoint
from sim_core.control import Control
from sim_core.errors import ConfigError
from sim_core.model import Model
from sim_core.optim.actions import action_gradient, check_actions
from sim_core.simulation import Simulation
from sim_core.solver_config import SolverConfig
from sim_core.state import State

PROGRESS_WEIGHT = 0.1
"""Score per completed fraction of the horizon (ThinShellLab ``stop_step / tot_timestep * 0.1``)."""
FEASIBLE_OFFSET = 5.0
"""Added to the reward of an episode that ran to the end (ThinShellLab ``reward + 5``)."""
REWARD_FD_STEP = 1e-6
"""Central-difference step of the fallback reward gradient (m for positions, rad for rest angles)."""


def episode_horizon(task, horizon: int | None) -> int:
    """The steps of an episode of ``task``: ``horizon``, or the task's when None.

    Raises:
        ConfigError: a horizon outside ``1..task.horizon``.
    """
    steps = int(horizon if horizon is not None else task.horizon)
    if not 1 <= steps <= task.horizon:
        raise ConfigError(f"task {task.name}: episode horizon must be in 1..{task.horizon}, got {steps}")
    return steps


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
        final_state: the last state reached.
        states: every state (None unless kept).
        wrench_peak_N: the largest net contact force on an effector over the episode, N.
    """

    reward: float
    steps_done: int
    horizon: int
    infeasible: str | None
    effector_poses: dict[str, np.ndarray] = field(default_factory=dict)
    gripper: dict[str, np.ndarray] = field(default_factory=dict)
    final_state: State | None = None
    states: list[State] | None = None
    wrench_peak_N: float = 0.0

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
                             self.effector_poses, self.gripper, wrench_peak_N=self.wrench_peak_N)


def reward_state_gradient(reward: Callable[[Model, State], float], model: Model,
                          state: State) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """dR/dx and dR/dtheta_bar of a reward at ``state`` by central differences (module docstring).

    Args:
        reward: ``reward(model, state) -> float``.
        model: the model.
        state: the state (not modified).

    Returns:
        ``(dR/dx (n, 3), {sheet: dR/dtheta_bar (h,)})`` (sheets whose rest angles the reward reads).
    """
    probe = state.copy()
    h = REWARD_FD_STEP
    base = float(reward(model, probe))
    rng = np.random.default_rng(0)

    def central(block: np.ndarray) -> np.ndarray:
        """Central differences over the entries of ``block`` (a view into ``probe``)."""
        out = np.zeros(block.shape)
        keep_all = block.copy()
        block += h * rng.choice([-1.0, 1.0], size=block.shape)
        touched = float(reward(model, probe)) != base
        block[...] = keep_all
        if not touched:
            return out
        flat, grad = block.reshape(-1), out.reshape(-1)
        for k in range(flat.size):
            keep = flat[k]
            flat[k] = keep + h
            up = reward(model, probe)
            flat[k] = keep - h
            down = reward(model, probe)
            flat[k] = keep
            grad[k] = (up - down) / (2.0 * h)
        return out

    gx = np.zeros(probe.x.shape)
    for b in model.bodies.values():
        gx[b.vertex_start:b.vertex_stop] = central(probe.x[b.vertex_start:b.vertex_stop])
    gtb = {name: central(tb) for name, tb in probe.hinge_theta_bar.items()}
    return gx, {k: v for k, v in gtb.items() if np.any(v)}


class Episode:
    """A task's simulation, reset for every episode.

    Args:
        task: a :class:`~sim_core.tasks.spec.TaskSpec`.
        horizon: steps per episode (default ``task.horizon``).
        params: global parameter values to set on the model (e.g. the values an inverse task tries).
        solver_config: Newton settings (default: the task's, no dt halving, so every step has an
            implicit derivative and the score CMA-ES ranks is the one gradient ascent differentiates).

    Raises:
        ConfigError: an invalid scene or parameter name, or a horizon beyond the task's.
    """

    def __init__(self, task, horizon: int | None = None, params: Mapping[str, float] | None = None,
                 solver_config: SolverConfig | None = None) -> None:
        from sim_core.tasks.rollout import TaskEpisode

        self.task = task
        self.horizon = episode_horizon(task, horizon)
        self.runner = TaskEpisode(task, dict(params) if params else None,
                                  solver_config=solver_config or SolverConfig(dt_halvings_on_failure=0))
        self.sim: Simulation = self.runner.sim
        self.action_dim = int(task.action_dim)

    @property
    def model(self) -> Model:
        """The simulated model."""
        return self.sim.model

    def set_parameters(self, params: Mapping[str, float]) -> None:
        """Set global parameters (``Model.set_parameter``) for the following episodes.

        Raises:
            ConfigError: unknown name or a bad value.
        """
        known = set(self.model.parameter_names)
        for name, value in params.items():
            if name not in known:
                raise ConfigError(f"task {self.task.name}: unknown parameter {name!r}; known: {sorted(known)}")
            self.sim.set_parameter(name, float(value))

    def _steps(self, actions: np.ndarray, record: bool):
        """Step the episode from its initial state: ``(states, step records, controls, wrench peak N)``
        (records and controls only when ``record``)."""
        self.runner.reset()
        sim = self.sim
        states, records, controls = [sim.state.copy()], [], []
        peak = 0.0
        for row in actions:
            info = self.runner.step(row)
            if info is None:
                break
            if record:
                if info.substeps != 1:  # SolverConfig.dt_halvings_on_failure > 0: no implicit derivative
                    raise ConfigError(f"task {self.task.name}: step {len(records)} halved dt; not differentiable")
                records.append(sim.solver.last_record)
                controls.append(Control({k: v.copy() for k, v in self.runner.pose_targets.items()},
                                        dict(self.runner.gripper_targets)))
            states.append(sim.state.copy())
            for w in self.runner.wrenches().values():
                peak = max(peak, float(np.linalg.norm(w[:3])))
            if self.runner.infeasible is not None:
                break
        return states, records, controls, peak

    def _result(self, states: list[State], peak: float, keep_states: bool) -> EpisodeResult:
        final = states[-1]
        infeasible = self.runner.infeasible
        reward = float(self.task.reward(self.model, final)) if infeasible is None else float("nan")
        if infeasible is None and not np.isfinite(reward):
            infeasible = f"reward is {reward}"
        poses = {k: np.stack([s.effector_pose[k] for s in states]) for k in final.effector_pose}
        grip = {k: np.array([s.gripper_opening[k] for s in states]) for k in self.runner.gripper_targets}
        return EpisodeResult(reward, len(states) - 1, self.horizon, infeasible, poses, grip, final,
                             states if keep_states else None, peak)

    def run(self, actions: np.ndarray, keep_states: bool = False) -> EpisodeResult:
        """Roll out ``actions`` from the initial state.

        Args:
            actions: shape ``(horizon, action_dim)`` within the task's bounds.
            keep_states: keep every state (else only the final one).

        Returns:
            the :class:`EpisodeResult` (infeasible, naming the step, when it stopped early).

        Raises:
            ConfigError: bad actions.
        """
        actions = self.task.check_actions(check_actions(actions, self.horizon, self.action_dim))
        states, _, _, peak = self._steps(actions, record=False)
        return self._result(states, peak, keep_states)

    def reward_gradient(self, actions: np.ndarray, params: Sequence[str] = ()) -> tuple[EpisodeResult, np.ndarray, dict[str, float]]:
        """The episode's reward and its exact derivatives (adjoint, :mod:`sim_core.adjoint`).

        Args:
            actions: shape ``(horizon, action_dim)`` within the task's bounds.
            params: global parameter names to differentiate as well.

        Returns:
            ``(result, dR/d actions (horizon, action_dim), {param: dR/dp})``; zeros when infeasible.

        Raises:
            ConfigError: bad actions or parameter names.
        """
        actions = self.task.check_actions(check_actions(actions, self.horizon, self.action_dim))
        states, records, controls, peak = self._steps(actions, record=True)
        res = self._result(states, peak, keep_states=False)
        if not res.feasible:
            return res, np.zeros_like(actions), {p: 0.0 for p in params}
        traj = adjoint.Trajectory(states=states, records=records, controls=controls, model_revision=self.model.revision)
        gx, gtb = reward_state_gradient(self.task.reward, self.model, res.final_state)
        dL_dx = np.zeros((self.horizon + 1,) + gx.shape)
        dL_dx[-1] = gx
        g = adjoint.rollout_gradient(self.sim, traj, dL_dx, params=params, dL_dtheta_bar=gtb)
        da = action_gradient(actions, self.task.action_layout, states[0].effector_pose, g)
        return res, da, dict(g.params)
