"""Uniform-grid spatial hash over axis-aligned bounding boxes (broad phase).

Items (boxes) are binned into every grid cell they overlap; a query box visits the cells it overlaps
and reports the items found there whose box overlaps it. A pair of overlapping boxes shares several
cells; it is reported only from the cell that contains the lower corner of the boxes' intersection
``max(lo_query, lo_item)``, which is unique, so no de-duplication pass is needed (Teschner et al.,
"Optimized Spatial Hashing for Collision Detection of Deformable Objects", VMV 2003, for the hash;
the lower-corner rule is the usual one of grid broad phases). With a cell size of the order of the
box size every box covers O(1) cells and the expected work is linear in the number of boxes plus
reported pairs (up to the sort of the cell keys).
"""

from __future__ import annotations

import numpy as np

from sim_core.errors import ConfigError, SimulationDivergedError

_OFFSET = 1 << 20  # cell coordinates are packed as 21-bit unsigned fields of one int64 key
_CELL_LIMIT = float(1 << 18)  # hash_cell_size keeps |cell index| <= 2^18 + 1
_WIDEST_CELLS = 256.0  # hash_cell_size: the widest box overlaps at most 257 cells per axis


def hash_cell_size(box_min: np.ndarray, box_max: np.ndarray, reach: float, radius: float) -> float:
    """Cell size of a hash over boxes ``(k, 3)`` (m) queried with boxes inflated by ``radius`` (m).

    ``max(mean_k max_d w_kd + 2 radius, (w_max + 2 radius) / 256, (reach + radius) / 2^18)`` with
    box widths ``w``: about one inflated box per cell, at most 257 cells per axis for the widest box,
    and cell indices within 2^18 + 1 for coordinates up to ``reach`` (the largest |coordinate| of all
    boxes, queries included), so that zero-size boxes and a zero radius still give a usable grid.
    The rule of the Taichi kernel :mod:`sim_core.ti_kernels.hash_grid`.
    """
    width = np.max(box_max - box_min, axis=1) if len(box_min) else np.zeros(1)
    cell = max(float(np.mean(width)) + 2.0 * radius, (float(np.max(width)) + 2.0 * radius) / _WIDEST_CELLS,
               (float(reach) + radius) / _CELL_LIMIT)
    return cell if cell > 0.0 else 1.0


MAX_COVERED_CELLS = 1 << 22
"""Cells all boxes of one hash may cover together before the positions count as diverged (with
:data:`CELLS_PER_BOX` times the box count when that is larger)."""

CELLS_PER_BOX = 64
"""Mean cells per box above which the positions count as diverged (boxes about the cell size cover 1-8)."""


def _cell_keys(cells: np.ndarray) -> np.ndarray:
    c = cells + _OFFSET
    return (c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2]


class SpatialHash:
    """Spatial hash of a set of axis-aligned boxes.

    Args:
        box_min: lower corners in m, shape ``(k, 3)``.
        box_max: upper corners in m, shape ``(k, 3)``.
        cell_size: grid spacing in m (> 0).

    Raises:
        ConfigError: non-positive cell size, non-finite boxes, or a scene so large relative to the
            cell size that cell coordinates exceed 2^20.
    """

    def __init__(self, box_min: np.ndarray, box_max: np.ndarray, cell_size: float) -> None:
        if not (np.isfinite(cell_size) and cell_size > 0):
            raise ConfigError(f"spatial hash: cell_size must be finite and > 0 (m), got {cell_size}")
        self.cell_size = float(cell_size)
        self.box_min = np.asarray(box_min, dtype=float)
        self.box_max = np.asarray(box_max, dtype=float)
        items, cells = self._covered_cells(self.box_min, self.box_max)
        keys = _cell_keys(cells)
        order = np.argsort(keys, kind="stable")
        self._keys = keys[order]
        self._items = items[order]

    def _cell_range(self, box_min: np.ndarray, box_max: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if not (np.all(np.isfinite(box_min)) and np.all(np.isfinite(box_max))):
            raise ConfigError("spatial hash: bounding boxes contain NaN or infinite coordinates")
        lo = np.floor(box_min / self.cell_size).astype(np.int64)
        hi = np.floor(box_max / self.cell_size).astype(np.int64)
        if lo.size and (lo.min() <= -_OFFSET or hi.max() >= _OFFSET - 1):
            raise ConfigError(
                f"spatial hash: scene extent too large for cell_size {self.cell_size:g} m (cell index beyond 2^20)"
            )
        return lo, hi

    def _covered_cells(self, box_min: np.ndarray, box_max: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(box index, cell) for every cell each box overlaps; shapes (m,), (m, 3)."""
        lo, hi = self._cell_range(box_min, box_max)
        extent = hi - lo + 1
        counts = np.prod(extent, axis=1)
        total = int(counts.sum())
        if total > max(MAX_COVERED_CELLS, CELLS_PER_BOX * lo.shape[0]):
            # elements stretched far beyond the cell size: a diverging iterate (e.g. a line-search
            # trial point), not a geometry worth hashing (it would need GiBs of cell lists)
            raise SimulationDivergedError(
                f"spatial hash: {lo.shape[0]} boxes cover {total} cells of {self.cell_size:g} m "
                f"(largest box {int(counts.max())} cells): the positions have diverged")
        owner = np.repeat(np.arange(lo.shape[0]), counts)
        start = np.cumsum(counts) - counts
        local = np.arange(owner.shape[0]) - np.repeat(start, counts)
        ex = extent[owner]
        ix = local % ex[:, 0]
        iy = (local // ex[:, 0]) % ex[:, 1]
        iz = local // (ex[:, 0] * ex[:, 1])
        return owner, lo[owner] + np.stack([ix, iy, iz], axis=1)

    def query(self, box_min: np.ndarray, box_max: np.ndarray) -> np.ndarray:
        """Pairs (query box, item box) whose closed boxes overlap, each reported once.

        Args:
            box_min, box_max: query boxes in m, shape ``(q, 3)``.

        Returns:
            int64 array of shape ``(p, 2)``: ``[query index, item index]``.
        """
        box_min = np.asarray(box_min, dtype=float)
        box_max = np.asarray(box_max, dtype=float)
        owner, cells = self._covered_cells(box_min, box_max)
        keys = _cell_keys(cells)
        left = np.searchsorted(self._keys, keys, side="left")
        right = np.searchsorted(self._keys, keys, side="right")
        counts = right - left
        q = np.repeat(owner, counts)
        cell = np.repeat(cells, counts, axis=0)
        start = np.cumsum(counts) - counts
        pos = np.arange(q.shape[0]) - np.repeat(start, counts) + np.repeat(left, counts)
        item = self._items[pos]
        overlap = np.all(
            (box_min[q] <= self.box_max[item]) & (self.box_min[item] <= box_max[q]), axis=1
        )
        corner = np.floor(np.maximum(box_min[q], self.box_min[item]) / self.cell_size).astype(np.int64)
        keep = overlap & np.all(corner == cell, axis=1)
        return np.stack([q[keep], item[keep]], axis=1).astype(np.int64)
