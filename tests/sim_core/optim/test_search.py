"""CMA-ES, gradient ascent and the hybrid on short task episodes: each beats the zero trajectory;
a run resumed from its checkpoint continues it exactly (sim_core.optim.search)."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest

from sim_core.errors import ConfigError
from sim_core.optim.actions import ControlPointDecoder
from sim_core.optim.evaluators import SerialEvaluator
from sim_core.optim.search import ActionSpace, load_checkpoint, new_state, optimise, save_checkpoint, step
from tests.sim_core.optim.task_support import folding_task, forming_task


def _space(task, control_points=2):
    return ActionSpace(ControlPointDecoder.for_task(task, control_points=control_points), SerialEvaluator(task), task)


def _zero_reward(space):
    return space.evaluator.evaluate([np.zeros((space.decoder.horizon, space.decoder.action_dim))])[0].reward


@pytest.mark.parametrize("make", [forming_task, folding_task])
@pytest.mark.parametrize("method, episodes", [("gd", 4), ("hybrid", 9)])  # cma: test_every_task.py
def test_short_optimisation_beats_the_zero_trajectory(make, method, episodes):
    task = make(horizon=4)
    if make is forming_task:  # Forming's reference defines its target (reward 0): start from zero
        task = dataclasses.replace(task, reference_actions=None)
    space = _space(task)
    zero = _zero_reward(space)
    state = optimise(new_state(method, episodes, seed=1, sigma=task.cma_sigma, population=6), space)
    assert state.episodes_done == episodes
    assert state.best_reward > zero + 1e-3 * abs(zero) + 1e-9, (zero, state.best_reward)
    # the best candidate reproduces its reward
    assert space.evaluator.evaluate([state.best_candidate])[0].reward == pytest.approx(state.best_reward, rel=1e-12)
    if method == "gd":  # the gradient steps improve on their start too
        assert state.best_reward > state.history[0].reward
    if method == "hybrid":
        assert [h.phase for h in state.history] == ["cma"] * 6 + ["gd"] * 3


def test_resumed_run_continues_from_its_checkpoint(tmp_path):
    task = forming_task(horizon=3)
    space = _space(task, control_points=1)
    full = optimise(new_state("hybrid", 8, seed=4, sigma=2.5, population=3, hybrid_fraction=0.8), space)
    assert [h.phase for h in full.history] == ["cma"] * 6 + ["gd"] * 2
    part = new_state("hybrid", 8, seed=4, sigma=2.5, population=3, hybrid_fraction=0.8)
    while part.episodes_done < 3:  # one CMA-ES generation, then stop ("killed")
        step(part, space)
    path = save_checkpoint(tmp_path / "checkpoint.pkl", part)
    resumed = load_checkpoint(path)
    assert resumed.episodes_done == 3 and resumed.es is not None
    optimise(resumed, space)
    assert [h.score for h in resumed.history] == [h.score for h in full.history]
    assert resumed.best_score == full.best_score
    np.testing.assert_array_equal(resumed.best_candidate, full.best_candidate)


def test_deadline_stops_after_a_batch_and_the_run_goes_on():
    task = forming_task(horizon=2)
    space = _space(task, control_points=1)
    state = optimise(new_state("cma", 9, seed=0, sigma=2.5, population=3), space, deadline=time.perf_counter())
    assert state.episodes_done == 3 and not state.done and state.best_candidate is not None
    assert state.stop_reason == "deadline"
    optimise(state, space)
    assert state.episodes_done == 9 and state.done and state.stop_reason == "episode budget spent"


def test_bad_settings_and_checkpoints_are_refused(tmp_path):
    with pytest.raises(ConfigError, match="method"):
        new_state("sgd", 5)
    with pytest.raises(ConfigError, match="population"):
        new_state("cma", 5, population=1)
    bad = tmp_path / "c.pkl"
    bad.write_bytes(b"not a pickle")
    with pytest.raises(ConfigError, match="c.pkl"):
        load_checkpoint(bad)


class _Plateau:
    """Analytic search space: reward ``-|z - c|^2`` within 1 of ``c = (3, 3)``, -1 elsewhere (a
    plateau where no action touches anything: zero gradient)."""

    c = np.array([3.0, 3.0])

    def _result(self, z):
        from sim_core.optim.episode import EpisodeResult

        d2 = float(np.sum((np.asarray(z) - self.c) ** 2))
        return EpisodeResult(-d2 if d2 < 1.0 else -1.0, 1, 1, None)

    def cma_start(self):
        return np.zeros(2), np.full(2, -10.0), np.full(2, 10.0)

    def cma_evaluate(self, points):
        return [self._result(z) for z in points]

    def gd_start(self, cma_point):
        return np.array(cma_point), np.full(2, -10.0), np.full(2, 10.0)

    def gd_gradient(self, y):
        inside = np.sum((y - self.c) ** 2) < 1.0
        return self._result(y), (-2.0 * (y - self.c) if inside else np.zeros(2))

    def candidate(self, phase, point):
        return np.array(point)


def test_hybrid_hands_a_zero_gradient_back_to_cma():
    state = optimise(new_state("hybrid", 13, seed=0, sigma=0.5, population=4), _Plateau())
    assert [h.phase for h in state.history] == ["cma"] * 8 + ["gd"] + ["cma"] * 4
    assert state.episodes_done == 13 and state.done
