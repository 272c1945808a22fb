"""Upper-triangle assembly of the Newton matrix and the symmetric (Cholesky) solvers.

- the cached-pattern upper-triangle assembly equals the reference COO assembly of
  ``D H D + (I - D)`` (``assemble_hessian``), also when the dynamic blocks or the free mask change;
- PARDISO's Cholesky solves SPD systems, reports an indefinite matrix as False (also one with a
  single slightly negative eigenvalue) and factorises correctly again afterwards on the same pattern;
- the Newton solver's exact-Hessian-first mode ends on the same state as the projected Newton.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from sim_core.assembly import HessianAssembler
from sim_core.builder import ModelBuilder
from sim_core.energies.base import HessianBlocks, assemble_hessian
from sim_core.linsolve import PardisoCholesky, ScipySymmetric, full_from_upper
from sim_core.mesh.sheet import grid_sheet
from sim_core.simulation import Simulation
from sim_core.solver import SolverConfig


def _random_blocks(rng, vertex_count: int, k: int, m: int) -> HessianBlocks:
    v = np.stack([rng.choice(vertex_count, m, replace=False) for _ in range(k)])
    a = rng.normal(size=(k, 3 * m, 3 * m))
    return HessianBlocks(v, a + np.swapaxes(a, 1, 2))


def _reference(parts, diag, free) -> np.ndarray:
    H = assemble_hessian(parts, free.size, diag).toarray()
    D = np.diag(free.astype(float))
    return D @ H @ D + np.diag((~free).astype(float))


def test_upper_assembly_matches_reference_with_changing_dynamic_blocks_and_free_mask():
    rng = np.random.default_rng(0)
    n_v = 20
    static = [_random_blocks(rng, n_v, 15, 3), _random_blocks(rng, n_v, 6, 4)]
    asm = HessianAssembler(3 * n_v)
    diag = rng.uniform(1.0, 2.0, 3 * n_v)
    for trial in range(4):
        free = np.repeat(rng.uniform(size=n_v) > (0.3 if trial < 2 else 0.5), 3)
        dynamic = [_random_blocks(rng, n_v, int(rng.integers(0, 5)), 4)] if trial != 1 else []
        if trial == 3:  # the same dynamic pattern twice (cached union), new values
            dynamic = [HessianBlocks(d.vertices, 2.0 * d.blocks) for d in last]
        U = asm.assemble_upper(static, dynamic, diag, free)
        assert U.has_sorted_indices
        assert np.all(sp.tril(U, k=-1).toarray() == 0.0)
        np.testing.assert_allclose(full_from_upper(U).toarray(), _reference(static + dynamic, diag, free),
                                   rtol=1e-13, atol=1e-12)
        last = dynamic


def test_cached_dynamic_map_and_static_values_path_match_reference():
    """Equal dynamic vertex arrays (new objects, new values) reuse the cached map, a subset of the
    dynamic entries reuses the union pattern; the static part given as slot values (fused kernels)
    equals the block path."""
    rng = np.random.default_rng(2)
    n_v = 24
    static = [_random_blocks(rng, n_v, 20, 3)]
    asm = HessianAssembler(3 * n_v)
    diag = rng.uniform(1.0, 2.0, 3 * n_v)
    free = np.repeat(rng.uniform(size=n_v) > 0.25, 3)
    first = [_random_blocks(rng, n_v, 6, 4), HessianBlocks.empty(4), _random_blocks(rng, n_v, 3, 2)]
    for dynamic in (first, [HessianBlocks(d.vertices.copy(), -1.5 * d.blocks) for d in first],
                    first[:1],  # a subset: the union pattern is kept (its other entries are zeros)
                    [_random_blocks(rng, n_v, 5, 4)], []):
        ref = _reference(static + dynamic, diag, free)
        U = asm.assemble_upper(static, dynamic, diag, free)
        np.testing.assert_allclose(full_from_upper(U).toarray(), ref, rtol=1e-13, atol=1e-12)
        pattern = asm.static_pattern([b.vertices for b in static], free)
        slots = pattern.slot_map(static[0].vertices)
        values = np.bincount(slots[slots >= 0], weights=static[0].blocks[slots >= 0], minlength=pattern.keys.size)
        V = asm.assemble_upper_values(pattern, values, dynamic, diag, free)
        np.testing.assert_allclose(full_from_upper(V).toarray(), ref, rtol=1e-13, atol=1e-12)


def test_a_second_assembler_on_the_first_ones_static_pattern_assembles_the_same_matrix():
    """A second assembler given the first one's static pattern (``use_pattern``: the slots fused kernels write
    into) assembles the same matrix from those slot values, with a union of dynamic entries of its own (the
    first one's union pattern is left as it was); a pattern of another DoF count is refused by name."""
    rng = np.random.default_rng(5)
    n_v = 18
    static = [_random_blocks(rng, n_v, 14, 3)]
    first, second = HessianAssembler(3 * n_v), HessianAssembler(3 * n_v)
    diag = rng.uniform(1.0, 2.0, 3 * n_v)
    free = np.repeat(rng.uniform(size=n_v) > 0.25, 3)
    pattern = first.static_pattern([b.vertices for b in static], free)
    slots = pattern.slot_map(static[0].vertices)
    values = np.bincount(slots[slots >= 0], weights=static[0].blocks[slots >= 0], minlength=pattern.keys.size)
    kept = [_random_blocks(rng, n_v, 4, 4)]
    U_before = first.assemble_upper_values(pattern, values, kept, diag, free)
    other = [_random_blocks(rng, n_v, 5, 4)]
    second.use_pattern(pattern)
    V = second.assemble_upper_values(pattern, values, other, diag, free)
    np.testing.assert_allclose(full_from_upper(V).toarray(), _reference(static + other, diag, free), rtol=1e-13,
                               atol=1e-12)
    U_after = first.assemble_upper_values(pattern, values, kept, diag, free)
    assert np.array_equal(U_after.indptr, U_before.indptr) and np.array_equal(U_after.indices, U_before.indices)
    with pytest.raises(ValueError, match="use_pattern: pattern of 54 DoFs, assembler of 9"):
        HessianAssembler(9).use_pattern(pattern)


def _spd_upper(rng, n: int, shift: float = 0.0):
    a = sp.random(n, n, density=0.05, random_state=int(rng.integers(1 << 30)))
    A = (a @ a.T + sp.eye(n)).toarray()
    w, q = np.linalg.eigh(A)
    return A, w, q


def test_pardiso_cholesky_solves_spd_and_reports_indefinite():
    pytest.importorskip("pypardiso")
    rng = np.random.default_rng(1)
    n = 60
    A, w, q = _spd_upper(rng, n)
    solver = PardisoCholesky()
    b = rng.normal(size=n)
    assert solver.factorize(sp.triu(sp.csr_matrix(A), format="csr"))
    np.testing.assert_allclose(A @ solver.solve(b), b, atol=1e-9)
    # one slightly negative eigenvalue (same pattern: only the values change)
    bad = A - (w[0] * (1.0 + 1e-6)) * np.eye(n)
    assert not solver.factorize(sp.triu(sp.csr_matrix(bad), format="csr"))
    good = A + 0.5 * np.eye(n)
    assert solver.factorize(sp.triu(sp.csr_matrix(good), format="csr"))
    np.testing.assert_allclose(good @ solver.solve(b), b, atol=1e-9)


def test_scipy_symmetric_solver_uses_the_full_matrix_and_reports_indefinite():
    """Diagonal-pivoting SuperLU: the pivots' signs are the inertia (Sylvester), like a Cholesky."""
    rng = np.random.default_rng(2)
    n = 30
    A, w, _ = _spd_upper(rng, n)
    solver = ScipySymmetric()
    assert solver.detects_indefinite
    b = rng.normal(size=n)
    assert solver.factorize(sp.triu(sp.csr_matrix(A), format="csr"))
    np.testing.assert_allclose(A @ solver.solve(b), b, atol=1e-9)
    bad = A - (w[0] * (1.0 + 1e-6)) * np.eye(n)  # one slightly negative eigenvalue
    assert not solver.factorize(sp.triu(sp.csr_matrix(bad), format="csr"))
    assert not solver.factorize(sp.triu(sp.csr_matrix(A - w[3] * np.eye(n) - 1e-9 * np.eye(n)), format="csr"))
    np.testing.assert_allclose(A @ solver.solve(b), b, atol=1e-9)  # the last good factorisation stays
    good = A + 0.5 * np.eye(n)
    assert solver.factorize(sp.triu(sp.csr_matrix(good), format="csr"))
    np.testing.assert_allclose(good @ solver.solve(b), b, atol=1e-9)


def test_exact_hessian_first_converges_to_the_projected_newton_state():
    pytest.importorskip("pypardiso")

    def run(exact_first: bool):
        b = ModelBuilder()
        material = {"youngs_modulus": 1e8, "poisson_ratio": 0.3, "thickness": 1e-3, "density": 1000.0,
                    "bending_stiffness": 1e-3}
        b.add_sheet("sheet", grid_sheet((0.05, 0.02), (8, 4), (0, 0, 0)), material,
                    fixed=np.arange(0, 32, 8), grid_shape=(8, 4))
        cfg = SolverConfig(tol_velocity=1e-9, exact_hessian_first=exact_first)
        sim = Simulation(b.finalize(gravity=(0, 0, -9.81)), dt=0.01, solver_config=cfg)
        infos = [sim.step() for _ in range(5)]
        return sim.state.x, infos

    x_exact, infos_exact = run(True)
    x_proj, infos_proj = run(False)
    np.testing.assert_allclose(x_exact, x_proj, rtol=0, atol=1e-8)
    assert sum(i.iterations for i in infos_exact) <= sum(i.iterations for i in infos_proj)
    assert all(i.projected_iterations == i.iterations for i in infos_proj)
