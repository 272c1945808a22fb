"""Lagged-friction rows of the adjoint: reused from the step's contact set vs a fresh pair search.

``ContactSet.friction`` records where each row of its ``LaggedFriction`` comes from
(``row_sources``); :func:`sim_core.adjoint_friction.friction_rows` differentiates the frames of those
rows without a second broad phase. The result must equal the rows found by searching the pairs
again at ``x^n`` (the path for a ``LaggedFriction`` without sources), and a wrong source must be
refused. Scene: the press-and-slide card of ``test_adjoint`` (gel-sheet and sheet-table friction).
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from sim_core.adjoint import rollout
from sim_core.adjoint_friction import friction_rows
from sim_core.contact_set import ContactSet, FrictionRowSource
from sim_core.energies.contact.reference import EdgeEdgeContact, PlaneContact, VertexTriangleContact
from sim_core.energies.friction.reference import LaggedFriction
from sim_core.errors import ThinShellError
from tests.sim_core.test_adjoint import _controls, _make


@pytest.fixture(scope="module")
def steps():
    sim = _make()
    traj = rollout(sim, _controls())
    out = []
    for rec, state in zip(traj.records, traj.states[:-1]):
        fr = next((p for p in rec.terms if isinstance(p, LaggedFriction)), None)
        if fr is not None:
            out.append((state, fr))
    assert out
    return sim.model, out


def _without_sources(fr: LaggedFriction) -> LaggedFriction:
    bare = copy.copy(fr)
    del bare.row_sources
    return bare


def test_contact_set_records_the_source_of_every_friction_row(steps):
    _, records = steps
    kinds = set()
    for _, fr in records:
        sources = fr.row_sources
        assert all(isinstance(s, FrictionRowSource) for s in sources)
        assert sum(s.pair_index.size for s in sources) == fr.vertices.shape[0]
        kinds |= {cls for s in sources for cls in (VertexTriangleContact, EdgeEdgeContact, PlaneContact)
                  if isinstance(s.potential, cls) and s.pair_index.size}
    assert {VertexTriangleContact, PlaneContact} <= kinds


def test_reused_rows_equal_a_fresh_pair_search(steps):
    model, records = steps
    for state, fr in records:
        reused = friction_rows(model, ContactSet(model), state, fr)
        searched = friction_rows(model, ContactSet(model), state, _without_sources(fr))
        np.testing.assert_array_equal(reused.vertices, searched.vertices)
        assert reused.body_pairs == searched.body_pairs
        for name in ("dlam", "normal", "dnormal", "weights", "dweights"):
            a, b = getattr(reused, name), getattr(searched, name)
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * max(1.0, float(np.abs(b).max(initial=0.0))))


def test_a_wrong_row_source_is_refused(steps):
    model, records = steps
    state, fr = max(records, key=lambda r: r[1].vertices.shape[0])
    bad = copy.copy(fr)
    i = next(i for i, s in enumerate(fr.row_sources) if s.pair_index.size)
    s = fr.row_sources[i]
    others = np.setdiff1d(np.arange(len(s.potential.vertices)), s.pair_index)
    assert others.size
    wrong = s.pair_index.copy()
    wrong[0] = others[0]
    bad.row_sources = fr.row_sources[:i] + [s._replace(pair_index=wrong)] + fr.row_sources[i + 1:]
    with pytest.raises(ThinShellError, match="do not match ContactSet.friction"):
        friction_rows(model, ContactSet(model), state, bad)


@pytest.mark.parametrize("kind", ["vertex_triangle", "edge_edge"])
def test_frame_derivatives_match_finite_differences_in_every_region(kind):
    """The batched regions (face / interior, edges and corners) give d, n, w whose derivatives
    equal central differences, in every Voronoi region."""
    from sim_core.adjoint_friction import edge_edge_frames, vertex_triangle_frames
    from sim_core.collision.distances import edge_edge_closest_points, point_triangle_closest_point

    def regions(z):
        if kind == "vertex_triangle":
            return point_triangle_closest_point(z[:, 0], z[:, 1], z[:, 2], z[:, 3])[1]
        return edge_edge_closest_points(z[:, 0], z[:, 1], z[:, 2], z[:, 3])[2]

    def closest_weights(z):
        if kind == "vertex_triangle":
            bary = point_triangle_closest_point(z[:, 0], z[:, 1], z[:, 2], z[:, 3])[0]
            return np.concatenate([np.ones((len(z), 1)), -bary], axis=1)
        s, t, _ = edge_edge_closest_points(z[:, 0], z[:, 1], z[:, 2], z[:, 3])
        return np.stack([1 - s, s, -(1 - t), -t], axis=1)

    frames = vertex_triangle_frames if kind == "vertex_triangle" else edge_edge_frames
    rng = np.random.default_rng(3)
    z = rng.normal(size=(600, 4, 3))
    side = rng.choice([-1.0, 1.0], size=600)
    region = regions(z)
    assert set(np.unique(region)) == set(range(7 if kind == "vertex_triangle" else 9))
    d, dd, n, dn, w, dw = frames(z, side)
    # values: the closest points of the narrow phase, n d = the gap vector sum_j w_j z_j
    np.testing.assert_allclose(w, closest_weights(z), rtol=0, atol=1e-12)
    np.testing.assert_allclose(n * d[:, None], np.einsum("kj,kjd->kd", w, z), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, rtol=0, atol=1e-12)
    h = 1e-6
    stable = np.ones(len(z), bool)
    fd = [np.zeros_like(dd), np.zeros_like(dn), np.zeros_like(dw)]
    for j in range(12):
        e = np.zeros((4, 3))
        e[j // 3, j % 3] = h
        plus, minus = frames(z + e, side), frames(z - e, side)
        stable &= (regions(z + e) == region) & (regions(z - e) == region)
        fd[0][:, j] = (plus[0] - minus[0]) / (2 * h)
        fd[1][:, :, j] = (plus[2] - minus[2]) / (2 * h)
        fd[2][:, :, j] = (plus[4] - minus[4]) / (2 * h)
    assert stable.mean() > 0.95
    for got, ref in zip((dd, dn, dw), fd):
        err = np.abs(got - ref)[stable].reshape(stable.sum(), -1).max(axis=1)
        scale = np.maximum(1.0, np.abs(ref)[stable].reshape(stable.sum(), -1).max(axis=1))
        assert np.max(err / scale) < 1e-5
