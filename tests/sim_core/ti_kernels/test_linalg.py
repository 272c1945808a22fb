"""Small dense linear algebra of the element kernels: the runtime-loop matrix product."""

# No ``from __future__ import annotations`` here: Taichi reads kernel annotations as objects.

import numpy as np


def test_matmul_equals_taichis_product_and_numpy(ti_cpu):
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels.linalg import F64_2, matmul

    @ti.kernel
    def products(a: F64_2, b: F64_2, c: F64_2, mine: F64_2, taichis: F64_2, chained: F64_2):
        A = ti.Matrix.zero(ti.f64, 3, 9)
        B = ti.Matrix.zero(ti.f64, 9, 4)
        C = ti.Matrix.zero(ti.f64, 4, 2)
        for i, j in ti.ndrange(3, 9):
            A[i, j] = a[i, j]
        for i, j in ti.ndrange(9, 4):
            B[i, j] = b[i, j]
        for i, j in ti.ndrange(4, 2):
            C[i, j] = c[i, j]
        P = matmul(A, B)
        Q = A @ B
        R = matmul(matmul(A, B), C)
        for i, j in ti.ndrange(3, 4):
            mine[i, j] = P[i, j]
            taichis[i, j] = Q[i, j]
        for i, j in ti.ndrange(3, 2):
            chained[i, j] = R[i, j]

    rng = np.random.default_rng(3)
    a, b, c = rng.standard_normal((3, 9)), rng.standard_normal((9, 4)), rng.standard_normal((4, 2))
    mine, taichis, chained = np.zeros((3, 4)), np.zeros((3, 4)), np.zeros((3, 2))
    products(a, b, c, mine, taichis, chained)
    assert np.array_equal(mine, taichis)  # the same sums in the same order
    assert np.allclose(mine, a @ b, rtol=0, atol=1e-14 * np.abs(a @ b).max())
    assert np.allclose(chained, a @ b @ c, rtol=0, atol=1e-14 * np.abs(a @ b @ c).max())
