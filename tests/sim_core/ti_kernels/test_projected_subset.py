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


class _KeptTerm:
    """A term whose exact blocks are kept on the device (``hessian_on_device``), PSD by construction or not: records
    what the operator asked it for."""

    def __init__(self, psd: bool, on_device: bool = True) -> None:
        self.psd_hessian = psd
        self.on_device = on_device
        self.asked: list[str] = []

    def hessian_on_device(self, x):
        self.asked.append("device")
        return "device blocks" if self.on_device else None

    def hessian(self, x, projection="clamp"):
        self.asked.append(projection)
        return "host blocks"


def test_projected_retry_takes_the_device_blocks_of_psd_terms_only():
    """The projected retry's operator (``LockstepSolver._term_hessian`` with a projection and marked copies) takes a
    term's exact blocks where they are kept when the term's Hessian is PSD by construction (``psd_hessian``: the
    projection changes nothing), and the term's projected ``hessian`` otherwise or where nothing is kept."""
    from types import SimpleNamespace

    from sim_core.batch.lockstep import LockstepSolver

    solver = SimpleNamespace(subset_projection=None, _block_rows=None)
    x = np.zeros((4, 3))
    marked = np.ones(4, dtype=bool)
    for psd, on_device, projection, vertices, want, asked in (
            (True, True, "clamp", marked, "device blocks", ["device"]),
            (True, True, "abs", None, "device blocks", ["device"]),
            (True, False, "clamp", marked, "host blocks", ["device", "clamp"]),
            (False, True, "clamp", marked, "host blocks", ["clamp"]),
            (False, True, "none", None, "device blocks", ["device"]),
            (False, True, "none", marked, "host blocks", ["none"])):
        term = _KeptTerm(psd, on_device)
        assert LockstepSolver._term_hessian(solver, term, x, projection, vertices) == want
        assert term.asked == asked, (psd, on_device, projection)


def test_friction_blocks_are_the_same_for_every_projection(ti_cpu):
    """The friction's ``psd_hessian``: its blocks (reference and kernels) are the same whatever the projection asked,
    and PSD (smallest eigenvalue above -1e-12 of the largest entry), in the mollified and the sliding regime."""
    from sim_core.energies.friction.kernel import TiLaggedFriction
    from sim_core.energies.friction.reference import LaggedFriction, tangent_basis

    rng = np.random.default_rng(3)
    p, n = 40, 30
    vertices = np.stack([rng.choice(n, size=4, replace=False) for _ in range(p)])
    weights = np.concatenate([np.ones((p, 1)), -rng.dirichlet(np.ones(3), size=p)], axis=1)
    normal = rng.normal(size=(p, 3))
    tangent = tangent_basis(normal / np.linalg.norm(normal, axis=1, keepdims=True))
    lam, mu = rng.uniform(0.5, 3.0, size=p), rng.uniform(0.2, 1.0, size=p)
    x_prev = rng.uniform(-0.01, 0.01, size=(n, 3))
    dt, eps_v = 5e-3, 0.01
    for cls in (LaggedFriction, TiLaggedFriction):
        friction = cls(vertices, weights, tangent, lam, mu, x_prev, eps_v, dt)
        assert friction.psd_hessian
        for scale in (0.3 * eps_v * dt, 20 * eps_v * dt):
            x = x_prev + rng.normal(scale=scale, size=x_prev.shape)
            exact = np.array(friction.hessian(x, "none").blocks)
            for projection in ("clamp", "abs"):
                np.testing.assert_array_equal(friction.hessian(x, projection).blocks, exact)
            assert np.linalg.eigvalsh(exact).min() >= -1e-12 * np.abs(exact).max()
