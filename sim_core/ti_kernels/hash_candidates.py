"""The contact set's candidate lists from the spatial-hash kernel, with the pair exclusions inside it.

:func:`sim_core.collision.candidates.vertex_triangle_candidates` and
:func:`~sim_core.collision.candidates.edge_edge_candidates` find box pairs and then drop, in NumPy,
the pairs that share a vertex and the same-body pairs closer than the self-contact rest distance
(looked up in a :class:`~sim_core.collision.rest_exclusion.RestExclusion`), and sort the rest.
:class:`HashCandidates` finds the box pairs with the spatial hash of
:mod:`sim_core.ti_kernels.hash_grid` (one launch per list; the kernel reads the positions and the elements' vertices and
forms the boxes itself), whose kernel applies both exclusions
before writing a pair (shared vertices by comparing the elements' vertex indices, the rest distance
by a binary search of the pair's key in the sorted keys of the rest exclusion) and applies the body
filter as the ``allowed`` matrix. The lists therefore equal the reference's; the twin of
:class:`sim_core.ti_kernels.sweep_candidates.SweepCandidates` (same interface and lists).
"""

from __future__ import annotations

import numpy as np

from sim_core.collision.candidates import PairFilter
from sim_core.collision.rest_exclusion import RestExclusion
from sim_core.ti_kernels.hash_grid import HashGrid
from sim_core.ti_kernels.pair_filters import CandidateElements, compile_candidate_kernels


class HashCandidates(CandidateElements):
    """Vertex-triangle and edge-edge candidate lists of fixed elements by a spatial hash.

    Args:
        vertices: global indices of the colliding vertices, shape ``(v,)``.
        triangles: global vertex indices of the colliding triangles, shape ``(t, 3)``.
        edges: global vertex indices of the colliding edges, shape ``(e, 2)``.
        pair_filter: the body / self-contact filter; needs ``body_pair_allowed``.
        rest_exclusion: the filter's :class:`RestExclusion` built for these same arrays.

    Raises:
        ConfigError: no body-pair table in the filter, or a rest exclusion of another filter.
    """

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, edges: np.ndarray, pair_filter: PairFilter,
                 rest_exclusion: RestExclusion) -> None:
        super().__init__(vertices, triangles, edges, pair_filter, rest_exclusion)
        positions: dict = {}  # the two grids search the same positions in turn: one device copy of frozen ones
        self.vt_grid, self.ee_grid = HashGrid(positions=positions), HashGrid(positions=positions)

    def vertex_triangle(self, x: np.ndarray, radius: float) -> np.ndarray:
        """``[global vertex, triangle row]`` pairs within ``radius`` (m) at ``x`` ``(n, 3)`` (m), int64
        ``(p, 2)``, sorted: :func:`sim_core.collision.candidates.vertex_triangle_candidates`'s list.

        Raises:
            ConfigError: the Taichi backend is not initialised, or ``x`` is not finite.
        """
        if self.vertices.size == 0 or self.triangles.shape[0] == 0:
            return np.zeros((0, 2), dtype=np.int64)
        return self.vt_grid.pairs(x, self._vertex_elements, self._vertex_body, self._vertex_keys,
                                  self._triangle_elements, self._triangle_body, self.allowed, self._vt_rest, radius)

    def edge_edge(self, x: np.ndarray, radius: float) -> np.ndarray:
        """``[edge row i, edge row j]`` pairs (``i < j``) within ``radius`` (m) at ``x`` ``(n, 3)`` (m),
        int64 ``(p, 2)``, sorted: :func:`sim_core.collision.candidates.edge_edge_candidates`'s list.

        Raises:
            ConfigError: the Taichi backend is not initialised, or ``x`` is not finite.
        """
        if self.edges.shape[0] < 2:
            return np.zeros((0, 2), dtype=np.int64)
        return self.ee_grid.pairs(x, self._edge_elements, self._edge_body, self._edge_keys, None, None, self.allowed,
                                  self._ee_rest, radius)

    def keys_of(self, pairs: np.ndarray) -> np.ndarray | None:
        """The packed keys ``first << 32 | second`` (int64 ``(p,)``, increasing) of a list the last
        :meth:`vertex_triangle` or :meth:`edge_edge` returned (the same array: :meth:`HashGrid.keys_of`), else None."""
        keys = self.vt_grid.keys_of(pairs)
        return self.ee_grid.keys_of(pairs) if keys is None else keys


def compile_kernels() -> None:
    """JIT-compile (or load from Taichi's offline cache) the kernel on two small sheets' lists.

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """
    compile_candidate_kernels(HashCandidates)
