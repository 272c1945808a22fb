"""The lockstep step's Dirichlet data vectorised over copies (sim_core.batch.effectors): the per-effector
boundary of NewtonSolver, pose limit and driven positions, to round-off."""

from __future__ import annotations

import copy
from types import SimpleNamespace

import numpy as np
import pytest

from sim_core.batch.effectors import StackedBoundary, limit_pose_steps
from sim_core.batch.stacked import stack_models
from sim_core.control import Control
from sim_core.effector import limit_pose_step
from sim_core.errors import ConfigError
from sim_core.scenes.task_scene import task_initial_state
from sim_core.solver import NewtonSolver
from sim_core.step_terms import FreeDofs
from tests.support.batch_copies import pad_model


def _unit(q):
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _poses(rng, count, spread_t, spread_r):
    """Poses near the origin and targets at about ``spread_t`` (m) and ``spread_r`` (rad) from them; every
    fourth current quaternion with w < 0 (the same rotation)."""
    current = np.concatenate([rng.normal(0, 0.01, (count, 3)), _unit(rng.normal(size=(count, 4)))], axis=1)
    current[::4, 3:] *= -1
    axis = _unit(rng.normal(size=(count, 3)))
    angle = spread_r * rng.uniform(0.0, 2.0, count)
    turn = np.concatenate([axis * np.sin(angle / 2)[:, None], np.cos(angle / 2)[:, None]], axis=1)
    q_c = current[:, 3:]
    target_q = np.stack([  # turn * q_c
        turn[:, 3] * q_c[:, 0] + turn[:, 0] * q_c[:, 3] + turn[:, 1] * q_c[:, 2] - turn[:, 2] * q_c[:, 1],
        turn[:, 3] * q_c[:, 1] - turn[:, 0] * q_c[:, 2] + turn[:, 1] * q_c[:, 3] + turn[:, 2] * q_c[:, 0],
        turn[:, 3] * q_c[:, 2] + turn[:, 0] * q_c[:, 1] - turn[:, 1] * q_c[:, 0] + turn[:, 2] * q_c[:, 3],
        turn[:, 3] * q_c[:, 3] - turn[:, 0] * q_c[:, 0] - turn[:, 1] * q_c[:, 1] - turn[:, 2] * q_c[:, 2]], axis=1)
    target = np.concatenate([current[:, :3] + spread_t * rng.uniform(0, 2, (count, 1)) * _unit(
        rng.normal(size=(count, 3))), target_q], axis=1)
    target[1, 3:] = current[1, 3:]  # no rotation at all: the series branch of the rotation vector
    return current, target


def test_limit_pose_steps_is_limit_pose_step_row_by_row():
    rng = np.random.default_rng(7)
    current, target = _poses(rng, 64, 1e-3, 0.02)
    got, limited = limit_pose_steps(current, target, 1e-3, 0.02)
    ref = [limit_pose_step(c, t, 1e-3, 0.02) for c, t in zip(current, target)]
    want = np.array([r[0] for r in ref])
    # the same rotation either sign of the quaternion: compare q q_ref's alignment and the positions
    np.testing.assert_allclose(got[:, :3], want[:, :3], rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", got[:, 3:], want[:, 3:])), 1.0, rtol=0, atol=1e-14)
    np.testing.assert_allclose(got[:, 3:], want[:, 3:], rtol=0, atol=1e-14)
    assert limited.tolist() == [r[1] for r in ref]
    assert 0 < limited.sum() < len(limited)  # both branches of the limit taken


def test_limit_pose_steps_names_a_target_that_is_not_a_pose():
    current = np.array([[0, 0, 0, 0, 0, 0, 1.0]] * 3)
    target = current.copy()
    target[2, 3:] = [0, 0, 0, 2.0]
    with pytest.raises(ConfigError, match="effector target pose 2 must be 7 finite numbers with a unit quaternion"):
        limit_pose_steps(current, target, 1e-3, 0.02)


def test_stacked_boundary_is_the_solvers_boundary_of_the_stacked_model():
    model = pad_model()
    fingered = copy.deepcopy(model)  # a gripper's fingers: the driven positions depend on the opening too
    pad = fingered.effectors["pad"]
    pad.finger_sign = np.where(np.arange(len(pad.vertices)) % 2 == 0, 1.0, -1.0)
    rng = np.random.default_rng(3)
    for m in (model, fingered):
        scene = stack_models([m] * 5)
        state = scene.stack_states([task_initial_state(m)] * 5)
        current = np.array([state.effector_pose[f"pad#{i}"] for i in range(5)])
        _, target = _poses(rng, 5, 2e-3, 0.05)
        target[:, :3] += current[:, :3]
        control = Control(effector_pose_target={f"pad#{i}": target[i] for i in (0, 1, 3, 4)},  # copy 2: none
                          gripper_target={"pad#3": 0.004})
        got = StackedBoundary(scene.model, 5, scene.effector_names)(state, control)
        want = NewtonSolver.boundary(SimpleNamespace(model=scene.model), state, control)
        assert np.array_equal(got[0], want[0])
        np.testing.assert_allclose(got[1], want[1], rtol=0, atol=1e-15)
        assert got[2].keys() == want[2].keys() and got[3] == want[3]
        for k in want[2]:
            np.testing.assert_allclose(got[2][k], want[2][k], rtol=0, atol=1e-15)
        assert sorted(got[4]) == sorted(want[4]) and "pad#2" not in got[4]
        assert np.array_equal(got[2]["pad#2"], state.effector_pose["pad#2"])


def test_a_stacked_boundary_makes_its_fixed_mask_once_and_the_free_dofs_are_kept_for_it():
    """The mask is the same read-only array at every call (the step's free DoFs then kept by identity, FreeDofs),
    made anew when the model's static mask changes."""
    model = pad_model()
    scene = stack_models([model] * 3)
    state = scene.stack_states([task_initial_state(model)] * 3)
    control = Control(effector_pose_target={"pad#1": state.effector_pose["pad#1"] + np.r_[1e-3, 0, 0, 0, 0, 0, 0]})
    boundary = StackedBoundary(scene.model, 3, scene.effector_names)
    first, again = boundary(state, control), boundary(state, control)
    assert first[0] is again[0] and not first[0].flags.writeable and first[0].sum() > scene.model.vertex_fixed.sum()
    assert not np.array_equal(first[1], state.x) and np.array_equal(again[1], first[1])  # copy 1's pad moved
    free_dofs = FreeDofs()
    free, fixed_dofs = free_dofs(first[0])
    assert free_dofs(again[0])[0] is free and free_dofs(again[0])[1] is fixed_dofs and not free.flags.writeable
    assert np.array_equal(free, np.repeat(~first[0], 3)) and not fixed_dofs.flags.writeable
    assert np.array_equal(fixed_dofs, np.broadcast_to(first[0][:, None], (len(first[0]), 3)))
    writeable = first[0].copy()
    assert free_dofs(writeable)[0] is not free_dofs(writeable)[0]  # a mask that may change: made at each call
    static = scene.model.vertex_fixed.copy()
    static[np.flatnonzero(~first[0])[0]] = True
    scene.model.vertex_fixed = static
    changed = boundary(state, control)[0]
    assert changed is not first[0] and changed.sum() == first[0].sum() + 1
    assert free_dofs(changed)[0] is not free
