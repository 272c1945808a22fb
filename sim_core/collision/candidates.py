"""Candidate contact pairs: spatial-hash broad phase plus topological and body exclusions.

A candidate is a pair whose bounding boxes come within ``radius`` of each other (the query box is
inflated by ``radius`` on every side); the narrow phase decides which candidates are active. Always
excluded: a vertex and a triangle that contains it, two edges that share a vertex. Optionally
(:class:`PairFilter`): body pairs that may not collide, and for pairs inside one body (self-contact)
the pairs already closer than ``self_rest_distance`` in the rest configuration, so that
topological neighbours of a sheet (which touch at rest, or would when a crease folds through
180 degrees) never generate contact and a sheet at rest has zero contact energy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim_core.collision.distances import edge_edge_distance, point_triangle_distance
from scipy.spatial import cKDTree

from sim_core.collision.spatial_hash import SpatialHash, hash_cell_size
from sim_core.errors import ConfigError


@dataclass(frozen=True)
class PairFilter:
    """Which pairs may collide beyond the topological exclusions.

    Attributes:
        vertex_body: body id of every global vertex, shape ``(vertex_count,)`` int (a triangle or
            edge belongs to the body of its first vertex).
        body_pair_allowed: shape ``(body_count, body_count)`` bool, symmetric; ``[i, i]`` enables
            self-contact of body i. None allows every pair.
        x_rest: rest positions in m, shape ``(vertex_count, 3)``; needed when
            ``self_rest_distance > 0``.
        self_rest_distance: same-body pairs whose rest distance is below this (m) are excluded.
    """

    vertex_body: np.ndarray
    body_pair_allowed: np.ndarray | None = None
    x_rest: np.ndarray | None = None
    self_rest_distance: float = 0.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.self_rest_distance) and self.self_rest_distance >= 0):
            raise ConfigError(f"PairFilter: self_rest_distance must be >= 0 (m), got {self.self_rest_distance}")
        if self.self_rest_distance > 0 and self.x_rest is None:
            raise ConfigError("PairFilter: self_rest_distance > 0 needs x_rest")
        if self.body_pair_allowed is not None:
            allowed = np.asarray(self.body_pair_allowed)
            nb = int(np.max(self.vertex_body)) + 1 if len(self.vertex_body) else 0
            if allowed.ndim != 2 or allowed.shape[0] != allowed.shape[1] or allowed.shape[0] < nb:
                raise ConfigError(
                    f"PairFilter: body_pair_allowed must be square with >= {nb} bodies, got shape {allowed.shape}"
                )

    def keep(self, body_a: np.ndarray, body_b: np.ndarray, rest_distance, rest_close=None) -> np.ndarray:
        """Mask of pairs to keep given the bodies of both sides and a lazy rest-distance function
        (``rest_distance(idx)`` in m of the pairs ``idx``), or, when given, a lazy verdict
        ``rest_close(idx)`` (bool, whether the rest distance is below ``self_rest_distance``, e.g.
        looked up in a :class:`sim_core.collision.rest_exclusion.RestExclusion`)."""
        keep = np.ones(body_a.shape[0], dtype=bool)
        if self.body_pair_allowed is not None:
            keep &= np.asarray(self.body_pair_allowed, dtype=bool)[body_a, body_b]
        if self.self_rest_distance > 0:
            same = keep & (body_a == body_b)
            if np.any(same):
                idx = np.flatnonzero(same)
                close = rest_close(idx) if rest_close is not None else rest_distance(idx) < self.self_rest_distance
                keep[idx[close]] = False
        return keep


def auto_cell_size(box_min: np.ndarray, box_max: np.ndarray, radius: float) -> float:
    """Cell size of the order of the mean inflated box: mean largest box extent + 2 radius (m)."""
    ext = np.max(box_max - box_min, axis=1) if box_min.shape[0] else np.zeros(1)
    return float(max(np.mean(ext) + 2.0 * radius, 1e-9))


def box_pairs_kdtree(
    a_min: np.ndarray, a_max: np.ndarray, b_min: np.ndarray | None, b_max: np.ndarray | None, radius: float
) -> np.ndarray:
    """Pairs of axis-aligned boxes that come within ``radius`` of each other (k-d tree broad phase).

    Box centres go into SciPy's ``cKDTree`` (C); centre pairs closer than ``sqrt(3) radius`` plus
    the two largest half-diagonals are candidates (boxes inflated by ``radius`` per axis overlap up
    to ``sqrt(3) radius`` apart), then the exact inflated-AABB overlap test filters them.
    Same result as the spatial hash (:class:`SpatialHash`), with the search done in compiled code.

    Args:
        a_min, a_max: boxes of set A, shape ``(ka, 3)``.
        b_min, b_max: boxes of set B, shape ``(kb, 3)``; None pairs A with itself (each unordered pair
            once, ``i < j``).
        radius: inflation in m.

    Returns:
        int64 ``(p, 2)`` of ``[index in A, index in B]``.
    """
    same = b_min is None
    if same:
        b_min, b_max = a_min, a_max
    ca, cb = 0.5 * (a_min + a_max), 0.5 * (b_min + b_max)
    ra = _max_half_diagonal(a_min, a_max)
    rb = _max_half_diagonal(b_min, b_max)
    reach = np.sqrt(3.0) * radius + ra + rb
    ta = cKDTree(ca)
    if same:
        pairs = ta.query_pairs(reach, output_type="ndarray").astype(np.int64)
    else:
        pairs = ta.sparse_distance_matrix(cKDTree(cb), reach, output_type="ndarray")
        pairs = np.stack([pairs["i"], pairs["j"]], axis=1).astype(np.int64)
    if pairs.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    i, j = pairs[:, 0], pairs[:, 1]
    # the inflated-AABB test axis by axis on contiguous coordinate columns (a reduction over the
    # short axis of (p, 3) arrays costs more than the comparisons)
    overlap = np.ones(pairs.shape[0], dtype=bool)
    for a_lo, a_hi, b_lo, b_hi in zip(a_min.T.copy(), a_max.T.copy(), b_min.T.copy(), b_max.T.copy()):
        overlap &= (a_lo[i] - radius <= b_hi[j]) & (b_lo[j] <= a_hi[i] + radius)
    return pairs[overlap]


def box_pairs_hash(
    a_min: np.ndarray, a_max: np.ndarray, b_min: np.ndarray | None, b_max: np.ndarray | None, radius: float
) -> np.ndarray:
    """:func:`box_pairs_kdtree`'s pairs by a :class:`SpatialHash` over set B (cell size
    :func:`~sim_core.collision.spatial_hash.hash_cell_size`), queried with A's boxes inflated by
    ``radius``: the same exact inflated-box test (``a_min - radius <= b_max`` and
    ``b_min <= a_max + radius``, same operands); within one set, pairs ``i < j`` (tested from ``i``).

    Args and returns: as :func:`box_pairs_kdtree`, rows sorted by A then B index.

    Raises:
        ConfigError: a box coordinate is NaN or infinite.
    """
    same = b_min is None
    if same:
        b_min, b_max = a_min, a_max
    if not len(a_min) or not len(b_min):
        return np.zeros((0, 2), dtype=np.int64)
    q_min, q_max = a_min - radius, a_max + radius
    reach = max(float(np.max(np.abs(q_min))), float(np.max(np.abs(q_max))), float(np.max(np.abs(b_min))),
                float(np.max(np.abs(b_max))))
    if not np.isfinite(reach) or not (np.all(np.isfinite(b_max)) and np.all(np.isfinite(a_max))):
        raise ConfigError("spatial hash: bounding boxes contain NaN or infinite coordinates")
    pairs = SpatialHash(b_min, b_max, hash_cell_size(b_min, b_max, reach, radius)).query(q_min, q_max)
    if same:
        pairs = pairs[pairs[:, 0] < pairs[:, 1]]
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


def _max_half_diagonal(box_min: np.ndarray, box_max: np.ndarray) -> float:
    """Largest half-diagonal of boxes ``(k, 3)`` in m (0 for none); element-wise, no short-axis reduction."""
    if not len(box_min):
        return 0.0
    d = box_max - box_min
    return 0.5 * float(np.sqrt(np.max(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])))


def _grouped_box_pairs(
    a_min: np.ndarray, a_max: np.ndarray, a_body: np.ndarray,
    b_min: np.ndarray | None, b_max: np.ndarray | None, b_body: np.ndarray | None,
    radius: float, allowed: np.ndarray, box_pairs=box_pairs_kdtree,
) -> np.ndarray:
    """:func:`box_pairs_kdtree` (or ``box_pairs``) run per allowed pair of bodies; the same pairs, in another order.

    A k-d tree over all boxes at once searches with the largest boxes' reach (the long edges of one
    body widen the search of every other) and returns pairs of bodies that may not touch (a solid's
    own edges) only for them to be filtered out; per body pair, each search uses that pair's reach
    and disallowed pairs are never formed.

    Args:
        a_min, a_max, a_body: boxes of set A ``(ka, 3)`` and the body of each ``(ka,)``.
        b_min, b_max, b_body: the same for set B, or None to pair A with itself (``i < j``).
        radius: inflation in m.
        allowed: ``(bodies, bodies)`` bool, symmetric.
        box_pairs: the search of one body pair, :func:`box_pairs_kdtree` (default) or
            :func:`box_pairs_hash` (same signature and pairs).

    Returns:
        int64 ``(p, 2)`` of ``[index in A, index in B]`` (``i < j`` when B is None).
    """
    same = b_min is None
    if same:
        b_min, b_max, b_body = a_min, a_max, a_body
    groups_a = {int(k): np.flatnonzero(a_body == k) for k in np.unique(a_body)}
    groups_b = groups_a if same else {int(k): np.flatnonzero(b_body == k) for k in np.unique(b_body)}
    out = []
    for ka, ia in groups_a.items():
        for kb, ib in groups_b.items():
            if not allowed[ka, kb] or (same and kb < ka):
                continue
            if same and ka == kb:
                pairs = box_pairs(a_min[ia], a_max[ia], None, None, radius)
            else:
                pairs = box_pairs(a_min[ia], a_max[ia], b_min[ib], b_max[ib], radius)
            pairs = np.stack([ia[pairs[:, 0]], ib[pairs[:, 1]]], axis=1)
            if same:
                pairs = np.sort(pairs, axis=1)
            out.append(pairs)
    return np.concatenate(out) if out else np.zeros((0, 2), dtype=np.int64)


def grouped_box_pairs_hash(
    a_min: np.ndarray, a_max: np.ndarray, a_body: np.ndarray,
    b_min: np.ndarray | None, b_max: np.ndarray | None, b_body: np.ndarray | None,
    radius: float, allowed: np.ndarray,
) -> np.ndarray:
    """:func:`_grouped_box_pairs` with a spatial hash per pair of bodies (:func:`box_pairs_hash`):
    the NumPy path's default broad phase; same arguments, pairs and errors (NaN: ``ConfigError``)."""
    return _grouped_box_pairs(a_min, a_max, a_body, b_min, b_max, b_body, radius, allowed, box_pairs_hash)


def _check(x: np.ndarray, radius: float) -> None:
    if x.ndim != 2 or x.shape[1] != 3:
        raise ConfigError(f"candidate search: x must have shape (n, 3), got {x.shape}")
    if not (np.isfinite(radius) and radius >= 0):
        raise ConfigError(f"candidate search: radius must be finite and >= 0 (m), got {radius}")


def vertex_triangle_candidates(
    x: np.ndarray,
    vertices: np.ndarray,
    triangles: np.ndarray,
    radius: float,
    exclude: PairFilter | None = None,
    cell_size: float | None = None,
    grouped_search=None,
    rest_exclusion=None,
) -> np.ndarray:
    """Vertex-triangle pairs whose bounding boxes are within ``radius``.

    Args:
        x: global positions in m, shape ``(n, 3)``.
        vertices: global indices of the colliding vertices, shape ``(v,)``.
        triangles: global vertex indices of the colliding triangles, shape ``(t, 3)``.
        radius: query radius in m (contact eps plus a margin).
        exclude: optional body / self-contact filter.
        cell_size: hash cell size in m (default :func:`auto_cell_size`).
        grouped_search: the search of box pairs of allowed bodies used with a body filter, a
            function with the signature and result (as a set) of :func:`_grouped_box_pairs` (the
            default), e.g. :func:`sim_core.ti_kernels.broad_phase.grouped_box_pairs`.
        rest_exclusion: optional :class:`sim_core.collision.rest_exclusion.RestExclusion` of
            ``exclude`` built for these same index arrays: the rest-distance exclusion is looked
            up there instead of recomputed (same pairs).

    Returns:
        int64 array ``(p, 2)``: ``[global vertex index, row of triangles]``, sorted.

    Raises:
        ConfigError: bad shapes or radius.
    """
    x = np.asarray(x, dtype=float)
    _check(x, radius)
    vertices = np.asarray(vertices, dtype=np.int64).reshape(-1)
    triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if vertices.size == 0 or triangles.shape[0] == 0:
        return np.zeros((0, 2), dtype=np.int64)
    tri_x = x[triangles]
    t_min = np.minimum(np.minimum(tri_x[:, 0], tri_x[:, 1]), tri_x[:, 2])
    t_max = np.maximum(np.maximum(tri_x[:, 0], tri_x[:, 1]), tri_x[:, 2])
    p = x[vertices]
    if cell_size is not None:
        pairs = SpatialHash(t_min, t_max, cell_size).query(p - radius, p + radius)
    elif exclude is not None and exclude.body_pair_allowed is not None:
        body = np.asarray(exclude.vertex_body)
        pairs = (grouped_search or _grouped_box_pairs)(p, p, body[vertices], t_min, t_max, body[triangles[:, 0]],
                                                       radius, np.asarray(exclude.body_pair_allowed, dtype=bool))
    else:
        pairs = box_pairs_kdtree(p, p, t_min, t_max, radius)
    v = vertices[pairs[:, 0]]
    tri = triangles[pairs[:, 1]]
    keep = (tri[:, 0] != v) & (tri[:, 1] != v) & (tri[:, 2] != v)
    v, t_idx, tri = v[keep], pairs[keep, 1], tri[keep]
    if exclude is not None:
        body = np.asarray(exclude.vertex_body)

        def rest_distance(idx: np.ndarray) -> np.ndarray:
            xr = np.asarray(exclude.x_rest, dtype=float)
            return point_triangle_distance(xr[v[idx]], xr[tri[idx, 0]], xr[tri[idx, 1]], xr[tri[idx, 2]])

        rest_close = None if rest_exclusion is None else (
            lambda idx: rest_exclusion.vertex_triangle_close(v[idx], t_idx[idx]))
        keep = exclude.keep(body[v], body[tri[:, 0]], rest_distance, rest_close)
        v, t_idx = v[keep], t_idx[keep]
    out = np.stack([v, t_idx], axis=1)
    return out[np.lexsort((out[:, 1], out[:, 0]))]


def edge_edge_candidates(
    x: np.ndarray,
    edges: np.ndarray,
    radius: float,
    exclude: PairFilter | None = None,
    cell_size: float | None = None,
    grouped_search=None,
    rest_exclusion=None,
) -> np.ndarray:
    """Edge-edge pairs whose bounding boxes are within ``radius``.

    Args:
        x: global positions in m, shape ``(n, 3)``.
        edges: global vertex indices of the colliding edges, shape ``(e, 2)``.
        radius: query radius in m.
        exclude: optional body / self-contact filter.
        cell_size: hash cell size in m (default :func:`auto_cell_size`).
        grouped_search: the search of box pairs of allowed bodies used with a body filter, a
            function with the signature and result (as a set) of :func:`_grouped_box_pairs` (the
            default), e.g. :func:`sim_core.ti_kernels.broad_phase.grouped_box_pairs`.
        rest_exclusion: optional :class:`sim_core.collision.rest_exclusion.RestExclusion` of
            ``exclude`` built for these same index arrays: the rest-distance exclusion is looked
            up there instead of recomputed (same pairs).

    Returns:
        int64 array ``(p, 2)``: ``[row i of edges, row j of edges]`` with ``i < j``, sorted.

    Raises:
        ConfigError: bad shapes or radius.
    """
    x = np.asarray(x, dtype=float)
    _check(x, radius)
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    if edges.shape[0] < 2:
        return np.zeros((0, 2), dtype=np.int64)
    ex = x[edges]
    e_min, e_max = np.minimum(ex[:, 0], ex[:, 1]), np.maximum(ex[:, 0], ex[:, 1])
    if cell_size is not None:
        pairs = SpatialHash(e_min, e_max, cell_size).query(e_min - radius, e_max + radius)
        pairs = pairs[pairs[:, 0] < pairs[:, 1]]
    elif exclude is not None and exclude.body_pair_allowed is not None:
        body = np.asarray(exclude.vertex_body)[edges[:, 0]]
        pairs = (grouped_search or _grouped_box_pairs)(e_min, e_max, body, None, None, None, radius,
                                                       np.asarray(exclude.body_pair_allowed, dtype=bool))
    else:
        pairs = box_pairs_kdtree(e_min, e_max, None, None, radius)
    ea, eb = edges[pairs[:, 0]], edges[pairs[:, 1]]
    share = (ea[:, 0] == eb[:, 0]) | (ea[:, 0] == eb[:, 1]) | (ea[:, 1] == eb[:, 0]) | (ea[:, 1] == eb[:, 1])
    pairs, ea, eb = pairs[~share], ea[~share], eb[~share]
    if exclude is not None:
        body = np.asarray(exclude.vertex_body)

        def rest_distance(idx: np.ndarray) -> np.ndarray:
            xr = np.asarray(exclude.x_rest, dtype=float)
            return edge_edge_distance(xr[ea[idx, 0]], xr[ea[idx, 1]], xr[eb[idx, 0]], xr[eb[idx, 1]])

        rest_close = None if rest_exclusion is None else (
            lambda idx: rest_exclusion.edge_edge_close(pairs[idx, 0], pairs[idx, 1]))
        pairs = pairs[exclude.keep(body[ea[:, 0]], body[eb[:, 0]], rest_distance, rest_close)]
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
