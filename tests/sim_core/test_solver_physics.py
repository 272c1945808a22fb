"""Physics checks of the Newton solver on analytic problems (issue: simulator core).

- free fall: implicit Euler's discrete solution x_{n+1} = x_n + dt v_n + dt^2 g, exactly;
- cantilever: clamped strip sagging under its weight vs Euler-Bernoulli w = q L^4 / (8 D);
- incline: a sheet on a plane tilted 1 degree below atan(mu) stays, 1 degree above slides with
  the analytic acceleration g (sin a - mu cos a).
"""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.builder import ModelBuilder
from sim_core.control import Control
from sim_core.errors import ConfigError, SimulationDivergedError
from sim_core.mesh.sheet import TriMesh, grid_sheet
from sim_core.model import ContactSettings
from sim_core.simulation import Simulation
from sim_core.solver import SolverConfig

G = 9.81


def _sheet_material(D: float, rho: float = 1000.0, t: float = 1e-3, E: float = 1e8, nu: float = 0.3) -> dict:
    return {"youngs_modulus": E, "poisson_ratio": nu, "thickness": t, "density": rho, "bending_stiffness": D}


def test_free_fall_matches_implicit_euler_exactly():
    b = ModelBuilder()
    b.add_sheet("sheet", grid_sheet((0.02, 0.01), (3, 2), (0, 0, 1.0)), _sheet_material(1e-3))
    sim = Simulation(b.finalize(gravity=(0, 0, -G)), dt=0.01, solver_config=SolverConfig(tol_velocity=1e-10))
    z0 = sim.state.x[:, 2].copy()
    v = 0.0
    z = z0.copy()
    for _ in range(5):
        sim.step()
        v = v - 0.01 * G
        z = z + 0.01 * v
    np.testing.assert_allclose(sim.state.x[:, 2], z, rtol=0, atol=1e-9)
    np.testing.assert_allclose(sim.state.v[:, 2], v, atol=1e-7)


@pytest.mark.parametrize("pattern", ["alternating", "regular"])
def test_cantilever_tip_deflection_matches_euler_bernoulli(pattern):
    """Strip L x W clamped along x = 0 (two vertex columns: zero slope), static under gravity.

    Resolution 41 x 5 vertices (dx = 2.5 mm), Kirchhoff bending with nu = 0 (a beam of stiffness D
    per unit width). Euler-Bernoulli: w_tip = q L^4 / (8 D), q = rho t g, with the discrete clamp at
    x = dx / 2 (the slope between the two fixed columns is zero). Quasi-static: one implicit step
    with dt = 10 s.
    """
    L, W, nx, ny = 0.1, 0.01, 41, 5
    D, rho, t = 0.1, 1000.0, 1e-3
    mesh = grid_sheet((L, W), (nx, ny), (0.0, 0.0, 0.0), pattern=pattern)
    ix = np.arange(nx * ny) % nx
    b = ModelBuilder()
    b.add_sheet("sheet", mesh, _sheet_material(D, rho, t, E=1e9, nu=0.0), fixed=np.nonzero(ix <= 1)[0])
    sim = Simulation(b.finalize(gravity=(0, 0, -G)), dt=10.0, solver_config=SolverConfig(tol_velocity=1e-9))
    sim.step()
    dx = L / (nx - 1)
    L_eff = L - dx / 2  # zero slope midway between the two fixed columns
    w_expected = rho * t * G * L_eff**4 / (8 * D)
    w_tip = -sim.state.x[ix == nx - 1, 2].mean()
    assert w_expected / L < 0.02  # small deflection regime
    assert abs(w_tip - w_expected) / w_expected < 0.05, (w_tip, w_expected)


def _incline_sim(angle_deg: float, mu: float):
    a = np.radians(angle_deg)
    R = np.array([[np.cos(a), 0, -np.sin(a)], [0, 1, 0], [np.sin(a), 0, np.cos(a)]])  # tilt about y
    flat = grid_sheet((0.02, 0.02), (3, 3), (-0.01, -0.01, 0.0))
    eps = 2e-4
    normal = R @ np.array([0.0, 0.0, 1.0])
    x = flat.x @ R.T + normal * eps * 0.999
    b = ModelBuilder()
    b.add_sheet("sheet", TriMesh(x, flat.triangles), _sheet_material(1e-3, rho=500.0, t=5e-4, E=1e8))
    b.add_plane("ramp", normal, 0.0)
    b.set_friction("sheet", "ramp", mu)
    contact = ContactSettings(stiffness=2e3, eps=eps, eps_v=1e-4)
    sim = Simulation(b.finalize(gravity=(0, 0, -G), contact=contact), dt=0.005,
                     solver_config=SolverConfig(tol_velocity=1e-8))
    downhill = R @ np.array([-1.0, 0.0, 0.0])  # the ramp descends toward -x' after the tilt
    if downhill[2] > 0:
        downhill = -downhill
    return sim, downhill, a


@pytest.mark.parametrize("offset_deg, slides", [(-1.0, False), (1.0, True)])
def test_incline_stick_slip_threshold(offset_deg, slides):
    mu = 0.5
    angle = np.degrees(np.arctan(mu)) + offset_deg
    sim, downhill, a = _incline_sim(angle, mu)
    x0 = sim.state.x.mean(axis=0)
    T = 0.3
    for _ in range(int(round(T / sim.dt))):
        sim.step()
    s = float((sim.state.x.mean(axis=0) - x0) @ downhill)
    accel = G * (np.sin(a) - mu * np.cos(a))
    if slides:
        expected = 0.5 * accel * T**2
        assert s > 2e-3
        assert abs(s - expected) / expected < 0.2, (s, expected)
    else:
        assert abs(s) < 1e-4, s


def test_nonconverging_step_names_the_step():
    b = ModelBuilder()
    b.add_sheet("sheet", grid_sheet((0.02, 0.01), (3, 2), (0, 0, 1.0)), _sheet_material(1e-3))
    sim = Simulation(b.finalize(), dt=0.01, solver_config=SolverConfig(max_iterations=1, tol_velocity=1e-14))
    sim.step(Control()) if False else None
    with pytest.raises(SimulationDivergedError, match=r"step 0 \(t = 0 s\).*did not converge"):
        sim.step()


def test_a_failed_step_is_retried_with_halved_dt(monkeypatch):
    """SolverConfig.dt_halvings_on_failure: a step whose Newton solve fails is redone as 2, 4, ...
    substeps of dt/2, dt/4, ...; the result is those substeps (here: free fall in 4 quarter steps,
    equal to a simulation at dt/4), and once the halvings are used up the failure is raised."""

    def sim(dt, halvings=0):
        b = ModelBuilder()
        b.add_sheet("sheet", grid_sheet((0.02, 0.01), (3, 2), (0, 0, 1.0)), _sheet_material(1e-3))
        return Simulation(b.finalize(gravity=(0, 0, -G)), dt=dt,
                          solver_config=SolverConfig(tol_velocity=1e-10, dt_halvings_on_failure=halvings))

    def failing_above(s, dt_max):
        single = s.solver._single_step

        def step(state_in, state_out, control, dt, guess=None):
            if dt > dt_max:
                raise SimulationDivergedError(f"step {state_in.step_index}: Newton did not converge (dt {dt:g})")
            return single(state_in, state_out, control, dt, guess=guess)

        monkeypatch.setattr(s.solver, "_single_step", step)
        return s

    retried = failing_above(sim(0.01, halvings=2), 0.004)
    info = retried.step()
    assert info.substeps == 4 and retried.state.t == pytest.approx(0.01)
    reference = sim(0.0025)
    for _ in range(4):
        reference.step()
    np.testing.assert_allclose(retried.state.x, reference.state.x, rtol=0, atol=1e-15)
    np.testing.assert_allclose(retried.state.v, reference.state.v, rtol=0, atol=1e-12)
    too_few = failing_above(sim(0.01, halvings=1), 0.004)
    x0 = too_few.state.x.copy()
    with pytest.raises(SimulationDivergedError, match=r"dt 0.005"):
        too_few.step()
    np.testing.assert_array_equal(too_few.state.x, x0)  # the state is kept when the step fails


def test_unknown_effector_in_control_is_rejected():
    b = ModelBuilder()
    b.add_sheet("sheet", grid_sheet((0.02, 0.01), (3, 2), (0, 0, 1.0)), _sheet_material(1e-3))
    sim = Simulation(b.finalize(), dt=0.01)
    with pytest.raises(ConfigError, match="unknown effector 'arm'"):
        sim.step(Control({"arm": np.array([0, 0, 0, 0, 0, 0, 1.0])}))


def test_a_position_guess_only_changes_where_newton_starts():
    """Control.position_guess: the cantilever step converges to the same solution from the guess
    (within the Newton tolerance), in one iteration when the guess is that solution, and a guess of
    the wrong shape or with NaN is refused naming the field."""
    mesh = grid_sheet((0.1, 0.01), (21, 3), (0.0, 0.0, 0.0))
    ix = np.arange(21 * 3) % 21

    def sim():
        b = ModelBuilder()
        b.add_sheet("sheet", mesh, _sheet_material(0.1, E=1e9, nu=0.0), fixed=np.nonzero(ix <= 1)[0])
        return Simulation(b.finalize(gravity=(0, 0, -G)), dt=10.0, solver_config=SolverConfig(tol_velocity=1e-9))

    cold = sim()
    info_cold = cold.step()
    solution = cold.state.x.copy()
    warm = sim()
    info_warm = warm.step(Control(position_guess=solution))
    assert info_warm.iterations == 2 < info_cold.iterations  # the guess, then its (tiny) correction
    np.testing.assert_allclose(warm.state.x, solution, rtol=0, atol=1e-8)
    # a guess halfway: same solution, fewer iterations than from the rest shape
    half = sim()
    info_half = half.step(Control(position_guess=0.5 * (solution + half.state.x)))
    np.testing.assert_allclose(half.state.x, solution, rtol=0, atol=1e-8)
    assert info_half.iterations <= info_cold.iterations
    bad = sim()
    with pytest.raises(ConfigError, match="position_guess.*shape"):
        bad.step(Control(position_guess=solution[:-1]))
    nan = solution.copy()
    nan[3, 1] = np.nan
    with pytest.raises(ConfigError, match="position_guess.*NaN"):
        bad.step(Control(position_guess=nan))


def test_reset_repeats_a_rollout_bit_for_bit_whatever_ran_before():
    """The Forming scene (hairpin sheet, self-contact, dome, table box; NumPy path): 4 benchmark
    steps, the same 4 steps again from the initial state, then ``reset`` and once more. After
    ``reset`` (:meth:`NewtonSolver.reset_caches`) the rollout equals the first bit for bit with the
    same iterations. Without it the repeated rollout differed by ~1e-17 m: the contact set's
    candidate lists and the Newton matrix's union pattern carried the first rollout's history."""
    from thinshell_ros.paths import bundled_scene

    from sim_core.scenes.task_scene import load_task_scene, task_initial_state
    from sim_core.tasks import forming_benchmark_offsets, pose_targets

    model = load_task_scene(bundled_scene("forming"))
    sim = Simulation(model)
    targets = pose_targets(model.effectors["dome"].initial_pose, forming_benchmark_offsets(4))

    def rollout():
        sim.state = task_initial_state(model)
        iterations = []
        for target in targets:
            control = Control()
            control.effector_pose_target["dome"] = target
            iterations.append(sim.step(control).iterations)
        return sim.state.x.copy(), iterations

    x_first, it_first = rollout()
    rollout()  # a history for the caches
    sim.reset()
    x_again, it_again = rollout()
    assert it_again == it_first
    assert np.array_equal(x_again, x_first)
    assert np.abs(x_first - task_initial_state(model).x).max() > 1e-4  # the rollout moved the sheet
