"""The Newton solver's chord start (``SolverConfig.chord_start``, opt-in): the first iteration of a
step that starts where the last one ended solves with that step's factorised Newton matrix.

Checked: it is taken exactly when the conditions hold (same positions bit for bit, same dt, same
fixed DoFs, the factorisation not replaced since, no position guess; never after ``reset_caches``);
each step still ends on the exact Newton stopping rule, at the solution the plain Newton start
reaches to within the two solutions' own tolerances; a chord update already below the tolerance
is not applied (the step is then the plain Newton step, bit for bit); it saves factorisations.
"""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.control import Control
from sim_core.simulation import Simulation
from sim_core.solver import SolverConfig
from tests.sim_core.test_adjoint import _scene

DT = 0.005  # the scene's dt


def _controls() -> list[Control]:
    """Press the gel into the card (steps 0-1), then drag it 0.5 mm per step along x."""
    zs = [0.00026, 0.00022] + [0.00022] * 6
    xs = [0.025, 0.025, 0.0255, 0.026, 0.0265, 0.027, 0.0275, 0.028]
    return [Control({"ee": np.array([x, 0.0, z, 1.0, 0.0, 0.0, 0.0])}) for x, z in zip(xs, zs)]


def _sim(**config) -> Simulation:
    """The card scene with the chord start on (it is opt-in) unless ``config`` says otherwise."""
    return Simulation.from_scene(_scene(), solver_config=SolverConfig(**{"chord_start": True, **config}))


def test_chord_start_steps_end_at_the_newton_solution_within_the_tolerance():
    """Each step of a press-and-drag rollout, solved again from the same state with a fresh solver
    (plain Newton start): both end on the exact stopping rule, and they agree to within the sum of
    their unapplied last updates (each is within its own of the solution, to first order)."""
    sim = _sim()
    plain = _sim(chord_start=False)
    tol = sim.solver.config.tol_velocity
    chords, factorisations, iterations, projected = [], [], [], []
    for k, control in enumerate(_controls()):
        start = sim.state.copy()
        before = sim.solver.linear_solver.factorizations
        info = sim.step(control)
        assert info.factorizations == sim.solver.linear_solver.factorizations - before
        factorisations.append(info.factorizations)
        chords.append(info.chord_iterations)
        iterations.append(info.iterations)
        projected.append(info.projected_iterations)
        plain.state = start
        plain.solver.reset_caches()
        ref = plain.step(control)
        assert ref.chord_iterations == 0
        assert info.residual_velocity < tol and ref.residual_velocity < tol
        bound = 2.0 * (info.residual_velocity + ref.residual_velocity) * DT + 1e-9
        assert np.max(np.abs(sim.state.x - plain.state.x)) < bound, k
    # the first step has no previous factorisation; every later one starts from it and then
    # factorises once per Newton iteration after the chord one (twice in a projected-fallback one)
    assert chords == [0] + [1] * (len(chords) - 1)
    assert factorisations == [i - c + p for i, c, p in zip(iterations, chords, projected)]


def test_chord_start_only_from_where_the_last_step_ended():
    controls = _controls()
    sim = _sim()
    sim.step(controls[0])
    after_first = sim.state.copy()
    assert sim.step(controls[1]).chord_iterations == 1
    # another start state (a restored one): plain start
    sim.state = after_first.copy()
    assert sim.step(controls[1]).chord_iterations == 0
    assert sim.step(controls[2]).chord_iterations == 1
    # the same positions but one changed by one ulp: plain start
    nudged = sim.state.copy()
    nudged.x = nudged.x.copy()
    nudged.x[0, 0] = np.nextafter(nudged.x[0, 0], np.inf)
    sim.state = nudged
    assert sim.step(controls[3]).chord_iterations == 0
    # another dt
    sim.dt = DT / 2
    assert sim.step(controls[4]).chord_iterations == 0
    assert sim.step(controls[4]).chord_iterations == 1
    sim.dt = DT
    sim.step(controls[5])
    # the linear solver factorised something else since the last step
    solver = sim.solver.linear_solver
    solver.factorize(sim.solver.last_record.hessian_upper)
    assert sim.step(controls[6]).chord_iterations == 0
    # reset_caches: a rollout from here does not depend on what ran before
    sim.solver.reset_caches()
    assert sim.step(controls[7]).chord_iterations == 0
    # a position guess: plain start (the guess's own first iteration)
    guess = Control({"ee": controls[7].effector_pose_target["ee"]}, position_guess=sim.state.x.copy())
    assert sim.step(guess).chord_iterations == 0


def test_chord_start_is_off_by_default_and_then_gives_plain_newton_steps():
    assert SolverConfig().chord_start is False
    sim = Simulation.from_scene(_scene())
    infos = [sim.step(c) for c in _controls()[:3]]
    assert all(i.chord_iterations == 0 for i in infos)


def test_chord_update_below_the_tolerance_is_not_applied():
    """The gel lifted off a card at rest on the table: a step's chord update is below 10 x tol, so
    the step takes the Newton update at the same start instead, and ends where a plain start ends,
    bit for bit (two identical rollouts, the second's last step with the chord start off)."""
    lift = Control({"ee": np.array([0.025, 0.0, 0.01, 1.0, 0.0, 0.0, 0.0])})
    sims = [_sim(), _sim()]
    for sim in sims:
        for _ in range(12):  # the gel rises 1 mm per step to 10 mm; the card rests on the table
            sim.step(lift)
    np.testing.assert_array_equal(sims[0].state.x, sims[1].state.x)
    sims[1].solver.config.chord_start = False
    with_chord, plain = (sim.step(lift) for sim in sims)
    assert with_chord.chord_iterations == 1 and plain.chord_iterations == 0
    assert with_chord.iterations == plain.iterations + 1
    assert with_chord.factorizations == plain.factorizations
    np.testing.assert_array_equal(sims[0].state.x, sims[1].state.x)


@pytest.mark.parametrize("linear_solver", ["pardiso", "scipy"])
def test_chord_start_with_either_symmetric_solver(linear_solver):
    sim = _sim(linear_solver=linear_solver)
    infos = [sim.step(c) for c in _controls()[:3]]
    assert [i.chord_iterations for i in infos] == [0, 1, 1]
    assert all(i.residual_velocity < sim.solver.config.tol_velocity for i in infos)
