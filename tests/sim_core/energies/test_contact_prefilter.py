"""The contact potentials measure only prefiltered pairs, with the results of measuring every pair."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.energies.contact.reference import EdgeEdgeContact, VertexTriangleContact

K, EPS = 1.0e4, 4.0e-4


def _potential(kind, rng, count):
    """``count`` random pairs of primitives of a few eps, near and far, with random sides."""
    base = rng.uniform(-3 * EPS, 3 * EPS, size=(count, 1, 3))
    x = (base + rng.uniform(-2 * EPS, 2 * EPS, size=(count, 4, 3))).reshape(-1, 3)
    sides = rng.choice([-1.0, 0.0, 1.0], size=count)
    groups = np.arange(4 * count).reshape(count, 4)
    if kind == "vt":
        pairs = np.stack([groups[:, 0], np.arange(count)], axis=1)
        return VertexTriangleContact(pairs, groups[:, 1:], sides, K, EPS), x
    pairs = np.stack([2 * np.arange(count), 2 * np.arange(count) + 1], axis=1)
    return EdgeEdgeContact(pairs, groups.reshape(-1, 2), sides, K, EPS), x


@pytest.mark.parametrize("kind", ["vt", "ee"])
def test_energy_active_pairs_frames_and_sides_equal_those_of_every_pair(kind):
    rng = np.random.default_rng(7)
    pot, x = _potential(kind, rng, 400)
    d = pot.distance(x)  # every pair, no prefilter
    active = np.flatnonzero(d < EPS)
    assert 0 < active.size < 400
    assert pot.energy(x) == float(0.5 * K * np.sum((d[active] - EPS) ** 2))  # bit for bit
    found, dd = pot._evaluate(x, 0)
    np.testing.assert_array_equal(found, active)
    np.testing.assert_array_equal(dd.d, d[active])
    np.testing.assert_array_equal(pot.active_mask(x), d < EPS)
    frames = pot.contact_frames(x)
    np.testing.assert_array_equal(frames.pair_index, active)
    np.testing.assert_array_equal(frames.lam, K * (EPS - d[active]))
    np.testing.assert_array_equal(pot.resolved_sides(x, d < EPS), pot.resolved_sides(x)[d < EPS])
    np.testing.assert_array_equal(pot.resolved_sides(x, active), pot.resolved_sides(x)[active])
