"""Batched gradients (sim_core.batch.adjoint): the reverse passes of a lockstep batch run together give each
copy the gradient of its separate rollout (sim_core.adjoint.rollout_gradient) to the solver tolerance, agree
with central differences, and a copy that fails gets none while the others' are unchanged."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sim_core import adjoint
from sim_core.batch import BatchedSimulation
from sim_core.batch.adjoint import TrajectoryRecorder, batched_rollout_gradient
from sim_core.errors import ConfigError
from sim_core.scenes.task_scene import task_initial_state
from sim_core.simulation import Simulation
from sim_core.solver_config import SolverConfig
from tests.support.batch_copies import MOTIONS, PARAMS, STEPS, control, pad_model

TIGHT = SolverConfig(tol_velocity=1e-8, tol_force=1e-10, dt_halvings_on_failure=0)
GRAD_PARAMS = ["pad.youngs_modulus", "sheet.bending_stiffness", "sheet.density", "friction.pad_sheet",
               "friction.sheet_table", "contact.stiffness", "damping"]


@pytest.fixture(scope="module")
def model():
    return pad_model()


def _weights(model, i: int) -> np.ndarray:
    """Copy ``i``'s loss ``L = sum(W * x_T)`` over the final positions: random weights on the sheet, shape (n, 3)."""
    W = np.zeros((model.vertex_count, 3))
    sheet = model.bodies["sheet"]
    rows = sheet.vertex_stop - sheet.vertex_start
    W[sheet.vertex_start:sheet.vertex_stop] = np.random.default_rng(10 + i).normal(size=(rows, 3))
    return W


def _loss_rows(model, i: int, steps: int = STEPS) -> np.ndarray:
    rows = np.zeros((steps + 1, model.vertex_count, 3))
    rows[-1] = _weights(model, i)
    return rows


def _batched(model, params=PARAMS, config=TIGHT, spoil=None):
    """Copies with ``params`` and MOTIONS stepped in lockstep and recorded; ``spoil(batch)`` edits it first."""
    batch = BatchedSimulation.from_model(model, len(params), params=params, state=task_initial_state(model),
                                         solver_config=dataclasses.replace(config, lockstep=True))
    if spoil is not None:
        spoil(batch)
    recorder = TrajectoryRecorder(batch)
    pose0 = batch.states[0].effector_pose["pad"].copy()
    for k in range(STEPS):
        recorder.step([control(pose0, MOTIONS[i], k) for i in range(batch.batch_size)])
    return batch, recorder.trajectory()


def _alone(model, params, config=TIGHT) -> Simulation:
    """A Simulation of its own of ``model`` with ``params``, at the task's initial state."""
    return BatchedSimulation.from_model(model, 1, params=[params], state=task_initial_state(model),
                                        solver_config=config).sims[0]


def _separate(model, params, motion, weights_of, config=TIGHT):
    """One copy rolled out alone: (its gradient, its loss)."""
    sim = _alone(model, params, config)
    pose0 = sim.state.effector_pose["pad"].copy()
    traj = adjoint.rollout(sim, [control(pose0, motion, k) for k in range(STEPS)])
    W = weights_of
    rows = np.zeros((STEPS + 1,) + W.shape)
    rows[-1] = W
    return adjoint.rollout_gradient(sim, traj, rows, params=GRAD_PARAMS), float(np.sum(W * traj.states[-1].x))


def _assert_same_gradient(got, want, rtol=1e-5):
    scale = max(np.abs(want.controls[k]["pad"]).max() for k in range(STEPS))
    for k in range(STEPS):
        np.testing.assert_allclose(got.controls[k]["pad"], want.controls[k]["pad"], rtol=rtol, atol=rtol * scale)
    np.testing.assert_allclose(got.x0, want.x0, rtol=rtol, atol=rtol * np.abs(want.x0).max())
    np.testing.assert_allclose(got.v0, want.v0, rtol=rtol, atol=rtol * np.abs(want.v0).max())
    np.testing.assert_allclose(got.initial_pose["pad"], want.initial_pose["pad"], rtol=rtol, atol=rtol * scale)
    for p in GRAD_PARAMS:
        assert got.params[p] == pytest.approx(want.params[p], rel=rtol, abs=1e-20), p


def test_batched_gradients_of_three_copies_equal_their_separate_gradients(model):
    batch, recording = _batched(model)
    assert recording.complete.all() and recording.step_count == STEPS
    got = batched_rollout_gradient(recording, [_loss_rows(model, i) for i in range(3)], GRAD_PARAMS,
                                   backend=batch.backend)
    assert got.failures == [None, None, None]
    for i in range(3):
        want, _ = _separate(model, PARAMS[i], MOTIONS[i], _weights(model, i))
        _assert_same_gradient(got.gradients[i], want)
    # the copies differ: their own parameters and motions reach their gradients
    g = got.gradients
    assert abs(g[1].params["friction.pad_sheet"] - g[2].params["friction.pad_sheet"]) > 1e-3 * abs(
        g[1].params["friction.pad_sheet"])
    # each copy's block by its own LU: the same solves
    blocks = batched_rollout_gradient(recording, [_loss_rows(model, i) for i in range(3)], GRAD_PARAMS,
                                      linear_solver="pardiso-blocks", backend=batch.backend)
    for i in range(3):
        _assert_same_gradient(blocks.gradients[i], got.gradients[i], rtol=1e-9)
    # a copy without a loss gets none; a loss of the wrong shape is refused, naming the copy
    partial = batched_rollout_gradient(recording, [None, _loss_rows(model, 1), None], GRAD_PARAMS)
    assert partial.gradients[0] is None and partial.failures[0] == "no loss given"
    _assert_same_gradient(partial.gradients[1], got.gradients[1], rtol=1e-8)
    with pytest.raises(ConfigError, match="copy 2's dL_dx has shape"):
        batched_rollout_gradient(recording, [None, None, np.zeros((STEPS, model.vertex_count, 3))])


def test_a_batched_gradient_matches_central_differences(model):
    """Copy 2's derivatives w.r.t. its pad-sheet friction and one commanded pose coordinate, against central
    differences of its separate rollouts."""
    _, recording = _batched(model)
    g = batched_rollout_gradient(recording, [None, None, _loss_rows(model, 2)], GRAD_PARAMS).gradients[2]
    W = _weights(model, 2)
    mu = PARAMS[2]["friction.pad_sheet"]
    h = 1e-4
    up = _separate(model, {**PARAMS[2], "friction.pad_sheet": mu + h}, MOTIONS[2], W)[1]
    down = _separate(model, {**PARAMS[2], "friction.pad_sheet": mu - h}, MOTIONS[2], W)[1]
    fd = (up - down) / (2 * h)
    assert abs(fd) > 1e-6  # the friction acts
    assert g.params["friction.pad_sheet"] == pytest.approx(fd, rel=2e-3)
    # the press depth (z) of step 1's command: the motion's press per step shifted for that step only
    hz = 1e-6

    def loss_with_press(dz: float) -> float:
        sim = _alone(model, PARAMS[2])
        pose0 = sim.state.effector_pose["pad"].copy()
        for k in range(STEPS):
            c = control(pose0, MOTIONS[2], k)
            if k == 1:
                c.effector_pose_target["pad"][2] += dz
            sim.step(c)
        return float(np.sum(W * sim.state.x))

    fd_z = (loss_with_press(hz) - loss_with_press(-hz)) / (2 * hz)
    assert abs(fd_z) > 1e-3
    assert g.controls[1]["pad"][2] == pytest.approx(fd_z, rel=2e-3)


def test_a_copy_that_fails_gets_no_gradient_and_the_others_are_unchanged(model):
    """Copy 1 starts from a blown-up state (a non-finite velocity): the batch reports it at step 0 and holds
    it; the reverse pass gives it no gradient and the other copies their separate gradients."""
    sheet = model.bodies["sheet"].vertices

    def spoil(batch):
        batch.sims[1].state.v[sheet[len(sheet) // 2]] = [0.0, 0.0, np.nan]

    batch, recording = _batched(model, spoil=spoil)
    assert list(recording.complete) == [True, False, True]
    assert "non-finite gradient" in recording.failures[1]
    got = batched_rollout_gradient(recording, [_loss_rows(model, i) for i in range(3)], GRAD_PARAMS,
                                   backend=batch.backend)
    assert got.gradients[1] is None and got.failures[1] == recording.failures[1]
    for i in (0, 2):
        assert got.failures[i] is None
        want, _ = _separate(model, PARAMS[i], MOTIONS[i], _weights(model, i))
        _assert_same_gradient(got.gradients[i], want)


def test_batched_gradients_need_a_lockstep_batch_and_unchanged_parameters(model):
    batch = BatchedSimulation.from_model(model, 2, state=task_initial_state(model), solver_config=TIGHT)
    with pytest.raises(ConfigError, match="lockstep"):
        TrajectoryRecorder(batch)
    batch, recording = _batched(model)
    batch.set_parameter(0, "friction.pad_sheet", 0.4)
    with pytest.raises(ConfigError, match=r"parameters of copies \[0\] changed"):
        batched_rollout_gradient(recording, [_loss_rows(model, i) for i in range(3)])


def test_the_adjoint_cg_on_a_taichi_backend_gives_the_direct_solves_gradients(model):
    """linear_solver="pcg" (the batched CG, as on the GPU) against the stacked LU, on one taichi-cpu recording;
    and the CG's LU fallback for a copy whose block is not positive definite."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    from sim_core.batch.adjoint_solvers import StackedAdjointCG

    batch, recording = _batched(model, config=dataclasses.replace(TIGHT, backend="taichi-cpu"))
    rows = [_loss_rows(model, i) for i in range(3)]
    direct = batched_rollout_gradient(recording, rows, GRAD_PARAMS, backend=batch.backend)
    cg = batched_rollout_gradient(recording, rows, GRAD_PARAMS, linear_solver="pcg", backend=batch.backend)
    for got, want in zip(cg.gradients, direct.gradients):
        _assert_same_gradient(got, want, rtol=1e-7)
    assert len(cg.solver.cg_iterations) == STEPS and min(cg.solver.cg_iterations) > 0
    assert cg.solver.lu_copies < 3 * STEPS  # the CG solved copies itself
    with pytest.raises(ConfigError, match="Taichi backend"):
        batched_rollout_gradient(recording, rows, linear_solver="pcg", backend="numpy")
    # a symmetric block-diagonal matrix whose copy-1 block is negative definite: the CG flags it, LU solves it
    dofs = recording.scene.dof_index
    N3 = 3 * recording.scene.model.vertex_count
    rng = np.random.default_rng(0)
    sign = np.ones(N3)
    sign[dofs[1]] = -1.0
    blocks = sp.block_diag([sp.random(len(d), len(d), density=0.01, random_state=i) for i, d in enumerate(dofs)])
    perm = np.argsort(np.concatenate(dofs))
    M = sp.csr_matrix(blocks)[perm][:, perm]
    A = (sp.diags(sign) @ (M @ M.T + sp.identity(N3))).tocsr()
    b = rng.normal(size=N3)
    solver = StackedAdjointCG(recording.scene)
    solver.factorize(A)
    np.testing.assert_allclose(solver.solve(b), spla.spsolve(A.tocsc(), b), rtol=1e-7, atol=1e-9)
    assert solver.lu_copies == 1


def test_a_recording_solved_by_the_batched_cg_gives_the_direct_recordings_gradients(model):
    """Forward steps solved by the batched CG (``linear_solver="pcg"``, the GPU's lockstep solver) keep no assembled
    Newton matrix in their records: the reverse pass assembles the exact Hessian at each converged step, and each
    copy's gradient is the one of the same copies stepped with the direct solver (tight tolerance)."""
    cfg = dataclasses.replace(TIGHT, backend="taichi-cpu")
    batch, direct_rec = _batched(model, config=cfg)
    _, cg_rec = _batched(model, config=dataclasses.replace(cfg, linear_solver="pcg"))
    assert all(r.hessian_upper is None for r in cg_rec.trajectory.records)  # what the GPU's forward leaves
    rows = [_loss_rows(model, i) for i in range(3)]
    direct = batched_rollout_gradient(direct_rec, rows, GRAD_PARAMS, backend=batch.backend)
    cg = batched_rollout_gradient(cg_rec, rows, GRAD_PARAMS, backend=batch.backend)
    for got, want in zip(cg.gradients, direct.gradients):
        _assert_same_gradient(got, want, rtol=1e-5)
