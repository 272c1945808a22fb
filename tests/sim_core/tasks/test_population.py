"""rollout_population: a population stepped as one batch gives each member the result of rollout alone."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from sim_core.errors import ConfigError
from sim_core.tasks.registry import load_task
from sim_core.scenes.task_scene import build_task_scene
from sim_core.tasks.rollout import PopulationRollout, TaskEpisode, build_task_simulation, effector_wrench, rollout, \
    rollout_population


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


def test_population_members_copy_one_built_scene(task):
    """The members' models are copies of one build of the task's scene: equal to a fresh build, each its own
    object, so that a member's parameters stay its own."""
    fresh = build_task_scene(copy.deepcopy(task.scene))
    stiffness = fresh.get_parameter("sheet.bending_stiffness")
    pop = PopulationRollout(task, [task.reference_actions[:1]] * 3, [None, {"sheet.bending_stiffness": 2.0 * stiffness},
                                                                      None])
    models = [ep.sim.model for ep in pop.episodes]
    assert len({id(m) for m in models}) == 3
    assert [m.get_parameter("sheet.bending_stiffness") for m in models] == [stiffness, 2.0 * stiffness, stiffness]
    for m in (models[0], models[2]):
        np.testing.assert_array_equal(m.x_rest, fresh.x_rest)
        np.testing.assert_array_equal(m.initial_x, fresh.initial_x)
        np.testing.assert_array_equal(m.vertex_fixed, fresh.vertex_fixed)
        assert list(m.bodies) == list(fresh.bodies) and m.meta == fresh.meta and m.friction == fresh.friction
        for name, body in fresh.bodies.items():
            assert m.bodies[name].material == body.material
            for attr in ("triangles", "edges", "tets", "hinges"):
                a, b = getattr(m.bodies[name], attr), getattr(body, attr)
                assert (a is None) == (b is None) and (a is None or np.array_equal(a, b))
        for name, e in fresh.effectors.items():
            np.testing.assert_array_equal(m.effectors[name].vertices, e.vertices)
            np.testing.assert_array_equal(m.effectors[name].initial_pose, e.initial_pose)


def test_episode_wrenches_follow_the_state(task):
    """An episode's wrenches are those of its current state: summed again once a step replaced it."""
    ep = TaskEpisode(task)
    before = ep.wrenches()
    for row in task.reference_actions[:2]:
        assert ep.step(row) is not None
    after = ep.wrenches()
    assert after is not ep.wrenches()  # a new dict each call: a caller's edit does not reach the next
    for name, w in after.items():
        np.testing.assert_array_equal(w, effector_wrench(ep.sim, ep.sim.state, name))
    assert np.linalg.norm(after["dome"][:3] - before["dome"][:3]) > 1e-3  # the dome pressed: the force changed, N
