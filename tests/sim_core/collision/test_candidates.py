"""Broad phase: spatial hash and candidate pairs equal brute force; exclusions."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.collision.candidates import PairFilter, box_pairs_kdtree, edge_edge_candidates, vertex_triangle_candidates
from sim_core.collision.distances import point_triangle_distance
from sim_core.collision.memory import ContactMemory, edge_edge_pair_sides, vertex_triangle_pair_sides
from sim_core.collision.spatial_hash import SpatialHash
from sim_core.energies.contact.reference import EdgeEdgeContact, VertexTriangleContact
from sim_core.errors import ConfigError, SimulationDivergedError


def _random_soup(rng, n=300, t=400, size=0.01):
    """Random small triangles and edges in a 5 cm cube (global vertex array)."""
    x = rng.uniform(0, 0.05, size=(n, 3))
    centre = rng.integers(0, n, size=t)
    # triangles made of nearby vertices: pick the 3 nearest of random centres
    d = np.linalg.norm(x[centre][:, None] - x[None], axis=2)
    tris = np.argsort(d, axis=1)[:, :3]
    edges = np.unique(np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1), axis=0)
    return x, tris, edges


def _overlap(amin, amax, bmin, bmax):
    return np.all((amin[:, None] <= bmax[None]) & (bmin[None] <= amax[:, None]), axis=2)


def test_spatial_hash_equals_brute_force():
    rng = np.random.default_rng(0)
    lo = rng.uniform(-1, 1, size=(200, 3))
    hi = lo + rng.uniform(0, 0.3, size=(200, 3))
    qlo = rng.uniform(-1, 1, size=(150, 3))
    qhi = qlo + rng.uniform(0, 0.2, size=(150, 3))
    pairs = SpatialHash(lo, hi, 0.17).query(qlo, qhi)
    brute = np.argwhere(_overlap(qlo, qhi, lo, hi))
    assert len({tuple(p) for p in pairs}) == len(pairs)  # each pair reported once
    assert {tuple(p) for p in pairs} == {tuple(p) for p in brute}


def test_spatial_hash_rejects_bad_cell_size():
    with pytest.raises(ConfigError, match="cell_size"):
        SpatialHash(np.zeros((1, 3)), np.ones((1, 3)), 0.0)


def _three_bodies(x):
    """Vertices dealt to 3 bodies in turn; pairs 0-2 and 1-1 excluded (no self contact of body 1)."""
    body = (np.arange(x.shape[0]) % 3).astype(np.int64)
    return body, np.array([[True, True, False], [True, False, True], [False, True, True]])


@pytest.mark.parametrize("seed", [1, 2])
def test_vertex_triangle_candidates_equal_brute_force(seed):
    rng = np.random.default_rng(seed)
    x, tris, _ = _random_soup(rng)
    body, allowed = _three_bodies(x)
    filt = PairFilter(vertex_body=body, body_pair_allowed=allowed, x_rest=x + 0.001, self_rest_distance=0.004)
    verts = np.arange(0, x.shape[0], 2)
    r = 0.002
    for exclude in (None, filt):
        got = vertex_triangle_candidates(x, verts, tris, r, exclude=exclude)
        tmin, tmax = x[tris].min(axis=1), x[tris].max(axis=1)
        ov = _overlap(x[verts] - r, x[verts] + r, tmin, tmax)
        expect = set()
        for i, j in np.argwhere(ov):
            v, tri = verts[i], tris[j]
            if v in tri:
                continue
            if exclude is not None:
                bv, bt = body[v], body[tri[0]]
                if not allowed[bv, bt]:
                    continue
                if bv == bt:
                    xr = filt.x_rest
                    dr = point_triangle_distance(xr[v][None], *xr[tri][:, None, :])[0]
                    if dr < 0.004:
                        continue
            expect.add((int(v), int(j)))
        assert {tuple(p) for p in got} == expect
        assert len(got) == len(expect) and len(expect) > 0


@pytest.mark.parametrize("seed", [3, 4])
def test_edge_edge_candidates_equal_brute_force(seed):
    rng = np.random.default_rng(seed)
    x, _, edges = _random_soup(rng)
    r = 0.001
    got = edge_edge_candidates(x, edges, r)
    emin, emax = x[edges].min(axis=1), x[edges].max(axis=1)
    ov = _overlap(emin - r, emax + r, emin, emax)
    expect = {
        (int(i), int(j))
        for i, j in np.argwhere(ov)
        if i < j and not set(edges[i].tolist()) & set(edges[j].tolist())
    }
    assert {tuple(p) for p in got} == expect and len(got) == len(expect) > 0
    assert np.all(got[:, 0] < got[:, 1])


@pytest.mark.parametrize("seed", [5, 6])
def test_edge_edge_candidates_with_body_filter_equal_brute_force(seed):
    # the filtered search runs one k-d tree per allowed body pair
    rng = np.random.default_rng(seed)
    x, _, edges = _random_soup(rng)
    body, allowed = _three_bodies(x)
    filt = PairFilter(vertex_body=body, body_pair_allowed=allowed)
    r = 0.001
    got = edge_edge_candidates(x, edges, r, exclude=filt)
    emin, emax = x[edges].min(axis=1), x[edges].max(axis=1)
    ov = _overlap(emin - r, emax + r, emin, emax)
    eb = body[edges[:, 0]]
    expect = {
        (int(i), int(j))
        for i, j in np.argwhere(ov)
        if i < j and not set(edges[i].tolist()) & set(edges[j].tolist()) and allowed[eb[i], eb[j]]
    }
    assert {tuple(p) for p in got} == expect and len(got) == len(expect) > 0
    assert np.all(got[:, 0] < got[:, 1])


def test_box_pairs_find_diagonal_overlaps_of_inflated_boxes():
    # a point off a box's corner by 0.9 r on each axis: the inflated boxes overlap although the
    # Euclidean distance (1.56 r) exceeds r
    r = 0.01
    lo, hi = np.zeros((1, 3)), np.full((1, 3), 0.001)
    p = hi + 0.9 * r
    assert box_pairs_kdtree(p, p, lo, hi, r).tolist() == [[0, 0]]


def _grid_sheet(nx, ny, dx):
    ix, iy = np.meshgrid(np.arange(nx), np.arange(ny))
    x = np.stack([ix.ravel() * dx, iy.ravel() * dx, np.zeros(nx * ny)], axis=1)
    tris = []
    for j in range(ny - 1):
        for i in range(nx - 1):
            v = j * nx + i
            tris += [[v, v + 1, v + nx + 1], [v, v + nx + 1, v + nx]]
    tris = np.array(tris)
    edges = np.unique(np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1), axis=0)
    return x, tris, edges


def test_flat_sheet_at_rest_has_zero_self_contact_energy_with_rest_filter():
    eps = 4e-4
    x, tris, edges = _grid_sheet(8, 8, 3e-4)  # spacing below eps: neighbours are within eps at rest
    body = np.zeros(x.shape[0], dtype=np.int64)
    verts = np.arange(x.shape[0])

    def energies(exclude):
        vt = vertex_triangle_candidates(x, verts, tris, 2 * eps, exclude=exclude)
        ee = edge_edge_candidates(x, edges, 2 * eps, exclude=exclude)
        e_vt = VertexTriangleContact(vt, tris, np.ones(len(vt)), 1e4, eps).energy(x)
        e_ee = EdgeEdgeContact(ee, edges, np.ones(len(ee)), 1e4, eps).energy(x)
        return e_vt, e_ee

    assert min(energies(None)) > 0.0  # without the rest filter the flat sheet touches itself
    filt = PairFilter(vertex_body=body, body_pair_allowed=np.ones((1, 1), bool), x_rest=x, self_rest_distance=2 * eps)
    assert energies(filt) == (0.0, 0.0)
    # a fold brings far-apart parts together: those pairs are kept
    x_fold = x.copy()
    far = x[:, 0] > 0.0015
    x_fold[far, 0] = 0.003 - x[far, 0]
    x_fold[far, 2] = 2e-4
    vt = vertex_triangle_candidates(x_fold, verts, tris, 2 * eps, exclude=filt)
    assert len(vt) > 0


def test_topological_exclusions():
    x, tris, edges = _grid_sheet(3, 3, 1e-3)
    vt = vertex_triangle_candidates(x, np.arange(9), tris, 1.0)
    assert all(v not in tris[t] for v, t in vt)
    ee = edge_edge_candidates(x, edges, 1.0)
    assert all(not set(edges[i]) & set(edges[j]) for i, j in ee)
    assert len(vt) == 9 * len(tris) - 3 * len(tris)


def test_candidate_errors_name_the_problem():
    x, tris, edges = _grid_sheet(3, 3, 1e-3)
    with pytest.raises(ConfigError, match="radius"):
        vertex_triangle_candidates(x, np.arange(9), tris, -1.0)
    with pytest.raises(ConfigError, match=r"shape \(n, 3\)"):
        edge_edge_candidates(x[:, :2], edges, 1e-3)
    with pytest.raises(ConfigError, match="needs x_rest"):
        PairFilter(vertex_body=np.zeros(9, np.int64), self_rest_distance=1e-3)
    with pytest.raises(ConfigError, match="body_pair_allowed"):
        PairFilter(vertex_body=np.arange(9), body_pair_allowed=np.ones((2, 2), bool))


def test_contact_memory_keeps_side_drops_ended_pairs_and_copies():
    mem = ContactMemory("vertex_triangle")
    mem.update(np.array([[5, 2], [1, 7]]), np.array([1.0, -1.0]))
    snapshot = mem.copy()
    # the pair (5, 2) continues with a different current sign: the remembered side wins
    sides = mem.resolve(np.array([[5, 2], [3, 3]]), np.array([-1.0, -1.0]))
    assert sides.tolist() == [1.0, -1.0]
    mem.update(np.array([[5, 2], [3, 3]]), sides)
    s, found = mem.lookup(np.array([[1, 7], [5, 2], [3, 3]]))
    assert found.tolist() == [False, True, True] and s.tolist() == [0.0, 1.0, -1.0]
    # the copy is independent
    s, found = snapshot.lookup(np.array([[1, 7], [3, 3]]))
    assert found.tolist() == [True, False] and s[0] == -1.0
    assert len(mem) == 2 and mem.pairs.tolist() == [[3, 3], [5, 2]]
    mem.update(np.zeros((0, 2), np.int64), np.zeros(0))
    assert len(mem) == 0 and not mem.lookup(np.array([[5, 2]]))[1][0]


def test_contact_memory_errors():
    mem = ContactMemory("edge_edge")
    with pytest.raises(ConfigError, match=r"edge_edge.*\+1 or -1"):
        mem.update(np.array([[0, 1]]), np.array([0.5]))
    with pytest.raises(ConfigError, match="2 pairs but 1 signs"):
        mem.update(np.array([[0, 1], [0, 2]]), np.array([1.0]))
    with pytest.raises(ConfigError, match="duplicate"):
        mem.update(np.array([[0, 1], [0, 1]]), np.array([1.0, 1.0]))


def test_pair_sides_come_from_memory_or_the_reference_positions():
    x = np.array([[0.3, 0.3, 0.1], [0, 0, 0], [1, 0, 0], [0, 1, 0], [0.3, 0.2, -0.1]])
    tris = np.array([[1, 2, 3]])
    pairs = np.array([[0, 0], [4, 0]])
    assert vertex_triangle_pair_sides(x, pairs, tris).tolist() == [1.0, -1.0]
    mem = ContactMemory("vertex_triangle")
    mem.update(np.array([[4, 0]]), np.array([1.0]))  # vertex 4 was above when the pair began
    assert vertex_triangle_pair_sides(x, pairs, tris, mem).tolist() == [1.0, 1.0]
    xe = np.array([[0, 0, 0], [1, 0, 0], [0.5, -0.5, 0.1], [0.5, 0.5, 0.1]])
    edges = np.array([[0, 1], [2, 3]])
    s = edge_edge_pair_sides(xe, np.array([[0, 1]]), edges)
    xe_flip = xe * np.array([1, 1, -1])
    assert edge_edge_pair_sides(xe_flip, np.array([[0, 1]]), edges).tolist() == (-s).tolist()


@pytest.mark.parametrize("seed", range(4))
def test_grouped_spatial_hash_equals_the_grouped_kdtree(seed):
    """The NumPy path's default broad phase (a SpatialHash per allowed body pair): the k-d tree
    reference's pairs on random boxes of interleaved bodies, within one set and between two, with
    and without inflation, zero-size boxes included."""
    from sim_core.collision.candidates import _grouped_box_pairs, grouped_box_pairs_hash

    rng = np.random.default_rng(seed)
    allowed = rng.random((3, 3)) < 0.7
    allowed |= allowed.T
    a_lo = rng.uniform(0.0, 1.0, (300, 3))
    a_hi = a_lo + rng.uniform(0.0, 0.05, (300, 3)) * (rng.random((300, 1)) < 0.8)  # a fifth zero-size
    b_lo = rng.uniform(0.0, 1.0, (200, 3))
    b_hi = b_lo + rng.uniform(0.0, 0.05, (200, 3))
    a_body, b_body = rng.integers(0, 3, 300), rng.integers(0, 3, 200)
    for args in ((a_lo, a_hi, a_body, None, None, None), (a_lo, a_lo, a_body, b_lo, b_hi, b_body)):
        for radius in (0.0, 0.02):
            ref = _grouped_box_pairs(*args, radius, allowed)
            new = grouped_box_pairs_hash(*args, radius, allowed)
            assert len(ref) > 0 or radius == 0.0
            np.testing.assert_array_equal(new[np.lexsort(new.T[::-1])], ref[np.lexsort(ref.T[::-1])])


def test_spatial_hash_box_pairs_of_points_empty_sets_and_nan():
    from sim_core.collision.candidates import box_pairs_hash

    points = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1e-3, 0.0, 0.0], [5.0, 5.0, 5.0]])
    np.testing.assert_array_equal(box_pairs_hash(points, points, None, None, 0.0), [[0, 1]])
    np.testing.assert_array_equal(box_pairs_hash(points, points, None, None, 1e-3), [[0, 1], [0, 2], [1, 2]])
    assert box_pairs_hash(points[:0], points[:0], points, points, 0.1).shape == (0, 2)
    bad = points.copy()
    bad[2, 1] = np.nan
    with pytest.raises(ConfigError, match="NaN or infinite"):
        box_pairs_hash(bad, bad, None, None, 0.1)


def test_spatial_hash_refuses_diverged_boxes_instead_of_allocating_cells():
    lo = np.zeros((3, 3))
    hi = np.full((3, 3), 1e-3)
    hi[1] = [5.0, 5.0, 5.0]  # one element stretched 5 m at a 1 mm cell size: 1.25e11 cells
    with pytest.raises(SimulationDivergedError, match="positions have diverged"):
        SpatialHash(lo, hi, 1e-3)
    SpatialHash(lo[[0, 2]], hi[[0, 2]], 1e-3)  # ordinary boxes still hash
