"""``SolverConfig.repeat_fixed_points``: a step whose inputs are those of a step that left its state
unchanged takes that step's result, says so in ``StepInfo.repeated``, and gives the same states as
solving it; any change of its inputs solves again."""

from __future__ import annotations

import numpy as np

from sim_core.control import Control
from sim_core.simulation import Simulation
from sim_core.solver import SolverConfig
from sim_core.bundled import config_dir

# the bundled scene: a card on the table, the tactile pad above it (not touching); it rests after
# a few steps, and a 0.2 mm move of the pad sets the gel vibrating for a few steps
PRESS_AT = (8, 20)  # steps that move the pad (down, then back up)


def _sim(repeat: bool) -> Simulation:
    return Simulation.from_scene(config_dir() / "scenes" / "press_slide.yaml", solver_config=SolverConfig(repeat_fixed_points=repeat))


def _control(sim: Simulation, k: int) -> Control:
    control = Control()
    if k in PRESS_AT:
        pose = np.array(sim.state.effector_pose["ee"])
        pose[2] += -2e-4 if k == PRESS_AT[0] else 2e-4
        control.effector_pose_target["ee"] = pose
    return control


def _run(repeat: bool, steps: int = 30):
    sim = _sim(repeat)
    xs, infos = [], []
    for k in range(steps):
        infos.append(sim.step(_control(sim, k)))
        xs.append(sim.state.x.copy())
    return sim, np.array(xs), infos


def test_repeated_steps_give_the_solved_states_and_say_so():
    solved_sim, solved, solved_infos = _run(False)
    sim, repeated, infos = _run(True)
    np.testing.assert_array_equal(repeated, solved)  # bit for bit
    assert [i.stop_reason for i in infos] == [i.stop_reason for i in solved_infos]
    assert [i.residual_velocity for i in infos] == [i.residual_velocity for i in solved_infos]
    assert [i.energy for i in infos] == [i.energy for i in solved_infos]
    flags = [i.repeated for i in infos]
    assert not any(i.repeated for i in solved_infos)
    # the scene comes to rest before each move and after it, and only a resting step is repeated
    assert flags[PRESS_AT[0] - 1] and flags[PRESS_AT[1] - 1] and flags[-1]
    assert not flags[PRESS_AT[0]] and not flags[PRESS_AT[1]]
    for k, info in enumerate(infos):
        if info.repeated:
            assert np.array_equal(repeated[k], repeated[k - 1])
            assert (info.iterations, info.factorizations, info.backtracks) == (0, 0, 0)
            assert info.converged_strict and info.residual_velocity < 1e-4
        else:
            assert info.iterations >= 1 and info.factorizations >= 1
    assert sim.step_totals.repeated_steps == sum(flags) > 0
    assert solved_sim.step_totals.repeated_steps == 0
    np.testing.assert_array_equal(sim.state.contact_force, solved_sim.state.contact_force)
    assert sim.state.t == solved_sim.state.t and sim.state.step_index == solved_sim.state.step_index == 30


def _at_rest() -> Simulation:
    sim = _sim(True)
    for _ in range(6):
        sim.step()
    assert sim.step().repeated
    return sim


def test_any_changed_input_solves_the_step_again():
    sim = _at_rest()
    # a command that moves the pad
    pose = np.array(sim.state.effector_pose["ee"])
    pose[0] += 1e-5
    assert not sim.step(Control(effector_pose_target={"ee": pose})).repeated
    sim = _at_rest()
    # a material parameter (the model's revision)
    sim.set_parameter("sheet.youngs_modulus", 1.01 * sim.get_parameter("sheet.youngs_modulus"))
    assert not sim.step().repeated
    sim = _at_rest()
    # a solver setting, and the state itself
    sim.solver.config.tol_velocity = 0.5e-4
    assert not sim.step().repeated
    sim = _at_rest()
    sim.state.v[0, 2] = 1e-12
    assert not sim.step().repeated
    sim = _at_rest()
    sim.reset()
    assert not sim.step().repeated
    # and a guess is always solved
    sim = _at_rest()
    assert not sim.step(Control(position_guess=sim.state.x.copy())).repeated


def _assert_same_observation(a, b) -> None:
    assert a.t == b.t and a.effector_pose.keys() == b.effector_pose.keys() and a.tactile.keys() == b.tactile.keys()
    for k in a.effector_pose:
        np.testing.assert_array_equal(a.effector_pose[k], b.effector_pose[k])
    for k in a.tactile:
        for u, v in zip(a.tactile[k], b.tactile[k]):
            np.testing.assert_array_equal(u, v)
    np.testing.assert_array_equal(a.sheet_points, b.sheet_points)
    np.testing.assert_array_equal(a.sheet_triangles, b.sheet_triangles)


def test_an_unchanged_state_observes_what_was_read_from_it_at_its_own_time():
    sim = _at_rest()
    first = sim.observe()
    assert sim.step().repeated
    second = sim.observe()
    reader = _sim(False)  # reads every observation afresh (nothing kept for these states)
    reader.state = sim.state.copy()
    assert second.t == sim.state.t > first.t
    _assert_same_observation(second, reader.observe())
    # the caller's copy is its own
    second.tactile["tactile"].markers_xyz[:] = 0.0
    assert np.all(np.abs(sim.observe().tactile["tactile"].markers_xyz[:, 2]) > 0)
    # a state changed in place is read again: the gel pushed up moves the markers, a sheet vertex
    # its point
    sim.state.x[sim.model.bodies["gel"].vertices, 2] += 1e-4
    sim.state.x[10, 2] += 1e-4
    moved = sim.observe()
    reader.state = sim.state.copy()
    _assert_same_observation(moved, reader.observe())
    assert not np.array_equal(moved.tactile["tactile"].markers_xyz, first.tactile["tactile"].markers_xyz)
    assert not np.array_equal(moved.sheet_points, first.sheet_points)
