"""The Householder-QL PSD projection of symmetric blocks (sim_core.ti_kernels.householder_projection, the device
path's kernel on CUDA) equals LAPACK's (numpy.linalg.eigh) and the Jacobi kernel's to round-off for the block sizes of
the fused elastic terms and contact elements; definite blocks and NaN blocks kept as they are."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.ti_kernels.block_projection import project_reduced_blocks  # noqa: E402 (Taichi imported here)


def symmetric_blocks(n: int) -> np.ndarray:
    """40 symmetric ``(n, n)`` blocks (the projection kernels' tests, here and in test_jacobi_projection): indefinite, definite (0-7), rank-deficient, diagonal, singular PSD, definite
    with its smallest eigenvalue near round-off, indefinite by 1e-6, a repeated negative eigenvalue, a zero block."""
    rng = np.random.default_rng(100 + n)
    a = rng.normal(size=(40, n, n))
    blocks = a + np.swapaxes(a, 1, 2)
    blocks[:8] = np.matmul(a[:8], np.swapaxes(a[:8], 1, 2)) + 0.1 * np.eye(n)
    blocks[8] = np.outer(a[8, 0], a[8, 0]) - np.outer(a[8, 1], a[8, 1])
    blocks[9] = np.diag(rng.normal(size=n))
    blocks[10] = np.outer(a[10, 0], a[10, 0]) + np.outer(a[10, 1], a[10, 1])
    q = np.linalg.qr(a[11])[0]
    blocks[11] = (q * np.r_[1e-14, np.ones(n - 1)]) @ q.T
    blocks[12] = (q * np.r_[-1e-6, np.ones(n - 1)]) @ q.T
    blocks[13] = (q * np.r_[-2.0, -2.0, np.ones(n - 2)]) @ q.T
    blocks[14] = 0.0
    blocks[15] *= 1e5  # a stiffness's scale (N/m)
    return blocks


@pytest.mark.parametrize("n", [3, 6, 9, 12, 15])
@pytest.mark.parametrize("projection", ["clamp", "abs"])
def test_householder_projection_matches_lapack_and_jacobi(ti_cpu, n, projection):
    blocks = symmetric_blocks(n)
    want = project_reduced_blocks(blocks.copy(), projection, method="lapack")
    jacobi = project_reduced_blocks(blocks.copy(), projection, method="jacobi")
    got = project_reduced_blocks(blocks.copy(), projection, method="householder")
    scale = np.maximum(np.abs(blocks).max(axis=(1, 2)), 1e-300)[:, None, None]
    assert np.all(np.abs(got - want) <= 1e-12 * scale)
    assert np.all(np.abs(got - jacobi) <= 1e-12 * scale)
    np.testing.assert_array_equal(got[:8], blocks[:8])  # definite: kept bit for bit
    np.testing.assert_array_equal(got[14], blocks[14])
    np.testing.assert_allclose(got[10:12], blocks[10:12], rtol=0, atol=1e-12 * scale.max())
    assert np.abs(got[12] - blocks[12]).max() > 1e-7  # its negative eigenvalue clamped
    w = np.linalg.eigvalsh(got)
    assert w.min() >= -1e-12 * scale.max()
    if projection == "abs":
        np.testing.assert_allclose(np.sort(w, axis=1), np.sort(np.abs(np.linalg.eigvalsh(blocks)), axis=1),
                                   atol=1e-11 * scale.max())


def test_householder_projection_keeps_a_nan_block_and_projects_the_others(ti_cpu):
    blocks = symmetric_blocks(6)[:16]
    blocks[3, 1, 2] = blocks[3, 2, 1] = np.nan
    got = project_reduced_blocks(blocks.copy(), "clamp", method="householder")
    want = project_reduced_blocks(np.delete(blocks, 3, axis=0), "clamp", method="lapack")
    assert np.isnan(got[3]).any()
    np.testing.assert_allclose(np.delete(got, 3, axis=0), want, rtol=0, atol=1e-12 * np.abs(blocks[:3]).max() * 1e3)
