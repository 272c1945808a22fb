"""The static sparsity pattern (:class:`sim_core.static_pattern.StaticPattern`) against its definition:
the sorted distinct keys ``row * n + col`` of the element blocks' entries with ``row < col`` between free
DoFs, plus the whole diagonal; the slots of block entries are their positions among those keys. Both
constructions (by vertex pairs, for masks that keep each vertex's DoFs together, and entry by entry)."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.static_pattern import StaticPattern


def _elements(rng, vertex_count: int) -> list[np.ndarray]:
    """Element arrays of 1 to 4 vertices over the first 80 % of the vertices (the rest in no element),
    with repeated vertices in some elements (padded edges ``[a, b, b]``)."""
    reach = int(0.8 * vertex_count)
    arrays = [rng.integers(0, reach, size=(rng.integers(5, 40), m)) for m in (1, 2, 3, 4)]
    padded = rng.integers(0, reach, size=(12, 2))
    arrays.append(np.concatenate([padded, padded[:, 1:]], axis=1))
    arrays.append(np.zeros((0, 3), dtype=np.int64))
    return arrays


def _definition(arrays: list[np.ndarray], free: np.ndarray):
    """(keys, kept entries' positions, their rows, their columns) by the rule, entry by entry."""
    n = free.size
    rows, cols = [], []
    for v in arrays:
        dofs = (3 * v[:, :, None] + np.arange(3)).reshape(v.shape[0], 3 * v.shape[1])
        rows.append(np.repeat(dofs, dofs.shape[1], axis=1).ravel())
        cols.append(np.tile(dofs, (1, dofs.shape[1])).ravel())
    rows.append(np.arange(n))
    cols.append(np.arange(n))
    r, c = np.concatenate(rows), np.concatenate(cols)
    keep = ((r < c) & free[r] & free[c]) | (r == c)
    return np.unique(r[keep] * n + c[keep]), np.flatnonzero(keep), r, c


def _free_mask(rng, mask: str, vertex_count: int) -> np.ndarray:
    """The DoF mask ``(3 vertex_count,)`` of a mask kind: every DoF free, whole vertices fixed, or DoFs fixed one by
    one (split vertices)."""
    if mask == "fixed vertices":
        return np.repeat(rng.uniform(size=vertex_count) > 0.3, 3)
    if mask == "split vertices":
        return rng.uniform(size=3 * vertex_count) > 0.3
    return np.ones(3 * vertex_count, dtype=bool)


@pytest.mark.parametrize("mask", ["all free", "fixed vertices", "split vertices"])
def test_pattern_and_slots_are_those_of_the_definition(mask):
    """Keys, diagonal slots, the kept entries' slots and every element's slot map equal the definition's,
    for every mask kind (the split mask takes the entry-by-entry construction)."""
    rng = np.random.default_rng(5)
    vertex_count = 60
    arrays = _elements(rng, vertex_count)
    free = _free_mask(rng, mask, vertex_count)
    n = free.size
    pattern = StaticPattern(arrays, free, n)
    keys, entry_index, r, c = _definition(arrays, free)
    np.testing.assert_array_equal(pattern.keys, keys)
    idx = np.arange(n)
    np.testing.assert_array_equal(pattern.diag_slots, np.searchsorted(keys, idx * n + idx))
    np.testing.assert_array_equal(pattern.fixed_diag_slots, pattern.diag_slots[~free])
    np.testing.assert_array_equal(pattern.entry_index, entry_index)
    np.testing.assert_array_equal(pattern.keys[pattern.slot], (r * n + c)[entry_index])
    for v in arrays:
        _assert_slots_of_definition(pattern, v, free)


@pytest.mark.parametrize("mask", ["all free", "fixed vertices", "split vertices"])
def test_csr_arrays_are_the_keys_rows_and_columns(mask, monkeypatch):
    """``csr()``: int32 row offsets and columns of the keys (``key // n``, ``key % n``) for both constructions,
    written a block of rows at a time (a block shorter than the rows here), the same objects at a second call."""
    rng = np.random.default_rng(8)
    vertex_count = 60
    free = _free_mask(rng, mask, vertex_count)
    n = free.size
    monkeypatch.setattr(StaticPattern, "_CSR_ROWS", 7)
    pattern = StaticPattern(_elements(rng, vertex_count), free, n)
    indptr, indices = pattern.csr()
    assert indptr.dtype == np.int32 and indices.dtype == np.int32
    np.testing.assert_array_equal(indptr, np.searchsorted(pattern.keys, np.arange(n + 1) * n))
    np.testing.assert_array_equal(np.repeat(np.arange(n), np.diff(indptr)), pattern.keys // n)
    np.testing.assert_array_equal(indices, pattern.keys % n)
    again = pattern.csr()
    assert again[0] is indptr and again[1] is indices


@pytest.mark.parametrize("mask", ["fixed vertices", "split vertices"])
def test_slot_map_of_elements_outside_the_pattern_is_refused(mask):
    """A block between free vertices that no element of the pattern joins, or a free vertex's own block
    when the vertex is in no element, is refused with a ValueError."""
    vertex_count = 20
    free = np.ones(3 * vertex_count, dtype=bool)
    free[:3] = False
    if mask == "split vertices":
        free[4] = False
    pattern = StaticPattern([np.array([[0, 1, 2], [3, 4, 5]])], free, 3 * vertex_count)
    assert pattern.slot_map(np.array([[0, 1]])).max() >= 0  # vertex 0 is fixed: its pairs are not kept
    with pytest.raises(ValueError, match="outside the pattern"):
        pattern.slot_map(np.array([[1, 7]]))
    with pytest.raises(ValueError, match="outside the pattern"):
        pattern.slot_map(np.array([[12]]))


def _assert_slots_of_definition(pattern: StaticPattern, v: np.ndarray, free: np.ndarray) -> None:
    """Every entry of ``pattern.slot_map(v)`` is the position of its key, or -1 where not kept."""
    n = free.size
    k, m = v.shape
    slots = pattern.slot_map(v)
    assert slots.shape == (k, 3 * m, 3 * m) and slots.dtype == np.int32
    dofs = (3 * v[:, :, None] + np.arange(3)).reshape(k, 3 * m)
    rows, cols = dofs[:, :, None] + 0 * dofs[:, None, :], dofs[:, None, :] + 0 * dofs[:, :, None]
    kept = ((rows < cols) & free[rows] & free[cols]) | (rows == cols)
    np.testing.assert_array_equal(slots[~kept], -1)
    np.testing.assert_array_equal(pattern.keys[slots[kept]], (rows * n + cols)[kept])


@pytest.mark.parametrize("held", [None, 2])
def test_slot_maps_of_translated_copies_are_the_first_copy_moved_and_those_of_the_definition(held):
    """Element arrays of five stacked copies of one scene (body-major: each body's copies one after the other,
    as sim_core.batch.stacked lays them out): the slot map is made from the first copy's chunk and moved
    (StaticPattern._translated_chunks finds the run of chunks), and equals the definition; a copy with another
    free mask (a held copy) ends the run, and the map of the rest, made element by element, still equals it;
    an array of two bodies' copies is two runs."""
    rng = np.random.default_rng(8)
    copies, per_copy = 5, (14, 9)  # two bodies: vertices per copy
    base = _elements(rng, per_copy[0])[:5] + [rng.integers(0, per_copy[1], size=(7, 3))]
    body_of = [0, 0, 0, 0, 0, 1]
    start = (0, copies * per_copy[0])  # each body's first stacked vertex
    arrays = [np.concatenate([b + start[body] + i * per_copy[body] for i in range(copies)])
              for b, body in zip(base, body_of)]
    vertex_count = copies * sum(per_copy)
    vertex_free = np.ones(vertex_count, dtype=bool)
    for body in (0, 1):
        fixed = rng.uniform(size=per_copy[body]) < 0.3
        for i in range(copies):
            vertex_free[start[body] + i * per_copy[body] + np.flatnonzero(fixed)] = False
    if held is not None:
        vertex_free[start[0] + held * per_copy[0]: start[0] + (held + 1) * per_copy[0]] = False
    free = np.repeat(vertex_free, 3)
    pattern = StaticPattern(arrays, free, free.size)
    keys, _, _, _ = _definition(arrays, free)
    np.testing.assert_array_equal(pattern.keys, keys)
    for v, b, body in zip(arrays, base, body_of):
        k0, offsets = pattern._translated_chunks(v)
        assert k0 == len(b) and offsets.size == (held if held is not None and body == 0 else copies)
        _assert_slots_of_definition(pattern, v, free)
    _assert_slots_of_definition(pattern, np.concatenate([arrays[2], arrays[5]]), free)  # two bodies' runs
    assert pattern._translated_chunks(np.array([[0, 1], [1, 2], [2, 3], [3, 4]])) is None  # chunks sharing vertices
