"""Parallel rollouts on Ray (sim_core.optim.evaluators.RayEvaluator): a CMA-ES run whose populations
are evaluated by 2 local Ray workers gives the same episodes and best reward as serial evaluation."""

from __future__ import annotations

import pytest

from sim_core.optim.actions import ControlPointDecoder
from sim_core.optim.evaluators import RayEvaluator, SerialEvaluator
from sim_core.optim.search import ActionSpace, new_state, optimise
from tests.sim_core.optim.task_support import folding_task

pytest.importorskip("ray")


def test_two_ray_workers_match_serial_evaluation():
    task = folding_task(horizon=3)
    decoder = ControlPointDecoder.for_task(task, control_points=1)
    serial = optimise(new_state("cma", 8, seed=7, sigma=2.5, population=4),
                      ActionSpace(decoder, SerialEvaluator(task), task))
    ray_eval = RayEvaluator(task, workers=2)
    try:
        parallel = optimise(new_state("cma", 8, seed=7, sigma=2.5, population=4), ActionSpace(decoder, ray_eval, task))
    finally:
        ray_eval.close()
    assert parallel.best_reward == serial.best_reward
    assert [h.score for h in parallel.history] == [h.score for h in serial.history]
    assert len({h.reward for h in serial.history}) > 1  # the candidates differ
