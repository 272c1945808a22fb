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
from sim_core.slot_translation import joined
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
        self._csr: tuple[np.ndarray, np.ndarray] | None = None  # (indptr, indices) of csr(), made at its first call
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
            for a in range(m):  # each local pair once: its vertices in increasing order
                for b in range(a + 1, m):
                    u, w = np.minimum(v[:, a], v[:, b]), np.maximum(v[:, a], v[:, b])
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
        start = indptr[:-1].reshape(N, 3)  # row 3 u + a starts at start[u, a]
        u_all = np.arange(N, dtype=np.int64)
        # own entries: row 3 u + a, columns 3 u + c for c = a (every vertex) and c > a (full ones), at the row's start
        for a in range(3):
            for c in range(a, 3):
                u = u_all if c == a else u_all[full]
                keys[start[u, a] + (c - a)] = (3 * u + a) * n + 3 * u + c
        # pair (u, w), rank t in u's list: rows 3 u + a, columns 3 w + b, at own + 3 t + b
        if pairs.size:
            first = (start + own)[pu] + 3 * (np.arange(pairs.size) - pair_start[pu])[:, None]  # (P, 3): column 3 w
            for a in range(3):
                value = (3 * pu + a) * n + 3 * pw
                for b in range(3):
                    keys[first[:, a] + b] = value + b
        self._vertex = (N, vertex_free, full, own, pairs, pair_start, indptr)
        return keys, indptr

    _CSR_ROWS = 1 << 16
    """Rows whose columns :meth:`csr` writes at a time (its temporaries: that many rows' keys)."""

    def csr(self) -> tuple[np.ndarray, np.ndarray]:
        """The pattern as CSR index arrays ``(indptr, indices)``: int32 ``(dof_count + 1,)`` and ``(nnz,)``, the
        columns of each row in increasing order (the keys' order; a row's first entry is its diagonal). Made at
        the first call (the rows' offsets from the vertex pairs' tables, or by bisection of the keys; the
        columns the keys less their rows' ``row * dof_count``, a block of rows at a time), then the same objects.

        Raises:
            ValueError: a pattern too large for int32 indices.
        """
        if self._csr is not None:
            return self._csr
        n, keys = self.dof_count, self.keys
        if max(n, keys.size) >= np.iinfo(np.int32).max:
            raise ValueError(f"StaticPattern.csr: {keys.size} entries of {n} rows do not fit int32 indices")
        indptr = (self._vertex[6] if self._vertex is not None
                  else np.searchsorted(keys, np.arange(n + 1, dtype=np.int64) * n))
        indices = np.empty(keys.size, dtype=np.int32)
        for r0 in range(0, n, self._CSR_ROWS):
            r1 = min(n, r0 + self._CSR_ROWS)
            s, e = int(indptr[r0]), int(indptr[r1])
            row_keys = np.repeat(np.arange(r0 * n, r1 * n, n, dtype=np.int64), np.diff(indptr[r0:r1 + 1]))
            indices[s:e] = keys[s:e] - row_keys
        self._csr = (indptr.astype(np.int32), indices)
        return self._csr

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
        runs = self.slot_runs(vertices)
        if not runs:
            m = vertices.shape[1]
            return np.zeros((0, 3 * m, 3 * m), dtype=np.int32)
        return joined(runs)

    def slot_runs(self, vertices: np.ndarray) -> list[tuple[np.ndarray, np.ndarray | None]]:
        """:meth:`slot_map` of ``vertices`` ``(k, m)`` in runs, in element order: ``(table, offsets)``, where
        ``table`` is the int32 slot map ``(k0, 3 m, 3 m)`` of the run's first chunk of ``k0`` elements and
        ``offsets`` int32 ``(P,)`` the slot shifts of its ``P`` translated chunks (a stacked scene's copies:
        the run's map is :func:`~sim_core.slot_translation.translated` of the two), or None where ``table`` is
        the map of the run's elements themselves. A caller that derives a table from the slot map entry by
        entry, moving with the slots, derives it from each run's ``table`` only.

        Raises:
            ValueError: a kept entry that is not in the pattern (its elements were not part of it).
        """
        vertices = np.asarray(vertices)
        k, m = vertices.shape
        if self._vertex is None:
            rows, cols = block_keys(vertices, self.dof_count)
            return [(self.lookup(rows, cols).reshape(k, 3 * m, 3 * m), None)]
        runs, at = [], 0
        while at < k:  # runs of translated chunks (a stacked scene's copies: sim_core.batch.stacked), each
            run = self._translated_chunks(vertices[at:])  # made from its first chunk, moved
            if run is None:
                runs.append((self._pair_slot_map(vertices[at:]), None))
                break
            k0, offsets = run
            runs.append((self._pair_slot_map(vertices[at:at + k0]), offsets))
            at += k0 * offsets.size
        return runs

    _CHUNK_TRIES = 16
    """Chunk lengths :meth:`_translated_chunks` tries at most."""

    def _translated_chunks(self, vertices: np.ndarray) -> tuple[int, np.ndarray] | None:
        """``(k0, offsets)`` when the element array ``vertices`` ``(k, m)`` begins with ``P >= 2`` chunks of
        ``k0`` elements, chunk ``j`` being chunk 0 with every vertex index moved by one shift ``s_j`` (a
        stacked scene's copies of one body), and the pattern's rows of chunk 0's vertices, moved by ``s_j``,
        are those rows moved by ``s_j`` (same free and own-block kinds, the same keys moved by ``3 s_j`` in
        row and column), starting ``offsets[j]`` slots later (int32 ``(P,)``); else None. Then every slot of
        chunk ``j`` is chunk 0's plus ``offsets[j]`` (slots are row starts plus ranks within the row). Chunk
        lengths are tried shortest first (at most :attr:`_CHUNK_TRIES`), each with its longest run of
        chunks."""
        k, m = vertices.shape
        if k < 4 or m == 0:
            return None
        v = vertices.astype(np.int64)
        moved = v - v[0]
        # chunk lengths L: element L is element 0 moved by a shift larger than the span of elements 0 .. L - 1
        # (chunks share no vertex, as stacked copies)
        span = np.maximum.accumulate(v.max(axis=1)) - np.minimum.accumulate(v.min(axis=1))
        lengths = np.flatnonzero(np.all(moved == moved[:, :1], axis=1))
        lengths = lengths[(lengths > 0) & (lengths <= k // 2)]
        shift = moved[lengths, :1]  # (c, 1); the second chunk's first, second and last elements must be moved alike
        alike = (np.all(v[lengths + 1] - v[1] == shift, axis=1)
                 & np.all(v[2 * lengths - 1] - v[lengths - 1] == shift, axis=1))
        lengths = lengths[alike & (shift[:, 0] > span[lengths - 1])][: self._CHUNK_TRIES]
        for k0 in lengths:
            k0 = int(k0)
            chunks = v[: k - k % k0].reshape(k // k0, k0, m)
            shifts = chunks[:, 0, 0] - v[0, 0]
            same = np.all(chunks - shifts[:, None, None] == chunks[0], axis=(1, 2))
            count = int(np.argmin(same)) if not same.all() else same.size  # the leading run of translated chunks
            if count < 2:
                continue
            offsets = self._translated_rows(np.unique(chunks[0]), shifts[:count])
            if offsets.size >= 2:
                return k0, offsets
        return None

    def _translated_rows(self, u: np.ndarray, shifts: np.ndarray) -> np.ndarray:
        """The slot offsets (int32) of the leading run of ``shifts`` ``(P,)`` (``shifts[0] = 0``) for which
        the rows of vertices ``u`` moved by the shift are the rows of ``u`` moved (:meth:`_translated_chunks`);
        its length is the run's."""
        N, vertex_free, full, own, pairs, pair_start, indptr = self._vertex
        n = self.dof_count
        inside = (shifts + u.min() >= 0) & (shifts + u.max() < N)
        shifts = shifts[: int(np.argmin(inside)) if not inside.all() else inside.size]
        moved = u[None, :] + shifts[:, None]  # (P, U)
        ok = np.all(vertex_free[moved] == vertex_free[u], axis=1) & np.all(full[moved] == full[u], axis=1)
        rows0 = (3 * u[:, None] + np.arange(3)).ravel()  # (R,)
        rows = rows0[None, :] + 3 * shifts[:, None]  # (P, R)
        start0, length0 = indptr[rows0], indptr[rows0 + 1] - indptr[rows0]
        offsets = indptr[rows] - start0  # (P, R): one offset per chunk, or the rows are not translated
        ok &= np.all(indptr[rows + 1] - indptr[rows] == length0, axis=1) & np.all(offsets == offsets[:, :1], axis=1)
        ok &= offsets[:, 0] + int(self.keys.size) <= np.iinfo(np.int32).max
        count = int(np.argmin(ok)) if not ok.all() else ok.size
        pos0 = (np.repeat(start0, length0) + np.arange(int(length0.sum()))
                - np.repeat(np.cumsum(length0) - length0, length0))
        keys0 = self.keys[pos0]
        for j in range(count):  # one chunk at a time: no (P, entries) temporaries
            if not np.array_equal(self.keys[pos0 + offsets[j, 0]], keys0 + 3 * shifts[j] * (n + 1)):
                count = j
                break
        return offsets[:count, 0].astype(np.int32)

    def _pair_slot_map(self, vertices: np.ndarray) -> np.ndarray:
        """:meth:`slot_map` by vertex pairs (the tables of :meth:`_by_vertex_pairs`)."""
        k, m = vertices.shape
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
