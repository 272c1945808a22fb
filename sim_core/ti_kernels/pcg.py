"""Batched preconditioned conjugate gradient in Taichi: the block-diagonal Newton system of a lockstep
batch solved on the device, one independent CG per copy.

:class:`BatchedPCG` follows the :class:`~sim_core.linsolve.SymmetricSolver` contract (``factorize``
takes the upper triangle of the symmetric Newton matrix, ``solve`` one right-hand side). The matrix
is ``A = U + U^T - diag(U) + sum_t F E_t F``: an assembled part given by its upper triangle ``U``
(CSR; the fused elastic terms' values in their fixed pattern, whose index arrays travel to the
device once) and a matrix-free part, element Hessians kept as 3x3 vertex blocks ``E_t``
(:class:`VertexBlocks`: contact and friction, never merged into a sparse pattern), ``F`` the
free-DoF mask. On the device ``U`` is expanded to both triangles (a gather through a pattern made
once), so that its product needs no atomics; the preconditioner is each vertex's 3x3 diagonal block
of ``A`` (from ``U`` and the diagonal blocks ``E_t``), inverted, and, where band blocks are given (``bands``:
e.g. each copy's sheet, :func:`~sim_core.batch.sheet_bands.sheet_band_dofs`), on their DoFs the block's own
matrix inverted exactly (:class:`~sim_core.ti_kernels.band_cholesky.BandBlocks`: a block-Jacobi preconditioner
whose large blocks take out the sheet's slow bending modes; on the Forming scene 269 -> 31 CG iterations a solve
at B = 1024). The matrix, the preconditioner and every CG vector stay in Taichi ndarrays (device memory on CUDA;
the stored matrices float64, or float32 with ``precision="mixed"``, :mod:`~sim_core.ti_kernels.precision`; the
vectors and sums float64 either way; the band blocks gathered from the float64 upper triangle); each iteration is
five passes over all copies, and one kernel launch runs :data:`ITERATIONS_PER_LAUNCH` iterations (the passes are its
top-level loops, which Taichi runs one after the other on the device):

* ``A p``: the rows of ``U + U^T - diag(U)`` (one thread a row), then each vertex block ``E_t``
  gathers ``p`` at its column vertex and adds into its row vertex (atomic adds); rows of copies that
  have stopped are skipped;
* per copy ``p.Ap``: :data:`REDUCTION_LANES` threads a copy, each summing a strided share of the
  copy's vertices (listed copy by copy, made once per segmentation) and adding its partial sum once;
* the update ``x += alpha_c p``, ``r -= alpha_c Ap``, ``z = M^-1 r`` with each copy's own
  ``alpha_c = r.z / p.Ap``, and per copy ``r.z`` and ``r.r``, by the same threads (with band blocks: ``z`` on
  their DoFs by the band blocks' tiled substitutions, then per copy ``r.z`` by a pass of its own);
* per copy: ``beta_c``, and the copy stops when ``|r_c| <= rtol |b_c|`` (or after ``p.Ap <= 0``:
  a matrix not positive definite on that copy, which :attr:`BatchedPCG.indefinite` reports);
* ``p = z + beta_c p``.

Copies are independent CGs (Hestenes & Stiefel 1952; preconditioned form: Saad, Iterative Methods
for Sparse Linear Systems, 2nd ed., Alg. 9.1), each with its own step sizes and stopping test, so a
copy's solution does not depend on the others. The host reads the count of running copies, with the per-copy
flags packed beside it (iterations run, indefinite, still running: one int32 array of ``1 + 3 B``, its one
synchronisation) first after the launches that cover the last solve's iterations, then after every launch
(:func:`_launches_before_test`); a copy that has stopped is left unchanged by later passes. The matrix must be
positive definite (the projected Newton matrix): :attr:`BatchedPCG.detects_indefinite` is False, so the solver
assembles the PSD-projected Hessian.
"""

from typing import Sequence

import numpy as np

from sim_core.symmetric_pattern import both_triangles
from sim_core.ti_backend import ti
from sim_core.ti_kernels import device_copy, transfer
from sim_core.ti_kernels.band_cholesky import BandBlocks, band_solve
from sim_core.ti_kernels.buffers import DeviceHessianBlocks, DeviceRows
from sim_core.ti_kernels.copy_vectors import REDUCTION_LANES, copy_sums, lane_count, lane_vertex
from sim_core.ti_kernels.launch import fast_kernel
from sim_core.ti_kernels.precision import VALUES, storage_dtype, stored

_F64 = ti.types.ndarray(dtype=ti.f64, ndim=1)
_I32 = ti.types.ndarray(dtype=ti.i32, ndim=1)


@ti.func
def _full_csr_matvec(indptr: ti.template(), indices: ti.template(), data: ti.template(), p: ti.template(),
                     ap: ti.template(), n: ti.i32):
    """``ap += A p`` for ``A`` stored with both triangles (CSR): one thread a row, no atomics."""
    for i in range(n):
        acc = 0.0
        for k in range(indptr[i], indptr[i + 1]):
            acc += data[k] * p[indices[k]]
        ap[i] += acc


@ti.kernel
def _gather(src: _F64, index: _I32, out: VALUES, count: ti.i32):
    """``out[k] = src[index[k]]`` for ``k < count`` (rounded to ``out``'s type)."""
    for k in range(count):
        out[k] = stored(src[index[k]], out)


@ti.func
def _vertex_blocks_matvec(brow: ti.template(), bcol: ti.template(), bval: ti.template(), free: ti.template(),
                          p: ti.template(), ap: ti.template(), nblocks: ti.i32):
    """``ap += F (sum_t E_t) F p``: ``E_t`` the 3x3 block ``bval[9 t: 9 t + 9]`` (row-major) at vertex rows
    ``brow[t]`` and vertex columns ``bcol[t]``, ``F = diag(free)`` (0 on fixed DoFs); one thread a block,
    a gather of ``p`` and an atomic scatter into ``ap``."""
    for t in range(nblocks):
        r = brow[t]
        c = bcol[t]
        for a in ti.static(range(3)):
            acc = 0.0
            for b in ti.static(range(3)):
                acc += bval[9 * t + 3 * a + b] * free[3 * c + b] * p[3 * c + b]
            ti.atomic_add(ap[3 * r + a], free[3 * r + a] * acc)


@ti.kernel
def _copy_values(src: _F64, dst: VALUES, count: ti.i32):
    """``dst[k] = src[k]`` for ``k < count`` (rounded to ``dst``'s type)."""
    for k in range(count):
        dst[k] = stored(src[k], dst)


@ti.kernel
def _add_diagonal(data: _F64, slots: _I32, diag: _F64, ndiag: ti.i32, fixed: _I32, nfixed: ti.i32):
    """``data[slots[i]] += diag[i]`` (distinct slots), then ``data[fixed[j]] = 1``."""
    for i in range(ndiag):
        data[slots[i]] += diag[i]
    for j in range(nfixed):
        data[fixed[j]] = 1.0


@ti.kernel
def _diag_blocks_csr(indptr: _I32, indices: _I32, data: _F64, blk: _F64, nvert: ti.i32):
    """``blk`` ``(9 nvert,)``: each vertex's 3x3 diagonal block of the upper-triangle CSR matrix (mirrored)."""
    for v in range(nvert):
        for a in ti.static(range(3)):
            for b in ti.static(range(3)):
                blk[9 * v + 3 * a + b] = 0.0
        for a in ti.static(range(3)):
            i = 3 * v + a
            for k in range(indptr[i], indptr[i + 1]):
                j = indices[k]
                if j // 3 == v:
                    blk[9 * v + 3 * a + j % 3] = data[k]
                    blk[9 * v + 3 * (j % 3) + a] = data[k]


@ti.func
def _element_block_position(vertices: ti.template(), first: ti.i32, t: ti.i32, m: ti.i32, at: ti.i32,
                            brow: ti.template(), bcol: ti.template()):
    """Vertex block ``t = (e m + a) m + b`` of element blocks over ``m`` vertices listed from ``vertices[first]``:
    writes its row vertex ``vertices[first + e m + a]`` and column vertex ``vertices[first + e m + b]`` at
    ``brow[at + t]``, ``bcol[at + t]``, and returns ``(e, a, b, at + t)``."""
    e = t // (m * m)
    a = (t // m) % m
    b = t % m
    k = at + t
    brow[k] = vertices[first + e * m + a]
    bcol[k] = vertices[first + e * m + b]
    return e, a, b, k


@ti.kernel
def _expand_element_blocks(vertices: _I32, first: ti.i32, blocks: _F64, offset: ti.i32, count: ti.i32, m: ti.i32,
                           at: ti.i32, brow: _I32, bcol: _I32, bval: VALUES):
    """Vertex blocks ``at + (e m + a) m + b`` of ``count`` element blocks over ``m`` vertices: row vertex
    ``vertices[first + e m + a]``, column vertex ``vertices[first + e m + b]``, values ``blocks`` of element ``e``
    (row-major ``(3m, 3m)`` from ``blocks[offset]``) at rows ``3 a + i``, columns ``3 b + j``."""
    for t in range(count * m * m):
        e, a, b, k = _element_block_position(vertices, first, t, m, at, brow, bcol)
        for i in ti.static(range(3)):
            for j in ti.static(range(3)):
                bval[9 * k + 3 * i + j] = stored(blocks[offset + (e * 3 * m + 3 * a + i) * 3 * m + 3 * b + j], bval)


@ti.kernel
def _expand_device_rows(vertices: _I32, first: ti.i32, blocks: ti.types.ndarray(dtype=ti.f64, ndim=3), start: ti.i32,
                        count: ti.i32, m: ti.i32, at: ti.i32, brow: _I32, bcol: _I32, bval: VALUES):
    """:func:`_expand_element_blocks` of element blocks held as rows ``start .. start + count`` of a
    ``(rows, 3m, 3m)`` ndarray (:class:`~sim_core.ti_kernels.buffers.DeviceRows`)."""
    for t in range(count * m * m):
        e, a, b, k = _element_block_position(vertices, first, t, m, at, brow, bcol)
        for i in ti.static(range(3)):
            for j in ti.static(range(3)):
                bval[9 * k + 3 * i + j] = stored(blocks[start + e, 3 * a + i, 3 * b + j], bval)


@ti.kernel
def _diag_blocks_add(brow: _I32, bcol: _I32, bval: VALUES, free: _F64, blk: _F64, nblocks: ti.i32):
    """``blk += F E_t F`` for every vertex block ``E_t`` on the diagonal (``brow[t] == bcol[t]``)."""
    for t in range(nblocks):
        v = brow[t]
        if bcol[t] == v:
            for a in ti.static(range(3)):
                for b in ti.static(range(3)):
                    ti.atomic_add(blk[9 * v + 3 * a + b], free[3 * v + a] * free[3 * v + b] * bval[9 * t + 3 * a + b])


@ti.kernel
def _invert_blocks(blk: _F64, inv: VALUES, nvert: ti.i32):
    """``inv`` ``(9 nvert,)``: the inverse of each 3x3 block of ``blk`` (its diagonal's inverse when the
    block is singular, 1 where the diagonal is zero), rounded to ``inv``'s type."""
    for v in range(nvert):
        m = ti.Matrix.zero(ti.f64, 3, 3)
        for a in ti.static(range(3)):
            for b in ti.static(range(3)):
                m[a, b] = blk[9 * v + 3 * a + b]
        det = m.determinant()
        scale = ti.abs(m[0, 0]) * ti.abs(m[1, 1]) * ti.abs(m[2, 2])
        out = ti.Matrix.zero(ti.f64, 3, 3)
        if det > 1e-12 * scale and scale > 0:
            out = m.inverse()
        else:
            for a in ti.static(range(3)):
                out[a, a] = 1.0 / m[a, a] if m[a, a] > 0 else 1.0
        for a in ti.static(range(3)):
            for b in ti.static(range(3)):
                inv[9 * v + 3 * a + b] = stored(out[a, b], inv)


@ti.kernel
def _apply(indptr: _I32, indices: _I32, data: VALUES, brow: _I32, bcol: _I32, bval: VALUES, free: _F64, p: _F64,
           ap: _F64, n: ti.i32, nblocks: ti.i32):
    """``ap = A p`` (``ap`` zeroed here) for the operator of :meth:`BatchedPCG.factorize`."""
    for i in range(n):
        ap[i] = 0.0
    _full_csr_matvec(indptr, indices, data, p, ap, n)
    _vertex_blocks_matvec(brow, bcol, bval, free, p, ap, nblocks)


@ti.kernel
def _reset_copies(rz: _F64, bb: _F64, pap: _F64, rz_new: _F64, rr: _F64, active: _I32, bad: _I32, done: _I32,
                  copies: ti.i32):
    """The start of a solve for every copy: running (``active`` 1), not indefinite, no iterations done, its
    sums zero."""
    for c in range(copies):
        rz[c] = 0.0
        bb[c] = 0.0
        pap[c] = 0.0
        rz_new[c] = 0.0
        rr[c] = 0.0
        active[c] = 1
        bad[c] = 0
        done[c] = 0


@ti.kernel
def _start(b: _F64, x: _F64, r: _F64, z: _F64, p: _F64, ap: _F64, inv: VALUES, rz: _F64, bb: _F64, active: _I32,
           order: _I32, start: _I32, nvert: ti.i32, copies: ti.i32):
    """``x = 0``, ``ap = 0``, ``r = b``, ``z = p = M^-1 b``; per copy ``rz = r.z`` and ``bb = b.b`` (zeroed
    before), summed :data:`REDUCTION_LANES` threads a copy (no atomic adds of every DoF into one address)."""
    for v in range(nvert):
        for a in ti.static(range(3)):
            i = 3 * v + a
            acc = 0.0
            for c in ti.static(range(3)):
                acc += inv[9 * v + 3 * a + c] * b[3 * v + c]
            x[i] = 0.0
            ap[i] = 0.0
            r[i] = b[i]
            z[i] = acc
            p[i] = acc
    copy_sums(r, z, rz, active, order, start, copies)
    copy_sums(b, b, bb, active, order, start, copies)


ITERATIONS_PER_LAUNCH = 8
"""CG iterations of one launch of :func:`_cg_iterations`."""

LAUNCHES_PER_TEST = 4
"""Launches of :func:`_cg_iterations` queued on the device before the host first reads whether a copy still runs,
where no earlier solve gives the count (:func:`_launches_before_test`)."""


def _launches_before_test(previous: int) -> int:
    """Launches of :func:`_cg_iterations` queued before the host first reads whether a copy still runs: those that
    cover ``previous``, the iterations of the solver's last solve (the Newton matrices of successive solves are
    alike), or :data:`LAUNCHES_PER_TEST` at the first solve; the host then reads it after every launch. A stopped
    copy's rows are skipped, so the iterations past the last copy's stop cost their passes' launches and the
    skipped threads (about 8 iterations at most, in place of up to ``8 LAUNCHES_PER_TEST - 1``)."""
    return -(-previous // ITERATIONS_PER_LAUNCH) if previous > 0 else LAUNCHES_PER_TEST


@ti.kernel
def _start_banded(r: _F64, z: _F64, p: _F64, rz: _F64, active: _I32, order: _I32, start: _I32, diag_inv: VALUES,
                  fwd: VALUES, back: VALUES, sub_y: _F64, sub_x: _F64, usable: _I32, band_dof: _I32, band_copy: _I32,
                  n: ti.i32, copies: ti.i32, nb: ti.i32, m: ti.i32, tile: ti.i32, tiles: ti.i32):
    """After :func:`_start`: ``z = p = M^-1 r`` with the band blocks' solves on their DoFs, per copy ``rz = r.z``."""
    band_solve(diag_inv, fwd, back, sub_y, sub_x, usable, band_dof, band_copy, active, r, z, nb, m, tile, tiles)
    for c in range(copies):
        rz[c] = 0.0
    copy_sums(r, z, rz, active, order, start, copies)
    for i in range(n):
        p[i] = z[i]


@ti.kernel
def _cg_iterations(indptr: _I32, indices: _I32, data: VALUES, brow: _I32, bcol: _I32, bval: VALUES, free: _F64,
                   inv: VALUES, seg: _I32, order: _I32, start: _I32, x: _F64, r: _F64, z: _F64, p: _F64, ap: _F64,
                   rz: _F64, rz_new: _F64, rr: _F64, bb: _F64, pap: _F64, beta: _F64, active: _I32, bad: _I32,
                   done: _I32, running: _I32, rtol2: ti.f64, n: ti.i32, nblocks: ti.i32, copies: ti.i32,
                   diag_inv: VALUES, fwd: VALUES, back: VALUES, sub_y: _F64, sub_x: _F64, usable: _I32, band_dof: _I32,
                   band_copy: _I32, nb: ti.i32, m: ti.i32, tile: ti.i32, tiles: ti.i32, banded: ti.template()):
    """:data:`ITERATIONS_PER_LAUNCH` CG iterations of every running copy; ``done[c]`` += the iterations copy
    ``c`` ran, ``running[0]`` = copies still running after them. ``order`` lists the vertices copy by copy, copy ``c``'s at
    ``order[start[c]:start[c + 1]]``. Each top-level loop is one device pass, run in order: ``Ap`` (``ap``
    zero on entry and on exit; the CSR part, then the vertex blocks; rows of stopped copies skipped), per
    copy ``p.Ap``, the update of ``x``, ``r``, ``z`` with per-copy ``r.z`` and ``r.r``, the per-copy test
    and ``beta``, and the new ``p``. The per-copy sums run :data:`REDUCTION_LANES` threads a copy."""
    for _ in ti.static(range(ITERATIONS_PER_LAUNCH)):
        for i in range(n):
            if active[seg[i]] != 0:
                acc = 0.0
                for k in range(indptr[i], indptr[i + 1]):
                    acc += data[k] * p[indices[k]]
                ap[i] += acc
        for t in range(nblocks):
            rv = brow[t]
            if active[seg[3 * rv]] != 0:
                cv = bcol[t]
                for a in ti.static(range(3)):
                    acc = 0.0
                    for b in ti.static(range(3)):
                        acc += bval[9 * t + 3 * a + b] * free[3 * cv + b] * p[3 * cv + b]
                    ti.atomic_add(ap[3 * rv + a], free[3 * rv + a] * acc)
        copy_sums(p, ap, pap, active, order, start, copies)
        for c, k in ti.ndrange(copies, REDUCTION_LANES):
            if active[c] != 0 and pap[c] > 0:
                alpha = rz[c] / pap[c]
                rz_acc = 0.0
                rr_acc = 0.0
                for q in range(lane_count(start, c, k)):
                    v = lane_vertex(order, start, c, k, q)
                    for a in ti.static(range(3)):
                        i = 3 * v + a
                        x[i] += alpha * p[i]
                        r[i] -= alpha * ap[i]
                    for a in ti.static(range(3)):
                        acc = 0.0
                        for b in ti.static(range(3)):
                            acc += inv[9 * v + 3 * a + b] * r[3 * v + b]
                        z[3 * v + a] = acc
                        rz_acc += r[3 * v + a] * acc
                        rr_acc += r[3 * v + a] * r[3 * v + a]
                if ti.static(not banded):
                    ti.atomic_add(rz_new[c], rz_acc)
                ti.atomic_add(rr[c], rr_acc)
        if ti.static(banded):  # z = L^-T L^-1 r on the band blocks' DoFs, then per copy r.z
            band_solve(diag_inv, fwd, back, sub_y, sub_x, usable, band_dof, band_copy, active, r, z, nb, m, tile, tiles)
            copy_sums(r, z, rz_new, active, order, start, copies)
        for c in range(copies):
            b = 0.0
            if active[c] != 0:
                done[c] += 1
                if pap[c] <= 0:
                    active[c] = 0
                    if bb[c] > 0:
                        bad[c] = 1
                elif rr[c] <= rtol2 * bb[c]:
                    active[c] = 0
                else:
                    b = rz_new[c] / rz[c]
                    rz[c] = rz_new[c]
            beta[c] = b
            rz_new[c] = 0.0
            rr[c] = 0.0
            pap[c] = 0.0
        for i in range(n):
            s = seg[i]
            if active[s] != 0:
                p[i] = z[i] + beta[s] * p[i]
            ap[i] = 0.0
    for _ in range(1):
        running[0] = 0
    for c in range(copies):
        ti.atomic_add(running[0], active[c])


class VertexBlocks:
    """A sum of 3x3 vertex blocks, the matrix-free part of a Newton matrix (element Hessians kept as blocks,
    never assembled): ``sum_t F E_t F`` with ``E_t`` at vertex rows ``rows[t]`` and vertex columns
    ``cols[t]``, ``F = diag(free)``.

    Made from explicit vertex blocks (``VertexBlocks(rows, cols, values, free)``) or from element Hessians
    (:meth:`from_element_blocks`, which keeps the element sets: :meth:`BatchedPCG.factorize` uploads them as
    they are and expands them into vertex blocks by a kernel, where they are; ``rows``, ``cols`` and
    ``values`` are then made on the host only when read).

    Args:
        rows, cols: vertex indices, int ``(K,)``.
        values: the blocks, ``(K, 3, 3)`` float64 (N/m).
        free: the free-DoF mask, ``(3 N,)`` bool (a fixed DoF's rows and columns are dropped).

    Attributes:
        free: the free-DoF mask, ``(3 N,)`` bool.
        count: number of vertex blocks ``K``.
        sets: None, or the element sets ``[(vertices int32 (k, m), blocks float64 (k, 3m, 3m))]`` (C order;
            ``blocks`` a NumPy array, or :class:`~sim_core.ti_kernels.buffers.DeviceRows` kept on the device).
    """

    def __init__(self, rows: np.ndarray, cols: np.ndarray, values: np.ndarray, free: np.ndarray) -> None:
        self._vertex_form: tuple | None = (np.asarray(rows, dtype=np.int32), np.asarray(cols, dtype=np.int32),
                                           np.asarray(values, dtype=np.float64).reshape(-1, 3, 3))
        self.free = np.asarray(free, dtype=bool)
        self.count = int(self._vertex_form[0].size)
        self.sets: list | None = None

    @classmethod
    def from_element_blocks(cls, element_blocks: Sequence, free: np.ndarray) -> "VertexBlocks":
        """The vertex blocks of element Hessians: each :class:`~sim_core.energies.base.HessianBlocks`
        (``vertices`` ``(k, m)``, ``blocks`` ``(k, 3m, 3m)``, symmetric) gives its ``k m^2`` 3x3 blocks
        ``(a, b)`` at vertices ``(vertices[e, a], vertices[e, b])``, in the order of the sets, elements,
        ``a`` and ``b``.

        Args:
            element_blocks: the element Hessians (any number of sets, any ``m``):
                :class:`~sim_core.energies.base.HessianBlocks`, or
                :class:`~sim_core.ti_kernels.buffers.DeviceHessianBlocks` (blocks left on the device).
            free: the free-DoF mask, ``(3 N,)`` bool.
        """
        out = cls.__new__(cls)
        out.sets = [(np.ascontiguousarray(b.vertices, dtype=np.int32),
                     b.blocks if isinstance(b, DeviceHessianBlocks)
                     else np.ascontiguousarray(b.blocks, dtype=np.float64))
                    for b in element_blocks if np.shape(b.vertices)[0]]
        out.free = np.asarray(free, dtype=bool)
        out.count = sum(v.shape[0] * v.shape[1] ** 2 for v, _ in out.sets)
        out._vertex_form = None
        return out

    @property
    def rows(self) -> np.ndarray:
        """Row vertex of each block, int32 ``(K,)``."""
        return self._vertex_blocks()[0]

    @property
    def cols(self) -> np.ndarray:
        """Column vertex of each block, int32 ``(K,)``."""
        return self._vertex_blocks()[1]

    @property
    def values(self) -> np.ndarray:
        """The blocks, ``(K, 3, 3)`` float64 (N/m)."""
        return self._vertex_blocks()[2]

    def _vertex_blocks(self) -> tuple:
        if self._vertex_form is None:
            rows = np.empty(self.count, dtype=np.int32)
            cols = np.empty(self.count, dtype=np.int32)
            values = np.empty((self.count, 3, 3))
            at = 0
            for v, blocks in self.sets:  # each set written once into its slice (no concatenation)
                k, m = v.shape
                if isinstance(blocks, DeviceRows):
                    blocks = blocks.to_numpy()
                part = slice(at, at + k * m * m)
                rows[part].reshape(k, m, m)[...] = v[:, :, None]
                cols[part].reshape(k, m, m)[...] = v[:, None, :]
                values[part].reshape(k, m, m, 3, 3)[...] = blocks.reshape(k, m, 3, m, 3).transpose(0, 1, 3, 2, 4)
                at = part.stop
            self._vertex_form = (rows, cols, values)
        return self._vertex_form


class BatchedPCG:
    """Block-Jacobi preconditioned CG for a block-diagonal symmetric positive definite matrix, one CG per
    block (module docstring); Taichi must be initialised (a Taichi solver backend).

    Args:
        segments: the block (copy) of each DoF, shape ``(n,)`` int, values ``0..B-1``, constant over a
            vertex's three DoFs; None: one block.
        rtol: per copy, stop at ``|r| <= rtol |b|``.
        max_iterations: CG iterations per solve at most (copies not converged by then keep their
            last iterate, and :attr:`unconverged` lists them).
        bands: None, or blocks of DoFs preconditioned by their own matrix, shape ``(nb, m)`` int, each row one
            copy's DoFs in a band-limiting order, -1 padding (:class:`~sim_core.ti_kernels.band_cholesky.BandBlocks`).
        precision: ``"double"``, or ``"mixed"``: the operator's stored values (the both-triangle CSR values, the
            vertex blocks) and the preconditioner (the vertex inverses, the band blocks' tiles) kept as float32,
            the vectors and sums float64 (:mod:`~sim_core.ti_kernels.precision`; for a loose ``rtol`` only).

    Raises:
        ValueError: ``bands`` without ``segments``.
        ConfigError: an unknown ``precision``.

    Attributes:
        name: ``"pcg"``.
        detects_indefinite: False (the Newton solver then assembles the projected Hessian).
        factorizations: :meth:`factorize` calls.
        iterations: CG iterations of the last solve (of the copy that ran the most).
        total_iterations: :attr:`iterations` summed over every solve so far.
        indefinite: copies whose matrix showed ``p.Ap <= 0`` in the last solve, shape ``(B,)`` bool.
        unconverged: copies still running after ``max_iterations``, shape ``(B,)`` bool.
        bands: the band blocks on the device (:class:`~sim_core.ti_kernels.band_cholesky.BandBlocks`, made at the
            first :meth:`factorize`), or None.
    """

    name = "pcg"
    device_copies = False
    """Whether :meth:`factorize` takes its ``copies`` as a device array too (here: a bool host mask only)."""
    direct = False
    """Whether a solve after :meth:`factorize` is a substitution with kept factors (here: CG iterations)."""
    detects_indefinite = False

    def __init__(self, segments: "np.ndarray | None" = None, rtol: float = 1e-10, max_iterations: int = 5000,
                 bands: "np.ndarray | None" = None, precision: str = "double") -> None:
        if bands is not None and segments is None:
            raise ValueError("BatchedPCG: band blocks need the segments")
        self.precision = precision
        self._dtype = storage_dtype(precision)  # of the stored matrices: full_data, bval, inv, the band tiles
        self.rtol = float(rtol)
        self._band_dofs = None if bands is None else np.asarray(bands)
        self.bands: BandBlocks | None = None  # made at the first factorize (Taichi initialised by then)
        self._banded = False
        self.max_iterations = int(max_iterations)
        self.factorizations = 0
        self.iterations = 0
        self.total_iterations = 0
        self._segments = None if segments is None else np.ascontiguousarray(segments, dtype=np.int32)
        self._arrays: dict[str, object] = {}
        self._uploaded: dict[str, np.ndarray] = {}  # name -> the host array last uploaded there
        self._staging: dict[str, np.ndarray] = {}  # name -> the host staging array of a _staged device array
        self._nblocks = 0
        self._full: tuple | None = None  # (indptr, indices, nnz) of the both-triangle pattern (_full_pattern)
        self._n = -1
        self.indefinite = np.zeros(0, dtype=bool)
        self.unconverged = np.zeros(0, dtype=bool)

    def _array(self, name: str, size: int, dtype=ti.f64):
        arr = self._arrays.get(name)
        if arr is None or arr.shape != (size,):
            arr = device_copy.new_ndarray(dtype, (size,))
            self._arrays[name] = arr
        return arr

    def _upload(self, name: str, host: np.ndarray, dtype) -> object:
        """The device copy of ``host`` (1-D) as ``name``, uploaded only when ``host`` is not the array
        object uploaded last under that name (index arrays of a fixed pattern travel once)."""
        size = max(host.size, 1)
        kept = self._arrays.get(name)
        arr = self._array(name, size, dtype)
        if self._uploaded.get(name) is not host or arr is not kept:
            np_type = np.int32 if dtype == ti.i32 else np.float64
            _copy_in(arr, np.ascontiguousarray(host, dtype=np_type) if host.size else np.zeros(1, np_type))
            self._uploaded[name] = host
        return arr

    def _resident(self, name: str, size: int, dtype=ti.f64):
        """A 1-D device array ``name`` of at least ``size`` entries, kept while it is large enough and else made
        anew with half again the room (so that a count that changes every Newton iteration, e.g. the contact
        blocks', allocates nothing in the steady state: the kernels take the count, not the array's length)."""
        arr = self._arrays.get(name)
        if arr is None or arr.shape[0] < size or arr.dtype != dtype:
            kept = 0 if arr is None or arr.dtype != dtype else arr.shape[0]
            arr = self._arrays[name] = device_copy.new_ndarray(dtype, (max(size, kept + kept // 2, 1),))
        return arr

    def _staged(self, name: str, parts: Sequence[np.ndarray], dtype) -> object:
        """The 1-D arrays ``parts`` one after the other in the device array ``name`` (:meth:`_resident`), in one
        upload of their total from a host staging array of the same capacity (kept beside it); returns the device
        array (entries past the total are left as they were)."""
        total = sum(int(part.size) for part in parts)
        arr = self._resident(name, total, dtype)
        np_type = np.int32 if dtype == ti.i32 else np.float64
        host = self._staging.get(name)
        if host is None or host.shape != tuple(arr.shape):
            host = self._staging[name] = np.zeros(arr.shape, dtype=np_type)
        at = 0
        for part in parts:
            host[at: at + part.size] = part
            at += part.size
        if total and not device_copy.to_device(arr, host, rows=total):
            arr.from_numpy(host)
        return arr

    def factorize(self, upper, blocks: "VertexBlocks | None" = None, diagonal: tuple | None = None,
                  copies: "np.ndarray | None" = None, keep_bands: bool = False) -> bool:
        """Keep the matrix ``A = U + U^T - diag(U) + sum_t F E_t F`` on the device and build its block-Jacobi
        preconditioner (each vertex's 3x3 diagonal block of ``A``, inverted); True.

        Args:
            upper: ``U``, the upper triangle of the assembled part, shape ``(n, n)``, ``n`` a multiple of 3:
                a CSR matrix, or ``(indptr, indices, data)`` CSR arrays (when ``indptr`` and ``indices``
                are the objects of the last call, only ``data`` travels to the device; ``data`` may be a
                Taichi ndarray already on the device, copied there without a host round trip).
            blocks: the matrix-free part (element Hessians as vertex blocks, :class:`VertexBlocks`), or
                None; the product ``A p`` gathers, multiplies and scatters them on the device.
            diagonal: None, or ``(slots, values, fixed)`` applied to ``U``'s data on the device before
                anything else: ``data[slots] += values`` (int ``(m,)`` distinct positions in ``data``,
                float ``(m,)``), then ``data[fixed] = 1`` (int ``(f,)``). Index arrays of the same objects
                as at the last call travel once.
            copies: None, or bool ``(B,)``: the band blocks of these copies only are factorised (the others' not
                used by the next solves, which take the vertex blocks' inverses there: for copies solved with a zero
                right-hand side, which stop at once either way, e.g. a Newton iteration's copies not retried).
            keep_bands: the band blocks' factors of the last call that made them kept as they are (not gathered from
                this matrix nor factorised again): the CG solves this matrix with a preconditioner of an earlier one
                (e.g. of the step's first Newton matrix); ignored before the band blocks were first factorised.

        Raises:
            ValueError: ``n`` is not a multiple of 3, does not match the segments, or the blocks' free
                mask is not of size ``n``.
        """
        indptr_h, indices_h, data_h, n = self._checked_csr(upper, blocks)
        keep_bands = keep_bands and self._banded
        if self.bands is not None and not keep_bands:  # a selection's mask copied before the launches below
            self.bands.select(copies)
        data = self._csr_on_device(indptr_h, indices_h, data_h, diagonal)
        seg = self._upload_segments()
        self._copy_order(seg)
        nvert = n // 3
        blk = self._array("blk", max(3 * n, 1))
        _diag_blocks_csr(self._arrays["indptr"], self._arrays["indices"], data, blk, nvert)
        full = self._full_operator(indptr_h, indices_h, data, n)
        brow, bcol, bval, free = self._blocks_on_device(blocks)
        if self._nblocks:
            _diag_blocks_add(brow, bcol, bval, free, blk, self._nblocks)
        _invert_blocks(blk, self._array("inv", max(3 * n, 1), self._dtype), nvert)
        if self._band_dofs is not None and not keep_bands:
            if self.bands is None:
                self.bands = BandBlocks(self._band_dofs, seg, dtype=self._dtype)
            a = self._arrays
            self._banded = bool(full[2]) and self.bands.assemble(
                a["full_indptr"], a["full_indices"], data, (brow, bcol, bval, free, self._nblocks), full,
                data_index=a["full_src"], copies=copies)
        return True

    def _checked_csr(self, upper, blocks: "VertexBlocks | None") -> tuple:
        """``upper``'s CSR arrays ``(indptr_h, indices_h, data_h, n)``, checked against the segments and ``blocks``'
        free mask (:meth:`factorize`'s ``ValueError``); counts the factorisation and sets the size and copies."""
        if isinstance(upper, tuple):
            indptr_h, indices_h, data_h = upper
        else:
            indptr_h, indices_h, data_h = upper.indptr, upper.indices, upper.data
        n = int(indptr_h.shape[0]) - 1
        if n % 3 or (self._segments is not None and self._segments.shape != (n,)):
            raise ValueError(f"BatchedPCG: matrix of size {n} for {None if self._segments is None else self._segments.shape[0]} "
                             f"segment entries (n must be a multiple of 3)")
        if blocks is not None and blocks.free.shape != (n,):
            raise ValueError(f"BatchedPCG: vertex blocks with a free mask of shape {blocks.free.shape}, expected ({n},)")
        self.factorizations += 1
        self._n = n
        self._copies = int(self._segments.max()) + 1 if self._segments is not None and n else 1
        return indptr_h, indices_h, data_h, n

    def _upload_segments(self) -> np.ndarray:
        """Each DoF's copy (the segments, or all 0) on the device as ``seg`` (uploaded once); returns the host array."""
        seg = self._segments if self._segments is not None else self._one_copy_segments()
        self._upload("seg", seg, ti.i32)
        return seg

    def _one_copy_segments(self) -> np.ndarray:
        """Without segments: ``n`` zeros, int32, the same host object while ``n`` stays (uploaded once)."""
        kept = self._staging.get("seg")
        if kept is None or kept.shape != (self._n,):
            kept = self._staging["seg"] = np.zeros(self._n, dtype=np.int32)
        return kept

    def _csr_on_device(self, indptr_h: np.ndarray, indices_h: np.ndarray, data_h, diagonal: tuple | None):
        """``U``'s CSR arrays on the device (``indptr``, ``indices`` uploaded only when other objects than at the
        last call; ``data_h`` uploaded, or copied on the device when it is a Taichi ndarray) and ``diagonal``
        (:meth:`factorize`) applied to its values; returns the values' device array ``data``."""
        nnz = int(indptr_h[-1])
        self._upload("indptr", indptr_h, ti.i32)
        self._upload("indices", indices_h if indices_h.size == nnz else indices_h[:nnz], ti.i32)
        data = self._array("data", max(nnz, 1))
        if nnz and isinstance(data_h, np.ndarray):
            transfer.upload(data, data_h[:nnz])
        elif nnz:
            _copy_values(data_h, data, nnz)
        if diagonal is not None and nnz:
            slots, values, fixed = diagonal
            _add_diagonal(data, self._upload("diag_slots", slots, ti.i32), self._upload("diag", values, ti.f64),
                          int(np.size(slots)), self._upload("fixed_slots", fixed, ti.i32), int(np.size(fixed)))
        return data

    def _full_operator(self, indptr_h: np.ndarray, indices_h: np.ndarray, data, n: int) -> tuple:
        """The both-triangle operator's values ``full_data`` (in the stored precision) gathered from ``U``'s device
        values ``data`` in the pattern of :meth:`_full_pattern`; returns that pattern's tuple."""
        full = self._full_pattern(indptr_h, indices_h, n)
        full_data = self._array("full_data", max(full[2], 1), self._dtype)
        if full[2]:
            _gather(data, self._arrays["full_src"], full_data, full[2])
        return full

    def _blocks_on_device(self, blocks: "VertexBlocks | None") -> tuple:
        """The vertex blocks ``(brow, bcol, bval, free)`` on the device (element sets expanded there; ``free`` uploaded
        once); sets their count."""
        self._nblocks = 0 if blocks is None else int(blocks.count)
        # the vertex blocks' arrays keep their capacity (the contact set's count changes every Newton iteration)
        brow = self._resident("brow", self._nblocks, ti.i32)
        bcol = self._resident("bcol", self._nblocks, ti.i32)
        bval = self._resident("bval", 9 * self._nblocks, self._dtype)
        free = self._upload("free", np.ones(1) if blocks is None else blocks.free, ti.f64)
        if self._nblocks and blocks.sets is not None:  # element sets uploaded as they are, expanded here
            verts_dev = self._staged("element_vertices", [verts.reshape(-1) for verts, _ in blocks.sets], ti.i32)
            host_sets = [vals.reshape(-1) for _, vals in blocks.sets if not isinstance(vals, DeviceRows)]
            vals_dev = self._staged("element_blocks", host_sets, ti.f64) if host_sets else None
            at = first = offset = 0
            for verts, vals in blocks.sets:
                k, m = verts.shape
                if isinstance(vals, DeviceRows):  # already on the device: no transfer
                    _expand_device_rows(verts_dev, first, vals.array, vals.start, k, m, at, brow, bcol, bval)
                else:
                    _expand_element_blocks(verts_dev, first, vals_dev, offset, k, m, at, brow, bcol, bval)
                    offset += vals.size
                first += verts.size
                at += k * m * m
        elif self._nblocks:
            self._staged("brow", [blocks.rows], ti.i32)
            self._staged("bcol", [blocks.cols], ti.i32)
            _copy_values(self._staged("bval_host", [blocks.values.reshape(-1)], ti.f64), bval, 9 * self._nblocks)
        return brow, bcol, bval, free

    def _copy_order(self, seg: np.ndarray) -> None:
        """The vertices grouped by copy on the device (``order``, ``start``: copy ``c``'s vertices are
        ``order[start[c]:start[c + 1]]``, in increasing order), for the per-copy sums of the CG; made again
        only when ``seg`` is another object than at the last call."""
        if self._uploaded.get("order_of") is seg:
            return
        vertex_copy = seg[::3]
        order = np.argsort(vertex_copy, kind="stable").astype(np.int32)
        start = np.zeros(self._copies + 1, dtype=np.int32)
        np.cumsum(np.bincount(vertex_copy, minlength=self._copies), out=start[1:])
        self._upload("order", order, ti.i32)
        self._upload("start", start, ti.i32)
        self._uploaded["order_of"] = seg

    def _full_pattern(self, indptr_h: np.ndarray, indices_h: np.ndarray, n: int) -> tuple:
        """The pattern of ``U + U^T - diag(U)`` (both triangles,
        :func:`~sim_core.symmetric_pattern.both_triangles`) of the upper-triangle CSR arrays: its ``indptr`` and
        ``indices`` on the device as ``full_indptr``, ``full_indices``,
        and ``full_src``, the position in ``U``'s data of each entry, so that the CG's product needs no atomics (one
        thread a row). Made again only when ``indptr_h`` or ``indices_h`` are other objects than at the last call.
        Returns ``(indptr_h, indices_h, full nnz)``."""
        kept = self._full
        if kept is not None and kept[0] is indptr_h and kept[1] is indices_h:
            return kept
        full_indptr, full_indices, source = both_triangles(indptr_h, indices_h, n)
        _copy_in(self._array("full_indptr", n + 1, ti.i32), full_indptr.astype(np.int32, copy=False))
        size = max(full_indices.size, 1)
        _copy_in(self._array("full_indices", size, ti.i32),
                 full_indices.astype(np.int32, copy=False) if full_indices.size else np.zeros(1, np.int32))
        _copy_in(self._array("full_src", size, ti.i32),
                 source.astype(np.int32, copy=False) if source.size else np.zeros(1, np.int32))
        self._full = (indptr_h, indices_h, int(full_indices.size))
        return self._full

    def _band_arguments(self) -> tuple:
        """The band blocks' device arrays for the CG kernels, then ``(nb, m, t, nt)``; placeholders when unused."""
        if self._banded:
            return (*self.bands.arguments(), self.bands.sizes())
        one_v, one_f = self._array("band_none_v", 1, self._dtype), self._array("band_none", 1)
        one_i = self._array("band_none_i", 1, ti.i32)
        return one_v, one_v, one_v, one_f, one_f, one_i, one_i, one_i, (0, 1, 1, 1)

    def _operator(self) -> tuple:
        a = self._arrays
        return a["full_indptr"], a["full_indices"], a["full_data"], a["brow"], a["bcol"], a["bval"], a["free"]

    def matvec(self, p: np.ndarray) -> np.ndarray:
        """``A p`` on the device for the matrix of the last :meth:`factorize` (``p`` shape ``(n,)``)."""
        if self._n < 0:
            raise RuntimeError("BatchedPCG: factorize before matvec")
        p = np.ascontiguousarray(p, dtype=np.float64)
        if p.shape != (self._n,):
            raise ValueError(f"BatchedPCG: vector of shape {p.shape}, expected ({self._n},)")
        pin = self._array("mv_in", max(self._n, 1))
        out = self._array("mv_out", max(self._n, 1))
        if self._n:
            transfer.upload(pin, p)
        _apply(*self._operator(), pin, out, self._n, self._nblocks)
        return transfer.download(out)[: self._n]

    def solve(self, b: np.ndarray) -> np.ndarray:
        """Solve ``A x = b`` (``b`` shape ``(n,)``) per copy to ``|r_c| <= rtol |b_c|``; returns ``x``."""
        n = self._n
        if n < 0:
            raise RuntimeError("BatchedPCG: factorize before solve")
        b = np.ascontiguousarray(b, dtype=np.float64)
        if b.shape != (n,):
            raise ValueError(f"BatchedPCG: right-hand side of shape {b.shape}, expected ({n},)")
        if n == 0:
            return np.zeros(0)
        transfer.upload(self._array("b", n), b)
        self._run()
        return transfer.download(self._arrays["x"])

    def solve_on_device(self, b, out) -> None:
        """:meth:`solve` from and into device memory: ``b`` and the solution ``out`` are float64 Taichi ndarrays
        ``(n / 3, 3)`` (a vertex's three DoFs a row, as the lockstep's stacked vectors,
        :mod:`sim_core.ti_kernels.copy_vectors`); nothing crosses to the host but the per-copy counts.

        Raises:
            RuntimeError: no :meth:`factorize` before.
            ValueError: ``b`` or ``out`` not of shape ``(n / 3, 3)``.
        """
        n = self._n
        if n < 0:
            raise RuntimeError("BatchedPCG: factorize before solve")
        for name, a in (("right-hand side", b), ("solution", out)):
            if tuple(a.shape) != (n // 3, 3):
                raise ValueError(f"BatchedPCG: {name} of shape {tuple(a.shape)}, expected ({n // 3}, 3)")
        if n == 0:
            return
        _flatten(b, self._array("b", n), n // 3)
        self._run()
        _unflatten(self._arrays["x"], out, n // 3)

    def _run(self) -> None:
        """The CG iterations of every copy from the right-hand side in the ``b`` array into ``x``; sets
        :attr:`iterations`, :attr:`indefinite` and :attr:`unconverged`."""
        n, B = self._n, self._copies
        a = self._arrays
        vec = {k: self._array(k, n) for k in ("b", "x", "r", "z", "p", "ap")}
        per = {k: self._array(k, B) for k in ("rz", "bb", "pap", "rz_new", "rr", "beta")}
        active = self._array("active", B, ti.i32)
        bad = self._array("bad", B, ti.i32)
        done = self._array("done", B, ti.i32)
        _reset_copies(per["rz"], per["bb"], per["pap"], per["rz_new"], per["rr"], active, bad, done, B)
        _start(vec["b"], vec["x"], vec["r"], vec["z"], vec["p"], vec["ap"], a["inv"], per["rz"], per["bb"], active,
               a["order"], a["start"], n // 3, B)
        band = self._band_arguments()
        if self._banded:
            _start_banded(vec["r"], vec["z"], vec["p"], per["rz"], active, a["order"], a["start"], *band[:-1], n, B,
                          *band[-1])
        rtol2 = self.rtol ** 2
        running = self._array("running", 1, ti.i32)
        flags = self._array("flags", 1 + 3 * B, ti.i32)
        launched = 0
        batch = _launches_before_test(self.iterations)
        read = None
        while launched < self.max_iterations:
            for _ in range(min(batch, -(-(self.max_iterations - launched) // ITERATIONS_PER_LAUNCH))):
                launched += ITERATIONS_PER_LAUNCH
                _cg_iterations(*self._operator(), a["inv"], a["seg"], a["order"], a["start"], vec["x"], vec["r"],
                               vec["z"], vec["p"], vec["ap"], per["rz"], per["rz_new"], per["rr"], per["bb"], per["pap"],
                               per["beta"], active, bad, done, running, rtol2, n, self._nblocks, B, *band[:-1],
                               *band[-1], self._banded)
            _pack_flags(running, done, bad, active, flags, B)
            read = _copy_out(flags)  # the host's one wait for the device in these launches: the count and the flags
            if int(read[0]) == 0:
                break
            batch = 1
        if read is None:  # (no iteration allowed: the flags as _reset_copies left them)
            _pack_flags(running, done, bad, active, flags, B)
            read = _copy_out(flags)
        self.iterations = int(read[1:1 + B].max()) if B else 0
        self.total_iterations += self.iterations
        self.indefinite = read[1 + B:1 + 2 * B].astype(bool)
        self.unconverged = read[1 + 2 * B:1 + 3 * B].astype(bool)


@fast_kernel
def _pack_flags(running: _I32, done: _I32, bad: _I32, active: _I32, flags: _I32, copies: ti.i32):
    """The CG's count of running copies and its per-copy flags in one int32 array of ``1 + 3 B``, so that the host
    reads them in one copy (:meth:`BatchedPCG._run`): ``flags[0]`` the running copies (``running[0]``), then
    ``done`` (iterations a copy ran), ``bad`` (indefinite) and ``active`` (still running), ``B`` entries each."""
    flags[0] = running[0]
    for c in range(copies):
        flags[1 + c] = done[c]
        flags[1 + copies + c] = bad[c]
        flags[1 + 2 * copies + c] = active[c]


@fast_kernel
def _flatten(rows: ti.types.ndarray(dtype=ti.f64, ndim=2), flat: _F64, nvert: ti.i32):
    """``flat[3 v + j] = rows[v, j]``."""
    for v in range(nvert):
        for j in ti.static(range(3)):
            flat[3 * v + j] = rows[v, j]


@fast_kernel
def _unflatten(flat: _F64, rows: ti.types.ndarray(dtype=ti.f64, ndim=2), nvert: ti.i32):
    """``rows[v, j] = flat[3 v + j]``."""
    for v in range(nvert):
        for j in ti.static(range(3)):
            rows[v, j] = flat[3 * v + j]


def _copy_in(array, host: np.ndarray) -> None:
    """``host`` (C-contiguous, ``array``'s dtype and size) into the 1-D ndarray ``array``: a byte copy
    (:mod:`sim_core.ti_kernels.device_copy`) where one can be made here, else Taichi's ``from_numpy``."""
    if array.dtype == ti.f64:
        transfer.upload(array, host)
    elif not device_copy.to_device(array, host):
        array.from_numpy(host)


def _copy_out(array) -> np.ndarray:
    """The int32 1-D ndarray ``array``'s values (a byte copy where one can be made, else ``to_numpy``)."""
    out = np.empty(array.shape, dtype=np.int32)
    return out if device_copy.to_host(out, array) else array.to_numpy()
