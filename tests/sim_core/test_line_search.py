"""The Newton solver's backtracking line search (issue: simulator core, "line search with an Armijo
condition"; DESIGN.md: ThinShellLab accepted steps that raised the energy, we do not).

Tested through the solver's public behaviour: every point at which the solver evaluates the
incremental potential is recorded (a wrapper on ``InertiaPotential.energy``, which the line search
calls once per new trial point), the Newton iterations are rebuilt from them (trial points of one
iteration lie on one ray from the iterate, at halving step lengths), and the incremental potential
E is re-evaluated independently from the step's terms (``NewtonSolver.last_record.terms``).
"""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.builder import ModelBuilder
from sim_core.energies.gravity.reference import GravityPotential
from sim_core.energies.inertia.reference import InertiaPotential
from sim_core.errors import SimulationDivergedError
from sim_core.mesh.sheet import grid_sheet
from sim_core.model import ContactSettings
from sim_core.simulation import Simulation
from sim_core.solver import SolverConfig

G = 9.81
ARMIJO_C = 1e-4
MATERIAL = {"youngs_modulus": 1e8, "poisson_ratio": 0.3, "thickness": 5e-4, "density": 1000.0, "bending_stiffness": 1e-3}


def _falling_sheet(height: float, dt: float, **config) -> Simulation:
    """A 3 x 2 sheet ``height`` (m) above a ground plane (k_c = 2e4 N/m, eps = 0.4 mm), at rest."""
    b = ModelBuilder()
    b.add_sheet("sheet", grid_sheet((0.02, 0.01), (3, 2), (0.0, 0.0, height)), MATERIAL)
    b.add_plane("ground", (0.0, 0.0, 1.0), 0.0)
    model = b.finalize(gravity=(0.0, 0.0, -G), contact=ContactSettings(stiffness=2e4, eps=4e-4))
    return Simulation(model, dt=dt, solver_config=SolverConfig(armijo_c=ARMIJO_C, **config))


def _record_trial_points(monkeypatch) -> list[np.ndarray]:
    """Copies of every point at which the solver evaluates the inertia energy, in call order."""
    points: list[np.ndarray] = []
    energy = InertiaPotential.energy

    def recording(self, x):
        points.append(np.array(x, copy=True))
        return energy(self, x)

    monkeypatch.setattr(InertiaPotential, "energy", recording)
    return points


def _iterations(points: list[np.ndarray]) -> list[tuple[np.ndarray, list[np.ndarray]]]:
    """``[(iterate x_k, its trial points in order)]``: a point continues the current iteration when
    its offset from x_k is half the previous trial's (alpha halved), else it is the first trial of
    the next iteration, whose iterate is the last trial point (the accepted one)."""
    out = [(points[0], [])]
    for p in points[1:]:
        base, trials = out[-1]
        if trials and np.allclose(p - base, 0.5 * (trials[-1] - base), rtol=1e-9, atol=1e-15):
            trials.append(p)
        elif trials:
            out.append((trials[-1], [p]))
        else:
            trials.append(p)
    return out


def test_backtracking_accepts_only_armijo_points_and_the_energy_decreases(monkeypatch):
    """A sheet 1 mm above the ground, at rest, stepped with dt = 0.1 s: the first Newton step (no
    contact at x^n, the quadratic model is free fall, g dt^2 = 98 mm, capped at
    ``max_displacement`` = 2.2 mm) lands 1.2 mm below the ground where the penalty energy
    (k_c / 2 (d - eps)^2) exceeds the gravity gained, so the line search must backtrack.

    Asserts: the step backtracked (``StepInfo.backtracks > 0``), as many rejected trial points as
    backtracks were evaluated, every rejected point violates and every accepted iterate satisfies
    E(x_k + s) <= E(x_k) + c g(x_k).s (J), E decreases strictly from iterate to iterate, and the
    step ends on the ground (sheet resting at d < eps: the contact carries its weight).
    """
    sim = _falling_sheet(0.001, dt=0.1)
    points = _record_trial_points(monkeypatch)
    info = sim.step()
    record = sim.solver.last_record
    free = record.free_dofs

    def energy(x):
        return sum(p.energy(x) for p in record.terms)

    def gradient(x):
        g = sum(p.gradient(x) for p in record.terms).reshape(-1)
        g[~free] = 0.0
        return g

    monkeypatch.undo()  # the checks below evaluate energies themselves
    iterations = _iterations(points)
    assert info.backtracks > 0
    rejected = sum(len(trials) - 1 for _, trials in iterations)
    assert rejected == info.backtracks, (rejected, info.backtracks)
    energies = [energy(iterations[0][0])]
    for x_k, trials in iterations:
        e_k, g_k = energy(x_k), gradient(x_k)
        for trial in trials[:-1]:  # rejected: sufficient decrease violated
            s = (trial - x_k).reshape(-1)
            assert energy(trial) > e_k + ARMIJO_C * float(g_k @ s)
        accepted = trials[-1]
        s = (accepted - x_k).reshape(-1)
        assert float(g_k @ s) < 0.0  # a descent direction
        assert energy(accepted) <= e_k + ARMIJO_C * float(g_k @ s)
        energies.append(energy(accepted))
    assert np.all(np.diff(energies) < 0.0), energies
    np.testing.assert_array_equal(iterations[-1][1][-1], sim.state.x)  # the last accepted point is the result
    z = sim.state.x[:, 2]
    assert np.all(z > 0.0) and np.all(z < 4e-4), z


def test_no_decrease_along_the_newton_direction_raises_naming_the_step(monkeypatch):
    """A gravity gradient of the wrong sign and three times too large (at the start of step 1 of a
    free fall the true gradient of E is 2 m g up, the solver sees 2 m g down) makes the Newton
    direction (up) an ascent direction of the energy: no step length gives a decrease, the
    line search halves ``max_backtracks`` times and the solver raises
    :class:`SimulationDivergedError` naming the step, its time and the Newton iteration; the
    state is left as it was."""
    sim = _falling_sheet(1.0, dt=0.01)
    sim.step()  # step 0 converges
    gradient = GravityPotential.gradient
    monkeypatch.setattr(GravityPotential, "gradient", lambda self, x: -3.0 * gradient(self, x))
    x_before = sim.state.x.copy()
    with pytest.raises(SimulationDivergedError,
                       match=r"step 1 \(t = 0\.01 s\): line search failed at Newton iteration 1 \(no decrease"):
        sim.step()
    np.testing.assert_array_equal(sim.state.x, x_before)
