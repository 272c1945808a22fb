"""``StepInfo.factorizations``: the Newton matrices a step factorised, as the linear solver counts them.

With the exact Hessian tried first, an iteration factorises once, or twice when the exact Hessian is
not positive definite and the projected one follows (``StepInfo.projected_iterations``); the last
iteration factorises nothing when the simplified Newton test ended the step
(``StepInfo.simplified_stops``, ``SolverConfig.simplified_newton_check``).
"""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.control import Control
from sim_core.simulation import Simulation
from sim_core.solver import SolverConfig
from tests.sim_core.test_adjoint import _scene


def _controls() -> list[Control]:
    """Press the gel into the card, then drag it 0.5 mm per step along x."""
    zs = [0.00026, 0.00022, 0.00022, 0.00022, 0.00022]
    xs = [0.025, 0.025, 0.0255, 0.026, 0.0265]
    return [Control({"ee": np.array([x, 0.0, z, 1.0, 0.0, 0.0, 0.0])}) for x, z in zip(xs, zs)]


@pytest.mark.parametrize("linear_solver", ["pardiso", "scipy"])
def test_factorizations_count_every_newton_matrix_factorised(linear_solver):
    sim = Simulation.from_scene(_scene(), solver_config=SolverConfig(linear_solver=linear_solver))
    counts, projected = [], 0
    for control in _controls():
        before = sim.solver.linear_solver.factorizations
        info = sim.step(control)
        assert info.factorizations == sim.solver.linear_solver.factorizations - before
        assert info.factorizations == info.iterations - info.simplified_stops + info.projected_iterations
        counts.append(info.factorizations)
        projected += info.projected_iterations
    assert all(c >= 1 for c in counts)
    if linear_solver == "pardiso":
        assert projected >= 1  # the press's first step needs the projected fallback: both are counted


def test_projection_only_config_factorises_once_per_iteration():
    sim = Simulation.from_scene(_scene(), solver_config=SolverConfig(exact_hessian_first=False))
    infos = [sim.step(c) for c in _controls()[:2]]
    assert all(i.factorizations == i.iterations and i.projected_iterations == i.iterations for i in infos)
