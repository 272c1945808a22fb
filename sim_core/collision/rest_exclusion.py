"""Same-body pairs closer than the self-contact rest distance, found once per model.

:class:`PairFilter` excludes pairs of one body whose distance in the rest configuration is below
``self_rest_distance`` (topological neighbours of a sheet). Rest positions never change, so the
verdict of every pair is fixed: :class:`RestExclusion` searches the rest configuration once
(k-d tree broad phase with radius ``self_rest_distance``, then the exact distance of
:mod:`sim_core.collision.distances`, the same function and inputs as the per-search test) and keeps
the close pairs as sorted integer keys; a candidate search then looks its pairs up
(``searchsorted``) instead of recomputing their rest distances.

Completeness: a pair at distance ``d < r`` has, on every axis, a gap between its bounding boxes of
at most ``d``, so its boxes inflated by ``r`` overlap and the box search returns it.

A body made of translated copies apart from each other (a stacked scene's, :mod:`sim_core.batch.stacked`) is
searched on its first copy and the candidate pairs moved into every copy, each pair's distance measured in its own
copy (:func:`_translated_copies`): the k-d tree of one copy instead of all, the same keys.
"""

from __future__ import annotations

import numpy as np

from sim_core.collision.candidates import PairFilter, box_pairs_kdtree
from sim_core.collision.distances import edge_edge_distance, point_triangle_distance
from sim_core.unique import sorted_unique


def _keys(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """int64 keys ``a << 32 | b`` of pairs of non-negative indices below 2**31, shape ``(p,)``."""
    return (np.asarray(a, dtype=np.int64) << 32) | np.asarray(b, dtype=np.int64)


def _batches(pairs: np.ndarray, size: int):
    """Consecutive row slices of ``pairs`` with at most ``size`` rows each."""
    for start in range(0, len(pairs), size):
        yield pairs[start:start + size]


def _members(sorted_keys: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Mask ``(p,)`` of ``keys`` found in ``sorted_keys``."""
    if not len(sorted_keys) or not len(keys):
        return np.zeros(len(keys), dtype=bool)
    pos = np.minimum(np.searchsorted(sorted_keys, keys), len(sorted_keys) - 1)
    return sorted_keys[pos] == keys


def _in_every_copy(pairs: np.ndarray, sizes: tuple[int, int], copies: int) -> np.ndarray:
    """The first copy's local pairs ``(p, 2)`` (positions in its two element lists of ``sizes``) repeated in every
    one of ``copies`` copies (copy ``c``'s positions moved by ``c * sizes``), int64 ``(copies p, 2)``, copy by copy."""
    if copies == 1:
        return pairs
    step = np.arange(copies, dtype=np.int64)[:, None, None] * np.array(sizes, dtype=np.int64)
    return (pairs[None] + step).reshape(-1, 2)


def _translated_copies(x: np.ndarray, vertices: np.ndarray, triangles: np.ndarray, edges: np.ndarray,
                       r: float) -> tuple[int, float]:
    """``(copies, reach)`` of one body's colliding vertices ``(v,)``, triangles ``(t, 3)`` and edges ``(e, 2)``
    (global vertex indices at rest positions ``x`` ``(n, 3)``, m): ``copies >= 2`` when they are that many equal
    chunks, chunk ``c`` being chunk 0 with every vertex index moved by one shift larger than chunk 0's span (a
    stacked scene's copies of a body, :mod:`sim_core.batch.stacked`; triangle counts tried shortest first, at
    most four), the chunks' positions chunk 0's moved by one offset up to ``delta`` (m, largest coordinate
    difference) with ``delta <= r / 64``, and no two chunks' boxes within ``r + 4 delta`` (no pair across
    copies); else ``(1, r)``. ``reach = r + 4 delta`` is the radius of the broad phase on chunk 0 whose
    candidates, moved into every chunk, hold every pair of that chunk closer than ``r`` (a pair's distance in chunk
    0 differs from its distance in chunk ``c`` by at most ``2 sqrt(3) delta``); each pair's distance is then
    measured in its own chunk, so the keys are those of a search of the whole body."""
    whole = (1, r)
    if len(triangles) < 2:
        return whole
    moved = triangles - triangles[:1]
    span = np.maximum.accumulate(triangles.max(axis=1)) - np.minimum.accumulate(triangles.min(axis=1))
    lengths = np.flatnonzero(np.all(moved == moved[:, :1], axis=1))
    lengths = lengths[(lengths > 0) & (moved[lengths, 0] > span[lengths - 1])]
    for T in lengths[:4]:  # the chunk's triangle count: shortest first
        T = int(T)
        copies = len(triangles) // T
        if copies < 2 or len(triangles) % T or len(vertices) % copies or len(edges) % copies or not len(vertices):
            continue
        V, E = len(vertices) // copies, len(edges) // copies
        chunked = vertices.reshape(copies, V)
        shift = chunked[:, :1] - chunked[:1, :1]  # (copies, 1) vertex index shifts
        if not (np.array_equal(chunked - shift, np.broadcast_to(chunked[:1], chunked.shape))
                and np.array_equal(triangles.reshape(copies, T, 3) - shift[:, :, None],
                                   np.broadcast_to(triangles[:T], (copies, T, 3)))
                and np.array_equal(edges.reshape(copies, E, 2) - shift[:, :, None],
                                   np.broadcast_to(edges[:E], (copies, E, 2)))):
            continue
        # the positions: chunk 0's moved by each chunk's offset, up to delta; the chunks' boxes
        used = np.concatenate([chunked, triangles.reshape(copies, -1), edges.reshape(copies, -1)], axis=1)
        p = x[used]  # (copies, u, 3)
        offset = p[:, :1] - p[:1, :1]
        delta = float(np.max(np.abs(p - offset - p[:1]))) if p.size else 0.0
        if not delta <= r / 64:
            continue
        reach = r + 4.0 * delta
        if len(box_pairs_kdtree(p.min(axis=1), p.max(axis=1), None, None, reach)):
            continue
        return copies, reach
    return whole


class RestExclusion:
    """The pairs of one body closer than ``pair_filter.self_rest_distance`` at rest.

    Args:
        pair_filter: the filter (``vertex_body``, ``body_pair_allowed``, ``x_rest``,
            ``self_rest_distance``); with ``self_rest_distance == 0`` nothing is excluded.
        vertices: global indices of the colliding vertices, shape ``(v,)``.
        triangles: global vertex indices of the colliding triangles, shape ``(t, 3)``; the
            vertex-triangle keys use rows of this array, as the candidate lists do.
        edges: global vertex indices of the colliding edges, shape ``(e, 2)``; edge-edge keys use
            rows of this array, ``i < j``.

        chunk: candidate pairs measured per batch (> 0). The exact distances make a few dozen
            temporaries per pair; batches bound them (a 100k-DoF sheet has ~9.3 million candidate
            vertex-triangle pairs at rest: 7.9 GB peak in one batch, ~0.3 GB in batches of 2**18).
            The keys do not depend on it.

    Only bodies whose self-contact is allowed are searched (pairs of other bodies never reach the
    rest-distance test).
    """

    def __init__(self, pair_filter: PairFilter, vertices: np.ndarray, triangles: np.ndarray,
                 edges: np.ndarray, chunk: int = 1 << 18) -> None:
        chunk = int(chunk)
        if chunk < 1:
            raise ValueError(f"RestExclusion: chunk must be >= 1, got {chunk!r}")
        self.pair_filter = pair_filter
        self.vertices = np.asarray(vertices, dtype=np.int64).reshape(-1)
        self.triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        self.edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
        self.vertex_triangle_keys = np.zeros(0, dtype=np.int64)
        self.edge_edge_keys = np.zeros(0, dtype=np.int64)
        r = float(pair_filter.self_rest_distance)
        if r <= 0:
            return
        xr = np.asarray(pair_filter.x_rest, dtype=float)
        body = np.asarray(pair_filter.vertex_body)
        allowed = (np.ones((int(body.max()) + 1,) * 2, dtype=bool) if pair_filter.body_pair_allowed is None
                   else np.asarray(pair_filter.body_pair_allowed, dtype=bool))
        vt_keys, ee_keys = [], []
        for k in sorted_unique(body):
            if not allowed[k, k]:
                continue
            vs = self.vertices[body[self.vertices] == k]
            ts = np.flatnonzero(body[self.triangles[:, 0]] == k)
            es = np.flatnonzero(body[self.edges[:, 0]] == k)
            copies, reach = _translated_copies(xr, vs, self.triangles[ts], self.edges[es], r)
            V, T, E = len(vs) // copies, len(ts) // copies, len(es) // copies  # one copy's
            if len(vs) and len(ts):
                tri_x = xr[self.triangles[ts[:T]]]
                first = box_pairs_kdtree(xr[vs[:V]], xr[vs[:V]], tri_x.min(axis=1), tri_x.max(axis=1), reach)
                for pairs in _batches(_in_every_copy(first, (V, T), copies), chunk):
                    v, t = vs[pairs[:, 0]], ts[pairs[:, 1]]
                    tri = self.triangles[t]
                    d = point_triangle_distance(xr[v], xr[tri[:, 0]], xr[tri[:, 1]], xr[tri[:, 2]])
                    vt_keys.append(_keys(v[d < r], t[d < r]))
            if E > 1:
                ex = xr[self.edges[es[:E]]]
                first = box_pairs_kdtree(ex.min(axis=1), ex.max(axis=1), None, None, reach)
                for pairs in _batches(_in_every_copy(first, (E, E), copies), chunk):
                    i, j = es[pairs[:, 0]], es[pairs[:, 1]]
                    i, j = np.minimum(i, j), np.maximum(i, j)
                    ea, eb = self.edges[i], self.edges[j]
                    d = edge_edge_distance(xr[ea[:, 0]], xr[ea[:, 1]], xr[eb[:, 0]], xr[eb[:, 1]])
                    ee_keys.append(_keys(i[d < r], j[d < r]))
        if vt_keys:
            self.vertex_triangle_keys = sorted_unique(np.concatenate(vt_keys))
        if ee_keys:
            self.edge_edge_keys = sorted_unique(np.concatenate(ee_keys))

    def matches(self, vertices: np.ndarray, triangles: np.ndarray, edges: np.ndarray) -> bool:
        """Whether this table was built for these vertex, triangle and edge arrays (same values)."""
        return (np.array_equal(self.vertices, vertices) and np.array_equal(self.triangles, triangles)
                and np.array_equal(self.edges, edges))

    def vertex_triangle_close(self, v: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Mask ``(p,)``: pairs of global vertex ``v`` and triangle row ``t`` closer than the rest distance."""
        return _members(self.vertex_triangle_keys, _keys(v, t))

    def edge_edge_close(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Mask ``(p,)``: pairs of edge rows ``i < j`` closer than the rest distance."""
        return _members(self.edge_edge_keys, _keys(i, j))
