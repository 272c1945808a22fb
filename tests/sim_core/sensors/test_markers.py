"""Marker grid order, embedding in the contact surface, interpolation on the deformed surface."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.errors import ConfigError
from sim_core.sensors.markers import (
    closest_triangle_points,
    embed_markers,
    marker_grid,
    marker_positions,
    marker_vertex_weights,
)


def _face(size: tuple[float, float], res: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """A z = 0 rectangle centred on the origin, vertex (ix, iy) at iy * nx + ix, two triangles per cell."""
    nx, ny = res
    xs = np.linspace(-size[0] / 2, size[0] / 2, nx)
    ys = np.linspace(-size[1] / 2, size[1] / 2, ny)
    X, Y = np.meshgrid(xs, ys)
    x = np.stack([X.ravel(), Y.ravel(), np.zeros(nx * ny)], axis=1)
    tris = []
    for iy in range(ny - 1):
        for ix in range(nx - 1):
            v00, v10, v01, v11 = iy * nx + ix, iy * nx + ix + 1, (iy + 1) * nx + ix, (iy + 1) * nx + ix + 1
            tris += [(v00, v10, v11), (v00, v11, v01)]
    return x, np.array(tris, dtype=np.int64)


def test_marker_grid_order_and_centring() -> None:
    p = marker_grid((3, 2), 0.002)
    expected = [
        [-0.002, -0.001, 0], [0, -0.001, 0], [0.002, -0.001, 0],
        [-0.002, 0.001, 0], [0, 0.001, 0], [0.002, 0.001, 0],
    ]
    np.testing.assert_allclose(p, expected, atol=1e-15)
    big = marker_grid((9, 7), 0.002)
    np.testing.assert_allclose(big.mean(axis=0), 0.0, atol=1e-15)
    i = 3 * 9 + 5  # iy = 3, ix = 5
    np.testing.assert_allclose(big[i], [(5 - 4) * 0.002, 0.0, 0.0], atol=1e-15)


def test_marker_grid_errors() -> None:
    with pytest.raises(ConfigError, match="marker_grid must be two positive integers"):
        marker_grid((0, 3), 0.002)
    with pytest.raises(ConfigError, match="marker_grid must be two positive integers"):
        marker_grid((2.5, 3), 0.002)
    with pytest.raises(ConfigError, match="marker_pitch must be a positive length"):
        marker_grid((3, 3), -0.002)


def test_embedding_reproduces_rest_positions_with_global_indices() -> None:
    x_face, tris = _face((0.0186, 0.0143), (10, 8))
    markers = marker_grid((9, 7), 0.002)
    emb = embed_markers(markers, x_face, tris)
    assert emb.triangle.shape == (63,) and emb.barycentric.shape == (63, 3)
    np.testing.assert_allclose(emb.barycentric.sum(axis=1), 1.0)
    assert np.all(emb.barycentric >= 0.0)
    # the gel lives at an offset in a global array of other bodies' vertices
    offset = 17
    x_global = np.vstack([np.random.default_rng(0).normal(size=(offset, 3)), x_face])
    np.testing.assert_allclose(marker_positions(emb, x_global, tris + offset), markers, atol=1e-15)
    verts, weights = marker_vertex_weights(emb, tris + offset)
    np.testing.assert_allclose(np.einsum("kj,kjd->kd", weights, x_global[verts]), markers, atol=1e-15)


def test_markers_follow_an_affine_deformation_exactly() -> None:
    x_face, tris = _face((0.0186, 0.0143), (7, 5))
    markers = marker_grid((9, 7), 0.002)
    emb = embed_markers(markers, x_face, tris)
    rng = np.random.default_rng(3)
    A = np.eye(3) + 0.2 * rng.normal(size=(3, 3))
    t = rng.normal(size=3) * 0.01
    moved = marker_positions(emb, x_face @ A.T + t, tris)
    np.testing.assert_allclose(moved, markers @ A.T + t, atol=1e-14)


def test_marker_off_the_surface_is_named() -> None:
    x_face, tris = _face((0.01, 0.01), (3, 3))
    markers = marker_grid((3, 3), 0.004)
    markers[4, 2] = -1e-4  # below the surface
    with pytest.raises(ConfigError, match="marker 4 .* off the contact"):
        embed_markers(markers, x_face, tris)
    with pytest.raises(ConfigError, match="marker 0 .* off the contact"):
        embed_markers(marker_grid((3, 3), 0.006), x_face, tris)  # grid wider than the face


def test_closest_point_outside_a_triangle_lies_on_its_edge() -> None:
    corners = np.array([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]])
    bary, d2 = closest_triangle_points(np.array([[0.5, -2.0, 0.0], [0.2, 0.2, 3.0], [2.0, 2.0, 0.0]]), corners)
    np.testing.assert_allclose(bary[:, 0], [[0.5, 0.5, 0.0], [0.6, 0.2, 0.2], [0.0, 0.5, 0.5]], atol=1e-14)
    np.testing.assert_allclose(d2[:, 0], [4.0, 9.0, 4.5], atol=1e-14)
