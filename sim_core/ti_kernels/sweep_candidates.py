"""The contact set's candidate lists with the pair exclusions applied inside the sweep kernel.

:func:`sim_core.collision.candidates.vertex_triangle_candidates` and
:func:`~sim_core.collision.candidates.edge_edge_candidates` find box pairs (on the Taichi backend
with the sweep of :mod:`sim_core.ti_kernels.broad_phase`) and then drop, in NumPy, the pairs that
share a vertex and the same-body pairs closer than the self-contact rest distance (looked up in a
:class:`~sim_core.collision.rest_exclusion.RestExclusion`), and sort the rest. On Forming's
edge-edge search two thirds of the box pairs are dropped, and the dozen array operations cost as
much as the sweep. :class:`SweepCandidates` runs the same sweep (same plan, same inflated-box test)
with a kernel that applies both exclusions before writing a pair: shared vertices by comparing the
elements' vertex indices, the rest distance by a binary search of the pair's key in the sorted
keys of the rest exclusion. Only the kept pairs leave the kernel; they are sorted by one
``np.sort`` of their int64 keys ``first << 32 | second``, the order of the reference's lexsort.
The lists therefore equal the reference's (the body filter is the sweep's ``allowed`` matrix, as
there).
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel and ti.func annotations as
# objects (string annotations are rejected).

import numpy as np

from sim_core.collision.candidates import PairFilter
from sim_core.collision.rest_exclusion import RestExclusion
from sim_core.ti_backend import require_backend, serial_loops, ti
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.broad_phase import SweepSearch
from sim_core.ti_kernels.launch import fast_kernel
from sim_core.ti_kernels.pair_filters import CandidateElements, compile_candidate_kernels, kept_pair

_F64_1, _F64_2, _I32_1, _I32_2 = linalg.F64_1, linalg.F64_2, linalg.I32_1, linalg.I32_2
_I64_1 = ti.types.ndarray(dtype=ti.i64, ndim=1)


@fast_kernel
def _sweep_candidates(a_lo: _F64_2, a_hi: _F64_2, a_body: _I32_1, a_position: _I32_1, a_vertices: _I32_2,
                      a_key: _I32_1, sorted_lo: _F64_2, sorted_hi: _F64_2, sorted_body: _I32_1, b_order: _I32_1,
                      b_vertices: _I32_2, segment: _I32_1, width: _F64_1, slack: _F64_1, body_lo: _F64_2,
                      body_hi: _F64_2, body_axis: _I32_1,
                      allowed: _I32_2, radius: ti.f64, same: ti.i32, rest_keys: _I64_1, out: _I32_2, count: _I32_1):
    """``count[0]`` (set to 0 by the caller) += the number of kept pairs; the first ``out.shape[0]``
    of them in ``out`` as ``[first, second]``: ``[a_key[i], j]`` between two sets, ``[min, max]`` of
    the two indices within one.

    B's boxes are sorted by body, then by lower bound on the body's sweep axis ``body_axis[k]``
    (body ``k`` in the sorted rows ``segment[k] <= s < segment[k + 1]``, widest box along that
    axis ``width[k]``, all its boxes within
    ``[body_lo[k], body_hi[k]]``). Each box ``i`` of A scans, in the segment of each body it may
    touch and whose bounding box it meets (inflated by ``radius`` and ``slack[k]``, so that no
    rounding of the exact test below is cut off), the boxes whose lower bound lies in
    ``[lo_i - radius - width[k] - slack[k], hi_i + radius + slack[k]]`` (start by binary search);
    within one set only bodies ``k >= body_i``, and in its own body only the boxes after it
    (``a_position``: its sorted row). A pair is kept when its inflated boxes overlap (the test of
    :func:`sim_core.ti_kernels.broad_phase._sweep_pairs`, same operands and side), the elements
    share no vertex, and, for two elements of one body, its key is not in ``rest_keys``."""
    capacity = out.shape[0]
    ti.loop_config(serialize=ti.static(serial_loops()))
    for i in range(a_lo.shape[0]):
        lo_i, hi_i = linalg.row3(a_lo, i), linalg.row3(a_hi, i)
        body_i = a_body[i]
        for kb in range(width.shape[0]):
            if allowed[body_i, kb] == 0 or (same != 0 and kb < body_i):
                continue
            apart = False  # box i (inflated, with slack) misses the box around all of body kb's boxes
            for d in ti.static(range(3)):
                apart = apart or (lo_i[d] - radius - slack[kb] > body_hi[kb, d]) or (
                    body_lo[kb, d] > hi_i[d] + radius + slack[kb])
            if apart:
                continue
            axis = body_axis[kb]
            lower = a_lo[i, axis] - radius - width[kb] - slack[kb]
            upper = a_hi[i, axis] + radius + slack[kb]
            first_row, end = segment[kb], segment[kb + 1]
            lo, hi = first_row, end
            while lo < hi:  # first row of the segment whose lower bound is >= lower
                mid = (lo + hi) // 2
                if sorted_lo[mid, axis] < lower:
                    lo = mid + 1
                else:
                    hi = mid
            if same != 0 and kb == body_i:
                lo = ti.max(lo, a_position[i] + 1)
            s = lo
            while s < end:  # (Taichi's ``and`` does not short-circuit: no read past the segment)
                if sorted_lo[s, axis] > upper:
                    break
                j = b_order[s]
                # within one set, the reference's side: the box of the lower body, then of the lower index
                swap = same != 0 and (kb < body_i or (kb == body_i and j < i))
                keep = True
                if swap:
                    for d in ti.static(range(3)):
                        keep = keep and (sorted_lo[s, d] - radius <= hi_i[d]) and (lo_i[d] <= sorted_hi[s, d] + radius)
                else:
                    for d in ti.static(range(3)):
                        keep = keep and (lo_i[d] - radius <= sorted_hi[s, d]) and (sorted_lo[s, d] <= hi_i[d] + radius)
                pair = kept_pair(a_vertices, a_key, i, b_vertices, j, same, ti.cast(body_i == kb, ti.i32), rest_keys,
                                 ti.cast(keep, ti.i32))
                keep = pair[0] != 0
                first, second = pair[1], pair[2]
                if keep:
                    k = ti.atomic_add(count[0], 1)
                    if k < capacity:
                        out[k, 0] = first
                        out[k, 1] = second
                s += 1


def _sorted_pairs(out: np.ndarray) -> np.ndarray:
    """int64 ``(p, 2)`` rows of ``out`` sorted by first, then second column (one sort of int64 keys)."""
    keys = (out[:, 0].astype(np.int64) << 32) | out[:, 1].astype(np.int64)
    keys.sort()
    return np.stack([keys >> 32, keys & 0xFFFFFFFF], axis=1)


class SweepCandidates(CandidateElements):
    """Vertex-triangle and edge-edge candidate lists of fixed elements, exclusions in the kernel.

    Args:
        vertices: global indices of the colliding vertices, shape ``(v,)``.
        triangles: global vertex indices of the colliding triangles, shape ``(t, 3)``.
        edges: global vertex indices of the colliding edges, shape ``(e, 2)``.
        pair_filter: the body / self-contact filter; needs ``body_pair_allowed``.
        rest_exclusion: the filter's :class:`RestExclusion` built for these same arrays.
        search: the :class:`SweepSearch` whose plans (and kept sweep axes) are used.
        vt_allowed: the vertex-triangle search's body table (:class:`CandidateElements`), or None.

    Raises:
        ConfigError: no body-pair table in the filter, a rest exclusion of another filter, or a ``vt_allowed`` of
            another shape.
    """

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, edges: np.ndarray, pair_filter: PairFilter,
                 rest_exclusion: RestExclusion, search: SweepSearch, vt_allowed: np.ndarray | None = None) -> None:
        super().__init__(vertices, triangles, edges, pair_filter, rest_exclusion, vt_allowed)
        self.search = search

    def vertex_triangle(self, x: np.ndarray, radius: float) -> np.ndarray:
        """``[global vertex, triangle row]`` pairs within ``radius`` (m) at ``x`` ``(n, 3)`` (m), int64
        ``(p, 2)``, sorted: :func:`sim_core.collision.candidates.vertex_triangle_candidates`'s list."""
        x = np.asarray(x, dtype=float)
        if self.vertices.size == 0 or self.triangles.shape[0] == 0:
            return np.zeros((0, 2), dtype=np.int64)
        tri_x = x[self.triangles]
        t_min = np.minimum(np.minimum(tri_x[:, 0], tri_x[:, 1]), tri_x[:, 2])
        t_max = np.maximum(np.maximum(tri_x[:, 0], tri_x[:, 1]), tri_x[:, 2])
        p = x[self.vertices]
        return self._run(p, p, self._vertex_body, t_min, t_max, self._triangle_body, self._vertex_elements,
                         self._vertex_keys, self._triangle_elements, self._vt_rest, radius, self.vt_allowed)

    def edge_edge(self, x: np.ndarray, radius: float) -> np.ndarray:
        """``[edge row i, edge row j]`` pairs (``i < j``) within ``radius`` (m) at ``x`` ``(n, 3)`` (m),
        int64 ``(p, 2)``, sorted: :func:`sim_core.collision.candidates.edge_edge_candidates`'s list."""
        x = np.asarray(x, dtype=float)
        if self.edges.shape[0] < 2:
            return np.zeros((0, 2), dtype=np.int64)
        ex = x[self.edges]
        e_min, e_max = np.minimum(ex[:, 0], ex[:, 1]), np.maximum(ex[:, 0], ex[:, 1])
        return self._run(e_min, e_max, self._edge_body, None, None, None, self._edge_elements, self._edge_keys,
                         self._edge_elements, self._ee_rest, radius, self.allowed)

    def _axes(self, a_lo: np.ndarray, a_hi: np.ndarray, a_body: np.ndarray, b_lo: np.ndarray, b_hi: np.ndarray,
              b_body: np.ndarray, same: bool, radius: float, allowed: np.ndarray) -> np.ndarray:
        """The sweep axis of each body of B, int32 ``(bodies,)``: kept from the last search of the kind
        and chosen again every ``refresh``-th one, as the axis along which the boxes of A that may
        touch the body leave the fewest of its boxes to scan."""
        search = self.search
        bodies = allowed.shape[0]
        kind = ("lists", same, len(a_lo), len(b_lo))
        axes, uses = search.axes.get(kind, (None, 0))
        if axes is not None and uses < search.refresh:
            search.axes[kind] = (axes, uses + 1)
            return axes
        axes = np.zeros(bodies, dtype=np.int32)
        for kb in range(bodies):
            rows = np.flatnonzero(b_body == kb)
            scanners = allowed[a_body, kb] != 0
            if same:
                scanners &= a_body <= kb
            if not rows.size or not np.any(scanners):
                continue
            best = None
            for axis in range(3):
                key = np.sort(b_lo[rows, axis])
                width = float(np.max(b_hi[rows, axis] - b_lo[rows, axis]))
                start = np.searchsorted(key, a_lo[scanners, axis] - radius - width, side="left")
                stop = np.searchsorted(key, a_hi[scanners, axis] + radius, side="right")
                scanned = int(np.sum(stop - start))
                if best is None or scanned < best[0]:
                    best = (scanned, axis)
            axes[kb] = best[1]
        search.axes[kind] = (axes, 1)
        return axes

    def _run(self, a_lo, a_hi, a_body, b_lo, b_hi, b_body, a_elements: np.ndarray, a_keys: np.ndarray,
             b_elements: np.ndarray, rest_keys: np.ndarray, radius: float, allowed: np.ndarray) -> np.ndarray:
        same = b_lo is None
        a_lo, a_hi = np.ascontiguousarray(a_lo, dtype=np.float64), np.ascontiguousarray(a_hi, dtype=np.float64)
        if same:
            b_lo, b_hi, b_body = a_lo, a_hi, a_body
        else:
            b_lo, b_hi = np.ascontiguousarray(b_lo, dtype=np.float64), np.ascontiguousarray(b_hi, dtype=np.float64)
        if a_lo.shape[0] == 0 or b_lo.shape[0] == 0:
            return np.zeros((0, 2), dtype=np.int64)
        require_backend("sweep candidate kernel")
        bodies = allowed.shape[0]
        body_axis = self._axes(a_lo, a_hi, a_body, b_lo, b_hi, b_body, same, radius, allowed)
        rows = np.arange(b_lo.shape[0])
        box_axis = body_axis[b_body]
        order = np.lexsort((b_lo[rows, box_axis], b_body))
        segment = np.searchsorted(b_body[order], np.arange(bodies + 1)).astype(np.int32)
        sorted_lo, sorted_hi = np.ascontiguousarray(b_lo[order]), np.ascontiguousarray(b_hi[order])
        extent = (sorted_hi - sorted_lo)[rows, box_axis[order]]
        width = _segment_reduce(extent, segment, np.maximum, 0.0)
        body_lo = _segment_reduce(sorted_lo, segment, np.minimum, np.inf)
        body_hi = _segment_reduce(sorted_hi, segment, np.maximum, -np.inf)
        scale = max(float(np.max(np.abs(a_lo))), float(np.max(np.abs(a_hi))), float(np.max(np.abs(b_lo))),
                    float(np.max(np.abs(b_hi))), float(radius))
        slack = 1e-9 * (scale + width)
        position = np.zeros(1, dtype=np.int32)
        if same:
            position = np.empty(order.size, dtype=np.int32)
            position[order] = np.arange(order.size, dtype=np.int32)
        sorted_body, order = np.ascontiguousarray(b_body[order]), order.astype(np.int32)
        out = np.empty((max(1024, 2 * (a_lo.shape[0] + order.shape[0])), 2), dtype=np.int32)
        count = np.zeros(1, dtype=np.int32)
        while True:
            _sweep_candidates(a_lo, a_hi, a_body, position, a_elements, a_keys, sorted_lo, sorted_hi, sorted_body,
                              order, b_elements, segment, width, slack, body_lo, body_hi, body_axis, allowed,
                              float(radius), int(same), rest_keys, out, count)
            found = int(count[0])
            if found <= out.shape[0]:
                return _sorted_pairs(out[:found])
            out = np.empty((found, 2), dtype=np.int32)
            count[0] = 0


def _segment_reduce(values: np.ndarray, segment: np.ndarray, ufunc, empty: float) -> np.ndarray:
    """``ufunc.reduce`` of the rows ``segment[k] <= s < segment[k + 1]`` of ``values`` ``(r,)`` or
    ``(r, 3)`` per segment ``k``; ``empty`` for an empty segment. Shape ``(k,) + values.shape[1:]``."""
    counts = np.diff(segment)
    out = np.full((counts.size,) + values.shape[1:], empty)
    filled = counts > 0
    if np.any(filled):
        out[filled] = ufunc.reduceat(values, segment[:-1][filled], axis=0)
    return np.ascontiguousarray(out)


def compile_kernels() -> None:
    """JIT-compile (or load from Taichi's offline cache) the kernel on two small sheets' lists.

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """
    compile_candidate_kernels(lambda *lists: SweepCandidates(*lists, SweepSearch()))
