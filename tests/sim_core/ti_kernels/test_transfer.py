"""Copies and fills of float64 Taichi ndarrays through kept launch plans (sim_core/ti_kernels/transfer.py)
equal Taichi's own ``from_numpy`` / ``to_numpy`` / ``fill``."""

from __future__ import annotations

import numpy as np
import pytest


def test_upload_download_and_fill_equal_taichis_own_copies(ti_cpu):
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels.transfer import download, fill, upload

    rng = np.random.default_rng(7)
    for shape in ((9,), (6, 3), (4, 12, 12)):
        dev = ti.ndarray(ti.f64, shape=shape)
        out = np.empty(shape)
        for call in range(3):  # the first call of a rank goes through Taichi, later ones through the plan
            values = rng.normal(size=shape)
            assert upload(dev, values) is dev
            assert np.array_equal(dev.to_numpy(), values)
            assert np.array_equal(download(dev), values)
            assert download(dev, out) is out and np.array_equal(out, values)
            fill(dev, float(call) - 0.25)
            assert np.array_equal(dev.to_numpy(), np.full(shape, float(call) - 0.25))
    dev = ti.ndarray(ti.f64, shape=(5, 3))
    upload(dev, np.arange(15, dtype=np.int64).reshape(5, 3))  # converted to float64
    assert np.array_equal(download(dev), np.arange(15.0).reshape(5, 3))


def test_transfers_refuse_arrays_of_another_shape(ti_cpu):
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels.transfer import download, upload

    dev = ti.ndarray(ti.f64, shape=(5, 3))
    with pytest.raises(ValueError, match=r"upload: values of shape \(3, 5\) for an ndarray of shape \(5, 3\)"):
        upload(dev, np.zeros((3, 5)))
    with pytest.raises(ValueError, match=r"download: out must be C-contiguous float64 of shape \(5, 3\)"):
        download(dev, np.zeros((5, 3), dtype=np.float32))
    with pytest.raises(ValueError, match="download: out must be C-contiguous"):
        download(dev, np.zeros((3, 5)).T)


def test_on_device_with_changed_copies_only_new_contents(ti_cpu, monkeypatch):
    """``buffers.on_device(..., refresh=True, changed=True)`` (the CUDA path's inputs, run here with the arch query
    answering "cuda"): the host array is copied to its device array at the first call and whenever its contents
    changed in place, and not when they are the last copy's (a device value written meanwhile stays)."""
    import sim_core.ti_backend as backend
    from sim_core.ti_kernels.buffers import on_device

    monkeypatch.setattr(backend, "current_arch", lambda: "cuda")
    kept: dict = {}
    host = np.arange(6, dtype=np.int32)
    dev = on_device(kept, "rows", host, refresh=True, changed=True)
    assert np.array_equal(dev.to_numpy(), host)
    dev[0] = 99  # a device write the host does not know of: a call with unchanged contents leaves it
    assert on_device(kept, "rows", host, refresh=True, changed=True) is dev and dev[0] == 99
    host[2] = -4  # contents changed in place: copied again
    assert on_device(kept, "rows", host, refresh=True, changed=True) is dev
    assert np.array_equal(dev.to_numpy(), host)
    dev[0] = 99  # without ``changed`` every call copies
    on_device(kept, "rows", host, refresh=True)
    assert dev[0] == host[0]


def test_add_into_adds_an_ndarray_or_a_numpy_array_entry_by_entry(ti_cpu):
    """``add_into`` is ``array + values`` bit for bit (one addition an entry), from an ndarray or a NumPy array; it
    refuses another shape or rank."""
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels.transfer import add_into, download, upload

    rng = np.random.default_rng(8)
    for shape in ((7, 3), (4, 12)):
        base, first, second = (rng.normal(size=shape) for _ in range(3))
        dev = upload(ti.ndarray(ti.f64, shape=shape), base)
        assert add_into(dev, upload(ti.ndarray(ti.f64, shape=shape), first)) is dev
        add_into(dev, second)
        assert np.array_equal(download(dev), (base + first) + second)
    with pytest.raises(ValueError, match=r"add_into: values of shape \(3, 7\) for an ndarray of shape \(7, 3\)"):
        add_into(ti.ndarray(ti.f64, shape=(7, 3)), np.zeros((3, 7)))
    with pytest.raises(ValueError, match=r"add_into: an ndarray of rank 2 is needed; got shape \(21,\)"):
        add_into(ti.ndarray(ti.f64, shape=(21,)), np.zeros(21))
