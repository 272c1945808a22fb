"""Side-memory geometry of vertex-triangle and edge-edge pairs at one configuration.

What the contact set (:mod:`sim_core.contact_set`) needs of its candidate pairs at the start of a
step (``x^n``) and of its active pairs at the end (``x^{n+1}``), before any side is chosen:

* vertex-triangle ``[p, a, b, c]``: whether ``p`` is above the face (its closest point on the
  triangle is in the face region, Ericson 2005, sec. 5.1.5) and the side of ``p`` w.r.t. the normal
  ``(b - a) x (c - a)`` (:func:`~sim_core.collision.distances.point_triangle_side`);
* edge-edge ``[a0, a1, b0, b1]``: the sine of the angle between the edges
  ``|ea x eb| / (|ea| |eb|)`` (near-parallel pairs are left out of the contact set), whether both
  closest points are interior (Ericson 2005, sec. 5.1.9) and the sign of
  ``((a1 - a0) x (b1 - b0)).(a0 - b0)`` (:func:`~sim_core.collision.distances.edge_edge_side`).

This NumPy function is the reference; :func:`sim_core.energies.contact.setup_kernel.pair_geometry` is its
Taichi twin (one launch for both pair kinds, equal bit for bit).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from sim_core.collision.distances import (
    EdgeEdgeRegion,
    PointTriangleRegion,
    edge_edge_closest_points,
    edge_edge_side,
    point_triangle_region,
    point_triangle_side,
)


class PairGeometry(NamedTuple):
    """Per-pair geometry of vertex-triangle (``vt_*``, shape ``(p,)``) and edge-edge (``ee_*``,
    shape ``(q,)``) pairs at one configuration (module docstring).

    Attributes:
        vt_above: the vertex projects onto the face interior (face region), bool.
        vt_side: side of the vertex w.r.t. ``(b - a) x (c - a)``, +1 / -1 (0 maps to +1).
        ee_sine: sine of the angle between the two edges, in [0, 1].
        ee_interior: both closest points are interior to their edges, bool.
        ee_side: sign of ``((a1 - a0) x (b1 - b0)).(a0 - b0)``, +1 / -1 (0 maps to +1).
    """

    vt_above: np.ndarray
    vt_side: np.ndarray
    ee_sine: np.ndarray
    ee_interior: np.ndarray
    ee_side: np.ndarray


class ListGeometry(NamedTuple):
    """What a step's sides need of a candidate list's :class:`PairGeometry` (shapes ``(p,)`` and ``(q,)``): its fields
    with ``ee_sine`` compared with the contact set's least edge sine (``ee_keep``: the edge-edge pairs not
    near-parallel, :meth:`sim_core.contact_set.ContactSet._pair_sides`).

    Attributes:
        vt_above, vt_side, ee_interior, ee_side: as :class:`PairGeometry`'s (sides float64).
        ee_keep: ``ee_sine > min_sine``, bool.
    """

    vt_above: np.ndarray
    vt_side: np.ndarray
    ee_keep: np.ndarray
    ee_interior: np.ndarray
    ee_side: np.ndarray

    @classmethod
    def of(cls, geometry: PairGeometry, min_sine: float) -> "ListGeometry":
        """The list geometry of ``geometry`` with edge-edge pairs kept where ``ee_sine > min_sine``."""
        return cls(geometry.vt_above, geometry.vt_side, geometry.ee_sine > min_sine, geometry.ee_interior,
                   geometry.ee_side)

    def rows(self, vt_rows: np.ndarray, ee_rows: np.ndarray) -> "ListGeometry":
        """The rows ``vt_rows`` ``(a,)`` of the vertex-triangle fields and ``ee_rows`` ``(b,)`` of the edge-edge ones."""
        return ListGeometry(self.vt_above[vt_rows], self.vt_side[vt_rows], self.ee_keep[ee_rows],
                            self.ee_interior[ee_rows], self.ee_side[ee_rows])


def pair_geometry(x: np.ndarray, vt_vertices: np.ndarray, ee_vertices: np.ndarray) -> PairGeometry:
    """Side-memory geometry of the pairs at positions ``x`` (module docstring).

    Args:
        x: positions, shape ``(n, 3)`` (m).
        vt_vertices: ``[p, a, b, c]`` global vertex indices, shape ``(p, 4)``; triangles non-degenerate.
        ee_vertices: ``[a0, a1, b0, b1]`` global vertex indices, shape ``(q, 4)``; edges of non-zero length.

    Returns:
        :class:`PairGeometry`.
    """
    x = np.asarray(x, dtype=float)
    vt_vertices = np.asarray(vt_vertices, dtype=np.int64).reshape(-1, 4)
    ee_vertices = np.asarray(ee_vertices, dtype=np.int64).reshape(-1, 4)
    z = x[vt_vertices]
    if len(z):
        above = point_triangle_region(z[:, 0], z[:, 1], z[:, 2], z[:, 3]) == PointTriangleRegion.FACE
        vt_side = point_triangle_side(z)
    else:
        above, vt_side = np.zeros(0, dtype=bool), np.zeros(0)
    z = x[ee_vertices]
    if len(z):
        da, db = z[:, 1] - z[:, 0], z[:, 3] - z[:, 2]
        sine = np.linalg.norm(np.cross(da, db), axis=1) / (np.linalg.norm(da, axis=1) * np.linalg.norm(db, axis=1))
        interior = edge_edge_closest_points(z[:, 0], z[:, 1], z[:, 2], z[:, 3])[2] == EdgeEdgeRegion.INTERIOR
        ee_side = edge_edge_side(z)
    else:
        sine, interior, ee_side = np.zeros(0), np.zeros(0, dtype=bool), np.zeros(0)
    return PairGeometry(above, vt_side, sine, interior, ee_side)
