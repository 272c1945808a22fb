"""Batched evaluation (sim_core.optim.evaluators.BatchedEvaluator): a CMA-ES run whose populations are
evaluated as one batch of scene copies gives the same episodes and best reward as serial evaluation:
exactly when the copies are stepped one after another, to the Newton tolerance in lockstep (the
default; at a tight tolerance the scores agree to 1e-6)."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.errors import ConfigError
from sim_core.optim.actions import ControlPointDecoder
from sim_core.optim.evaluators import BatchedEvaluator, SerialEvaluator, make_evaluator
from sim_core.optim.search import ActionSpace, new_state, optimise
from sim_core.solver_config import SolverConfig
from tests.sim_core.optim.task_support import folding_task


TIGHT = SolverConfig(dt_halvings_on_failure=0, tol_velocity=1e-7)
"""Newton settings at which a lockstep batch and separate runs agree to about 1e-8 in the rewards."""


def test_batched_cma_population_matches_serial_evaluation():
    task = folding_task(horizon=3)
    decoder = ControlPointDecoder.for_task(task, control_points=1)
    serial = optimise(new_state("cma", 8, seed=7, sigma=2.5, population=4),
                      ActionSpace(decoder, SerialEvaluator(task, solver_config=TIGHT), task))
    evaluator = make_evaluator(task, batched=True, solver_config=TIGHT)
    assert evaluator.solver_config.lockstep  # the population is one lockstep batch
    batched = optimise(new_state("cma", 8, seed=7, sigma=2.5, population=4), ActionSpace(decoder, evaluator, task))
    assert batched.best_reward == pytest.approx(serial.best_reward, rel=1e-6)
    np.testing.assert_allclose([h.score for h in batched.history], [h.score for h in serial.history], rtol=1e-6)
    assert len({h.reward for h in serial.history}) > 1  # the candidates differ


def test_sequential_batch_matches_serial_evaluation_exactly():
    task = folding_task(horizon=2)
    rng = np.random.default_rng(3)
    actions = [rng.uniform(-1.0, 1.0, (2, task.action_dim)) * 0.5 * (task.action_high - task.action_low) / 2
               for _ in range(3)]
    want = SerialEvaluator(task).evaluate(actions)
    got = BatchedEvaluator(task, lockstep=False).evaluate(actions)
    assert [g.reward for g in got] == pytest.approx([w.reward for w in want], rel=1e-12)


def test_batched_parameters_per_sequence_match_serial():
    task = folding_task(horizon=2)
    a = np.zeros((2, task.action_dim))
    serial = SerialEvaluator(task)
    d0 = serial.episode.model.get_parameter("sheet.bending_stiffness")
    params = [{"sheet.bending_stiffness": d0}, {"sheet.bending_stiffness": 20.0 * d0}]
    want = serial.evaluate([a, a], params)
    # one after another (exactly the serial episodes): the stiff copy's fold has two equilibria within
    # reach of its second step, and which one Newton finds depends on rounding (the lockstep batch's
    # translated copy finds the other one)
    got = BatchedEvaluator(task, lockstep=False).evaluate([a, a], params)
    for g, w in zip(got, want):
        assert g.steps_done == w.steps_done and g.infeasible == w.infeasible
        assert g.reward == pytest.approx(w.reward, rel=1e-9, abs=1e-15)
        assert g.wrench_peak_N == pytest.approx(w.wrench_peak_N, rel=1e-6, abs=1e-9)
    assert got[0].reward != got[1].reward  # the parameters reach the copies
    with pytest.raises(ConfigError, match="batched"):
        make_evaluator(task, workers=2, batched=True)
