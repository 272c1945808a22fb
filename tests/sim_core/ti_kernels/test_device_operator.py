"""The batched CG's Newton operator (sim_core.batch.lockstep.LockstepSolver._device_operator with
sim_core.ti_kernels.pcg.BatchedPCG): the static elastic part in its fixed pattern plus the contact and
friction Hessians applied matrix-free as vertex blocks equals the assembled Newton matrix, product by
product and in its block-Jacobi preconditioner, with the exact and with the projected element Hessians."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from sim_core.batch import BatchedSimulation
from sim_core.energies.base import HessianBlocks
from sim_core.scenes.task_scene import task_initial_state
from sim_core.solver_config import SolverConfig
from sim_core.step_info import StepInfo
from tests.support.batch_copies import MOTIONS, PARAMS, control, pad_model


def _full(upper: sp.csr_matrix) -> sp.csr_matrix:
    return (upper + sp.triu(upper, k=1).T).tocsr()


def _assert_block_jacobi(solver, matrix) -> None:
    """The CG's preconditioner is each vertex's 3x3 diagonal block of ``matrix`` inverted (a block whose
    determinant is not positive: the inverse of its positive diagonal entries, 1 elsewhere)."""
    nvert = matrix.shape[0] // 3
    inv = solver._arrays["inv"].to_numpy()[: 9 * nvert].reshape(nvert, 3, 3)
    dense = matrix.toarray() if sp.issparse(matrix) else matrix
    for v in range(nvert):
        blk = dense[3 * v:3 * v + 3, 3 * v:3 * v + 3]
        if np.linalg.det(blk) > 1e-12 * np.prod(np.abs(np.diag(blk))):
            np.testing.assert_allclose(inv[v] @ blk, np.eye(3), atol=1e-9)
        else:
            d = np.diag(blk)
            np.testing.assert_allclose(inv[v], np.diag(np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), 1.0)), rtol=1e-14)


def test_vertex_blocks_product_is_the_assembled_element_blocks_product(ti_cpu):
    from sim_core.ti_kernels.pcg import BatchedPCG, VertexBlocks

    rng = np.random.default_rng(3)
    nvert = 7
    n = 3 * nvert
    sets = []
    for k, m in ((5, 2), (3, 4), (4, 1)):
        verts = np.array([rng.choice(nvert, m, replace=False) for _ in range(k)])
        a = rng.normal(size=(k, 3 * m, 3 * m))
        sets.append(HessianBlocks(verts, a + a.transpose(0, 2, 1)))
    free = np.ones(n, dtype=bool)
    free[3:6] = False  # vertex 1 fixed
    # the reference: every block entry (r, s) at DoFs (R, S), both free, summed into a dense matrix
    want = np.zeros((n, n))
    for b in sets:
        dofs = (3 * b.vertices[:, :, None] + np.arange(3)).reshape(b.vertices.shape[0], -1)
        for e in range(dofs.shape[0]):
            want[np.ix_(dofs[e], dofs[e])] += b.blocks[e]
    want *= np.outer(free, free)
    diag = rng.uniform(1.0, 2.0, n)
    upper = sp.csr_matrix(np.diag(diag))
    want += np.diag(diag)
    element_form = VertexBlocks.from_element_blocks(sets, free)  # expanded into vertex blocks by a kernel
    vertex_form = VertexBlocks(element_form.rows, element_form.cols, element_form.values, free)  # uploaded as such
    assert element_form.count == vertex_form.count == sum(b.vertices.size * b.vertices.shape[1] for b in sets)
    for blocks in (element_form, vertex_form):
        solver = BatchedPCG()
        solver.factorize(upper, blocks)
        for _ in range(3):
            p = rng.normal(size=n)
            np.testing.assert_allclose(solver.matvec(p), want @ p, rtol=1e-13, atol=1e-12 * np.abs(want).sum())
        _assert_block_jacobi(solver, want)


def _random_sets(rng, nvert: int, shapes) -> list:
    """Positive semi-definite element Hessians ``HessianBlocks`` of ``k`` elements over ``m`` distinct vertices each,
    per ``(k, m)`` of ``shapes``."""
    sets = []
    for k, m in shapes:
        verts = np.array([rng.choice(nvert, m, replace=False) for _ in range(k)]).reshape(k, m)
        a = rng.normal(size=(k, 3 * m, 3 * m))
        sets.append(HessianBlocks(verts, a @ a.transpose(0, 2, 1)))
    return sets


def _dense_sum(sets, free: np.ndarray) -> np.ndarray:
    """Every element block entry at its DoFs summed into a dense matrix, fixed DoFs' rows and columns dropped."""
    n = free.size
    want = np.zeros((n, n))
    for b in sets:
        dofs = (3 * b.vertices[:, :, None] + np.arange(3)).reshape(b.vertices.shape[0], -1)
        for e in range(dofs.shape[0]):
            want[np.ix_(dofs[e], dofs[e])] += b.blocks[e]
    return want * np.outer(free, free)


def test_contact_blocks_stay_resident_while_their_count_changes(ti_cpu, monkeypatch):
    """One solver factorised in turn with contact sets whose counts change (as a Newton loop's contact set does, some
    sets' blocks left on the device as ``DeviceRows``): every product equals the assembled matrix's, and once the
    arrays have grown to the largest count no device array is made again (the vertex blocks and the packed element
    sets keep their capacity, their counts passed to the kernels), and the element sets travel in one upload of
    vertices and one of host blocks a factorisation."""
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels import device_copy, pcg as pcg_module
    from sim_core.ti_kernels.buffers import DeviceHessianBlocks, DeviceRows
    from sim_core.ti_kernels.pcg import BatchedPCG, VertexBlocks

    rng = np.random.default_rng(11)
    nvert = 9
    n = 3 * nvert
    free = np.ones(n, dtype=bool)
    free[6:9] = False  # vertex 2 fixed
    diag = rng.uniform(1.0, 2.0, n)
    upper = sp.csr_matrix(np.diag(diag))
    made, uploads = [], []
    new, to_device = device_copy.new_ndarray, device_copy.to_device
    monkeypatch.setattr(pcg_module.device_copy, "new_ndarray", lambda *a: made.append(a) or new(*a))
    monkeypatch.setattr(pcg_module.device_copy, "to_device",
                        lambda *a, **k: uploads.append(a[0]) or to_device(*a, **k))
    solver = BatchedPCG()
    # the largest count first, then smaller and mixed ones
    for turn, shapes in enumerate((((9, 2), (5, 4), (6, 1)), ((2, 2), (1, 4)), ((7, 2),), ((3, 2), (4, 4), (1, 1)))):
        sets = _random_sets(rng, nvert, shapes)
        element = []
        for j, b in enumerate(sets):  # every other set's blocks left on the device, as the contact pairs' are
            if j % 2:
                rows = device_copy.new_ndarray(ti.f64, (b.blocks.shape[0] + 2, *b.blocks.shape[1:]))
                rows.from_numpy(np.concatenate([np.zeros((2, *b.blocks.shape[1:])), b.blocks]))
                element.append(DeviceHessianBlocks(b.vertices, DeviceRows(rows, 2, b.blocks.shape[0])))
            else:
                element.append(b)
        want = _dense_sum(sets, free) + np.diag(diag)
        made.clear()
        uploads.clear()
        solver.factorize(upper, VertexBlocks.from_element_blocks(element, free))
        if turn > 0:
            assert made == [], f"turn {turn}: device arrays made again: {made}"
            into = [sum(u is solver._arrays[name] for u in uploads) for name in ("element_vertices", "element_blocks")]
            assert into == [1, 1], into  # every set's vertices in one upload, the host sets' blocks in one
        for _ in range(2):
            p = rng.normal(size=n)
            np.testing.assert_allclose(solver.matvec(p), want @ p, rtol=1e-13, atol=1e-12 * np.abs(want).sum())
        _assert_block_jacobi(solver, want)
        x = rng.normal(size=n)
        np.testing.assert_allclose(solver.solve(want @ x), x, rtol=1e-7, atol=1e-7 * np.abs(x).max())


@pytest.mark.parametrize("device_hessian", [False, True])
def test_newton_operator_with_contacts_equals_the_assembled_matrix(ti_cpu, monkeypatch, device_hessian):
    """With ``device_hessian`` the exact contact Hessians reach the CG without leaving the kernel's ndarray."""
    from sim_core.energies.contact.batch_kernel import PairBatch
    from sim_core.ti_kernels.buffers import DeviceRows

    monkeypatch.setattr(PairBatch, "two_pass", True if device_hessian else PairBatch.two_pass)
    monkeypatch.setattr(PairBatch, "device_hessian", device_hessian)
    # the potentials below are evaluated at host positions, which on CUDA would take the single environment's packed
    # launch (host Hessians); the lockstep's Newton loop evaluates them at its device iterate
    monkeypatch.setattr(PairBatch, "packed", False)
    model = pad_model()
    config = SolverConfig(backend=f"taichi-{ti_cpu}", lockstep=True, linear_solver="pcg", cg_precision="double")
    batch = BatchedSimulation.from_model(model, 3, params=PARAMS, state=task_initial_state(model), solver_config=config)
    pose0 = batch.states[0].effector_pose["pad"].copy()
    for k in range(3):  # press until the pad and the table touch the sheet
        batch.step([control(pose0, MOTIONS[i], k) for i in range(3)])
    engine = batch.lockstep
    solver = engine.solver
    controls = engine.scene.stack_controls([control(pose0, MOTIONS[i], 3) for i in range(3)])
    step, x = solver._set_up_step(engine.state, controls, batch.sims[0].dt, None, StepInfo())
    x = x + np.random.default_rng(0).normal(scale=2e-5, size=x.shape) * step.free.reshape(-1, 3)
    contact_terms = solver.contact.potentials(x, step.x_n, step.memory)
    dynamic = contact_terms + step.dynamic_terms
    assert step.fused is not None
    rng = np.random.default_rng(1)
    for projection in ("none", "clamp"):
        upper, blocks, diagonal = solver._device_operator(step, x, projection, dynamic)
        assert any(isinstance(v, DeviceRows) for _, v in blocks.sets) == (device_hessian and projection == "none")
        assembled = _full(solver._assemble_hessian(step, x, projection, dynamic))
        assert blocks.rows.size > 0  # contact and friction blocks take part
        solver.pcg.factorize(upper, blocks, diagonal)
        scale = abs(assembled).max()
        for _ in range(3):
            p = rng.normal(size=assembled.shape[0])
            got = solver.pcg.matvec(p)
            np.testing.assert_allclose(got, assembled @ p, rtol=0, atol=1e-11 * scale * np.abs(p).max())
        _assert_block_jacobi(solver.pcg, assembled)
    # the projected matrix of one copy (the lockstep's second try for the copies whose exact Hessian was
    # indefinite): right in that copy's rows and columns
    marked = np.zeros(engine.scene.model.vertex_count, dtype=bool)
    marked[engine.scene.index[1]] = True
    dofs = engine.scene.dof_index[1]
    upper, blocks, diagonal = solver._device_operator(step, x, "clamp", dynamic, marked)
    solver.pcg.factorize(upper, blocks, diagonal)
    assembled = _full(solver._assemble_hessian(step, x, "clamp", dynamic))
    scale = abs(assembled).max()
    for _ in range(3):
        p = np.zeros(assembled.shape[0])
        p[dofs] = rng.normal(size=dofs.size)
        np.testing.assert_allclose(solver.pcg.matvec(p)[dofs], (assembled @ p)[dofs], rtol=0,
                                   atol=1e-11 * scale * np.abs(p).max())
