"""Sparse assembly of projected Hessian blocks with a cached sparsity pattern.

The elastic potentials keep the same elements from step to step, so the map from their block
entries to the non-zeros of the CSR matrix is computed once (sort + unique of the linear indices)
and every later assembly is one ``np.bincount`` (no COO -> CSR conversion, no index sort). Contact
and friction blocks change every iteration and are assembled by plain COO -> CSR and added.
Dirichlet DoFs are eliminated by zeroing their rows and columns and putting 1 on the diagonal.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import scipy.sparse as sp

from sim_core.potentials.base import HessianBlocks, assemble_hessian, block_dof_indices


class _Pattern:
    """CSR pattern of a fixed list of element-vertex arrays plus the full diagonal."""

    def __init__(self, vertex_arrays: Sequence[np.ndarray], dof_count: int) -> None:
        rows, cols = [], []
        for v in vertex_arrays:
            dofs = block_dof_indices(v)
            n = dofs.shape[1]
            rows.append(np.repeat(dofs, n, axis=1).reshape(-1))
            cols.append(np.tile(dofs, (1, n)).reshape(-1))
        idx = np.arange(dof_count)
        rows.append(idx)
        cols.append(idx)
        lin = np.concatenate(rows).astype(np.int64) * dof_count + np.concatenate(cols)
        uniq, inverse = np.unique(lin, return_inverse=True)
        self.scatter = inverse.astype(np.int64)
        self.nnz = int(uniq.size)
        self.row = uniq // dof_count
        self.col = uniq % dof_count
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(self.row, minlength=dof_count))]).astype(np.int64)
        self.indices = self.col.astype(np.int32 if dof_count < 2**31 else np.int64)
        self.diag_slots = self.scatter[-dof_count:]
        self.dof_count = dof_count
        self._free_key: bytes | None = None

    def fixed_entries(self, free: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Masks over the non-zeros: entries in a fixed row or column, and fixed diagonal slots."""
        key = np.packbits(free).tobytes()
        if key != self._free_key:
            self._fixed = ~(free[self.row] & free[self.col])
            self._fixed_diag = self.diag_slots[~free]
            self._free_key = key
        return self._fixed, self._fixed_diag


class HessianAssembler:
    """Assemble ``static`` blocks (cached pattern) + ``dynamic`` blocks + a diagonal into CSR.

    Args:
        dof_count: ``3 * vertex_count``.
    """

    def __init__(self, dof_count: int) -> None:
        self.dof_count = dof_count
        self._key: tuple | None = None
        self._pattern: _Pattern | None = None

    def assemble(
        self,
        static: Sequence[HessianBlocks],
        dynamic: Sequence[HessianBlocks],
        diagonal: np.ndarray,
        free: np.ndarray,
    ) -> sp.csr_matrix:
        """Constrained Hessian ``D H D + (I - D)`` with ``D = diag(free)``.

        Args:
            static: blocks whose ``vertices`` arrays are the same objects every call (elastic terms).
            dynamic: blocks that change (contact, friction).
            diagonal: extra diagonal, shape ``(dof_count,)`` (inertia, damping).
            free: free-DoF mask, shape ``(dof_count,)`` bool.

        Returns:
            CSR matrix ``(dof_count, dof_count)`` with sorted indices.
        """
        key = tuple((id(b.vertices), b.vertices.shape) for b in static)
        if key != self._key:
            self._pattern = _Pattern([b.vertices for b in static], self.dof_count)
            self._key = key
            self._keep_alive = [b.vertices for b in static]
        pat = self._pattern
        vals = np.concatenate([b.blocks.reshape(-1) for b in static] + [np.asarray(diagonal, dtype=float)])
        data = np.bincount(pat.scatter, weights=vals, minlength=pat.nnz)
        fixed, fixed_diag = pat.fixed_entries(free)
        data[fixed] = 0.0
        data[fixed_diag] = 1.0
        H = sp.csr_matrix((data, pat.indices, pat.indptr), shape=(self.dof_count, self.dof_count))
        parts = [b for b in dynamic if b.blocks.shape[0]]
        if parts:
            C = assemble_hessian(parts, self.dof_count)
            D = sp.diags(free.astype(float))
            H = (H + D @ C @ D).tocsr()
            H.sort_indices()
        return H
