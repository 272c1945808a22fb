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
from sim_core.errors import ThinShellError
from sim_core.potentials.contact import EdgeEdgeContact, PlaneContact, VertexTriangleContact
from sim_core.potentials.friction import LaggedFriction
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
