"""The bounding-box prefilter of the contact energy leaves out inactive pairs only."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.potentials.contact import EdgeEdgeContact, VertexTriangleContact

K, EPS = 1.0e4, 4.0e-4


def _cloud(rng, count):
    """``count`` random 4-vertex groups of size ~eps scattered over a few eps (near and far pairs)."""
    base = rng.uniform(-3 * EPS, 3 * EPS, size=(count, 1, 3))
    return (base + rng.uniform(-2 * EPS, 2 * EPS, size=(count, 4, 3))).reshape(-1, 3)


def _potential(kind, rng, count, sides):
    x = _cloud(rng, count)
    groups = np.arange(4 * count).reshape(count, 4)
    if kind == "vt":
        triangles = groups[:, 1:]
        pairs = np.stack([groups[:, 0], np.arange(count)], axis=1)
        return VertexTriangleContact(pairs, triangles, sides, K, EPS), x
    edges = groups.reshape(-1, 2)
    pairs = np.stack([2 * np.arange(count), 2 * np.arange(count) + 1], axis=1)
    return EdgeEdgeContact(pairs, edges, sides, K, EPS), x


@pytest.mark.parametrize("kind", ["vt", "ee"])
def test_prefilter_keeps_every_active_pair_and_the_exact_energy(kind):
    rng = np.random.default_rng(7)
    count = 400
    sides = rng.choice([-1.0, 0.0, 1.0], size=count)
    pot, x = _potential(kind, rng, count, sides)
    d = pot.distance(x)  # every pair, no prefilter
    active = np.flatnonzero(d < EPS)
    assert 0 < active.size < count
    maybe = pot._maybe_active(x[pot.vertices])
    assert np.all(maybe[active])  # no active pair is left out
    assert np.any(~maybe)  # and the filter does leave out some
    assert pot.energy(x) == float(0.5 * K * np.sum((d[active] - EPS) ** 2))  # bit for bit
    found, dd = pot._evaluate(x, 0)
    np.testing.assert_array_equal(found, active)
    np.testing.assert_array_equal(dd.d, d[active])


@pytest.mark.parametrize("kind", ["vt", "ee"])
def test_prefilter_keeps_signed_pairs_at_any_distance(kind):
    """A signed pair far from its face may still have d < 0 (penetrated): never left out."""
    rng = np.random.default_rng(3)
    pot, x = _potential(kind, rng, 50, np.ones(50))
    x = x * 100.0  # far apart
    assert np.all(pot._maybe_active(x[pot.vertices]))
    unsigned, _ = _potential(kind, np.random.default_rng(3), 50, np.zeros(50))
    assert not np.all(unsigned._maybe_active(x[unsigned.vertices]))


@pytest.mark.parametrize("kind", ["vt", "ee"])
def test_active_mask_frames_and_sides_use_the_same_active_pairs(kind):
    rng = np.random.default_rng(11)
    count = 300
    pot, x = _potential(kind, rng, count, rng.choice([-1.0, 0.0, 1.0], size=count))
    d = pot.distance(x)
    active = np.flatnonzero(d < EPS)
    np.testing.assert_array_equal(pot.active_mask(x), d < EPS)
    frames = pot.contact_frames(x)
    np.testing.assert_array_equal(frames.pair_index, active)
    np.testing.assert_array_equal(frames.lam, K * (EPS - d[active]))
    mask = d < EPS
    np.testing.assert_array_equal(pot.resolved_sides(x, mask), pot.resolved_sides(x)[mask])
    np.testing.assert_array_equal(pot.resolved_sides(x, active), pot.resolved_sides(x)[active])
