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


CARDS = [f"card_{i}.bending_stiffness" for i in range(3)]


@pytest.fixture(scope="module")
def tied_space():
    """Card's three bending stiffnesses (equal hidden values) tied into one searched coordinate."""
    import dataclasses

    task = dataclasses.replace(short_task("card", 3), tied={CARDS[1]: CARDS[0], CARDS[2]: CARDS[0]})
    truth = task.true_parameters[CARDS[0]]
    return parameter_space(task, SerialEvaluator(task, 3), 3, {n: 2.0 * truth for n in CARDS}), truth


def test_tied_parameters_are_one_coordinate(tied_space):
    sp, truth = tied_space
    assert [s.name for s in sp.specs] == [CARDS[0]]
    assert sp.values(np.array([np.log(0.5)])) == pytest.approx({n: truth for n in CARDS})


def test_tied_gradient_is_the_sum_over_the_group(tied_space):
    """Moving the one tied coordinate moves all three stiffnesses: its derivative is the sum of the
    untied derivatives at the same values (the same adjoint; the chain factor theta is shared)."""
    sp, truth = tied_space
    u = np.array([0.1])
    res, g = sp.gd_gradient(u)
    untied = parameter_space(short_task("card", 3), None, 3, {n: 2.0 * truth for n in CARDS})
    res_u, g_u = untied.gd_gradient(np.full(3, 0.1))
    assert res.feasible and res.reward == pytest.approx(res_u.reward, rel=1e-12)
    assert np.all(g_u != 0.0) and np.ptp(g_u) > 0.0  # the three cards respond differently
    assert g[0] == pytest.approx(g_u.sum(), rel=1e-9)


def test_tied_follower_must_start_with_its_leader(tied_space):
    from sim_core.errors import ConfigError

    sp, truth = tied_space
    with pytest.raises(ConfigError, match="is tied to"):
        parameter_space(sp.task, None, 3, {CARDS[0]: 2.0 * truth, CARDS[1]: truth, CARDS[2]: 2.0 * truth})
