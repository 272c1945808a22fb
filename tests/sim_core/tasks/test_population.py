"""rollout_population: a population stepped as one batch gives each member the result of rollout alone."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.errors import ConfigError
from sim_core.tasks.registry import load_task
from sim_core.tasks.rollout import build_task_simulation, rollout, rollout_population


@pytest.fixture(scope="module")
def task():
    return load_task("folding_u")


def test_population_members_match_separate_rollouts(task):
    ref = task.reference_actions[:3]
    rng = np.random.default_rng(3)
    pushed = np.clip(ref + rng.uniform(-1.0, 1.0, ref.shape) * 0.5 * task.action_high, task.action_low, task.action_high)
    population = [ref, pushed, ref[:2]]  # different actions, one member shorter
    stiffness = build_task_simulation(task).get_parameter("sheet.bending_stiffness")
    params = [None, {"sheet.bending_stiffness": 3.0 * stiffness}, None]
    got = rollout_population(task, population, params)
    assert len(got) == 3
    for actions, p, res in zip(population, params, got):
        alone = rollout(task, actions, p)
        assert res.steps_done == alone.steps_done == len(actions) and res.infeasible is None
        assert res.reward == pytest.approx(alone.reward, rel=1e-9, abs=1e-12)
        for k in alone.effector_poses:
            np.testing.assert_allclose(res.effector_poses[k], alone.effector_poses[k], atol=1e-12)
        for k in alone.wrench:
            np.testing.assert_allclose(res.wrench[k], alone.wrench[k], atol=1e-6)
        assert [i.iterations for i in res.step_infos] == [i.iterations for i in alone.step_infos]
    assert abs(got[0].reward - got[1].reward) > 1e-9  # the members differ: the comparison could fail


def test_population_errors_name_the_member(task):
    bad = np.zeros((2, task.action_dim))
    bad[1, 0] = 1.0  # far outside the per-step bound
    with pytest.raises(ConfigError, match="population member 1: .*action\\[1\\]\\[0\\]"):
        rollout_population(task, [np.zeros((2, task.action_dim)), bad])
    with pytest.raises(ConfigError, match="2 parameter sets for 1"):
        rollout_population(task, [np.zeros((1, task.action_dim))], [{}, {}])
    assert rollout_population(task, []) == []
