"""The lockstep's projected retry: contact pair blocks of the marked copies projected by the Jacobi kernel
(its CUDA path) equal the pair potentials' own projected blocks."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.batch.lockstep import projected_subset_blocks
from tests.sim_core.ti_kernels.test_contact_batch import _potentials


@pytest.mark.parametrize("projection", ["clamp", "abs"])
def test_jacobi_projected_subset_blocks_equal_the_terms_own(ti_cpu, projection):
    x, _, (vt, ee) = _potentials(200)
    marked = np.zeros(x.shape[0], dtype=bool)
    marked[: x.shape[0] // 2] = True
    for term in (vt, ee):
        want = term.hessian_of_vertices(x, projection, marked)
        exact = term.hessian_of_vertices(x, "none", marked)
        w = np.linalg.eigvalsh(exact.blocks)
        assert len(want.blocks) > 10 and np.any(w.min(axis=1) < -1e-6 * np.abs(w).max())  # indefinite blocks
        for method in ("jacobi", "lapack"):
            got = projected_subset_blocks(term, x, projection, marked, method)
            np.testing.assert_array_equal(got.vertices, want.vertices)
            scale = np.abs(want.blocks).max(axis=(1, 2), keepdims=True)
            assert np.all(np.abs(got.blocks - want.blocks) <= 1e-10 * scale), (term, method)
        assert np.linalg.eigvalsh(got.blocks).min() >= -1e-9 * np.abs(w).max()
        np.testing.assert_array_equal(term.hessian_of_vertices(x, "none", marked).blocks, exact.blocks)  # untouched
