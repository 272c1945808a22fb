"""Broad phase in one Taichi kernel: pairs of inflated boxes that overlap, by a spatial hash.

The Taichi twin of :class:`sim_core.collision.spatial_hash.SpatialHash` inside the grouped search of
:func:`sim_core.collision.candidates._grouped_box_pairs` (k-d trees per pair of bodies, the reference
and test oracle): the same pairs, found on a uniform grid whose cells are hashed into a table
(Teschner et al., "Optimized Spatial Hashing for Collision Detection of Deformable Objects", VMV
2003: bucket ``(c_x p1 xor c_y p2 xor c_z p3) mod m`` with ``p1, p2, p3 = 73856093, 19349663,
83492791``). One launch of :func:`_hash_pairs` runs, as consecutive loops:

1. the cell size ``h = max(mean_b max_d (b_hi - b_lo)_d + 2 radius, widest / 256, max |coordinate| / 2^18)``
   (about one inflated box per cell; the second bound keeps the cells of the widest box below 257
   per axis, the third keeps cell indices far inside the 21-bit fields of the cell keys);
2. a counting sort of the boxes of set B into the buckets of the cells they overlap (count per
   bucket, prefix sum into ``bucket_start`` by chunks of buckets, scatter of ``(box, cell key)`` entries);
3. for each box ``a`` of set A, inflated by ``radius``, a visit of the cells it overlaps: the
   entries of the cell (its bucket, entries of other cells of the bucket skipped by their key) are
   pairs when their bodies may touch and the reference's exact inflated-box test holds,

       a_lo - radius <= b_hi  and  b_lo <= a_hi + radius      (per axis, same operands),

   and a pair is reported only from the cell of the lower corner of the boxes' intersection
   ``max(a_lo - radius, b_lo)``, which both boxes overlap, so each pair once (cells are
   ``floor(v / h)``; rounding is monotone, so the corner's cell lies in both boxes' cell ranges).

Within one set (A paired with itself) a pair is tested from the box of the lower body, then of the
lower index, as the reference does. The kernel also applies the candidate exclusions of
:mod:`sim_core.ti_kernels.hash_candidates` when given element vertices and rest keys: pairs of
elements that share a vertex, and same-body pairs whose key ``first << 32 | second`` is in the
sorted rest-distance keys. The pairs are therefore exactly the reference's; they are returned
sorted (one ``np.sort`` of int64 keys, the order of the reference's lexsort; on CUDA a counting sort by the first
index and an insertion sort of each index's few partners on the device, :func:`sorted_on_device`: the same keys), and
the sorted keys are kept for the caller (:meth:`HashGrid.keys_of`: the contact set's side memory looks its pairs up
among them).

Loops run serially on the CPU (entries and pairs in box order), in parallel on CUDA (atomic
counters; the sort makes the result the same). The entry and output buffers are kept by a
:class:`HashGrid` between searches; when one was too small the kernel reports the size needed and
runs again on a larger one.
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel and ti.func annotations as
# objects (string annotations are rejected).

import numpy as np

from sim_core.array_pool import ArrayPool
from sim_core.errors import ConfigError
from sim_core.ti_backend import current_arch, require_backend, serial_loops, ti
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.buffers import copy_back, on_device
from sim_core.ti_kernels.launch import FastKernel, fast_kernel
from sim_core.ti_kernels.pair_filters import kept_pair
from sim_core.ti_kernels.scan import SCAN_CHUNK, running_sums

_F64_1, _F64_2, _I32_1, _I32_2 = linalg.F64_1, linalg.F64_2, linalg.I32_1, linalg.I32_2
_I64_1 = ti.types.ndarray(dtype=ti.i64, ndim=1)

_KEY_OFFSET = 1 << 20  # cell indices are packed as 21-bit unsigned fields of one int64 key
_CELL_LIMIT = float(1 << 18)  # the cell size keeps |cell index| <= 2^18 + 1
_WIDEST_CELLS = 256.0  # the widest box overlaps at most 257 cells per axis
_P1, _P2, _P3 = 73856093, 19349663, 83492791  # Teschner et al. 2003
# count: [0] pairs found, [1] entries needed, [2] 1 if a coordinate is not finite
_PAIRS, _ENTRIES, _BAD = 0, 1, 2


@ti.func
def _cell_of(v: ti.f64, inv_cell: ti.f64) -> ti.i32:
    """Cell index ``floor(v / h)`` along one axis (``v * (1 / h)``: monotone in ``v``)."""
    return ti.cast(ti.floor(v * inv_cell), ti.i32)


@ti.func
def _cell_key(c0: ti.i32, c1: ti.i32, c2: ti.i32) -> ti.i64:
    """The cell's int64 key: three 21-bit fields (as :mod:`sim_core.collision.spatial_hash`)."""
    return (ti.cast(c0 + _KEY_OFFSET, ti.i64) << 42) | (ti.cast(c1 + _KEY_OFFSET, ti.i64) << 21) | ti.cast(
        c2 + _KEY_OFFSET, ti.i64)


@ti.func
def _bucket(c0: ti.i32, c1: ti.i32, c2: ti.i32, mask: ti.i64) -> ti.i32:
    """Teschner et al.'s hash of a cell, ``(c0 p1 xor c1 p2 xor c2 p3) mod m`` for ``m = mask + 1`` (a power of 2)."""
    h = (ti.cast(c0, ti.i64) * _P1) ^ (ti.cast(c1, ti.i64) * _P2) ^ (ti.cast(c2, ti.i64) * _P3)
    return ti.cast(h & mask, ti.i32)


@ti.func
def _element_box(x: ti.template(), vertices: ti.template(), i: ti.i32):
    """``(lo, hi, finite)``: the corners of element ``i``'s box (min / max over its vertices, exact)
    and whether all its coordinates are finite."""
    v = vertices[i, 0]
    lo = ti.Vector([x[v, 0], x[v, 1], x[v, 2]], dt=ti.f64)
    hi = lo
    for u in range(1, vertices.shape[1]):
        w = vertices[i, u]
        for d in ti.static(range(3)):
            lo[d] = ti.min(lo[d], x[w, d])
            hi[d] = ti.max(hi[d], x[w, d])
    finite = True
    for u in range(vertices.shape[1]):
        w = vertices[i, u]
        for d in ti.static(range(3)):
            finite = finite and ti.abs(x[w, d]) <= 1e300
    return lo, hi, finite


@ti.func
def _cells(v, inv_cell: ti.f64):
    """The cell indices of point ``v`` (3 int32)."""
    return ti.Vector([_cell_of(v[0], inv_cell), _cell_of(v[1], inv_cell), _cell_of(v[2], inv_cell)])


@ti.func
def _stored_box(box: ti.template(), j: ti.i32):
    """``(lo, hi)``: the corners of box ``j`` as stored in ``box`` ``(nb, 6)``."""
    return (ti.Vector([box[j, 0], box[j, 1], box[j, 2]], dt=ti.f64),
            ti.Vector([box[j, 3], box[j, 4], box[j, 5]], dt=ti.f64))


@fast_kernel
def _hash_pairs(x: _F64_2, a_vertices: _I32_2, a_body: _I32_1, a_key: _I32_1, b_vertices: _I32_2, b_body: _I32_1,
                allowed: _I32_2, rest_keys: _I64_1, radius: ti.f64,
                cell_scale: ti.f64, same: ti.i32, bucket_start: _I32_1, bucket_fill: _I32_1, entry_item: _I32_1,
                entry_cell: _I64_1, entry_lower: _I32_1, box: _F64_2, body_box: _F64_2, scale: _F64_1, out: _I32_2,
                count: _I32_1, chunk_total: _I32_1):
    """Pairs of elements (rows of ``a_vertices`` and ``b_vertices``: vertex indices into ``x``) whose
    boxes (the min / max of their vertices' positions) overlap when A's are inflated by ``radius``.

    ``count[0]`` (set to 0 by the caller) += the number of kept pairs; the first ``out.shape[0]``
    of them in ``out`` as ``[first, second]``: ``[a_key[i], j]`` between two sets, ``[min, max]`` of
    the two indices within one (module docstring). ``count[1]``: the entries needed (none are
    written and no pair is searched when ``entry_item`` is shorter); ``count[2]``: 1 when a
    coordinate is not finite (nothing searched). Buckets are per hashed cell and body of B
    (``bucket_fill.shape[0] = cells * bodies``, cells a power of 2; ``bucket_start``: one longer), so
    a box visits only the entries of the bodies it may touch, and of those only within the cell range
    of the body's bounding box (scratch ``body_box`` ``(bodies, 6)``: lower, upper corner).
    Scratch ``chunk_total`` ``(ceil(buckets / SCAN_CHUNK),)``: the bucket counts' prefix sum by chunks.
    Scratch ``box`` ``(nb, 6)``: B's boxes (lower, upper corner); ``entry_lower`` (as ``entry_item``):
    bit ``d`` set when the entry's cell is its box's lowest along axis ``d``. ``scale``: scratch,
    ``[cell size, 1 / cell size, sum of box widths, widest box, largest |coordinate|]``; the
    mean-width term of the cell size is multiplied by ``cell_scale``.

    The lower-corner rule is tested on cell indices before the boxes are read: ``floor`` is monotone,
    so the cell of ``max(q_lo, b_lo)`` is ``max(cell(q_lo), cell(b_lo))`` per axis, which is the
    visited cell ``c`` (``cell(q_lo) <= c`` and ``cell(b_lo) <= c`` for every visited entry) exactly
    when, on each axis with ``cell(q_lo) < c``, ``c`` is the lowest cell of B's box."""
    na, nb = a_vertices.shape[0], b_vertices.shape[0]
    bodies = body_box.shape[0]
    buckets = bucket_fill.shape[0]
    mask = ti.cast(buckets // bodies - 1, ti.i64)
    capacity, entry_capacity = out.shape[0], entry_item.shape[0]
    # 1. cell size and the bodies' bounding boxes (sums in box order on the CPU)
    ti.loop_config(serialize=True)  # one thread; never the CPU thread pool (a forked worker hangs there)
    for _ in range(1):
        for k in ti.static(range(2, 5)):
            scale[k] = 0.0
        count[_ENTRIES] = 0
        count[_BAD] = 0
        for k in range(bodies):
            for d in ti.static(range(3)):
                body_box[k, d] = ti.math.inf
                body_box[k, 3 + d] = -ti.math.inf
    ti.loop_config(serialize=ti.static(serial_loops()))
    for j in range(nb):
        b_lo, b_hi, finite = _element_box(x, b_vertices, j)
        width, reach = 0.0, 0.0
        body_j = b_body[j]
        for d in ti.static(range(3)):
            box[j, d] = b_lo[d]
            box[j, 3 + d] = b_hi[d]
            width = ti.max(width, b_hi[d] - b_lo[d])
            reach = ti.max(reach, ti.max(ti.abs(b_lo[d]), ti.abs(b_hi[d])))
            ti.atomic_min(body_box[body_j, d], b_lo[d])
            ti.atomic_max(body_box[body_j, 3 + d], b_hi[d])
        if not finite:
            count[_BAD] = 1
        ti.atomic_add(scale[2], width)
        ti.atomic_max(scale[3], width)
        ti.atomic_max(scale[4], reach)
    ti.loop_config(serialize=ti.static(serial_loops()))
    for i in range(na):
        if same == 0:  # (within one set the loop above saw these boxes)
            a_lo, a_hi, finite = _element_box(x, a_vertices, i)
            reach = 0.0
            for d in ti.static(range(3)):
                reach = ti.max(reach, ti.max(ti.abs(a_lo[d]), ti.abs(a_hi[d])))
            if not finite:
                count[_BAD] = 1
            ti.atomic_max(scale[4], reach)
    ti.loop_config(serialize=True)  # one thread; never the CPU thread pool (a forked worker hangs there)
    for _ in range(1):
        cell = ti.max(ti.max(cell_scale * (scale[2] / ti.max(nb, 1) + 2.0 * radius),
                             (scale[3] + 2.0 * radius) / _WIDEST_CELLS),
                      ti.max((scale[4] + radius) / _CELL_LIMIT, 1e-300))
        scale[0] = cell
        scale[1] = 1.0 / cell
    # 2. counting sort of B's boxes into the buckets (cell, body) of their cells
    ti.loop_config(serialize=ti.static(serial_loops()))
    for h in range(buckets + 1):
        bucket_start[h] = 0
    ti.loop_config(serialize=ti.static(serial_loops()))
    for j in range(nb):
        if count[_BAD] == 0:
            body_j = b_body[j]
            b_lo, b_hi = _stored_box(box, j)
            lo, hi = _cells(b_lo, scale[1]), _cells(b_hi, scale[1])
            for c0 in range(lo[0], hi[0] + 1):
                for c1 in range(lo[1], hi[1] + 1):
                    for c2 in range(lo[2], hi[2] + 1):
                        ti.atomic_add(bucket_start[_bucket(c0, c1, c2, mask) * bodies + body_j + 1], 1)
    running_sums(bucket_start, buckets, chunk_total, count, _ENTRIES)  # the buckets' offsets, the entries needed
    ti.loop_config(serialize=ti.static(serial_loops()))
    for h in range(buckets):
        bucket_fill[h] = bucket_start[h]
    ti.loop_config(serialize=ti.static(serial_loops()))
    for j in range(nb):
        if count[_BAD] == 0 and count[_ENTRIES] <= entry_capacity:
            body_j = b_body[j]
            b_lo, b_hi = _stored_box(box, j)
            lo, hi = _cells(b_lo, scale[1]), _cells(b_hi, scale[1])
            for c0 in range(lo[0], hi[0] + 1):
                for c1 in range(lo[1], hi[1] + 1):
                    for c2 in range(lo[2], hi[2] + 1):
                        slot = ti.atomic_add(bucket_fill[_bucket(c0, c1, c2, mask) * bodies + body_j], 1)
                        entry_item[slot] = j
                        entry_cell[slot] = _cell_key(c0, c1, c2)
                        entry_lower[slot] = (ti.cast(c0 == lo[0], ti.i32) | (ti.cast(c1 == lo[1], ti.i32) << 1)
                                             | (ti.cast(c2 == lo[2], ti.i32) << 2))
    # 3. each box of A visits, per body it may touch, the cells of its inflated box within the body's box
    ti.loop_config(serialize=ti.static(serial_loops()))
    for i in range(na):
        if count[_BAD] == 0 and count[_ENTRIES] <= entry_capacity:
            inv = scale[1]
            a_lo, a_hi, _ = _element_box(x, a_vertices, i)
            q_lo = a_lo - radius
            q_hi = a_hi + radius
            q_cell = _cells(q_lo, inv)
            body_i = a_body[i]
            for kb in range(bodies):
                if allowed[body_i, kb] == 0 or (same != 0 and kb < body_i):
                    continue
                # cells of the query within the cells of body kb's box (its pairs' corners lie there)
                lo_c = ti.Vector([0, 0, 0])
                hi_c = ti.Vector([-1, -1, -1])
                if body_box[kb, 0] <= body_box[kb, 3]:  # the body has boxes
                    for d in ti.static(range(3)):
                        lo_c[d] = ti.max(q_cell[d], _cell_of(body_box[kb, d], inv))
                        hi_c[d] = ti.min(_cell_of(q_hi[d], inv), _cell_of(body_box[kb, 3 + d], inv))
                same_body = ti.cast(body_i == kb, ti.i32)
                for c0 in range(lo_c[0], hi_c[0] + 1):
                    for c1 in range(lo_c[1], hi_c[1] + 1):
                        for c2 in range(lo_c[2], hi_c[2] + 1):
                            key = _cell_key(c0, c1, c2)
                            # the lower-corner rule: lowest cell of B's box on the axes where the query's is lower
                            need = (ti.cast(c0 > q_cell[0], ti.i32) | (ti.cast(c1 > q_cell[1], ti.i32) << 1)
                                    | (ti.cast(c2 > q_cell[2], ti.i32) << 2))
                            b = _bucket(c0, c1, c2, mask) * bodies + kb
                            for s in range(bucket_start[b], bucket_start[b + 1]):
                                if entry_cell[s] != key or (entry_lower[s] & need) != need:
                                    continue
                                j = entry_item[s]
                                # within one body of one set, from the box of the lower index
                                if same_body != 0 and same != 0 and j <= i:
                                    continue
                                b_lo, b_hi = _stored_box(box, j)
                                keep = True
                                for d in ti.static(range(3)):
                                    keep = keep and (q_lo[d] <= b_hi[d]) and (b_lo[d] <= q_hi[d])
                                pair = kept_pair(a_vertices, a_key, i, b_vertices, j, same, same_body, rest_keys,
                                                 ti.cast(keep, ti.i32))
                                if pair[0] != 0:
                                    k = ti.atomic_add(count[_PAIRS], 1)
                                    if k < capacity:
                                        out[k, 0] = pair[1]
                                        out[k, 1] = pair[2]


@fast_kernel
def _sort_pairs(out: _I32_2, found: ti.i32, first_count: ti.i32, start: _I32_1, fill: _I32_1, chunk_total: _I32_1,
                keys: _I64_1):
    """``keys[:found]``: the packed keys ``first << 32 | second`` of the rows ``out[:found]`` (int32
    ``[first, second]``, distinct, ``0 <= first < first_count``, ``second >= 0``), increasing: a counting sort of the
    rows by ``first`` (``start`` ``(first_count + 1,)``: each first's run, by the counts' running sums,
    :func:`~sim_core.ti_kernels.scan.running_sums`; ``fill`` ``(first_count,)``: the runs' next free slots), then
    each run sorted by insertion in one thread (a run is the candidates of one vertex or edge: tens). Scratch
    ``chunk_total`` ``(ceil(first_count / SCAN_CHUNK),)``. The result does not depend on the threads' order."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for a in range(first_count + 1):
        start[a] = 0
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(found):
        ti.atomic_add(start[out[k, 0] + 1], 1)
    running_sums(start, first_count, chunk_total, fill, 0)  # the runs' offsets (the total into fill[0], set below)
    ti.loop_config(serialize=ti.static(serial_loops()))
    for a in range(first_count):
        fill[a] = start[a]
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(found):
        first = out[k, 0]
        slot = ti.atomic_add(fill[first], 1)
        keys[slot] = (ti.cast(first, ti.i64) << 32) | ti.cast(out[k, 1], ti.i64)
    ti.loop_config(serialize=ti.static(serial_loops()))
    for a in range(first_count):
        low = start[a]
        for s in range(low + 1, start[a + 1]):
            key = keys[s]
            t = s
            while t > low and keys[t - 1] > key:
                keys[t] = keys[t - 1]
                t -= 1
            keys[t] = key


def sorted_pairs_and_keys(out: np.ndarray, pool: ArrayPool | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(pairs, keys)``: the int64 ``(p, 2)`` rows of ``out`` ``(p, 2)`` (int32, non-negative) sorted by first, then
    second column, and their packed keys ``first << 32 | second``, int64 ``(p,)`` in the same order (one sort of the
    keys, built and split in place: no temporaries of the 1.75 million pairs of 1024 stacked Forming copies; the keys
    are :class:`~sim_core.collision.memory.ContactMemory`'s, which the contact set looks its remembered pairs up in).
    ``pool``: where the two arrays are made (:class:`~sim_core.array_pool.ArrayPool`, a grid's: blocks of earlier
    searches that nothing holds any more), or None: fresh arrays."""
    keys = out[:, 0].astype(np.int64) if pool is None else pool.copy_of("keys", out[:, 0], np.int64)
    keys <<= 32
    keys |= out[:, 1]
    keys.sort()
    return _pairs_of(keys, pool), keys


def _pairs_of(keys: np.ndarray, pool: ArrayPool | None) -> np.ndarray:
    """The int64 pairs ``(p, 2)`` ``[first, second]`` of packed keys ``first << 32 | second`` ``(p,)`` (non-negative),
    in an array of ``pool`` (or a fresh one)."""
    pairs = np.empty((len(keys), 2), dtype=np.int64) if pool is None else pool.empty("pairs", (len(keys), 2), np.int64)
    np.right_shift(keys, 32, out=pairs[:, 0])
    np.bitwise_and(keys, 0xFFFFFFFF, out=pairs[:, 1])
    return pairs


def sorted_on_device(out, found: int, first_count: int, device: dict, pool: ArrayPool | None = None
                     ) -> tuple[np.ndarray, np.ndarray, object]:
    """:func:`sorted_pairs_and_keys` of the rows ``out[:found]`` where ``out`` is (int32 ``(capacity, 2)``, distinct
    rows, first column in ``[0, first_count)``: a Taichi ndarray in device memory on CUDA, else a NumPy array), sorted
    there by one launch of :func:`_sort_pairs`; only the sorted keys are copied back (the host sort of a 1024-copy
    Forming batch's 1.8 million keys took 43 ms on an H100's host: docs/benchmarks_log.md, session 45, 28grad). The
    same arrays, and the sorted keys where the launch wrote them (a Taichi int64 ndarray of at least ``found`` entries,
    the cache's: valid until the next sort with the same ``device``). ``device``: the cache of the kernel's work arrays
    (:func:`~sim_core.ti_kernels.buffers.on_device`); ``pool``: as :func:`sorted_pairs_and_keys`'."""
    arrays = device.setdefault("sort_host", {})
    starts = arrays.get("start")
    if starts is None or starts.shape[0] < first_count + 1:
        arrays["start"] = np.zeros(first_count + 1 + first_count // 4, dtype=np.int32)
        arrays["fill"] = np.zeros(arrays["start"].shape[0], dtype=np.int32)
        arrays["chunk_total"] = np.zeros(-(-arrays["start"].shape[0] // SCAN_CHUNK), dtype=np.int32)
    if arrays.get("keys") is None or arrays["keys"].shape[0] < found:
        arrays["keys"] = np.zeros(max(found + found // 4, 16), dtype=np.int64)
    work = [on_device(device, f"sort_{name}", arrays[name], scratch=True)
            for name in ("start", "fill", "chunk_total", "keys")]
    _sort_pairs(out, int(found), int(first_count), *work)
    kept = copy_back(arrays["keys"], work[3], found)[:found]
    keys = kept.copy() if pool is None else pool.copy_of("keys", kept)
    return _pairs_of(keys, pool), keys, work[3]


def _power_of_two(n: int) -> int:
    return 1 << max(4, int(n - 1).bit_length())


class HashGrid:
    """The buffers of :func:`_hash_pairs` for one kind of search, kept (and grown) between searches.

    Each search needs a bucket table (a power of 2, about twice the boxes of set B), the entries of
    B's boxes (one per overlapped cell), B's boxes and the output pairs; kept as the same arrays, they are
    bound to the compiled kernel once (the positions are bound as given, a new binding per search): each grid
    launches through its own :class:`~sim_core.ti_kernels.launch.FastKernel` of the one compiled
    kernel, whose launch plan keeps its arrays bound (:mod:`sim_core.ti_kernels.launch`), so the
    contact set's two grids, searched in turn, do not re-bind each other's arrays at every launch.
    On CUDA the grid keeps them in device memory instead (:meth:`_on_device`), sorts the pairs there
    (:func:`sorted_on_device`) and copies back only the pair count and the sorted keys (the scale the kernel computes
    stays there; the sorted keys too until its next search, :meth:`device_keys_of`).

    Args:
        cell_scale: the factor of the cell size's mean-width term (:func:`_hash_pairs`).
        positions: the cache of the positions' device copy (a :func:`~sim_core.ti_kernels.buffers.on_device` dict),
            shared by the grids that search the same positions in turn (a contact set's two lists), or None for one
            of this grid's own.
    """

    def __init__(self, cell_scale: float = 1.0, positions: dict | None = None) -> None:
        self._positions = {} if positions is None else positions
        self._launch = FastKernel(_hash_pairs.kernel)
        self.bucket_start = self.bucket_fill = self.chunk_total = np.zeros(0, dtype=np.int32)
        self.entry_item = self.entry_lower = np.zeros(0, dtype=np.int32)
        self.entry_cell = np.zeros(0, dtype=np.int64)
        self.box = np.zeros((0, 6), dtype=np.float64)
        self.out = np.zeros((0, 2), dtype=np.int32)
        self.body_box = np.zeros((0, 6), dtype=np.float64)
        self.scale = np.zeros(5, dtype=np.float64)
        self.cell_scale = cell_scale
        self.count = np.zeros(3, dtype=np.int32)
        self._last: tuple | None = None  # (pairs, keys) of the last search (keys_of)
        self._pool = ArrayPool()  # the sorted pairs and keys, reused once no list or cache holds them

    def pairs(self, x: np.ndarray, a_vertices: np.ndarray, a_body: np.ndarray, a_key: np.ndarray,
              b_vertices: np.ndarray | None, b_body: np.ndarray | None, allowed: np.ndarray, rest_keys: np.ndarray,
              radius: float) -> np.ndarray:
        """The kept pairs of elements (module docstring), int64 ``(p, 2)``, sorted.

        Args:
            x: positions in m, float64 ``(n, 3)``.
            a_vertices: vertex indices (rows of ``x``) of each element of set A, int32 ``(ka, m)``; its
                box spans them.
            a_body: body of each A element, int32 ``(ka,)``.
            a_key: first column of a pair with A element ``i`` (between two sets), int32 ``(ka,)``.
            b_vertices, b_body: the same for set B, or None to pair A with itself (pairs ``[i, j]``
                with ``i < j``).
            allowed: ``(bodies, bodies)`` int32, symmetric.
            rest_keys: sorted int64 keys of excluded same-body pairs, non-empty.
            radius: inflation in m (finite, >= 0).

        Raises:
            ConfigError: the Taichi backend is not initialised, or a coordinate is NaN or infinite.
        """
        require_backend("spatial-hash broad-phase kernel")
        same = b_vertices is None
        if same:
            b_vertices, b_body = a_vertices, a_body
        if a_vertices.shape[0] == 0 or b_vertices.shape[0] == 0:
            return np.zeros((0, 2), dtype=np.int64)
        # the positions as given when they are a C-contiguous float64 array (bound by address on the CPU, sent
        # straight into the kept device array on CUDA: no host copy and no comparison with the last search's)
        positions = x if type(x) is np.ndarray and x.dtype == np.float64 and x.flags.c_contiguous \
            else np.ascontiguousarray(x, dtype=np.float64)
        nb = b_vertices.shape[0]
        bodies = allowed.shape[0]
        buckets = _power_of_two(2 * nb) * bodies
        if self.body_box.shape[0] != bodies:
            self.body_box = np.zeros((bodies, 6), dtype=np.float64)
        if self.bucket_fill.shape[0] != buckets:
            self.bucket_fill = np.zeros(buckets, dtype=np.int32)
            self.bucket_start = np.zeros(buckets + 1, dtype=np.int32)
            self.chunk_total = np.zeros(-(-buckets // SCAN_CHUNK), dtype=np.int32)
        if self.box.shape[0] != nb:
            self.box = np.zeros((nb, 6), dtype=np.float64)
        if self.entry_item.shape[0] < 4 * nb:
            self._grow_entries(8 * nb)
        if self.out.shape[0] < 1024:
            self.out = np.empty((max(1024, 2 * (a_vertices.shape[0] + nb)), 2), dtype=np.int32)
        while True:
            self.count[_PAIRS] = 0
            arrays = (positions, a_vertices, a_body, a_key, b_vertices, b_body, allowed, rest_keys, self.bucket_start,
                      self.bucket_fill, self.entry_item, self.entry_cell, self.entry_lower, self.box, self.body_box,
                      self.scale, self.out, self.count, self.chunk_total)
            if current_arch() == "cuda":
                arrays = self._on_device(arrays)
            self._launch(*arrays[:8], float(radius), self.cell_scale, int(same), *arrays[8:])
            on_gpu = arrays[0] is not positions
            if on_gpu:  # the count copied back from the device (the pairs are sorted there, below)
                copy_back(self.count, arrays[17])
            if self.count[_BAD]:
                raise ConfigError("spatial-hash broad phase: bounding boxes contain NaN or infinite coordinates")
            entries, found = int(self.count[_ENTRIES]), int(self.count[_PAIRS])
            if entries > self.entry_item.shape[0]:
                self._grow_entries(entries + entries // 4)
                continue
            if found > self.out.shape[0]:
                self.out = np.empty((found + found // 4, 2), dtype=np.int32)
                continue
            device_keys = None
            if on_gpu:
                first_count = a_vertices.shape[0] if same else self._first_count(a_key)
                pairs, keys, device_keys = sorted_on_device(arrays[16], found, first_count, self.__dict__["_device"],
                                                            self._pool)
            else:
                pairs, keys = sorted_pairs_and_keys(self.out[:found], self._pool)
            self._last = (pairs, keys, device_keys)
            return pairs

    def _first_count(self, a_key: np.ndarray) -> int:
        """``max(a_key) + 1`` (the bound of the pairs' first column between two sets), kept per ``a_key`` object
        (the element lists are never edited in place)."""
        kept = getattr(self, "_first_bound", None)
        if kept is None or kept[0] is not a_key:
            kept = self._first_bound = (a_key, int(a_key.max()) + 1 if len(a_key) else 0)
        return kept[1]

    def keys_of(self, pairs: np.ndarray) -> np.ndarray | None:
        """The packed keys ``first << 32 | second`` (int64 ``(p,)``, increasing) of ``pairs`` when they are the array
        the last :meth:`pairs` returned (the same object), made by its sort; else None."""
        last = self._last
        return last[1] if last is not None and last[0] is pairs else None

    def device_keys_of(self, pairs: np.ndarray):
        """:meth:`keys_of` where the sort left them on CUDA (a Taichi int64 ndarray whose first ``len(pairs)`` entries
        are the keys, valid until this grid's next search) when ``pairs`` is the array the last :meth:`pairs` returned
        and it was sorted there; else None."""
        last = self._last
        return last[2] if last is not None and last[0] is pairs else None

    def _on_device(self, arrays: tuple) -> tuple:
        """The launch's arrays (the order of :func:`_hash_pairs`' array arguments) as Taichi ndarrays in device
        memory (:func:`~sim_core.ti_kernels.buffers.on_device`, kept per grid): the pair count sent at every launch,
        the positions at every launch unless they are frozen (a read-only array that owns its memory, whose values
        cannot change while it exists: sent once into the positions' cache, which the grids searching it in turn
        share), the element lists when they are other objects than at the last launch (never edited in place), the
        work arrays when the host replaced them (grown: the device copy starts from the same zeros and keeps what the
        kernel leaves in it, as the host array does on the CPU)."""
        names = ("x", "a_vertices", "a_body", "a_key", "b_vertices", "b_body", "allowed", "rest_keys",
                 "bucket_start", "bucket_fill", "entry_item", "entry_cell", "entry_lower", "box", "body_box", "scale",
                 "out", "count", "chunk_total")
        device = self.__dict__.setdefault("_device", {})
        x = arrays[0]
        frozen = not x.flags.writeable and x.base is None
        return (on_device(self._positions, "x", x, refresh=not frozen),) + tuple(
            on_device(device, name, host, refresh=name == "count") for name, host in zip(names[1:], arrays[1:]))

    def _grow_entries(self, size: int) -> None:
        self.entry_item = np.zeros(size, dtype=np.int32)
        self.entry_lower = np.zeros(size, dtype=np.int32)
        self.entry_cell = np.zeros(size, dtype=np.int64)


_NO_REST = np.full(1, -1, dtype=np.int64)  # matches no pair key (keys are >= 0)


class HashSearch:
    """:func:`grouped_box_pairs` on kept buffers (one :class:`HashGrid` per kind of search): the
    callable the candidate functions of :mod:`sim_core.collision.candidates` take as ``grouped_search``."""

    def __init__(self) -> None:
        self.grids: dict[bool, HashGrid] = {}

    def __call__(self, a_min: np.ndarray, a_max: np.ndarray, a_body: np.ndarray, b_min: np.ndarray | None,
                 b_max: np.ndarray | None, b_body: np.ndarray | None, radius: float, allowed: np.ndarray) -> np.ndarray:
        """As :func:`grouped_box_pairs` (same arguments, result and errors).

        Each box is an element of two points, its corners: rows ``[lo_i, hi_i]`` of one position
        array (the min / max of the two is the box again), no two boxes sharing a point.
        """
        same = b_min is None
        grid = self.grids.setdefault(same, HashGrid())
        na = len(a_min)
        allowed = np.ascontiguousarray(allowed, dtype=np.int32)
        a_body = np.ascontiguousarray(a_body, dtype=np.int32)
        a_key = np.arange(na, dtype=np.int32)
        if same:
            x = np.concatenate([np.asarray(a_min, dtype=np.float64).reshape(-1, 3),
                                np.asarray(a_max, dtype=np.float64).reshape(-1, 3)])
            a_vertices = np.stack([a_key, a_key + na], axis=1)
            return grid.pairs(x, a_vertices, a_body, a_key, None, None, allowed, _NO_REST, radius)
        nb = len(b_min)
        x = np.concatenate([np.asarray(v, dtype=np.float64).reshape(-1, 3) for v in (a_min, a_max, b_min, b_max)])
        a_vertices = np.stack([a_key, a_key + na], axis=1)
        b_rows = 2 * na + np.arange(nb, dtype=np.int32)
        b_vertices = np.stack([b_rows, b_rows + nb], axis=1)
        return grid.pairs(x, a_vertices, a_body, a_key, b_vertices, np.ascontiguousarray(b_body, dtype=np.int32),
                          allowed, _NO_REST, radius)


def grouped_box_pairs(
    a_min: np.ndarray, a_max: np.ndarray, a_body: np.ndarray,
    b_min: np.ndarray | None, b_max: np.ndarray | None, b_body: np.ndarray | None,
    radius: float, allowed: np.ndarray,
) -> np.ndarray:
    """The pairs of :func:`sim_core.collision.candidates._grouped_box_pairs`, by a spatial hash (module docstring).

    Args:
        a_min, a_max, a_body: boxes of set A ``(ka, 3)`` in m and the body of each ``(ka,)``.
        b_min, b_max, b_body: the same for set B, or None to pair A with itself (each unordered pair
            once, as ``[i, j]`` with ``i < j``).
        radius: inflation in m.
        allowed: ``(bodies, bodies)`` bool, symmetric.

    Returns:
        int64 ``(p, 2)`` of ``[index in A, index in B]``, sorted (same set as the reference).

    Raises:
        ConfigError: the Taichi backend is not initialised, or a box coordinate is NaN or infinite.
    """
    return HashSearch()(a_min, a_max, a_body, b_min, b_max, b_body, radius, allowed)


def compile_kernels() -> None:
    """JIT-compile (or load from Taichi's offline cache) the hash kernel on two boxes.

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """
    lo = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    grouped_box_pairs(lo, lo + 1.0, np.zeros(2, np.int32), None, None, None, 0.1, np.ones((1, 1), bool))
    sorted_on_device(np.array([[1, 0], [0, 2]], dtype=np.int32), 2, 2, {})  # (CUDA's sort of the pairs)
