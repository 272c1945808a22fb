"""Inverse tasks: identify material parameters from a task's observed motion with the optimisers of
:mod:`sim_core.optim.search`, in the search coordinates of ``thinshell sysid``.

An inverse task (``TaskSpec.kind == "inverse"``) replays its reference trajectory and rewards the
final state's closeness to the state observed at the hidden ``true_parameters``. The parameters are
searched as ``thinshell sysid`` searches them when fitting a recording
(:func:`sim_core.parameter_coordinates.parameter_spec`) - a positive scale parameter (stiffness, friction coefficient) as ``u = ln(theta / theta_0)`` within a factor 1000,
a Poisson ratio linearly - so CMA-ES steps are relative and a gradient step respects the bounds. The
episode is the same as a manipulation task's (:class:`sim_core.optim.episode.Episode`); the gradient
is the adjoint's parameter derivative (``dR/du = dR/dtheta dtheta/du``). Several points' gradients
(``gd_starts > 1``, :meth:`ParameterSpace.gd_gradients`) come from one lockstep batch of the replayed
episode, one copy per point with its own parameter values, whose adjoint passes run together
(:class:`sim_core.optim.batch_gradient.BatchedEpisodeGradients`: each copy's parameter derivatives are
those of its episode alone, to the Newton tolerance).

Tied parameters (``TaskSpec.tied``, ``{follower: leader}``) are one coordinate: a follower takes its
leader's value and its derivative adds to the leader's (``dR/du_leader = sum over the group``).

The reward is a scalar (sum of squared position errors), not a residual vector, so the least-squares
local phase of ``thinshell sysid`` does not apply; CMA-ES, Adam and the hybrid do.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from sim_core.errors import ConfigError
from sim_core.optim.episode import Episode
from sim_core.solver_config import SolverConfig
from sim_core.parameter_coordinates import ParameterSpec, parameter_spec


@dataclass
class ParameterSpace:
    """The identified parameters of an inverse task as a :class:`sim_core.optim.search.SearchSpace`.

    Both CMA-ES and gradient ascent search the sysid coordinates ``u`` (one per searched parameter:
    every identified one that is not tied to another, 0 at the start values). It is a
    :class:`~sim_core.optim.search.BatchedGradientSpace` (``gd_starts > 1``).

    Args:
        task: the inverse task.
        specs: one :class:`~sim_core.parameter_coordinates.ParameterSpec` per searched parameter (start = ``initial``).
        evaluator: batch evaluator of the task (serial or Ray) at ``horizon``.
        horizon: steps per episode.
        episode: in-process episode for gradients (built on first use when None).
        solver_config: Newton settings of the gradient episodes, single and batched (Episode's default when None).
        batched_gradients: the :class:`~sim_core.optim.batch_gradient.BatchedEpisodeGradients` of
            :meth:`gd_gradients` (built on first use when None).
    """

    task: Any
    specs: tuple[ParameterSpec, ...]
    evaluator: Any
    horizon: int
    episode: Episode | None = None
    solver_config: SolverConfig | None = None
    batched_gradients: Any = None

    def values(self, u: np.ndarray) -> dict[str, float]:
        """Values of every identified parameter at coordinates ``u`` (followers = their leader)."""
        out = {s.name: s.to_value(float(v)) for s, v in zip(self.specs, u)}
        out.update({f: out[lead] for f, lead in self.task.tied.items()})
        return out

    def actions(self) -> np.ndarray:
        """The replayed actions: the task's reference cut to the horizon, shape ``(horizon, action_dim)``."""
        ref = self.task.reference_actions
        if ref is None:
            return np.zeros((self.horizon, self.task.action_dim))
        return np.asarray(ref, dtype=float)[: self.horizon]

    def cma_start(self):
        b = np.array([s.u_bounds for s in self.specs], dtype=float)
        return np.zeros(len(self.specs)), b[:, 0], b[:, 1]

    def cma_evaluate(self, points):
        a = self.actions()
        return self.evaluator.evaluate([a] * len(points), params=[self.values(u) for u in points])

    def gd_start(self, cma_point):
        x0, low, high = self.cma_start()
        return (x0 if cma_point is None else np.array(cma_point, dtype=float)), low, high

    def gd_gradient(self, y):
        if self.episode is None:
            self.episode = Episode(self.task, self.horizon, solver_config=self.solver_config)
        values = self.values(y)
        self.episode.set_parameters(values)
        res, _, dp = self.episode.reward_gradient(self.actions(), params=list(values))
        return res.summary(), self.search_gradient(values, dp)

    def gd_gradients(self, ys):
        if self.batched_gradients is None:
            from sim_core.optim.batch_gradient import BatchedEpisodeGradients

            self.batched_gradients = BatchedEpisodeGradients(self.task, self.horizon, solver_config=self.solver_config)
        values = [self.values(y) for y in ys]
        a = self.actions()
        out = self.batched_gradients.reward_gradients([a] * len(values), values, list(self.task.identify))
        return [(res.summary(), self.search_gradient(v, dp)) for v, (res, _, dp) in zip(values, out)]

    def search_gradient(self, values: Mapping[str, float], dp: Mapping[str, float]) -> np.ndarray:
        """dR/du from the parameter derivatives (module docstring: a follower's derivative adds to its
        leader's; ``dtheta/du`` is ``theta`` for a log coordinate, the spec's scale for a linear one).

        Args:
            values: every identified parameter's value at the point (:meth:`values`).
            dp: dR/d theta of every identified parameter (zeros for an infeasible episode).

        Returns:
            dR/du, shape ``(len(specs),)``.
        """
        group = {s.name: dp[s.name] + sum(dp[f] for f, lead in self.task.tied.items() if lead == s.name)
                 for s in self.specs}
        return np.array([group[s.name] * (values[s.name] if s.log else s.scale) for s in self.specs])

    def candidate(self, phase, point):
        return self.values(point)


def parameter_space(task, evaluator, horizon: int, start: Mapping[str, float] | None = None,
                    solver_config=None) -> ParameterSpace:
    """The :class:`ParameterSpace` of an inverse task.

    Args:
        task: the inverse task (``identify`` names the parameters).
        evaluator: batch evaluator of the task.
        horizon: steps per episode.
        start: start value per identified parameter (default: the scene's values); a tied follower's,
            if given, must equal its leader's.
        solver_config: Newton settings of the gradient episodes (Episode's default when None).

    Raises:
        ConfigError: not an inverse task, no identified parameter, a start naming another parameter,
            or a follower started apart from its leader.
    """
    if task.kind != "inverse" or not task.identify:
        raise ConfigError(f"task {task.name}: not an inverse task with identified parameters (kind {task.kind!r})")
    start = dict(start or {})
    unknown = set(start) - set(task.identify)
    if unknown:
        raise ConfigError(f"task {task.name}: start values for {sorted(unknown)}, which it does not identify "
                          f"(it identifies {list(task.identify)})")
    ep = Episode(task, horizon, solver_config=solver_config)
    value = {name: float(start.get(name, ep.model.get_parameter(name))) for name in task.identify}
    for follower, leader in task.tied.items():
        if value[follower] != value[leader]:
            raise ConfigError(f"task {task.name}: {follower} is tied to {leader} but starts at {value[follower]} "
                              f"against {value[leader]}")
    specs = tuple(parameter_spec(name, value[name]) for name in task.identify if name not in task.tied)
    return ParameterSpace(task, specs, evaluator, horizon, ep, solver_config)
