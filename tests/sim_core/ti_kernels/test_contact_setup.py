"""The contact set-up kernels (pair geometry, contact frames, tangent bases) equal the NumPy
reference, the reference pair geometry means what it says, and the contact set takes the same
sides, friction and side memory on the Taichi backend as on the NumPy reference."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.collision.distances import (
    EdgeEdgeRegion,
    PointTriangleRegion,
    edge_edge_closest_points,
    point_triangle_closest_point,
)
from sim_core.collision.pair_geometry import pair_geometry
from sim_core.energies.contact.reference import EdgeEdgeContact, VertexTriangleContact
from sim_core.energies.friction.reference import tangent_basis
from tests.sim_core.ti_kernels.test_contact_distance import EPS, _near_parallel_edges, _random_pairs


def _batch(seed: int, count: int = 3000) -> tuple[np.ndarray, np.ndarray]:
    """Positions ``(4 k, 3)`` of random 4-vertex pairs (near-parallel edge pairs included) and the
    pairs' vertex indices ``(k, 4)``."""
    rng = np.random.default_rng(seed)
    z = np.concatenate([_random_pairs(rng, count), _near_parallel_edges(rng, count // 3)])
    return z.reshape(-1, 3), np.arange(4 * z.shape[0]).reshape(-1, 4)


def test_reference_pair_geometry_of_known_configurations():
    tri = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    x = np.array([[0.2, 0.2, 0.1]] + tri + [[0.2, 0.2, -0.1]] + tri + [[2.0, 2.0, 0.1]] + tri)
    vt = np.arange(12).reshape(3, 4)
    # crossing edges, b above a; then parallel edges
    x_ee = np.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.5], [0.0, 1.0, 0.5],
                     [0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.1, 0.0], [1.0, 0.1, 0.0]])
    x = np.concatenate([x, x_ee])
    ee = 12 + np.arange(8).reshape(2, 4)
    geo = pair_geometry(x, vt, ee)
    np.testing.assert_array_equal(geo.vt_above, [True, True, False])
    np.testing.assert_array_equal(geo.vt_side, [1.0, -1.0, 1.0])
    np.testing.assert_allclose(geo.ee_sine, [1.0, 0.0], atol=1e-15)
    assert geo.ee_interior[0]
    # (a1 - a0) x (b1 - b0) = +z (times 4), a0 - b0 = (-1, 1, -0.5): below
    assert geo.ee_side[0] == -1.0
    empty = pair_geometry(x, np.zeros((0, 4), np.int64), np.zeros((0, 4), np.int64))
    assert all(a.shape == (0,) for a in empty)


def test_pair_geometry_kernel_equals_the_reference_bit_for_bit(ti_cpu):
    from sim_core.energies.contact.setup_kernel import pair_geometry as ti_pair_geometry

    x, vertices = _batch(3)
    ref, tik = pair_geometry(x, vertices, vertices), ti_pair_geometry(x, vertices, vertices)
    for name in ref._fields:
        np.testing.assert_array_equal(getattr(tik, name), getattr(ref, name), err_msg=name)
        assert getattr(tik, name).dtype == getattr(ref, name).dtype, name
    # every outcome is exercised: above / beside, both sides, interior / not, kept / near-parallel
    assert ref.vt_above.any() and not ref.vt_above.all() and ref.ee_interior.any() and not ref.ee_interior.all()
    assert set(np.unique(ref.vt_side)) == set(np.unique(ref.ee_side)) == {-1.0, 1.0}
    assert (ref.ee_sine < 0.1).any() and (ref.ee_sine > 0.1).any()
    # the two kinds in one launch, any of them empty
    only_vt = ti_pair_geometry(x, vertices[:5], np.zeros((0, 4), np.int64))
    np.testing.assert_array_equal(only_vt.vt_side, ref.vt_side[:5])
    assert only_vt.ee_side.shape == (0,)
    only_ee = ti_pair_geometry(x, np.zeros((0, 4), np.int64), vertices[:5])
    np.testing.assert_array_equal(only_ee.ee_sine, ref.ee_sine[:5])


def _int32_lists(seed: int, monkeypatch, device_arguments: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions and two overlapping int32 pair-vertex lists of ``_batch(seed)``, as a candidate list keeps them;
    with ``device_arguments`` the set-up kernels' CUDA launch path emulated on the CPU arch."""
    from sim_core import ti_backend
    from sim_core.energies.contact import setup_kernel

    x, vertices = _batch(seed)
    if device_arguments:
        for module in (setup_kernel, ti_backend):
            monkeypatch.setattr(module, "current_arch", lambda: "cuda")
    return x, vertices[: len(vertices) // 2].astype(np.int32), vertices[len(vertices) // 3:].astype(np.int32)


@pytest.mark.parametrize("device_arguments", [False, True])
def test_pair_geometry_of_kept_int32_indices_equals_the_reference(ti_cpu, monkeypatch, device_arguments):
    """``pair_geometry(..., device=cache)`` reads a candidate list's kept int32 indices as they are (through CUDA's
    launch path too, emulated on the CPU arch: their device copies kept in the cache, sent once per array object);
    the same geometry as the kernel's launch through its kept arrays (which equals the NumPy reference bit for bit
    on the CPU, above), an empty kind included, and at frozen positions taken as they are; other index arrays are
    refused."""
    from sim_core.energies.contact import setup_kernel

    x, vt, ee = _int32_lists(5, monkeypatch, device_arguments)
    cache: dict = {}
    for vt_rows, ee_rows in ((vt, ee), (vt, ee), (vt[:0], ee), (vt, ee[:0])):
        ref = setup_kernel.pair_geometry(x, vt_rows.astype(np.int64), ee_rows.astype(np.int64))
        got = setup_kernel.pair_geometry(x, vt_rows, ee_rows, device=cache)
        for name in ref._fields:
            np.testing.assert_array_equal(getattr(got, name), getattr(ref, name), err_msg=name)
    if device_arguments:
        assert cache["geometry_vt"][0] is vt and cache["geometry_ee"][0] is ee
    else:
        assert not cache
    # frozen positions (a lockstep batch's iterates) are passed as they are, on CUDA sent once per array object
    for scale in (1e-3, 2e-3, 2e-3):
        y = x + scale
        y.flags.writeable = False
        ref = setup_kernel.pair_geometry(y.copy(), vt.astype(np.int64), ee.astype(np.int64))
        got = setup_kernel.pair_geometry(y, vt, ee, device=cache)
        for name in ref._fields:
            np.testing.assert_array_equal(getattr(got, name), getattr(ref, name), err_msg=name)
        if device_arguments:
            assert setup_kernel._ARRAYS.device()["frozen_x:_geometry_kernel"][0] is y
    with pytest.raises(ValueError, match="C-contiguous int32"):
        setup_kernel.pair_geometry(x, vt.astype(np.int64), ee, device=cache)


@pytest.mark.parametrize("device_arguments", [False, True])
def test_pair_codes_equal_the_geometry_with_the_sines_compared(ti_cpu, monkeypatch, device_arguments):
    """``pair_codes`` (one int32 code a pair copied back) gives ``pair_geometry``'s sides and regions and its sines
    compared with the least sine (host and emulated CUDA launch paths; empty kinds; thresholds at, between and
    beyond the measured sines); sides are float64 as the geometry's."""
    from sim_core.collision.pair_geometry import ListGeometry
    from sim_core.energies.contact import setup_kernel

    x, vt, ee = _int32_lists(6, monkeypatch, device_arguments)
    cache: dict = {}
    ref = setup_kernel.pair_geometry(x, vt, ee, device=cache)
    sines = np.sort(ref.ee_sine)
    for min_sine in (0.0, sines[len(sines) // 2], 0.5 * (sines[1] + sines[2]), 1.0, 0.1):
        for vt_rows, ee_rows in ((vt, ee), (vt[:0], ee), (vt, ee[:0])):
            want = ListGeometry.of(setup_kernel.pair_geometry(x, vt_rows, ee_rows, device=cache), min_sine)
            got = setup_kernel.pair_codes(x, vt_rows, ee_rows, min_sine, cache)
            for name in want._fields:
                np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)
                assert getattr(got, name).dtype == getattr(want, name).dtype, name
    assert 0 < int(np.sum(ref.ee_sine > 0.1)) < len(ee)  # both kinds of pairs at the last threshold
    with pytest.raises(ValueError, match="C-contiguous int32"):
        setup_kernel.pair_codes(x, vt.astype(np.int64), ee, 0.1, cache)


@pytest.mark.parametrize("point_first", [True, False])
def test_contact_frames_kernel_equals_the_reference(ti_cpu, point_first):
    from sim_core.energies.contact.setup_kernel import contact_frames

    x, vertices = _batch(4)
    rng = np.random.default_rng(5)
    sides = rng.choice([-1.0, 0.0, 1.0], size=len(vertices))
    # a reference potential with every pair active (eps beyond every distance) and these vertices
    pairs, table = np.zeros((0, 2), np.int64), np.zeros((1, 3 if point_first else 2), np.int64)
    ref = (VertexTriangleContact if point_first else EdgeEdgeContact)(pairs, table, np.zeros(0), 1.0, 1.0)
    ref.vertices, ref.sides = vertices, sides
    f = ref.contact_frames(x)
    assert f.pair_index.size == len(vertices)
    weights, normal = contact_frames(x, vertices, sides, point_first)
    # the edge parameters of near-parallel edges (sine < 1e-2, left out of the contact set) are
    # ill-conditioned: the round-off of the dot products is amplified there
    kept = pair_geometry(x, vertices[:0], vertices).ee_sine > 1e-2 if not point_first else slice(None)
    np.testing.assert_allclose(weights[kept], f.weights[kept], rtol=0, atol=1e-12)
    np.testing.assert_allclose(normal[kept], f.normal[kept], rtol=0, atol=1e-12)
    np.testing.assert_allclose(weights, f.weights, rtol=0, atol=1e-9)
    np.testing.assert_allclose(normal, f.normal, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0, atol=1e-14)
    z = x[vertices]
    if point_first:  # every region, and the face normals oriented by the resolved side
        region = point_triangle_closest_point(z[:, 0], z[:, 1], z[:, 2], z[:, 3])[1]
        assert set(np.unique(region)) == {int(r) for r in PointTriangleRegion}
    else:
        region = edge_edge_closest_points(z[:, 0], z[:, 1], z[:, 2], z[:, 3])[2]
        assert set(np.unique(region)) == {int(r) for r in EdgeEdgeRegion}
    empty_w, empty_n = contact_frames(x, np.zeros((0, 4), np.int64), np.zeros(0), point_first)
    assert empty_w.shape == (0, 4) and empty_n.shape == (0, 3)


def test_kept_launch_arrays_give_each_call_its_own_results(ti_cpu):
    """The set-up functions copy into kept arrays (longer than a later call's pairs) and out of them:
    a shorter call after a longer one, and other positions, give what fresh arrays give."""
    from sim_core.energies.contact import setup_kernel as contact_setup

    x, vertices = _batch(4, 300)
    geometry = contact_setup.pair_geometry(x, vertices, vertices)
    frames = contact_setup.contact_frames(x, vertices, np.ones(len(vertices)), True)
    tangents = contact_setup.tangent_basis(frames[1])
    y, short = 2.0 * x, vertices[:7]
    for name, value in zip(geometry._fields, contact_setup.pair_geometry(y, short, short[:3])):
        np.testing.assert_array_equal(value, getattr(pair_geometry(y, short, short[:3]), name), err_msg=name)
    weights, normal = contact_setup.contact_frames(y, short, -np.ones(7), False)
    assert weights.shape == (7, 4) and normal.shape == (7, 3)
    np.testing.assert_array_equal(contact_setup.tangent_basis(normal), tangent_basis(normal))
    np.testing.assert_array_equal(contact_setup.tangent_basis(frames[1]), tangents)  # earlier results unchanged
    assert frames[0].shape == (len(vertices), 4) and not np.shares_memory(frames[1], normal)


def test_tangent_basis_kernel_equals_the_reference_and_is_orthonormal(ti_cpu):
    from sim_core.energies.contact.setup_kernel import tangent_basis as ti_tangent_basis

    rng = np.random.default_rng(6)
    normal = rng.normal(size=(500, 3))
    normal[:3] = [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.6, 0.0, -0.8]]  # ties of argmin |n|
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    T = ti_tangent_basis(normal)
    np.testing.assert_array_equal(T, tangent_basis(normal))
    frame = np.concatenate([T, normal[:, :, None]], axis=2)
    np.testing.assert_allclose(np.einsum("kdi,kdj->kij", frame, frame), np.broadcast_to(np.eye(3), (500, 3, 3)),
                               atol=1e-14)
    assert ti_tangent_basis(np.zeros((0, 3))).shape == (0, 3, 2)


def _forming_contact(backend: str):
    from sim_core.contact_set import ContactSet
    from sim_core.scenes.task_scene import load_task_scene, task_initial_state
    from thinshell_ros.paths import bundled_scene

    model = load_task_scene(bundled_scene("forming"))
    return ContactSet(model, backend=backend), task_initial_state(model).x


def test_contact_set_sides_friction_and_memory_equal_the_reference_on_the_taichi_backend(ti_cpu):
    """A pressed Forming state: the Taichi set-up keeps the same pairs and step sides, friction rows
    (frames to round-off) and remembered sides as the NumPy reference."""
    from sim_core.energies.friction.kernel import TiLaggedFriction

    results = []
    for backend in ("numpy", "taichi-cpu"):
        contact, x = _forming_contact(backend)
        rng = np.random.default_rng(7)
        # jitter the rest state by a fraction of eps so that pairs of every kind touch
        x_n = x + 0.4 * contact.eps * rng.normal(size=x.shape)
        memory = contact.begin_step(x_n, None)
        vt, ee = contact.potentials(x_n, x_n, memory)[:2]
        friction = contact.friction(x_n, 0.01, memory)
        x_end = x_n + 0.2 * contact.eps * rng.normal(size=x.shape)
        end_memory = contact.end_step(x_end, memory)
        results.append((vt, ee, friction, end_memory))
    (vt, ee, fr, mem), (ti_vt, ti_ee, ti_fr, ti_mem) = results
    assert type(ti_fr) is TiLaggedFriction
    assert len(vt.pairs) and len(ee.pairs) and fr.vertices.shape[0] > 0
    assert np.any(vt.sides != 0) and np.any(ee.sides != 0)  # signed pairs too
    for a, b in ((ti_vt, vt), (ti_ee, ee)):
        np.testing.assert_array_equal(a.pairs, b.pairs)
        np.testing.assert_array_equal(a.sides, b.sides)
    np.testing.assert_array_equal(ti_fr.vertices, fr.vertices)
    np.testing.assert_array_equal(ti_fr.lam, fr.lam)
    np.testing.assert_array_equal(ti_fr.mu, fr.mu)
    np.testing.assert_allclose(ti_fr.weights, fr.weights, rtol=0, atol=1e-12)
    np.testing.assert_allclose(ti_fr.tangent, fr.tangent, rtol=0, atol=1e-12)
    assert ti_mem.vertex_triangle == mem.vertex_triangle and ti_mem.edge_edge == mem.edge_edge
    assert len(mem.vertex_triangle) and len(mem.edge_edge)


def test_friction_frames_equal_the_frames_of_each_kind_and_their_tangents_bit_for_bit(ti_cpu):
    """One launch over vertex-triangle rows then edge-edge rows gives what contact_frames of each kind
    and tangent_basis give, bit for bit (every split, the empty list too)."""
    from sim_core.energies.contact import setup_kernel as contact_setup

    x, vertices = _batch(8, 400)
    sides = np.random.default_rng(9).choice([-1.0, 0.0, 1.0], size=len(vertices))
    for split in (0, 1, 137, len(vertices)):
        weights, normal, tangent = contact_setup.friction_frames(x, vertices, sides, split)
        parts = [contact_setup.contact_frames(x, vertices[:split], sides[:split], True),
                 contact_setup.contact_frames(x, vertices[split:], sides[split:], False)]
        np.testing.assert_array_equal(weights, np.concatenate([w for w, _ in parts]))
        np.testing.assert_array_equal(normal, np.concatenate([n for _, n in parts]))
        np.testing.assert_array_equal(tangent, contact_setup.tangent_basis(normal))
    empty = contact_setup.friction_frames(x, vertices[:0], sides[:0], 0)
    assert [a.shape for a in empty] == [(0, 4), (0, 3), (0, 3, 2)]


def test_friction_frames_read_positions_held_on_the_device_as_they_are(ti_cpu, monkeypatch):
    """With ``x_device`` (the positions where the solver's terms hold them on the device) the frames launch and the
    candidate lists' codes read that array, through CUDA's launch path emulated on the CPU arch, instead of sending
    ``x``: the same values bit for bit, and no device copy of the positions made for the launch; off CUDA ``x`` itself
    is read."""
    from sim_core import ti_backend
    from sim_core.energies.contact import setup_kernel as contact_setup
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels.transfer import upload

    x, vertices = _batch(11, 300)
    sides = np.random.default_rng(3).choice([-1.0, 0.0, 1.0], size=len(vertices))
    x.flags.writeable = False  # read-only, as a lockstep batch's x^n
    want = contact_setup.friction_frames(x, vertices, sides, 120)
    held = upload(ti.ndarray(ti.f64, x.shape), np.ascontiguousarray(x))
    stale = ti.ndarray(ti.f64, x.shape)  # zeros: what a launch reading the device array would see
    for got, ref in zip(contact_setup.friction_frames(x, vertices, sides, 120, stale), want):  # off CUDA: x read
        np.testing.assert_array_equal(got, ref)
    for module in (contact_setup, ti_backend):
        monkeypatch.setattr(module, "current_arch", lambda: "cuda")
    names = []  # the launch arrays sent or kept on the device, by name (position 0: the positions)
    on_device = contact_setup.on_device
    monkeypatch.setattr(contact_setup, "on_device", lambda kept, name, *a, **k: (names.append(name),
                                                                                on_device(kept, name, *a, **k))[1])
    for got, ref in zip(contact_setup.friction_frames(x, vertices, sides, 120), want):  # x sent
        np.testing.assert_array_equal(got, ref)
    assert any(name.startswith(("0:", "frozen_x:")) for name in names)
    names.clear()
    for got, ref in zip(contact_setup.friction_frames(x, vertices, sides, 120, held), want):  # x read where held
        np.testing.assert_array_equal(got, ref)
    assert names and not any(name.startswith(("0:", "frozen_x:")) for name in names)
    assert not np.array_equal(contact_setup.friction_frames(x, vertices, sides, 120, stale)[0], want[0])
    # the candidate lists' codes (the pairs' sides at x^n and at the converged positions) likewise
    vt, ee = vertices[:150].astype(np.int32), vertices[100:].astype(np.int32)
    codes = contact_setup.pair_codes(x, vt, ee, 0.1, {})
    names.clear()
    for name, got in zip(codes._fields, contact_setup.pair_codes(x, vt, ee, 0.1, {}, held)):
        np.testing.assert_array_equal(got, getattr(codes, name), err_msg=name)
    assert names and not any(name.startswith(("0:", "frozen_x:")) for name in names)


def test_the_contact_sets_one_launch_friction_equals_the_frames_of_its_potentials(ti_cpu):
    """On the Taichi backend the contact set builds its friction from one set-up launch: the rows, row
    sources, normal forces, coefficients, frames and tangents of the pair potentials' contact_frames
    and the Taichi tangent bases, bit for bit."""
    from sim_core.energies.contact.reference import concatenate_frames
    from sim_core.energies.friction.kernel import TiLaggedFriction

    contact, x = _forming_contact("taichi-cpu")
    x_n = x + 0.4 * contact.eps * np.random.default_rng(7).normal(size=x.shape)
    memory = contact.begin_step(x_n, None)
    friction = contact.friction(x_n, 0.01, memory)
    vt, ee = contact.potentials(x_n, x_n, memory)[:2]
    frames = [pot.contact_frames(x_n) for pot in (vt, ee)]
    assert all(len(f.lam) for f in frames)
    ref = TiLaggedFriction.from_frames(concatenate_frames(frames), friction.mu, x_n, contact.model.contact.eps_v, 0.01)
    for name in ("vertices", "weights", "tangent", "lam", "x_prev"):
        np.testing.assert_array_equal(getattr(friction, name), getattr(ref, name), err_msg=name)
    assert friction.eps_u == ref.eps_u
    assert [s.potential for s in friction.row_sources] == [vt, ee]
    for source, f in zip(friction.row_sources, frames):
        assert source.obstacle is None
        np.testing.assert_array_equal(source.pair_index, f.pair_index)
    bodies = contact.vertex_body
    names = contact.body_names
    second = np.concatenate([frames[0].vertices[:, 1], frames[1].vertices[:, 2]])
    expected_mu = [contact.model.friction_coefficient(names[bodies[a]], names[bodies[b]])
                   for a, b in zip(friction.vertices[:, 0], second)]
    np.testing.assert_array_equal(friction.mu, expected_mu)
