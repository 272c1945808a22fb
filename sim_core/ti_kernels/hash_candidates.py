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

# No ``from __future__ import annotations`` here: Taichi reads kernel annotations as objects.

import numpy as np

from sim_core.collision.candidates import PairFilter
from sim_core.collision.rest_exclusion import RestExclusion
from sim_core.ti_backend import serial_loops, ti
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.buffers import on_device
from sim_core.ti_kernels.device_copy import new_ndarray
from sim_core.ti_kernels.hash_grid import HashGrid
from sim_core.ti_kernels.launch import fast_kernel
from sim_core.ti_kernels.pair_filters import CandidateElements, compile_candidate_kernels

_I32_2 = linalg.I32_2
_I64_1 = ti.types.ndarray(dtype=ti.i64, ndim=1)


@fast_kernel
def _vertices_kernel(keys: _I64_1, count: ti.i32, first_vertices: _I32_2, first_is_vertex: ti.i32,
                     second_vertices: _I32_2, out: _I32_2):
    """``out[k]`` (int32 ``(count, 4)``): the global vertices of the pair of sorted key ``keys[k]`` ``first << 32 |
    second``: ``[first, second_vertices[second]]`` (a vertex and a triangle row, ``first_is_vertex`` 1;
    :func:`~sim_core.energies.contact.reference.vertex_triangle_vertices`) or ``[first_vertices[first],
    second_vertices[second]]`` (two edge rows; :func:`~sim_core.energies.contact.reference.edge_edge_vertices`)."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for k in range(count):
        key = keys[k]
        first = ti.cast(key >> 32, ti.i32)
        second = ti.cast(key - (ti.cast(first, ti.i64) << 32), ti.i32)  # (keys >= 0: the low 32 bits)
        if first_is_vertex != 0:
            out[k, 0] = first
            for c in ti.static(range(3)):
                out[k, 1 + c] = second_vertices[second, c]
        else:
            for c in ti.static(range(2)):
                out[k, c] = first_vertices[first, c]
                out[k, 2 + c] = second_vertices[second, c]


class HashCandidates(CandidateElements):
    """Vertex-triangle and edge-edge candidate lists of fixed elements by a spatial hash.

    Args:
        vertices: global indices of the colliding vertices, shape ``(v,)``.
        triangles: global vertex indices of the colliding triangles, shape ``(t, 3)``.
        edges: global vertex indices of the colliding edges, shape ``(e, 2)``.
        pair_filter: the body / self-contact filter; needs ``body_pair_allowed``.
        rest_exclusion: the filter's :class:`RestExclusion` built for these same arrays.
        vt_allowed: the vertex-triangle search's body table (:class:`CandidateElements`), or None.

    Raises:
        ConfigError: no body-pair table in the filter, a rest exclusion of another filter, or a ``vt_allowed`` of
            another shape.
    """

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, edges: np.ndarray, pair_filter: PairFilter,
                 rest_exclusion: RestExclusion, vt_allowed: np.ndarray | None = None) -> None:
        super().__init__(vertices, triangles, edges, pair_filter, rest_exclusion, vt_allowed)
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
                                  self._triangle_elements, self._triangle_body, self.vt_allowed, self._vt_rest, radius)

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

    def device_vertices(self, vt: np.ndarray, ee: np.ndarray) -> tuple[object, object] | None:
        """On CUDA, the int32 global vertices ``(p, 4)`` and ``(q, 4)`` of the lists the last :meth:`vertex_triangle`
        and :meth:`edge_edge` returned (the same arrays), gathered by one launch of :func:`_vertices_kernel` a list
        from the sorted keys where their sort left them (:meth:`HashGrid.device_keys_of`): new Taichi ndarrays in
        device memory (None for an empty list), equal to
        :meth:`~sim_core.energies.contact.pair_lists.CandidateVertices.int32_vertices`; None where a list's keys are
        not there (another arch, other arrays). Nothing crosses: the element tables are sent once."""
        keys = (self.vt_grid.device_keys_of(vt), self.ee_grid.device_keys_of(ee))
        if any(k is None and len(pairs) for k, pairs in zip(keys, (vt, ee))):
            return None
        device = self.__dict__.setdefault("_device", {})
        out = []
        for pairs, k, name, second, vertex_first in ((vt, keys[0], "triangles", self._triangle_elements, 1),
                                                     (ee, keys[1], "edges", self._edge_elements, 0)):
            if not len(pairs):
                out.append(None)
                continue
            table = on_device(device, name, second)  # (the vertex-triangle kernel reads no first table)
            vertices = new_ndarray(ti.i32, (len(pairs), 4))
            _vertices_kernel(k, len(pairs), table, vertex_first, table, vertices)
            out.append(vertices)
        return out[0], out[1]

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
