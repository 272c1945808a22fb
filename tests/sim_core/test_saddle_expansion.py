"""A Newton step that starts at a saddle of its incremental potential: a card buckling under a sliding pad.

A pad on a series spring (the joint drive step, :mod:`sim_core.drive_compression`) is pressed onto a card clamped
at one edge and slid towards the clamp: the friction drags the card into compression and, at the slide's fifth step,
it buckles. The flat card is then a saddle of the step's incremental potential: the exact Hessian is indefinite
(its negative curvature on the card), the Newton matrix is projected, and the projected update moves away from the
saddle by a fraction of the way a step. That is the state in which the joint drive step of nominal_s101 from +30 %
stalled at step 189 (docs/benchmarks_log.md, session 59, 49stall). Checked: the expansion of such an iteration's step
(``SolverConfig.max_expansions``, :meth:`sim_core.solver.NewtonSolver._expansion`) leaves the saddle in a few
iterations where the projected updates alone take most of the step's iteration limit, to the same minimum, every
step solved jointly (no secant retry); steps whose Newton matrices were exact are bitwise the same with or without
it; and the quadratic forms it reads against the dense matrices.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from sim_core.control import Control
from sim_core.errors import ConfigError
from sim_core.scenes import load_scene
from sim_core.series_drive import SeriesSpringDrive
from sim_core.simulation import Simulation
from sim_core.solver_config import SolverConfig
from sim_core.symmetric_pattern import upper_quadratic_form

DOWN = np.array([0.0, 0.0, -1.0])
ANCHOR_DEPTH = 3.0e-3  # m below the card's top: about 8 N on the 3,000 N/m spring
BUCKLING_STEP = 18  # the step (0-based) at which the card leaves the flat saddle


def _scene() -> dict:
    """A 40 x 20 mm card (13 x 7 vertices, 0.3 mm, a playing card's bending stiffness) clamped at x = -30 mm on a
    frictionless table, under the tactile pad at x = 0 (gel-card friction 0.8), with gravity."""
    return {
        "version": 1, "name": "card_buckling", "dt": 0.01, "gravity": [0.0, 0.0, -9.81],
        "table": {"height": 0.0, "friction": 0.0},
        "sheet": {"size": [0.04, 0.02], "resolution": [13, 7], "thickness": 0.0003, "density": 700.0,
                  "origin": [-0.03, -0.01, 0.00015], "clamped_edge": "x0",
                  "material": {"youngs_modulus": 3.0e9, "poisson_ratio": 0.3, "bending_stiffness": 0.0074}},
        "sensors": {"tactile": {"effector": "ee", "gel_size": [0.0186, 0.0143, 0.004],
                                "gel_material": {"youngs_modulus": 3.0e5, "poisson_ratio": 0.45, "density": 1100.0},
                                "friction": 0.8, "marker_grid": [3, 3], "marker_pitch": 0.004,
                                "camera": {"fx": 300.0, "fy": 300.0, "cx": 160.0, "cy": 120.0, "width": 320,
                                           "height": 240, "distance": 0.025}}},
        "effectors": {"ee": {"initial_pose": [0.0, 0.0, 0.0015, 1.0, 0.0, 0.0, 0.0]}},
        "simulation": {"gel_resolution": [4, 3, 2]},
    }


def _path() -> list[tuple[float, float]]:
    """The anchor's (x, z), m: down in 10 steps, 3 steps of dwell, then the slide towards the clamp at 2 mm/s."""
    bottom = 0.0003 - ANCHOR_DEPTH
    down = [(0.0, 0.0015 + (bottom - 0.0015) * k / 10) for k in range(1, 11)]
    return down + [(0.0, bottom)] * 3 + [(-0.0002 * k, bottom) for k in range(1, 7)]


def _slide(max_expansions: int | None = None):
    """The pad pressed and slid through the joint drive step, each step to a replay's 1e-7 m/s: per step the drive's
    result, the solver's :class:`~sim_core.step_info.StepInfo` and the positions."""
    config = SolverConfig(tol_velocity=1e-7) if max_expansions is None else SolverConfig(
        tol_velocity=1e-7, max_expansions=max_expansions)
    sim = Simulation(load_scene(_scene()), dt=0.01, solver_config=config)
    gel = sim.model.bodies[sim.model.sensors["tactile"].gel_body].vertices
    drive = SeriesSpringDrive("ee", 3000.0, gel, force_tolerance=1e-3, damping=30.0, solve="joint")
    infos = []
    step = sim.solver.step

    def recorded(*args, **kwargs):
        infos.append(step(*args, **kwargs))
        return infos[-1]

    sim.solver.step = recorded
    b, slope, steps = 0.0, 0.0, []
    for x, z in _path():
        result = drive.step(sim, Control({"ee": np.array([x, 0.0, z, 1.0, 0.0, 0.0, 0.0])}), DOWN, start=b,
                            contact_slope=slope)
        b, slope = result.compression, result.contact_slope
        steps.append((result, infos[-1], sim.state.x.copy()))
    return sim, steps


def test_a_buckling_card_leaves_the_saddle_in_a_few_newton_iterations():
    sim, steps = _slide()
    _, slow = _slide(max_expansions=0)
    card = slice(sim.model.bodies["sheet"].vertex_start, sim.model.bodies["sheet"].vertex_stop)
    assert all(result.joint and result.converged for result, _, _ in steps)  # no secant retry
    result, info, x = steps[BUCKLING_STEP]
    _, info_slow, x_slow = slow[BUCKLING_STEP]
    # the step starts at the saddle: the exact Hessian indefinite, projected iterations
    assert info_slow.projected_iterations > 30 and info_slow.iterations > 40  # of the 60 allowed
    assert info.expansions > 0 and info.iterations < 25
    assert info.converged_strict and info_slow.converged_strict
    # the card buckles (lifts well off the table), to the same minimum
    assert np.max(x[card, 2]) > 5e-4
    assert np.max(np.abs(x - x_slow)) < 1e-8  # the Newton tolerance: 1e-7 m/s over 10 ms
    assert result.compression == pytest.approx(slow[BUCKLING_STEP][0].compression, abs=1e-9)
    # before the buckling the exact Newton matrices were positive definite: nothing expanded, bit for bit the same
    first = next(k for k, (_, i, _) in enumerate(steps) if i.expansions)
    assert first == BUCKLING_STEP
    assert all(np.array_equal(steps[k][2], slow[k][2]) for k in range(first))


def test_the_quadratic_forms_are_the_dense_matrices():
    rng = np.random.default_rng(3)
    dense = rng.standard_normal((7, 7))
    dense = dense + dense.T
    v = rng.standard_normal(7)
    upper = sp.csr_matrix(np.triu(dense))
    assert upper_quadratic_form(upper, v) == pytest.approx(float(v @ dense @ v), rel=1e-12)


def test_max_expansions_must_not_be_negative():
    with pytest.raises(ConfigError, match="max_expansions must be >= 0"):
        SolverConfig(max_expansions=-1)
