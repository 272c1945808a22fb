"""``sim_core.unique.sorted_unique`` and ``compact_indices`` return exactly ``np.unique``'s results."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.unique import sorted_unique


def _arrays(rng):
    yield np.zeros(0, dtype=np.int64)
    yield np.array([5], dtype=np.int64)
    yield rng.integers(-3, 4, size=200)  # many repeats, negative values (the -1 of unkept keys)
    yield rng.integers(0, 2**40, size=3000)  # mostly distinct
    yield np.where(rng.uniform(size=5000) < 0.8, -1, rng.integers(0, 3_000_000, size=5000))
    yield rng.normal(size=100).round(1)
    rows = rng.integers(0, 4, size=(300, 4)).astype(np.int64)  # element rows compared as bytes
    yield rows.view(np.dtype((np.void, 32))).reshape(-1)


@pytest.mark.parametrize("return_index, return_inverse", [(False, False), (True, False), (False, True), (True, True)])
def test_sorted_unique_equals_numpy_unique(return_index, return_inverse):
    rng = np.random.default_rng(4)
    for values in _arrays(rng):
        got = sorted_unique(values, return_index=return_index, return_inverse=return_inverse)
        ref = np.unique(values, return_index=return_index, return_inverse=return_inverse)
        if not (return_index or return_inverse):
            got, ref = (got,), (ref,)
        assert len(got) == len(ref)
        for a, b in zip(got, ref):
            assert a.dtype == b.dtype or a.dtype.kind == b.dtype.kind == "i"
            np.testing.assert_array_equal(a, b)
        if return_inverse:
            np.testing.assert_array_equal(got[0][got[-1]], values)


def test_sorted_unique_rejects_arrays_that_are_not_one_dimensional():
    with pytest.raises(ValueError, match="must be 1-D, got shape \\(2, 3\\)"):
        sorted_unique(np.zeros((2, 3)))


def test_compact_indices_are_np_unique_with_the_inverse_in_the_input_shape():
    """Pairs of four vertex indices (repeats, gaps): the distinct indices and each one's position among them are
    ``np.unique``'s; an empty set gives empty arrays of the input's shape; a negative index is refused."""
    from sim_core.unique import compact_indices

    rng = np.random.default_rng(4)
    pairs = rng.integers(3, 5000, size=(700, 4))
    own, local = compact_indices(pairs)
    expected, inverse = np.unique(pairs, return_inverse=True)
    np.testing.assert_array_equal(own, expected)
    np.testing.assert_array_equal(local, inverse.reshape(pairs.shape))
    np.testing.assert_array_equal(own[local], pairs)
    own32, local32 = compact_indices(pairs.astype(np.int32), dtype=np.int32)  # a kernel's indices: int32 positions
    assert local32.dtype == np.int32 and local32.flags.c_contiguous
    np.testing.assert_array_equal(own32, expected)
    np.testing.assert_array_equal(local32, local)
    none = compact_indices(np.zeros((0, 4), dtype=np.int32))
    assert none[0].shape == (0,) and none[1].shape == (0, 4)
    with pytest.raises(ValueError, match="must be >= 0"):
        compact_indices(np.array([[0, -1]]))


def test_compact_indices_of_parts_equal_those_of_their_concatenation():
    """A tuple of index arrays (int64, int32, an empty part, the largest index in the second) gives what their
    concatenation gives, bit for bit and in the same dtypes, also with a bound ``size`` given; parts of unequal
    trailing shapes, a negative index in any part and an index not below a given bound are refused."""
    from sim_core.unique import compact_indices

    rng = np.random.default_rng(5)
    parts = (rng.integers(0, 3000, size=(400, 4)), np.zeros((0, 4), dtype=np.int64),
             rng.integers(2000, 6000, size=(300, 4)))
    for dtype in (np.int64, np.int32):
        for cast in (np.int64, np.int32):
            cast_parts = tuple(part.astype(cast) for part in parts)
            own, local = compact_indices(cast_parts, dtype=dtype)
            own_c, local_c = compact_indices(np.concatenate(cast_parts), dtype=dtype)
            assert own.dtype == own_c.dtype and local.dtype == local_c.dtype == dtype and local.shape == (700, 4)
            np.testing.assert_array_equal(own, own_c)
            np.testing.assert_array_equal(local, local_c)
            for size in (6000, 9000):  # a known bound (at and above the largest index + 1): the same arrays
                own_s, local_s = compact_indices(cast_parts, dtype=dtype, size=size)
                assert own_s.dtype == own.dtype and local_s.dtype == dtype
                np.testing.assert_array_equal(own_s, own)
                np.testing.assert_array_equal(local_s, local)
    with pytest.raises(IndexError):
        compact_indices(parts, size=int(parts[2].max()))  # the largest index is not below the bound
    empty = compact_indices((np.zeros((0, 4), dtype=np.int64), np.zeros((0, 4), dtype=np.int64)), dtype=np.int32)
    assert empty[0].shape == (0,) and empty[1].shape == (0, 4) and empty[1].dtype == np.int32
    with pytest.raises(ValueError, match="equal shapes"):
        compact_indices((np.zeros((2, 4), dtype=np.int64), np.zeros((2, 2), dtype=np.int64)))
    with pytest.raises(ValueError, match="must be >= 0"):
        compact_indices((parts[0], np.array([[1, 2, -3, 4]])))


def test_spread_rows_inverts_the_gather_of_compact_indices():
    """Rows gathered on the named indices and spread back give the full array on those rows, zero elsewhere."""
    from sim_core.unique import compact_indices, spread_rows

    full = np.arange(30.0).reshape(10, 3)
    own, _ = compact_indices(np.array([[7, 2], [2, 9]]))
    out = spread_rows(own, full[own], 10)
    np.testing.assert_array_equal(out[own], full[own])
    assert not out[np.setdiff1d(np.arange(10), own)].any()
