"""Sparse assembly of Hessian blocks into the upper triangle of the constrained Newton matrix.

The Newton matrix is ``D H D + (I - D)`` with ``D = diag(free)``: Dirichlet DoFs are eliminated by
dropping their rows and columns and putting 1 on their diagonal. It is symmetric, so only its upper
triangle (``row <= col``, full diagonal) is assembled, the input of the Cholesky solver
(:class:`sim_core.linsolve.PardisoCholesky`).

Patterns are cached as maps from block entries to CSR slots, so an assembly is a few
``np.bincount`` calls (no COO -> CSR conversion, no index sort):

* static blocks (elastic terms, the same elements every call, recognised by the identity of their
  ``vertices`` arrays) + the diagonal: one map, rebuilt when the arrays or the free mask change;
* dynamic blocks (contact, friction: the active pairs change): the sorted unique keys of their
  kept entries are compared with the last call's; the union pattern with the static one and both
  maps into it are rebuilt only when they differ (the active set is usually stable over the last
  Newton iterations of a step, and the linear solver then also keeps its symbolic analysis).

Fused kernels (:mod:`sim_core.fused_elastic`) skip the per-element blocks: they get the static
pattern (:meth:`HessianAssembler.static_pattern`) and its per-element slot maps
(:meth:`StaticPattern.slot_map`), add their Hessian entries straight into the static value array,
and :meth:`HessianAssembler.assemble_upper_values` merges that array with the dynamic blocks.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import scipy.sparse as sp

from sim_core.potentials.base import HessianBlocks, block_dof_indices


def _block_keys(vertices: np.ndarray, dof_count: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column DoF of every entry of blocks over ``vertices`` ``(k, m)``, each ``(k (3m)^2,)``."""
    dofs = block_dof_indices(vertices)
    n = dofs.shape[1]
    rows = np.repeat(dofs, n, axis=1).reshape(-1)
    cols = np.tile(dofs, (1, n)).reshape(-1)
    return rows, cols


class StaticPattern:
    """Upper-triangle pattern of fixed element-vertex arrays plus the full diagonal, for one free mask.

    An entry ``(row, col)`` of an element block is kept when ``row < col`` and both DoFs are free,
    or ``row == col`` (the diagonal; fixed DoFs get 1 there).

    Attributes:
        keys: sorted unique linear keys ``row * n + col`` of the kept entries, shape ``(nnz,)``.
        entry_index: positions of the kept entries in the concatenated block values (blocks in
            order, then the diagonal), shape ``(kept,)``.
        slot: CSR slot of each kept entry, shape ``(kept,)``.
        diag_slots: slot of every diagonal entry, shape ``(dof_count,)``.
        fixed_diag_slots: slots of the diagonal entries of fixed DoFs.
    """

    def __init__(self, vertex_arrays: Sequence[np.ndarray], free: np.ndarray, dof_count: int) -> None:
        self.dof_count = dof_count
        self.free = free
        rows, cols = [], []
        for v in vertex_arrays:
            r, c = _block_keys(v, dof_count)
            rows.append(r)
            cols.append(c)
        idx = np.arange(dof_count)
        rows.append(idx)
        cols.append(idx)
        r = np.concatenate(rows).astype(np.int64)
        c = np.concatenate(cols).astype(np.int64)
        keep = ((r < c) & free[r] & free[c]) | (r == c)
        self.entry_index = np.flatnonzero(keep)
        self.keys, self.slot = np.unique(r[keep] * dof_count + c[keep], return_inverse=True)
        self.diag_slots = np.searchsorted(self.keys, idx * dof_count + idx)
        self.fixed_diag_slots = self.diag_slots[~free]

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
        """
        rows, cols = _block_keys(np.asarray(vertices), self.dof_count)
        k, m = np.asarray(vertices).shape
        return self.lookup(rows, cols).reshape(k, 3 * m, 3 * m)


class HessianAssembler:
    """Assemble ``static`` blocks + ``dynamic`` blocks + a diagonal into the constrained upper triangle.

    Args:
        dof_count: ``3 * vertex_count``.
    """

    def __init__(self, dof_count: int) -> None:
        self.dof_count = dof_count
        self._static_key: tuple | None = None
        self._static: StaticPattern | None = None
        self._keep_alive: list[np.ndarray] = []
        self._dynamic_keys: np.ndarray | None = None
        self._union: tuple | None = None
        self._dynamic_map: tuple | None = None  # (signature, entry index, entry slots, union)

    def static_pattern(self, vertex_arrays: Sequence[np.ndarray], free: np.ndarray) -> StaticPattern:
        """The cached pattern of the static element-vertex arrays (rebuilt when they or ``free`` change).

        Args:
            vertex_arrays: the ``vertices`` arrays of the static blocks, the same objects every call.
            free: free-DoF mask, shape ``(dof_count,)`` bool.
        """
        key = (tuple((id(v), v.shape) for v in vertex_arrays), np.packbits(free).tobytes())
        if key != self._static_key:
            self._static = StaticPattern(list(vertex_arrays), free, self.dof_count)
            self._static_key = key
            self._keep_alive = list(vertex_arrays)  # ids stay unique while referenced
            self._dynamic_keys = None
            self._union = None
        return self._static

    def _union_pattern(self, pat: StaticPattern, dyn_keys: np.ndarray) -> tuple:
        """(static slots, dynamic unique keys -> slots, indptr, indices, nnz) of static U dynamic."""
        if self._union is not None and self._dynamic_keys is not None and np.array_equal(dyn_keys, self._dynamic_keys):
            return self._union
        n = self.dof_count
        # merge two sorted unique key arrays in linear time (no re-sort of the static keys)
        pos = np.minimum(np.searchsorted(pat.keys, dyn_keys), max(pat.keys.size - 1, 0))
        extra = dyn_keys[pat.keys[pos] != dyn_keys] if pat.keys.size else dyn_keys
        keys = np.insert(pat.keys, np.searchsorted(pat.keys, extra), extra)
        static_slots = np.arange(pat.keys.size) + np.searchsorted(extra, pat.keys)
        dynamic_slots = np.searchsorted(keys, dyn_keys)
        rows = keys // n
        indptr = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(np.bincount(rows, minlength=n), out=indptr[1:])
        indices = (keys % n).astype(np.int32)
        self._dynamic_keys = dyn_keys
        self._union = (static_slots, dynamic_slots, indptr, indices, keys.size)
        return self._union

    def assemble_upper(
        self,
        static: Sequence[HessianBlocks],
        dynamic: Sequence[HessianBlocks],
        diagonal: np.ndarray,
        free: np.ndarray,
    ) -> sp.csr_matrix:
        """Upper triangle (with the diagonal) of ``D H D + (I - D)``, ``D = diag(free)``.

        Args:
            static: blocks whose ``vertices`` arrays are the same objects every call (elastic terms).
            dynamic: blocks that change (contact, friction).
            diagonal: extra diagonal, shape ``(dof_count,)`` (inertia, damping).
            free: free-DoF mask, shape ``(dof_count,)`` bool.

        Returns:
            CSR matrix ``(dof_count, dof_count)`` with sorted indices, entries ``row <= col`` only.
        """
        pat = self.static_pattern([b.vertices for b in static], free)
        diagonal = np.asarray(diagonal, dtype=float)
        vals = np.concatenate([b.blocks.reshape(-1) for b in static] + [diagonal])
        static_data = np.bincount(pat.slot, weights=vals[pat.entry_index], minlength=pat.keys.size)
        static_data[pat.fixed_diag_slots] = 1.0
        return self._merge_dynamic(pat, static_data, dynamic, free)

    def assemble_upper_values(
        self,
        pattern: StaticPattern,
        static_values: np.ndarray,
        dynamic: Sequence[HessianBlocks],
        diagonal: np.ndarray,
        free: np.ndarray,
    ) -> sp.csr_matrix:
        """:meth:`assemble_upper` with the static part given as values in ``pattern``'s slots.

        Args:
            pattern: :meth:`static_pattern` of this call's static arrays and ``free``.
            static_values: summed static Hessian entries per slot, shape ``(pattern.keys.size,)``
                (e.g. written by fused kernels through :meth:`StaticPattern.slot_map`); not modified.
            dynamic, diagonal, free: as :meth:`assemble_upper`.
        """
        if pattern is not self._static:
            raise ValueError("assemble_upper_values: pattern is not this assembler's current static pattern")
        static_data = np.array(static_values, dtype=float)
        static_data[pattern.diag_slots] += diagonal
        static_data[pattern.fixed_diag_slots] = 1.0
        return self._merge_dynamic(pattern, static_data, dynamic, free)

    def _merge_dynamic(
        self, pat: StaticPattern, static_data: np.ndarray, dynamic: Sequence[HessianBlocks], free: np.ndarray
    ) -> sp.csr_matrix:
        """The CSR upper triangle of the static values in ``pat``'s slots plus the dynamic blocks.

        The map from the dynamic block entries to the union slots is kept with the blocks' vertex
        arrays (by value): over the last Newton iterations of a step the active pairs repeat, and
        the merge is then one gather and one ``bincount``.
        """
        n = self.dof_count
        blocks = [b for b in dynamic if b.blocks.shape[0]]
        signature = (pat, np.packbits(free).tobytes(), tuple((b.vertices.shape, b.vertices.tobytes()) for b in blocks))
        cached = self._dynamic_map
        if cached is None or cached[0] != signature:
            dyn_r, dyn_c, dyn_keep = [], [], []
            for b in blocks:
                r, c = _block_keys(b.vertices, n)
                keep = (r <= c) & free[r] & free[c]
                dyn_r.append(r[keep])
                dyn_c.append(c[keep])
                dyn_keep.append(keep)
            if blocks:
                lin = np.concatenate(dyn_r) * n + np.concatenate(dyn_c)
                dyn_keys, dyn_slot = np.unique(lin, return_inverse=True)
                entry_index = np.flatnonzero(np.concatenate(dyn_keep))
            else:
                dyn_keys, dyn_slot = np.zeros(0, np.int64), np.zeros(0, np.int64)
                entry_index = np.zeros(0, np.int64)
            union = self._union_pattern(pat, dyn_keys)
            cached = (signature, entry_index, union[1][dyn_slot], union)
            self._dynamic_map = cached
        _, entry_index, dynamic_entry_slots, (static_slots, _, indptr, indices, nnz) = cached
        data = np.zeros(nnz)
        data[static_slots] = static_data
        if blocks:
            values = np.concatenate([b.blocks.reshape(-1) for b in blocks])[entry_index]
            data += np.bincount(dynamic_entry_slots, weights=values, minlength=nnz)
        return sp.csr_matrix((data, indices, indptr), shape=(n, n))
