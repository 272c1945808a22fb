"""Simulation's solver, built at its first use: settings and backend read without it, the same steps bit for bit
as a solver built at once; NewtonSolver builds one contact set, and one more at each cache reset."""

from __future__ import annotations

import copy

import numpy as np
import pytest

import sim_core.simulation
import sim_core.solver
from sim_core.scenes.task_scene import task_initial_state
from sim_core.simulation import Simulation
from sim_core.solver import NewtonSolver
from sim_core.solver_config import SolverConfig
from tests.support.batch_copies import MOTIONS, control, pad_model
from tests.support.counting import counting


@pytest.fixture(scope="module")
def model():
    return pad_model()


def _steps(sim: Simulation, count: int = 3) -> list[np.ndarray]:
    pose0 = sim.state.effector_pose["pad"].copy()
    out = []
    for k in range(count):
        sim.step(control(pose0, MOTIONS[1], k))
        out.append(sim.state.x.copy())
    return out


def test_solver_is_built_at_its_first_use_and_steps_as_one_built_at_once(model, monkeypatch):
    config = SolverConfig(max_iterations=40)
    eager = Simulation(copy.deepcopy(model), solver_config=config)
    eager.state = task_initial_state(eager.model)
    assert eager.solver.config is config  # built here, before the parameter is set (notify_model_changed)
    eager.set_parameter("pad.youngs_modulus", 6e5)
    built = counting(monkeypatch, sim_core.simulation, "NewtonSolver")
    lazy = Simulation(copy.deepcopy(model), solver_config=config)
    lazy.state = task_initial_state(lazy.model)
    lazy.set_parameter("pad.youngs_modulus", 6e5)
    lazy.reset()
    lazy.state = task_initial_state(lazy.model)
    assert lazy.solver_config is config and lazy.backend == "numpy" and lazy.step_totals.steps == 0
    assert built == []  # settings, backend, parameters and a reset need no solver
    x0 = lazy.state.x.copy()
    x_lazy = _steps(lazy)
    assert len(built) == 1 and lazy.solver is built[0] and lazy.solver.config is config
    x_eager = _steps(eager)
    for a, b in zip(x_lazy, x_eager):
        np.testing.assert_array_equal(a, b)
    assert lazy.last_info.iterations == eager.last_info.iterations >= 1
    assert np.max(np.abs(x_lazy[-1] - x0)) > 1e-4  # the pad pressed the sheet: the steps moved it


def test_newton_solver_builds_one_contact_set_and_a_new_one_at_each_reset(model, monkeypatch):
    made = counting(monkeypatch, sim_core.solver, "ContactSet")
    solver = NewtonSolver(model)
    assert len(made) == 1 and solver.contact is made[0]
    solver.reset_caches()
    assert len(made) == 2 and solver.contact is made[1]
