"""Small dense linear algebra inside Taichi kernels: symmetric eigen-decomposition and PSD projection.

All functions are ``ti.func`` on per-element local matrices (float64), called from the outer
parallel loop of an element kernel, so every thread works on its own element.

* :func:`jacobi_eigh`: cyclic Jacobi eigenvalue iteration with exact rotations (Golub & Van Loan,
  "Matrix Computations", 4th ed., section 8.5; rotation formulas of Rutishauser 1966). Eigenvalues
  to high relative accuracy; used for 3x3, 6x6 and 9x9 blocks.
* :func:`project_psd_translation_free`: the PSD projection of an element Hessian of a
  translation-invariant energy (a function of vertex differences only), done in the
  ``3 m - 3`` dimensional complement of the rigid translations (the Taichi twin of
  :func:`sim_core.energies.membrane.reference.project_psd_translation_free`). The orthonormal basis of the
  complement is the Helmert basis ``h (x) I_3``; any orthonormal basis gives the same projection.
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel and ti.func annotations as
# objects (string annotations are rejected).

import math

from sim_core.ti_backend import ti

PROJECTION_CODES: dict[str, int] = {"none": 0, "clamp": 1, "abs": 2}
"""Integer codes of the PSD projections passed to the kernels (see ``base.Projection``)."""

JACOBI_MAX_SWEEPS = 30
"""Upper bound on Jacobi sweeps; convergence is quadratic, 6 to 10 sweeps reach float64 accuracy."""

JACOBI_REL_TOL = 1e-32
"""Stop when the squared off-diagonal Frobenius norm is below this times the squared norm of A."""


def projection_code(projection: str) -> int:
    """Integer code of a PSD projection name.

    Raises:
        ValueError: unknown projection (same message as the NumPy reference).
    """
    try:
        return PROJECTION_CODES[projection]
    except (KeyError, TypeError):
        raise ValueError(f"unknown PSD projection {projection!r}; use 'none', 'clamp' or 'abs'") from None


def helmert_basis(m: int) -> list[list[float]]:
    """Orthonormal basis of the vectors of R^m that sum to zero (Helmert), shape ``(m, m - 1)``.

    Column ``r`` is ``(1, ..., 1, -(r + 1), 0, ..., 0) / sqrt((r + 1)(r + 2))`` with ``r + 1`` ones.
    """
    out = [[0.0] * (m - 1) for _ in range(m)]
    for r in range(m - 1):
        s = 1.0 / math.sqrt((r + 1) * (r + 2))
        for a in range(r + 1):
            out[a][r] = s
        out[r + 1][r] = -(r + 1) * s
    return out


def translation_free_basis(m: int) -> list[list[float]]:
    """``helmert_basis(m) (x) I_3`` as a ``(3 m, 3 m - 3)`` list: columns span the non-translations."""
    h = helmert_basis(m)
    out = [[0.0] * (3 * (m - 1)) for _ in range(3 * m)]
    for a in range(m):
        for r in range(m - 1):
            for c in range(3):
                out[3 * a + c][3 * r + c] = h[a][r]
    return out


@ti.func
def jacobi_eigh(A: ti.template(), Q: ti.template()):
    """In place: ``A`` (n x n symmetric) -> diagonal of eigenvalues, ``Q`` <- eigenvectors (columns).

    Cyclic-by-row Jacobi: for each pair ``p < q`` the rotation ``J`` with ``t = tan(phi)`` the smaller
    root of ``t^2 + 2 theta t - 1 = 0``, ``theta = (a_qq - a_pp) / (2 a_pq)``, zeroes ``a_pq``;
    ``A <- J^T A J``, ``Q <- Q J``. Sweeps stop when the off-diagonal mass is below
    ``JACOBI_REL_TOL`` times the total.
    """
    n = ti.static(A.n)
    total = 0.0
    for i in range(n):
        for j in range(n):
            Q[i, j] = 0.0
            total += A[i, j] * A[i, j]
        Q[i, i] = 1.0
    for _sweep in range(JACOBI_MAX_SWEEPS):
        off = 0.0
        for p in range(n - 1):
            for q in range(p + 1, n):
                off += A[p, q] * A[p, q]
        if off <= JACOBI_REL_TOL * total:
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = A[p, q]
                if apq != 0.0:
                    theta = 0.5 * (A[q, q] - A[p, p]) / apq
                    t = 1.0 / (ti.abs(theta) + ti.sqrt(theta * theta + 1.0))
                    if theta < 0.0:
                        t = -t
                    c = 1.0 / ti.sqrt(t * t + 1.0)
                    s = t * c
                    for k in range(n):
                        akp = A[k, p]
                        akq = A[k, q]
                        A[k, p] = c * akp - s * akq
                        A[k, q] = s * akp + c * akq
                    for k in range(n):
                        apk = A[p, k]
                        aqk = A[q, k]
                        A[p, k] = c * apk - s * aqk
                        A[q, k] = s * apk + c * aqk
                    A[p, q] = 0.0
                    A[q, p] = 0.0
                    for k in range(n):
                        qkp = Q[k, p]
                        qkq = Q[k, q]
                        Q[k, p] = c * qkp - s * qkq
                        Q[k, q] = s * qkp + c * qkq


@ti.func
def filter_eigenvalue(w: ti.f64, code: ti.i32) -> ti.f64:
    """Eigenvalue after projection ``code`` (0 none, 1 clamp to 0, 2 absolute value)."""
    out = w
    if code == 1:
        out = ti.max(w, 0.0)
    elif code == 2:
        out = ti.abs(w)
    return out


@ti.func
def project_psd_sym(A: ti.template(), code: ti.i32):
    """In place: symmetric ``A`` -> ``sum_m f(w_m) q_m q_m^T`` (``f`` per :func:`filter_eigenvalue`).

    Nothing is done for ``code == 0`` or when no eigenvalue is negative (as the NumPy reference,
    which returns the symmetrised block in that case).
    """
    if code != 0:
        n = ti.static(A.n)
        W = A
        Q = ti.Matrix.zero(ti.f64, n, n)
        jacobi_eigh(W, Q)
        negative = 0
        for m in range(n):
            if W[m, m] < 0.0:
                negative = 1
        if negative == 1:
            for i in range(n):
                for j in range(i, n):
                    acc = 0.0
                    for m in range(n):
                        acc += Q[i, m] * filter_eigenvalue(W[m, m], code) * Q[j, m]
                    A[i, j] = acc
                    A[j, i] = acc


@ti.func
def project_psd_translation_free(H: ti.template(), code: ti.i32):
    """In place: PSD projection of a ``3 m x 3 m`` translation-invariant element Hessian.

    ``H <- B P(B^T H B) B^T`` with ``B = helmert (x) I_3`` (``3 m x (3 m - 3)``) and ``P`` the
    projection of :func:`project_psd_sym`; ``code == 0`` leaves ``H`` unchanged.
    """
    if code != 0:
        n = ti.static(H.n)
        r = ti.static(H.n - 3)
        B = ti.Matrix(ti.static(translation_free_basis(H.n // 3)), ti.f64)
        T = ti.Matrix.zero(ti.f64, n, r)
        for i in range(n):
            for s in range(r):
                acc = 0.0
                for k in range(n):
                    acc += H[i, k] * B[k, s]
                T[i, s] = acc
        R = ti.Matrix.zero(ti.f64, r, r)
        for p in range(r):
            for s in range(p, r):
                acc = 0.0
                for k in range(n):
                    acc += B[k, p] * T[k, s]
                R[p, s] = acc
                R[s, p] = acc
        project_psd_sym(R, code)
        for i in range(n):
            for s in range(r):
                acc = 0.0
                for k in range(r):
                    acc += B[i, k] * R[k, s]
                T[i, s] = acc
        for i in range(n):
            for j in range(i, n):
                acc = 0.0
                for k in range(r):
                    acc += T[i, k] * B[j, k]
                H[i, j] = acc
                H[j, i] = acc


F64_1 = ti.types.ndarray(dtype=ti.f64, ndim=1)
F64_2 = ti.types.ndarray(dtype=ti.f64, ndim=2)
F64_3 = ti.types.ndarray(dtype=ti.f64, ndim=3)
I32_1 = ti.types.ndarray(dtype=ti.i32, ndim=1)
I32_2 = ti.types.ndarray(dtype=ti.i32, ndim=2)
I32_3 = ti.types.ndarray(dtype=ti.i32, ndim=3)
"""Kernel argument types of the element kernels: float64 / int32 NumPy arrays of 1-3 dimensions."""


@ti.func
def cofactor(F):
    """``cof F = dJ/dF`` of a 3x3 ``F``: column j is the cross product of the other two columns (in order)."""
    c0 = ti.Vector([F[0, 0], F[1, 0], F[2, 0]])
    c1 = ti.Vector([F[0, 1], F[1, 1], F[2, 1]])
    c2 = ti.Vector([F[0, 2], F[1, 2], F[2, 2]])
    k0 = c1.cross(c2)
    k1 = c2.cross(c0)
    k2 = c0.cross(c1)
    return ti.Matrix([[k0[0], k1[0], k2[0]], [k0[1], k1[1], k2[1]], [k0[2], k1[2], k2[2]]], ti.f64)


@ti.func
def row3(a: ti.template(), i: ti.i32):
    """Row ``i`` of an ``(n, 3)`` array as a 3-vector (a vertex position, a box corner)."""
    return ti.Vector([a[i, 0], a[i, 1], a[i, 2]])


@ti.func
def matmul(a: ti.template(), b: ti.template()):
    """``a @ b`` of local matrices (``a`` n x m, ``b`` m x p) with runtime loops.

    The same sums in the same order as Taichi's ``@`` (``0 + a_i0 b_0j + a_i1 b_1j + ...``), so the
    same values, but the frontend builds one loop body instead of ``n p m`` unrolled products (the
    kernel's Python-side compile time grows with the number of unrolled expressions).
    """
    c = ti.Matrix.zero(ti.f64, a.n, b.m)
    for i, j in ti.ndrange(a.n, b.m):
        acc = 0.0
        for k in range(a.m):
            acc += a[i, k] * b[k, j]
        c[i, j] = acc
    return c
