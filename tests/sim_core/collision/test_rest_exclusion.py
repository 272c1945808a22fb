"""RestExclusion: the rest-distance exclusion looked up from a table built once equals the
per-search computation (same candidate lists), and the table holds exactly the close pairs."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.collision.candidates import PairFilter, edge_edge_candidates, vertex_triangle_candidates
from sim_core.collision.distances import edge_edge_distance, point_triangle_distance
from sim_core.collision.rest_exclusion import RestExclusion
from tests.sim_core.collision.test_candidates import _grid_sheet, _random_soup, _three_bodies


def _deformed(rng, x, scale):
    return x + rng.normal(scale=scale, size=x.shape)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_candidates_with_rest_exclusion_equal_the_per_search_distances(seed):
    rng = np.random.default_rng(seed)
    x_rest, tris, edges = _random_soup(rng)
    body, allowed = _three_bodies(x_rest)
    filt = PairFilter(vertex_body=body, body_pair_allowed=allowed, x_rest=x_rest, self_rest_distance=0.004)
    verts = np.unique(tris)
    rest = RestExclusion(filt, verts, tris, edges)
    assert rest.matches(verts, tris, edges)
    assert len(rest.vertex_triangle_keys) and len(rest.edge_edge_keys)
    for scale in (0.0, 0.002, 0.01):
        x = _deformed(rng, x_rest, scale)
        for radius in (0.002, 0.006):
            ref = vertex_triangle_candidates(x, verts, tris, radius, filt)
            got = vertex_triangle_candidates(x, verts, tris, radius, filt, rest_exclusion=rest)
            np.testing.assert_array_equal(got, ref)
            ref = edge_edge_candidates(x, edges, radius, filt)
            got = edge_edge_candidates(x, edges, radius, filt, rest_exclusion=rest)
            np.testing.assert_array_equal(got, ref)


def test_table_holds_exactly_the_same_body_pairs_closer_than_the_rest_distance():
    x_rest, tris, edges = _grid_sheet(9, 7, 0.002)
    r = 0.0045
    filt = PairFilter(vertex_body=np.zeros(len(x_rest), np.int64), body_pair_allowed=np.ones((1, 1), bool),
                      x_rest=x_rest, self_rest_distance=r)
    verts = np.arange(len(x_rest))
    rest = RestExclusion(filt, verts, tris, edges)
    # brute force over every vertex-triangle and edge-edge pair
    v, t = (a.ravel() for a in np.meshgrid(verts, np.arange(len(tris)), indexing="ij"))
    d = point_triangle_distance(x_rest[v], *(x_rest[tris[t, k]] for k in range(3)))
    want = np.sort((v[d < r] << 32) | t[d < r])
    np.testing.assert_array_equal(rest.vertex_triangle_keys, want)
    i, j = np.triu_indices(len(edges), 1)
    d = edge_edge_distance(x_rest[edges[i, 0]], x_rest[edges[i, 1]], x_rest[edges[j, 0]], x_rest[edges[j, 1]])
    want = np.sort((i[d < r] << 32) | j[d < r])
    np.testing.assert_array_equal(rest.edge_edge_keys, want)
    assert rest.vertex_triangle_close(v[:5], t[:5]).dtype == bool


def test_no_rest_distance_excludes_nothing_and_bodies_without_self_contact_are_skipped():
    x_rest, tris, edges = _grid_sheet(5, 5, 0.002)
    body = np.zeros(len(x_rest), np.int64)
    none = RestExclusion(PairFilter(vertex_body=body), np.unique(tris), tris, edges)
    assert not len(none.vertex_triangle_keys) and not len(none.edge_edge_keys)
    no_self = RestExclusion(PairFilter(vertex_body=body, body_pair_allowed=np.zeros((1, 1), bool), x_rest=x_rest,
                                       self_rest_distance=0.004), np.unique(tris), tris, edges)
    assert not len(no_self.vertex_triangle_keys) and not len(no_self.edge_edge_keys)
    assert not np.any(no_self.edge_edge_close(np.array([0, 1]), np.array([2, 3])))


def test_batched_distances_give_the_same_table():
    """The candidate pairs are measured in batches (bounded memory on large sheets); any batch size
    gives the same keys as one batch."""
    x_rest, tris, edges = _grid_sheet(9, 7, 0.002)
    filt = PairFilter(vertex_body=np.zeros(len(x_rest), np.int64), body_pair_allowed=np.ones((1, 1), bool),
                      x_rest=x_rest, self_rest_distance=0.0045)
    verts = np.arange(len(x_rest))
    whole = RestExclusion(filt, verts, tris, edges, chunk=1 << 30)
    for chunk in (1, 7, 100):
        part = RestExclusion(filt, verts, tris, edges, chunk=chunk)
        np.testing.assert_array_equal(part.vertex_triangle_keys, whole.vertex_triangle_keys)
        np.testing.assert_array_equal(part.edge_edge_keys, whole.edge_edge_keys)
    assert len(whole.vertex_triangle_keys) > 100 and len(whole.edge_edge_keys) > 100
    with pytest.raises(ValueError, match="chunk must be >= 1"):
        RestExclusion(filt, verts, tris, edges, chunk=0)


def _brute_force_keys(x, verts, tris, edges, r):
    """The vertex-triangle and edge-edge keys of every pair closer than ``r`` (one body), pair by pair."""
    v, t = (a.ravel() for a in np.meshgrid(verts, np.arange(len(tris)), indexing="ij"))
    d = point_triangle_distance(x[v], *(x[tris[t, k]] for k in range(3)))
    vt = np.sort((v[d < r] << 32) | t[d < r])
    i, j = np.triu_indices(len(edges), 1)
    d = edge_edge_distance(x[edges[i, 0]], x[edges[i, 1]], x[edges[j, 0]], x[edges[j, 1]])
    return vt, np.sort((i[d < r] << 32) | j[d < r])


@pytest.mark.parametrize("gap", [0.05, 0.001])
def test_translated_copies_of_a_body_give_the_keys_of_every_pair(gap):
    """A body made of five translated copies of a sheet (a stacked scene's): searched on its first copy and moved
    (the copies apart, at offsets that round the positions) or as a whole (the copies closer than the rest
    distance: pairs across copies); either way its keys are those of every pair closer than the rest distance."""
    from sim_core.collision.rest_exclusion import _translated_copies

    x0, tris0, edges0 = _grid_sheet(9, 7, 0.002)
    n, copies, r = len(x0), 5, 0.0045
    width = float(np.ptp(x0[:, 0]))
    x = np.concatenate([x0 + np.array([c * (width + gap), 0.1 / 3.0, 0.0]) for c in range(copies)])
    tris = np.concatenate([tris0 + c * n for c in range(copies)])
    edges = np.concatenate([edges0 + c * n for c in range(copies)])
    verts = np.arange(len(x))
    filt = PairFilter(vertex_body=np.zeros(len(x), np.int64), body_pair_allowed=np.ones((1, 1), bool), x_rest=x,
                      self_rest_distance=r)
    found, reach = _translated_copies(x, verts, tris, edges, r)
    assert found == (copies if gap > r else 1) and r <= reach <= r * (1 + 1e-9)
    rest = RestExclusion(filt, verts, tris, edges)
    vt, ee = _brute_force_keys(x, verts, tris, edges, r)
    np.testing.assert_array_equal(rest.vertex_triangle_keys, vt)
    np.testing.assert_array_equal(rest.edge_edge_keys, ee)
    across = (ee >> 32) // len(edges0) != (ee & 0xFFFFFFFF) // len(edges0)
    assert across.any() == (gap < r)
