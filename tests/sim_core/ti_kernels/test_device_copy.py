"""Byte copies by address between NumPy arrays and Taichi ndarrays (sim_core/ti_kernels/device_copy.py) equal
Taichi's own ``from_numpy`` / ``to_numpy``, and refuse arrays of another shape or dtype."""

from __future__ import annotations

import threading

import numpy as np
import pytest


@pytest.mark.parametrize("dtype_name", ["f64", "i32", "i64"])
def test_copies_equal_taichis_own(ti_cpu, dtype_name):
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels.device_copy import to_device, to_host

    dtype = {"f64": (ti.f64, np.float64), "i32": (ti.i32, np.int32), "i64": (ti.i64, np.int64)}[dtype_name]
    rng = np.random.default_rng(11)
    for shape in ((7,), (5, 3), (3, 12, 12)):
        dev = ti.ndarray(dtype[0], shape=shape)
        for _ in range(2):
            values = (rng.normal(size=shape) * 1e3).astype(dtype[1])
            assert to_device(dev, values)  # the thread that initialised Taichi can always copy
            assert np.array_equal(dev.to_numpy(), values)
            dev.from_numpy(values[::-1].copy())
            out = np.empty(shape, dtype=dtype[1])
            assert to_host(out, dev) and np.array_equal(out, values[::-1])


def test_copies_refuse_another_shape_or_dtype(ti_cpu):
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels.device_copy import to_device, to_host

    dev = ti.ndarray(ti.f64, shape=(4, 3))
    needed = r"C-contiguous float64 array of shape \(4, 3\) is needed; got float64 \(3, 4\)"
    with pytest.raises(ValueError, match=needed):
        to_device(dev, np.zeros((3, 4)))
    with pytest.raises(ValueError, match=r"got int32 \(4, 3\)"):
        to_host(np.zeros((4, 3), dtype=np.int32), dev)
    with pytest.raises(ValueError, match="C-contiguous"):
        to_host(np.zeros((3, 4)).T, dev)
    read_only = np.zeros((4, 3))
    read_only.flags.writeable = False
    with pytest.raises(ValueError, match="read-only"):
        to_host(read_only, dev)


def test_a_prefix_of_rows_comes_back_and_the_rest_is_left(ti_cpu):
    """``to_host(..., rows=k)`` and ``buffers.copy_back(..., rows=k)`` copy the first ``k`` rows only (a kept
    array of a larger capacity whose launch wrote those); a count outside the array is refused."""
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels.buffers import copy_back
    from sim_core.ti_kernels.device_copy import to_host

    values = np.arange(36, dtype=np.float64).reshape(12, 3)
    dev = ti.ndarray(ti.f64, shape=(12, 3))
    dev.from_numpy(values)
    for copy in (lambda out, k: to_host(out, dev, k), lambda out, k: copy_back(out, dev, k),
                 lambda out, k: copy_back(out, values, k)):
        for k in (0, 5, 12):
            out = np.full((12, 3), -1.0)
            copy(out, k)
            assert np.array_equal(out[:k], values[:k]) and np.all(out[k:] == -1.0)
    with pytest.raises(ValueError, match=r"13 rows asked of an array of shape \(12, 3\)"):
        to_host(np.zeros((12, 3)), dev, 13)


def test_another_thread_copies_or_declines(ti_cpu):
    """From a thread that never launched a kernel the copy is made (CPU) or declined with nothing copied
    (CUDA, where that thread has no current context); the values are right either way."""
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels.device_copy import to_device

    dev = ti.ndarray(ti.f64, shape=(6,))
    dev.fill(-1.0)
    values = np.arange(6.0)
    done = {}
    thread = threading.Thread(target=lambda: done.setdefault("copied", to_device(dev, values)))
    thread.start()
    thread.join()
    assert done["copied"] == (ti_cpu == "cpu")
    assert np.array_equal(dev.to_numpy(), values if done["copied"] else np.full(6, -1.0))


@pytest.mark.parametrize("dtype_name", ["f64", "i32"])
def test_zero_sets_every_entry_to_zero_in_order_with_kernels(ti_cpu, dtype_name):
    """``zero`` clears the whole ndarray, after the kernel launched before it and before the one launched after it
    (the legacy stream's order on CUDA), and ``transfer.fill`` with 0.0 (a memset) equals Taichi's ``fill``."""
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels.device_copy import zero
    from sim_core.ti_kernels.transfer import fill

    dtype = {"f64": ti.f64, "i32": ti.i32}[dtype_name]
    dev = ti.ndarray(dtype, shape=(5, 12, 12))
    dev.fill(3)  # a kernel launch before the memset
    assert zero(dev)
    assert not dev.to_numpy().any()
    dev.fill(7)  # and after it
    assert (dev.to_numpy() == 7).all()
    if dtype_name == "f64":
        want = ti.ndarray(ti.f64, shape=(5, 12, 12))
        for value in (0.0, -0.0, 2.5):
            want.fill(value)
            assert fill(dev, value) is dev
            assert np.array_equal(dev.to_numpy(), want.to_numpy())
        assert not fill(dev, 0.0).to_numpy().tobytes().strip(b"\x00")  # +0.0: every byte 0


def test_pinned_host_arrays_are_zeroed_float64_and_copy_both_ways(ti_cpu):
    """``pinned_zeros``: a zero float64 array of the shape (page-locked on CUDA), writable, that the byte copies
    take both ways with the values kept; made and dropped many times over (its memory given back each time)."""
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels.device_copy import new_ndarray, pinned_zeros, to_device, to_host

    rng = np.random.default_rng(4)
    dev = new_ndarray(ti.f64, (300, 3))
    for _ in range(50):
        host = pinned_zeros((300, 3))
        assert host.shape == (300, 3) and host.dtype == np.float64 and host.flags.writeable
        assert host.flags.c_contiguous and not np.any(host)
        values = rng.normal(size=(300, 3))
        host[:] = values
        assert to_device(dev, host)
        back = pinned_zeros((300, 3))
        assert to_host(back, dev) and np.array_equal(back, values)
    assert pinned_zeros((0, 3)).shape == (0, 3)


def test_pinned_blocks_are_reused_only_once_no_array_over_them_is_left(ti_cpu):
    """``PinnedBlocks`` hands out a writeable array over a block of its own, that the byte copies fill; a block comes
    back for reuse when its array and every view of it are gone, not before; the blocks are ordinary memory on the
    CPU (page-locked on CUDA)."""
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels.device_copy import PinnedBlocks, new_ndarray, to_device, to_host

    assert PinnedBlocks((300, 3)).page_locked == (ti_cpu == "cuda")  # page-locked where a CUDA context is
    blocks = PinnedBlocks((300, 3), page_locked=False)
    rng = np.random.default_rng(5)
    dev = new_ndarray(ti.f64, (300, 3))
    values = rng.normal(size=(300, 3))
    assert to_device(dev, values)
    a = blocks.take()
    assert a.shape == (300, 3) and a.dtype == np.float64 and a.flags.writeable and a.flags.c_contiguous
    assert to_host(a, dev) and np.array_equal(a, values)
    view = a[10:20]
    b = blocks.take()
    assert blocks.allocated == 2 and not np.shares_memory(a, b)
    del a
    c = blocks.take()  # a's block is held by its view
    assert blocks.allocated == 3 and np.array_equal(view, values[10:20])
    address = view.__array_interface__["data"][0] - 10 * 3 * 8
    del view
    d = blocks.take()  # now a's block comes back
    assert blocks.allocated == 3 and d.__array_interface__["data"][0] == address
    for _ in range(20):  # b, c and d held: one more block, taken and dropped over again
        blocks.take()
    assert blocks.allocated == 4 and not np.shares_memory(b, c) and not np.shares_memory(c, d)


def test_rows_on_device_keeps_one_array_of_the_owners_capacity(ti_cpu, monkeypatch):
    """``buffers.rows_on_device`` (the CUDA branch, run on the CPU arch): the first rows of a kept ndarray hold the
    host array; the same object again is neither copied nor reallocated, another object of no more rows is copied into
    the same ndarray (the rows after it left as they are), a longer one gets a new ndarray of twice the rows at least;
    ``refresh`` copies an array edited in place; ``to_device`` with ``rows`` copies that prefix only."""
    import sim_core.ti_backend as backend
    from sim_core.ti_kernels import buffers, device_copy

    monkeypatch.setattr(backend, "current_arch", lambda: "cuda")
    kept: dict = {}
    first = np.arange(40, dtype=np.int32).reshape(10, 4)
    dev = buffers.rows_on_device(kept, "v", first)
    assert tuple(dev.shape) == (16, 4) and np.array_equal(dev.to_numpy()[:10], first)
    copies = []
    monkeypatch.setattr(device_copy, "_copy", lambda *a, _copy=device_copy._copy: (copies.append(a[3]), _copy(*a))[1])
    assert buffers.rows_on_device(kept, "v", first) is dev and copies == []
    second = -np.arange(12, dtype=np.int32).reshape(3, 4)
    assert buffers.rows_on_device(kept, "v", second) is dev and copies == [3]
    assert np.array_equal(dev.to_numpy()[:3], second) and np.array_equal(dev.to_numpy()[3:10], first[3:])
    second[0, 0] = 99
    assert buffers.rows_on_device(kept, "v", second, refresh=True) is dev and dev.to_numpy()[0, 0] == 99
    longer = np.ones((20, 4), dtype=np.int32)
    grown = buffers.rows_on_device(kept, "v", longer)
    assert grown is not dev and tuple(grown.shape) == (32, 4) and np.array_equal(grown.to_numpy()[:20], longer)
    assert buffers.rows_on_device(kept, "w", np.zeros((0, 3))).shape == (16, 3)
    monkeypatch.setattr(backend, "current_arch", lambda: "cpu")
    other: dict = {}
    assert buffers.rows_on_device(other, "v", first) is first and other == {}


def test_unheld_rows_hands_out_only_arrays_nothing_else_holds(ti_cpu):
    """``buffers.unheld_rows``: an array comes back only once nothing but the kept list holds it (a caller's reference
    or a ``DeviceRows`` keeps it out), with at least the rows asked for and the tail asked for; one too short is
    replaced, and past ``spares`` held arrays a new one is made outside the list."""
    from sim_core.ti_kernels.buffers import DeviceRows, unheld_rows

    kept: dict = {}
    first = unheld_rows(kept, "h", 100, (12,), spares=2)
    assert first.shape[0] >= 100 and tuple(first.shape[1:]) == (12,)
    rows, first_id, first_rows = DeviceRows(first, 0, 100), id(first), first.shape[0]
    del first
    second = unheld_rows(kept, "h", 100, (12,), spares=2)
    assert id(second) != first_id
    third = unheld_rows(kept, "h", 10, (12,), spares=2)  # both held: a new one, not kept
    assert id(third) not in (first_id, id(second)) and len(kept["h"]) == 2
    del rows, third
    assert id(unheld_rows(kept, "h", 50, (12,), spares=2)) == first_id  # the DeviceRows gone: free again
    second_id = id(second)
    del second
    assert {id(unheld_rows(kept, "h", 100, (12,), spares=2)) for _ in range(2)} <= {first_id, second_id}
    longer = unheld_rows(kept, "h", 10 * first_rows, (12,), spares=2)  # both free, both short: one replaced
    assert longer.shape[0] >= 10 * first_rows and any(a is longer for a in kept["h"]) and len(kept["h"]) == 2
    del longer
    assert unheld_rows(kept, "h", 10, (12, 12), spares=2).shape[1:] == (12, 12)  # another tail: not a (12,) array
