"""The candidate lists' vertices (sim_core/energies/contact/pair_lists.py): the pairs' global vertices, and the
pair batch's layout (every vertex-triangle candidate and some edge-edge ones as rows of the compaction of every
candidate's vertices); the potentials built on them equal those that compute their own vertices."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.energies.contact.pair_lists import CandidateVertices
from sim_core.energies.contact.reference import (EdgeEdgeContact, VertexTriangleContact, edge_edge_vertices,
                                                 vertex_triangle_vertices)
from sim_core.errors import ConfigError


def _lists():
    rng = np.random.default_rng(3)
    triangles = rng.integers(0, 400, size=(60, 3))
    edges = rng.integers(0, 400, size=(90, 2))
    vt = np.stack([rng.integers(0, 400, 150), rng.integers(0, 60, 150)], axis=1)
    ee = np.stack([rng.integers(0, 90, 200), rng.integers(0, 90, 200)], axis=1)
    return vt, ee, triangles, edges


def test_candidate_vertices_are_the_pairs_vertices_and_the_batch_layout_points_at_them():
    vt, ee, triangles, edges = _lists()
    lists = CandidateVertices(vt, ee, triangles, edges)
    assert lists.of(vt, ee) and not lists.of(vt.copy(), ee)
    np.testing.assert_array_equal(lists.vt_vertices, vertex_triangle_vertices(vt, triangles))
    np.testing.assert_array_equal(lists.ee_vertices, edge_edge_vertices(ee, edges))
    rows = np.array([0, 3, 4, 17, 199])
    layouts = [lists.batch_layout(rows) for _ in range(2)]
    sized = CandidateVertices(vt, ee, triangles, edges, vertex_count=400).batch_layout(rows)  # the vertex count known
    for got, want in zip(sized[:4], layouts[0][:4]):  # own, local, rows, ee_rows
        assert got.dtype == want.dtype
        np.testing.assert_array_equal(got, want)
    assert layouts[1].local is layouts[0].local and layouts[1].device is lists.device  # made once, kept
    # the layout rows given (the kept rows' launch made them on CUDA): taken as they are, checked for their length
    given = layouts[0].rows.copy()
    assert lists.batch_layout(rows, given).rows is given
    with pytest.raises(ValueError, match="batch_layout: rows"):
        lists.batch_layout(rows, given[:-1])
    with pytest.raises(ValueError, match="batch_layout: rows"):
        lists.batch_layout(rows, given.astype(np.int64))
    for own, local, batch_rows, ee_rows, _ in layouts:
        assert local.dtype == np.int32 and local.shape == (150 + 200, 4) and batch_rows.dtype == np.int32
        np.testing.assert_array_equal(ee_rows, rows)
        np.testing.assert_array_equal(batch_rows, np.concatenate([np.arange(150), 150 + rows]))
        np.testing.assert_array_equal(own, np.unique(np.concatenate([lists.vt_vertices, lists.ee_vertices])))
        np.testing.assert_array_equal(own[local[batch_rows]],
                                      np.concatenate([lists.vt_vertices, lists.ee_vertices[rows]]))
    vt32, ee32 = lists.int32_vertices()
    assert vt32.dtype == ee32.dtype == np.int32 and lists.int32_vertices()[0] is vt32
    np.testing.assert_array_equal(vt32, lists.vt_vertices)
    np.testing.assert_array_equal(ee32, lists.ee_vertices)


def test_list_keys_and_the_step_sides_through_them_equal_the_lookups():
    """``CandidateVertices.keys``: the packed keys of sorted unique lists (None for a list that is not: its pairs are
    then looked up one by one), made once; ``step_sides`` through them gives the sides, bit for bit, of
    looking every pair above its face up in the memory."""
    from sim_core.collision.memory import ContactMemory
    from sim_core.collision.step_sides import step_sides

    vt, ee, triangles, edges = _lists()
    vt, ee = np.unique(vt, axis=0), np.unique(ee, axis=0)
    lists = CandidateVertices(vt, ee, triangles, edges)
    keys = lists.keys()
    assert lists.keys() is keys
    for pairs, k in zip((vt, ee), keys):
        np.testing.assert_array_equal(k, (pairs[:, 0] << 32) | pairs[:, 1])
    assert CandidateVertices(vt[::-1], ee, triangles, edges).keys()[0] is None
    # keys given (a search's sort made them): taken as they are when increasing; a list given none makes its own
    given = CandidateVertices(vt, ee, triangles, edges, keys=(keys[0].copy(), None)).keys()
    np.testing.assert_array_equal(given[0], keys[0])
    np.testing.assert_array_equal(given[1], keys[1])
    assert CandidateVertices(vt[::-1], ee, triangles, edges, keys=(keys[0][::-1], keys[1])).keys()[0] is None
    rng = np.random.default_rng(4)
    for pairs, k in zip((vt, ee), keys):
        memory = ContactMemory()
        remembered = np.concatenate([pairs[rng.choice(len(pairs), 30, replace=False)], [[399, 59], [1000, 2]]])
        memory.update(remembered, rng.choice([-1.0, 1.0], size=len(remembered)))
        above = rng.random(len(pairs)) < 0.5
        geometric = rng.choice([-1.0, 1.0], size=len(pairs))
        want = step_sides(above, pairs, geometric, memory)
        got = step_sides(above, pairs, geometric, memory, k)
        assert got.dtype == want.dtype and got.tobytes() == want.tobytes()
        assert np.any(got[above] != geometric[above])  # remembered sides taken
        for keys_given in (None, k):  # written into a given array (part of a larger one, holding other values before)
            block = np.full(len(pairs) + 3, 5.0)
            written = step_sides(above, pairs, geometric, memory, keys_given, block[2:-1])
            assert written.base is block and written.tobytes() == want.tobytes() and block[0] == block[-1] == 5.0


def test_potentials_given_their_vertices_equal_those_that_compute_them():
    vt, ee, triangles, edges = _lists()
    lists = CandidateVertices(vt, ee, triangles, edges)
    rng = np.random.default_rng(4)
    x = rng.normal(scale=0.01, size=(400, 3))
    for cls, pairs, elements, vertices in ((VertexTriangleContact, vt, triangles, lists.vt_vertices),
                                           (EdgeEdgeContact, ee, edges, lists.ee_vertices)):
        sides = rng.choice([-1.0, 0.0, 1.0], size=len(pairs))
        given = cls(pairs, elements, sides, 1e3, 0.01, vertices=vertices)
        own = cls(pairs, elements, sides, 1e3, 0.01)
        assert given.vertices is vertices
        np.testing.assert_array_equal(given.distance(x), own.distance(x))
        with pytest.raises(ConfigError, match=rf"{len(pairs)} pairs but vertices of shape \(3, 4\)"):
            cls(pairs, elements, sides, 1e3, 0.01, vertices=vertices[:3])


def test_sheet_vertices_off_solids_drops_the_pairs_of_a_sheet_vertex_and_a_solid_triangle_with_their_keys():
    """The filter's rows are the pairs whose vertex is not a sheet's or whose triangle is not a solid's, in order;
    the keys follow the pairs (None stays None)."""
    from sim_core.energies.contact.pair_lists import sheet_vertices_off_solids

    vt, _, triangles, _ = _lists()
    vt = np.unique(vt, axis=0)
    rng = np.random.default_rng(6)
    sheet_vertex, solid_triangle = rng.random(400) < 0.5, rng.random(60) < 0.5
    want = np.array([pair for pair in vt if not (sheet_vertex[pair[0]] and solid_triangle[pair[1]])])
    assert 0 < len(want) < len(vt)
    keys = (vt[:, 0] << 32) | vt[:, 1]
    got, got_keys = sheet_vertices_off_solids(vt, keys, sheet_vertex, solid_triangle)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(got_keys, (want[:, 0] << 32) | want[:, 1])
    assert sheet_vertices_off_solids(vt, None, sheet_vertex, solid_triangle)[1] is None
