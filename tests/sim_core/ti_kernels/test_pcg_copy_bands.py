"""Whole-copy band blocks of the batched CG (sim_core.batch.sheet_bands.copy_band_dofs) and band factors kept from an
earlier matrix (BatchedPCG.factorize(..., keep_bands=True)): a copy's whole system as one band block is its exact
inverse (the CG stops after one or two iterations), a stacked scene's free vertices in reverse Cuthill-McKee order
narrow its band, and with kept factors the CG still solves the new matrix to its tolerance."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import reverse_cuthill_mckee

from sim_core.batch.sheet_bands import copy_band_dofs
from sim_core.batch.stacked import stack_models
from tests.sim_core.ti_kernels.test_pcg import _plate_copies
from tests.support.batch_copies import pad_model


def _element_pattern(scene) -> sp.csr_matrix:
    """The upper triangle (DoFs, CSR) of the stacked model's elastic coupling: every pair of vertices of a tet, a
    sheet triangle or a hinge, three DoFs each."""
    model = scene.model
    rows, cols = [], []
    for body in model.bodies.values():
        for elements in (body.tets, body.triangles, body.hinges):
            if elements is None or not len(elements):
                continue
            k = elements.shape[1]
            rows.append(np.repeat(elements, k, axis=1).ravel())
            cols.append(np.tile(elements, (1, k)).ravel())
    r, c = np.concatenate(rows), np.concatenate(cols)
    dof_r = np.repeat(3 * r, 9) + np.tile(np.repeat(np.arange(3), 3), r.size)  # each vertex pair's 3x3 DoFs
    dof_c = np.repeat(3 * c, 9) + np.tile(np.tile(np.arange(3), 3), c.size)
    n = 3 * model.vertex_count
    upper = sp.triu(sp.coo_matrix((np.ones(dof_r.size), (dof_r, dof_c)), shape=(n, n)).tocsr(), format="csr")
    upper.sort_indices()
    return upper


def _band(order_dofs: np.ndarray, upper: sp.csr_matrix) -> int:
    """The largest ``|p(i) - p(j)|`` over the pattern's entries with both DoFs in ``order_dofs`` (``p``: position)."""
    pos = np.full(upper.shape[0], -1)
    pos[order_dofs] = np.arange(order_dofs.size)
    coo = upper.tocoo()
    keep = (pos[coo.row] >= 0) & (pos[coo.col] >= 0)
    return int(np.abs(pos[coo.row[keep]] - pos[coo.col[keep]]).max())


def test_each_copys_free_vertices_in_reverse_cuthill_mckee_order_narrow_the_band():
    model = pad_model()
    model.vertex_fixed[model.bodies["sheet"].vertices[:3]] = True
    scene = stack_models([model, model, model])
    upper = _element_pattern(scene)
    free = np.repeat(~scene.model.vertex_fixed, 3)
    bands = copy_band_dofs(scene, free, upper.indptr, upper.indices)
    local_free = np.flatnonzero(~model.vertex_fixed)
    assert bands.shape == (3, 3 * local_free.size)
    for c in range(3):
        expect = np.sort((3 * scene.index[c][local_free][:, None] + np.arange(3)).ravel())
        assert np.array_equal(np.sort(bands[c]), expect)
        local = np.searchsorted(scene.index[c], bands[c][::3] // 3)  # the same local order in every copy
        assert np.array_equal(local, np.searchsorted(scene.index[0], bands[0][::3] // 3))
    natural = np.sort(bands[0])
    assert _band(bands[0], upper) < _band(natural, upper)
    # a contact pair of copy 0 joins the graph: the sheet's and the pad's vertices of the pair come closer in the
    # order (apart, the two bodies are two components, one ordered after the other)
    sheet, pad = model.bodies["sheet"].vertices, model.bodies["pad"].vertices
    pairs = scene.index[0][np.array([[sheet[-1], pad[0]], [pad[0], sheet[-1]]])]

    def distance(order: np.ndarray) -> int:
        pos = {int(d): k for k, d in enumerate(order)}
        return abs(pos[3 * int(pairs[0, 0])] - pos[3 * int(pairs[0, 1])])

    with_pairs = copy_band_dofs(scene, free, upper.indptr, upper.indices, pairs)
    assert distance(with_pairs[0]) < distance(bands[0]), (distance(with_pairs[0]), distance(bands[0]))


def test_a_copys_whole_system_as_one_band_block_is_solved_in_one_or_two_iterations(ti_cpu):
    """Each copy's plate and gel chain (the chain coupled to the plate) as one band block in reverse Cuthill-McKee
    order: the preconditioner is the copy's exact inverse, so the CG stops after one or two iterations at 1e-10, the
    solution SciPy's, against dozens with the plate alone as a block."""
    from sim_core.ti_kernels.pcg import BatchedPCG

    A, upper, segments, plates, n_copy = _plate_copies()
    block = A[:n_copy, :n_copy]
    vertex_graph = (abs(block[::3, ::3]) + abs(block[::3, 1::3]) + abs(block[1::3, ::3]) > 0).astype(float)
    order = reverse_cuthill_mckee(sp.csr_matrix(vertex_graph), symmetric_mode=True)
    whole = np.stack([n_copy * c + (3 * order[:, None] + np.arange(3)).ravel() for c in range(3)])
    b = np.random.default_rng(5).normal(size=A.shape[0])
    want = sp.linalg.spsolve(A.tocsc(), b)
    iterations = {}
    for name, bands in (("plates", plates), ("whole", whole)):
        solver = BatchedPCG(segments, rtol=1e-10, bands=bands)
        solver.factorize(upper)
        x = solver.solve(b)
        iterations[name] = solver.iterations
        assert solver.bands.usable.all() and not solver.unconverged.any()
        for c in range(3):
            part = slice(n_copy * c, n_copy * (c + 1))
            assert np.linalg.norm(A[part, part] @ x[part] - b[part]) <= 1e-10 * np.linalg.norm(b[part]), (name, c)
            assert np.linalg.norm(x[part] - want[part]) <= 1e-6 * np.linalg.norm(want[part]), (name, c)
    assert iterations["whole"] <= 2 < 5 * iterations["whole"] < iterations["plates"], iterations


def test_band_factors_kept_from_an_earlier_matrix_precondition_the_new_one_which_is_solved_to_its_tolerance(ti_cpu):
    """Factorised on ``A1``, kept for ``A2 = A1 + a diagonal shift``: the band tiles are those of ``A1`` to the bit,
    the CG solves ``A2`` to the tolerance (its own operator), in more iterations than with ``A2``'s own factors; a
    factorisation with the factors refreshed gives ``A2``'s own factors' solve again."""
    from sim_core.ti_kernels.pcg import BatchedPCG

    A1, upper1, segments, plates, n_copy = _plate_copies()
    shift = sp.diags(np.random.default_rng(6).uniform(0.5, 2.0, A1.shape[0]) * 50.0)
    A2 = (A1 + shift).tocsr()
    upper2 = sp.triu(A2, format="csr")
    upper2.sort_indices()
    b = np.random.default_rng(7).normal(size=A1.shape[0])
    own = BatchedPCG(segments, rtol=1e-10, bands=plates)
    own.factorize(upper2)
    x_own = own.solve(b)
    solver = BatchedPCG(segments, rtol=1e-10, bands=plates)
    solver.factorize(upper1)
    tiles = [a.to_numpy().copy() for a in solver.bands.arguments()[:3]]
    solver.factorize(upper2, keep_bands=True)
    for kept, now in zip(tiles, solver.bands.arguments()[:3]):
        np.testing.assert_array_equal(now.to_numpy(), kept)
    x = solver.solve(b)
    for c in range(3):
        part = slice(n_copy * c, n_copy * (c + 1))
        assert np.linalg.norm(A2[part, part] @ x[part] - b[part]) <= 1e-10 * np.linalg.norm(b[part]), c
    assert solver.iterations > own.iterations, (solver.iterations, own.iterations)
    solver.factorize(upper2)
    np.testing.assert_allclose(solver.solve(b), x_own, rtol=0, atol=1e-12 * np.abs(x_own).max())
    assert solver.iterations == own.iterations
