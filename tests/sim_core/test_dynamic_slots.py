"""Cached merge of the dynamic Hessian blocks (:mod:`sim_core.dynamic_slots`).

The cached merge (element tables, translated on rebuilds of the union pattern) must give exactly
the CSR arrays (``indptr``, ``indices``, and ``data`` bit for bit) of an uncached computation of the
union-pattern rule, over call sequences with repeated, changed and new dynamic vertex arrays, block
sets that come and go or change their element size, fixed-vertex masks that change, keys that
expire after :data:`STICKY_ASSEMBLIES` assemblies, new static patterns, and table pruning.
"""

from __future__ import annotations

import numpy as np
import pytest

import sim_core.dynamic_slots as dynamic_slots
from sim_core.assembly import HessianAssembler, StaticPattern
from sim_core.dynamic_slots import STICKY_ASSEMBLIES, DynamicMerge, block_keys
from sim_core.energies.base import HessianBlocks


class _UncachedMerge:
    """The union-pattern rule computed from scratch every call (sets of keys, sorting, searching)."""

    def __init__(self, dof_count: int) -> None:
        self.n = dof_count
        self.count = 0
        self.pattern = None
        self.last_used: dict[int, int] = {}

    def merge(self, pat, static_data, dynamic, free):
        n = self.n
        self.count += 1
        blocks = [b for b in dynamic if b.blocks.shape[0]]
        keys, values = [], []
        for b in blocks:
            r, c = block_keys(b.vertices, n)
            keep = (r <= c) & free[r] & free[c]
            keys.append(r[keep] * n + c[keep])
            values.append(b.blocks.reshape(-1)[keep])
        current = set(np.concatenate(keys + [np.zeros(0, np.int64)]).tolist())
        if self.pattern is not pat:
            self.pattern = pat
            self.last_used = {}
        elif not current <= self.last_used.keys():
            recent = {k for k, t in self.last_used.items() if t > self.count - STICKY_ASSEMBLIES}
            self.last_used = dict.fromkeys(recent | current, 0)
        for k in current:
            self.last_used[k] = self.count
        dyn = np.array(sorted(self.last_used), dtype=np.int64)
        union = np.union1d(pat.keys, dyn)
        data = np.zeros(union.size)
        data[np.searchsorted(union, pat.keys)] = static_data
        if blocks:
            slots = np.searchsorted(union, np.concatenate(keys))
            data += np.bincount(slots, weights=np.concatenate(values), minlength=union.size)
        indptr = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(np.bincount(union // n, minlength=n), out=indptr[1:])
        return indptr, union % n, data


def _assert_same_csr(U, ref) -> None:
    indptr, indices, data = ref
    np.testing.assert_array_equal(U.indptr, indptr)
    np.testing.assert_array_equal(U.indices, indices)
    assert U.data.tobytes() == data.tobytes()  # bit-identical values


def _blocks(rng, vertices: np.ndarray) -> HessianBlocks:
    m = vertices.shape[1]
    a = rng.normal(size=(vertices.shape[0], 3 * m, 3 * m))
    return HessianBlocks(np.asarray(vertices, dtype=np.int64), a + np.swapaxes(a, 1, 2))


def _elements(rng, vertex_count: int, k: int, m: int) -> np.ndarray:
    return np.stack([rng.choice(vertex_count, m, replace=False) for _ in range(k)]).reshape(k, m)


def _contact_sequence(rng, vertex_count: int, calls: int):
    """Dynamic vertex arrays like a contact set's: a candidate pool whose active subset changes,
    repeats between iterations, gains new pairs, and sometimes an empty or differently shaped set."""
    pool4 = _elements(rng, vertex_count, 40, 4)
    pool1 = np.arange(vertex_count)[:, None]
    previous = None
    for call in range(calls):
        kind = rng.uniform()
        if previous is not None and kind < 0.3:  # the same arrays (new values): an iterate repeats
            yield [HessianBlocks(v.copy(), rng.normal(size=b.shape)) for v, b in previous]
            continue
        if kind > 0.9:  # new pairs appear (a new candidate search)
            pool4 = np.concatenate([pool4, _elements(rng, vertex_count, 5, 4)])
        vt = pool4[np.sort(rng.choice(pool4.shape[0], int(rng.integers(0, 25)), replace=False))]
        ee = pool4[rng.permutation(pool4.shape[0])[: int(rng.integers(0, 8))]]  # unsorted order
        plane = pool1[rng.uniform(size=vertex_count) < 0.2]
        sets = [vt, ee, plane] if call % 7 else [plane, vt]  # a shifted list: other sizes per position
        if call % 11 == 5:
            sets = sets + [np.concatenate([vt[:3], vt[:3]])]  # a repeated element within one set
        blocks = [_blocks(rng, v) for v in sets]
        previous = [(b.vertices, b.blocks) for b in blocks]
        yield blocks


@pytest.mark.parametrize("table_elements, vertex_scale", [(8192, 1), (3, 1), (8192, 1700)])
def test_cached_merge_equals_uncached_rule_over_call_sequences(monkeypatch, table_elements, vertex_scale):
    """Bit-identical CSR on every call, the free mask changing under one static pattern, new static
    patterns, and more than STICKY_ASSEMBLIES calls (keys expire); a small table bound (pruning)
    changes nothing, nor do vertex indices too large for one int64 element identifier (51,000
    vertices: 51,000^4 > 2^62, the tables then compare vertex rows as bytes)."""
    monkeypatch.setattr(dynamic_slots, "TABLE_ELEMENTS", table_elements)
    rng = np.random.default_rng(7)
    n_v = 30
    vertex_count = n_v * vertex_scale
    static = [vertex_scale * _elements(rng, n_v, 25, 3)]
    free = np.ones(3 * vertex_count, dtype=bool)
    pat = StaticPattern(static, free, 3 * vertex_count)
    cached, uncached = DynamicMerge(3 * vertex_count), _UncachedMerge(3 * vertex_count)
    rebuilds = 0
    last_indices = None
    for call, dynamic in enumerate(_contact_sequence(rng, n_v, 3 * STICKY_ASSEMBLIES)):
        dynamic = [HessianBlocks(vertex_scale * b.vertices, b.blocks) for b in dynamic]
        if call in (40, 90):  # fixed vertices (a clamp), same static pattern object
            free = np.repeat(rng.uniform(size=vertex_count) > 0.2, 3)
        if call == 120:  # a new static pattern (rebuilt for a new free mask)
            free = np.repeat(rng.uniform(size=vertex_count) > 0.3, 3)
            pat = StaticPattern(static, free, 3 * vertex_count)
        static_data = rng.normal(size=pat.keys.size)
        U = cached.merge(pat, static_data, dynamic, free)
        _assert_same_csr(U, uncached.merge(pat, static_data, dynamic, free))
        assert all(t._ids.dtype.kind == ("V" if vertex_count ** t.m >= 2**62 else "i") for t in cached._tables.values())
        if last_indices is not None and not np.array_equal(last_indices, U.indices):
            rebuilds += 1
        last_indices = U.indices
    assert rebuilds >= 5  # the sequence exercised rebuilds of the union pattern
    assert any(t._ids.dtype.kind == "V" for t in cached._tables.values()) == (vertex_scale > 1)


def test_keys_expire_only_after_sticky_assemblies():
    """An entry used once stays in the pattern (as a zero) through later rebuilds until it has been
    unused for STICKY_ASSEMBLIES assemblies, then leaves it at the next rebuild."""
    rng = np.random.default_rng(3)
    n_v = 12
    free = np.ones(3 * n_v, dtype=bool)
    pat = StaticPattern([np.array([[0, 1, 2]])], free, 3 * n_v)
    cached, uncached = DynamicMerge(3 * n_v), _UncachedMerge(3 * n_v)
    a, b = np.array([[3, 7]]), np.array([[4, 9]])
    sequence = ([[a]] * (STICKY_ASSEMBLIES + 5) + [[a, b]] + [[a]] * (STICKY_ASSEMBLIES - 1)
                + [[a, b], [np.array([[5, 10]])]])
    sizes = []
    for sets in sequence:
        dynamic = [_blocks(rng, v) for v in sets]
        static_data = rng.normal(size=pat.keys.size)
        U = cached.merge(pat, static_data, dynamic, free)
        _assert_same_csr(U, uncached.merge(pat, static_data, dynamic, free))
        sizes.append(U.nnz)
    # b enters once, stays while unused (a alone), is kept by the rebuild for (5, 10) only if recent
    assert sizes[STICKY_ASSEMBLIES + 5] > sizes[0]
    assert sizes[-3] == sizes[STICKY_ASSEMBLIES + 5]


def test_assembler_paths_equal_uncached_rule():
    """Through HessianAssembler: assemble_upper and assemble_upper_values merge with the same
    result as the uncached rule (also across a new static pattern for a new free mask)."""
    rng = np.random.default_rng(11)
    n_v = 20
    static = [_blocks(rng, _elements(rng, n_v, 18, 3))]
    diag = rng.uniform(1.0, 2.0, 3 * n_v)
    asm = HessianAssembler(3 * n_v)
    uncached = _UncachedMerge(3 * n_v)
    free = np.ones(3 * n_v, dtype=bool)
    for call, dynamic in enumerate(_contact_sequence(rng, n_v, 30)):
        if call == 15:
            free = np.repeat(rng.uniform(size=n_v) > 0.25, 3)
        U = asm.assemble_upper(static, dynamic, diag, free)
        pat = asm.static_pattern([b.vertices for b in static], free)
        entries = np.concatenate([static[0].blocks.reshape(-1), diag])[pat.entry_index]
        static_data = np.bincount(pat.slot, weights=entries, minlength=pat.keys.size)
        static_data[pat.fixed_diag_slots] = 1.0
        _assert_same_csr(U, uncached.merge(pat, static_data, dynamic, free))
        slots = pat.slot_map(static[0].vertices)
        values = np.bincount(slots[slots >= 0], weights=static[0].blocks[slots >= 0], minlength=pat.keys.size)
        V = asm.assemble_upper_values(pat, values, dynamic, diag, free)
        static_values = values.copy()
        static_values[pat.diag_slots] += diag
        static_values[pat.fixed_diag_slots] = 1.0
        _assert_same_csr(V, uncached.merge(pat, static_values, dynamic, free))


def test_element_with_only_static_keys_that_left_the_dynamic_set():
    """An element whose entries are all static keys (a plane contact on a vertex of an elastic
    element) that has left the dynamic key set is mapped again when it comes back: the rule then
    rebuilds the set (here dropping the key of a pair last used 50 assemblies before), as the
    uncached computation does, although the element's slots are still in the CSR pattern."""
    rng = np.random.default_rng(5)
    n_v = 12
    free = np.ones(3 * n_v, dtype=bool)
    pat = StaticPattern([np.array([[0, 1, 2]])], free, 3 * n_v)
    cached, uncached = DynamicMerge(3 * n_v), _UncachedMerge(3 * n_v)
    plane, other = np.array([[0]]), np.array([[11]])
    sequence = ([[plane, np.array([[5, 6]])]] + [[other, np.array([[5, 6]])]] * 6
                + [[other, np.array([[5, 6], [9, 10]])]] + [[other, np.array([[5, 6]])]] * 48
                + [[other, np.array([[5, 6], [7, 8]])], [plane, np.array([[7, 8]])]])
    sizes = []
    for sets in sequence:
        dynamic = [_blocks(rng, v) for v in sets]
        static_data = rng.normal(size=pat.keys.size)
        U = cached.merge(pat, static_data, dynamic, free)
        _assert_same_csr(U, uncached.merge(pat, static_data, dynamic, free))
        sizes.append(U.nnz)
    assert sizes[-1] < sizes[-2]  # the pair (9, 10) left the pattern at the last call's rebuild


def test_matrices_of_one_union_share_read_only_sorted_index_arrays():
    """Merges under one union pattern return matrices with their own values but the same index
    arrays, read-only (an in-place change of one matrix's pattern raises) and flagged sorted; SciPy's
    own checks on such a matrix pass, and a rebuilt union gives new arrays."""
    import scipy.sparse as sp

    rng = np.random.default_rng(13)
    n_v = 10
    free = np.ones(3 * n_v, dtype=bool)
    pat = StaticPattern([np.array([[0, 1, 2], [2, 3, 4]])], free, 3 * n_v)
    merge = DynamicMerge(3 * n_v)
    pair = np.array([[5, 6]])
    first = merge.merge(pat, rng.normal(size=pat.keys.size), [_blocks(rng, pair)], free)
    second = merge.merge(pat, rng.normal(size=pat.keys.size), [_blocks(rng, pair)], free)
    assert first.indices is second.indices and first.indptr is second.indptr
    assert not np.shares_memory(first.data, second.data) and not np.array_equal(first.data, second.data)
    assert first.has_sorted_indices and first.has_canonical_format
    with pytest.raises(ValueError, match="read-only"):
        first.indices[0] = 1
    checked = sp.csr_matrix((second.data.copy(), second.indices.copy(), second.indptr.copy()), shape=second.shape)
    checked.check_format(full_check=True)
    assert checked.has_sorted_indices
    np.testing.assert_array_equal((second - checked).toarray(), 0.0)
    empty = [merge.merge(pat, rng.normal(size=pat.keys.size), [], free) for _ in range(2)]  # static values only
    assert not np.shares_memory(empty[0].data, empty[1].data) and not np.array_equal(empty[0].data, empty[1].data)
    third = merge.merge(pat, rng.normal(size=pat.keys.size), [_blocks(rng, np.array([[7, 9]]))], free)  # new keys
    assert third.indices is not second.indices and third.nnz > second.nnz
    with pytest.raises(ValueError, match="3 values for"):
        merge.union.matrix(np.zeros(3))


def test_a_body_held_after_steps_leaves_no_dynamic_entry_and_steps_on():
    """The card's table contact and friction blocks were merged while it was free; once every card
    vertex is held, no dynamic entry is kept (an empty bincount, int64 in NumPy) and the Newton
    matrix is still a float matrix: the step converges and the held card stays where it is."""
    from sim_core.bundled import config_dir
    from sim_core.simulation import Simulation

    sim = Simulation.from_scene(config_dir() / "scenes" / "press_slide.yaml")
    for _ in range(3):
        sim.step()
    card = sim.model.bodies["sheet"].vertices
    sim.model.vertex_fixed[card] = True
    x_card = sim.state.x[card].copy()
    info = sim.step()
    assert info.converged_strict and info.factorizations >= 1
    np.testing.assert_array_equal(sim.state.x[card], x_card)
