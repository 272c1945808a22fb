"""``sim_core.settle.settle``: the bundled scene settles to a fixed point of its implicit-Euler step
within the sleeping threshold (its card then asleep); a scene that cannot come to rest is reported
after the cap, not stepped forever."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sim_core.builder import ModelBuilder
from sim_core.bundled import config_dir
from sim_core.mesh.sheet import grid_sheet
from sim_core.settle import SETTLE_TOLERANCE_FRACTION, settle
from sim_core.simulation import Simulation
from sim_core.solver import SolverConfig

SCENE = config_dir() / "scenes" / "press_slide.yaml"
GRAVITY = 9.81


def _node_like(sleeping: bool = True) -> Simulation:
    """The bundled scene with the sim node's solver settings (NumPy backend)."""
    return Simulation.from_scene(SCENE, solver_config=SolverConfig(repeat_fixed_points=True, sleeping=sleeping))


def _tight_update(sim: Simulation) -> float:
    """The largest vertex speed (m/s) of one step from ``sim``'s state under zero commands, solved to
    ``SETTLE_TOLERANCE_FRACTION * sleep_velocity`` by a fresh solver with no sleeping and no repeats:
    how far the state is from a fixed point of the step."""
    cfg = sim.solver.config
    probe = Simulation(sim.model, dt=sim.dt, solver_config=dataclasses.replace(
        cfg, tol_velocity=SETTLE_TOLERANCE_FRACTION * cfg.sleep_velocity, sleeping=False, repeat_fixed_points=False))
    probe.state = sim.state.copy()
    probe.step(sim.model.control())
    return float(np.max(np.linalg.norm(probe.state.x - sim.state.x, axis=1)) / sim.dt)


@pytest.fixture(scope="module")
def settled():
    sim = _node_like()
    initial = sim.state.copy()
    info = settle(sim, 50)
    return sim, initial, info


def test_the_initial_state_is_not_a_fixed_point_and_the_settled_one_is(settled):
    sim, initial, info = settled
    rest = sim.solver.config.sleep_velocity
    assert info.settled and info.reason == "" and 0 < info.steps <= 50, info
    # the scene file's state: a step solved to below the threshold moves it faster than the threshold
    start = _node_like(sleeping=False)
    assert _tight_update(start) > 10 * rest
    # the settled state: at rest, and a step from it moves nothing faster than the threshold
    assert not np.any(sim.state.v)
    assert info.residual_velocity <= rest
    assert _tight_update(sim) <= rest
    # the equilibrium lies within a micrometre of the scene file's state (the pad's gel sags under gravity)
    assert 0 < info.displacement == pytest.approx(np.max(np.linalg.norm(sim.state.x - initial.x, axis=1)))
    assert info.displacement < 1e-6


def test_the_settled_scene_sleeps_and_starts_at_the_initial_time(settled):
    sim, initial, info = settled
    assert info.sleeping == ("sheet",) and info.awake == ()
    assert sim.state.t == initial.t and sim.state.step_index == initial.step_index
    assert sim.solver.config.tol_velocity == SolverConfig().tol_velocity  # the solver's own settings are back
    x = sim.state.x.copy()
    for _ in range(3):  # zero commands: the card stays asleep and nothing moves
        step = sim.step(sim.model.control())
        assert step.sleeping == ("sheet",) and step.woken == ()
    assert np.array_equal(sim.state.x, x)
    assert "settled in" in info.describe() and "asleep: sheet" in info.describe()


def test_a_cap_below_the_settling_steps_is_reported():
    sim = _node_like()
    info = settle(sim, 2)
    assert not info.settled and info.steps == 2 and info.max_steps == 2
    assert info.reason == "still moving after 2 steps"
    assert "did not settle in 2 steps (cap 2)" in info.describe()
    assert settle(_node_like(), 0).reason == "no step was allowed"
    with pytest.raises(ValueError, match="max_steps must be >= 0"):
        settle(sim, -1)


def test_a_falling_sheet_cannot_settle_and_is_reported_after_the_cap():
    # a 4 x 4 sheet with nothing under it falls freely: implicit Euler gives v_n = -g n dt and a drop of
    # g dt^2 n (n + 1) / 2 after n steps, never at rest
    b = ModelBuilder()
    material = {"youngs_modulus": 1e7, "poisson_ratio": 0.3, "thickness": 5e-4, "density": 500.0,
                "bending_stiffness": 1e-4}
    b.add_sheet("sheet", grid_sheet((0.03, 0.03), (4, 4), (-0.015, -0.015, 0.0)), material)
    dt, n = 0.005, 12
    sim = Simulation(b.finalize(), dt=dt, solver_config=SolverConfig(repeat_fixed_points=True, sleeping=True))
    x_file = sim.state.x.copy()
    info = settle(sim, n)
    assert not info.settled and info.steps == n and info.reason == f"still moving after {n} steps"
    assert info.sleeping == () and info.awake == ("sheet",)
    assert info.residual_velocity == pytest.approx(GRAVITY * n * dt, rel=1e-3)
    assert info.displacement == pytest.approx(GRAVITY * dt ** 2 * n * (n + 1) / 2, rel=1e-3)
    assert sim.state.t == 0.0 and sim.state.step_index == 0
    # not settled: the sheet starts where its file puts it, at rest, not 12 steps into its fall
    assert np.array_equal(sim.state.x, x_file) and not np.any(sim.state.v)


def test_a_rest_farther_than_one_steps_tolerance_from_the_scene_state_is_not_taken():
    # the bundled scene's rest is 0.27 um from its file state (the gel's sag): under one step's Newton
    # tolerance at tol_velocity 1e-4 m/s (0.5 um), over it at 1e-6 m/s (5 nm); there the node starts
    # from the file state, which a replay of its recording also starts from
    sim = Simulation.from_scene(SCENE, solver_config=SolverConfig(repeat_fixed_points=True, sleeping=True,
                                                                  tol_velocity=1e-6))
    x_file = sim.state.x.copy()
    info = settle(sim, 400)
    assert not info.settled and "one step's Newton tolerance" in info.reason
    assert sim.dt * 1e-6 < info.displacement < 0.5 * sim.dt * 1e-4 * 2
    assert np.array_equal(sim.state.x, x_file) and not np.any(sim.state.v)
