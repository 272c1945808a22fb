"""The lockstep's projected retry: contact pair blocks of the marked copies projected by the Jacobi kernel
(its CUDA path) equal the pair potentials' own projected blocks."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.batch.subset_projection import projected_subset_blocks
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


@pytest.mark.parametrize("projection", ["clamp", "abs"])
def test_projected_subset_blocks_left_on_the_device_equal_the_terms_own(ti_cpu, monkeypatch, projection):
    """With the pair kernel's exact blocks kept where it ran (CUDA's defaults in a lockstep batch, whose pair batch
    reads device positions and so takes no packed launch; here on any arch) and a ``BlockRowsProjector``, the marked
    pairs' blocks are gathered, projected by the Jacobi kernel and left there: the pair potentials' own projected
    blocks, for every marked set in turn (the scratch arrays grown, then reused), each result still valid after the
    later ones."""
    from sim_core.energies.contact.batch_kernel import PairBatch
    from sim_core.ti_kernels.block_projection import BlockRowsProjector
    from sim_core.ti_kernels.buffers import DeviceHessianBlocks

    monkeypatch.setattr(PairBatch, "two_pass", True)
    monkeypatch.setattr(PairBatch, "device_hessian", True)
    monkeypatch.setattr(PairBatch, "packed", False)  # (the packed launch, CUDA's for few pairs, keeps them on the host)
    x, linked, alone = _potentials(200)
    projector = BlockRowsProjector()
    every, half, none = (np.zeros(x.shape[0], dtype=bool) for _ in range(3))
    every[:] = True
    half[: x.shape[0] // 2] = True
    results = []  # every result kept to the end: a later projection must not overwrite an earlier one's blocks
    for marked in (half, every, half, none):
        for term, own in zip(linked, alone):
            results.append((projected_subset_blocks(term, x, projection, marked, "jacobi", projector),
                            own.hessian_of_vertices(x, projection, marked), marked is none))
    for got, want, empty in results:
        assert isinstance(got, DeviceHessianBlocks)
        np.testing.assert_array_equal(got.vertices, want.vertices)
        assert got.blocks.shape == want.blocks.shape and (len(want.blocks) > 10 or empty)
        blocks = got.blocks.to_numpy()
        scale = np.abs(want.blocks).max(axis=(1, 2), keepdims=True)
        assert np.all(np.abs(blocks - want.blocks) <= 1e-10 * scale)
    with pytest.raises(ValueError, match="projection"):
        projected_subset_blocks(linked[0], x, "flip", half, "jacobi", projector)
