"""Narrow phase: closest points against dense sampling, regions, distance derivatives vs FD."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.collision.distances import (
    EdgeEdgeRegion,
    PointTriangleRegion,
    edge_edge_closest_points,
    edge_edge_contact_distance,
    edge_edge_distance,
    point_triangle_closest_point,
    point_triangle_contact_distance,
    point_triangle_distance,
)
from tests.support.fd import relative_error

TRI = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.01, 0.0]])


def _sampled_triangle_distance(p, a, b, c, n=120):
    u, v = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1))
    m = u + v <= 1
    q = a + u[m, None] * (b - a) + v[m, None] * (c - a)
    return np.min(np.linalg.norm(q - p, axis=1))


def _sampled_segment_distance(a0, a1, b0, b1, n=400):
    s = np.linspace(0, 1, n + 1)
    pa = a0 + s[:, None] * (a1 - a0)
    pb = b0 + s[:, None] * (b1 - b0)
    return np.min(np.linalg.norm(pa[:, None] - pb[None], axis=2))


def test_point_triangle_distance_matches_dense_sampling():
    rng = np.random.default_rng(1)
    k = 60
    a, b, c = rng.normal(size=(3, k, 3))
    p = rng.normal(size=(k, 3)) * 1.5
    d = point_triangle_distance(p, a, b, c)
    bary, _ = point_triangle_closest_point(p, a, b, c)
    assert np.all(bary >= -1e-12) and np.allclose(bary.sum(axis=1), 1.0)
    for i in range(k):
        ds = _sampled_triangle_distance(p[i], a[i], b[i], c[i])
        assert d[i] <= ds + 1e-12
        assert ds - d[i] < 0.03 * np.linalg.norm(b[i] - a[i]) + 0.03 * np.linalg.norm(c[i] - a[i])


@pytest.mark.parametrize(
    "p, region",
    [
        ([0.002, 0.003, 0.001], PointTriangleRegion.FACE),
        ([0.005, -0.002, 0.001], PointTriangleRegion.EDGE_AB),
        ([0.007, 0.007, -0.001], PointTriangleRegion.EDGE_BC),
        ([-0.002, 0.005, 0.001], PointTriangleRegion.EDGE_CA),
        ([-0.001, -0.001, 0.001], PointTriangleRegion.VERTEX_A),
        ([0.012, -0.001, 0.001], PointTriangleRegion.VERTEX_B),
        ([-0.001, 0.012, 0.001], PointTriangleRegion.VERTEX_C),
    ],
)
def test_point_triangle_regions(p, region):
    _, r = point_triangle_closest_point(np.array([p]), *TRI[:, None, :])
    assert r[0] == region


def test_edge_edge_distance_matches_sampling_including_parallel():
    rng = np.random.default_rng(2)
    k = 40
    a0, a1, b0, b1 = rng.normal(size=(4, k, 3))
    # a few exactly parallel and overlapping pairs
    perp = np.cross(a1[:5] - a0[:5], rng.normal(size=(5, 3)))
    b0[:5] = a0[:5] + 0.3 * perp / np.linalg.norm(perp, axis=1, keepdims=True)
    b1[:5] = b0[:5] + 0.7 * (a1[:5] - a0[:5])
    d = edge_edge_distance(a0, a1, b0, b1)
    s, t, _ = edge_edge_closest_points(a0, a1, b0, b1)
    assert np.all(np.isfinite(s)) and np.all((s >= 0) & (s <= 1) & (t >= 0) & (t <= 1))
    for i in range(k):
        ds = _sampled_segment_distance(a0[i], a1[i], b0[i], b1[i])
        assert d[i] <= ds + 1e-12
        assert ds - d[i] < 0.02
    assert np.allclose(d[:5], 0.3)


def test_edge_edge_regions():
    z = np.array(
        [
            [[0, 0, 0], [1, 0, 0], [0.5, -1, 0.1], [0.5, 1, 0.1]],  # crossing: interior
            [[0, 0, 0], [1, 0, 0], [1.5, -1, 0.1], [1.5, 1, 0.1]],  # a1 against edge b
            [[0, 0, 0], [1, 0, 0], [1.5, 0, 0.1], [2.5, 0.2, 0.1]],  # a1 - b0 corners
            [[0, 0, 0], [1, 0, 0], [0.2, 0.1, 0.1], [0.9, 0.1, 0.1]],  # parallel: endpoint-edge
        ],
        dtype=float,
    )
    _, _, r = edge_edge_closest_points(z[:, 0], z[:, 1], z[:, 2], z[:, 3])
    assert r[0] == EdgeEdgeRegion.INTERIOR
    assert r[1] == EdgeEdgeRegion.A1_EDGE_B
    assert r[2] == EdgeEdgeRegion.A1_B0
    assert EdgeEdgeRegion.A0_EDGE_B <= r[3] <= EdgeEdgeRegion.B1_EDGE_A


def _fd_check(fn, z, side, h=1e-8):
    dd = fn(z, side, 2)
    k = z.shape[0]
    flat = z.reshape(k, 12)
    g_fd = np.zeros((k, 12))
    H_fd = np.zeros((k, 12, 12))
    for i in range(12):
        zp, zm = flat.copy(), flat.copy()
        zp[:, i] += h
        zm[:, i] -= h
        p = fn(zp.reshape(k, 4, 3), side, 1)
        m = fn(zm.reshape(k, 4, 3), side, 1)
        assert np.array_equal(p.region, dd.region) and np.array_equal(m.region, dd.region)
        g_fd[:, i] = (p.d - m.d) / (2 * h)
        H_fd[:, :, i] = (p.grad - m.grad) / (2 * h)
    assert relative_error(dd.grad, g_fd) < 1e-5
    assert relative_error(dd.hess, H_fd) < 1e-5
    assert np.allclose(dd.hess, np.swapaxes(dd.hess, 1, 2))
    return dd


@pytest.mark.parametrize("region", list(PointTriangleRegion))
def test_point_triangle_contact_distance_derivatives(region):
    rng = np.random.default_rng(int(region))
    targets = {
        PointTriangleRegion.FACE: [0.003, 0.003, 0.0002],
        PointTriangleRegion.EDGE_AB: [0.005, -0.0003, 0.0002],
        PointTriangleRegion.EDGE_BC: [0.0056, 0.0056, -0.0002],
        PointTriangleRegion.EDGE_CA: [-0.0003, 0.004, 0.0002],
        PointTriangleRegion.VERTEX_A: [-0.0002, -0.0002, 0.0002],
        PointTriangleRegion.VERTEX_B: [0.0103, -0.0002, -0.0002],
        PointTriangleRegion.VERTEX_C: [-0.0002, 0.0103, 0.0002],
    }
    z = np.concatenate([np.array(targets[region])[None], TRI])[None] + rng.normal(scale=3e-5, size=(1, 4, 3))
    for side in (1.0, -1.0):
        dd = _fd_check(point_triangle_contact_distance, z, np.array([side]))
        assert dd.region[0] == region
        if region == PointTriangleRegion.FACE:
            n = np.cross(z[0, 2] - z[0, 1], z[0, 3] - z[0, 1])
            assert dd.d[0] == pytest.approx(side * n @ (z[0, 0] - z[0, 1]) / np.linalg.norm(n))
        else:
            assert dd.d[0] == pytest.approx(point_triangle_distance(*z.transpose(1, 0, 2))[0])


@pytest.mark.parametrize(
    "z, expect",
    [
        ([[0, 0, 0], [0.01, 0, 0], [0.005, -0.005, 0.0002], [0.004, 0.005, 0.0003]], EdgeEdgeRegion.INTERIOR),
        ([[0, 0, 0], [0.01, 0, 0], [0.0102, -0.005, 0.0002], [0.0104, 0.005, 0.0001]], EdgeEdgeRegion.A1_EDGE_B),
        ([[0, 0, 0], [0.01, 0, 0], [0.0102, 0.0001, 0.0002], [0.02, 0.003, 0.001]], EdgeEdgeRegion.A1_B0),
        # nearly parallel (angle ~ 1e-4 rad): endpoint-edge distance
        ([[0, 0, 0], [0.01, 0, 0], [0.002, 0.0001, 0.0002], [0.012, 0.0001, 0.000201]], None),
    ],
)
def test_edge_edge_contact_distance_derivatives(z, expect):
    rng = np.random.default_rng(3)
    z = np.array(z, dtype=float)[None] + rng.normal(scale=1e-7, size=(1, 4, 3))
    for side in (1.0, -1.0):
        dd = _fd_check(edge_edge_contact_distance, z, np.array([side]))
        if expect is None:
            assert EdgeEdgeRegion.A0_EDGE_B <= dd.region[0] <= EdgeEdgeRegion.B1_EDGE_A
        else:
            assert dd.region[0] == expect
        if expect != EdgeEdgeRegion.INTERIOR:
            assert dd.d[0] == pytest.approx(edge_edge_distance(*z.transpose(1, 0, 2))[0], rel=1e-9)


def test_signed_distance_equals_unsigned_on_remembered_side():
    """On the remembered side the contact distance is the Euclidean one (C1 across regions)."""
    rng = np.random.default_rng(4)
    p = rng.uniform(-0.002, 0.012, size=(200, 3))
    p[:, 2] = np.abs(p[:, 2]) + 1e-5
    z = np.concatenate([p[:, None], np.broadcast_to(TRI, (200, 3, 3))], axis=1)
    dd = point_triangle_contact_distance(z, np.ones(200), 0)
    assert np.allclose(dd.d, point_triangle_distance(*z.transpose(1, 0, 2)), rtol=1e-10, atol=1e-15)
    dd_neg = point_triangle_contact_distance(z * np.array([1, 1, -1]), -np.ones(200), 0)
    assert np.allclose(dd_neg.d, dd.d, rtol=1e-10, atol=1e-15)


def test_point_triangle_region_equals_the_closest_point_region():
    # region-only classification (used by the contact distances) vs the full closest-point routine,
    # including points exactly on a vertex and on an edge (ties between the Voronoi tests)
    from sim_core.collision.distances import point_triangle_closest_point, point_triangle_region

    rng = np.random.default_rng(11)
    z = rng.normal(size=(4000, 4, 3))
    z[:200, 0] = z[:200, 1]
    z[200:400, 0] = 0.5 * (z[200:400, 2] + z[200:400, 3])
    _, region = point_triangle_closest_point(z[:, 0], z[:, 1], z[:, 2], z[:, 3])
    assert np.array_equal(point_triangle_region(z[:, 0], z[:, 1], z[:, 2], z[:, 3]), region)
    assert len(np.unique(region)) == 7


@pytest.mark.parametrize("seed", [21, 22])
def test_closed_form_distance_derivatives_equal_the_jets(seed):
    # the closed-form primitives (used by the contact distances) against the forward-mode jet
    # reference at random configurations: same values, derivatives to rounding
    from sim_core.collision import distance_derivatives as closed
    from sim_core.collision.distances import _point_line, _point_point, _signed_volume_distance

    rng = np.random.default_rng(seed)
    k = 300
    z = rng.normal(size=(k, 4, 3)) * rng.uniform(1e-4, 1.0, size=(k, 1, 1))
    side = np.where(rng.uniform(size=k) < 0.5, -1.0, 1.0)
    slots = np.array([rng.permutation(4)[:3] for _ in range(k)])
    cases = [
        (closed.signed_volume(z, side, True, 2), _signed_volume_distance(z, side, True, 2)),
        (closed.signed_volume(z, side, False, 2), _signed_volume_distance(z, side, False, 2)),
        (closed.point_line(z, *slots.T, 2), _point_line(z, *slots.T, 2)),
        (closed.point_point(z, slots[:, 0], slots[:, 1], 2), _point_point(z, slots[:, 0], slots[:, 1], 2)),
    ]
    for got, ref in cases:
        assert np.array_equal(got.val, ref.val)
        assert relative_error(got.grad, ref.grad) < 1e-12
        assert relative_error(got.hess, ref.hess) < 1e-12
    assert np.array_equal(closed.signed_volume(z, side, True, 1).grad, cases[0][0].grad)  # order 1: same gradient
