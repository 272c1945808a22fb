"""Batched reward gradients (sim_core.optim.batch_gradient) and the multi-start gradient phase
(``gd_starts``, sim_core.optim.search): several episodes differentiated together give each the gradient of
its own episode; K Adam runs stepped together follow the runs a single start would."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.errors import ConfigError
from sim_core.optim.batch_gradient import BatchedEpisodeGradients
from sim_core.optim.episode import Episode, EpisodeResult
from sim_core.optim.search import new_state, optimise
from sim_core.solver_config import SolverConfig
from tests.sim_core.optim.task_support import folding_task

TIGHT = SolverConfig(tol_velocity=1e-9, tol_force=5e-8, dt_halvings_on_failure=0)


def _actions(task, seed, press=6e-4):
    """Random actions within 40 % of the bounds, pressing down by at least ``press`` m per step (as
    test_action_gradient.py: Folding's dome must reach the fold)."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(-0.4, 0.4, size=(task.horizon, task.action_dim)) * task.action_high
    a[:, 2] = -np.abs(a[:, 2]) * (1 - press / 1e-3) - press
    return a


def test_batched_reward_gradients_equal_each_episodes_own():
    """Three Folding-U episodes with their own actions and parameters, differentiated together: each gets
    the reward, action gradient and parameter derivatives of Episode.reward_gradient alone."""
    task = folding_task(horizon=3)
    ep = Episode(task, solver_config=TIGHT)
    mu, rho = ep.model.get_parameter("friction.dome_sheet"), ep.model.get_parameter("sheet.density")
    k = ep.model.get_parameter("sheet.bending_stiffness")
    params = [{}, {"friction.dome_sheet": 0.5 * mu, "sheet.density": 1.3 * rho}, {"sheet.bending_stiffness": 1.3 * k}]
    names = ["sheet.bending_stiffness", "sheet.density", "sheet.yield_angle", "friction.dome_sheet",
             "contact.stiffness"]
    actions = [_actions(task, seed) for seed in (3, 4, 5)]
    got = BatchedEpisodeGradients(task, solver_config=TIGHT).reward_gradients(actions, params, names)
    for a, p, (res, da, dp) in zip(actions, params, got):
        want_res, want_da, want_dp = Episode(task, params=p, solver_config=TIGHT).reward_gradient(a, params=names)
        assert res.feasible and want_res.feasible
        assert res.reward == pytest.approx(want_res.reward, rel=1e-9)
        scale = np.abs(want_da).max()
        assert scale > 0.0
        np.testing.assert_allclose(da, want_da, rtol=1e-6, atol=1e-7 * scale)
        for name in names:
            tiny = 1e-9 * abs(want_dp["sheet.bending_stiffness"])
            assert dp[name] == pytest.approx(want_dp[name], rel=1e-6, abs=tiny), name
    assert np.abs(got[0][1] - got[2][1]).max() > 1e-3 * np.abs(got[0][1]).max()  # the episodes differ
    with pytest.raises(ConfigError, match="2 parameter sets for 3 episodes"):
        BatchedEpisodeGradients(task).reward_gradients(actions, params[:2])


class _Bowls:
    """``-|y - c|^2`` (2-D) from a given start: a stand-in search space with exact gradients, so that K Adam
    runs stepped together can be compared with K single-start runs; it keeps the points of every batch."""

    c = np.array([0.7, -0.3])

    def __init__(self, start):
        self.start = np.array(start, dtype=float)
        self.batches: list[list[np.ndarray]] = []

    def _result(self, y):
        return EpisodeResult(-float(np.sum((y - self.c) ** 2)), 1, 1, None)

    def cma_start(self):
        return np.zeros(2), np.full(2, -10.0), np.full(2, 10.0)

    def cma_evaluate(self, points):
        return [self._result(z) for z in points]

    def gd_start(self, cma_point):
        return (self.start.copy() if cma_point is None else np.array(cma_point)), np.full(2, -10.0), np.full(2, 10.0)

    def gd_gradient(self, y):
        return self._result(y), -2.0 * (y - self.c)

    def gd_gradients(self, ys):
        self.batches.append([np.array(y) for y in ys])
        return [self.gd_gradient(y) for y in ys]

    def candidate(self, phase, point):
        return np.array(point)


def test_k_gradient_runs_stepped_together_follow_their_single_start_runs():
    K, steps = 3, 5
    space = _Bowls([2.0, 1.0])
    state = optimise(new_state("gd", K * steps, seed=4, sigma=0.8, learning_rate=0.3, gd_starts=K), space)
    assert [len(b) for b in space.batches] == [K] * steps  # one batch of K gradients a step
    starts = space.batches[0]
    np.testing.assert_array_equal(starts[0], [2.0, 1.0])  # the gradient method's own start, then restarts
    assert min(np.linalg.norm(starts[i] - starts[j]) for i in range(K) for j in range(i)) > 0.1
    for k in range(K):
        alone = optimise(new_state("gd", steps, learning_rate=0.3), _Bowls(starts[k]))
        assert [h.reward for h in state.history[k::K]] == pytest.approx([h.reward for h in alone.history], rel=1e-12)
        np.testing.assert_allclose(state.adams[k]["y"], alone.adam["y"], rtol=1e-12)
    assert state.best_reward == max(h.reward for h in state.history)
    with pytest.raises(ConfigError, match="gd_starts"):
        new_state("cma", 4, gd_starts=2)


def test_hybrid_starts_its_k_runs_at_the_best_feasible_cma_candidates():
    space = _Bowls([2.0, 1.0])
    state = optimise(new_state("hybrid", 12, seed=1, sigma=0.5, population=4, gd_starts=2), space)
    phases = [h.phase for h in state.history]
    assert phases == ["cma"] * 8 + ["gd"] * 4
    best_two = sorted((h.score for h in state.history[:8]), reverse=True)[:2]
    assert [score for score, _ in state.cma_candidates] == best_two
    for (_, point), start in zip(state.cma_candidates, space.batches[0]):
        np.testing.assert_array_equal(point, start)

