"""How a Newton step ends (sim_core.solver): strict and relaxed stopping tests counted in StepInfo,
substep retries with halved dt, and the error of a step that fails at every substep size."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.builder import ModelBuilder
from sim_core.errors import ConfigError, SimulationDivergedError
from sim_core.mesh.sheet import grid_sheet
from sim_core.simulation import Simulation
from sim_core.solver import RELAXED_STOPS, STRICT_STOPS, SolverConfig

G = 9.81
DT = 0.01
FALL_RESIDUAL = G * DT  # the first Newton update of free fall from rest, scaled: |g dt^2| / dt (m/s)


def _falling_sheet(config: SolverConfig, v0: float = 0.0, dt: float = DT) -> Simulation:
    """A small free sheet in gravity, moving down at ``v0`` (m/s): the incremental potential is
    quadratic in a rigid translation, so Newton's first full step is the solution."""
    b = ModelBuilder()
    material = {"youngs_modulus": 1e8, "poisson_ratio": 0.3, "thickness": 1e-3, "density": 1000.0,
                "bending_stiffness": 1e-3}
    b.add_sheet("sheet", grid_sheet((0.02, 0.01), (3, 2), (0, 0, 1.0)), material)
    sim = Simulation(b.finalize(gravity=(0, 0, -G)), dt=dt, solver_config=config)
    sim.state.v[:, 2] = -v0
    return sim


def test_a_strict_step_reports_its_stopping_test():
    sim = _falling_sheet(SolverConfig(tol_velocity=1e-8))
    info = sim.step()
    assert info.stop_reason in STRICT_STOPS and info.converged_strict and not info.needs_attention
    assert info.accepted_tolerance == 1e-8 and info.residual_velocity < 1e-8
    assert (info.relaxed_accepts, info.stalled_accepts, info.line_search_failures, info.retries) == (0, 0, 0, 0)
    assert info.substeps == 1


def test_a_stalled_step_is_accepted_at_the_declared_relaxed_tolerance_and_counted():
    # the move per iteration is capped far below the Newton update, so the residual drops by only
    # 1e-4 m/s per iteration: below 10 x tol, it has not dropped by 10 % after stall_iterations
    tol = FALL_RESIDUAL / 8.0
    config = SolverConfig(tol_velocity=tol, max_displacement=1e-6, stall_iterations=4)
    info = _falling_sheet(config).step()
    assert info.stop_reason == "stalled" and info.iterations == 5
    assert not info.converged_strict and info.needs_attention
    assert info.accepted_tolerance == pytest.approx(10.0 * tol)
    assert (info.relaxed_accepts, info.stalled_accepts) == (1, 1)
    assert tol < info.residual_velocity < 10.0 * tol
    # with the stall tolerance at the strict one the same step is not accepted
    strict = SolverConfig(tol_velocity=tol, max_displacement=1e-6, stall_iterations=4, stall_tolerance_factor=1.0,
                          max_iterations=8)
    with pytest.raises(SimulationDivergedError, match=r"step 0 \(t = 0 s\): Newton did not converge in 8 iterations"):
        _falling_sheet(strict).step()


def test_a_failed_line_search_below_the_relaxed_tolerance_is_accepted_and_counted():
    # no backtrack allowed: the first line search fails with the residual at the first Newton update
    tol = FALL_RESIDUAL / 50.0
    sim = _falling_sheet(SolverConfig(tol_velocity=tol, max_backtracks=0))
    x0 = sim.state.x.copy()
    info = sim.step()
    assert info.stop_reason == "line_search_relaxed" and info.iterations == 1
    assert (info.line_search_failures, info.relaxed_accepts, info.stalled_accepts) == (1, 1, 0)
    assert info.accepted_tolerance == pytest.approx(100.0 * tol) and not info.converged_strict
    np.testing.assert_array_equal(sim.state.x, x0)  # accepted where it stood: why it must be counted
    assert sim.step_totals.relaxed_steps == 1 and sim.step_totals.first_relaxed_step == 0
    # on the round-off test alone (the relaxed residual tolerance off): accepted, tolerance inf
    roundoff = _falling_sheet(SolverConfig(tol_velocity=tol, max_backtracks=0, line_search_tolerance_factor=1.0,
                                           stationary_slope_rtol=1e300)).step()
    assert roundoff.stop_reason == "line_search_roundoff" and roundoff.accepted_tolerance == np.inf
    assert roundoff.relaxed_accepts == 1
    # neither: the failure is raised, naming the step
    with pytest.raises(SimulationDivergedError, match=r"step 0 \(t = 0 s\): line search failed at Newton iteration 1"):
        _falling_sheet(SolverConfig(tol_velocity=tol, max_backtracks=0, line_search_tolerance_factor=1.0)).step()


def test_every_stop_reason_is_declared():
    assert set(STRICT_STOPS).isdisjoint(RELAXED_STOPS)
    assert "stalled" in RELAXED_STOPS and "velocity" in STRICT_STOPS


def test_a_step_that_fails_at_dt_succeeds_in_halved_substeps_and_reports_them():
    # 1 m/s down with at most 1 mm per iteration: a 10 ms step needs >= 11 iterations, a 5 ms
    # substep about half as many; 8 iterations allowed
    config = SolverConfig(tol_velocity=1e-8, max_displacement=1e-3, max_iterations=8, dt_halvings_on_failure=3)
    sim = _falling_sheet(config, v0=1.0)
    info = sim.step()
    assert (info.substeps, info.retries) == (2, 1) and info.needs_attention and info.converged_strict
    assert sim.state.step_index == 1 and sim.state.t == DT
    totals = sim.step_totals
    assert (totals.steps, totals.substeps, totals.retries, totals.retried_steps) == (1, 2, 1, 1)
    assert totals.first_relaxed_step == 0
    # the same two half steps taken one by one
    reference = _falling_sheet(SolverConfig(tol_velocity=1e-8, max_displacement=1e-3, max_iterations=8), v0=1.0,
                               dt=DT / 2)
    reference.step()
    reference.step()
    np.testing.assert_allclose(sim.state.x, reference.state.x, rtol=0, atol=1e-12)
    sim.reset()
    assert sim.step_totals.steps == 0


def test_a_step_that_fails_at_every_substep_size_names_the_step_and_the_retries():
    config = SolverConfig(max_iterations=1, tol_velocity=1e-14, dt_halvings_on_failure=2)
    sim = _falling_sheet(config)
    x0 = sim.state.x.copy()
    with pytest.raises(SimulationDivergedError,
                       match=r"^step 0 \(t = 0 s\): Newton failed at dt = 0.01 s and at every substep down to "
                             r"dt/4 = 0.0025 s \(2 retries, SolverConfig.dt_halvings_on_failure exhausted\); "
                             r"last failure: step 0 \(t = 0 s\): Newton did not converge in 1 iterations") as err:
        sim.step()
    assert (err.value.step_index, err.value.t) == (0, 0.0)
    np.testing.assert_array_equal(sim.state.x, x0)  # the state is kept when the step fails
    assert sim.step_totals.steps == 0


def test_a_later_substep_failure_names_the_step_it_belongs_to():
    sim = _falling_sheet(SolverConfig(tol_velocity=1e-8))
    sim.step()
    sim.solver.config = SolverConfig(max_iterations=1, tol_velocity=1e-14, dt_halvings_on_failure=1)
    with pytest.raises(SimulationDivergedError, match=r"^step 1 \(t = 0.01 s\).*last failure: step 1 \(t = 0.01 s\)") as err:
        sim.step()
    assert err.value.step_index == 1 and err.value.t == pytest.approx(DT)


@pytest.mark.parametrize("key, value, message", [
    ("stall_tolerance_factor", 0.5, "stall_tolerance_factor must be a finite number >= 1, got 0.5"),
    ("line_search_tolerance_factor", float("nan"), "line_search_tolerance_factor must be a finite number >= 1"),
    ("stationary_slope_rtol", -1.0, "stationary_slope_rtol must be a finite number >= 0, got -1.0"),
    ("dt_halvings_on_failure", -1, "dt_halvings_on_failure must be >= 0, got -1"),
])
def test_relaxed_tolerances_and_halvings_are_validated(key, value, message):
    with pytest.raises(ConfigError, match=message):
        SolverConfig(**{key: value})
