"""The pattern of a symmetric matrix from its upper triangle: :func:`both_triangles`, the CSR index arrays of
``U + U^T - diag(U)`` with the source of each entry in ``U``, so that the full matrix's values are one gather of the
upper triangle's (:class:`sim_core.linsolve.SymmetricExpansion`, the batched CG's both-triangle operator
:class:`sim_core.ti_kernels.pcg.BatchedPCG`).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def both_triangles(indptr: np.ndarray, indices: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The CSR pattern of ``U + U^T - diag(U)`` (both triangles) of an upper triangle ``U``'s CSR index arrays,
    with the position in ``U``'s data of each of its entries.

    Row ``i`` of the result is row ``i`` of ``U^T`` less its diagonal (one transposition, SciPy's C
    ``csr_tocsc``: those columns are below ``i``, in increasing order) followed by row ``i`` of ``U`` (sorted
    first where it is not), written into the output by two masked placements; no sort of the entries. Entries
    stored twice stay twice, explicit zeros stay.

    Args:
        indptr: ``U``'s row offsets, int ``(n + 1,)``.
        indices: ``U``'s column indices, int ``(nnz,)`` or longer (entries past ``indptr[-1]`` are ignored).
        n: rows (and columns) of ``U``.

    Returns:
        ``(full_indptr, full_indices, source)``: int ``(n + 1,)``, ``(f,)`` and ``(f,)`` (int32 when ``f`` and
        ``n`` fit, else int64), the result's rows in increasing column order and, per entry, the position in
        ``U``'s data of the entry it copies.

    Raises:
        ValueError: ``U`` has an entry below the diagonal.
    """
    nnz = int(indptr[-1])
    wide = max(n, 2 * nnz) >= np.iinfo(np.int32).max
    dtype = np.int64 if wide else np.int32
    upper = sp.csr_matrix((np.arange(nnz, dtype=dtype), np.asarray(indices)[:nnz], indptr), shape=(n, n))
    counts = np.diff(upper.indptr)
    if not upper.has_sorted_indices:
        upper = upper.copy()  # not the caller's indices
        upper.sort_indices()  # data (the positions) moves with the indices
    row = np.arange(n, dtype=dtype)
    # each row's smallest column, at its start (sorted rows): an entry below the diagonal shows there
    first = np.where(counts > 0, upper.indices[np.minimum(upper.indptr[:-1], max(nnz - 1, 0))], n) if nnz else row + n
    if np.any(first < row):
        raise ValueError("the matrix has entries below the diagonal (not an upper triangle)")
    diagonal = first == row
    twice = diagonal & (counts > 1)
    twice[twice] = upper.indices[upper.indptr[:-1][twice] + 1] == row[twice]
    lower = upper.T.tocsr()  # U^T: row i holds the columns j <= i of U's column i, increasing (the diagonal last)
    if twice.any():  # a diagonal stored more than once: every such entry found
        rows = np.repeat(row, counts)
        diagonal = np.bincount(rows[upper.indices == rows], minlength=n)
        strict = lower.indices != np.repeat(row, np.diff(lower.indptr))
    else:
        strict = np.ones(nnz, dtype=bool)
        strict[lower.indptr[1:][diagonal] - 1] = False
    lower_counts = np.diff(lower.indptr) - diagonal
    full_indptr = np.zeros(n + 1, dtype=dtype)
    np.cumsum(lower_counts + counts, out=full_indptr[1:])
    runs = np.empty(2 * n, dtype=np.int64)  # per row: its U^T run, then its U run
    runs[0::2], runs[1::2] = lower_counts, counts
    from_upper = np.repeat(np.tile(np.array([False, True]), n), runs)
    from_lower = ~from_upper
    full_indices = np.empty(from_upper.size, dtype=dtype)
    source = np.empty(from_upper.size, dtype=dtype)
    full_indices[from_upper] = upper.indices
    full_indices[from_lower] = lower.indices[strict]
    source[from_upper] = upper.data
    source[from_lower] = lower.data[strict]
    return full_indptr, full_indices, source
