"""PSD-projected element Hessians of the fused Newton path, added straight into CSR slot values.

The Newton solver (:mod:`sim_core.solver`) falls back to the PSD-projected Hessian when PARDISO's
Cholesky refuses the exact one. The projection is per element block, as in the reference
potentials (:func:`sim_core.energies.base.project_psd`, "clamp" of Teran et al. 2005 or "abs"),
and for an energy that depends only on vertex differences it is done in the ``3 m - 3``
dimensional complement of the rigid translations
(:func:`sim_core.energies.membrane.reference.project_psd_translation_free`): with ``B = h (x) I_3``, ``h``
the Helmert basis of :func:`sim_core.ti_kernels.linalg.helmert_basis` (``m x (m - 1)``, any
orthonormal basis of the complement gives the same projection),

    P(H) = B P(B^T H B) B^T.

The work is split where each part is cheapest (measured, docs/benchmarks_log.md):

* :meth:`TranslationFreeProjector.reduced` / :meth:`~TranslationFreeProjector.expanded` (NumPy, the host path):
  ``B^T H B`` and ``B R B^T`` as stacked matrix products with a constant ``B`` (about 0.25 ms for
  480 blocks of 18 x 18; a Taichi loop per element took 3 ms, and one large GEMM over the stacked
  rows, 0.4 ms alone, took 25 ms inside a replay on the loaded 2-core VM: OpenBLAS threads it).
* :func:`project_reduced_blocks`: on the CPU one batched ``numpy.linalg.eigh`` (LAPACK) and
  ``Q f(w) Q^T`` only for the blocks with a negative eigenvalue (``f`` per projection); a Taichi
  Jacobi eigen-solver was slower than LAPACK there for the 15 x 15 reduced Kirchhoff blocks, and a
  Cholesky test that skips the eigen-decomposition of definite blocks pays nothing: at the
  replay's fallback iterates every Kirchhoff block has about 7 negative eigenvalues out of 15. On
  CUDA the cyclic Jacobi kernel (:func:`jacobi_project_blocks`, one block per GPU thread, the block index the
  last and fastest of its arrays so that a warp's loads and stores are coalesced) for many
  blocks: a lockstep batch of 256 Forming copies projects 10^5 such blocks per fallback, several
  seconds of LAPACK; one environment's few hundred blocks go to LAPACK on the host instead
  (:data:`HOST_PROJECTION_MAX_BLOCKS`), where they take less time than the kernel's serial thread.
* :func:`add_blocks` (Taichi, the host path): the projected blocks added into the values of the solver's static
  pattern through the per-element slot map (:meth:`sim_core.assembly.StaticPattern.slot_map`:
  entry ``[e, r, s]`` is a slot or -1), in element order on the CPU (bitwise reproducible), with
  no ``np.bincount`` over the block entries.
* The device path (:meth:`TranslationFreeProjector.add_projected_rows`, :func:`add_upper_block_rows`): the
  reduction, the Jacobi projection and the expansion of the listed blocks as kernels where the blocks are, the
  upper triangles added through the packed upper slot table of the exact Hessian (:func:`upper_slot_table`,
  below; already on the device), so that no block, no full slot map (a lockstep batch of 1024 Forming copies:
  1.1 GB of int32 over its three elastic terms) and no partial sum crosses between host and device.
  :class:`BlockRowsProjector` projects listed blocks of a device array (the contact pairs' of a lockstep batch's
  retried copies) and leaves them there.

The result equals the reference's projected blocks to round-off: the reference reconstructs every
block of a batch in which some block has a negative eigenvalue, and returns the symmetrised block
when none has; here a block is reconstructed only when it has a negative eigenvalue itself.

The fused kernels (``sim_core/energies/<energy>/fused_*kernel.py``), which compute the local upper triangle
``r <= s`` of each symmetric element block, read their slots from :func:`upper_slot_table`: the
slot map folded onto its upper triangle and packed, one int32 per entry (:func:`upper_index`,
:func:`add_upper_entry`), in place of the two entries ``[e, r, s]`` and ``[e, s, r]`` of the full
map and their two tests. Half the memory, one load and one well-predicted test per entry, and the
same sums in the same order (bitwise the same values).
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel and ti.func annotations as
# objects (string annotations are rejected).

import functools

import numpy as np

from sim_core.slot_translation import joined
from sim_core.ti_backend import current_arch, serial_loops, ti
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.buffers import DeviceArray, on_device, rows_on_device
from sim_core.ti_kernels.device_copy import new_ndarray
from sim_core.ti_kernels.householder_projection import householder_project_blocks
from sim_core.ti_kernels.launch import fast_kernel
from sim_core.ti_kernels.transfer import download, fill, upload

_F64_1, _F64_2, _F64_3, _I32_2, _I32_3 = linalg.F64_1, linalg.F64_2, linalg.F64_3, linalg.I32_2, linalg.I32_3
_I32_1 = ti.types.ndarray(dtype=ti.i32, ndim=1)


@functools.lru_cache(maxsize=8)
def helmert_array(vertex_count: int) -> np.ndarray:
    """:func:`~sim_core.ti_kernels.linalg.helmert_basis` as a C-contiguous float64 ``(m, m - 1)`` array."""
    out = np.array(linalg.helmert_basis(vertex_count), dtype=np.float64).reshape(vertex_count, vertex_count - 1)
    out.flags.writeable = False
    return out


@fast_kernel
def add_blocks(blocks: _F64_3, slots: _I32_3, values: _F64_1):
    """``values[slots[e, i, j]] += blocks[e, i, j]`` where the slot is >= 0 (the assembler's keep rule)."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for e in range(blocks.shape[0]):
        for i in range(blocks.shape[1]):
            for j in range(blocks.shape[2]):
                k = slots[e, i, j]
                if k >= 0:
                    values[k] += blocks[e, i, j]


@fast_kernel
def add_block_rows(blocks: _F64_3, slots: _I32_3, rows: _I32_1, count: ti.i32, values: _F64_1):
    """``values[slots[e, i, j]] += blocks[e, i, j]`` for the blocks ``e = rows[r]``, ``r < count``, where the
    slot is >= 0 (:func:`add_blocks` of the listed blocks, in the order listed on the CPU)."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for r in range(count):
        e = rows[r]
        for i in range(blocks.shape[1]):
            for j in range(blocks.shape[2]):
                k = slots[e, i, j]
                if k >= 0:
                    values[k] += blocks[e, i, j]


def upper_slot_table(slots: np.ndarray) -> np.ndarray:
    """The slot map ``slots`` (int32 ``(k, n, n)``, :meth:`sim_core.assembly.StaticPattern.slot_map`)
    folded onto the local upper triangles: int32 ``(k, n (n + 1) / 2)``, entry
    ``[e, upper_index(n, r, s)]`` for ``r <= s`` (row-major).

    A local upper entry ``(r, s)`` goes to ``slots[e, r, s]`` and, for ``r < s``, to
    ``slots[e, s, r]`` (the assembler's rule). At most one of the two is kept, unless local DoFs
    ``r`` and ``s`` are the same global DoF (an element with a repeated vertex); both are then the
    same diagonal slot, which receives the value twice. So the packed entry is that slot (>= 0),
    -1 (not stored: a fixed DoF, or the lower triangle of the global matrix), or ``-2 - slot`` (the
    value goes twice into ``slot``), as :func:`add_upper_entry` reads it.
    """
    k, n, _ = slots.shape
    rows, cols = np.triu_indices(n)
    upper = slots[:, rows, cols]
    lower = np.where(rows != cols, slots[:, cols, rows], -1)
    packed = np.where(upper >= 0, upper, lower)
    packed = np.where((upper >= 0) & (lower >= 0), -2 - upper, packed)
    return np.ascontiguousarray(packed, dtype=np.int32)


class SlotTables:
    """The slot tables of the element blocks over ``vertices`` ``(k, m)`` in ``pattern``
    (:class:`sim_core.static_pattern.StaticPattern`): :attr:`upper`, the packed upper table the fused kernels'
    exact blocks read (:func:`upper_slot_table` of the slot map, int32 ``(k, 3 m (3 m + 1) / 2)``), made here, and
    :attr:`full`, the slot map itself (:meth:`~sim_core.static_pattern.StaticPattern.slot_map`, int32
    ``(k, 3 m, 3 m)``) that only the projected blocks read, made at its first read. Both are the tables of those
    two functions, made for the first chunk of each run of translated chunks
    (:meth:`~sim_core.static_pattern.StaticPattern.slot_runs`: a stacked scene's copies) and moved chunk by
    chunk (:func:`~sim_core.slot_translation.translated`), not folded over every copy's map.

    Raises:
        ValueError: a kept entry that is not in the pattern (its elements were not part of it).
    """

    def __init__(self, pattern, vertices: np.ndarray) -> None:
        m = np.shape(vertices)[1]
        self._runs = pattern.slot_runs(vertices) or [(np.zeros((0, 3 * m, 3 * m), dtype=np.int32), None)]
        self.upper = joined([(upper_slot_table(table), offsets) for table, offsets in self._runs])
        self._full: np.ndarray | None = None

    @property
    def full(self) -> np.ndarray:
        """The slot map (class docstring), int32 ``(k, 3 m, 3 m)``; made at the first read, then kept."""
        if self._full is None:
            self._full = joined(self._runs)
        return self._full


class BoundSlotTables:
    """The slot tables of a fused elastic kernel whose element blocks are those of its ``vertices`` ``(k, m)``
    (a mixin of the fused kernels): :meth:`bind` makes them for a pattern, ``_upper`` is the packed upper table the
    exact blocks read, ``_slots`` the full slot map the projected blocks read (made at its first read)."""

    _tables: SlotTables | None = None
    _upper: np.ndarray | None = None

    def bind(self, pattern) -> None:
        """The slot tables of the blocks in ``pattern`` (:class:`sim_core.static_pattern.StaticPattern`,
        :class:`SlotTables`): packed upper, for the exact blocks, now; full, for the projected ones, at their first
        use."""
        self._tables = SlotTables(pattern, self.vertices)
        self._upper = self._tables.upper

    @property
    def _slots(self) -> np.ndarray | None:
        """The full slot map of the blocks (:attr:`SlotTables.full`): made at its first read; None before
        :meth:`bind`."""
        return None if self._tables is None else self._tables.full


@ti.func
def upper_index(n: ti.template(), r, s):
    """Position of the local upper entry ``(r, s)``, ``r <= s``, of an ``n x n`` block in the rows of
    :func:`upper_slot_table` (row-major; a constant for compile-time ``r``, ``s``)."""
    return r * n - r * (r - 1) // 2 + s - r


@ti.func
def add_upper_entry(values: ti.template(), slot: ti.i32, value: ti.f64):
    """Add ``value`` at a packed slot of :func:`upper_slot_table`: once for ``slot >= 0``, twice at
    ``-2 - slot`` for ``slot <= -2`` (two adds, as the full map's two entries), nothing for -1."""
    if slot >= 0:
        values[slot] += value
    elif slot <= -2:
        values[-2 - slot] += value
        values[-2 - slot] += value


JACOBI_SWEEPS = 60
"""Cyclic Jacobi sweeps at most per block (:func:`jacobi_project_blocks`; 15 x 15 blocks take 6 to 10)."""

HOST_PROJECTION_MAX_BLOCKS = 1024
"""Up to this many reduced blocks, :meth:`TranslationFreeProjector.add_projected_rows` projects them on the host
(one download, LAPACK, one upload) instead of by :func:`jacobi_project_blocks` on the device. The Jacobi kernel
runs one block per GPU thread, serially in global memory: for one Forming environment's 210 Kirchhoff blocks
(15 x 15) it took 7.6 ms a call on average and 15.8 ms at most on the H200 (docs/benchmarks_log.md, session 39),
while LAPACK takes about 10 us a 15 x 15 block on one core. Its time hardly grows with the block count until
the GPU is full, so a lockstep batch's tens of thousands of blocks stay on the device."""


@fast_kernel
def jacobi_project_blocks(blocks: _F64_3, work: _F64_3, vectors: _F64_3, count: ti.i32, code: ti.i32):
    """PSD projection of symmetric blocks in place by the cyclic Jacobi eigenvalue method (Golub & Van
    Loan, Matrix Computations, 4th ed., Sec. 8.5.3; the rotation of their Alg. 8.5.1), one block per
    thread: rotations ``A <- J^T A J`` of a copy (``work``) zero its off-diagonal entries in turn until
    their norm is below ``1e-15`` of the block's, ``V`` (``vectors``) accumulating ``J``. A rotation updates
    only the upper triangle of the symmetric copy: rows / columns ``p``, ``q`` outside the ``2 x 2`` block, and
    that block by ``a_pp - t a_pq``, ``a_qq + t a_pq``, ``0`` (their Sec. 8.5.2; ``t = tan`` of the angle), 4
    ``n`` loads and stores of ``work`` instead of 8 ``n`` for the full ``J^T A J``. A block with a
    negative eigenvalue (a diagonal entry of the rotated copy) is replaced by ``V f(w) V^T`` (``code`` 1
    clamp: ``f(w) = max(w, 0)``, 2 abs: ``|w|``), the others keep their entries.

    The block index is the last (fastest) one: ``blocks`` ``(n, n, k)``, block ``e`` is ``blocks[:, :, e]``, so
    that the threads of a warp, which handle consecutive blocks and run the same rotation, read and write
    consecutive addresses (coalesced on a GPU); the first ``count`` blocks are projected (``count <= k``).
    ``work`` and ``vectors`` are scratch arrays of the blocks' shape. On the GPU all blocks run at once (no host
    round trip for LAPACK)."""
    for e in range(count):
        n = blocks.shape[0]
        total = 0.0
        off = 0.0
        for i in range(n):
            for j in range(n):
                vectors[i, j, e] = 1.0 if i == j else 0.0
                a = 0.5 * (blocks[i, j, e] + blocks[j, i, e])
                total += a * a
                if j > i:
                    off += a * a
                if j >= i:  # the upper triangle is used
                    work[i, j, e] = a
        sweep = 0
        while sweep < JACOBI_SWEEPS and off > 1e-30 * total:
            sweep += 1
            for p in range(n - 1):
                for q in range(p + 1, n):
                    apq = work[p, q, e]
                    if apq != 0.0:
                        theta = (work[q, q, e] - work[p, p, e]) / (2.0 * apq)
                        t = 1.0 / (ti.abs(theta) + ti.sqrt(theta * theta + 1.0))
                        if theta < 0.0:
                            t = -t
                        c = 1.0 / ti.sqrt(t * t + 1.0)
                        s = t * c
                        for k in range(n):  # rows / columns p, q of J^T A J off the 2 x 2 block, upper triangle
                            if k != p and k != q:
                                kp0, kp1 = ti.min(k, p), ti.max(k, p)
                                kq0, kq1 = ti.min(k, q), ti.max(k, q)
                                akp = work[kp0, kp1, e]
                                akq = work[kq0, kq1, e]
                                work[kp0, kp1, e] = c * akp - s * akq
                                work[kq0, kq1, e] = s * akp + c * akq
                        work[p, p, e] = work[p, p, e] - t * apq  # the 2 x 2 block diagonalised
                        work[q, q, e] = work[q, q, e] + t * apq
                        work[p, q, e] = 0.0
                        for k in range(n):  # V J
                            vkp = vectors[k, p, e]
                            vkq = vectors[k, q, e]
                            vectors[k, p, e] = c * vkp - s * vkq
                            vectors[k, q, e] = s * vkp + c * vkq
            off = 0.0
            for i in range(n):
                for j in range(i + 1, n):
                    off += work[i, j, e] * work[i, j, e]
        negative = 0
        for k in range(n):
            if work[k, k, e] < 0.0:
                negative = 1
        if negative == 1:
            for k in range(n):
                w = work[k, k, e]
                work[k, k, e] = ti.max(w, 0.0) if code == 1 else ti.abs(w)
            for i in range(n):
                for j in range(i, n):
                    acc = 0.0
                    for k in range(n):
                        acc += vectors[i, k, e] * work[k, k, e] * vectors[j, k, e]
                    blocks[i, j, e] = acc
                    blocks[j, i, e] = acc


DEVICE_KERNELS = {"jacobi": jacobi_project_blocks, "householder": householder_project_blocks}
"""The projection kernels by method name (one block a thread, block index last; the same projection to round-off)."""

DEVICE_METHOD = "householder"
"""The kernel the device path projects with (:func:`project_reduced_blocks` on CUDA,
:meth:`TranslationFreeProjector.add_projected_rows` beyond :data:`HOST_PROJECTION_MAX_BLOCKS` blocks,
:class:`BlockRowsProjector`): Householder tridiagonalisation and implicit QL, ~4x fewer memory operations a 15 x 15
block than the cyclic Jacobi sweeps (:mod:`sim_core.ti_kernels.householder_projection`; session 54, the retries'
device time measured in docs/gpu_roofline.md)."""


def project_reduced_blocks(blocks: np.ndarray, projection: str, method: str | None = None) -> np.ndarray:
    """PSD projection of symmetric blocks; only blocks with a negative eigenvalue are rebuilt.

    Args:
        blocks: symmetric blocks, shape ``(k, n, n)`` (modified in place and returned).
        projection: ``"clamp"`` (negative eigenvalues -> 0) or ``"abs"`` (-> their absolute value);
            ``"none"`` returns ``blocks`` unchanged.
        method: ``"lapack"`` (one batched ``numpy.linalg.eigh``), ``"jacobi"`` (:func:`jacobi_project_blocks`
            in Taichi), ``"householder"`` (:func:`~sim_core.ti_kernels.householder_projection.householder_project_blocks`
            in Taichi) or None: :data:`DEVICE_METHOD` on CUDA (all blocks at once on the device), LAPACK elsewhere.

    Returns:
        ``blocks``, every block with a negative eigenvalue replaced by ``Q f(w) Q^T``.

    Raises:
        ValueError: unknown projection (the reference's message) or method.
    """
    code = linalg.projection_code(projection)
    if method not in (None, "lapack") + tuple(DEVICE_KERNELS):
        raise ValueError(f"project_reduced_blocks: unknown method {method!r} (lapack, jacobi, householder)")
    if code == 0 or blocks.shape[0] == 0:
        return blocks
    if method is None and current_arch() == "cuda":
        method = DEVICE_METHOD
    if method in DEVICE_KERNELS:
        out = np.ascontiguousarray(np.moveaxis(blocks, 0, -1), dtype=np.float64)  # the kernel's layout (n, n, k)
        DEVICE_KERNELS[method](out, np.empty_like(out), np.empty_like(out), out.shape[2], code)
        blocks[:] = np.moveaxis(out, -1, 0)
        return blocks
    w, q = np.linalg.eigh(blocks)
    negative = np.any(w < 0.0, axis=1)
    if np.all(negative):
        w = np.maximum(w, 0.0) if code == 1 else np.abs(w)
        blocks[:] = np.matmul(q * w[:, None, :], np.swapaxes(q, 1, 2))
    elif np.any(negative):
        w, q = w[negative], q[negative]
        w = np.maximum(w, 0.0) if code == 1 else np.abs(w)
        blocks[negative] = np.matmul(q * w[:, None, :], np.swapaxes(q, 1, 2))
    return blocks


@fast_kernel
def reduce_block_rows(blocks: _F64_3, helmert: _F64_2, rows: _I32_1, count: ti.i32, reduced: _F64_3):
    """``reduced[:, :, r] = sym(B^T H B)`` of the blocks ``H = blocks[rows[r]]`` ``(3 m, 3 m)``, ``r < count``, with
    ``B = helmert (x) I_3`` (``helmert`` ``(m, m - 1)``) and ``sym(A) = (A + A^T) / 2``: one thread an entry,
    ``B^T H B`` summed over the vertex pairs ``(u, v)`` of the Kronecker factor. ``reduced`` ``(3 m - 3, 3 m - 3,
    c)`` is in the layout of :func:`jacobi_project_blocks` (the block index last). The entry indices are the fastest
    of the loop, so that the threads of a warp read one block (``blocks`` is block index first: ``3 m x 3 m``
    consecutive entries, read 72 times a thread) and write one store each: 161,280 Kirchhoff blocks (``m = 6``) in
    2.7 ms on an H100, against 54 ms with the block index fastest, where each of a warp's loads touches 32 blocks
    (measured in session 46: docs/benchmarks_log.md)."""
    m = helmert.shape[0]
    size = 3 * (m - 1)
    for r, a, b in ti.ndrange(count, size, size):
        e = rows[r]
        pa, ca, pb, cb = a // 3, a % 3, b // 3, b % 3
        acc = 0.0
        for u in range(m):
            for v in range(m):
                acc += helmert[u, pa] * helmert[v, pb] * (blocks[e, 3 * u + ca, 3 * v + cb]
                                                         + blocks[e, 3 * v + cb, 3 * u + ca])
        reduced[a, b, r] = 0.5 * acc


@fast_kernel
def expand_add_upper_rows(reduced: _F64_3, helmert: _F64_2, upper: _I32_2, rows: _I32_1, count: ti.i32,
                          values: _F64_1):
    """Add ``(B R B^T)[i, j]``, ``i <= j``, for ``R = reduced[:, :, r]``, ``r < count`` (``B = helmert (x) I_3``), at
    the packed slot ``upper[rows[r], upper_index(3 m, i, j)]`` (:func:`upper_slot_table`, :func:`add_upper_entry`):
    one thread an entry of the upper triangle. ``B R B^T`` is symmetric, so this adds what the full slot map adds
    (to round-off: the entry ``[j, i]`` is summed in another order), with half the expansions."""
    m = helmert.shape[0]
    n = 3 * m
    ti.loop_config(serialize=ti.static(serial_loops()))
    for i, j, r in ti.ndrange(n, n, count):
        if i <= j:
            slot = upper[rows[r], i * n - i * (i - 1) // 2 + j - i]
            if slot != -1:
                u, ci, v, cj = i // 3, i % 3, j // 3, j % 3
                acc = 0.0
                for p in range(m - 1):
                    for q in range(m - 1):
                        acc += helmert[u, p] * helmert[v, q] * reduced[3 * p + ci, 3 * q + cj, r]
                add_upper_entry(values, slot, acc)


@fast_kernel
def add_upper_block_rows(blocks: _F64_3, upper: _I32_2, rows: _I32_1, count: ti.i32, values: _F64_1):
    """Add the upper triangles of the symmetric blocks ``blocks[rows[r]]`` ``(n, n)``, ``r < count``, at their packed
    slots ``upper[rows[r], upper_index(n, i, j)]`` (:func:`upper_slot_table`, :func:`add_upper_entry`): for
    blocks symmetric bit for bit, the values :func:`add_block_rows` adds through the full slot map, from half the
    entries and a table of half the size."""
    n = blocks.shape[1]
    ti.loop_config(serialize=ti.static(serial_loops()))
    for r, i, j in ti.ndrange(count, n, n):
        if i <= j:
            e = rows[r]
            add_upper_entry(values, upper[e, i * n - i * (i - 1) // 2 + j - i], blocks[e, i, j])


def marked_rows(elements: np.ndarray, vertices: np.ndarray | None, closed: bool = False) -> np.ndarray:
    """The rows of ``elements`` ``(k, m)`` (vertex indices) with a vertex marked in ``vertices`` (bool ``(n,)``), int32
    increasing; every row ``0 .. k - 1`` with None. The mask is gathered a column at a time (``m`` gathers of ``k``
    and an or), not as one ``(k, m)`` gather reduced by ``any`` (3-5x the time at 10^6 elements); with ``closed`` (the
    caller's promise that an element's vertices are all marked or none, as whole copies of a stacked scene) the
    first column alone (one gather)."""
    if vertices is None:
        return np.arange(elements.shape[0], dtype=np.int32)
    mask = np.asarray(vertices)
    hit = mask[elements[:, 0]]
    for j in range(1, 1 if closed else elements.shape[1]):
        hit |= mask[elements[:, j]]
    return np.flatnonzero(hit).astype(np.int32)


def projected_rows(kept: dict, elements: np.ndarray, vertices: np.ndarray | None, closed: bool = False) -> np.ndarray:
    """:func:`marked_rows` of ``elements`` for the mask ``vertices``, kept in ``kept`` (a fused part's device dict) for
    the same ``elements`` and ``vertices`` objects and ``closed``: the rows a part staged before the projection's
    kernels were queued (its ``stage_projected_rows``) are the same object at its ``add_projected_on_device``, whose
    uploads of them (:func:`~sim_core.ti_kernels.buffers.rows_on_device`) then find them on the device."""
    entry = kept.get("projected_rows")
    if entry is not None and entry[0] is elements and entry[1] is vertices and entry[2] == closed:
        return entry[3]
    rows = marked_rows(elements, vertices, closed)
    kept["projected_rows"] = (elements, vertices, closed, rows)
    return rows


def stage_projected_rows(kept: dict, elements: np.ndarray, vertices: np.ndarray | None, closed: bool, name: str,
                         projector: "TranslationFreeProjector | None" = None) -> None:
    """A fused part's ``stage_projected_rows``: its :func:`projected_rows` of ``elements`` for ``vertices`` and
    ``closed`` sent to the device now, into its kept array ``name`` (:func:`~sim_core.ti_kernels.buffers.rows_on_device`)
    and, with ``projector``, into the projector's (:meth:`TranslationFreeProjector.stage_rows`), before the projection's
    kernels are queued (:meth:`sim_core.fused_elastic.FusedElastic.projected_hessian_values_device`): its
    ``add_projected_on_device`` then copies nothing (a synchronous copy waits for every kernel queued before it)."""
    if not elements.shape[0]:
        return
    rows = projected_rows(kept, elements, vertices, closed)
    rows_on_device(kept, name, rows)
    if projector is not None:
        projector.stage_rows(rows)


def add_projected_where_run(part, x: np.ndarray, projection: str, values: np.ndarray,
                            vertices: np.ndarray | None = None) -> None:
    """``values`` ``(pattern.keys.size,)`` (host) += a fused part's projected blocks made by its kernels
    (``part.add_projected_on_device``, with ``vertices`` as it takes them): on CUDA summed into device sums kept in
    ``part._device`` under ``"sums"`` (:func:`~sim_core.ti_kernels.buffers.on_device`) and downloaded once, so that
    no block crosses to the host; elsewhere the kernels add into ``values`` directly.

    Raises:
        ValueError: unknown projection (the part's).
    """
    sums = on_device(part._device, "sums", values, scratch=True)
    if sums is values:  # host arrays (CPU arch)
        part.add_projected_on_device(x, projection, values, vertices)
        return
    fill(sums, 0.0)
    part.add_projected_on_device(x, projection, sums, vertices)
    values += download(sums)


class KeptArrays:
    """Taichi ndarrays kept by name between calls (a mixin): :meth:`_kept` of a fixed shape, :meth:`_columns` of a
    block-last array that grows with the largest block count asked for (no allocation while the count does not
    grow)."""

    _device: dict | None = None

    def _kept(self, name: str, shape: tuple, dtype, host: np.ndarray | None = None):
        """A Taichi ndarray ``name`` of ``shape`` kept between calls (reallocated when the shape changes), holding
        ``host`` when given (copied only when it differs from the last copy: the Helmert basis once, one
        environment's rows while they stay the same)."""
        if self._device is None:
            self._device = {}
        kept = self._device.get(name)
        if kept is None:
            kept = self._device[name] = DeviceArray(dtype)
        if host is None or not host.size:
            return kept.ensure(shape)
        return kept.upload(host)

    def _columns(self, name: str, lead: tuple, count: int):
        """The float64 ndarray ``name`` of shape ``lead + (c,)``, ``c >= count`` the largest count asked for."""
        kept = None if self._device is None else self._device.get(name)
        held = 0 if kept is None or kept.shape is None or kept.shape[:-1] != tuple(lead) else kept.shape[-1]
        return self._kept(name, tuple(lead) + (max(int(count), held),), ti.f64)


class TranslationFreeProjector(KeptArrays):
    """Projects translation-invariant element blocks and adds them into slot values (module docstring).

    Args:
        vertex_count: vertices per element ``m`` (blocks are ``3 m x 3 m``).
    """

    def __init__(self, vertex_count: int) -> None:
        self.helmert = helmert_array(vertex_count)
        self.basis = np.kron(self.helmert, np.eye(3))  # B, (3 m, 3 m - 3), orthonormal columns
        self._device: dict[str, DeviceArray] = {}  # the Taichi ndarrays of add_projected_rows, by name
        self._host_reduced: np.ndarray | None = None  # add_projected_rows' host copy of the reduced blocks

    def reduced(self, blocks: np.ndarray) -> np.ndarray:
        """``B^T H B`` of every block ``H`` of ``blocks`` ``(k, 3 m, 3 m)``: ``(k, 3 m - 3, 3 m - 3)``."""
        return np.matmul(np.matmul(self.basis.T, blocks), self.basis)

    def expanded(self, reduced: np.ndarray) -> np.ndarray:
        """``B R B^T`` of every block ``R`` of ``reduced`` ``(k, 3 m - 3, 3 m - 3)``: ``(k, 3 m, 3 m)``."""
        return np.ascontiguousarray(np.matmul(np.matmul(self.basis, reduced), self.basis.T))

    def project(self, blocks: np.ndarray, projection: str) -> np.ndarray:
        """The ``projection`` of symmetric translation-invariant ``blocks`` ``(k, 3 m, 3 m)`` (N/m):
        ``B P(B^T H B) B^T``, a new array.

        Raises:
            ValueError: unknown projection.
        """
        linalg.projection_code(projection)
        if projection == "none" or blocks.shape[0] == 0:
            return np.array(blocks, dtype=np.float64)
        reduced = self.reduced(blocks)
        reduced = 0.5 * (reduced + np.swapaxes(reduced, 1, 2))
        return self.expanded(project_reduced_blocks(reduced, projection))

    def add_projected(self, blocks: np.ndarray, projection: str, slots: np.ndarray, values: np.ndarray) -> None:
        """Add the ``projection`` of ``blocks`` ``(k, 3 m, 3 m)`` (N/m) into ``values`` through ``slots``
        (int32 ``(k, 3 m, 3 m)``, -1 = not stored).

        Raises:
            ValueError: unknown projection.
        """
        if blocks.shape[0] == 0:
            linalg.projection_code(projection)
            return
        add_blocks(self.project(blocks, projection), slots, values)

    def stage_rows(self, rows: np.ndarray) -> None:
        """Send ``rows`` (int32 ``(c,)``) to the device now, before the kernels of a projection are queued, so that
        :meth:`add_projected_rows` of the same rows copies nothing (a synchronous copy waits for every kernel queued
        before it)."""
        if rows.shape[0]:
            self._kept("rows", rows.shape, ti.i32, rows)

    def add_projected_rows(self, blocks, projection: str, upper, rows: np.ndarray, values,
                           method: str | None = None) -> None:
        """:meth:`add_projected` of the blocks ``rows`` (int32 ``(c,)``) of ``blocks`` by kernels where the arrays
        are (Taichi ndarrays on the device), through the packed upper slot table ``upper`` (int32
        ``(k, 3 m (3 m + 1) / 2)``, :func:`upper_slot_table` of the slot map): the reduction ``B^T H B``
        (:func:`reduce_block_rows`) and the expansion and scatter of the upper triangles
        (:func:`expand_add_upper_rows`) as kernels; the reduced blocks' projection by a kernel of
        :data:`DEVICE_KERNELS` where they are, or on the host (:func:`project_reduced_blocks` with LAPACK: the reduced
        blocks downloaded, projected and uploaded, two copies of ``c (3 m - 3)^2`` float64). ``blocks``
        ``(k, 3 m, 3 m)``, ``values``: ndarrays or NumPy arrays; the sums equal :meth:`add_projected`'s to round-off. The reduced blocks' arrays
        are kept and grow with the largest ``c`` asked for (no allocation while the count does not grow).

        Args:
            method: ``"jacobi"`` or ``"householder"`` (that kernel), ``"lapack"`` (the host) or None: LAPACK for at
                most :data:`HOST_PROJECTION_MAX_BLOCKS` blocks (one environment), :data:`DEVICE_METHOD`'s kernel for
                more.

        Raises:
            ValueError: unknown projection or method.
        """
        code = linalg.projection_code(projection)
        if method not in (None, "lapack") + tuple(DEVICE_KERNELS):
            raise ValueError(f"add_projected_rows: unknown method {method!r} (lapack, jacobi, householder)")
        count = int(rows.shape[0])
        if count == 0:
            return
        rows_arg = self._kept("rows", rows.shape, ti.i32, rows)
        if code == 0:
            add_upper_block_rows(blocks, upper, rows_arg, count, values)
            return
        size = self.basis.shape[1]
        reduced = self._columns("reduced", (size, size), count)
        shape = tuple(reduced.shape)
        helmert = self._kept("helmert", self.helmert.shape, ti.f64, self.helmert)
        reduce_block_rows(blocks, helmert, rows_arg, count, reduced)
        if method == "lapack" or (method is None and count <= HOST_PROJECTION_MAX_BLOCKS):
            host = self._host_reduced
            if host is None or host.shape != shape:
                host = self._host_reduced = np.empty(shape)
            download(reduced, host)
            listed = np.moveaxis(host[:, :, :count], -1, 0).copy()  # (count, size, size)
            host[:, :, :count] = np.moveaxis(project_reduced_blocks(listed, projection, method="lapack"), 0, -1)
            upload(reduced, host)
        else:
            work, vectors = (self._kept(name, shape, ti.f64) for name in ("work", "vectors"))
            DEVICE_KERNELS[method or DEVICE_METHOD](reduced, work, vectors, count, code)
        expand_add_upper_rows(reduced, helmert, upper, rows_arg, count, values)


@fast_kernel
def _gather_block_columns(blocks: _F64_3, start: ti.i32, rows: _I32_1, count: ti.i32, columns: _F64_3):
    """``columns[i, j, r] = blocks[start + rows[r], i, j]``, ``r < count``: listed blocks in the layout of
    :func:`jacobi_project_blocks` (block index last)."""
    for i, j, r in ti.ndrange(blocks.shape[1], blocks.shape[2], count):
        columns[i, j, r] = blocks[start + rows[r], i, j]


@fast_kernel
def _block_rows(columns: _F64_3, count: ti.i32, blocks: _F64_3):
    """``blocks[r, i, j] = columns[i, j, r]``, ``r < count`` (the inverse of :func:`_gather_block_columns`)."""
    for r, i, j in ti.ndrange(count, columns.shape[0], columns.shape[1]):
        blocks[r, i, j] = columns[i, j, r]


class BlockRowsProjector(KeptArrays):
    """PSD projection of listed symmetric blocks of an array where the kernels run (a device array on CUDA), the
    result left there: the blocks gathered into the projection kernels' layout (scratch arrays kept here), projected
    by a kernel of :data:`DEVICE_KERNELS` and written back in rows into a new array (no block crosses to the host;
    :func:`project_reduced_blocks` with the same ``method`` to round-off, bit for bit the same arithmetic)."""

    def project(self, blocks, start: int, rows: np.ndarray, projection: str, method: str | None = None):
        """The ``projection`` ("none", "clamp", "abs") of the blocks ``blocks[start + rows[r]]``, ``r < c``, of
        ``blocks`` (float64 ``(k, n, n)`` ndarray, symmetric blocks) as a new float64 ndarray ``(max(c, 1), n, n)``
        (its first ``c`` rows; a new one at each call, so that the blocks of several terms projected in turn stay
        valid together, as the pair kernel's own arrays do); ``rows`` int ``(c,)``; ``method``: a key of
        :data:`DEVICE_KERNELS`, None for :data:`DEVICE_METHOD`.

        Raises:
            ValueError: unknown projection or method.
        """
        code = linalg.projection_code(projection)
        kernel = DEVICE_KERNELS.get(method or DEVICE_METHOD)
        if kernel is None:
            raise ValueError(f"BlockRowsProjector: unknown method {method!r} (jacobi, householder)")
        count = int(rows.shape[0])
        n = int(blocks.shape[1])
        out = new_ndarray(ti.f64, (max(count, 1), n, n))
        if count:
            columns = self._columns("columns", (n, n), count)
            listed = self._kept("rows", (count,), ti.i32, np.ascontiguousarray(rows, dtype=np.int32))
            _gather_block_columns(blocks, int(start), listed, count, columns)
            if code:
                kernel(columns, self._columns("work", (n, n), count), self._columns("vectors", (n, n), count), count,
                       code)
            _block_rows(columns, count, out)
        return out


def compile_kernels() -> None:
    """On CUDA, JIT-compile (or load from Taichi's offline cache) the device path's kernels on one-block Taichi
    ndarrays: the projections (:data:`DEVICE_KERNELS`), the reduction and expansion of
    :meth:`TranslationFreeProjector.add_projected_rows`, the upper-triangle scatter and :class:`BlockRowsProjector`'s
    gathers; nothing on other archs (which take them
    only in tests) or before :func:`sim_core.ti_backend.init_backend`. One environment's projection runs on the host
    (:data:`HOST_PROJECTION_MAX_BLOCKS`), so without this a lockstep batch compiles them at its first projected
    iteration (in its timed steps)."""
    if current_arch() != "cuda":
        return
    m, n = 2, 6
    blocks, columns = new_ndarray(ti.f64, (1, n, n)), new_ndarray(ti.f64, (n, n, 1))
    reduced, work, vectors = (new_ndarray(ti.f64, (n - 3, n - 3, 1)) for _ in range(3))
    rows, values = new_ndarray(ti.i32, (1,)), new_ndarray(ti.f64, (1,))
    upper = new_ndarray(ti.i32, (1, n * (n + 1) // 2))
    helmert = new_ndarray(ti.f64, (m, m - 1))
    upload(helmert, helmert_array(m))
    reduce_block_rows(blocks, helmert, rows, 1, reduced)
    jacobi_project_blocks(reduced, work, vectors, 1, 1)
    householder_project_blocks(reduced, work, vectors, 1, 1)
    expand_add_upper_rows(reduced, helmert, upper, rows, 1, values)
    add_upper_block_rows(blocks, upper, rows, 1, values)
    _gather_block_columns(blocks, 0, rows, 1, columns)
    _block_rows(columns, 1, blocks)
