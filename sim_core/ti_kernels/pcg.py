"""Batched preconditioned conjugate gradient in Taichi: the block-diagonal Newton system of a lockstep
batch solved on the device, one independent CG per copy.

:class:`BatchedPCG` follows the :class:`~sim_core.linsolve.SymmetricSolver` contract (``factorize``
takes the upper triangle of the symmetric Newton matrix, ``solve`` one right-hand side). The matrix,
its 3x3 vertex-block Jacobi preconditioner and every CG vector stay in Taichi ndarrays (device memory
on CUDA); each iteration is five passes over all copies, and one kernel launch runs
:data:`ITERATIONS_PER_LAUNCH` iterations (the passes are its top-level loops, which Taichi runs one
after the other on the device):

* ``A p`` from the upper triangle (CSR): each stored entry ``a_ij`` adds ``a_ij p_j`` to row ``i``
  and, off the diagonal, ``a_ij p_i`` to row ``j`` (atomic adds);
* per copy ``p.Ap`` (a segmented sum by the DoF's copy);
* the update ``x += alpha_c p``, ``r -= alpha_c Ap``, ``z = M^-1 r`` with each copy's own
  ``alpha_c = r.z / p.Ap``, and per copy ``r.z`` and ``r.r``;
* per copy: ``beta_c``, and the copy stops when ``|r_c| <= rtol |b_c|`` (or after ``p.Ap <= 0``:
  a matrix not positive definite on that copy, which :attr:`BatchedPCG.indefinite` reports);
* ``p = z + beta_c p``.

Copies are independent CGs (Hestenes & Stiefel 1952; preconditioned form: Saad, Iterative Methods
for Sparse Linear Systems, 2nd ed., Alg. 9.1), each with its own step sizes and stopping test, so a
copy's solution does not depend on the others. The host reads the count of running copies after
each launch (its one synchronisation); a copy that has stopped is left unchanged by later passes. The matrix must be positive definite (the projected Newton matrix):
:attr:`BatchedPCG.detects_indefinite` is False, so the solver assembles the PSD-projected Hessian.
"""

import numpy as np
import scipy.sparse as sp

from sim_core.ti_backend import ti

_F64 = ti.types.ndarray(dtype=ti.f64, ndim=1)
_I32 = ti.types.ndarray(dtype=ti.i32, ndim=1)


@ti.kernel
def _block_jacobi(indptr: _I32, indices: _I32, data: _F64, inv: _F64, nvert: ti.i32):
    """``inv`` ``(9 nvert,)``: the inverse of each vertex's 3x3 diagonal block (its diagonal's inverse
    when the block is singular, 1 where the diagonal is zero)."""
    for v in range(nvert):
        blk = ti.Matrix.zero(ti.f64, 3, 3)
        for a in ti.static(range(3)):
            i = 3 * v + a
            for k in range(indptr[i], indptr[i + 1]):
                j = indices[k]
                if j // 3 == v:
                    blk[a, j % 3] = data[k]
                    blk[j % 3, a] = data[k]
        det = blk.determinant()
        scale = ti.abs(blk[0, 0]) * ti.abs(blk[1, 1]) * ti.abs(blk[2, 2])
        out = ti.Matrix.zero(ti.f64, 3, 3)
        if det > 1e-12 * scale and scale > 0:
            out = blk.inverse()
        else:
            for a in ti.static(range(3)):
                out[a, a] = 1.0 / blk[a, a] if blk[a, a] > 0 else 1.0
        for a in ti.static(range(3)):
            for b in ti.static(range(3)):
                inv[9 * v + 3 * a + b] = out[a, b]


@ti.kernel
def _start(b: _F64, x: _F64, r: _F64, z: _F64, p: _F64, inv: _F64, seg: _I32, rz: _F64, bb: _F64, nvert: ti.i32):
    """``x = 0``, ``r = b``, ``z = p = M^-1 b``; per copy ``rz = r.z`` and ``bb = b.b`` (zeroed before)."""
    for v in range(nvert):
        for a in ti.static(range(3)):
            i = 3 * v + a
            acc = 0.0
            for c in ti.static(range(3)):
                acc += inv[9 * v + 3 * a + c] * b[3 * v + c]
            x[i] = 0.0
            r[i] = b[i]
            z[i] = acc
            p[i] = acc
            s = seg[i]
            rz[s] += b[i] * acc
            bb[s] += b[i] * b[i]


ITERATIONS_PER_LAUNCH = 8
"""CG iterations of one launch of :func:`_cg_iterations` (the host tests for the end between launches)."""


@ti.kernel
def _cg_iterations(indptr: _I32, indices: _I32, data: _F64, inv: _F64, seg: _I32, x: _F64, r: _F64, z: _F64,
                   p: _F64, ap: _F64, rz: _F64, rz_new: _F64, rr: _F64, bb: _F64, pap: _F64, beta: _F64,
                   active: _I32, bad: _I32, running: _I32, rtol2: ti.f64, n: ti.i32, copies: ti.i32):
    """:data:`ITERATIONS_PER_LAUNCH` CG iterations of every running copy; ``running[0]`` = copies still
    running after them. Each top-level loop is one device pass, run in order: ``Ap`` (``ap`` zero on
    entry and on exit), per copy ``p.Ap``, the update of ``x``, ``r``, ``z`` with per-copy ``r.z`` and
    ``r.r``, the per-copy test and ``beta``, and the new ``p``."""
    for _ in ti.static(range(ITERATIONS_PER_LAUNCH)):
        for i in range(n):  # ap += A p, A symmetric stored as its upper triangle
            acc = 0.0
            pi = p[i]
            for k in range(indptr[i], indptr[i + 1]):
                j = indices[k]
                a = data[k]
                acc += a * p[j]
                if j != i:
                    ti.atomic_add(ap[j], a * pi)
            ti.atomic_add(ap[i], acc)
        for i in range(n):
            ti.atomic_add(pap[seg[i]], p[i] * ap[i])
        for v in range(n // 3):
            s = seg[3 * v]
            if active[s] != 0 and pap[s] > 0:
                alpha = rz[s] / pap[s]
                for a in ti.static(range(3)):
                    i = 3 * v + a
                    x[i] += alpha * p[i]
                    r[i] -= alpha * ap[i]
                for a in ti.static(range(3)):
                    i = 3 * v + a
                    acc = 0.0
                    for c in ti.static(range(3)):
                        acc += inv[9 * v + 3 * a + c] * r[3 * v + c]
                    z[i] = acc
                    ti.atomic_add(rz_new[s], r[i] * acc)
                    ti.atomic_add(rr[s], r[i] * r[i])
        for c in range(copies):
            b = 0.0
            if active[c] != 0:
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


class BatchedPCG:
    """Block-Jacobi preconditioned CG for a block-diagonal symmetric positive definite matrix, one CG per
    block (module docstring); Taichi must be initialised (a Taichi solver backend).

    Args:
        segments: the block (copy) of each DoF, shape ``(n,)`` int, values ``0..B-1``, constant over a
            vertex's three DoFs; None: one block.
        rtol: per copy, stop at ``|r| <= rtol |b|``.
        max_iterations: CG iterations per solve at most (copies not converged by then keep their
            last iterate, and :attr:`unconverged` lists them).

    Attributes:
        name: ``"pcg"``.
        detects_indefinite: False (the Newton solver then assembles the projected Hessian).
        factorizations: :meth:`factorize` calls.
        iterations: CG iterations of the last solve (launches times :data:`ITERATIONS_PER_LAUNCH`).
        indefinite: copies whose matrix showed ``p.Ap <= 0`` in the last solve, shape ``(B,)`` bool.
        unconverged: copies still running after ``max_iterations``, shape ``(B,)`` bool.
    """

    name = "pcg"
    detects_indefinite = False

    def __init__(self, segments: "np.ndarray | None" = None, rtol: float = 1e-10, max_iterations: int = 5000) -> None:
        self.rtol = float(rtol)
        self.max_iterations = int(max_iterations)
        self.factorizations = 0
        self.iterations = 0
        self._segments = None if segments is None else np.ascontiguousarray(segments, dtype=np.int32)
        self._arrays: dict[str, object] = {}
        self._n = -1
        self.indefinite = np.zeros(0, dtype=bool)
        self.unconverged = np.zeros(0, dtype=bool)

    def _array(self, name: str, size: int, dtype=ti.f64):
        arr = self._arrays.get(name)
        if arr is None or arr.shape != (size,):
            arr = ti.ndarray(dtype=dtype, shape=(size,))
            self._arrays[name] = arr
        return arr

    def factorize(self, upper: "sp.csr_matrix") -> bool:
        """Keep the matrix ``A = U + U^T - diag(U)`` (``U`` its upper triangle, CSR, shape ``(n, n)``,
        ``n`` a multiple of 3) on the device and build its block-Jacobi preconditioner; True.

        Raises:
            ValueError: ``n`` is not a multiple of 3 or does not match the segments.
        """
        n = upper.shape[0]
        if n % 3 or (self._segments is not None and self._segments.shape != (n,)):
            raise ValueError(f"BatchedPCG: matrix of size {n} for {None if self._segments is None else self._segments.shape[0]} "
                             f"segment entries (n must be a multiple of 3)")
        self.factorizations += 1
        self._n = n
        seg = self._segments if self._segments is not None else np.zeros(n, dtype=np.int32)
        self._copies = int(seg.max()) + 1 if n else 1
        indptr = self._array("indptr", n + 1, ti.i32)
        indptr.from_numpy(upper.indptr.astype(np.int32))
        nnz = int(upper.indptr[-1])
        indices = self._array("indices", max(nnz, 1), ti.i32)
        data = self._array("data", max(nnz, 1))
        if nnz:
            indices.from_numpy(upper.indices[:nnz].astype(np.int32))
            data.from_numpy(np.ascontiguousarray(upper.data[:nnz], dtype=np.float64))
        segs = self._array("seg", max(n, 1), ti.i32)
        if self._arrays.get("_seg_host") is not seg:
            segs.from_numpy(seg if n else np.zeros(1, np.int32))
            self._arrays["_seg_host"] = seg
        _block_jacobi(indptr, indices, data, self._array("inv", max(3 * n, 1)), n // 3)
        return True

    def solve(self, b: np.ndarray) -> np.ndarray:
        """Solve ``A x = b`` (``b`` shape ``(n,)``) per copy to ``|r_c| <= rtol |b_c|``; returns ``x``."""
        n, B = self._n, self._copies
        if n < 0:
            raise RuntimeError("BatchedPCG: factorize before solve")
        b = np.ascontiguousarray(b, dtype=np.float64)
        if b.shape != (n,):
            raise ValueError(f"BatchedPCG: right-hand side of shape {b.shape}, expected ({n},)")
        if n == 0:
            return np.zeros(0)
        a = self._arrays
        vec = {k: self._array(k, n) for k in ("b", "x", "r", "z", "p", "ap")}
        per = {k: self._array(k, B) for k in ("rz", "bb", "pap", "rz_new", "rr", "beta")}
        active = self._array("active", B, ti.i32)
        bad = self._array("bad", B, ti.i32)
        vec["b"].from_numpy(b)
        for k in ("rz", "bb", "pap", "rz_new", "rr"):
            per[k].fill(0.0)
        active.fill(1)
        bad.fill(0)
        vec["ap"].fill(0.0)
        nvert = n // 3
        _start(vec["b"], vec["x"], vec["r"], vec["z"], vec["p"], a["inv"], a["seg"], per["rz"], per["bb"], nvert)
        rtol2 = self.rtol ** 2
        running = self._array("running", 1, ti.i32)
        it = 0
        while it < self.max_iterations:
            it += ITERATIONS_PER_LAUNCH
            _cg_iterations(a["indptr"], a["indices"], a["data"], a["inv"], a["seg"], vec["x"], vec["r"], vec["z"],
                           vec["p"], vec["ap"], per["rz"], per["rz_new"], per["rr"], per["bb"], per["pap"], per["beta"],
                           active, bad, running, rtol2, n, B)
            if int(running.to_numpy()[0]) == 0:
                break
        self.iterations = it
        self.indefinite = bad.to_numpy().astype(bool)
        self.unconverged = active.to_numpy().astype(bool)
        return vec["x"].to_numpy()
