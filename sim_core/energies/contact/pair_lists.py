"""The vertices of a contact set's candidate pair lists, computed once per list.

A candidate search (:mod:`sim_core.contact_set`) gives a vertex-triangle list ``(p, 2)`` and an edge-edge list
``(q, 2)`` that stay in use until the next search: the step's potentials are built over them (every
vertex-triangle pair, the edge-edge pairs that are not near-parallel), their geometry is measured at the converged
positions, and the next step, whose first iterates the same search usually covers, builds its potentials over them
again with new sides. :class:`CandidateVertices` keeps, for one pair of lists, the pairs' global vertices
(``[p, a, b, c]`` and ``[a0, a1, b0, b1]``, :func:`~sim_core.energies.contact.reference.vertex_triangle_vertices` and
:func:`~sim_core.energies.contact.reference.edge_edge_vertices`) and, on the Taichi backend, their positions among
the distinct vertices they name (:func:`~sim_core.unique.compact_indices`: the pair batch's kernel indices,
:class:`~sim_core.energies.contact.batch_kernel.PairBatch`), so that a stacked batch of 1024 Forming copies (1.75
million candidate pairs) gathers and compacts them once per search instead of at every potential, batch and
geometry measurement.
"""

from __future__ import annotations

import numpy as np

from sim_core.energies.contact.reference import edge_edge_vertices, vertex_triangle_vertices
from sim_core.unique import compact_indices


class CandidateVertices:
    """The global vertices of candidate lists ``vt`` ``(p, 2)`` (``[vertex, triangle row]``) and ``ee`` ``(q, 2)``
    (``[edge row, edge row]``) over ``triangles`` ``(t, 3)`` and ``edges`` ``(e, 2)``.

    Attributes:
        vt, ee: the lists (the arrays given: :meth:`of` matches them by identity).
        vt_vertices: ``[p, a, b, c]`` int64 ``(p, 4)``.
        ee_vertices: ``[a0, a1, b0, b1]`` int64 ``(q, 4)``.
    """

    def __init__(self, vt: np.ndarray, ee: np.ndarray, triangles: np.ndarray, edges: np.ndarray) -> None:
        self.vt, self.ee = vt, ee
        self.vt_vertices = vertex_triangle_vertices(vt, triangles)
        self.ee_vertices = edge_edge_vertices(ee, edges)
        self._compact: tuple | None = None

    def of(self, vt: np.ndarray, ee: np.ndarray) -> bool:
        """Whether these are the vertices of the lists ``vt`` and ``ee`` (the same array objects)."""
        return vt is self.vt and ee is self.ee

    def batch_indices(self, ee_rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(own, local)`` of the pairs of every vertex-triangle candidate and the edge-edge candidates ``ee_rows``
        (int ``(r,)``), in that order: ``own`` int64 ``(u,)`` the sorted distinct vertices every candidate names (a
        superset of those of the chosen pairs), ``local`` int32 ``(p + r, 4)`` the pairs' vertices as positions in
        ``own`` (the argument ``compact`` of :class:`~sim_core.energies.contact.batch_kernel.PairBatch`); the
        compaction of every candidate's vertices is made on first use and kept."""
        if self._compact is None:
            p = len(self.vt_vertices)
            own, local = compact_indices(np.concatenate([self.vt_vertices, self.ee_vertices], dtype=np.int32),
                                         dtype=np.int32)
            self._compact = (own, local[:p], local[p:])
        own, vt_local, ee_local = self._compact
        return own, np.concatenate([vt_local, np.take(ee_local, ee_rows, axis=0)])


def lookup_pairs(old: tuple | None, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(pos, found)`` of ``pairs`` ``(p, 2)`` in ``old`` (``(old pairs, old arrays)``, the old pairs sorted as
    candidate lists are): rows ``pos`` ``(p,)`` of the old arrays hold the pairs ``found`` (bool ``(p,)``). The same
    list (the same array object) is found row for row without a search."""
    if old is None or not len(old[0]) or not len(pairs):
        return np.zeros(len(pairs), dtype=np.int64), np.zeros(len(pairs), dtype=bool)
    old_pairs = old[0]
    if old_pairs is pairs:
        return np.arange(len(pairs), dtype=np.int64), np.ones(len(pairs), dtype=bool)
    keys = (pairs[:, 0] << 32) | pairs[:, 1]
    old_keys = (old_pairs[:, 0] << 32) | old_pairs[:, 1]
    pos = np.minimum(np.searchsorted(old_keys, keys), len(old_keys) - 1)
    return pos, old_keys[pos] == keys


def merge_rows(old: tuple | None, pos: np.ndarray, found: np.ndarray, fresh: tuple) -> tuple:
    """Per-pair arrays over a pair list: the rows ``found`` (bool ``(p,)``) taken from rows ``pos`` ``(p,)`` of the
    arrays of ``old`` (:func:`lookup_pairs`), the others from ``fresh`` (computed for the pairs not found, in order):
    the per-pair results do not depend on which other pairs are in the list."""
    if not np.any(found):
        return fresh
    old_values = old[1]
    if np.all(found):
        return tuple(v[pos] for v in old_values)
    out = []
    for v, f in zip(old_values, fresh):
        merged = np.empty(len(found), dtype=v.dtype)
        merged[found] = v[pos[found]]
        merged[~found] = f
        out.append(merged)
    return tuple(out)
