"""Element-pair filters shared by the broad-phase kernels (:mod:`sim_core.ti_kernels.sweep_candidates`,
:mod:`sim_core.ti_kernels.hash_grid`): pairs of elements that share a vertex, and pairs in the
contact set's rest-distance exclusion (:class:`sim_core.collision.rest_exclusion.RestExclusion`,
sorted int64 keys ``first << 32 | second``), are not contact candidates. :class:`CandidateElements`
holds the element tables both candidate-list classes pass to their kernels.
"""

# No ``from __future__ import annotations`` here: Taichi reads ti.func annotations as objects.

import numpy as np

from sim_core.collision.candidates import PairFilter
from sim_core.collision.rest_exclusion import RestExclusion
from sim_core.errors import ConfigError
from sim_core.ti_backend import ti


def compile_candidate_kernels(make) -> None:
    """JIT-compile (or load from Taichi's offline cache) a candidate-list kernel on two small sheets:
    ``make(vertices, triangles, edges, pair_filter, rest_exclusion)`` returns the candidate-list
    object (a :class:`CandidateElements`), whose two lists are then computed once.

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """
    x = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.1], [1.0, 0.0, 0.1],
                  [0.0, 1.0, 0.1]])
    triangles = np.array([[0, 1, 2], [3, 4, 5]])
    edges = np.array([[0, 1], [1, 2], [2, 0], [3, 4], [4, 5], [5, 3]])
    pair_filter = PairFilter(vertex_body=np.array([0, 0, 0, 1, 1, 1]), body_pair_allowed=np.ones((2, 2), bool))
    candidates = make(np.arange(6), triangles, edges, pair_filter, RestExclusion(pair_filter, np.arange(6), triangles,
                                                                                 edges))
    candidates.vertex_triangle(x, 0.2)
    candidates.edge_edge(x, 0.2)


class CandidateElements:
    """The colliding elements of a contact set as the broad-phase kernels read them (int32 tables).

    Args:
        vertices: global indices of the colliding vertices, shape ``(v,)``.
        triangles: global vertex indices of the colliding triangles, shape ``(t, 3)``.
        edges: global vertex indices of the colliding edges, shape ``(e, 2)``.
        pair_filter: the body / self-contact filter; needs ``body_pair_allowed``.
        rest_exclusion: the filter's :class:`RestExclusion` built for these same arrays.

        vt_allowed: the body table of the vertex-triangle search, ``(bodies, bodies)`` bool, entry ``[vertex's body,
            triangle's body]`` (not symmetric: e.g. a sheet's vertices off a solid's triangles, the contact set's
            ``sheet_vertices_vs_solids`` off), or None for the filter's ``body_pair_allowed``; the edge-edge search
            takes the filter's.

    Raises:
        ConfigError: no body-pair table in the filter, a rest exclusion of another filter, or a ``vt_allowed`` of
            another shape (the message names the subclass).
    """

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, edges: np.ndarray, pair_filter: PairFilter,
                 rest_exclusion: RestExclusion, vt_allowed: np.ndarray | None = None) -> None:
        who = type(self).__name__
        if pair_filter.body_pair_allowed is None:
            raise ConfigError(f"{who}: the pair filter needs a body_pair_allowed table")
        if rest_exclusion.pair_filter is not pair_filter:
            raise ConfigError(f"{who}: the rest exclusion was built for another pair filter")
        body = np.asarray(pair_filter.vertex_body)
        self.vertices = np.asarray(vertices, dtype=np.int64).reshape(-1)
        self.triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        self.edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
        self.allowed = np.ascontiguousarray(pair_filter.body_pair_allowed, dtype=np.int32)
        if vt_allowed is not None and np.shape(vt_allowed) != self.allowed.shape:
            raise ConfigError(f"{who}: a vertex-triangle body table of shape {np.shape(vt_allowed)} for "
                              f"{self.allowed.shape[0]} bodies")
        self.vt_allowed = self.allowed if vt_allowed is None else np.ascontiguousarray(vt_allowed, dtype=np.int32)
        self._vertex_body = body[self.vertices].astype(np.int32)
        self._triangle_body = body[self.triangles[:, 0]].astype(np.int32)
        self._edge_body = body[self.edges[:, 0]].astype(np.int32)
        self._vertex_elements = np.ascontiguousarray(self.vertices[:, None], dtype=np.int32)
        self._vertex_keys = np.ascontiguousarray(self.vertices, dtype=np.int32)
        self._triangle_elements = np.ascontiguousarray(self.triangles, dtype=np.int32)
        self._edge_elements = np.ascontiguousarray(self.edges, dtype=np.int32)
        self._edge_keys = np.arange(self.edges.shape[0], dtype=np.int32)
        # keys are >= 0: a -1 in front keeps the array sorted and non-empty and matches no pair
        self._vt_rest = np.concatenate([[-1], rest_exclusion.vertex_triangle_keys]).astype(np.int64)
        self._ee_rest = np.concatenate([[-1], rest_exclusion.edge_edge_keys]).astype(np.int64)


@ti.func
def shares_vertex(a_vertices: ti.template(), i: ti.i32, b_vertices: ti.template(), j: ti.i32) -> ti.i32:
    """1 if element ``i`` of A and element ``j`` of B have a vertex in common."""
    shared = 0
    for u in range(a_vertices.shape[1]):
        for w in range(b_vertices.shape[1]):
            if a_vertices[i, u] == b_vertices[j, w]:
                shared = 1
    return shared


@ti.func
def is_rest_close(rest_keys: ti.template(), key: ti.i64) -> ti.i32:
    """1 if ``key`` is in the sorted, non-empty ``rest_keys``: a binary search without branches on
    the keys (the last key ``<= key`` found by halving the range with a select)."""
    base, size = 0, rest_keys.shape[0]
    while size > 1:
        half = size // 2
        base = ti.select(rest_keys[base + half] <= key, base + half, base)
        size -= half
    return ti.cast(rest_keys[base] == key, ti.i32)


@ti.func
def kept_pair(a_vertices: ti.template(), a_key: ti.template(), i: ti.i32, b_vertices: ti.template(), j: ti.i32,
              same: ti.i32, same_body: ti.i32, rest_keys: ti.template(), keep: ti.i32):
    """``[keep, first, second]`` (int32 3-vector) of the box pair ``(i, j)`` whose boxes overlap when
    ``keep`` is 1: the pair as the lists hold it (``[a_key[i], j]``, or ``[min, max]`` of a set with
    itself, ``same``) and whether it survives the shared-vertex test and, for two elements of one
    body (``same_body``), the rest-distance exclusion."""
    if keep != 0:
        keep = 1 - shares_vertex(a_vertices, i, b_vertices, j)
    first, second = a_key[i], j
    if same != 0:
        first, second = ti.min(i, j), ti.max(i, j)
    if keep != 0 and same_body != 0:
        keep = 1 - is_rest_close(rest_keys, (ti.cast(first, ti.i64) << 32) | ti.cast(second, ti.i64))
    return ti.Vector([keep, first, second], dt=ti.i32)
