"""Per-copy operations on stacked device vectors (sim_core.ti_kernels.copy_vectors.CopyVectors) equal CopyRuns's on
the same NumPy arrays: sums to round-off, maxima, finiteness and copy updates exactly, trial points and norms bit for
bit on the CPU (to round-off on CUDA, which fuses multiply-adds: ``assert_same_sums``); the diagonal
quadratic's gradient and energy; the batched CG's device-in / device-out solve equals its host solve."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.batch.copy_runs import CopyRuns
from sim_core.batch.stacked import stack_models
from tests.sim_core.ti_kernels.conftest import assert_same_sums
from tests.support.batch_copies import pad_model


@pytest.fixture(scope="module")
def stacked():
    """Four copies of the pad scene (two bodies and a table: each copy a few runs of stacked vertices)."""
    return stack_models([pad_model() for _ in range(4)])


def _arrays(stacked, rng):
    """Two stacked ``(N, 3)`` arrays: copy 2 of ``b`` zero, copy 1 of ``a`` with a NaN and copy 3 with an infinity."""
    N = stacked.model.vertex_count
    a, b = rng.normal(size=(N, 3)), rng.normal(size=(N, 3))
    b[stacked.index[2]] = 0.0
    a[stacked.index[1][5], 1] = np.nan
    a[stacked.index[3][2], 0] = -np.inf
    return a, b


def test_per_copy_reductions_equal_copy_runs(ti_cpu, stacked):
    from sim_core.ti_kernels.copy_vectors import CopyVectors

    runs, vectors = CopyRuns(stacked.index), CopyVectors(stacked.index)
    assert vectors.copies == 4 and vectors.vertex_count == runs.vertex_count
    a, b = _arrays(stacked, np.random.default_rng(5))
    da, db = vectors.upload(a), vectors.upload(b)
    np.testing.assert_array_equal(vectors.download(da), a)
    finite = np.nan_to_num(a, nan=0.5, posinf=1.0, neginf=-1.0)
    df = vectors.upload(finite)
    np.testing.assert_allclose(vectors.dot(df, db), runs.dot(finite, b), rtol=1e-13, atol=1e-13)
    assert vectors.dot(db, db)[2] == 0.0
    got = vectors.largest_abs(da)  # NaN for copy 1, infinite for copy 3
    np.testing.assert_array_equal(got, runs.largest_abs(a))
    assert np.isnan(got[1]) and got[3] == np.inf
    np.testing.assert_array_equal(vectors.largest_abs(df), runs.largest_abs(finite))
    assert_same_sums(vectors.largest_norm(db), runs.largest_norm(b))  # CUDA fuses the squares' multiply-adds
    norms = vectors.largest_norm(da)  # a NaN or an infinity: NaN
    assert np.isnan(norms[1]) and np.isnan(norms[3]) and np.all(np.isfinite(norms[[0, 2]]))
    np.testing.assert_array_equal(vectors.all_finite(da), runs.all_finite(a))
    np.testing.assert_array_equal(vectors.any_dof(db), [True, True, False, True])
    huge = np.full_like(b, 1e200)  # squares overflow: not finite, as CopyRuns says
    assert np.all(np.isnan(vectors.largest_norm(vectors.upload(huge))))


def test_scalars_in_one_read_equal_copy_runs(ti_cpu, stacked):
    """The dot product, both arrays' largest entries and the second's largest vertex norm of one launch equal
    CopyRuns's (NaN and infinite copies in either array) and the single-purpose kernels'."""
    from sim_core.ti_kernels.copy_vectors import CopyVectors

    runs, vectors = CopyRuns(stacked.index), CopyVectors(stacked.index)
    a, b = _arrays(stacked, np.random.default_rng(11))
    b[stacked.index[0][3], 2] = np.inf  # b: copy 0 infinite, copy 2 zero
    for u, v in ((a, b), (b, a)):
        du, dv = vectors.upload(u), vectors.upload(v)
        dot, big_u, big_v, norm_v = vectors.scalars(du, dv)
        with np.errstate(invalid="ignore"):
            np.testing.assert_allclose(dot, runs.dot(u, v), rtol=1e-13, atol=1e-13)
        np.testing.assert_array_equal(big_u, runs.largest_abs(u))
        np.testing.assert_array_equal(big_v, runs.largest_abs(v))
        np.testing.assert_array_equal(big_u, vectors.largest_abs(du))
        finite = np.isfinite(norm_v)
        np.testing.assert_array_equal(finite, runs.all_finite(v))  # NaN where v is not finite
        np.testing.assert_array_equal(np.isnan(vectors.largest_norm(dv)), ~finite)
        assert_same_sums(norm_v[finite], runs.largest_norm(v)[finite])
    finite = np.nan_to_num(a, nan=0.5, posinf=1.0, neginf=-1.0)
    dot, big, _, norm = vectors.scalars(vectors.upload(finite), vectors.upload(finite))
    np.testing.assert_allclose(dot, runs.dot(finite, finite), rtol=1e-13)
    np.testing.assert_allclose(dot, vectors.dot(vectors.upload(finite), vectors.upload(finite)), rtol=1e-14)
    np.testing.assert_array_equal(big, runs.largest_abs(finite))
    assert_same_sums(norm, runs.largest_norm(finite))


@pytest.mark.parametrize("device_sums", [False, True])
def test_scalars_read_a_copy_sums_in_the_same_copy(ti_cpu, stacked, monkeypatch, device_sums):
    """``scalars(a, b, sums)``: the four scalars of ``scalars(a, b)`` and, fifth, ``sums.read()`` bit for bit (the
    sums' kernel and host values, read in the scalars' one copy back where they are device arrays: on CUDA, and
    here on the test arch with the arch query of :mod:`~sim_core.ti_kernels.copy_vectors` answering "cuda")."""
    from sim_core.ti_kernels import copy_vectors
    from sim_core.ti_kernels.copy_vectors import CopySums, CopyVectors

    if device_sums:
        monkeypatch.setattr(copy_vectors, "current_arch", lambda: "cuda")
    vectors = CopyVectors(stacked.index)
    a, b = _arrays(stacked, np.random.default_rng(17))
    copy_of_vertex = np.empty(vectors.vertex_count, dtype=np.int64)
    for c, vertices in enumerate(stacked.index):
        copy_of_vertex[vertices] = c
    sums = CopySums(copy_of_vertex, vectors.copies)
    assert (sums.device_values is not None) == (device_sums or ti_cpu == "cuda")
    rng = np.random.default_rng(19)
    y, w = rng.normal(size=a.shape), rng.uniform(0.5, 2.0, len(a))
    for _ in range(2):  # the second time over sums zeroed again and another scalars' launch before
        sums.zero()
        finite = np.nan_to_num(b)
        sums.add_diagonal_quadratic(vectors.upload(finite), vectors.upload(y), _weights(w))
        sums.add(np.arange(vectors.copies, dtype=np.float64))
        expected = sums.read()
        assert np.all(expected > 0)
        du, dv = vectors.upload(a), vectors.upload(b)
        *four, read = vectors.scalars(du, dv, sums)
        for got, want in zip(four, vectors.scalars(du, dv)):
            np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(read, expected)


def _weights(w: np.ndarray):
    """``w`` ``(n,)`` as a float64 Taichi ndarray."""
    from sim_core.ti_backend import ti

    out = ti.ndarray(ti.f64, shape=w.shape)
    out.from_numpy(w)
    return out


def test_trial_points_and_copy_updates_equal_copy_runs(ti_cpu, stacked):
    from sim_core.ti_kernels.copy_vectors import CopyVectors

    runs, vectors = CopyRuns(stacked.index), CopyVectors(stacked.index)
    rng = np.random.default_rng(7)
    x, d = rng.normal(size=(2, runs.vertex_count, 3))
    dx, dd = vectors.upload(x), vectors.upload(d)
    alphas = np.array([0.5, 0.0, 2.0, -0.25])
    assert_same_sums(vectors.download(vectors.moved(dx, dd, alphas)), runs.moved(x, d, alphas))
    mask = np.array([True, False, False, True])
    want = runs.zero_copies(x.copy(), mask)
    np.testing.assert_array_equal(vectors.download(vectors.zero_copies(vectors.copy(dx), mask)), want)
    want = runs.copy_where(x.copy(), -d, mask)
    np.testing.assert_array_equal(vectors.download(vectors.copy_where(vectors.copy(dx), dd, mask, scale=-1.0)), want)
    # take the masked copies from -d, zero the others: the CG's right-hand side
    want = runs.copy_where(np.zeros_like(x), -d, mask)
    np.testing.assert_array_equal(vectors.download(vectors.blend(vectors.copy(dx), dd, mask, ~mask, -1.0)), want)
    dofs = np.array([0, 4, 3 * runs.vertex_count - 1])
    want = x.copy().reshape(-1)
    want[dofs] = 0.0
    np.testing.assert_array_equal(vectors.download(vectors.zero_dofs(vectors.copy(dx), dofs)).reshape(-1), want)
    vertices = np.array([3, 11, 2, 40])
    rows = rng.normal(size=(4, 3))
    want = x.copy()
    want[vertices] += rows
    got = vectors.add_rows(vectors.copy(dx), vertices, rows)
    np.testing.assert_array_equal(vectors.download(got), want)
    np.testing.assert_array_equal(vectors.download(vectors.add(got, d)), want + d)


def test_diagonal_quadratic_gradient_and_energy(ti_cpu):
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels import copy_vectors, device_copy, transfer

    rng = np.random.default_rng(2)
    n = 150  # three partial sums, the last one short
    x, y = rng.normal(size=(2, n, 3))
    w = rng.uniform(0.0, 3.0, n)
    g0 = rng.normal(size=(n, 3))
    weight = transfer.upload(device_copy.new_ndarray(ti.f64, (n,)), w)
    g = transfer.upload(copy_vectors.new_vectors(n), g0)
    partial = device_copy.new_ndarray(ti.f64, (copy_vectors.energy_chunks(n),))
    copy_vectors.add_diagonal_quadratic(transfer.upload(copy_vectors.new_vectors(n), x),
                                        transfer.upload(copy_vectors.new_vectors(n), y), weight, g, partial)
    assert_same_sums(transfer.download(g), g0 + w[:, None] * (x - y))
    assert float(np.sum(transfer.download(partial))) == pytest.approx(0.5 * np.sum(w[:, None] * (x - y) ** 2),
                                                                      rel=1e-14)


def test_cg_solve_on_device_equals_the_host_solve(ti_cpu):
    import scipy.sparse as sp

    from sim_core.ti_kernels import copy_vectors, transfer
    from sim_core.ti_kernels.pcg import BatchedPCG

    rng = np.random.default_rng(4)
    nvert, B = 12, 3
    n = 3 * nvert
    segments = np.repeat(np.arange(B), n // B)
    blocks = []
    for _ in range(B):
        m = rng.normal(size=(n // B, n // B))
        blocks.append(m @ m.T + (n // B) * np.eye(n // B))
    A = sp.block_diag(blocks).tocsr()
    solver = BatchedPCG(segments, rtol=1e-12)
    solver.factorize(sp.triu(A).tocsr())
    b = rng.normal(size=n)
    b[segments == 1] = 0.0  # a copy with nothing to solve
    want = solver.solve(b)
    out = copy_vectors.new_vectors(nvert)
    solver.solve_on_device(transfer.upload(copy_vectors.new_vectors(nvert), b.reshape(-1, 3)), out)
    np.testing.assert_array_equal(transfer.download(out).reshape(-1), want)
    np.testing.assert_allclose(A @ want, b, atol=1e-9 * np.abs(b).max())
    with pytest.raises(ValueError, match="right-hand side of shape"):
        solver.solve_on_device(copy_vectors.new_vectors(nvert + 1), out)


def test_blends_send_their_actions_only_when_they_change(ti_cpu, stacked, monkeypatch):
    """The blends' per-copy actions go up only when no action buffer holds them: a repeated mask, or two masks in turn
    (the Newton loop's right-hand side and update), make no upload and still give the masked result; a third mask
    takes the buffer used least lately (one upload); the trial points' step sizes (the float64 buffer, which kernels
    also write) are sent every time."""
    from sim_core.ti_kernels import copy_vectors as module
    from sim_core.ti_kernels.copy_vectors import CopyVectors

    runs, vectors = CopyRuns(stacked.index), CopyVectors(stacked.index)
    rng = np.random.default_rng(8)
    x, d = rng.normal(size=(2, runs.vertex_count, 3))
    dx, dd = vectors.upload(x), vectors.upload(d)
    sent = []
    to_device = module.device_copy.to_device
    monkeypatch.setattr(module.device_copy, "to_device",
                        lambda array, host, *a: sent.append(array) or to_device(array, host, *a))
    assert module.ACTION_BUFFERS == 2
    buffers = [buffer for buffer, _ in vectors._actions]
    first, second, third = (np.array(m) for m in ([True, False, False, True], [False, True, False, True],
                                                   [True, True, False, False]))
    for k, (mask, uploads) in enumerate(((first, 1), (first, 0), (second, 1), (second, 0), (first, 0), (third, 1),
                                         (first, 0), (second, 1), (third, 1), (first, 1))):
        sent.clear()
        want = runs.zero_copies(x.copy(), mask)
        got = vectors.zero_copies(vectors.copy(dx), mask)
        assert sum(any(s is b for b in buffers) for s in sent) == uploads, k
        np.testing.assert_array_equal(vectors.download(got), want)
    alphas = np.array([0.5, 0.0, 2.0, -0.25])
    for _ in range(2):
        sent.clear()
        assert_same_sums(vectors.download(vectors.moved(dx, dd, alphas)), runs.moved(x, d, alphas))
        assert sum(s is vectors._per_copy for s in sent) == 1


def test_new_vectors_are_spares_no_one_holds_zero_filled(ti_cpu, stacked, monkeypatch):
    """``new`` hands out an array again only when nothing but the spares holds it, zero-filled (its former values
    gone), so trial points and directions that are dropped cost no allocation; one that is held keeps its values
    through further ``new``, ``moved`` and ``upload`` calls; the spares are capped."""
    from sim_core.ti_kernels import buffers, copy_vectors
    from sim_core.ti_kernels.copy_vectors import SPARE_VECTORS, CopyVectors

    made = []
    new_ndarray = buffers.device_copy.new_ndarray
    monkeypatch.setattr(buffers.device_copy, "new_ndarray", lambda *a: made.append(a) or new_ndarray(*a))
    vectors = CopyVectors(stacked.index)
    N = vectors.vertex_count
    made.clear()  # (the constructor's own arrays)
    rng = np.random.default_rng(3)
    a, d = rng.normal(size=(N, 3)), rng.normal(size=(N, 3))
    held = vectors.upload(a)
    direction = vectors.upload(d)
    assert len(made) == 2
    trial = vectors.moved(held, direction, np.full(4, 0.5))
    want = a + 0.5 * d
    np.testing.assert_array_equal(vectors.download(trial), want)
    del trial  # dropped: its array is handed out again, zeroed
    again = vectors.new()
    assert len(made) == 3 and not np.any(vectors.download(again))
    np.testing.assert_array_equal(vectors.download(held), a)  # held arrays untouched
    np.testing.assert_array_equal(vectors.download(direction), d)
    kept = [vectors.new() for _ in range(SPARE_VECTORS + 2)]  # more than the cap: the extras outside the spares
    assert len({id(k) for k in kept}) == len(kept) and len(vectors._spares["vectors"]) == SPARE_VECTORS
    assert all(k.shape == (N, 3) for k in kept) and len(made) == 3 + SPARE_VECTORS + 2  # (`again` held too)
    del kept, again
    count = len(made)
    for _ in range(5):  # a Newton iteration's vectors once the first ones are dropped: no allocation
        x = vectors.upload(a)
        vectors.moved(x, vectors.new(), np.zeros(4))
    assert len(made) == count
    assert copy_vectors.new_vectors(N).shape == (N, 3)
