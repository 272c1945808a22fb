"""The static part of the Newton matrix's sparsity pattern: the upper-triangle entries of fixed
element-vertex arrays plus the full diagonal, for one free mask (:class:`StaticPattern`), and the
DoF keys of Hessian blocks (:func:`block_keys`), shared by :mod:`sim_core.assembly` and
:mod:`sim_core.dynamic_slots`.

When each vertex's three DoFs are all free or all fixed (every scene of this project: fixed DoFs come
from fixed vertices), the pattern is made from *vertex pairs*: the element arrays' distinct pairs
``u < w`` of free vertices (one per 3x3 block, nine times fewer items to sort than the DoF entries), each
expanded into its nine entries in sorted order, and a vertex's own block (its upper triangle when it is
free and in an element, else its diagonal). :meth:`StaticPattern.slot_map` then looks up vertex pairs
as well. A mask that splits a vertex's DoFs takes the entry-by-entry construction; both give the same
keys and slots (the pattern is a function of the arrays and the mask).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from sim_core.energies.base import block_dof_indices
from sim_core.unique import sorted_unique


def block_keys(vertices: np.ndarray, dof_count: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column DoF of every entry of blocks over ``vertices`` ``(k, m)``, each ``(k (3m)^2,)``."""
    dofs = block_dof_indices(vertices)
    n = dofs.shape[1]
    rows = np.repeat(dofs, n, axis=1).reshape(-1)
    cols = np.tile(dofs, (1, n)).reshape(-1)
    return rows, cols


_BLOCK_KEPT = np.array([np.zeros((3, 3), bool), np.ones((3, 3), bool), np.triu(np.ones((3, 3), bool)), np.eye(3, dtype=bool)])
"""Kept entries (i, j) of a 3x3 vertex block by its kind: none (lower triangle, a fixed vertex), between two free
vertices, a free vertex's own block (upper triangle), a fixed vertex's own block (diagonal)."""


class StaticPattern:
    """Upper-triangle pattern of fixed element-vertex arrays plus the full diagonal, for one free mask.

    An entry ``(row, col)`` of an element block is kept when ``row < col`` and both DoFs are free,
    or ``row == col`` (the diagonal; fixed DoFs get 1 there).

    Args:
        vertex_arrays: element vertex arrays, each ``(k, m)`` int.
        free: free-DoF mask, shape ``(dof_count,)`` bool.
        dof_count: DoFs ``3 N``.

    Attributes:
        keys: sorted unique linear keys ``row * n + col`` of the kept entries, shape ``(nnz,)``.
        entry_index: positions of the kept entries in the concatenated block values (blocks in
            order, then the diagonal), shape ``(kept,)`` (made on first use).
        slot: CSR slot of each kept entry, shape ``(kept,)`` (made on first use).
        diag_slots: slot of every diagonal entry, shape ``(dof_count,)``.
        fixed_diag_slots: slots of the diagonal entries of fixed DoFs.
    """

    def __init__(self, vertex_arrays: Sequence[np.ndarray], free: np.ndarray, dof_count: int) -> None:
        self.dof_count = dof_count
        self.free = free
        self._arrays = [np.asarray(v) for v in vertex_arrays]
        self._entries: tuple[np.ndarray, np.ndarray] | None = None  # (entry_index, slot)
        self._vertex: tuple | None = None  # the vertex-pair tables (_by_vertex_pairs)
        idx = np.arange(dof_count)
        vertex_free = np.asarray(free, dtype=bool).reshape(-1, 3) if dof_count % 3 == 0 else None
        if vertex_free is not None and np.array_equal(vertex_free, np.repeat(vertex_free[:, :1], 3, axis=1)):
            self.keys, indptr = self._by_vertex_pairs(vertex_free[:, 0])
            self.diag_slots = indptr[:-1]  # a row's first entry is its diagonal
        else:
            r, c = self._raw_entries()
            keep = ((r < c) & free[r] & free[c]) | (r == c)
            entry_index = np.flatnonzero(keep)
            self.keys, slot = sorted_unique(r[keep] * dof_count + c[keep], return_inverse=True)
            self._entries = (entry_index, slot)
            self.diag_slots = np.searchsorted(self.keys, idx * dof_count + idx)
        self.fixed_diag_slots = self.diag_slots[~free]

    def _raw_entries(self) -> tuple[np.ndarray, np.ndarray]:
        """Rows and columns (int64) of every block entry, blocks in order, then the diagonal."""
        rows, cols = [], []
        for v in self._arrays:
            r, c = block_keys(v, self.dof_count)
            rows.append(r)
            cols.append(c)
        idx = np.arange(self.dof_count)
        rows.append(idx)
        cols.append(idx)
        return np.concatenate(rows).astype(np.int64), np.concatenate(cols).astype(np.int64)

    def _by_vertex_pairs(self, vertex_free: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The keys and the rows' CSR offsets ``indptr`` ``(dof_count + 1,)`` from vertex pairs (module
        docstring); keeps the tables :meth:`slot_map` reads."""
        N = vertex_free.shape[0]
        n = self.dof_count
        in_element = np.zeros(N, dtype=bool)
        pair_keys = []
        for v in self._arrays:
            k, m = v.shape
            if k == 0:
                continue
            v = v.astype(np.int64)
            in_element[v.ravel()] = True
            u = np.broadcast_to(v[:, :, None], (k, m, m)).ravel()
            w = np.broadcast_to(v[:, None, :], (k, m, m)).ravel()
            kept = (u < w) & vertex_free[u] & vertex_free[w]
            pair_keys.append(u[kept] * N + w[kept])
        pairs = sorted_unique(np.concatenate(pair_keys)) if pair_keys else np.zeros(0, dtype=np.int64)
        pu, pw = pairs // N, pairs % N
        pair_start = np.zeros(N + 1, dtype=np.int64)
        np.cumsum(np.bincount(pu, minlength=N), out=pair_start[1:])
        full = vertex_free & in_element  # own block: upper triangle (else the diagonal only)
        own = np.where(full[:, None], 3 - np.arange(3)[None, :], 1)  # (N, 3): own entries in row 3 u + a
        neighbours = np.diff(pair_start)
        indptr = np.zeros(n + 1, dtype=np.int64)
        np.cumsum((own + 3 * neighbours[:, None]).ravel(), out=indptr[1:])
        keys = np.empty(int(indptr[-1]), dtype=np.int64)
        rows = np.arange(n, dtype=np.int64)
        # own entries: row 3 u + a, columns 3 u + a ... (3 u + 2 when full), at the row's start
        own_len = own.ravel()
        own_row = np.repeat(rows, own_len)
        own_pos = np.arange(own_row.size) - np.repeat(np.cumsum(own_len) - own_len, own_len)
        keys[indptr[own_row] + own_pos] = own_row * n + own_row + own_pos
        # pair (u, w), rank t in u's list: rows 3 u + a, columns 3 w + b, at own + 3 t + b
        if pairs.size:
            t = np.arange(pairs.size) - pair_start[pu]
            a = np.arange(3)
            r = 3 * pu[:, None, None] + a[None, :, None]  # (P, 3, 1)
            pos = indptr[r] + own[pu][:, :, None] + 3 * t[:, None, None] + a[None, None, :]
            keys[pos] = r * n + 3 * pw[:, None, None] + a[None, None, :]
        self._vertex = (N, vertex_free, full, own, pairs, pair_start, indptr)
        return keys, indptr

    @property
    def entry_index(self) -> np.ndarray:
        """Positions of the kept entries in the concatenated block values, shape ``(kept,)``."""
        return self._kept_entries()[0]

    @property
    def slot(self) -> np.ndarray:
        """CSR slot of each kept entry, shape ``(kept,)``."""
        return self._kept_entries()[1]

    def _kept_entries(self) -> tuple[np.ndarray, np.ndarray]:
        if self._entries is None:
            r, c = self._raw_entries()
            keep = ((r < c) & self.free[r] & self.free[c]) | (r == c)
            self._entries = (np.flatnonzero(keep), np.searchsorted(self.keys, r[keep] * self.dof_count + c[keep]))
        return self._entries

    def lookup(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Slot of each entry ``(rows, cols)`` under the keep rule of the class, -1 where not kept.

        Args:
            rows, cols: global DoF indices, int arrays of one shape.

        Returns:
            int32 array of that shape.

        Raises:
            ValueError: a kept entry that is not in the pattern (its elements were not part of it).
        """
        n = self.dof_count
        r = np.asarray(rows, dtype=np.int64)
        c = np.asarray(cols, dtype=np.int64)
        keep = ((r < c) & self.free[r] & self.free[c]) | (r == c)
        key = r[keep] * n + c[keep]
        pos = np.minimum(np.searchsorted(self.keys, key), max(self.keys.size - 1, 0))
        if key.size and not np.array_equal(self.keys[pos], key):
            raise ValueError("StaticPattern.lookup: entries outside the pattern")
        out = np.full(r.shape, -1, dtype=np.int32)
        out[keep] = pos
        return out

    def slot_map(self, vertices: np.ndarray) -> np.ndarray:
        """Slots of the entries of element blocks over ``vertices`` ``(k, m)``: int32 ``(k, 3 m, 3 m)``.

        Entry ``[e, r, s]`` is the slot of local DoFs ``(r, s)`` of element ``e``, or -1 where the
        entry is not kept (lower triangle, a fixed DoF). A kernel that computes the local upper
        triangle ``r <= s`` of a symmetric block adds each value at ``[e, r, s]`` and, for ``r < s``,
        at ``[e, s, r]`` (where those are >= 0): every global upper entry then receives its value once
        (twice where two local DoFs are the same global DoF, as the full block sum does).

        Raises:
            ValueError: a kept entry that is not in the pattern (its elements were not part of it).
        """
        vertices = np.asarray(vertices)
        k, m = vertices.shape
        if self._vertex is None:
            rows, cols = block_keys(vertices, self.dof_count)
            return self.lookup(rows, cols).reshape(k, 3 * m, 3 * m)
        N, vertex_free, full, own, pairs, pair_start, indptr = self._vertex
        v = vertices.astype(np.int64)
        a = np.arange(3)
        u, w = v[:, :, None], v[:, None, :]  # (k, m, 1), (k, 1, m): the local vertex pair (a, b)
        between = (u < w) & vertex_free[u] & vertex_free[w]  # (k, m, m)
        same = np.broadcast_to(u == w, between.shape)
        if np.any(same & ~full[u] & vertex_free[u]):
            raise ValueError("StaticPattern.slot_map: entries outside the pattern")
        rank = np.zeros(between.shape, dtype=np.int64)  # the pair's rank in u's list of pairs
        if between.any():
            key = (u * N + w)[between]
            q = np.minimum(np.searchsorted(pairs, key), max(pairs.size - 1, 0))
            if pairs.size == 0 or not np.array_equal(pairs[q], key):
                raise ValueError("StaticPattern.slot_map: entries outside the pattern")
            rank[between] = q - np.broadcast_to(pair_start[u], between.shape)[between]
        row_start = indptr[3 * v[:, :, None] + a].astype(np.int32)  # (k, m, 3): row 3 u + i starts at its diagonal
        # the block of pair (a, b), row i: its first column's slot (between: after the own entries and the
        # earlier pairs' blocks; same vertex: the diagonal's slot less i), column j at that + j
        base = np.where(between[:, :, None, :],
                        (row_start + own[v].astype(np.int32))[:, :, :, None] + (3 * rank).astype(np.int32)[:, :, None, :],
                        (row_start - a.astype(np.int32))[:, :, :, None])  # (k, m, 3, m)
        kind = np.where(between, 1, np.where(same, np.where(full[u], 2, 3), 0))  # (k, m, m)
        kept = _BLOCK_KEPT[kind].transpose(0, 1, 3, 2, 4)  # (k, m, 3, m, 3)
        out = np.where(kept, base[..., None] + np.arange(3, dtype=np.int32), np.int32(-1))
        return out.reshape(k, 3 * m, 3 * m)
