"""The distance bounds leave out only pairs farther than eps, for every region and side."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.collision.distance_bounds import edge_edge_may_touch, point_triangle_may_touch
from sim_core.collision.distances import (
    edge_edge_contact_distance,
    edge_edge_side,
    point_triangle_contact_distance,
    point_triangle_side,
)

EPS = 4.0e-4
KINDS = {
    "vt": (point_triangle_may_touch, point_triangle_contact_distance, point_triangle_side),
    "ee": (edge_edge_may_touch, edge_edge_contact_distance, edge_edge_side),
}


def _configurations(rng, count, spread):
    """``count`` random pairs (k, 4, 3) of primitives of a few eps, ``spread`` eps apart at most."""
    base = rng.uniform(-spread * EPS, spread * EPS, size=(count, 1, 3))
    return base + rng.uniform(-3 * EPS, 3 * EPS, size=(count, 4, 3))


def _near_parallel_edges(rng, count):
    """Edge pairs with angles from 1e-7 to 1e-1 rad about eps apart (the plane bound's guard)."""
    a0 = rng.normal(size=(count, 3)) * EPS
    e = rng.normal(size=(count, 3))
    e /= np.linalg.norm(e, axis=1, keepdims=True)
    tilt = rng.normal(size=(count, 3))
    angle = 10.0 ** rng.uniform(-7, -1, size=(count, 1))
    f = e + angle * tilt
    offset = rng.normal(size=(count, 3)) * 1.5 * EPS
    length = 6.0 * EPS
    return np.stack([a0, a0 + length * e, a0 + offset, a0 + offset + length * f], axis=1)


def _distance(kind, z, side):
    _, distance, geometric = KINDS[kind]
    resolved = np.where(side == 0.0, geometric(z), side)
    return distance(z, resolved, 0).d


@pytest.mark.parametrize("kind", ["vt", "ee"])
@pytest.mark.parametrize("spread", [1.0, 5.0])
def test_left_out_pairs_are_farther_than_eps(kind, spread):
    rng = np.random.default_rng(5)
    z = _configurations(rng, 4000, spread)
    if kind == "ee":
        z = np.concatenate([z, _near_parallel_edges(rng, 2000)])
    for side in (np.zeros(len(z)), np.ones(len(z)), -np.ones(len(z))):
        d = _distance(kind, z, side)
        keep = KINDS[kind][0](z, side, EPS)
        assert np.all(keep[d < EPS])  # no active pair is left out
        assert np.any(~keep) and np.any(keep & (d < EPS))  # the bound does leave out, the set is not trivial


@pytest.mark.parametrize("kind", ["vt", "ee"])
def test_signed_pairs_are_kept_on_the_wrong_side_at_any_distance(kind):
    """A vertex far behind its face (d << 0) is kept; the same pair far in front is left out."""
    rng = np.random.default_rng(3)
    z = _configurations(rng, 200, 1.0) * 30.0  # far apart
    geometric = KINDS[kind][2](z)
    d_behind = _distance(kind, z, -geometric)
    keep_behind = KINDS[kind][0](z, -geometric, EPS)
    assert np.all(keep_behind[d_behind < EPS])
    in_front = KINDS[kind][0](z, geometric, EPS)
    assert np.mean(in_front) < 0.5
