"""The both-triangle pattern of an upper triangle (:func:`sim_core.symmetric_pattern.both_triangles`) against its
definition."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from sim_core.symmetric_pattern import both_triangles


def _definition(indptr: np.ndarray, indices: np.ndarray, n: int):
    """Rows, columns and sources of ``U + U^T - diag(U)`` entry by entry: each stored entry ``(i, j)`` at position
    ``p`` gives ``(i, j, p)`` and, off the diagonal, ``(j, i, p)``; sorted by row, column, then ``U^T``'s entries of
    a column before ``U``'s and each in its order of storage."""
    nnz = int(indptr[-1])
    rows = np.repeat(np.arange(n), np.diff(indptr))
    cols = np.asarray(indices[:nnz])
    entries = [(i, j, p) for p, (i, j) in enumerate(zip(rows.tolist(), cols.tolist()))]
    entries += [(j, i, p) for p, (i, j) in enumerate(zip(rows.tolist(), cols.tolist())) if i != j]
    entries.sort(key=lambda e: (e[0], e[1], e[0] == rows[e[2]], e[2]))
    out = np.array(entries, dtype=np.int64).reshape(-1, 3)
    return np.searchsorted(out[:, 0], np.arange(n + 1)), out[:, 1], out[:, 2]


def _upper(rng: np.random.Generator, n: int, density: float, diagonal: bool) -> sp.csr_matrix:
    upper = sp.triu(sp.random(n, n, density=density, random_state=rng, format="csr"), format="csr")
    if diagonal:
        upper = sp.csr_matrix(upper + sp.eye(n))
    upper.sort_indices()
    return upper


@pytest.mark.parametrize("diagonal", [True, False])
def test_pattern_and_sources_are_the_definitions(diagonal):
    """Random upper triangles with and without a full diagonal, sorted rows, unsorted rows (the sources then the
    positions in the unsorted arrays, the caller's arrays unchanged), stored duplicates, trailing unused entries."""
    rng = np.random.default_rng(11)
    for trial in range(12):
        n = int(rng.integers(1, 40))
        upper = _upper(rng, n, rng.uniform(0.0, 0.4), diagonal)
        indptr, indices = upper.indptr.copy(), upper.indices.copy()
        if trial % 3 == 1:  # rows shuffled in place
            for i in range(n):
                rng.shuffle(indices[indptr[i]:indptr[i + 1]])
        if trial % 3 == 2 and indices.size:  # an entry stored twice (row 0's first again), then unused room
            row = np.repeat(np.arange(n), np.diff(indptr))
            indices = np.insert(indices, indptr[row[0] + 1], indices[0])
            indptr = indptr.copy()
            indptr[row[0] + 1:] += 1
            indices = np.concatenate([indices, [n - 1, 0]])
        given = (indptr.copy(), indices.copy())
        full_indptr, full_indices, source = both_triangles(indptr, indices, n)
        ref = _definition(indptr, indices, n)
        np.testing.assert_array_equal(full_indptr, ref[0])
        np.testing.assert_array_equal(full_indices, ref[1])
        np.testing.assert_array_equal(source, ref[2])
        np.testing.assert_array_equal(indptr, given[0])
        np.testing.assert_array_equal(indices, given[1])


def test_values_gathered_by_source_are_the_symmetric_matrix():
    rng = np.random.default_rng(12)
    upper = _upper(rng, 30, 0.2, True)
    upper.data = rng.normal(size=upper.nnz)
    full_indptr, full_indices, source = both_triangles(upper.indptr, upper.indices, 30)
    full = sp.csr_matrix((upper.data[source], full_indices, full_indptr), shape=(30, 30))
    dense = upper.toarray()
    np.testing.assert_array_equal(full.toarray(), dense + np.triu(dense, 1).T)


def test_empty_matrix_and_lower_entries():
    indptr, indices, source = both_triangles(np.zeros(4, dtype=np.int32), np.zeros(0, dtype=np.int32), 3)
    np.testing.assert_array_equal(indptr, np.zeros(4))
    assert indices.size == 0 and source.size == 0
    with pytest.raises(ValueError, match="below the diagonal"):
        both_triangles(np.array([0, 1, 2]), np.array([0, 0]), 2)
