"""Per-copy reductions and expansions on a stacked scene's arrays, without gathering the copies' DoFs.

A stacked model (:mod:`sim_core.batch.stacked`) lays its vertices out body-major: copy ``i``'s vertices of
one body are one contiguous run of stacked vertices, so the ``N`` stacked vertices are a few runs per copy
(one per body). Consecutive runs of one length (a body's runs over the copies of a material group) are the
rows of a *block*, a 2-D view of the stacked array (``a[3 v0: 3 v0 + 3 m s].reshape(m, 3 s)``: ``m`` runs of
``s`` vertices). :class:`CopyRuns` holds those blocks and computes what the lockstep Newton iteration needs
per copy (dot products, largest norms, finiteness, the step sizes spread over the DoFs, updates of whole
copies) with one pass over the stacked array in its own order (row reductions of each block's view, then
one small reduction over the runs of each copy), instead of gathering every copy's DoFs into a ``(B, 3 n)``
array first (``x[dof_index]``: an indexed copy of the whole array at each use) and without temporaries of
the stacked array's size.

Sums are taken in another order than a sum over the gathered ``(B, 3 n)`` rows, so they agree with it to
round-off, not bit for bit.
"""

from __future__ import annotations

import numpy as np


class CopyRuns:
    """The runs of consecutive stacked vertices that belong to one copy, grouped in blocks (module docstring).

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
        blocks: ``(first run, first vertex, runs m, vertices a run s)`` of each block of consecutive runs of
            one length, in stacked order (they tile ``0 .. N - 1``).
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
        first = np.flatnonzero(np.r_[True, self.lengths[1:] != self.lengths[:-1]]) if N else np.zeros(0, np.int64)
        ends = np.r_[first[1:], len(self.starts)]
        self.blocks = [(int(r0), int(self.starts[r0]), int(r1 - r0), int(self.lengths[r0]))
                       for r0, r1 in zip(first, ends)]

    def _rows(self, a: np.ndarray, width: int = 3) -> list[np.ndarray]:
        """Each block's view of the stacked ``a`` (``width`` entries a vertex), shape ``(m, width s)``."""
        flat = a.reshape(-1)
        return [flat[width * v0: width * (v0 + m * s)].reshape(m, width * s) for _, v0, m, s in self.blocks]

    def _per_run(self, parts: list[np.ndarray]) -> np.ndarray:
        return np.concatenate(parts) if parts else np.zeros(0)

    def _row_copies(self, values: np.ndarray) -> list[np.ndarray]:
        """Per-copy ``values`` ``(B,)`` at each block's rows (runs), one ``(m,)`` array a block."""
        at = np.asarray(values)[self.run_copy]
        return [at[r0:r0 + m] for r0, _, m, _ in self.blocks]

    def dot(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Per copy ``sum_k a_k b_k`` over its DoFs, shape ``(B,)``, of stacked arrays ``a``, ``b`` of ``3 N``
        entries (any shape of that size)."""
        per_run = self._per_run([np.einsum("ij,ij->i", ra, rb) for ra, rb in zip(self._rows(a), self._rows(b))])
        return np.bincount(self.run_copy, weights=per_run, minlength=self.copies)

    def any_dof(self, mask: np.ndarray) -> np.ndarray:
        """Per copy whether any of its ``3 n`` DoFs is set (non-zero) in ``mask`` (``3 N`` entries, bool or a
        number: a NaN counts as set), shape ``(B,)``."""
        out = np.zeros(self.copies, dtype=bool)
        if self.vertex_count:
            np.logical_or.at(out, self.run_copy, self._per_run([r.any(axis=1) for r in self._rows(mask)]))
        return out

    def all_finite(self, a: np.ndarray) -> np.ndarray:
        """Per copy whether all its DoFs of the stacked array ``a`` (``3 N`` entries) are finite, shape ``(B,)``.
        One pass: a run whose sum is finite has only finite entries; the runs whose sum is not (a NaN or an
        infinity, or finite entries whose sum overflows) are tested entry by entry."""
        out = np.ones(self.copies, dtype=bool)
        if not self.vertex_count:
            return out
        rows = self._rows(a)
        for (r0, _, _, _), r in zip(self.blocks, rows):
            sums = r.sum(axis=1)
            for k in np.flatnonzero(~np.isfinite(sums)):
                out[self.run_copy[r0 + k]] &= bool(np.isfinite(r[k]).all())
        return out

    def largest_norm(self, d: np.ndarray) -> np.ndarray:
        """Per copy the largest vertex norm ``max_v |d_v|`` of the stacked ``d`` (``(N, 3)`` or ``3 N``
        entries), shape ``(B,)``; NaN where a copy's ``d`` is not finite (a NaN or an infinity)."""
        out = np.zeros(self.copies)
        if not self.vertex_count:
            return out
        parts = []
        for r, (_, _, m, s) in zip(self._rows(d), self.blocks):
            v = r.reshape(m, s, 3)
            sq = v[..., 0] * v[..., 0]
            sq += v[..., 1] * v[..., 1]
            sq += v[..., 2] * v[..., 2]
            parts.append(sq.max(axis=1))  # a NaN propagates
        with np.errstate(invalid="ignore"):  # a NaN is the answer for its copy
            np.maximum.at(out, self.run_copy, self._per_run(parts))
        out[~np.isfinite(out)] = np.nan
        return np.sqrt(out)

    def largest_abs(self, a: np.ndarray) -> np.ndarray:
        """Per copy ``max_k |a_k|`` over its DoFs of the stacked ``a`` (``3 N`` entries), shape ``(B,)``: NaN where a
        copy's ``a`` has a NaN, infinite where it has an infinity and no NaN (so it also tells finite copies)."""
        out = np.zeros(self.copies)
        if self.vertex_count:
            per_run = self._per_run([np.maximum(r.max(axis=1), -r.min(axis=1)) for r in self._rows(a)])
            with np.errstate(invalid="ignore"):  # a NaN is the answer for its copy
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
        out = np.empty((self.vertex_count, 3))
        for o, rx, rd, al in zip(self._rows(out), self._rows(x), self._rows(d), self._row_copies(alphas)):
            np.multiply(rd, al[:, None], out=o)
            o += rx
        return out

    def zero_copies(self, a: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """``a`` (``3 N`` entries) with the DoFs of the copies in ``mask`` (bool ``(B,)``) set to 0, in place;
        returns ``a``."""
        for r, m in zip(self._rows(a), self._row_copies(mask)):
            r[m] = 0.0
        return a

    def copy_where(self, dst: np.ndarray, src: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """``dst`` (``3 N`` entries) with the DoFs of the copies in ``mask`` (bool ``(B,)``) taken from ``src``
        (same size), in place; returns ``dst``."""
        for rd, rs, m in zip(self._rows(dst), self._rows(src), self._row_copies(mask)):
            rd[m] = rs[m]
        return dst
