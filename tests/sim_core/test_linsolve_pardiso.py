"""PARDISO through ctypes (LU and Cholesky share one handle) and the cached upper -> full expansion."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from sim_core.errors import SimulationDivergedError
from sim_core.linsolve import PardisoCholesky, PardisoSolver, ScipySymmetric, SymmetricExpansion, full_from_upper

pardiso = pytest.importorskip("pypardiso")


def _random_upper(rng: np.random.Generator, n: int, density: float, explicit_zeros: int = 0) -> sp.csr_matrix:
    A = sp.random(n, n, density=density, random_state=rng, format="csr")
    U = sp.triu(A + A.T, format="csr") + sp.diags(rng.uniform(1.0, 2.0, n) * n)
    U = sp.csr_matrix(U)
    U.sort_indices()
    if explicit_zeros:
        off = np.flatnonzero(U.indices != np.repeat(np.arange(n), np.diff(U.indptr)))
        U.data[rng.choice(off, size=min(explicit_zeros, off.size), replace=False)] = 0.0
    return U


def test_expansion_equals_full_from_upper_over_repeated_and_new_patterns():
    rng = np.random.default_rng(3)
    expand = SymmetricExpansion()
    U = _random_upper(rng, 40, 0.1)
    for k in range(6):
        if k == 3:  # a new pattern
            U = _random_upper(rng, 40, 0.15)
        U = U.copy()
        U.data = rng.normal(size=U.data.size)
        full = expand(U)
        ref = full_from_upper(U)
        assert full.has_sorted_indices
        np.testing.assert_array_equal(full.toarray(), ref.toarray())
        np.testing.assert_array_equal(full.toarray(), full.toarray().T)


def test_expansion_keeps_explicit_zeros_and_rejects_lower_entries():
    rng = np.random.default_rng(4)
    U = _random_upper(rng, 30, 0.2, explicit_zeros=5)
    full = SymmetricExpansion()(U)
    np.testing.assert_array_equal(full.toarray(), full_from_upper(U).toarray())
    diag = np.count_nonzero(U.indices == np.repeat(np.arange(30), np.diff(U.indptr)))
    assert full.nnz == 2 * U.nnz - diag  # every stored entry of U is stored in the full matrix
    L = sp.csr_matrix(U.toarray().T)
    with pytest.raises(ValueError, match="below the diagonal"):
        SymmetricExpansion()(L)


def test_lu_solves_general_and_indefinite_systems_with_pattern_reuse():
    rng = np.random.default_rng(5)
    n = 60
    A = sp.random(n, n, density=0.08, random_state=rng, format="csr") + sp.diags(rng.uniform(-3, 3, n))
    A = sp.csr_matrix(A + sp.eye(n) * 0.5)
    solver = PardisoSolver()
    for k in range(3):  # same pattern, new values: the symbolic analysis is reused
        A = A.copy()
        A.data = A.data * rng.uniform(0.5, 1.5, A.data.size)
        solver.factorize(A)
        b = rng.normal(size=(n, 2))
        x = solver.solve(b)
        assert x.shape == (n, 2)
        assert np.linalg.norm(A @ x - b) <= 1e-9 * np.linalg.norm(b)
        x1 = solver.solve(b[:, 0])
        assert x1.shape == (n,)
        np.testing.assert_allclose(x1, x[:, 0], rtol=1e-10, atol=1e-12)
    # an indefinite symmetric matrix (where the Cholesky refuses), with a new pattern
    U = _random_upper(rng, n, 0.1)
    S = full_from_upper(U) - sp.eye(n) * 1.5 * n
    assert not PardisoCholesky().factorize(sp.triu(S, format="csr"))
    solver.factorize(S)
    b = rng.normal(size=n)
    assert np.linalg.norm(S @ solver.solve(b) - b) <= 1e-9 * np.linalg.norm(b)


def test_lu_errors_are_clear():
    solver = PardisoSolver()
    with pytest.raises(SimulationDivergedError, match="before factorisation"):
        solver.solve(np.ones(3))
    with pytest.raises(ValueError, match="not square"):
        solver.factorize(sp.csr_matrix(np.ones((2, 3))))


def test_cholesky_and_scipy_symmetric_agree_after_expansion_cache():
    rng = np.random.default_rng(6)
    U = _random_upper(rng, 50, 0.1, explicit_zeros=4)
    b = rng.normal(size=50)
    ref = np.linalg.solve(full_from_upper(U).toarray(), b)
    chol, lu_sym = PardisoCholesky(), ScipySymmetric()
    for _ in range(2):
        assert chol.factorize(U) and lu_sym.factorize(U)
        np.testing.assert_allclose(chol.solve(b), ref, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(lu_sym.solve(b), ref, rtol=1e-9, atol=1e-12)


def _constrained(U: sp.csr_matrix, fixed: np.ndarray) -> sp.csr_matrix:
    """``U`` with the rows and columns of ``fixed`` replaced by the identity (as the Newton matrix)."""
    D = sp.diags((~fixed).astype(float))
    C = sp.csr_matrix(sp.triu(D @ U @ D) + sp.diags(fixed.astype(float)))
    C.sort_indices()
    return C


def test_cholesky_splits_off_identity_rows_with_the_whole_matrix_solution():
    """The Cholesky factorises only the DoFs that are not decoupled identity rows, and its solution
    equals, bit for bit, PARDISO's of the whole matrix (the whole matrix factorised by a handle of
    its own); right-hand sides with one or several columns."""
    from sim_core.linsolve import IdentityRows, PardisoHandle

    rng = np.random.default_rng(11)
    n = 90
    U = _random_upper(rng, n, 0.06)
    fixed = np.zeros(n, dtype=bool)
    fixed[rng.choice(n, size=35, replace=False)] = True
    C = _constrained(U, fixed)
    split = IdentityRows(C.indptr, C.indices, C.data)
    np.testing.assert_array_equal(split.identity, fixed)
    assert split.kept.size == n - 35
    solver = PardisoCholesky()
    assert solver.factorize(C)
    whole = PardisoHandle(matrix_type=2, iparm=solver._handle.iparm)
    assert whole.factorize(C.indptr, C.indices, C.data) == 0
    for b in (rng.normal(size=n), rng.normal(size=(n, 3))):
        x = solver.solve(b)
        assert x.shape == b.shape
        err, ref = whole.solve(b)
        assert err == 0
        np.testing.assert_array_equal(x, ref.reshape(b.shape))
        np.testing.assert_array_equal(x[fixed], b[fixed])  # x_i = b_i exactly
    A = full_from_upper(C).toarray()
    np.testing.assert_allclose(A @ solver.solve(b), b, atol=1e-10)


def test_identity_rows_follow_values_and_pattern_changes():
    """A decoupled DoF whose diagonal is not 1 (a free vertex touching nothing) stays in the system
    (a later matrix where an identity row's diagonal is not 1 gets a new split); a new pattern gets
    a new split; a matrix that is all identity needs no factorisation; an indefinite reduced block
    is reported."""
    rng = np.random.default_rng(12)
    n = 40
    U = _random_upper(rng, n, 0.1)
    fixed = np.zeros(n, dtype=bool)
    fixed[:10] = True
    C = _constrained(U, fixed)
    C.data[C.indptr[0]] = 4.0  # row 0: decoupled, diagonal 4
    solver = PardisoCholesky()
    assert solver.factorize(C)
    assert solver._split.kept.size == 31 and not solver._split.identity[0]
    b = rng.normal(size=n)
    np.testing.assert_allclose(full_from_upper(C).toarray() @ solver.solve(b), b, atol=1e-10)
    assert solver.solve(b)[0] == pytest.approx(b[0] / 4.0, rel=1e-15)
    C2 = C.copy()
    C2.data[C2.indptr[0]] = 1.0
    C2.data[C2.indptr[5]] = 2.0  # an identity row no more
    assert solver.factorize(C2)
    assert solver._split.kept.size == 31 and solver._split.identity[0] and not solver._split.identity[5]
    np.testing.assert_allclose(full_from_upper(C2).toarray() @ solver.solve(b), b, atol=1e-10)
    I = sp.csr_matrix(sp.eye(n))
    assert solver.factorize(I)
    np.testing.assert_array_equal(solver.solve(b), b)
    with pytest.raises(ValueError, match="right-hand side has 5 rows"):
        solver.solve(np.ones(5))
    N = C2.copy()
    N.data[N.indptr[20]] = -50.0 * n  # a free DoF's diagonal made negative: not positive definite
    assert not solver.factorize(N)
    with pytest.raises(SimulationDivergedError, match="without a successful factorisation"):
        solver.solve(b)


def test_handle_reanalyses_only_new_patterns_and_trusts_only_read_only_arrays():
    """The symbolic analysis (phase 11) runs for a new pattern only: the same read-only arrays again
    are taken without comparison, equal arrays (other objects, or writeable ones, which could have
    changed in place) are compared; a changed pattern, even in the same writeable arrays, is analysed
    again. Every factorisation solves as a fresh handle's does, bit for bit."""
    from sim_core.linsolve import PardisoHandle

    rng = np.random.default_rng(21)
    n = 60
    iparm = PardisoCholesky()._handle.iparm
    C = _random_upper(rng, n, 0.08)
    C = sp.csr_matrix(C + sp.diags(np.full(n, 2.0 * n)))  # positive definite
    C.sort_indices()
    handle = PardisoHandle(matrix_type=2, iparm=iparm)
    phases = []
    call = handle._call

    def counted(phase, data, b=None):
        if phase != 33:
            phases.append(phase)
        return call(phase, data, b)

    handle._call = counted
    b = rng.normal(size=n)

    def check(indptr, indices, data):
        assert handle.factorize(indptr, indices, data) == 0
        fresh = PardisoHandle(matrix_type=2, iparm=iparm)
        assert fresh.factorize(indptr.copy(), indices.copy(), data) == 0
        assert handle.solve(b)[1].tobytes() == fresh.solve(b)[1].tobytes()

    indptr, indices = C.indptr.copy(), C.indices.copy()
    indptr.flags.writeable = indices.flags.writeable = False
    check(indptr, indices, C.data)
    check(indptr, indices, 2.0 * C.data)  # the same read-only arrays: no analysis
    check(C.indptr.copy(), C.indices.copy(), C.data)  # equal writeable copies: compared, no analysis
    assert phases == [11, 22, 22, 22]
    mutable_ptr, mutable_ind = C.indptr.copy(), C.indices.copy()
    check(mutable_ptr, mutable_ind, C.data)
    D = _random_upper(rng, n, 0.12)
    D = sp.csr_matrix(D + sp.diags(np.full(n, 2.0 * n)))
    D.sort_indices()
    if D.indices.size == mutable_ind.size:  # same sizes: change the writeable arrays in place
        mutable_ptr[:], mutable_ind[:] = D.indptr, D.indices
        check(mutable_ptr, mutable_ind, D.data)
    else:
        check(D.indptr, D.indices, D.data)
    assert phases == [11, 22, 22, 22, 22, 11, 22]


def test_cholesky_reuses_the_split_of_a_shared_read_only_pattern():
    """Matrices that share one read-only pattern (as the assembler's do) keep one identity-row split
    and one analysis; their solutions equal those of copies with fresh writeable arrays."""
    rng = np.random.default_rng(22)
    n = 50
    U = _random_upper(rng, n, 0.1)
    fixed = np.zeros(n, dtype=bool)
    fixed[rng.choice(n, size=12, replace=False)] = True
    C = _constrained(sp.csr_matrix(U + sp.diags(np.full(n, 2.0 * n))), fixed)
    C.indices.flags.writeable = C.indptr.flags.writeable = False
    solver, reference = PardisoCholesky(), PardisoCholesky()
    b = rng.normal(size=n)
    splits = set()
    for scale in (1.0, 1.5, 3.0):
        data = C.data * scale
        data[C.indptr[:-1][fixed]] = 1.0  # the identity rows (their diagonal only) stay 1
        M = sp.csr_matrix((data, C.indices, C.indptr), shape=C.shape)
        assert solver.factorize(M)
        splits.add(id(solver._split))
        R = sp.csr_matrix((M.data.copy(), M.indices.copy(), M.indptr.copy()), shape=M.shape)
        assert reference.factorize(R)
        assert solver.solve(b).tobytes() == reference.solve(b).tobytes()
    assert len(splits) == 1
    assert not solver._split.indptr.flags.writeable and not solver._split.indices.flags.writeable


def test_mkl_runtime_is_the_library_pypardiso_found_on_import():
    """The MKL library is pypardiso's own module-level solver's (searched once, on import), and a handle
    built on it solves."""
    import pypardiso.scipy_aliases

    from sim_core.linsolve import mkl_runtime

    assert mkl_runtime() is pypardiso.scipy_aliases.pypardiso_solver.libmkl
    A = sp.csr_matrix(np.array([[4.0, 1.0], [1.0, 3.0]]))
    lu = PardisoSolver()
    lu.factorize(A)
    np.testing.assert_allclose(A @ lu.solve(np.array([1.0, 2.0])), [1.0, 2.0], rtol=1e-12)
