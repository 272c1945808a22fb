"""Markers on the gel contact surface: rest grid, embedding in surface triangles, deformed positions.

A marker is painted on the gel's contact surface, so it moves with the surface: it is embedded once,
in the rest configuration, as (triangle, barycentric coordinates) of its closest surface triangle,
and its deformed position is the barycentric interpolation of that triangle's deformed vertices
(the standard embedding of points in a piecewise-linear surface). Marker order: ``i = iy * nx + ix``
(INTERFACES.md).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from sim_core.errors import ConfigError


class MarkerEmbedding(NamedTuple):
    """Markers embedded in a list of surface triangles.

    Attributes:
        triangle: index of each marker's triangle in the triangle list it was embedded in,
            shape ``(k,)``, int64.
        barycentric: barycentric coordinates of each marker in its triangle, shape ``(k, 3)``,
            rows sum to 1, all entries in ``[0, 1]``.
    """

    triangle: np.ndarray
    barycentric: np.ndarray


def marker_grid(marker_grid: tuple[int, int], pitch: float) -> np.ndarray:
    """Rest positions of a regular marker grid in the sensor frame.

    Marker ``i = iy * nx + ix`` sits at ``((ix - (nx - 1)/2) pitch, (iy - (ny - 1)/2) pitch, 0)``:
    the grid is centred on the sensor origin, on the contact surface ``z = 0``.

    Args:
        marker_grid: ``(nx, ny)`` markers along sensor x and y (each >= 1).
        pitch: marker spacing, m (> 0).

    Returns:
        shape ``(nx * ny, 3)``, m.

    Raises:
        ConfigError: ``marker_grid`` is not two positive integers or ``pitch`` is not a positive number.
    """
    try:
        nx, ny = (int(v) for v in marker_grid)
        ok = all(float(v) == int(v) for v in marker_grid)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"marker_grid must be two positive integers [nx, ny], got {marker_grid!r}") from err
    if not ok or nx < 1 or ny < 1:
        raise ConfigError(f"marker_grid must be two positive integers [nx, ny], got {marker_grid!r}")
    pitch = float(pitch)
    if not np.isfinite(pitch) or pitch <= 0.0:
        raise ConfigError(f"marker_pitch must be a positive length (m), got {pitch!r}")
    ix, iy = np.meshgrid(np.arange(nx), np.arange(ny))  # (ny, nx): row-major with y outer
    points = np.zeros((nx * ny, 3))
    points[:, 0] = (ix.reshape(-1) - 0.5 * (nx - 1)) * pitch
    points[:, 1] = (iy.reshape(-1) - 0.5 * (ny - 1)) * pitch
    return points


def _closest_point_segments(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Parameter ``s`` in [0, 1] and squared distance of ``p`` to segments ``a + s (b - a)``; broadcasting."""
    ab = b - a
    denom = np.maximum(np.einsum("...d,...d->...", ab, ab), 1e-300)
    s = np.clip(np.einsum("...d,...d->...", p - a, ab) / denom, 0.0, 1.0)
    diff = p - (a + s[..., None] * ab)
    return s, np.einsum("...d,...d->...", diff, diff)


def closest_triangle_points(points: np.ndarray, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Barycentric coordinates of the closest point of every triangle to every point.

    Inside the triangle's prism the closest point is the orthogonal projection onto its plane;
    otherwise it lies on one of the three edges (Ericson, Real-Time Collision Detection, 5.1.5).

    Args:
        points: shape ``(k, 3)``.
        corners: triangle corners, shape ``(t, 3, 3)``.

    Returns:
        ``(barycentric (k, t, 3), squared distance (k, t))``.
    """
    p = np.asarray(points, dtype=float)[:, None, :]  # (k, 1, 3)
    a, b, c = (corners[None, :, j, :] for j in range(3))  # (1, t, 3)
    # projection onto the plane, barycentrics by the normal-equation of [b - a, c - a]
    e1, e2, r = b - a, c - a, p - a
    d11 = np.einsum("...d,...d->...", e1, e1)
    d12 = np.einsum("...d,...d->...", e1, e2)
    d22 = np.einsum("...d,...d->...", e2, e2)
    r1 = np.einsum("...d,...d->...", r, e1)
    r2 = np.einsum("...d,...d->...", r, e2)
    det = np.maximum(d11 * d22 - d12 * d12, 1e-300)
    beta = (d22 * r1 - d12 * r2) / det
    gamma = (d11 * r2 - d12 * r1) / det
    alpha = 1.0 - beta - gamma
    bary = np.stack(np.broadcast_arrays(alpha, beta, gamma), axis=-1)
    proj = alpha[..., None] * a + beta[..., None] * b + gamma[..., None] * c
    dist2 = np.einsum("...d,...d->...", p - proj, p - proj)
    inside = np.all(bary >= 0.0, axis=-1)
    # closest points on the three edges, for points projecting outside
    s_ab, d_ab = _closest_point_segments(p, a, b)
    s_bc, d_bc = _closest_point_segments(p, b, c)
    s_ca, d_ca = _closest_point_segments(p, c, a)
    edge_d = np.stack([d_ab, d_bc, d_ca], axis=-1)
    edge = np.argmin(edge_d, axis=-1)
    zero = np.zeros_like(s_ab)
    bary_ab = np.stack([1.0 - s_ab, s_ab, zero], axis=-1)
    bary_bc = np.stack([zero, 1.0 - s_bc, s_bc], axis=-1)
    bary_ca = np.stack([s_ca, zero, 1.0 - s_ca], axis=-1)
    bary_edge = np.where((edge == 0)[..., None], bary_ab, np.where((edge == 1)[..., None], bary_bc, bary_ca))
    bary = np.where(inside[..., None], bary, bary_edge)
    dist2 = np.where(inside, dist2, np.min(edge_d, axis=-1))
    return bary, dist2


def embed_markers(
    rest_points_sensor: np.ndarray,
    surface_x_rest_sensor: np.ndarray,
    surface_triangles: np.ndarray,
    tol: float | None = None,
) -> MarkerEmbedding:
    """Embed markers in the closest triangle of the gel's contact surface at rest.

    Args:
        rest_points_sensor: marker rest positions, shape ``(k, 3)``, m, sensor frame.
        surface_x_rest_sensor: rest positions of the vertices the triangles index, shape ``(n, 3)``,
            m, same frame.
        surface_triangles: contact-surface triangles, shape ``(t, 3)``, indices into
            ``surface_x_rest_sensor``.
        tol: largest accepted marker-to-surface distance, m; default ``1e-6`` times the surface's
            bounding-box diagonal.

    Returns:
        the embedding; ``triangle`` indexes ``surface_triangles``.

    Raises:
        ConfigError: no triangles, bad triangle indices, or a marker farther than ``tol`` from the
            surface (the marker index and its distance are named).
    """
    points = np.asarray(rest_points_sensor, dtype=float).reshape(-1, 3)
    x_rest = np.asarray(surface_x_rest_sensor, dtype=float).reshape(-1, 3)
    tris = np.asarray(surface_triangles, dtype=np.int64).reshape(-1, 3)
    if tris.shape[0] == 0:
        raise ConfigError("embed_markers: the contact surface has no triangles")
    if tris.min() < 0 or tris.max() >= x_rest.shape[0]:
        raise ConfigError(
            f"embed_markers: surface triangle indices must lie in [0, {x_rest.shape[0]}), "
            f"got [{tris.min()}, {tris.max()}]"
        )
    corners = x_rest[tris]
    if tol is None:
        used = x_rest[np.unique(tris)]
        tol = 1e-6 * max(float(np.linalg.norm(used.max(axis=0) - used.min(axis=0))), 1e-12)
    bary, dist2 = closest_triangle_points(points, corners)
    best = np.argmin(dist2, axis=1)
    rows = np.arange(points.shape[0])
    dist = np.sqrt(dist2[rows, best])
    off = np.nonzero(dist > tol)[0]
    if off.size:
        i = int(off[0])
        raise ConfigError(
            f"embed_markers: marker {i} at {points[i].tolist()} lies {dist[i]:.3g} m off the contact "
            f"surface (tolerance {tol:.3g} m); {off.size} marker(s) off the surface"
        )
    b = np.clip(bary[rows, best], 0.0, 1.0)
    b /= b.sum(axis=1, keepdims=True)
    return MarkerEmbedding(triangle=best.astype(np.int64), barycentric=b)


def marker_positions(embedding: MarkerEmbedding, x: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Marker positions on the deformed surface by barycentric interpolation.

    ``p_i = sum_j barycentric[i, j] * x[triangles[triangle[i], j]]``.

    Args:
        embedding: from :func:`embed_markers`.
        x: vertex positions, shape ``(n, 3)``, m (typically the model's global array).
        triangles: the triangle list the embedding was made on, with indices into ``x`` (global
            indices when ``x`` is global), shape ``(t, 3)``.

    Returns:
        shape ``(k, 3)``, m, in the frame of ``x``.
    """
    corners = np.asarray(x, dtype=float)[np.asarray(triangles)[embedding.triangle]]  # (k, 3, 3)
    return np.einsum("kj,kjd->kd", embedding.barycentric, corners)


def marker_vertex_weights(embedding: MarkerEmbedding, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The linear map ``x -> marker positions`` as vertex indices and weights (for adjoints).

    ``d p_i / d x_v = w I_3`` for the (vertex ``v``, weight ``w``) pairs of marker ``i``.

    Returns:
        ``(vertices (k, 3) int64, weights (k, 3))``.
    """
    return np.asarray(triangles, dtype=np.int64)[embedding.triangle], embedding.barycentric.copy()
