"""Penalty contact: FD derivatives per region, PSD blocks, side memory, plane force, frames."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.collision.distances import EdgeEdgeRegion, PointTriangleRegion
from sim_core.energies.contact.reference import EdgeEdgeContact, PlaneContact, VertexTriangleContact
from sim_core.errors import ConfigError
from sim_core.workspace import workspace_of
from tests.support.fd import dense_hessian, fd_gradient, fd_hessian, relative_error

K, EPS = 1.0e4, 4.0e-4
TRI = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.01, 0.0]])

# vertex positions relative to TRI in each region, all within eps of the triangle
VT_POINTS = {
    PointTriangleRegion.FACE: [0.003, 0.003, 0.0002],
    PointTriangleRegion.EDGE_AB: [0.005, -0.0002, 0.0002],
    PointTriangleRegion.EDGE_BC: [0.0052, 0.0052, -0.0002],
    PointTriangleRegion.EDGE_CA: [-0.0002, 0.004, 0.0002],
    PointTriangleRegion.VERTEX_A: [-0.0002, -0.0002, 0.0002],
    PointTriangleRegion.VERTEX_B: [0.0102, -0.0001, -0.0002],
    PointTriangleRegion.VERTEX_C: [-0.0001, 0.0102, 0.0002],
}


def _check_potential(pot, x, n_active):
    assert pot.energy(x) > 0.0
    g = pot.gradient(x)
    assert relative_error(g, fd_gradient(pot.energy, x, h=1e-8)) < 1e-5
    blocks = pot.hessian(x, "none")
    assert blocks.vertices.shape[0] == n_active
    H = dense_hessian(blocks, x.shape[0])
    assert relative_error(H, fd_hessian(pot.gradient, x, h=1e-8)) < 1e-5
    projected = pot.hessian(x, "clamp").blocks
    assert np.min(np.linalg.eigvalsh(projected)) > -1e-9 * np.max(np.abs(projected))
    dg = pot.parameter_gradient(x, "stiffness")
    k0 = pot.stiffness
    pot.stiffness = k0 * (1 + 1e-6)
    gp = pot.gradient(x)
    pot.stiffness = k0
    assert relative_error(dg, (gp - g) / (k0 * 1e-6)) < 1e-5
    with pytest.raises(KeyError):
        pot.parameter_gradient(x, "eps")


def _vt_scene(rng, regions):
    """One triangle per pair (global vertex array), randomly rotated/perturbed."""
    xs, tris, pairs = [], [], []
    for i, region in enumerate(regions):
        local = np.concatenate([np.array(VT_POINTS[region])[None], TRI]) + rng.normal(scale=2e-5, size=(4, 3))
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        xs.append(local @ q.T + rng.normal(size=3) * 0.1)
        tris.append([4 * i + 1, 4 * i + 2, 4 * i + 3])
        pairs.append([4 * i, i])
    return np.concatenate(xs), np.array(tris), np.array(pairs)


@pytest.mark.parametrize("side", [1.0, -1.0, 0.0])
def test_vertex_triangle_fd_every_region(side):
    rng = np.random.default_rng(10)
    regions = list(PointTriangleRegion)
    x, tris, pairs = _vt_scene(rng, regions)
    # with side -1 the face-region vertex (above the triangle) counts as penetrated
    pot = VertexTriangleContact(pairs, tris, np.full(len(pairs), side), K, EPS)
    d = pot.distance(x)
    assert np.all(d < EPS)
    _check_potential(pot, x, len(pairs))


def test_vertex_triangle_inactive_pairs_contribute_nothing():
    x = np.concatenate([[[0.003, 0.003, 0.001]], TRI])
    pot = VertexTriangleContact(np.array([[0, 0]]), np.array([[1, 2, 3]]), np.array([1.0]), K, EPS)
    assert pot.energy(x) == 0.0 and np.all(pot.gradient(x) == 0.0)
    assert pot.hessian(x).blocks.shape == (0, 12, 12)
    assert pot.contact_frames(x).lam.shape == (0,)


def test_unsigned_pairs_measure_the_euclidean_distance_from_either_side():
    """Side 0: d is the distance to the triangle (edge) whichever side the vertex (edge) is on."""
    tris = np.array([[1, 2, 3]])
    for z in (1e-4, -1e-4):
        x = np.concatenate([[[0.003, 0.003, z]], TRI])
        pot = VertexTriangleContact(np.array([[0, 0]]), tris, np.array([0.0]), K, EPS)
        assert pot.distance(x)[0] == pytest.approx(1e-4)
        assert -pot.gradient(x)[0, 2] == pytest.approx(np.sign(z) * K * (EPS - 1e-4))  # pushed away
        assert pot.resolved_sides(x)[0] == np.sign(z)
        frames = pot.contact_frames(x)
        assert np.allclose(frames.normal[0], [0, 0, np.sign(z)])
    edges = np.array([[0, 1], [2, 3]])
    for z in (1e-4, -1e-4):
        x = np.array([[0, 0, 0], [0.01, 0, 0], [0.005, -0.005, z], [0.005, 0.005, z]], dtype=float)
        pot = EdgeEdgeContact(np.array([[0, 1]]), edges, np.array([0.0]), K, EPS)
        assert pot.distance(x)[0] == pytest.approx(1e-4)
        assert np.sign(-pot.gradient(x)[2, 2]) == np.sign(z)


def test_side_memory_pushes_penetrated_vertex_back():
    """A vertex 0.1 mm below the triangle, remembered on the + side, is pushed up (back)."""
    x = np.concatenate([[[0.003, 0.003, -1e-4]], TRI])
    tris = np.array([[1, 2, 3]])  # normal (b - a) x (c - a) = +z
    pot = VertexTriangleContact(np.array([[0, 0]]), tris, np.array([1.0]), K, EPS)
    force = -pot.gradient(x)
    assert pot.distance(x)[0] == pytest.approx(-1e-4)
    assert force[0, 2] == pytest.approx(K * (EPS + 1e-4))  # k (eps - d) with d = -1e-4
    assert np.allclose(force[0, :2], 0.0)
    assert np.allclose(force.sum(axis=0), 0.0)  # reaction on the triangle
    # without memory (side taken from the current, penetrated position) it would be pushed through
    pot_wrong = VertexTriangleContact(np.array([[0, 0]]), tris, np.array([-1.0]), K, EPS)
    assert -pot_wrong.gradient(x)[0, 2] < 0.0


def edge_edge_fd_scene(rng) -> tuple[np.ndarray, int]:
    """Four edge pairs (interior, point-edge, point-point, near-parallel closest points), each
    randomly rotated and moved: positions ``(16, 3)`` m and the number of pairs (4)."""
    configs = [
        [[0, 0, 0], [0.01, 0, 0], [0.005, -0.005, 0.0002], [0.004, 0.005, 0.0003]],  # interior
        [[0, 0, 0], [0.01, 0, 0], [0.0102, -0.005, 0.0002], [0.0104, 0.005, 0.0001]],  # point-edge
        [[0, 0, 0], [0.01, 0, 0], [0.0102, 0.0001, 0.0002], [0.02, 0.003, 0.001]],  # point-point
        [[0, 0, 0], [0.01, 0, 0], [0.002, 0.0001, 0.0002], [0.012, 0.0001, 0.000201]],  # near-parallel
    ]
    xs = []
    for c in configs:
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        xs.append((np.array(c) + rng.normal(scale=1e-6, size=(4, 3))) @ q.T + rng.normal(size=3) * 0.1)
    return np.concatenate(xs), 4


@pytest.mark.parametrize("side", [1.0, -1.0, 0.0])
def test_edge_edge_fd_generic_and_near_parallel(side):
    x, _ = edge_edge_fd_scene(np.random.default_rng(11))
    edges = np.arange(16).reshape(8, 2)
    pairs = np.array([[0, 1], [2, 3], [4, 5], [6, 7]])
    pot = EdgeEdgeContact(pairs, edges, np.full(4, side), K, EPS)
    assert np.all(pot.distance(x) < EPS)
    _check_potential(pot, x, 4)


def test_edge_edge_side_memory_pushes_crossed_edges_back():
    # edge b crossed 0.1 mm below edge a; remembered side is the one of "b above a"
    x = np.array([[0, 0, 0], [0.01, 0, 0], [0.005, -0.005, -1e-4], [0.005, 0.005, -1e-4]], dtype=float)
    n = np.cross(x[1] - x[0], x[3] - x[2])
    side_above = np.sign(n @ (x[0] - (x[2] + [0, 0, 2e-4])))
    pot = EdgeEdgeContact(np.array([[0, 1]]), np.array([[0, 1], [2, 3]]), np.array([side_above]), K, EPS)
    assert pot.distance(x)[0] == pytest.approx(-1e-4)
    force = -pot.gradient(x)
    assert np.all(force[2:, 2] > 0) and np.all(force[:2, 2] < 0)
    frames = pot.contact_frames(x)
    assert frames.lam[0] == pytest.approx(K * (EPS + 1e-4))
    assert np.allclose(frames.normal[0], [0, 0, -1])  # force on edge a points down


def test_plane_contact_force_and_fd():
    rng = np.random.default_rng(12)
    x = rng.uniform(-0.01, 0.01, size=(6, 3))
    x[:, 2] = [0.0101, 0.0102, 0.0099, 0.0105, 0.0110, 0.01035]  # table at z = 0.01
    pot = PlaneContact(np.arange(6), [0, 0, 2.0], 0.01, K, EPS)
    d = x[:, 2] - 0.01
    force = -pot.gradient(x)
    expect = np.where(d < EPS, K * (EPS - d), 0.0)
    assert np.allclose(force[:, 2], expect) and np.allclose(force[:, :2], 0.0)
    _check_potential(pot, x, int(np.sum(d < EPS)))
    frames = pot.contact_frames(x)
    assert np.allclose(frames.lam, expect[d < EPS]) and np.allclose(frames.normal, [0, 0, 1])


def test_contact_frames_give_the_force_on_the_first_side():
    rng = np.random.default_rng(13)
    x, tris, pairs = _vt_scene(rng, list(PointTriangleRegion))
    pot = VertexTriangleContact(pairs, tris, np.ones(len(pairs)), K, EPS)
    fr = pot.contact_frames(x)
    force = -pot.gradient(x)
    assert np.allclose(force[pairs[:, 0]], fr.lam[:, None] * fr.normal)
    assert np.allclose(np.linalg.norm(fr.normal, axis=1), 1.0)
    # weights reproduce vertex minus closest point, which lies along the normal
    rel = np.einsum("kj,kjd->kd", fr.weights, x[fr.vertices])
    assert np.allclose(np.einsum("kd,kd->k", rel, fr.normal), pot.distance(x))
    ee_x = np.array([[0, 0, 0], [0.01, 0, 0], [0.0102, 0.0001, 0.0002], [0.02, 0.003, 0.001]], float)
    ee = EdgeEdgeContact(np.array([[0, 1]]), np.array([[0, 1], [2, 3]]), np.array([1.0]), K, EPS)
    f = ee.contact_frames(ee_x)
    assert np.allclose(-ee.gradient(ee_x)[1], f.lam[0] * f.normal[0])


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: VertexTriangleContact([[0, 0]], [[1, 2, 3]], [1.0], 0.0, EPS), "stiffness"),
        (lambda: VertexTriangleContact([[0, 0]], [[1, 2, 3]], [1.0], K, np.nan), "eps"),
        (lambda: VertexTriangleContact([[0, 0]], [[1, 2, 3]], [0.5], K, EPS), r"\+1 or -1"),
        (lambda: VertexTriangleContact([[0, 4]], [[1, 2, 3]], [1.0], K, EPS), "triangle index"),
        (lambda: EdgeEdgeContact([[0, 1]], [[0, 1], [2, 3]], np.ones(2), K, EPS), "1 pairs but 2 sides"),
        # checked (a contact set's own candidates and step sides): the values are not checked again, the shapes and
        # the penalty's parameters still are
        (lambda: EdgeEdgeContact([[0, 1]], [[0, 1], [2, 3]], np.ones(2), K, EPS, checked=True), "1 pairs but 2 sides"),
        (lambda: VertexTriangleContact([[0, 0]], [[1, 2, 3]], [1.0], 0.0, EPS, checked=True), "stiffness"),
        (lambda: PlaneContact(np.arange(3), [0, 0, 0], 0.0, K, EPS), "normal"),
        (lambda: PlaneContact(np.arange(3), [0, 0, 1], 0.0, -5.0, EPS), "stiffness"),
    ],
)
def test_constructor_errors(make, match):
    with pytest.raises(ConfigError, match=match):
        make()


def test_penalty_is_c1_at_face_edge_boundary_on_the_remembered_side():
    """Energy gradient is continuous when a vertex above the triangle crosses into the edge region."""
    tris = np.array([[1, 2, 3]])
    pot = VertexTriangleContact(np.array([[0, 0]]), tris, np.array([1.0]), K, EPS)
    g = []
    for y in (1e-9, -1e-9):  # just inside / outside edge ab (y = 0)
        x = np.concatenate([[[0.004, y, 2e-4]], TRI])
        g.append(pot.gradient(x))
    assert relative_error(g[0], g[1]) < 1e-5
    assert np.isclose(pot.energy(np.concatenate([[[0.004, 1e-9, 2e-4]], TRI])), 0.5 * K * (2e-4 - EPS) ** 2)


def test_kept_evaluation_is_reused_only_for_the_same_function():
    # energy, gradient and Hessian of one x share one distance evaluation, also across a copy of the
    # potential with the same pairs and sides (inherit_evaluation); other sides do not inherit
    rng = np.random.default_rng(12)
    regions = list(PointTriangleRegion)
    x, tris, pairs = _vt_scene(rng, regions)
    sides = np.ones(len(pairs))
    fresh = VertexTriangleContact(pairs, tris, sides, K, EPS)
    e, g, h = fresh.energy(x), fresh.gradient(x), fresh.hessian(x, "none").blocks
    first = VertexTriangleContact(pairs, tris, sides, K, EPS)
    first.energy(x)  # keeps the order-0 result
    same = VertexTriangleContact(pairs, tris, sides.copy(), K, EPS)
    same.inherit_evaluation(first)
    assert workspace_of(same).get(same, "evaluation") is workspace_of(first).get(first, "evaluation")
    assert same.energy(x) == e
    assert np.array_equal(same.gradient(x), g) and np.array_equal(same.hessian(x, "none").blocks, h)
    flipped = VertexTriangleContact(pairs, tris, -sides, K, EPS)
    flipped.inherit_evaluation(first)
    assert workspace_of(flipped).get(flipped, "evaluation") is None
    # a kept result is only used at equal positions
    x2 = x + 1e-6
    assert same.energy(x2) == VertexTriangleContact(pairs, tris, sides, K, EPS).energy(x2)


def test_kept_evaluation_is_matched_bitwise_and_its_stiffness_terms_per_stiffness():
    # equal positions in another array reuse the evaluation; positions changed in place, or of
    # another dtype, do not; the energy and gradient follow a changed stiffness; a returned gradient
    # is the caller's (changing it leaves the kept one as it was)
    from sim_core.energies.contact.reference import positions_key

    rng = np.random.default_rng(13)
    x, tris, pairs = _vt_scene(rng, list(PointTriangleRegion))
    pot = VertexTriangleContact(pairs, tris, np.ones(len(pairs)), K, EPS)
    g = pot.gradient(x)
    kept = workspace_of(pot).get(pot, "evaluation")
    assert pot.energy(x.copy()) > 0.0 and workspace_of(pot).get(pot, "evaluation") is kept
    assert positions_key(x) == positions_key(x.copy()) != positions_key(x.astype(np.float32))
    assert positions_key(x.tolist()) == positions_key(x)
    y = x.copy()
    y[0, 2] += 1e-7  # in place: another key, a new evaluation
    assert positions_key(y) != positions_key(x)
    assert pot.energy(y) == VertexTriangleContact(pairs, tris, np.ones(len(pairs)), K, EPS).energy(y)
    assert workspace_of(pot).get(pot, "evaluation") is not kept
    pot.gradient(x)[:] = 0.0
    np.testing.assert_array_equal(pot.gradient(x), g)
    e = pot.energy(x)
    pot.stiffness = 2.0 * K
    assert pot.energy(x) == VertexTriangleContact(pairs, tris, np.ones(len(pairs)), 2.0 * K, EPS).energy(x) != e
    np.testing.assert_array_equal(pot.gradient(x),
                                  VertexTriangleContact(pairs, tris, np.ones(len(pairs)), 2.0 * K, EPS).gradient(x))


def test_frozen_positions_are_keyed_by_identity_and_give_the_same_evaluation():
    """A read-only array that owns its memory (the lockstep solver's iterates) is keyed by identity: equal to its
    own key only, not to an equal frozen copy's nor to the bytes key of the same values; a read-only view or a
    writeable array is keyed by its bytes. The evaluations are the same either way."""
    from sim_core.energies.base import positions_key

    rng = np.random.default_rng(17)
    x, tris, pairs = _vt_scene(rng, list(PointTriangleRegion))
    frozen, twin = x.copy(), x.copy()
    frozen.flags.writeable = twin.flags.writeable = False
    assert positions_key(frozen) == positions_key(frozen) != positions_key(twin)
    assert positions_key(frozen) != positions_key(x) and positions_key(x) != positions_key(frozen)
    view = x[:]
    view.flags.writeable = False
    assert positions_key(view) == positions_key(x)  # a view: its base may still change, so its bytes
    assert len({positions_key(frozen), positions_key(frozen)}) == 1
    pot = VertexTriangleContact(pairs, tris, np.ones(len(pairs)), K, EPS)
    ref = VertexTriangleContact(pairs, tris, np.ones(len(pairs)), K, EPS)
    np.testing.assert_array_equal(pot.gradient(frozen), ref.gradient(x))
    kept = workspace_of(pot).get(pot, "evaluation")
    assert pot.energy(frozen) == ref.energy(x) and workspace_of(pot).get(pot, "evaluation") is kept
    assert pot.energy(twin) == ref.energy(x) and workspace_of(pot).get(pot, "evaluation") is not kept


@pytest.mark.parametrize("projection", ["none", "clamp"])
def test_hessian_of_marked_vertices_is_the_marked_pairs_blocks(projection):
    """With a vertex mask, the Hessian holds the blocks of the active pairs whose vertices are marked
    (each pair here has its own four vertices), equal to those of the whole Hessian, and no other."""
    rng = np.random.default_rng(4)
    regions = list(PointTriangleRegion)
    x, tris, pairs = _vt_scene(rng, regions)
    pot = VertexTriangleContact(pairs, tris, np.full(len(pairs), 1.0), K, EPS)
    whole = pot.hessian(x, projection)
    marked = np.zeros(x.shape[0], dtype=bool)
    chosen = np.array([1, 4, 5])
    marked[(4 * chosen[:, None] + np.arange(4)).ravel()] = True
    part = pot.hessian_of_vertices(x, projection, marked)
    rows = np.flatnonzero(marked[whole.vertices[:, 0]])
    assert rows.size == chosen.size
    np.testing.assert_array_equal(part.vertices, whole.vertices[rows])
    np.testing.assert_allclose(part.blocks, whole.blocks[rows], rtol=0, atol=1e-12 * np.abs(whole.blocks).max())
