"""Reward gradients of several episodes of a task at once: the episodes stepped as one lockstep batch
(:func:`sim_core.tasks.rollout.rollout_population`'s batch, recorded by
:class:`sim_core.batch.adjoint.TrajectoryRecorder`) and their adjoint passes run together
(:func:`sim_core.batch.adjoint.batched_rollout_gradient`: one factorisation and one solve of all copies'
exact Hessians per step).

Each episode gets what :meth:`sim_core.optim.episode.Episode.reward_gradient` gives it alone, to the Newton
tolerance of the lockstep forward pass: the :class:`~sim_core.optim.episode.EpisodeResult`, dR/d actions
(the reward's state gradient by :func:`~sim_core.optim.episode.reward_state_gradient`, pulled back through
the adjoint and :func:`~sim_core.optim.actions.action_gradient`) and the parameter derivatives; zeros for
an infeasible episode (a solver failure or an early stop: the others' gradients are unchanged by it).
"""

from __future__ import annotations

import dataclasses
from typing import Mapping, Sequence

import numpy as np

from sim_core.batch.adjoint import TrajectoryRecorder, batched_rollout_gradient
from sim_core.errors import ConfigError, ThinShellError
from sim_core.optim.actions import action_gradient, check_actions
from sim_core.optim.episode import EpisodeResult, episode_horizon, reward_state_gradient
from sim_core.optim.evaluators import episode_result
from sim_core.solver_config import SolverConfig


class BatchedEpisodeGradients:
    """Reward gradients of a task's episodes, evaluated together (module docstring).

    Args:
        task: the task.
        horizon: steps per episode (default the task's).
        params: global parameter values of the episodes (a call's ``params`` are added to them for it).
        solver_config: Newton settings (default as :class:`~sim_core.optim.episode.Episode`: no dt halving);
            ``lockstep`` is set. The adjoint's solver: :meth:`adjoint_solver`.

    Raises:
        ConfigError: a horizon outside ``1..task.horizon``.
    """

    def __init__(self, task, horizon: int | None = None, params: Mapping[str, float] | None = None,
                 solver_config: SolverConfig | None = None) -> None:
        self.task = task
        self.horizon = episode_horizon(task, horizon)
        self.params = dict(params or {})
        self.solver_config = dataclasses.replace(solver_config or SolverConfig(dt_halvings_on_failure=0),
                                                 lockstep=True)

    def adjoint_solver(self, backend: str) -> str:
        """The batched adjoint's solver (:func:`~sim_core.batch.adjoint.batched_rollout_gradient`) on the concrete
        ``backend``: the batched CG where the lockstep Newton solves take it (``linear_solver="pcg"``, and any
        setting on ``taichi-cuda``), else each copy's block by its own LU of the configured direct solver."""
        if self.solver_config.linear_solver == "pcg" or backend == "taichi-cuda":
            return "pcg"
        return f"{self.solver_config.linear_solver}-blocks"

    def reward_gradients(self, actions: Sequence[np.ndarray], params: Sequence[Mapping[str, float]] | None = None,
                         grad_params: Sequence[str] = ()) -> list[tuple[EpisodeResult, np.ndarray, dict[str, float]]]:
        """Each episode's reward and its derivatives, the episodes stepped and differentiated together.

        Args:
            actions: per episode, shape ``(horizon, action_dim)`` within the task's bounds.
            params: per episode, parameter values added to the evaluator's (or None).
            grad_params: global parameter names to differentiate as well.

        Returns:
            per episode ``(result without states, dR/d actions (horizon, action_dim), {param: dR/dp})``;
            zeros for an infeasible episode.

        Raises:
            ConfigError: bad actions (naming the episode), parameter lists of the wrong length, unknown names.
        """
        from sim_core.tasks.rollout import PopulationRollout

        task, T = self.task, self.horizon
        seqs = []
        for i, a in enumerate(actions):
            try:
                seqs.append(task.check_actions(check_actions(a, T, task.action_dim)))
            except ConfigError as err:
                raise ConfigError(f"episode {i}: {err}") from err
        if params is not None and len(params) != len(seqs):
            raise ConfigError(f"batched gradients: {len(params)} parameter sets for {len(seqs)} episodes")
        if not seqs:
            return []
        plist = [{**self.params, **dict(params[i] if params is not None else {})} for i in range(len(seqs))]
        rollout = PopulationRollout(task, seqs, plist, solver_config=self.solver_config)
        recorder = TrajectoryRecorder(rollout.batch)
        results = [episode_result(r, T) for r in rollout.run(step=recorder.step)]
        zeros = {p: 0.0 for p in grad_params}
        out = [(r, np.zeros_like(a), dict(zeros)) for r, a in zip(results, seqs)]
        if not any(r.feasible for r in results):
            return out
        rows, dtb = [], []
        for ep, r in zip(rollout.episodes, results):
            if not r.feasible:
                rows.append(None)
                dtb.append(None)
                continue
            gx, gtb = reward_state_gradient(task.reward, ep.sim.model, ep.sim.state)
            dl = np.zeros((T + 1,) + gx.shape)
            dl[-1] = gx
            rows.append(dl)
            dtb.append(gtb)
        grads = batched_rollout_gradient(recorder.trajectory(), rows, grad_params, dtb,
                                         linear_solver=self.adjoint_solver(rollout.batch.backend),
                                         backend=rollout.batch.backend)
        for i, (r, g) in enumerate(zip(results, grads.gradients)):
            if r.feasible:
                if g is None:
                    raise ThinShellError(f"batched gradients: episode {i} ran to the end but has no gradient "
                                         f"({grads.failures[i]})")
                start = {k: v[0] for k, v in r.effector_poses.items()}
                out[i] = (r, action_gradient(seqs[i], task.action_layout, start, g), dict(g.params))
        return out
