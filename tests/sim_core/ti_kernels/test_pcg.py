"""The batched block-Jacobi conjugate gradient (sim_core.ti_kernels.pcg.BatchedPCG): each copy's block of
a block-diagonal system solved to its own tolerance, a copy with a zero right-hand side left at zero,
an indefinite copy reported; and a lockstep batch whose Newton systems it solves gives the separate
runs' states."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from sim_core.batch import BatchedSimulation
from sim_core.scenes.task_scene import task_initial_state
from sim_core.solver_config import SolverConfig
from tests.support.batch_copies import MOTIONS, PARAMS, control, pad_model, separate_run


def _spd_block(m: int, seed: int, shift: float) -> sp.csr_matrix:
    """A sparse symmetric positive definite ``(m, m)`` matrix with 3x3 vertex coupling, condition ~1e3."""
    rng = np.random.default_rng(seed)
    a = sp.random(m, m, density=0.08, random_state=rng)
    return (a @ a.T + shift * sp.eye(m) + sp.kron(sp.eye(m // 3), rng.uniform(0.1, 1.0) * np.ones((3, 3)))).tocsr()


def test_each_copy_is_solved_to_its_tolerance(ti_cpu):
    from sim_core.ti_kernels.pcg import BatchedPCG

    blocks = [_spd_block(60, seed, shift) for seed, shift in ((0, 0.01), (1, 1.0), (2, 10.0))]
    A = sp.block_diag(blocks, format="csr")
    segments = np.repeat(np.arange(3), 60)
    solver = BatchedPCG(segments, rtol=1e-12)
    upper = sp.triu(A, format="csr")
    upper.sort_indices()
    assert solver.factorize(upper)
    b = np.random.default_rng(5).normal(size=A.shape[0])
    b[60:120] = 0.0  # copy 1 has nothing to solve
    x = solver.solve(b)
    want = spla.spsolve(A.tocsc(), b)
    for c in (0, 2):
        part = slice(60 * c, 60 * (c + 1))
        assert np.linalg.norm(x[part] - want[part]) <= 1e-9 * np.linalg.norm(want[part])
        assert np.linalg.norm(A[part, part] @ x[part] - b[part]) <= 1e-11 * np.linalg.norm(b[part])
    np.testing.assert_array_equal(x[60:120], 0.0)
    assert not solver.indefinite.any() and not solver.unconverged.any() and solver.iterations > 8
    # a copy whose block is indefinite is reported; the others are still solved
    blocks[2] = (blocks[2] - 50.0 * sp.eye(60)).tocsr()
    A = sp.block_diag(blocks, format="csr")
    upper = sp.triu(A, format="csr")
    upper.sort_indices()
    solver.factorize(upper)
    x = solver.solve(b)
    assert list(solver.indefinite) == [False, False, True]
    assert np.linalg.norm(x[:60] - want[:60]) <= 1e-9 * np.linalg.norm(want[:60])


def test_a_copy_not_converged_within_the_iteration_limit_is_reported_with_the_iterations_run(ti_cpu):
    from sim_core.ti_kernels.pcg import BatchedPCG

    blocks = [_spd_block(90, 0, 1e-3), sp.eye(90, format="csr")]  # copy 1: the identity, one iteration
    A = sp.block_diag(blocks, format="csr")
    upper = sp.triu(A, format="csr")
    upper.sort_indices()
    solver = BatchedPCG(np.repeat(np.arange(2), 90), rtol=1e-14, max_iterations=40)
    solver.factorize(upper)
    b = np.random.default_rng(2).normal(size=180)
    x = solver.solve(b)
    assert list(solver.unconverged) == [True, False] and not solver.indefinite.any()
    assert solver.iterations == 40  # five launches of 8, each iteration of copy 0 counted once
    np.testing.assert_allclose(x[90:], b[90:], rtol=1e-14)  # the identity block is solved at once
    r = np.linalg.norm(A[:90, :90] @ x[:90] - b[:90])
    assert 1e-14 * np.linalg.norm(b[:90]) < r < np.linalg.norm(b[:90])  # copy 0 progressed, not to tolerance


def test_the_count_and_every_copys_flags_come_back_in_one_read_a_poll(ti_cpu, monkeypatch):
    """The host's reads of a solve: one int32 array a poll of the running count, holding every copy's iterations,
    indefinite and unconverged flags too (copy 0 unconverged at the limit, copy 1 done in one iteration, copy 2
    indefinite), each flag the copy's own."""
    from sim_core.ti_kernels import pcg as pcg_module
    from sim_core.ti_kernels.pcg import ITERATIONS_PER_LAUNCH, LAUNCHES_PER_TEST, BatchedPCG

    blocks = [_spd_block(90, 0, 1e-3), sp.eye(90, format="csr"), (_spd_block(90, 3, 1.0) - 50.0 * sp.eye(90)).tocsr()]
    upper = sp.triu(sp.block_diag(blocks, format="csr"), format="csr")
    upper.sort_indices()
    limit = ITERATIONS_PER_LAUNCH * (LAUNCHES_PER_TEST + 2)
    solver = BatchedPCG(np.repeat(np.arange(3), 90), rtol=1e-14, max_iterations=limit)
    solver.factorize(upper)
    reads = []
    copy_out = pcg_module._copy_out
    monkeypatch.setattr(pcg_module, "_copy_out", lambda array: reads.append(array.shape) or copy_out(array))
    solver.solve(np.random.default_rng(2).normal(size=270))
    # a first poll after LAUNCHES_PER_TEST launches, then one a launch up to the limit: 3 polls, 3 reads
    assert reads == [(1 + 3 * 3,)] * 3
    assert list(solver.unconverged) == [True, False, False]
    assert list(solver.indefinite) == [False, False, True]
    assert solver.iterations == limit


def test_values_on_the_device_and_the_diagonal_added_there_give_the_matrix_with_that_diagonal(ti_cpu):
    """``factorize`` with ``U``'s values as a Taichi ndarray and a diagonal (added at given slots, 1 at the
    fixed ones) on the device multiplies and solves as the matrix assembled on the host, and leaves the
    passed values unchanged."""
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels.pcg import BatchedPCG

    blocks = [_spd_block(30, seed, 1.0) for seed in (3, 4)]
    A = sp.block_diag(blocks, format="csr")
    upper = sp.triu(A, format="csr")
    upper.sort_indices()
    n = A.shape[0]
    slots = np.array([upper.indptr[i] + np.flatnonzero(upper.indices[upper.indptr[i]:upper.indptr[i + 1]] == i)[0]
                      for i in range(n)])
    rng = np.random.default_rng(7)
    diag = rng.uniform(1.0, 3.0, n)
    fixed = slots[[4, 40]]  # two DoFs whose diagonal entry is set to 1
    want = upper.copy()
    want.data[slots] += diag
    want.data[fixed] = 1.0
    want_full = (want + sp.triu(want, k=1).T).tocsr()
    device_values = ti.ndarray(ti.f64, shape=(upper.nnz + 5,))  # longer than nnz, as the fused kernels' array
    device_values.from_numpy(np.concatenate([upper.data, np.full(5, np.nan)]))
    solver = BatchedPCG(np.repeat(np.arange(2), 30), rtol=1e-12)
    solver.factorize((upper.indptr, upper.indices, device_values), None, (slots, diag, fixed))
    p = rng.normal(size=n)
    np.testing.assert_allclose(solver.matvec(p), want_full @ p, rtol=1e-13, atol=1e-13 * np.abs(want_full @ p).max())
    b = rng.normal(size=n)
    x = solver.solve(b)
    assert np.linalg.norm(want_full @ x - b) <= 1e-10 * np.linalg.norm(b)
    np.testing.assert_array_equal(device_values.to_numpy()[: upper.nnz], upper.data)


def _plate_and_solid(nx: int, ny: int, solid: int, stiffness: float) -> sp.csr_matrix:
    """A copy's Newton matrix like a sheet on a gel: a plate's bending operator ``K_b (L^2 (x) I_3)`` (``L`` the
    ``nx x ny`` grid Laplacian, vertex ``ix * ny + iy``) plus a mass term, then ``solid`` vertices of a chain
    Laplacian, the plate's last vertex coupled to the chain's first. Stiff against its mass (condition ~1e5)."""
    def chain(k: int) -> sp.csr_matrix:
        return sp.diags([-np.ones(k - 1), 2.0 * np.ones(k), -np.ones(k - 1)], [-1, 0, 1])

    lap = sp.kronsum(chain(ny), chain(nx))  # vertex ix * ny + iy
    plate = stiffness * sp.kron(lap @ lap, sp.eye(3)) + sp.eye(3 * nx * ny)
    body = 1e2 * sp.kron(chain(solid), sp.eye(3)) + sp.eye(3 * solid)
    a = sp.block_diag([plate, body]).tolil()
    k = 3 * (nx * ny - 1)
    for d in range(3):
        a[k + d, 3 * nx * ny + d] = a[3 * nx * ny + d, k + d] = -10.0
        a[k + d, k + d] += 10.0
        a[3 * nx * ny + d, 3 * nx * ny + d] += 10.0
    return a.tocsr()


def _plate_copies(scale: float = 1.0) -> tuple:
    """Three plate-and-gel copies (:func:`_plate_and_solid`, plate stiffness 1e3, 3e3, 1e4) times ``scale``:
    ``(A, upper triangle CSR, segments, each copy's plate as a band block, DoFs a copy)``."""
    nx, ny, solid = 12, 5, 20
    A = sp.block_diag([scale * _plate_and_solid(nx, ny, solid, s) for s in (1e3, 3e3, 1e4)], format="csr")
    n_copy = 3 * (nx * ny + solid)
    upper = sp.triu(A, format="csr")
    upper.sort_indices()
    bands = np.stack([n_copy * c + np.arange(3 * nx * ny) for c in range(3)])
    return A, upper, np.repeat(np.arange(3), n_copy), bands, n_copy


def test_band_blocks_of_the_plates_cut_the_iterations_and_each_copy_is_solved_to_its_tolerance(ti_cpu):
    """Each copy's plate as a band block (its vertices along the grid's long axis): the solution is SciPy's to the
    tolerance, in fewer than a third of the block-Jacobi iterations; a copy with nothing to solve stays at zero."""
    from sim_core.ti_kernels.pcg import BatchedPCG

    A, upper, segments, bands, n_copy = _plate_copies()
    b = np.random.default_rng(4).normal(size=A.shape[0])
    b[n_copy:2 * n_copy] = 0.0
    want = spla.spsolve(A.tocsc(), b)
    iterations = {}
    for name, band in (("jacobi", None), ("bands", bands)):
        solver = BatchedPCG(segments, rtol=1e-10, bands=band)
        solver.factorize(upper)
        x = solver.solve(b)
        iterations[name] = solver.iterations
        for c in (0, 2):
            part = slice(n_copy * c, n_copy * (c + 1))
            assert np.linalg.norm(A[part, part] @ x[part] - b[part]) <= 1e-10 * np.linalg.norm(b[part]), (name, c)
            assert np.linalg.norm(x[part] - want[part]) <= 1e-6 * np.linalg.norm(want[part]), (name, c)
        np.testing.assert_array_equal(x[n_copy:2 * n_copy], 0.0)
        assert not solver.indefinite.any() and not solver.unconverged.any()
    assert solver.bands.width == 3 * 2 * 5 and solver.bands.usable.all()  # L^2 couples rows ix and ix + 2 (ny = 5)
    assert 3 * iterations["bands"] < iterations["jacobi"], iterations


@pytest.mark.parametrize("rtol", [1e-4, 1e-7])  # the lockstep's; one near float32's rounding times the condition
def test_mixed_precision_solves_to_the_tolerance_and_equals_the_double_solution_within_it(ti_cpu, rtol):
    """Stored in float32 (operator, vertex inverses, band tiles), the CG solves the stiff plate-and-gel copies
    (condition ~1e5) to the tolerance plus the operator's rounding ``2^-24 |A| |x|``, within that of the float64
    CG's solution, in about as many iterations; its product is the matrix's to float32 rounding, not exactly."""
    from sim_core.ti_kernels.pcg import BatchedPCG

    A, upper, segments, bands, n_copy = _plate_copies(np.pi)  # entries not float32's
    rng = np.random.default_rng(8)
    b = rng.normal(size=A.shape[0])
    b[n_copy:2 * n_copy] = 0.0
    x, iterations = {}, {}
    for precision in ("double", "mixed"):
        solver = BatchedPCG(segments, rtol=rtol, bands=bands, precision=precision)
        solver.factorize(upper)
        x[precision] = solver.solve(b)
        iterations[precision] = solver.iterations
        assert solver.bands.usable.all() and not solver.indefinite.any() and not solver.unconverged.any()
        for c in (0, 2):
            part = slice(n_copy * c, n_copy * (c + 1))
            rounding = 2.0 ** -24 * np.linalg.norm(abs(A[part, part]) @ np.abs(x[precision][part]))  # |A~ - A| |x|
            residual = np.linalg.norm(A[part, part] @ x[precision][part] - b[part])
            assert residual <= 1.01 * rtol * np.linalg.norm(b[part]) + (rounding if precision == "mixed" else 0.0)
        np.testing.assert_array_equal(x[precision][n_copy:2 * n_copy], 0.0)
    for c in (0, 2):
        part = slice(n_copy * c, n_copy * (c + 1))
        change = A[part, part] @ (x["mixed"][part] - x["double"][part])
        assert np.linalg.norm(change) <= 2.0 * rtol * np.linalg.norm(b[part]) + 2.0 ** -23 * np.linalg.norm(
            abs(A[part, part]) @ np.abs(x["mixed"][part]))
    assert iterations["mixed"] <= iterations["double"] + 3, iterations
    p = rng.normal(size=A.shape[0])
    rounding = np.abs(solver.matvec(p) - A @ p)
    assert 0.0 < rounding.max() and np.all(rounding <= 2.0 ** -23 * (abs(A) @ np.abs(p)))


def test_an_unknown_precision_is_refused(ti_cpu):
    from sim_core.errors import ConfigError
    from sim_core.ti_kernels.pcg import BatchedPCG

    with pytest.raises(ConfigError, match="precision"):
        BatchedPCG(np.zeros(3, np.int32), precision="half")
    with pytest.raises(ConfigError, match="cg_precision"):
        SolverConfig(backend=f"taichi-{ti_cpu}", cg_precision="single")


@pytest.mark.parametrize("device_hessian, precision", [(False, "mixed"), (True, "mixed"), (False, "double")])
def test_lockstep_batch_with_the_conjugate_gradient_gives_the_separate_runs(ti_cpu, monkeypatch, device_hessian,
                                                                              precision):
    """With ``device_hessian`` (CUDA's defaults) the CG takes the contact Hessians from the pair kernel's ndarray,
    and the projected retry projects the contact pair blocks and the elastic terms' reduced blocks by the device's
    projection kernel (``block_projection.DEVICE_METHOD``, Householder-QL; the separate runs: LAPACK); the CG in
    either precision."""
    from sim_core.energies.contact.batch_kernel import PairBatch
    from sim_core.ti_kernels import block_projection

    monkeypatch.setattr(PairBatch, "two_pass", True if device_hessian else PairBatch.two_pass)
    monkeypatch.setattr(PairBatch, "device_hessian", device_hessian)
    projected = []
    if device_hessian:  # the elastic blocks' projection as on CUDA (project_reduced_blocks: the device's kernel)
        monkeypatch.setattr(block_projection, "current_arch", lambda: "cuda")
        kernel = block_projection.DEVICE_KERNELS[block_projection.DEVICE_METHOD]
        monkeypatch.setitem(block_projection.DEVICE_KERNELS, block_projection.DEVICE_METHOD,
                            lambda *args: (projected.append(args[3]), kernel(*args))[1])
    model = pad_model()
    steps = 2
    batch = BatchedSimulation.from_model(model, 3, params=PARAMS, state=task_initial_state(model),
                                         solver_config=SolverConfig(backend=f"taichi-{ti_cpu}", lockstep=True,
                                                                    linear_solver="pcg", cg_precision=precision))
    assert batch.lockstep.solver.pcg.precision == precision
    if device_hessian:
        batch.lockstep.solver.subset_projection = block_projection.DEVICE_METHOD
    pose0 = batch.states[0].effector_pose["pad"].copy()
    got = []
    for k in range(steps):
        res = batch.step([control(pose0, MOTIONS[i], k) for i in range(3)])
        assert res.failed_now == []
        got.append([s.x.copy() for s in batch.states])
    assert batch.lockstep.solver.pcg.iterations > 0
    assert batch.lockstep.solver.pcg.bands.usable.all()  # each copy's sheet a band block of the preconditioner
    assert not device_hessian or sum(projected) > 0  # projected retries ran, their blocks by the device's kernel
    tol = SolverConfig().tol_velocity * 0.005
    for i in range(3):
        alone = separate_run(model, PARAMS[i], MOTIONS[i])
        for k in range(steps):
            assert np.max(np.abs(got[k][i] - alone[k].x)) <= tol, (i, k)


def test_pcg_needs_a_taichi_backend():
    from sim_core.errors import ConfigError

    with pytest.raises(ConfigError, match="pcg"):
        SolverConfig(linear_solver="pcg")


def test_a_retry_of_some_copies_factorises_their_band_blocks_alone_with_the_same_steps(ti_cpu, monkeypatch):
    """A lockstep batch whose projected retries take some of its copies only (the pad batch's first two steps: one,
    two or three of the three copies): each retry factorises the band blocks of its copies alone
    (``BatchedPCG.factorize(..., copies=)``), and the steps equal those with every copy's band blocks factorised at
    every retry (the same Newton iterations copy by copy, positions to the CPU arch's parallel round-off; the batch
    against each copy's separate run with these retries:
    :func:`test_lockstep_batch_with_the_conjugate_gradient_gives_the_separate_runs`)."""
    from sim_core.ti_kernels.band_cholesky import BandBlocks
    from sim_core.ti_kernels.pcg import BatchedPCG

    model = pad_model()
    steps = 2
    selections = []
    factorize = BatchedPCG.factorize

    def recorded(self, upper, blocks=None, diagonal=None, copies=None):
        selections.append(None if copies is None else np.array(copies))
        return factorize(self, upper, blocks, diagonal, copies)

    monkeypatch.setattr(BatchedPCG, "factorize", recorded)

    def run() -> tuple[list, list]:
        batch = BatchedSimulation.from_model(model, 3, params=PARAMS, state=task_initial_state(model),
                                             solver_config=SolverConfig(backend=f"taichi-{ti_cpu}", lockstep=True,
                                                                        linear_solver="pcg"))
        pose0 = batch.states[0].effector_pose["pad"].copy()
        states, iterations = [], []
        for k in range(steps):
            res = batch.step([control(pose0, MOTIONS[i], k) for i in range(3)])
            assert res.failed_now == []
            states.append([s.x.copy() for s in batch.states])
            iterations.append([info.iterations for info in res.infos])
        return states, iterations

    states, iterations = run()
    some = [c for c in selections if c is not None]
    assert any(0 < c.sum() < c.size for c in some)  # retries of some copies only
    selections.clear()
    select = BandBlocks.select
    monkeypatch.setattr(BandBlocks, "select", lambda self, copies: select(self, None))  # every block each time
    every, every_iterations = run()
    assert any(c is not None for c in selections)
    assert iterations == every_iterations
    for k in range(steps):
        for i in range(3):
            assert np.max(np.abs(states[k][i] - every[k][i])) <= 1e-9, (k, i)
