"""Inverse tasks through sysid's parameter coordinates (sysid.inverse_task): the search gradient
dR/du (adjoint, u = ln theta / theta_0) against central differences of the reward, and a short
CMA-ES run from twice the hidden bending stiffness that moves toward it (Bouncing, 3 steps)."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.optim.evaluators import SerialEvaluator
from sim_core.optim.search import new_state, optimise
from sysid.inverse_task import parameter_space
from tests.sim_core.optim.task_support import short_task

NAME = "sheet.bending_stiffness"


@pytest.fixture(scope="module")
def space():
    task = short_task("bouncing", 3)
    truth = task.true_parameters[NAME]
    return parameter_space(task, SerialEvaluator(task, 3), 3, {NAME: 2.0 * truth}), truth


def test_search_gradient_matches_central_differences(space):
    sp, _ = space
    u = np.array([0.1])
    res, g = sp.gd_gradient(u)
    assert res.feasible and g[0] != 0.0
    h = 1e-4
    up, down = sp.cma_evaluate([u + h, u - h])
    # default Newton tolerances (the optimiser's): the difference quotient carries ~0.5 % of solver
    # error; a wrong chain rule (dR/dtheta without the factor theta) is off by orders of magnitude
    assert g[0] == pytest.approx((up.reward - down.reward) / (2 * h), rel=2e-2)


def test_short_cma_run_moves_toward_the_hidden_value(space):
    sp, truth = space
    start = sp.cma_evaluate([np.zeros(1)])[0].reward
    state = optimise(new_state("cma", 6, seed=3, sigma=0.3, population=3), sp)
    assert state.best_reward > start
    assert abs(np.log(state.best_candidate[NAME] / truth)) < np.log(2.0)
    assert sp.specs[0].log and sp.specs[0].initial == pytest.approx(2.0 * truth)


def test_start_must_name_identified_parameters():
    from sim_core.errors import ConfigError

    task = short_task("bouncing", 3)
    with pytest.raises(ConfigError, match="does not identify"):
        parameter_space(task, None, 3, {"sheet.density": 1.0})
    with pytest.raises(ConfigError, match="not an inverse task"):
        parameter_space(short_task("forming", 3), None, 3)
