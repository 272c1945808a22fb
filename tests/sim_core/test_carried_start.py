"""``SolverConfig.carried_start``: a step's Newton iterations start with the effector's solid carried
by the effector's rigid motion (:mod:`sim_core.carried_start`); the step's result is the one from
``x^n`` within the Newton tolerance, in fewer iterations."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.bundled import config_dir
from sim_core.carried_start import carry_driven_bodies
from sim_core.control import Control
from sim_core.effector import driven_positions
from sim_core.errors import ConfigError
from sim_core.scenes import load_scene
from sim_core.settle import settle
from sim_core.simulation import Simulation
from sim_core.solver import SolverConfig
from sim_core.transforms import quat_from_rotvec, quat_multiply

SCENES = config_dir() / "scenes"


def _pairwise(x: np.ndarray) -> np.ndarray:
    return np.linalg.norm(x[:, None, :] - x[None, :, :], axis=-1)


def test_the_pad_is_carried_rigidly_onto_its_driven_targets_and_nothing_else_moves():
    model = load_scene(SCENES / "press_slide.yaml")
    state = model.state()
    eff = model.effectors["ee"]
    gel = model.bodies[model.sensors["tactile"].gel_body]
    pose0 = np.array(state.effector_pose["ee"], dtype=float)
    pose1 = pose0.copy()
    pose1[:3] += [3e-4, -2e-4, 5e-4]
    pose1[3:] = quat_multiply(quat_from_rotvec(np.array([0.01, -0.02, 0.015])), pose0[3:])
    fixed = np.zeros(len(state.x), dtype=bool)
    x = state.x.copy()
    moved = carry_driven_bodies(model, state.x, state.v, 0.005, state.effector_pose, {}, {"ee": pose1}, {}, fixed,
                                state.x, x)
    assert moved == [gel.name]
    # the map is the effector's own: its driven vertices land on their targets
    np.testing.assert_allclose(x[eff.vertices], driven_positions(eff, pose1, eff.initial_opening), atol=1e-15)
    # a rigid motion of the whole gel; the sheet is not carried
    g = gel.vertices
    np.testing.assert_allclose(_pairwise(x[g]), _pairwise(state.x[g]), atol=1e-15)
    assert np.abs(x[g] - state.x[g]).max() > 4e-4
    others = np.setdiff1d(np.arange(len(x)), g)
    assert np.array_equal(x[others], state.x[others])
    # fixed vertices are left alone; an effector that does not move moves nothing
    held = fixed.copy()
    held[g[:10]] = True
    x2 = state.x.copy()
    carry_driven_bodies(model, state.x, state.v, 0.005, state.effector_pose, {}, {"ee": pose1}, {}, held, state.x, x2)
    assert np.array_equal(x2[g[:10]], state.x[g[:10]]) and np.array_equal(x2[g[10:]], x[g[10:]])
    x3 = state.x.copy()
    assert carry_driven_bodies(model, state.x, state.v, 0.005, state.effector_pose, {}, state.effector_pose, {},
                               fixed, state.x, x3) == []
    assert np.array_equal(x3, state.x)


def _lifted(model, state, body: str, effector: str, dz: float):
    """``state`` with ``body`` and ``effector`` moved by ``dz`` (m) along world z."""
    b = model.bodies[body]
    state.x[b.vertex_start:b.vertex_stop, 2] += dz
    state.effector_pose[effector] = np.array(state.effector_pose[effector], dtype=float)
    state.effector_pose[effector][2] += dz
    return state


def test_a_pad_within_contact_reach_is_not_carried():
    """The bundled pad hangs 3.85 mm above the card: lowered by 3 mm it is within the contact search
    radius (1.4 mm) of the card, and its step starts at x^n."""
    model = load_scene(SCENES / "press_slide.yaml")
    gel = model.sensors["tactile"].gel_body
    fixed = np.zeros(model.vertex_count, dtype=bool)
    for dz, carried in ((0.0, [gel]), (-3e-3, [])):
        state = _lifted(model, model.state(), gel, "ee", dz)
        pose1 = np.array(state.effector_pose["ee"], dtype=float)
        pose1[2] -= 2e-4
        x = state.x.copy()
        assert carry_driven_bodies(model, state.x, state.v, 0.005, state.effector_pose, {}, {"ee": pose1}, {},
                                   fixed, state.x, x) == carried
        assert np.array_equal(x, state.x) == (not carried)


def test_a_gripper_holding_both_fingers_is_carried_only_while_its_opening_is_held():
    """The interact scene's gripper lifted 5 cm clear of the card and the table."""
    model = load_scene(SCENES / "interact.yaml")
    state = _lifted(model, model.state(), "gripper", "gripper", 0.05)
    eff = model.effectors["gripper"]
    pose1 = np.array(state.effector_pose["gripper"], dtype=float)
    pose1[:3] += [1e-3, 0.0, 5e-4]
    fixed = np.zeros(len(state.x), dtype=bool)
    x = state.x.copy()
    assert carry_driven_bodies(model, state.x, state.v, 0.005, state.effector_pose, state.gripper_opening,
                               {"gripper": pose1}, dict(state.gripper_opening), fixed, state.x, x) == ["gripper"]
    opening = float(state.gripper_opening.get("gripper", eff.initial_opening))
    np.testing.assert_allclose(x[eff.vertices], driven_positions(eff, pose1, opening), atol=1e-15)
    # closing the fingers is not one rigid motion of the body: the start stays x^n
    x = state.x.copy()
    assert carry_driven_bodies(model, state.x, state.v, 0.005, state.effector_pose, state.gripper_opening,
                               {"gripper": pose1}, {"gripper": opening - 1e-3}, fixed, state.x, x) == []
    assert np.array_equal(x, state.x)


def _probe_run(carried: bool) -> tuple[np.ndarray, list]:
    """The sim node's solver on the bundled scene settled to rest: the pad in the air moved 0.2 mm up
    and back four times, a resting step after each move."""
    sim = Simulation.from_scene(SCENES / "press_slide.yaml", solver_config=SolverConfig(
        repeat_fixed_points=True, sleeping=True, carried_start=carried))
    assert settle(sim, 400).settled
    pose = np.array(sim.state.effector_pose["ee"], dtype=float)
    xs, infos = [], []
    for k in range(8):
        target = pose.copy()
        target[2] += 2e-4 if k % 2 == 0 else 0.0
        for _ in range(2):
            control = Control()
            control.effector_pose_target["ee"] = target
            infos.append(sim.step(control))
            xs.append(sim.state.x.copy())
    return np.array(xs), infos


def test_a_pad_moved_in_the_air_takes_one_newton_iteration_and_reaches_the_same_state_within_tolerance():
    x_plain, plain = _probe_run(False)
    x_carried, carried = _probe_run(True)
    moves = slice(0, None, 2)
    # from x^n: 4 iterations on the default gel's four layers (3 on the two-layer mesh before session 51)
    assert [i.iterations for i in plain[moves]] == [4] * 8
    assert [i.iterations for i in carried[moves]] == [1] * 8
    assert all(i.converged_strict for i in plain + carried)
    tol = SolverConfig().tol_velocity * 0.005  # m: the Newton tolerance over the scene's 5 ms step
    assert np.abs(x_carried - x_plain).max() < tol


def test_carried_start_is_refused_with_lockstep():
    with pytest.raises(ConfigError, match="carried_start is not available with lockstep"):
        SolverConfig(carried_start=True, lockstep=True)
