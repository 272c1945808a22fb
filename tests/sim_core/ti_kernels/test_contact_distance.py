"""Taichi contact distance kernels equal the NumPy reference; the Taichi contact potentials pass the
reference's finite-difference checks and the contact set uses them on the Taichi backend."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.collision import distances as reference
from sim_core.collision.distances import EdgeEdgeRegion, PointTriangleRegion
from sim_core.energies.contact.reference import EdgeEdgeContact, VertexTriangleContact
from tests.sim_core.energies import test_contact as ref_tests
from tests.sim_core.ti_kernels.conftest import relative_error

EPS = 4.0e-4


def _kernels():
    from sim_core.energies.contact import distance_kernel as contact_distance

    return {
        "vt": (contact_distance.point_triangle_contact_distance, reference.point_triangle_contact_distance,
               reference.point_triangle_side, PointTriangleRegion),
        "ee": (contact_distance.edge_edge_contact_distance, reference.edge_edge_contact_distance,
               reference.edge_edge_side, EdgeEdgeRegion),
    }


def _random_pairs(rng, count):
    base = rng.uniform(-3 * EPS, 3 * EPS, size=(count, 1, 3))
    return base + rng.uniform(-3 * EPS, 3 * EPS, size=(count, 4, 3))


def _near_parallel_edges(rng, count):
    a0 = rng.normal(size=(count, 3)) * EPS
    e = rng.normal(size=(count, 3))
    e /= np.linalg.norm(e, axis=1, keepdims=True)
    f = e + 10.0 ** rng.uniform(-5, -1, size=(count, 1)) * rng.normal(size=(count, 3))
    off = rng.normal(size=(count, 3)) * EPS
    return np.stack([a0, a0 + 6 * EPS * e, a0 + off, a0 + off + 6 * EPS * f], axis=1)


@pytest.mark.parametrize("kind", ["vt", "ee"])
def test_distance_gradient_hessian_and_regions_equal_the_reference(ti_cpu, kind):
    tik, ref, geometric, regions = _kernels()[kind]
    rng = np.random.default_rng(1)
    z = _random_pairs(rng, 3000)
    if kind == "ee":
        z = np.concatenate([z, _near_parallel_edges(rng, 1000)])
    side = rng.choice([-1.0, 0.0, 1.0], size=z.shape[0])
    resolved = np.where(side == 0.0, geometric(z), side)  # the reference takes resolved sides
    for order in (0, 1, 2):
        a, b = ref(z, resolved, order), tik(z, side, order)
        assert set(np.unique(a.region)) == {int(r) for r in regions}  # every region is exercised
        np.testing.assert_array_equal(b.region, a.region)
        np.testing.assert_array_equal(b.d, a.d)  # same expressions: bit for bit
        if order >= 1:
            np.testing.assert_array_equal(b.grad, a.grad)
        if order >= 2:
            scale = np.max(np.abs(a.hess), axis=(1, 2), keepdims=True)
            assert np.max(np.abs(b.hess - a.hess) / scale) < 1e-12
        else:
            assert b.hess is None


@pytest.mark.parametrize("kind", ["vt", "ee"])
def test_empty_batch(ti_cpu, kind):
    tik = _kernels()[kind][0]
    out = tik(np.zeros((0, 4, 3)), np.zeros(0), 2)
    assert out.d.shape == (0,) and out.grad.shape == (0, 12) and out.hess.shape == (0, 12, 12)


@pytest.mark.parametrize("side", [1.0, -1.0, 0.0])
def test_taichi_vertex_triangle_contact_fd_and_reference(ti_cpu, side):
    from sim_core.energies.contact.kernel import TiVertexTriangleContact

    rng = np.random.default_rng(10)
    x, tris, pairs = ref_tests._vt_scene(rng, list(PointTriangleRegion))
    sides = np.full(len(pairs), side)
    pot = TiVertexTriangleContact(pairs, tris, sides, ref_tests.K, EPS)
    ref_tests._check_potential(pot, x, len(pairs))
    _assert_same(pot, VertexTriangleContact(pairs, tris, sides, ref_tests.K, EPS), x)


@pytest.mark.parametrize("side", [1.0, -1.0, 0.0])
def test_taichi_edge_edge_contact_fd_and_reference(ti_cpu, side):
    from sim_core.energies.contact.kernel import TiEdgeEdgeContact

    rng = np.random.default_rng(11)
    z = np.concatenate([_random_pairs(rng, 40), _near_parallel_edges(rng, 20)])
    x = z.reshape(-1, 3)
    edges = np.arange(x.shape[0]).reshape(-1, 2)
    pairs = np.stack([np.arange(0, len(edges), 2), np.arange(1, len(edges), 2)], axis=1)
    sides = np.full(len(pairs), side)
    pot = TiEdgeEdgeContact(pairs, edges, sides, ref_tests.K, EPS)
    ref_pot = EdgeEdgeContact(pairs, edges, sides, ref_tests.K, EPS)
    _assert_same(pot, ref_pot, x)
    # finite differences on the pairs of the reference FD test (one per region, near-parallel too)
    x_fd, active = ref_tests.edge_edge_fd_scene(np.random.default_rng(11))
    edges = np.arange(16).reshape(8, 2)
    pairs = np.array([[0, 1], [2, 3], [4, 5], [6, 7]])
    ref_tests._check_potential(TiEdgeEdgeContact(pairs, edges, np.full(4, side), ref_tests.K, EPS), x_fd, active)


def _assert_same(pot, ref_pot, x):
    """Energy, active pairs, gradient (bit for bit) and Hessian blocks (1e-12) equal the reference's."""
    assert pot.energy(x) == ref_pot.energy(x)
    np.testing.assert_array_equal(pot.active_mask(x), ref_pot.active_mask(x))
    np.testing.assert_array_equal(pot.gradient(x), ref_pot.gradient(x))
    for projection in ("none", "clamp"):
        h, h_ref = pot.hessian(x, projection), ref_pot.hessian(x, projection)
        np.testing.assert_array_equal(h.vertices, h_ref.vertices)
        assert relative_error(h.blocks, h_ref.blocks) < 1e-12
    f, f_ref = pot.contact_frames(x), ref_pot.contact_frames(x)
    np.testing.assert_array_equal(f.lam, f_ref.lam)
    np.testing.assert_array_equal(f.pair_index, f_ref.pair_index)
    np.testing.assert_array_equal(f.vertices, f_ref.vertices)
    # weights and normals of the set-up kernel: the reference's dot products (einsum) round differently
    np.testing.assert_allclose(f.weights, f_ref.weights, rtol=0, atol=1e-12)
    np.testing.assert_allclose(f.normal, f_ref.normal, rtol=0, atol=1e-12)


def test_contact_set_uses_the_kernels_on_the_taichi_backend(ti_cpu):
    from sim_core.contact_set import ContactSet
    from sim_core.energies.contact.kernel import TiEdgeEdgeContact, TiVertexTriangleContact
    from sim_core.scenes.task_scene import load_task_scene, task_initial_state
    from thinshell_ros.paths import bundled_scene

    model = load_task_scene(bundled_scene("forming"))
    x = task_initial_state(model).x
    contact = ContactSet(model)
    memory = contact.begin_step(x, None)
    vt, ee = contact.potentials(x, x, memory)[:2]
    assert type(vt) is VertexTriangleContact and type(ee) is EdgeEdgeContact
    contact = ContactSet(model, backend="taichi-cpu")
    memory = contact.begin_step(x, None)
    ti_vt, ti_ee = contact.potentials(x, x, memory)[:2]
    assert type(ti_vt) is TiVertexTriangleContact and type(ti_ee) is TiEdgeEdgeContact
    for a, b in ((ti_vt, vt), (ti_ee, ee)):
        np.testing.assert_array_equal(a.pairs, b.pairs)
        assert a.energy(x) == b.energy(x)
