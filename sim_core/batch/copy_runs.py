"""Per-copy reductions and expansions on a stacked scene's arrays, without gathering the copies' DoFs.

A stacked model (:mod:`sim_core.batch.stacked`) lays its vertices out body-major: copy ``i``'s vertices of
one body are one contiguous run of stacked vertices, so the ``N`` stacked vertices are a few runs per copy
(one per body). :class:`CopyRuns` holds those runs and computes what the lockstep Newton iteration needs per
copy (dot products, largest norms, finiteness, the step sizes spread over the DoFs) with one pass over the
stacked array in its own order (``np.ufunc.reduceat`` over the runs, then one small sum over the runs of
each copy), instead of gathering every copy's DoFs into a ``(B, 3 n)`` array first (``x[dof_index]``: an
indexed copy of the whole array at each use).

Sums are taken in another order than a sum over the gathered ``(B, 3 n)`` rows, so they agree with it to
round-off, not bit for bit.
"""

from __future__ import annotations

import numpy as np


class CopyRuns:
    """The runs of consecutive stacked vertices that belong to one copy.

    Args:
        index: stacked vertex of copy ``i``'s vertex ``v``, shape ``(B, n)`` int (every stacked vertex is
            one copy's: ``B n`` distinct values ``0 .. B n - 1``).

    Raises:
        ValueError: ``index`` is not a permutation of ``0 .. B n - 1``.

    Attributes:
        copies: ``B``.
        vertex_count: stacked vertices ``N = B n``.
        starts: first stacked vertex of each run, shape ``(R,)`` int64, increasing.
        lengths: vertices of each run, shape ``(R,)`` int64.
        run_copy: the copy of each run, shape ``(R,)`` int64.
    """

    def __init__(self, index: np.ndarray) -> None:
        index = np.asarray(index)
        B, n = index.shape
        N = B * n
        copy_of = np.full(N, -1, dtype=np.int64)
        if N:
            flat = index.reshape(-1)
            if flat.min() < 0 or flat.max() >= N:
                raise ValueError(f"CopyRuns: stacked vertex indices outside 0..{N - 1}")
            copy_of[flat] = np.repeat(np.arange(B), n)
            if np.any(copy_of < 0):
                raise ValueError("CopyRuns: the copies' vertex indices are not a permutation of the stacked vertices")
        self.copies = B
        self.vertex_count = N
        self.starts = np.flatnonzero(np.r_[True, copy_of[1:] != copy_of[:-1]]) if N else np.zeros(0, np.int64)
        self.lengths = np.diff(np.r_[self.starts, N]).astype(np.int64)
        self.run_copy = copy_of[self.starts]
        self._dof_starts = 3 * self.starts

    def _per_copy(self, per_run: np.ndarray) -> np.ndarray:
        return np.bincount(self.run_copy, weights=per_run, minlength=self.copies)

    def dot(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Per copy ``sum_k a_k b_k`` over its DoFs, shape ``(B,)``, of stacked arrays ``a``, ``b`` of ``3 N``
        entries (any shape of that size)."""
        if not self.vertex_count:
            return np.zeros(self.copies)
        return self._per_copy(np.add.reduceat(np.multiply(a.reshape(-1), b.reshape(-1)), self._dof_starts))

    def any_dof(self, mask: np.ndarray) -> np.ndarray:
        """Per copy whether any of its ``3 n`` DoFs is set in ``mask`` (bool, ``3 N`` entries), shape ``(B,)``."""
        if not self.vertex_count:
            return np.zeros(self.copies, dtype=bool)
        out = np.zeros(self.copies, dtype=bool)
        np.logical_or.at(out, self.run_copy, np.logical_or.reduceat(mask.reshape(-1), self._dof_starts))
        return out

    def all_finite(self, a: np.ndarray) -> np.ndarray:
        """Per copy whether all its DoFs of the stacked array ``a`` (``3 N`` entries) are finite, shape ``(B,)``.
        One pass: a run whose sum is finite has only finite entries; the runs whose sum is not (a NaN or an
        infinity, or finite entries whose sum overflows) are tested entry by entry."""
        if not self.vertex_count:
            return np.ones(self.copies, dtype=bool)
        flat = a.reshape(-1)
        finite_run = np.isfinite(np.add.reduceat(flat, self._dof_starts))
        for r in np.flatnonzero(~finite_run):
            start = self._dof_starts[r]
            finite_run[r] = np.isfinite(flat[start:start + 3 * self.lengths[r]]).all()
        out = np.ones(self.copies, dtype=bool)
        np.logical_and.at(out, self.run_copy, finite_run)
        return out

    def largest_norm(self, d: np.ndarray) -> np.ndarray:
        """Per copy the largest vertex norm ``max_v |d_v|`` of the stacked ``d`` (``(N, 3)`` or ``3 N``
        entries), shape ``(B,)``; NaN where a copy's ``d`` has a NaN."""
        if not self.vertex_count:
            return np.zeros(self.copies)
        d3 = d.reshape(-1, 3)
        sq = d3[:, 0] * d3[:, 0] + d3[:, 1] * d3[:, 1] + d3[:, 2] * d3[:, 2]
        per_run = np.fmax.reduceat(sq, self.starts)
        out = np.zeros(self.copies)
        np.fmax.at(out, self.run_copy, per_run)
        out[~self.all_finite(d)] = np.nan
        return np.sqrt(out)

    def largest_abs(self, a: np.ndarray) -> np.ndarray:
        """Per copy ``max_k |a_k|`` over its DoFs of the stacked ``a`` (``3 N`` entries), shape ``(B,)``."""
        if not self.vertex_count:
            return np.zeros(self.copies)
        per_run = np.maximum.reduceat(np.abs(a.reshape(-1)), self._dof_starts)
        out = np.zeros(self.copies)
        np.maximum.at(out, self.run_copy, per_run)
        return out

    def per_vertex(self, values: np.ndarray) -> np.ndarray:
        """Per-copy ``values`` ``(B,)`` spread over the stacked vertices, shape ``(N,)``."""
        return np.repeat(np.asarray(values)[self.run_copy], self.lengths)

    def per_dof(self, values: np.ndarray) -> np.ndarray:
        """Per-copy ``values`` ``(B,)`` spread over the stacked DoFs, shape ``(3 N,)``."""
        return np.repeat(np.asarray(values)[self.run_copy], 3 * self.lengths)

    def moved(self, x: np.ndarray, d: np.ndarray, alphas: np.ndarray) -> np.ndarray:
        """``x + alpha_i d`` on copy ``i``'s vertices (m, a new ``(N, 3)`` array), ``x`` and ``d`` stacked
        ``(N, 3)``, ``alphas`` ``(B,)``."""
        return x + self.per_vertex(alphas)[:, None] * d.reshape(-1, 3)
