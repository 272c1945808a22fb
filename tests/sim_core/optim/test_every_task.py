"""On every manipulation task of ``config/tasks``, a short CMA-ES run (2- or 3-step episodes,
2 generations of 3) beats the zero trajectory. Inverse tasks: tests/sim_core/optim/test_inverse_task.py."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.optim.actions import ControlPointDecoder
from sim_core.optim.evaluators import SerialEvaluator
from sim_core.optim.search import ActionSpace, new_state, optimise
from sim_core.tasks.registry import load_task, task_names
from tests.sim_core.optim.task_support import short_task

STEPS = {"separating": 2, "following": 2}  # 1464-vertex gripper scenes: 0.5 s a step; others 3 steps
MANIPULATION = [n for n in task_names() if load_task(n).kind == "manipulation"]


def test_the_tasks_are_there():
    assert {"forming", "folding_l", "lifting"} <= set(MANIPULATION)


@pytest.mark.parametrize("name", MANIPULATION)
def test_short_cma_run_beats_the_zero_trajectory(name):
    steps = STEPS.get(name, 3)
    task = short_task(name, steps)
    space = ActionSpace(ControlPointDecoder.for_task(task, steps, 1), SerialEvaluator(task, steps), task)
    zero = space.evaluator.evaluate([np.zeros((steps, task.action_dim))])[0]
    assert zero.feasible
    state = optimise(new_state("cma", 6, seed=1, sigma=task.cma_sigma, population=3), space)
    assert state.best_reward > zero.reward + 1e-6 * abs(zero.reward), (zero.reward, state.best_reward)
