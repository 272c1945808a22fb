"""Sparse assembly of Hessian blocks into the upper triangle of the constrained Newton matrix.

The Newton matrix is ``D H D + (I - D)`` with ``D = diag(free)``: Dirichlet DoFs are eliminated by
dropping their rows and columns and putting 1 on their diagonal. It is symmetric, so only its upper
triangle (``row <= col``, full diagonal) is assembled, the input of the Cholesky solver
(:class:`sim_core.linsolve.PardisoCholesky`).

Patterns are cached as maps from block entries to CSR slots, so an assembly is a few
``np.bincount`` calls (no COO -> CSR conversion, no index sort):

* static blocks (elastic terms, the same elements every call, recognised by the identity of their
  ``vertices`` arrays) + the diagonal: one map, rebuilt when the arrays or the free mask change;
* dynamic blocks (contact, friction: the active pairs change): their entries are mapped into a
  union pattern "static + recently used dynamic entries", which is rebuilt only when an entry
  that is not in it appears; dynamic entries stay in it (as structural zeros) until they have been
  unused for :data:`STICKY_ASSEMBLIES` assemblies. So the pattern, and with it the linear solver's
  symbolic analysis, changes far less often than the active contact set (contacts that come and go
  between Newton iterations). :mod:`sim_core.dynamic_slots` keeps the slots of the dynamic elements
  seen so far, so a merge maps only new elements and a rebuild translates the old pattern.

Fused kernels (:mod:`sim_core.fused_elastic`) skip the per-element blocks: they get the static
pattern (:meth:`HessianAssembler.static_pattern`) and its per-element slot maps
(:meth:`StaticPattern.slot_map`), add their Hessian entries straight into the static value array,
and :meth:`HessianAssembler.assemble_upper_values` merges that array with the dynamic blocks.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import scipy.sparse as sp

from sim_core.dynamic_slots import STICKY_ASSEMBLIES, DynamicMerge, block_keys  # noqa: F401 (documented here)
from sim_core.potentials.base import HessianBlocks
from sim_core.unique import sorted_unique


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
            r, c = block_keys(v, dof_count)
            rows.append(r)
            cols.append(c)
        idx = np.arange(dof_count)
        rows.append(idx)
        cols.append(idx)
        r = np.concatenate(rows).astype(np.int64)
        c = np.concatenate(cols).astype(np.int64)
        keep = ((r < c) & free[r] & free[c]) | (r == c)
        self.entry_index = np.flatnonzero(keep)
        self.keys, self.slot = sorted_unique(r[keep] * dof_count + c[keep], return_inverse=True)
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
        rows, cols = block_keys(np.asarray(vertices), self.dof_count)
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
        self._dynamic = DynamicMerge(dof_count)

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
        return self._static

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
        return self._dynamic.merge(pat, static_data, dynamic, free)

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
        return self._dynamic.merge_values(pattern, static_values, diagonal, dynamic, free)
