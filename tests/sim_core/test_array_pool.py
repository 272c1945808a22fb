"""sim_core/array_pool.py: a block is handed out again only when nothing but the pool holds it (no caller, view or
cache), so a reused block never changes an array someone still reads; the candidate lists' vertices and the hash
search's sorted pairs written into pooled blocks equal fresh ones."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.array_pool import ArrayPool


def test_a_block_is_reused_only_when_nothing_else_holds_it():
    pool = ArrayPool(keep=2)
    a = pool.empty("x", (10, 4), np.int64)
    assert a.shape == (10, 4) and a.dtype == np.int64 and a.flags.c_contiguous
    a[:] = 7
    b = pool.empty("x", (10, 4), np.int64)  # ``a`` held: another block
    assert not np.shares_memory(a, b) and np.all(a == 7)
    cache = {"kept": a[3:5]}  # a view of ``a``'s block kept elsewhere
    del a
    c = pool.empty("x", (9, 4), np.int64)
    assert not np.shares_memory(c, cache["kept"])  # (``b`` is held, ``a``'s block through the view)
    del cache, b
    d = pool.empty("x", (8, 4), np.int64)  # a free block, long enough: reused
    assert any(np.shares_memory(d, block) for block in pool._blocks["x"])
    assert not np.shares_memory(d, c)
    assert not np.shares_memory(pool.empty("x", (8, 4), np.int32), d)  # another dtype: not that block
    assert not np.shares_memory(pool.empty("x", (8, 3), np.int64), d)  # another row shape: not that block
    assert len(pool._blocks["x"]) <= 2  # the oldest forgotten beyond ``keep``
    del d
    long = pool.empty("y", (5,), np.float64)
    del long
    longer = pool.empty("y", (50,), np.float64)  # the free block is too short: replaced
    assert longer.shape == (50,) and len(pool._blocks["y"]) == 1
    with pytest.raises(ValueError, match="at least one dimension"):
        pool.empty("z", (), np.float64)
    with pytest.raises(ValueError, match="keep must be >= 1"):
        ArrayPool(keep=0)


def test_pooled_list_vertices_equal_fresh_ones_and_never_overwrite_held_lists():
    """``CandidateVertices(..., pool=...)``: the same vertex and int32 arrays as without a pool; lists made while the
    last ones are held get blocks of their own, the blocks of dropped lists are written again; a row out of range
    raises IndexError."""
    from sim_core.energies.contact.pair_lists import CandidateVertices
    from tests.sim_core.energies.test_pair_lists import _lists

    vt, ee, triangles, edges = _lists()
    pool = ArrayPool()
    want = CandidateVertices(vt, ee, triangles, edges)
    first = CandidateVertices(vt, ee, triangles, edges, pool=pool)
    held = (first.vt_vertices.copy(), first.ee_vertices.copy())
    for k in range(3):
        rows = slice(k, None)
        lists = CandidateVertices(vt[rows], ee[rows], triangles, edges, pool=pool)
        np.testing.assert_array_equal(lists.vt_vertices, want.vt_vertices[rows])
        np.testing.assert_array_equal(lists.ee_vertices, want.ee_vertices[rows])
        for got, fresh in zip(lists.int32_vertices(), (want.vt_vertices[rows], want.ee_vertices[rows])):
            assert got.dtype == np.int32
            np.testing.assert_array_equal(got, fresh)
        for array, copy in zip((first.vt_vertices, first.ee_vertices), held):  # the held lists' arrays unchanged
            np.testing.assert_array_equal(array, copy)
            assert not np.shares_memory(array, lists.vt_vertices) and not np.shares_memory(array, lists.ee_vertices)
    reused = CandidateVertices(vt, ee, triangles, edges, pool=pool)  # (the lists of k = 0, 1 dropped by now)
    assert len(pool._blocks["ee_vertices"]) == 3  # (one block for ``first``, two for the lists of k = 0, 1, 2)
    assert any(np.shares_memory(reused.ee_vertices, block) for block in pool._blocks["ee_vertices"])
    assert not np.shares_memory(reused.ee_vertices, lists.ee_vertices)
    np.testing.assert_array_equal(reused.ee_vertices, want.ee_vertices)
    wrong = ee.copy()
    wrong[3, 1] = len(edges)
    with pytest.raises(IndexError, match="out of range"):
        CandidateVertices(vt, wrong, triangles, edges, pool=pool)


def test_copy_of_holds_the_values_converted_and_is_a_block_of_the_pool():
    """``ArrayPool.copy_of``: ``values.astype(dtype)`` (``values``' dtype by default) in a pooled block, which a later
    call of the same name writes again once nothing holds it."""
    pool = ArrayPool()
    values = np.array([[1, 2], [3, -4]], dtype=np.int64)
    got = pool.copy_of("v", values, np.int32)
    assert got.dtype == np.int32 and np.array_equal(got, values.astype(np.int32))
    block = id(got.base)  # (an id: a reference would hold the block)
    del got
    again = pool.copy_of("v", values[:1], np.int32)
    assert id(again.base) == block and np.array_equal(again, values[:1])
    same = pool.copy_of("w", values)
    assert same.dtype == np.int64 and np.array_equal(same, values)
