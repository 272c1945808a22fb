"""PSD projection of symmetric blocks by Householder tridiagonalisation and implicit QL, one block a thread.

The device path of the projected Newton matrix (:mod:`sim_core.ti_kernels.block_projection`: a lockstep batch's
projected retries, the reduced 15 x 15 Kirchhoff blocks of every retried copy and the 12 x 12 contact pair blocks)
projects tens of thousands of blocks at once, one GPU thread a block, the block index the last and fastest of the
arrays (a warp's loads and stores coalesced). The cyclic Jacobi method of
:func:`~sim_core.ti_kernels.block_projection.jacobi_project_blocks` takes 6 to 10 sweeps of ``n (n - 1) / 2`` rotations
for a 15 x 15 block, each rotation ``8 n`` loads and stores of the block and its eigenvectors: ~10^5 memory
operations a block, which at 1024 Forming copies (~2.2 x 10^5 reduced Kirchhoff blocks) keep an H100 busy for
tens of milliseconds a retry (session 53's profile: ~55 ms of device time a retry against a ~1.7 ms floor).
Householder's reduction to tridiagonal form and the implicit QL iteration with the transformations accumulated
(the EISPACK routines ``tred2`` and ``tql2``; Wilkinson & Reinsch, Handbook for Automatic Computation II, 1971,
contributions II/2 and II/3; here in the form of JAMA's ``EigenvalueDecomposition``, public domain) need
``~(4/3) n^3`` operations for the reduction and its accumulation and ``~3 n^3`` for QL (about two QL iterations an
eigenvalue), ~4x fewer memory operations than Jacobi for the same blocks, with the same result to round-off.

Semantics are those of the Jacobi kernel, so that either serves the same callers: each block is symmetrised
(``(A + A^T) / 2``) in the working copy; a block with a negative eigenvalue is replaced by ``V f(w) V^T`` (``code`` 1
clamp: ``f(w) = max(w, 0)``, 2 abs: ``|w|``), the others keep their entries bit for bit; NaN blocks are kept (every
loop is bounded).
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel and ti.func annotations as
# objects (string annotations are rejected).

from sim_core.ti_backend import ti
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.launch import fast_kernel

_F64_3 = linalg.F64_3

QL_ITERATIONS = 60
"""Implicit QL iterations at most an eigenvalue (:func:`householder_project_blocks`; a 15 x 15 block takes about two
an eigenvalue)."""

_EPS = 2.0 ** -52  # float64 machine epsilon: QL's deflation test |e_m| <= eps * max_l (|d_l| + |e_l|)


@ti.func
def _hypot(a, b):
    """``sqrt(a^2 + b^2)`` without overflow or underflow of the squares."""
    x, y = ti.abs(a), ti.abs(b)
    big, small = ti.max(x, y), ti.min(x, y)
    r = 0.0
    if big > 0.0:
        q = small / big
        r = big * ti.sqrt(1.0 + q * q)
    return r


@ti.func
def _tridiagonalise(work: ti.template(), vectors: ti.template(), n: ti.i32, b: ti.i32):
    """Householder reduction of the symmetric ``vectors[:, :, b]`` ``(n, n)`` to tridiagonal form (``tred2``): the
    diagonal into ``work[0, :, b]``, the subdiagonal into ``work[1, 1:, b]`` (``work[1, 0, b] = 0``), the orthogonal
    transformation accumulated into ``vectors[:, :, b]``."""
    for j in range(n):
        work[0, j, b] = vectors[n - 1, j, b]
    for step in range(n - 1):
        i = n - 1 - step
        scale = 0.0
        h = 0.0
        for k in range(i):
            scale += ti.abs(work[0, k, b])
        if scale == 0.0:
            work[1, i, b] = work[0, i - 1, b]
            for j in range(i):
                work[0, j, b] = vectors[i - 1, j, b]
                vectors[i, j, b] = 0.0
                vectors[j, i, b] = 0.0
        else:
            for k in range(i):  # the Householder vector of row i
                work[0, k, b] /= scale
                h += work[0, k, b] * work[0, k, b]
            f = work[0, i - 1, b]
            g = ti.sqrt(h)
            if f > 0.0:
                g = -g
            work[1, i, b] = scale * g
            h = h - f * g
            work[0, i - 1, b] = f - g
            for j in range(i):
                work[1, j, b] = 0.0
            for j in range(i):  # A u into work[1]
                fj = work[0, j, b]
                vectors[j, i, b] = fj
                gj = work[1, j, b] + vectors[j, j, b] * fj
                for k in range(j + 1, i):
                    gj += vectors[k, j, b] * work[0, k, b]
                    work[1, k, b] += vectors[k, j, b] * fj
                work[1, j, b] = gj
            f = 0.0
            for j in range(i):
                work[1, j, b] /= h
                f += work[1, j, b] * work[0, j, b]
            hh = f / (h + h)
            for j in range(i):
                work[1, j, b] -= hh * work[0, j, b]
            for j in range(i):  # A <- A - u q^T - q u^T on the lower triangle
                fj = work[0, j, b]
                gj = work[1, j, b]
                for k in range(j, i):
                    vectors[k, j, b] -= fj * work[1, k, b] + gj * work[0, k, b]
                work[0, j, b] = vectors[i - 1, j, b]
                vectors[i, j, b] = 0.0
        work[0, i, b] = h
    for i in range(n - 1):  # the transformations accumulated
        vectors[n - 1, i, b] = vectors[i, i, b]
        vectors[i, i, b] = 1.0
        h = work[0, i + 1, b]
        if h != 0.0:
            for k in range(i + 1):
                work[0, k, b] = vectors[k, i + 1, b] / h
            for j in range(i + 1):
                g = 0.0
                for k in range(i + 1):
                    g += vectors[k, i + 1, b] * vectors[k, j, b]
                for k in range(i + 1):
                    vectors[k, j, b] -= g * work[0, k, b]
        for k in range(i + 1):
            vectors[k, i + 1, b] = 0.0
    for j in range(n):
        work[0, j, b] = vectors[n - 1, j, b]
        vectors[n - 1, j, b] = 0.0
    vectors[n - 1, n - 1, b] = 1.0
    work[1, 0, b] = 0.0


@ti.func
def _diagonalise(work: ti.template(), vectors: ti.template(), n: ti.i32, b: ti.i32):
    """Implicit QL with shifts (``tql2``) of the tridiagonal matrix of :func:`_tridiagonalise`: the eigenvalues into
    ``work[0, :, b]`` (unsorted), the eigenvectors the columns of ``vectors[:, :, b]``."""
    for i in range(1, n):
        work[1, i - 1, b] = work[1, i, b]
    work[1, n - 1, b] = 0.0
    f = 0.0
    tst1 = 0.0
    for l in range(n):
        tst1 = ti.max(tst1, ti.abs(work[0, l, b]) + ti.abs(work[1, l, b]))
        m = l
        while m < n - 1 and ti.abs(work[1, m, b]) > _EPS * tst1:  # a negligible subdiagonal entry
            m += 1
        if m > l:
            iteration = 0
            while iteration < QL_ITERATIONS:
                iteration += 1
                g = work[0, l, b]  # the shift
                p = (work[0, l + 1, b] - g) / (2.0 * work[1, l, b])
                r = _hypot(p, 1.0)
                if p < 0.0:
                    r = -r
                work[0, l, b] = work[1, l, b] / (p + r)
                work[0, l + 1, b] = work[1, l, b] * (p + r)
                dl1 = work[0, l + 1, b]
                h = g - work[0, l, b]
                for i in range(l + 2, n):
                    work[0, i, b] -= h
                f += h
                p = work[0, m, b]  # the implicit QL transformation
                c, c2, c3 = 1.0, 1.0, 1.0
                el1 = work[1, l + 1, b]
                s, s2 = 0.0, 0.0
                for back in range(m - l):
                    i = m - 1 - back
                    c3 = c2
                    c2 = c
                    s2 = s
                    gi = c * work[1, i, b]
                    hi = c * p
                    r = _hypot(p, work[1, i, b])
                    work[1, i + 1, b] = s * r
                    s = work[1, i, b] / r
                    c = p / r
                    p = c * work[0, i, b] - s * gi
                    work[0, i + 1, b] = hi + s * (c * gi + s * work[0, i, b])
                    for k in range(n):  # the eigenvectors
                        vk = vectors[k, i + 1, b]
                        vectors[k, i + 1, b] = s * vectors[k, i, b] + c * vk
                        vectors[k, i, b] = c * vectors[k, i, b] - s * vk
                p = -s * s2 * c3 * el1 * work[1, l, b] / dl1
                work[1, l, b] = s * p
                work[0, l, b] = c * p
                if not ti.abs(work[1, l, b]) > _EPS * tst1:  # converged (or NaN: stop)
                    break
        work[0, l, b] = work[0, l, b] + f
        work[1, l, b] = 0.0


@fast_kernel
def householder_project_blocks(blocks: _F64_3, work: _F64_3, vectors: _F64_3, count: ti.i32, code: ti.i32):
    """PSD projection of the symmetric blocks ``blocks[:, :, e]`` ``(n, n)``, ``e < count``, in place (module
    docstring): each block's eigen-decomposition by Householder tridiagonalisation and implicit QL, one block a
    thread; a block with a negative eigenvalue replaced by ``V f(w) V^T`` (``code`` 1 clamp, 2 abs), the others kept
    as they are. ``work`` and ``vectors``: scratch arrays of the blocks' shape ``(n, n, k)`` (``n >= 2``; ``work``'s
    first two rows hold a block's diagonal and subdiagonal). The layout and the semantics of
    :func:`~sim_core.ti_kernels.block_projection.jacobi_project_blocks`: the same projection to round-off."""
    for e in range(count):
        n = blocks.shape[0]
        for i in range(n):
            for j in range(n):
                vectors[i, j, e] = 0.5 * (blocks[i, j, e] + blocks[j, i, e])
        _tridiagonalise(work, vectors, n, e)
        _diagonalise(work, vectors, n, e)
        negative = 0
        for k in range(n):
            if work[0, k, e] < 0.0:
                negative = 1
        if negative == 1:
            for k in range(n):
                w = work[0, k, e]
                work[0, k, e] = ti.max(w, 0.0) if code == 1 else ti.abs(w)
            for i in range(n):
                for j in range(i, n):
                    acc = 0.0
                    for k in range(n):
                        acc += vectors[i, k, e] * work[0, k, e] * vectors[j, k, e]
                    blocks[i, j, e] = acc
                    blocks[j, i, e] = acc
