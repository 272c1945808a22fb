"""The batched envelope Cholesky (sim_core.ti_kernels.envelope_cholesky.BatchedEnvelope): each copy's block of a
block-diagonal system solved exactly (against SciPy's sparse solve), with matrix-free vertex blocks outside the
assembled pattern widening the envelope, an indefinite copy reported, float32 factors refined to float64 accuracy.
A lockstep batch whose Newton systems it solves gives the separate runs' states, and isolates a diverging copy:
``tests/sim_core/batch/test_lockstep.py`` (its ``envelope`` cases)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from sim_core.solver_config import SolverConfig

PANEL = 5
"""Columns a panel of ``schedule="blocks"`` here (ignored by the others): not a divisor of a vertex's three, few
to compile."""


def _grid_block(nx: int, ny: int, seed: int, shift: float) -> sp.csr_matrix:
    """A symmetric positive definite matrix of a ``nx x ny`` vertex grid (3 DoFs a vertex, 3x3 blocks coupling grid
    neighbours and diagonals), its vertices numbered in one random order for every ``seed`` (so that the order
    matters; the copies of a lockstep batch share their pattern), its values by ``seed``."""
    rng = np.random.default_rng(seed)
    nv = nx * ny
    ij = np.arange(nv).reshape(nx, ny)
    pairs = [(ij[:-1, :].ravel(), ij[1:, :].ravel()), (ij[:, :-1].ravel(), ij[:, 1:].ravel()),
             (ij[:-1, :-1].ravel(), ij[1:, 1:].ravel())]
    perm = np.random.default_rng(99).permutation(nv)
    lap = sp.lil_matrix((nv, nv))
    for a, b in pairs:
        for u, v in zip(perm[a], perm[b]):
            w = rng.uniform(0.5, 2.0)
            lap[u, v] -= w
            lap[v, u] -= w
            lap[u, u] += w
            lap[v, v] += w
    m3 = rng.normal(size=(3, 3))
    return (sp.kron(lap.tocsr(), np.eye(3) + 0.2 * (m3 @ m3.T)) + shift * sp.eye(3 * nv)).tocsr()


def _upper(A: sp.spmatrix) -> sp.csr_matrix:
    u = sp.triu(A, format="csr")
    u.sort_indices()
    return u


@pytest.mark.parametrize("schedule", ["rows", "pairs", "dots", "panels", "blocks"])
def test_each_copy_is_solved_exactly_and_a_zero_right_hand_side_gives_zero(ti_cpu, schedule):
    """Each order of the elimination: right-looking entry by entry or by rows, left-looking by dot products (one thread
    a copy here: the entries' order is CUDA's by lane)."""
    from sim_core.ti_kernels.envelope_cholesky import BatchedEnvelope

    blocks = [_grid_block(12, 4, seed, shift) for seed, shift in ((0, 1e-3), (1, 1.0), (2, 10.0))]
    A = sp.block_diag(blocks, format="csr")
    m = blocks[0].shape[0]
    segments = np.repeat(np.arange(3), m)
    solver = BatchedEnvelope(segments, schedule=schedule, panel=PANEL)
    assert solver.schedule == schedule
    assert solver.factorize(_upper(A))
    b = np.random.default_rng(5).normal(size=A.shape[0])
    b[m:2 * m] = 0.0
    x = solver.solve(b)
    want = spla.spsolve(A.tocsc(), b)
    np.testing.assert_allclose(x, want, rtol=0, atol=1e-10 * np.abs(want).max())
    np.testing.assert_array_equal(x[m:2 * m], 0.0)
    assert not solver.indefinite.any() and solver.iterations == 1
    assert solver.entries < m * (m + 1) // 2 / 3  # the envelope of the RCM order, far under the dense triangle
    # a copy whose block is indefinite is reported; the others are still solved exactly
    blocks[2] = (blocks[2] - 50.0 * sp.eye(m)).tocsr()
    solver.factorize(_upper(sp.block_diag(blocks, format="csr")))
    x = solver.solve(b)
    assert list(solver.indefinite) == [False, False, True]
    np.testing.assert_allclose(x[:m], want[:m], rtol=0, atol=1e-10 * np.abs(want).max())


@pytest.mark.parametrize("schedule", ["dots", "panels", "blocks"])
def test_vertex_blocks_outside_the_pattern_widen_the_envelope_and_the_diagonal_is_applied(ti_cpu, schedule):
    """Contact-like 3x3 blocks between far vertices of a copy (matrix-free in the CG) are factorised exactly: the
    envelope widens to hold them; the inertia diagonal and the fixed DoFs' 1 are applied on the device; the fixed
    DoFs' blocks are masked out."""
    from sim_core.ti_kernels.envelope_cholesky import BatchedEnvelope
    from sim_core.energies.base import HessianBlocks
    from sim_core.ti_kernels.pcg import VertexBlocks

    blocks = [_grid_block(5, 4, seed, 0.0) for seed in (3, 4)]
    A0 = sp.block_diag(blocks, format="csr")
    n = A0.shape[0]
    m = blocks[0].shape[0]
    segments = np.repeat(np.arange(2), m)
    rng = np.random.default_rng(7)
    # two-vertex element blocks (6x6, PSD) between vertices far apart in each copy
    verts = np.array([[0, 19], [2, 17], [20 + 1, 20 + 18]], dtype=np.int64)
    vals = []
    for _ in verts:
        g = rng.normal(size=(6, 6))
        vals.append(g @ g.T)
    vals = np.array(vals)
    free = np.ones(n)
    free[3 * 5: 3 * 5 + 3] = 0.0  # vertex 5 of copy 0 fixed
    upper = _upper(A0)
    rows = np.repeat(np.arange(n), np.diff(upper.indptr))
    upper.data[((free[rows] == 0) | (free[upper.indices] == 0)) & (rows != upper.indices)] = 0.0  # as the elastic
    # pattern of a step, which couples no fixed DoF
    diag_values = rng.uniform(1.0, 2.0, size=n)
    diag_slots = np.array([upper.indptr[i] for i in range(n)], dtype=np.int32)  # the diagonal is each row's first
    assert np.array_equal(upper.indices[diag_slots], np.arange(n))
    fixed = diag_slots[free == 0.0]
    # the matrix the CG's operator applies
    F = sp.diags(free)
    E = sp.lil_matrix((n, n))
    for (u, v), blk in zip(verts, vals):
        idx = np.concatenate([3 * u + np.arange(3), 3 * v + np.arange(3)])
        E[np.ix_(idx, idx)] = E[np.ix_(idx, idx)].toarray() + blk
    U = upper.copy()
    U.data = U.data.copy()
    U.data[diag_slots] += diag_values
    U.data[fixed] = 1.0
    A = (U + U.T - sp.diags(U.diagonal()) + F @ E.tocsr() @ F).tocsc()
    solver = BatchedEnvelope(segments, schedule=schedule, panel=PANEL)
    vb = VertexBlocks.from_element_blocks([HessianBlocks(verts, vals)], free)
    solver.factorize((upper.indptr, upper.indices, upper.data.copy()), vb, (diag_slots, diag_values, fixed))
    b = rng.normal(size=n)
    x = solver.solve(b)
    assert solver.widenings == 1 and not solver.indefinite.any()  # found with the solve's read, then done again
    want = spla.spsolve(A, b)
    np.testing.assert_allclose(x, want, rtol=0, atol=1e-10 * np.abs(want).max())
    # the same blocks again: no widening
    solver.factorize((upper.indptr, upper.indices, upper.data.copy()), vb, (diag_slots, diag_values, fixed))
    assert solver.widenings == 1
    np.testing.assert_allclose(solver.solve(b), want, rtol=0, atol=1e-10 * np.abs(want).max())
    # a fresh envelope given copy 1 alone as a device mask: widened by its block, factorised again with the same mask
    from sim_core.ti_kernels.copy_vectors import CopyVectors

    one = np.array([False, True])
    solver = BatchedEnvelope(segments, schedule=schedule, panel=PANEL)
    solver.factorize((upper.indptr, upper.indices, upper.data.copy()), vb, (diag_slots, diag_values, fixed),
                     copies=CopyVectors(np.arange(n // 3).reshape(2, -1)).blend_actions(one, ~one))
    x = solver.solve(b)
    assert solver.widenings == 1 and not solver.indefinite.any()
    np.testing.assert_array_equal(x[:m], 0.0)
    np.testing.assert_allclose(x[m:], want[m:], rtol=0, atol=1e-10 * np.abs(want).max())


@pytest.mark.parametrize("schedule", ["dots", "panels", "blocks"])
def test_float32_factors_with_refinement_reach_the_float64_solution(ti_cpu, schedule):
    from sim_core.ti_kernels.envelope_cholesky import BatchedEnvelope

    blocks = [_grid_block(6, 5, seed, shift) for seed, shift in ((8, 1e-2), (9, 1.0))]
    A = sp.block_diag(blocks, format="csr")
    segments = np.repeat(np.arange(2), blocks[0].shape[0])
    b = np.random.default_rng(1).normal(size=A.shape[0])
    want = spla.spsolve(A.tocsc(), b)
    errors = []
    for refinements in (0, 3):
        solver = BatchedEnvelope(segments, precision="mixed", refinements=refinements, schedule=schedule,
                                 panel=PANEL)
        solver.factorize(_upper(A))
        errors.append(np.abs(solver.solve(b) - want).max() / np.abs(want).max())
        assert solver.iterations == 1 + refinements
    assert 1e-9 < errors[0] < 1e-3  # float32 factors alone: float32's accuracy times the condition
    assert errors[1] < 1e-12


def test_a_dot_products_group_must_be_a_power_of_two_dividing_the_lanes(ti_cpu):
    from sim_core.ti_kernels.envelope_cholesky import BatchedEnvelope

    segments = np.zeros(6, dtype=np.int32)
    assert BatchedEnvelope(segments).group == 1  # one thread a copy on the CPU
    assert BatchedEnvelope(segments, lanes=256, group=8).group == 8
    for lanes, group in ((128, 3), (128, 64), (16, 32)):
        with pytest.raises(ValueError, match=f"dividing the {lanes} lanes, got {group}"):
            BatchedEnvelope(segments, lanes=lanes, group=group)
    with pytest.raises(ValueError, match=r"schedule must be one of pairs\|rows\|dots\|panels\|blocks, got .columns."):
        BatchedEnvelope(segments, schedule="columns")


def test_envelope_needs_a_taichi_backend():
    from sim_core.errors import ConfigError

    with pytest.raises(ConfigError, match="envelope"):
        SolverConfig(linear_solver="envelope")


@pytest.mark.parametrize("schedule", ["dots", "panels", "blocks"])
def test_a_diverged_copy_is_isolated_and_copies_left_out_get_zero(ti_cpu, schedule):
    """A copy whose matrix holds NaN (a diverged copy of a lockstep batch) is reported and leaves the others exact; the
    copies left out of a factorisation (``copies``) get a zero solution, the others the exact one."""
    from sim_core.ti_kernels.envelope_cholesky import BatchedEnvelope

    blocks = [_grid_block(6, 4, seed, 1.0) for seed in (21, 22, 23)]
    m = blocks[0].shape[0]
    segments = np.repeat(np.arange(3), m)
    b = np.random.default_rng(8).normal(size=3 * m)
    A = sp.block_diag(blocks, format="csr")
    want = spla.spsolve(A.tocsc(), b)
    upper = _upper(A)
    solver = BatchedEnvelope(segments, schedule=schedule, panel=PANEL)
    diverged = upper.copy()
    rows = np.repeat(np.arange(3 * m), np.diff(upper.indptr))
    diverged.data = np.where(rows // m == 1, np.nan, upper.data)
    solver.factorize(diverged)
    x = solver.solve(b)
    assert list(solver.indefinite) == [False, True, False]
    for c in (0, 2):
        part = slice(c * m, (c + 1) * m)
        np.testing.assert_allclose(x[part], want[part], rtol=0, atol=1e-10 * np.abs(want[part]).max())
    solver.factorize(upper, copies=np.array([True, False, True]))
    x = solver.solve(b)
    assert not solver.indefinite.any()
    np.testing.assert_array_equal(x[m:2 * m], 0.0)
    np.testing.assert_allclose(x, np.where(segments == 1, 0.0, want), rtol=0, atol=1e-10 * np.abs(want).max())


@pytest.mark.parametrize("schedule", ["dots", "panels", "blocks"])
def test_copies_marked_on_the_device_are_solved_as_by_a_full_factorisation_and_the_others_not_touched(ti_cpu,
                                                                                                       schedule):
    """The copies to factorise given as a device array (a blend's actions, as the lockstep's converged copies are
    left out): the marked copies' solutions are those of every copy's factorisation bit for bit; a copy left out
    whose matrix holds NaN is neither gathered nor reported, and gets 0; a host mask after it is sent again."""
    from sim_core.ti_kernels.copy_vectors import CopyVectors
    from sim_core.ti_kernels.envelope_cholesky import BatchedEnvelope

    blocks = [_grid_block(6, 4, seed, 1.0) for seed in (31, 32, 33)]
    m = blocks[0].shape[0]
    segments = np.repeat(np.arange(3), m)
    b = np.random.default_rng(9).normal(size=3 * m)
    upper = _upper(sp.block_diag(blocks, format="csr"))
    solver = BatchedEnvelope(segments, schedule=schedule, panel=PANEL)
    assert solver.device_copies
    solver.factorize(upper)
    full = solver.solve(b)
    rows = np.repeat(np.arange(3 * m), np.diff(upper.indptr))
    diverged = upper.copy()
    diverged.data = np.where(rows // m == 1, np.nan, upper.data)
    vectors = CopyVectors(np.arange(3 * m // 3).reshape(3, m // 3))
    marked = np.array([True, False, True])
    solver.factorize(diverged, copies=vectors.blend_actions(marked, ~marked))
    x = solver.solve(b)
    assert not solver.indefinite.any()
    np.testing.assert_array_equal(x, np.where(segments == 1, 0.0, full))
    solver.factorize(diverged, copies=np.array([True, True, False]))
    x = solver.solve(b)
    assert list(solver.indefinite) == [False, True, False]
    np.testing.assert_array_equal(x[:m], full[:m])
    np.testing.assert_array_equal(x[2 * m:], 0.0)


def test_values_on_the_device_go_straight_into_the_envelope_without_the_cgs_set_up(ti_cpu):
    """``U``'s values handed over as a device array, with the inertia diagonal and the fixed DoFs' 1: the solve is
    exact and none of the CG's set-up is made (no block-Jacobi inverse, no both-triangle operator); the operator is
    made at :meth:`matvec`'s first use and equals ``A``."""
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels.envelope_cholesky import BatchedEnvelope

    blocks = [_grid_block(5, 4, seed, 0.5) for seed in (31, 32)]
    A0 = sp.block_diag(blocks, format="csr")
    n, m = A0.shape[0], blocks[0].shape[0]
    upper = _upper(A0)
    rng = np.random.default_rng(4)
    diag_slots = upper.indptr[:-1].astype(np.int32)  # each row's first entry: its diagonal
    diag_values = rng.uniform(1.0, 2.0, size=n)
    fixed = diag_slots[[3, 4, 5, m + 9]]
    rows = np.repeat(np.arange(n), np.diff(upper.indptr))
    fixed_dof = np.isin(np.arange(n), upper.indices[fixed])
    upper.data[(fixed_dof[rows] | fixed_dof[upper.indices]) & (rows != upper.indices)] = 0.0
    U = upper.copy()
    U.data[diag_slots] += diag_values
    U.data[fixed] = 1.0
    A = (U + U.T - sp.diags(U.diagonal())).tocsc()
    data = ti.ndarray(ti.f64, (upper.nnz,))
    data.from_numpy(upper.data)
    solver = BatchedEnvelope(np.repeat(np.arange(2), m))
    solver.factorize((upper.indptr, upper.indices, data), None, (diag_slots, diag_values, fixed))
    b = rng.normal(size=n)
    want = spla.spsolve(A, b)
    np.testing.assert_allclose(solver.solve(b), want, rtol=0, atol=1e-10 * np.abs(want).max())
    assert not {"inv", "blk", "full_data", "data"} & set(solver._arrays)
    np.testing.assert_allclose(solver.matvec(want), A @ want, rtol=1e-12, atol=1e-12 * np.abs(b).max())
    np.testing.assert_array_equal(data.to_numpy(), upper.data)  # the caller's values left as they were


@pytest.mark.parametrize("schedule", ["dots", "panels"])
def test_the_substitution_by_vertices_is_the_substitution_by_rows_in_another_order_of_passes(ti_cpu, schedule):
    """``substitution="vertices"`` (a vertex's three rows a pass) solves each copy exactly, float64 and float32 factors
    alike; on one thread a copy it is the same operations in the same order as ``"rows"`` (a row a pass), so the two
    solutions agree to the last bits (a rounding's difference allowed for a compiler's fused multiply-adds)."""
    from sim_core.ti_kernels.envelope_cholesky import BatchedEnvelope

    blocks = [_grid_block(7, 4, seed, shift) for seed, shift in ((41, 1e-2), (42, 1.0))]
    A = sp.block_diag(blocks, format="csr")
    segments = np.repeat(np.arange(2), blocks[0].shape[0])
    b = np.random.default_rng(11).normal(size=A.shape[0])
    want = spla.spsolve(A.tocsc(), b)
    for precision in ("double", "mixed"):
        got = {}
        for substitution in ("rows", "vertices", "vertices-ahead"):
            solver = BatchedEnvelope(segments, precision=precision, refinements=0, schedule=schedule,
                                     substitution=substitution)
            assert solver.substitution == substitution
            solver.factorize(_upper(A))
            got[substitution] = solver.solve(b)
        for name in ("vertices", "vertices-ahead"):
            np.testing.assert_allclose(got[name], got["rows"], rtol=1e-13, atol=0)
        tol = 1e-10 if precision == "double" else 1e-3  # float32 factors alone: float32's accuracy times the condition
        np.testing.assert_allclose(got["vertices"], want, rtol=0, atol=tol * np.abs(want).max())
    with pytest.raises(ValueError, match=r"substitution must be one of rows\|vertices\|vertices-ahead, got .columns."):
        BatchedEnvelope(segments, substitution="columns")
