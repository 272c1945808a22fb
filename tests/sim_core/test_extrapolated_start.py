"""``SolverConfig.extrapolated_start``: a step's Newton iterations start at ``x^n + dt v^n`` (a first-order
predictor) instead of ``x^n``; the step minimises the same potential, so from the same state its result is the
one from ``x^n`` within the Newton tolerance, and a pad pressed and slid over the card at a steady speed takes
fewer Newton iterations."""

from __future__ import annotations

import dataclasses

import numpy as np

from sim_core.bundled import config_dir
from sim_core.control import Control
from sim_core.settle import settle
from sim_core.simulation import Simulation
from sim_core.solver import SolverConfig
from sim_core.step_info import StepInfo

SCENES = config_dir() / "scenes"
DT = 0.005


def _press_and_slide(sim: Simulation) -> list[np.ndarray]:
    """Effector targets: from rest 3.85 mm above the card, down 4.2 mm in 21 steps (40 mm/s), then 12 steps
    sliding 0.1 mm a step (20 mm/s) along x at that depth."""
    pose = np.array(sim.state.effector_pose["ee"], dtype=float)
    targets = []
    for k in range(1, 22):
        t = pose.copy()
        t[2] -= 2e-4 * k
        targets.append(t)
    for k in range(1, 13):
        t = targets[20].copy()
        t[0] += 1e-4 * k
        targets.append(t)
    return targets


def _control(target: np.ndarray) -> Control:
    control = Control()
    control.effector_pose_target["ee"] = target
    return control


def test_the_first_iterate_is_the_last_velocity_carried_on_and_the_fixed_vertices_at_their_targets():
    sim = Simulation.from_scene(SCENES / "press_slide.yaml", dt=DT,
                                solver_config=SolverConfig(extrapolated_start=True))
    state = sim.state.copy()
    rng = np.random.default_rng(0)
    state.v = rng.normal(scale=1e-3, size=state.x.shape)
    target = np.array(state.effector_pose["ee"], dtype=float)
    target[2] -= 1e-4
    _, x0 = sim.solver._set_up_step(state, _control(target), DT, None, StepInfo())
    fixed = sim.solver.boundary(state, _control(target))[0]
    np.testing.assert_array_equal(x0[~fixed], (state.x + DT * state.v)[~fixed])
    np.testing.assert_array_equal(x0[fixed], sim.solver.boundary(state, _control(target))[1][fixed])
    # a position guess is taken as given
    guess = state.x + 1e-6
    control = _control(target)
    control.position_guess = guess
    _, x1 = sim.solver._set_up_step(state, control, DT, guess, StepInfo())
    np.testing.assert_array_equal(x1[~fixed], guess[~fixed])


def test_a_pressed_and_sliding_pad_steps_to_the_same_state_in_fewer_newton_iterations():
    plain = Simulation.from_scene(SCENES / "press_slide.yaml", dt=DT)
    assert settle(plain, 400).settled
    predicted = Simulation.from_scene(SCENES / "press_slide.yaml", dt=DT,
                                      solver_config=dataclasses.replace(plain.solver.config, extrapolated_start=True))
    iterations = {"plain": 0, "predicted": 0}
    gaps, touching = [], 0
    for target in _press_and_slide(plain):
        start = plain.state.copy()
        info = plain.step(_control(target))
        iterations["plain"] += info.iterations
        predicted.state = start.copy()
        other = predicted.step(_control(target))
        iterations["predicted"] += other.iterations
        # a step accepted on a relaxed test (stalled at round-off) is within its own accepted tolerance
        accepted = max(info.accepted_tolerance, other.accepted_tolerance) * DT
        gaps.append(float(np.abs(predicted.state.x - plain.state.x).max()) / accepted)
        touching += bool(np.any(plain.state.contact_force))
    assert touching >= 12  # the slide is in contact
    # the same step's minimiser from both starts: within a few accepted Newton tolerances
    assert max(gaps) < 5.0, max(gaps)
    assert iterations["predicted"] < 0.85 * iterations["plain"], iterations
