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


class _NoFeasibleCma(_Plateau):
    """Every CMA-ES episode stops early (as on Pick-Folding, where the zero trajectory loses contact)."""

    started_from = "unset"

    def cma_evaluate(self, points):
        from sim_core.optim.episode import EpisodeResult

        return [EpisodeResult(float("nan"), 0, 1, "no contact") for _ in points]

    def gd_start(self, cma_point):
        self.started_from = cma_point
        return super().gd_start(self.c + 0.5 if cma_point is None else cma_point)


def test_hybrid_without_a_feasible_cma_point_starts_the_gradient_phase_on_its_own():
    space = _NoFeasibleCma()
    state = optimise(new_state("hybrid", 8, seed=0, sigma=0.5, population=3), space)
    assert space.started_from is None
    assert [h.phase for h in state.history] == ["cma"] * 6 + ["gd"] * 2
    assert state.best_phase == "gd" and state.best_reward > -0.5  # the descent improved on -0.5


def test_gd_gives_the_same_episodes_for_every_seed():
    # the seed drives CMA-ES's sampling only: gradient ascent starts from the task's reference (else
    # zero) and its steps are deterministic, so two seeds give bit-identical runs
    task = dataclasses.replace(forming_task(horizon=3), reference_actions=None)
    runs = [optimise(new_state("gd", 3, seed=seed), _space(task)) for seed in (0, 5)]
    assert [h.reward for h in runs[0].history] == [h.reward for h in runs[1].history]
    assert runs[0].history[-1].reward != runs[0].history[0].reward  # the steps moved
    np.testing.assert_array_equal(runs[0].best_point, runs[1].best_point)
    cma = [optimise(new_state("cma", 4, seed=seed, population=4), _space(task)) for seed in (0, 5)]
    assert [h.reward for h in cma[0].history] != [h.reward for h in cma[1].history]


def test_gd_on_a_plateau_stops_and_says_why():
    class Flat(_Plateau):
        def gd_start(self, cma_point):
            return super().gd_start(np.zeros(2))

    state = optimise(new_state("gd", 5), Flat())
    assert state.episodes_done == 1 and state.done and "zero gradient" in state.stop_reason
    cma_state = optimise(new_state("cma", 10, population=4), Flat())
    assert cma_state.episodes_done == 8 and cma_state.stop_reason.startswith("episode budget spent (what is left")


class _QuadraticEvaluator:
    """Reward ``-sum((a - target) / 1e-4)^2`` of per-step actions; keeps every evaluated sequence."""

    def __init__(self, target):
        self.target, self.seen = np.asarray(target, dtype=float), []

    def evaluate(self, actions):
        from sim_core.optim.episode import EpisodeResult

        self.seen += [np.array(a) for a in actions]
        return [EpisodeResult(-float(np.sum(((a - self.target) / 1e-4) ** 2)), 6, 6, None) for a in actions]


def _warm_space(start, target, reference):
    import types

    decoder = ControlPointDecoder(6, 2, np.full(2, 6e-5), np.full(2, -2e-3), np.full(2, 2e-3))
    task = types.SimpleNamespace(name="Quadratic", reference_actions=reference)
    return ActionSpace(decoder, _QuadraticEvaluator(target), task, start=start)


def test_reference_start_centres_cma_on_the_reference_and_evaluates_it_first():
    reference = np.outer(np.linspace(1e-3, 1.5e-3, 6), [1.0, -1.0])  # 17-25 units from zero
    target = reference + np.array([3e-4, 1.2e-4])  # 5 and 2 units from the reference
    warm = _warm_space("reference", target, reference)
    np.testing.assert_array_equal(warm.decode(np.zeros(4)), reference)
    low, high = warm.cma_start()[1:]
    np.testing.assert_allclose(high, 4e-3 / 6e-5)  # the span of the action bounds
    np.testing.assert_allclose(low, -4e-3 / 6e-5)
    state = optimise(new_state("cma", 24, seed=2, sigma=1.0, population=6), warm)
    np.testing.assert_array_equal(warm.evaluator.seen[0], reference)  # the warm start itself, first
    assert state.history[0].reward == pytest.approx(-np.sum(((reference - target) / 1e-4) ** 2))
    cold = _warm_space("zero", target, reference)
    cold_state = optimise(new_state("cma", 24, seed=2, sigma=1.0, population=6), cold)
    assert not np.array_equal(cold.evaluator.seen[0], reference)
    # same budget and seed: the search around the reference ends far closer to the target
    assert state.best_reward > state.history[0].reward > 100.0 * cold_state.best_reward
    # the best candidate is the actions it scored (reference + control points)
    assert warm.evaluator.evaluate([state.best_candidate])[0].reward == pytest.approx(state.best_reward)


def test_reference_start_needs_a_reference_and_a_known_start():
    with pytest.raises(ConfigError, match="needs the task's reference trajectory"):
        _warm_space("reference", np.zeros((6, 2)), None)
    with pytest.raises(ConfigError, match="CMA-ES start must be one of"):
        _warm_space("mean", np.zeros((6, 2)), np.zeros((6, 2)))
    with pytest.raises(ConfigError, match="base actions have shape"):
        _warm_space("zero", np.zeros((6, 2)), None).decoder.decode(np.zeros(4), np.zeros((5, 2)))


class _Bowl(_Plateau):
    """``-(y - 0.7)^2`` everywhere (1-D): Adam with a step of 2 overshoots the optimum by far."""

    c = np.array([0.7])

    def _result(self, z):
        from sim_core.optim.episode import EpisodeResult

        return EpisodeResult(-float(np.sum((np.asarray(z) - self.c) ** 2)), 1, 1, None)

    def gd_start(self, cma_point):
        return np.zeros(1), np.full(1, -10.0), np.full(1, 10.0)

    def gd_gradient(self, y):
        return self._result(y), -2.0 * (y - self.c)


def test_a_step_that_does_not_improve_backtracks_with_half_the_step():
    state = optimise(new_state("gd", 12, learning_rate=2.0), _Bowl())
    rewards = [h.reward for h in state.history]
    assert rewards[0] == pytest.approx(-0.49) and rewards[1] == pytest.approx(-1.69)  # 0 -> 2: overshoot
    assert rewards[2] == pytest.approx(-0.09)  # back at 0, half the step: 0 -> 1
    assert state.adam["lr"] <= 0.25 and state.best_reward > -1e-3  # the step shrank onto the optimum


class _BowlWithWall(_Bowl):
    """``-(y - 1.4)^2`` for y <= 1.5, infeasible beyond (a contact force over the limit, say)."""

    c = np.array([1.4])

    def _result(self, z):
        from sim_core.optim.episode import EpisodeResult

        if np.asarray(z)[0] > 1.5:
            return EpisodeResult(float("nan"), 0, 1, "max force")
        return super()._result(z)


def test_an_infeasible_step_backtracks_from_the_best_point_without_evaluating_it_again():
    state = optimise(new_state("gd", 4, learning_rate=2.0), _BowlWithWall())
    assert state.history[0].reward == pytest.approx(-1.96)  # y = 0
    assert state.history[1].infeasible == "max force"  # y = 2
    assert state.history[2].reward == pytest.approx(-0.16)  # y = 1: half the step from 0, at once
    assert state.best_reward > -0.16 - 1e-6  # (Adam's epsilon: y = 1 - 1e-8)
