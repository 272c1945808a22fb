"""The static part of the Newton matrix's sparsity pattern: the upper-triangle entries of fixed
element-vertex arrays plus the full diagonal, for one free mask (:class:`StaticPattern`), and the
DoF keys of Hessian blocks (:func:`block_keys`), shared by :mod:`sim_core.assembly` and
:mod:`sim_core.dynamic_slots`."""

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
