"""The hash search's pairs sorted on the device (``hash_grid.sorted_on_device``, the CUDA path of ``HashGrid.pairs``)
equal the host's sort (``sorted_pairs_and_keys``) exactly, from NumPy rows (the CPU arch) or a Taichi ndarray (device
memory under ``THINSHELL_TEST_ARCH=cuda``); and hash searches through that path give the k-d tree reference's pairs."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.collision import candidates
from tests.sim_core.ti_kernels.conftest import TEST_ARCH
from tests.sim_core.ti_kernels.test_broad_phase import _boxes, _sorted


def _rows(seed: int, count: int, first_count: int) -> np.ndarray:
    """Distinct int32 rows ``[first, second]`` in no order: short runs of many firsts, one long run, firsts unused."""
    rng = np.random.default_rng(seed)
    rows = np.stack([rng.integers(0, first_count // 2, count), rng.integers(0, 1 << 31, count)], axis=1)
    rows[:300, 0] = first_count - 1  # one first with hundreds of partners
    rows = np.unique(rows.astype(np.int32), axis=0)
    return rows[rng.permutation(len(rows))]


def _ndarray(rows: np.ndarray):
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels.device_copy import new_ndarray

    array = new_ndarray(ti.i32, rows.shape)
    array.from_numpy(rows)
    return array


@pytest.mark.parametrize("on_device", [False, True])
@pytest.mark.parametrize("seed, count, first_count", [(0, 3000, 1000), (1, 5000, 40), (2, 1, 3)])
def test_the_device_sort_equals_the_hosts(ti_cpu, on_device, seed, count, first_count):
    """Pairs (int64 ``(p, 2)``) and keys (int64 ``(p,)``, increasing) equal ``sorted_pairs_and_keys`` of the first
    ``found`` rows bit for bit, the rows after them ignored, the kernel's work arrays kept and grown in the cache;
    no rows give empty arrays."""
    from sim_core.ti_kernels.hash_grid import sorted_on_device, sorted_pairs_and_keys

    rows = _rows(seed, count, first_count)
    found = len(rows) - min(len(rows) - 1, 5)
    out = np.concatenate([rows, np.full((7, 2), -5, dtype=np.int32)])  # capacity past the rows found
    cache: dict = {}
    want_pairs, want_keys = sorted_pairs_and_keys(rows[:found])
    for given in (out, out[:found + 2]):  # a second sort with the same (kept) work arrays
        pairs, keys, device_keys = sorted_on_device(_ndarray(given) if on_device else given, found, first_count,
                                                    cache)
        assert pairs.dtype == keys.dtype == np.int64
        np.testing.assert_array_equal(pairs, want_pairs)
        np.testing.assert_array_equal(keys, want_keys)
        np.testing.assert_array_equal(np.asarray(device_keys if isinstance(device_keys, np.ndarray)
                                                 else device_keys.to_numpy())[:found], want_keys)
    assert np.all(np.diff(keys) > 0)
    pairs, keys, _ = sorted_on_device(_ndarray(out) if on_device else out, 0, first_count, cache)
    assert pairs.shape == (0, 2) and keys.shape == (0,)


def test_hash_searches_sorted_on_the_device_give_the_reference_pairs(ti_cpu, monkeypatch):
    """Random boxes within one set and between two: ``HashSearch`` on its CUDA path (on the CPU arch the arch queries
    answer "cuda", the loops stay serial; a GPU under ``THINSHELL_TEST_ARCH=cuda``) sorts its pairs on the device,
    launched with device arrays only, and returns the k-d tree reference's pairs with their keys."""
    from sim_core.ti_kernels import hash_grid
    from sim_core.ti_kernels.hash_grid import HashSearch

    if TEST_ARCH == "cpu":
        import sim_core.ti_backend

        for module in (hash_grid, sim_core.ti_backend):
            monkeypatch.setattr(module, "current_arch", lambda: "cuda")
    launches = []
    kernel = hash_grid._sort_pairs
    monkeypatch.setattr(hash_grid, "_sort_pairs", lambda *a: (launches.append(a), kernel(*a))[1])
    rng = np.random.default_rng(7)
    bodies = 3
    allowed = rng.random((bodies, bodies)) < 0.7
    allowed |= allowed.T
    a_lo, a_hi = _boxes(rng, 400, 1.0, 0.12)
    b_lo, b_hi = _boxes(rng, 300, 1.0, 0.1)
    a_body, b_body = rng.integers(0, bodies, 400), rng.integers(0, bodies, 300)
    search = HashSearch()
    for args in ((a_lo, a_hi, a_body, None, None, None), (a_lo, a_lo, a_body, b_lo, b_hi, b_body)):
        ref = _sorted(candidates._grouped_box_pairs(*args, 0.05, allowed))
        assert len(ref) > 100
        pairs = search(*args, 0.05, allowed)
        np.testing.assert_array_equal(pairs, ref)
        grid = search.grids[args[3] is None]
        np.testing.assert_array_equal(grid.keys_of(pairs), (ref[:, 0] << 32) | ref[:, 1])
    assert len(launches) == 2 and not any(isinstance(a, np.ndarray) for args in launches for a in args)
