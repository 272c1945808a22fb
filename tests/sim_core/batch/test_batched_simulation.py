"""BatchedSimulation: per copy the states of separate runs; a failing copy is reported, the others finish."""

from __future__ import annotations

import numpy as np
import pytest

import sim_core.simulation
import sim_core.solver
from sim_core.batch import BatchedSimulation
from sim_core.control import Control
from sim_core.errors import ConfigError
from sim_core.scenes.task_scene import build_task_scene, task_initial_state
from sim_core.simulation import Simulation
from sim_core.solver_config import SolverConfig
from tests.support.batch_copies import MOTIONS, PARAMS, STEPS, control, pad_model, separate_run
from tests.support.counting import counting
from tests.support.press_scenes import pad_scene, paper_sheet

@pytest.fixture(scope="module")
def model():
    return pad_model()


def _batch(model, configs=None):
    return BatchedSimulation.from_model(model, 3, params=PARAMS, state=task_initial_state(model), solver_config=configs)


def test_batch_of_three_gives_the_states_of_three_separate_runs(model):
    batch = _batch(model)
    pose0 = batch.states[0].effector_pose["pad"].copy()
    per_step = []
    for k in range(STEPS):
        res = batch.step([control(pose0, MOTIONS[i], k) for i in range(3)])
        assert res.failed_now == [] and all(info is not None and info.iterations >= 1 for info in res.infos)
        per_step.append([s.copy() for s in batch.states])
    tol = SolverConfig().tol_velocity * 0.005  # the Newton tolerance as a displacement per 5 ms step, m
    for i in range(3):
        alone = separate_run(model, PARAMS[i], MOTIONS[i])
        for k in range(STEPS):
            got, ref = per_step[k][i], alone[k]
            assert np.max(np.abs(got.x - ref.x)) <= tol, (i, k)
            assert np.max(np.abs(got.contact_force - ref.contact_force)) <= 1e-6 * max(1.0, np.abs(ref.contact_force).max())
            assert got.step_index == ref.step_index == k + 1
    # the copies really differ (own actions and parameters): the comparison above could fail
    x = batch.positions()
    assert x.shape == (3, model.vertex_count, 3)
    assert min(np.max(np.abs(x[0] - x[1])), np.max(np.abs(x[0] - x[2])), np.max(np.abs(x[1] - x[2]))) > 100 * tol
    assert batch.sims[1].get_parameter("pad.youngs_modulus") == 6e5 and batch.sims[0].get_parameter("pad.youngs_modulus") == 3e5


def test_a_copy_that_diverges_is_reported_and_the_others_finish(model):
    failing = SolverConfig(max_iterations=1)  # Newton cannot converge in one iteration under the pad's contact
    batch = _batch(model, [SolverConfig(), failing, SolverConfig()])
    start = batch.states[1].x.copy()
    pose0 = batch.states[0].effector_pose["pad"].copy()
    failed_at = None
    for k in range(STEPS):
        res = batch.step([control(pose0, MOTIONS[i], k) for i in range(3)])
        if res.failed_now:
            assert res.failed_now == [1] and res.infos[1] is None and failed_at is None
            failed_at = k
        if failed_at is not None and k > failed_at:
            assert not res.stepped[1]  # a failed copy is not stepped again
    assert failed_at == 0
    assert batch.failures[0] is None and batch.failures[2] is None
    assert batch.failures[1].startswith("step 0 ")  # the solver's message names the step
    assert list(batch.active) == [True, False, True]
    np.testing.assert_array_equal(batch.states[1].x, start)  # the last good state is kept
    tol = SolverConfig().tol_velocity * 0.005
    for i in (0, 2):
        alone = separate_run(model, PARAMS[i], MOTIONS[i])
        assert batch.states[i].step_index == STEPS
        assert np.max(np.abs(batch.states[i].x - alone[-1].x)) <= tol
    batch.reset()
    assert list(batch.active) == [True, True, True] and batch.states[0].step_index == 0


def test_copies_must_be_copies_of_one_scene(model):
    other = build_task_scene(pad_scene({"sheet": paper_sheet((0.03, 0.03), (6, 6), (-0.015, -0.015, 0.0))}, 6e-4, []))
    with pytest.raises(ConfigError, match="copy 1 is not a copy"):
        BatchedSimulation([Simulation(model), Simulation(other)])
    sim = Simulation(model)
    with pytest.raises(ConfigError, match="share a model"):
        BatchedSimulation([sim, Simulation(model)])
    with pytest.raises(ConfigError, match="batch copy 1: .*youngs_modulus"):
        BatchedSimulation.from_model(model, 2, params=[{}, {"pad.youngs_modulus": -1.0}])
    with pytest.raises(ConfigError, match="3 controls for a batch of 2"):
        BatchedSimulation.from_model(model, 2).step([None] * 3)
    two = BatchedSimulation.from_model(model, 2, state=task_initial_state(model))
    bad = Control(effector_pose_target={"pad": np.full(7, np.nan)})
    with pytest.raises(ConfigError, match="batch copy 1: effector 'pad' pose target is not finite"):
        two.step([None, bad])
    with pytest.raises(ConfigError, match="batch copy 0: unknown effector 'dome'"):
        two.step([Control(effector_pose_target={"dome": np.zeros(7)}), None])
    assert [s.state.step_index for s in two.sims] == [0, 0]  # no copy moved
    with pytest.raises(ConfigError, match="batch_size"):
        BatchedSimulation.from_model(model, 0)


def test_lockstep_copies_build_no_solver_and_a_reset_clears_the_stacked_caches(model, monkeypatch):
    copies_built = counting(monkeypatch, sim_core.simulation, "NewtonSolver")
    contact_sets = counting(monkeypatch, sim_core.solver, "ContactSet")
    batch = BatchedSimulation.from_model(model, 3, params=PARAMS, state=task_initial_state(model),
                                         solver_config=SolverConfig(lockstep=True))
    pose0 = batch.states[0].effector_pose["pad"].copy()
    controls = [control(pose0, MOTIONS[i], 0) for i in range(3)]
    x0 = batch.positions()
    first = batch.step(controls)
    x_first = batch.positions()
    # the stacked solver's contact set only: no copy built a solver, the fresh stacked solver's caches not reset
    assert copies_built == [] and len(contact_sets) == 1 and batch.lockstep.solver.contact is contact_sets[0]
    batch.reset()
    batch.sims[0].state, batch.sims[1].state, batch.sims[2].state = (task_initial_state(s.model) for s in batch.sims)
    again = batch.step(controls)
    # a stepped solver's caches are cleared for the new states: the same controls give the same step bit for bit
    assert len(contact_sets) == 2 and batch.lockstep.solver.contact is contact_sets[1]
    np.testing.assert_array_equal(batch.positions(), x_first)
    assert [i.iterations for i in again.infos] == [i.iterations for i in first.infos]
    assert np.max(np.abs(x_first - x0)) > 1e-4 and copies_built == []  # the step moved the pads
