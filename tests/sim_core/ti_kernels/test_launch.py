"""Cached launch plans (sim_core/ti_kernels/launch.py) give the results of Taichi's own calls."""

# No ``from __future__ import annotations``: Taichi reads kernel annotations as objects.

import numpy as np
import pytest

from sim_core.ti_backend import ti
from tests.sim_core.ti_kernels.conftest import TEST_ARCH, assert_same_sums

_F64_1 = ti.types.ndarray(dtype=ti.f64, ndim=1)
_F64_2 = ti.types.ndarray(dtype=ti.f64, ndim=2)
_I32_1 = ti.types.ndarray(dtype=ti.i32, ndim=1)


def _kernels():
    from sim_core.ti_kernels.launch import fast_kernel

    @fast_kernel
    def weighted_sum(x: _F64_2, w: _F64_1, idx: _I32_1, scale: ti.f64, shift: ti.i32, negate: ti.template(),
                     out: _F64_1) -> ti.f64:
        total = 0.0
        ti.loop_config(serialize=True)
        for k in range(idx.shape[0]):
            v = scale * w[k] * x[idx[k] + shift, 1]
            if ti.static(negate):
                v = -v
            out[k] += v
            total += v
        return total

    @fast_kernel
    def count_positive(x: _F64_1) -> ti.i32:
        n = 0
        ti.loop_config(serialize=True)
        for k in range(x.shape[0]):
            if x[k] > 0:
                n += 1
        return n

    return weighted_sum, count_positive


def _reference(x, w, idx, scale, shift, negate):
    v = scale * w * x[idx + shift, 1]
    return -v if negate else v


def test_repeated_calls_equal_the_numpy_reference(ti_cpu):
    weighted_sum, count_positive = _kernels()
    rng = np.random.default_rng(0)
    for call in range(4):  # the first call of a signature goes through Taichi, later ones through the plan
        for negate in (False, True):
            n = 5 + 3 * call
            x = rng.normal(size=(n + 2, 3))
            w = rng.normal(size=n)
            idx = rng.integers(0, n, size=n).astype(np.int32)
            out = np.ones(n)
            total = weighted_sum(x, w, idx, 1.5, 2, negate, out)
            expected = _reference(x, w, idx, 1.5, 2, negate)
            np.testing.assert_allclose(out, 1.0 + expected, rtol=0, atol=1e-14)
            assert total == pytest.approx(float(np.sum(expected)), rel=1e-13, abs=1e-14)
            assert count_positive(x[:, 0].copy()) == int(np.sum(x[:, 0] > 0))
    assert len(weighted_sum._plans) == 2  # one plan per template value
    assert all(plan is not None for plan in weighted_sum._plans.values())


def test_arrays_that_are_not_c_contiguous_take_taichis_path(ti_cpu):
    weighted_sum, _ = _kernels()
    rng = np.random.default_rng(1)
    x = np.asfortranarray(rng.normal(size=(8, 3)))
    w, idx = rng.normal(size=4), np.arange(4, dtype=np.int32)
    for _ in range(2):
        out = np.zeros(4)
        weighted_sum(x, w, idx, 2.0, 1, False, out)
        np.testing.assert_allclose(out, _reference(x, w, idx, 2.0, 1, False), rtol=0, atol=1e-14)
    assert not weighted_sum._plans  # no plan for a Fortran-ordered array


def test_a_wrong_dtype_is_rejected_by_taichi_every_time(ti_cpu):
    _, count_positive = _kernels()
    count_positive(np.ones(3))
    for _ in range(2):
        with pytest.raises(Exception):
            count_positive(np.ones(3, dtype=np.float32))


def test_plain_functions_are_refused():
    from sim_core.ti_kernels.launch import FastKernel

    with pytest.raises(TypeError, match="not a plain @ti.kernel"):
        FastKernel(lambda x: x)


def test_a_reused_launch_context_sees_each_calls_arrays(ti_cpu):
    """On the CPU a plan keeps its launch context and rebinds only the array slots whose argument
    is another array object: the same objects modified in place, one argument swapped for another
    array and back, and arrays of another length all give the NumPy reference."""
    weighted_sum, count_positive = _kernels()
    rng = np.random.default_rng(2)
    x = rng.normal(size=(12, 3))
    w = rng.normal(size=6)
    idx = rng.integers(0, 8, size=6).astype(np.int32)
    for call in range(3):
        x[:] = rng.normal(size=x.shape)  # same objects, new contents
        w[:] = rng.normal(size=w.shape)
        out = np.zeros(6)
        total = weighted_sum(x, w, idx, 0.5 + call, 1, False, out)
        expected = _reference(x, w, idx, 0.5 + call, 1, False)
        np.testing.assert_allclose(out, expected, rtol=0, atol=1e-14)
        assert total == pytest.approx(float(np.sum(expected)), rel=1e-13, abs=1e-14)
    plan = next(p for p in weighted_sum._plans.values())
    # the context is kept on the CPU only (on CUDA each launch gets a new one: launch._Plan)
    assert plan.compiled is not None and (plan.ctx is not None) == (ti_cpu == "cpu")
    # another index array while x and w stay bound, then the first one again
    idx2 = rng.integers(0, 8, size=6).astype(np.int32)
    for ids in (idx2, idx, idx2):
        out = np.zeros(6)
        weighted_sum(x, w, ids, 2.0, 3, False, out)
        np.testing.assert_allclose(out, _reference(x, w, ids, 2.0, 3, False), rtol=0, atol=1e-14)
    # a shorter vector of the same dtype through the same plan
    v = rng.normal(size=9)
    for n in (9, 4, 9):
        assert count_positive(v[:n].copy()) == int(np.sum(v[:n] > 0))


def test_calls_from_another_thread_get_their_own_context(ti_cpu):
    """A plan's reused context belongs to the thread that made it; another thread's calls bind a
    fresh context (same results) and leave the owner's bindings as they were."""
    import threading

    weighted_sum, _ = _kernels()
    rng = np.random.default_rng(3)
    x, w, idx = rng.normal(size=(10, 3)), rng.normal(size=5), np.arange(5, dtype=np.int32)
    for _ in range(2):
        weighted_sum(x, w, idx, 1.0, 0, False, np.zeros(5))
    plan = next(p for p in weighted_sum._plans.values())
    bound = [b if b is None else b[0] for b in plan.bound]
    results = {}

    def other():
        x2, w2 = rng.normal(size=(10, 3)), rng.normal(size=5)
        out = np.zeros(5)
        weighted_sum(x2, w2, idx, 1.0, 2, False, out)
        results["other"] = (out, _reference(x2, w2, idx, 1.0, 2, False))

    t = threading.Thread(target=other)
    t.start()
    t.join()
    np.testing.assert_allclose(results["other"][0], results["other"][1], rtol=0, atol=1e-14)
    assert [b if b is None else b[0] for b in plan.bound] == bound
    out = np.zeros(5)
    weighted_sum(x, w, idx, 1.0, 0, False, out)
    np.testing.assert_allclose(out, _reference(x, w, idx, 1.0, 0, False), rtol=0, atol=1e-14)


def test_repeated_scalars_and_arrays_changed_in_place(ti_cpu):
    """A plan sets a scalar again only when it changed (a zero float always: its sign matters), and
    an array whose dtype was changed in place is checked again (Taichi's path rejects it)."""
    weighted_sum, count_positive = _kernels()
    rng = np.random.default_rng(4)
    x, w, idx = rng.normal(size=(10, 3)), rng.normal(size=5), np.arange(5, dtype=np.int32)
    for scale in (1.5, 1.5, -0.0, 0.0, -0.0, 2.5, 2.5):
        out = np.full(5, -0.0)  # -0.0 + v keeps the sign of a zero v
        weighted_sum(x, w, idx, scale, 1, False, out)
        expected = np.full(5, -0.0) + _reference(x, w, idx, scale, 1, False)
        np.testing.assert_array_equal(out, expected)
        np.testing.assert_array_equal(np.signbit(out), np.signbit(expected))
    for shift in (0, 0, 2, 0):
        out = np.zeros(5)
        weighted_sum(x, w, idx, 1.0, shift, False, out)
        np.testing.assert_array_equal(out, _reference(x, w, idx, 1.0, shift, False))
    v = rng.normal(size=6)
    for _ in range(3):
        assert count_positive(v) == int(np.sum(v > 0))
    v.dtype = np.int64  # same object and shape, another dtype
    with pytest.raises(Exception):
        count_positive(v)


def test_data_pointer_is_the_arrays_address():
    from sim_core.ti_kernels.launch import _data_pointer

    a = np.arange(24.0).reshape(4, 6)
    read_only = a.copy()
    read_only.flags.writeable = False
    for v in (a, a[1:], a[:0], read_only, np.zeros(0, dtype=np.int32)):
        assert _data_pointer(v) == v.ctypes.data


def test_read_only_and_offset_arrays_are_bound_at_their_address(ti_cpu):
    weighted_sum, _ = _kernels()
    rng = np.random.default_rng(5)
    x, w, idx = rng.normal(size=(12, 3)), rng.normal(size=8), np.arange(5, dtype=np.int32)
    x.flags.writeable = False
    for w_view in (w[3:], w[1:6], w[3:]):  # views with an offset, C-contiguous
        out = np.zeros(5)
        weighted_sum(x, w_view, idx, 1.0, 0, False, out)
        np.testing.assert_array_equal(out, _reference(x, w_view, idx, 1.0, 0, False))


def test_summing_kernel_returns_the_in_order_sum_of_its_loop(ti_cpu):
    """A ``summing_kernel`` returns what its loop added into ``energy[0]``: the sum of the terms in loop order
    (bit for bit on the CPU; on CUDA the compiler fuses multiply-adds: ``assert_same_sums``), the same as the
    returned scalar of the same loop; the kept array is zeroed by the kernel, so a second call does not add to
    the first's sum."""
    from sim_core.ti_kernels.launch import fast_kernel, summing_kernel

    def squares(x: _F64_1, w: _F64_1, energy: _F64_1):
        energy[0] = 0.0
        ti.loop_config(serialize=True)
        for k in range(x.shape[0]):
            energy[0] += w[k] * x[k] * x[k]

    @fast_kernel
    def squares_returned(x: _F64_1, w: _F64_1) -> ti.f64:
        total = 0.0
        ti.loop_config(serialize=True)
        for k in range(x.shape[0]):
            total += w[k] * x[k] * x[k]
        return total

    summed = summing_kernel(squares)
    rng = np.random.default_rng(3)
    for n in (1, 7, 1000):
        x, w = rng.normal(size=n), rng.uniform(0.5, 2.0, size=n)
        in_order = 0.0
        for k in range(n):
            in_order += w[k] * x[k] * x[k]
        for _ in range(2):
            total = summed(x, w)
            assert isinstance(total, float)
            assert_same_sums(total, in_order, rel=1e-14)  # serial loops; on CUDA with fused multiply-adds
            assert_same_sums(total, squares_returned(x, w), rel=1e-14)


def test_planned_launches_bind_taichi_ndarrays(ti_cpu):
    """Taichi ndarray arguments go through the kept plans too (bound again at every launch): repeated
    calls, another ndarray object in the same slot and a NumPy array in place of an ndarray (another
    signature) all give Taichi's own results."""
    from sim_core.ti_kernels.launch import fast_kernel

    @fast_kernel
    def axpy(a: ti.f64, x: _F64_1, y: _F64_1):
        for k in range(x.shape[0]):
            y[k] = a * x[k] + y[k]

    rng = np.random.default_rng(5)
    x_host = rng.normal(size=11)
    x_dev, y_dev, y_other = (ti.ndarray(ti.f64, shape=(11,)) for _ in range(3))
    x_dev.from_numpy(x_host)
    y_dev.fill(1.0)
    y_other.fill(-2.0)
    expected_dev, expected_other = np.ones(11), np.full(11, -2.0)
    for call in range(4):
        a = 0.5 + call
        axpy(a, x_dev, y_dev)
        expected_dev = a * x_host + expected_dev
        np.testing.assert_allclose(y_dev.to_numpy(), expected_dev, rtol=0, atol=1e-13)
        axpy(a, x_host, y_other)  # a NumPy array where an ndarray was: another plan
        expected_other = a * x_host + expected_other
        np.testing.assert_allclose(y_other.to_numpy(), expected_other, rtol=0, atol=1e-13)
    assert len([p for p in axpy._plans.values() if p is not None]) == 2


def test_deferred_sums_are_the_plain_calls_sums_in_launch_order(ti_cpu):
    """In a ``DeferredSums`` block a ``summing_kernel`` launch returns NaN without waiting for its sum, each launch
    into a cell of its own (two launches of one kernel do not share one), and ``values()`` after the block gives
    the plain calls' sums in launch order; the cells are reused by the next block; a block inside a block is
    refused."""
    from sim_core.ti_kernels.launch import DeferredSums, summing_kernel

    def squares(x: _F64_1, w: _F64_1, energy: _F64_1):
        energy[0] = 0.0
        ti.loop_config(serialize=True)
        for k in range(x.shape[0]):
            energy[0] += w[k] * x[k] * x[k]

    def cubes(x: _F64_1, energy: _F64_1):
        energy[0] = 0.0
        ti.loop_config(serialize=True)
        for k in range(x.shape[0]):
            energy[0] += x[k] * x[k] * x[k]

    summed, cubed = summing_kernel(squares), summing_kernel(cubes)
    rng = np.random.default_rng(8)
    sums = DeferredSums()
    for n in (5, 300):
        x, y, w = rng.normal(size=n), rng.normal(size=n), rng.uniform(0.5, 2.0, size=n)
        plain = [summed(x, w), cubed(x), summed(y, w)]
        with sums:
            returned = [summed(x, w), cubed(x), summed(y, w)]
            assert sums.launches == 3
            with pytest.raises(RuntimeError, match="already active"):
                DeferredSums().__enter__()
        assert all(np.isnan(r) for r in returned)
        assert sums.values() == plain
        assert summed(x, w) == plain[0]  # outside a block: the plain call again


def test_summing_kernel_cells_spread_the_sum_and_are_zeroed_before_each_launch(ti_cpu):
    """A kernel that adds element ``k`` at cell ``k % cells`` and does not zero its cells returns the sum of its
    terms, again at a second call and inside a ``DeferredSums`` block after another kernel used the same cells
    (one cell in loop order on the CPU: bit for bit; ``SUM_CELLS`` cells on a GPU)."""
    from sim_core.ti_backend import serial_loops
    from sim_core.ti_kernels.launch import DeferredSums, summing_kernel

    def spread(x: _F64_1, energy: _F64_1):
        ti.loop_config(serialize=ti.static(serial_loops()))  # serial on the CPU, parallel on a GPU
        for k in range(x.shape[0]):
            energy[k % energy.shape[0]] += x[k] * x[k]

    summed = summing_kernel(spread)
    rng = np.random.default_rng(9)
    sums = DeferredSums()
    for n in (3, 5000):
        x, y = rng.normal(size=n), rng.normal(size=n)
        in_order = 0.0
        for k in range(n):
            in_order += x[k] * x[k]
        assert_same_sums(summed(x), in_order, rel=1e-14)
        assert_same_sums(summed(x), in_order, rel=1e-14)  # the cells zeroed again, not added to
        with sums:
            summed(y)
            summed(x)
        assert_same_sums(sums.values()[1], in_order, rel=1e-14)
        with sums:  # the block's cells again, zeroed
            summed(x)
        assert_same_sums(sums.values()[0], in_order, rel=1e-14)


def test_shared_deferred_sums_read_one_sum_array_once(ti_cpu, monkeypatch):
    """``DeferredSums(shared=True)``: where the sum arrays have several cells (a GPU's; here host arrays of 4 cells),
    every launch of a block adds into one array, zeroed once, and ``total()`` is the plain calls' sum (to round-off:
    the terms in another order) read in one copy; ``values()`` is refused then. With one cell (the CPU's) each launch
    keeps its own cell: ``values()`` are the plain calls' sums and ``total()`` their sum in launch order."""
    from sim_core.ti_kernels import launch
    from sim_core.ti_kernels.launch import DeferredSums, summing_kernel

    def squares(x: _F64_1, w: _F64_1, energy: _F64_1):
        ti.loop_config(serialize=True)
        for k in range(x.shape[0]):
            energy[k % energy.shape[0]] += w[k] * x[k] * x[k]

    summed = summing_kernel(squares)
    rng = np.random.default_rng(9)
    x, y, w = rng.normal(size=50), rng.normal(size=50), rng.uniform(0.5, 2.0, size=50)
    plain = [summed(x, w), summed(y, w), summed(x, w)]
    if TEST_ARCH == "cpu":  # the CPU's one-cell arrays: not shared
        alone = DeferredSums(shared=True)
        with alone:
            summed(x, w)
            summed(y, w)
            summed(x, w)
        assert not alone.sharing and alone.values() == plain and alone.total() == (plain[0] + plain[1]) + plain[2]
    monkeypatch.setattr(launch, "_new_cells", lambda runtime: np.zeros(4))
    reads = []
    cells_sum = launch._cells_sum
    monkeypatch.setattr(launch, "_cells_sum", lambda array: (reads.append(array), cells_sum(array))[1])
    shared = DeferredSums(shared=True)
    for _ in range(2):  # the array zeroed again by the next block
        with shared:
            returned = [summed(x, w), summed(y, w), summed(x, w)]
        assert shared.sharing and shared.launches == 3 and all(np.isnan(r) for r in returned)
        reads.clear()
        assert shared.total() == pytest.approx(sum(plain), rel=1e-13, abs=0.0)
        assert len(reads) == 1
        with pytest.raises(RuntimeError, match="total"):
            shared.values()
    separate = DeferredSums()
    with separate:
        summed(x, w)
        summed(y, w)
    assert not separate.sharing and separate.values() == pytest.approx(plain[:2], rel=1e-13, abs=0.0)


@pytest.mark.parametrize("cells", [1, 4])  # the CPU's one cell a launch; a GPU's shared sum array (host cells here)
def test_deferred_sums_sum_of_items_read_now_or_later(ti_cpu, monkeypatch, cells):
    """``DeferredSums.sum_of``: ``start`` plus each item's sum (a summing kernel's, or the value of an item that
    launched none) in one block; with ``read`` False a callable that reads the same sum later, with no read before
    it is called; an item launching two summing kernels is refused."""
    from sim_core.ti_kernels import launch
    from sim_core.ti_kernels.launch import DeferredSums, summing_kernel

    def squares(x: _F64_1, energy: _F64_1):
        ti.loop_config(serialize=True)
        for k in range(x.shape[0]):
            energy[k % energy.shape[0]] += x[k] * x[k]

    summed = summing_kernel(squares)
    rng = np.random.default_rng(12)
    xs = [rng.normal(size=40), None, rng.normal(size=7)]  # the middle item launches nothing: its value 2.5
    plain = [summed(xs[0]), 2.5, summed(xs[2])]
    if cells > 1:
        monkeypatch.setattr(launch, "_new_cells", lambda runtime: np.zeros(cells))
    reads = []
    cells_sum = launch._cells_sum
    monkeypatch.setattr(launch, "_cells_sum", lambda array: (reads.append(array), cells_sum(array))[1])
    sums = DeferredSums(shared=True)

    def run(x):
        return 2.5 if x is None else summed(x)

    now = sums.sum_of(xs, run, 1.0)
    assert now == pytest.approx(1.0 + sum(plain), rel=1e-13, abs=0.0)
    reads.clear()
    later = sums.sum_of(xs, run, 1.0, read=False)
    assert callable(later) and not reads
    assert later() == now and reads
    with pytest.raises(RuntimeError, match="launched 2 summing kernels"):
        sums.sum_of([xs[0]], lambda x: summed(x) + summed(x))
