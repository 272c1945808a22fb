"""Inverse tasks through sysid's parameter coordinates (sim_core.optim.inverse_task): the search gradient
dR/du (adjoint, u = ln theta / theta_0) against central differences of the reward (Bouncing; Card's
three bending stiffnesses, tied and untied), several points' gradients from one batch against each
point's own (Bouncing; Card tied), and a short CMA-ES run from twice the hidden bending stiffness that
moves toward it (Bouncing, 3 steps)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sim_core.optim.evaluators import SerialEvaluator
from sim_core.optim.search import new_state, optimise
from sim_core.solver_config import SolverConfig
from sim_core.optim.inverse_task import parameter_space
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


TIGHT = SolverConfig(tol_velocity=1e-9, tol_force=5e-8, dt_halvings_on_failure=0)
"""Newton to 1e-9 m/s with the default projected fallback: with ``projection="none"`` the third step's
indefinite Hessian stalls the line search at 4e-4 m/s for some stiffnesses (u = 0.1 + 1e-4 for card_0)."""


@pytest.mark.parametrize("tied", [True, False])
def test_card_bending_gradient_matches_central_differences(tied):
    """Card at 3 steps from 2x the hidden stiffnesses (u = 0.1 above): the adjoint's dR/du of the tied
    coordinate (all three cards) and of card_0 alone against central differences, h = 1e-3.

    The reward there is tiny (-1e-7 m^2: the cards are about 17 um rms from the observed motion), so
    the difference quotient is only meaningful through converged steps: with the default tolerances
    the third step is accepted as stalled at 2e-4 m/s (1 um per Newton update), the quotient is that of
    the stalled iterate (3.7-4x the adjoint's for card_0, changing sign with h for card_2;
    docs/benchmarks_log.md, "the Card gradient against finite differences"). Converged (:data:`TIGHT`) it
    agrees to a few 1e-4 relative (h^2 truncation: up to 7e-2 at h = 1e-2); a follower left out of the
    sum (1/3 of the tied derivative), a missing chain factor theta or a sign error is far outside.
    """
    task = short_task("card", 3)
    truth = task.true_parameters[CARDS[0]]
    if tied:
        task = dataclasses.replace(task, tied={CARDS[1]: CARDS[0], CARDS[2]: CARDS[0]})
    sp = parameter_space(task, None, 3, {n: 2.0 * truth for n in CARDS}, solver_config=TIGHT)
    u = np.full(len(sp.specs), 0.1)
    res, g = sp.gd_gradient(u)
    assert res.feasible and g[0] < 0.0  # stiffer than the observation: softening raises the reward
    h, e = 1e-3, np.eye(len(sp.specs))[0]

    def reward(point):
        sp.episode.set_parameters(sp.values(point))
        r = sp.episode.run(sp.actions())
        assert r.feasible, r.infeasible
        return r.reward

    fd = (reward(u + h * e) - reward(u - h * e)) / (2 * h)
    assert g[0] == pytest.approx(fd, rel=2e-3)


def test_tied_follower_must_start_with_its_leader(tied_space):
    from sim_core.errors import ConfigError

    sp, truth = tied_space
    with pytest.raises(ConfigError, match="is tied to"):
        parameter_space(sp.task, None, 3, {CARDS[0]: 2.0 * truth, CARDS[1]: truth, CARDS[2]: 2.0 * truth})


@pytest.mark.parametrize("name, horizon, tied, points", [("bouncing", 3, False, [0.1, -0.3, 0.4]),
                                                         ("card", 2, True, [0.1, -0.4])])
def test_batched_gradients_equal_each_points_own(name, horizon, tied, points):
    """K points' rewards and dR/du from one lockstep batch (ParameterSpace.gd_gradients: one copy of the
    replayed episode per point, with its own parameter values, the copies' reverse passes run together)
    equal ParameterSpace.gd_gradient's at each point alone, to the Newton tolerance (TIGHT: 1e-8 relative
    measured). Bouncing: one sheet, three points; Card: three sheets tied into one coordinate, so each copy's
    derivative sums its three cards' (the followers' per-copy derivatives)."""
    task = short_task(name, horizon)
    if tied:
        task = dataclasses.replace(task, tied={CARDS[1]: CARDS[0], CARDS[2]: CARDS[0]})
    sp = parameter_space(task, None, horizon, {n: 2.0 * task.true_parameters[n] for n in task.identify},
                         solver_config=TIGHT)
    ys = [np.full(len(sp.specs), u) for u in points]
    got = sp.gd_gradients(ys)
    assert len(got) == len(ys)
    for y, (res, g) in zip(ys, got):
        want_res, want_g = sp.gd_gradient(y)
        assert res.feasible and want_res.feasible
        assert res.reward == pytest.approx(want_res.reward, rel=1e-8)
        assert g.shape == want_g.shape and np.all(want_g != 0.0)
        np.testing.assert_allclose(g, want_g, rtol=1e-6)
    first = np.array([g[0] for _, g in got])
    assert np.ptp(first) > 0.1 * np.abs(first).max()  # the points differ: a copy given another's values fails
