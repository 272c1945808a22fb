"""The batched CG's band blocks (sim_core.ti_kernels.band_cholesky.BandBlocks): each block's matrix (its CSR
entries and the vertex blocks in its band) factorised and inverted on the device, applied as the block's exact
inverse; a block whose band is not positive definite is reported and left out."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp


def _banded_spd(m: int, w: int, seed: int) -> np.ndarray:
    """A dense symmetric positive definite ``(m, m)`` matrix whose entries vanish beyond ``w`` of the diagonal."""
    rng = np.random.default_rng(seed)
    g = np.tril(np.triu(rng.normal(size=(m, m)), -w // 2), w // 2)
    return g @ g.T + 0.5 * np.eye(m)


def _operator(a: sp.csr_matrix):
    """The both-triangle CSR of ``a`` as device ndarrays ``(indptr, indices, data)``."""
    from sim_core.ti_kernels import device_copy
    from sim_core.ti_backend import ti

    out = []
    for host, dtype in ((a.indptr, ti.i32), (a.indices, ti.i32), (a.data, ti.f64)):
        arr = device_copy.new_ndarray(dtype, (host.size,))
        arr.from_numpy(host.astype(np.int32 if dtype == ti.i32 else np.float64))
        out.append(arr)
    return out


def _system(seed: int = 0):
    """Three copies of 18 DoFs (6 vertices): vertices 0-3 of each copy a band block (listed in a shuffled vertex
    order, in which the block is banded with half-bandwidth 6 DoFs), the rest coupled to them; copy 2's block
    lists vertices 0-2 and pads. Returns the matrix, the blocks' DoFs, the segments and copy 0's vertex order."""
    rng = np.random.default_rng(seed)
    n_copy, copies = 18, 3
    blocks, dofs, orders = [], np.full((copies, 12), -1), []
    for c in range(copies):
        size = 12 if c < 2 else 9
        vertex_order = rng.permutation(size // 3)
        order = (3 * vertex_order[:, None] + np.arange(3)).reshape(-1)  # band position -> copy DoF
        a = _banded_spd(n_copy, 6, seed + c)
        a[:size, :size] = 0.0
        a[np.ix_(order, order)] = _banded_spd(size, 6, seed + 10 + c) + 4.0 * np.eye(size)
        a[:size, size:] *= 0.1
        a[size:, :size] *= 0.1
        a = 0.5 * (a + a.T) + n_copy * np.eye(n_copy)
        blocks.append(a)
        dofs[c, :size] = n_copy * c + order
        orders.append(vertex_order)
    a = sp.block_diag(blocks, format="csr")
    a.eliminate_zeros()  # the pattern is the nonzeros (the band's width is measured on it)
    return a, dofs, np.repeat(np.arange(copies), n_copy), orders[0]


def test_each_block_is_applied_as_its_exact_inverse_with_the_vertex_blocks_in_its_band(ti_cpu):
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels import device_copy
    from sim_core.ti_kernels.band_cholesky import BandBlocks

    a, dofs, seg, order = _system()
    n = a.shape[0]
    bands = BandBlocks(dofs, seg)
    # in copy 0's band: a diagonal vertex block and the pair coupling two vertices next in the band order (5 DoFs
    # apart at most); one across copies, left out
    rng = np.random.default_rng(3)
    e = rng.normal(size=(3, 3))
    brow = np.array([order[0], order[0], order[1], 0], np.int32)
    bcol = np.array([order[0], order[1], order[0], 6], np.int32)
    bval = np.stack([e @ e.T, 0.3 * e, 0.3 * e.T, 0.1 * np.eye(3)]).reshape(-1)
    free = np.ones(n)
    free[3 * order[0] + 1] = 0.0  # a fixed DoF drops its rows and columns of the blocks
    dev = []
    for host, dtype in ((brow, ti.i32), (bcol, ti.i32), (bval, ti.f64), (free, ti.f64)):
        arr = device_copy.new_ndarray(dtype, (host.size,))
        arr.from_numpy(host)
        dev.append(arr)
    indptr, indices, data = _operator(a)
    key = object()
    assert bands.assemble(indptr, indices, data, (*dev, 4), key)
    assert bands.width == 6 and bands.usable.all()
    full = a.toarray()
    for t in range(3):
        rows, cols = 3 * brow[t] + np.arange(3), 3 * bcol[t] + np.arange(3)
        full[np.ix_(rows, cols)] += free[rows, None] * free[None, cols] * bval[9 * t: 9 * t + 9].reshape(3, 3)
    r = rng.normal(size=n)
    z = np.full(n, 7.0)
    r_dev, z_dev, active = (device_copy.new_ndarray(ti.f64, (n,)), device_copy.new_ndarray(ti.f64, (n,)),
                            device_copy.new_ndarray(ti.i32, (3,)))
    r_dev.from_numpy(r)
    z_dev.from_numpy(z)
    active.from_numpy(np.array([1, 1, 1], np.int32))
    bands.apply(r_dev, z_dev, active)
    got = z_dev.to_numpy()
    for c in range(3):
        d = dofs[c][dofs[c] >= 0]
        want = np.linalg.solve(full[np.ix_(d, d)], r[d])
        np.testing.assert_allclose(got[d], want, rtol=1e-10, atol=1e-12 * np.abs(want).max())
    untouched = np.setdiff1d(np.arange(n), dofs[dofs >= 0])
    np.testing.assert_array_equal(got[untouched], 7.0)
    # an inactive copy's block is left as it was
    active.from_numpy(np.array([1, 0, 1], np.int32))
    z_dev.from_numpy(z)
    bands.apply(r_dev, z_dev, active)
    np.testing.assert_array_equal(z_dev.to_numpy()[dofs[1]], 7.0)


def test_blocks_of_many_panels_are_inverted_exactly_as_their_values_change(ti_cpu):
    """Blocks of several elimination panels and launches and of several tiles (one padded), as two Newton matrices of
    one pattern: the second assembly re-uses the first's band positions; each block applied is NumPy's inverse."""
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels import band_cholesky, device_copy
    from sim_core.ti_kernels.band_cholesky import BandBlocks

    m, w = 3 * band_cholesky.PANEL * band_cholesky.PANELS_PER_LAUNCH - 5, 20
    sizes = (m, m - 9)
    pattern = [sp.csr_matrix(_banded_spd(k, w, 7 + c)) for c, k in enumerate(sizes)]
    a = sp.block_diag(pattern, format="csr")
    a.eliminate_zeros()
    n = a.shape[0]
    dofs = np.full((2, m), -1)
    dofs[0] = np.arange(m)
    dofs[1, :sizes[1]] = m + np.arange(sizes[1])
    bands = BandBlocks(dofs, np.repeat([0, 1], sizes))
    indptr, indices, data = _operator(a)
    key = object()
    rng = np.random.default_rng(5)
    scale = sp.diags(rng.uniform(0.5, 2.0, size=n))
    r_dev, z_dev, active = (device_copy.new_ndarray(ti.f64, (n,)), device_copy.new_ndarray(ti.f64, (n,)),
                            device_copy.new_ndarray(ti.i32, (2,)))
    active.from_numpy(np.ones(2, np.int32))
    for values in (a, (scale @ a @ scale).tocsr()):  # the second, D A D: the same pattern, positive definite
        values.sort_indices()
        assert np.array_equal(values.indices, a.indices) and np.array_equal(values.indptr, a.indptr)
        data.from_numpy(values.data)
        assert bands.assemble(indptr, indices, data, None, key)
        assert bands.width == w and bands.usable.all()
        assert bands.tile * bands.tiles >= m and bands.tile >= w and bands.tiles > 2  # several tiles each way
        inverse = np.empty((n, n))
        for j in range(n):  # the blocks applied to each unit vector: the columns of their inverse
            r_dev.from_numpy(np.eye(1, n, j)[0])
            bands.apply(r_dev, z_dev, active)
            inverse[:, j] = z_dev.to_numpy()
        dense = values.toarray()
        for c, k in enumerate(sizes):
            d = dofs[c, :k]
            want = np.linalg.inv(dense[np.ix_(d, d)])
            np.testing.assert_allclose(inverse[np.ix_(d, d)], want, rtol=0, atol=1e-10 * np.abs(want).max())
    r = rng.normal(size=n)
    r_dev.from_numpy(r)
    bands.apply(r_dev, z_dev, active)
    want = np.linalg.solve(dense, r)  # the blocks are the whole matrix
    np.testing.assert_allclose(z_dev.to_numpy(), want, rtol=0, atol=1e-9 * np.abs(want).max())


def test_float32_tiles_apply_each_block_inverse_to_float32_rounding_times_its_condition(ti_cpu):
    """Tiles stored as float32 (factorised in float64, each tile entry rounded once): the product solves each block
    to about ``2^-24 cond`` (condition ~170 here), not exactly; the same blocks with float64 tiles to ~1e-15."""
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels import band_cholesky, device_copy
    from sim_core.ti_kernels.band_cholesky import BandBlocks

    m, w = 3 * band_cholesky.PANEL * band_cholesky.PANELS_PER_LAUNCH - 5, 20
    sizes = (m, m - 9)
    blocks = [np.pi * _banded_spd(k, w, 7 + c) for c, k in enumerate(sizes)]  # entries not float32's
    a = sp.block_diag([sp.csr_matrix(block) for block in blocks], format="csr")
    a.eliminate_zeros()
    n = a.shape[0]
    dofs = np.full((2, m), -1)
    dofs[0] = np.arange(m)
    dofs[1, :sizes[1]] = m + np.arange(sizes[1])
    r = np.random.default_rng(1).normal(size=n)
    r_dev, z_dev, active = (device_copy.new_ndarray(ti.f64, (n,)), device_copy.new_ndarray(ti.f64, (n,)),
                            device_copy.new_ndarray(ti.i32, (2,)))
    r_dev.from_numpy(r)
    active.from_numpy(np.ones(2, np.int32))
    want = np.linalg.solve(a.toarray(), r)
    cond = max(np.linalg.cond(block) for block in blocks)
    for dtype, bound in ((ti.f64, 1e-13), (ti.f32, 2.0 ** -24 * cond)):
        bands = BandBlocks(dofs, np.repeat([0, 1], sizes), dtype=dtype)
        assert bands.assemble(*_operator(a), None, object()) and bands.usable.all()
        bands.apply(r_dev, z_dev, active)
        z = z_dev.to_numpy()
        error = np.abs(z - want).max() / np.abs(want).max()
        assert error <= bound, (dtype, error, bound)
        assert np.linalg.norm(a @ z - r) <= bound * np.linalg.norm(r)
    assert error > 1e-12  # float32 tiles: rounded


def test_a_block_that_is_not_positive_definite_is_reported_and_left_out(ti_cpu):
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels import device_copy
    from sim_core.ti_kernels.band_cholesky import BandBlocks

    a, dofs, seg, _ = _system(1)
    a = a.tolil()
    for k in dofs[2][dofs[2] >= 0]:
        a[k, k] = -50.0
    a = a.tocsr()
    bands = BandBlocks(dofs, seg)
    assert bands.assemble(*_operator(a), None, object())
    assert list(bands.usable) == [True, True, False]
    n = a.shape[0]
    r_dev, z_dev, active = (device_copy.new_ndarray(ti.f64, (n,)), device_copy.new_ndarray(ti.f64, (n,)),
                            device_copy.new_ndarray(ti.i32, (3,)))
    r_dev.from_numpy(np.ones(n))
    active.from_numpy(np.ones(3, np.int32))
    bands.apply(r_dev, z_dev, active)
    z = z_dev.to_numpy()
    assert np.all(z[dofs[2][dofs[2] >= 0]] == 0.0) and np.all(z[dofs[0]] != 0.0)


def test_a_selection_of_copies_factorises_their_blocks_alone_to_the_bit(ti_cpu):
    """``assemble(..., copies=)`` (a lockstep retry's copies): the selected copies' blocks are applied bit for bit as
    when every block is factorised, the others are not usable (their DoFs left by ``apply``); without a selection
    every block is factorised again. The blocks' values change between the assemblies (a matrix not positive
    definite at the unselected block is never factorised)."""
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels import device_copy
    from sim_core.ti_kernels.band_cholesky import BandBlocks

    a, dofs, seg, _ = _system(4)
    n = a.shape[0]
    bands = BandBlocks(dofs, seg)
    indptr, indices, data = _operator(a)
    key = object()
    r_dev, z_dev, active = (device_copy.new_ndarray(ti.f64, (n,)), device_copy.new_ndarray(ti.f64, (n,)),
                            device_copy.new_ndarray(ti.i32, (3,)))
    r_dev.from_numpy(np.random.default_rng(2).normal(size=n))
    active.from_numpy(np.ones(3, np.int32))

    def applied(copies, values) -> np.ndarray:
        data.from_numpy(values)
        assert bands.assemble(indptr, indices, data, None, key, copies=copies)
        z_dev.from_numpy(np.full(n, 7.0))
        bands.apply(r_dev, z_dev, active)
        return z_dev.to_numpy()

    every = applied(None, a.data)
    assert bands.usable.all()
    broken = a.tolil()
    for k in dofs[1][dofs[1] >= 0]:
        broken[k, k] = -50.0  # copy 1's block indefinite: left out of the selection, never factorised
    broken = broken.tocsr()
    assert np.array_equal(broken.indices, a.indices)
    some = applied(np.array([True, False, True]), broken.data)
    assert list(bands.usable) == [True, False, True]
    for c in (0, 2):
        d = dofs[c][dofs[c] >= 0]
        np.testing.assert_array_equal(some[d], every[d])
    np.testing.assert_array_equal(some[dofs[1]], 7.0)
    np.testing.assert_array_equal(applied(None, a.data), every)
    assert bands.usable.all()


def test_a_band_wider_than_the_limit_is_not_used(ti_cpu):
    from sim_core.ti_kernels.band_cholesky import BandBlocks

    a, dofs, seg, _ = _system(2)
    bands = BandBlocks(dofs, seg, max_width=5)
    assert not bands.assemble(*_operator(a), None, object())
    assert bands.width == 0


@pytest.mark.parametrize("dofs, why", [(np.array([[0, 1, 2], [2, 3, 4]]), "in two blocks"),
                                       (np.array([[0, 1, 40]]), "outside the matrix"),
                                       (np.array([[0, 1, 20]]), "more than one copy")])
def test_blocks_that_overlap_leave_the_matrix_or_span_copies_are_refused(dofs, why):
    from sim_core.ti_kernels.band_cholesky import BandBlocks

    with pytest.raises(ValueError, match=why):
        BandBlocks(dofs, np.repeat(np.arange(2), 18))
