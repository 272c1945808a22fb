"""Narrow phase: closest points, region classification and contact distances with derivatives.

Closest points follow the Voronoi-region tests of Ericson, *Real-Time Collision Detection* (2005),
sec. 5.1.5 (point-triangle) and 5.1.9 (segment-segment); everything is vectorised over pairs.

Contact distance (the ``d`` of the penalty ``k_c/2 (d - eps)^2``, DESIGN.md "Contact"):

* vertex-triangle: where the vertex projects inside the triangle (face region) ``d`` is the signed
  distance along the triangle normal oriented to the remembered side, ``d = side n.(p - a)``;
  elsewhere it is the unsigned distance to the closest edge (point-line) or corner (point-point).
* edge-edge: where both closest points are interior to their edges and the edges are not nearly
  parallel, ``d = side n.(a0 - b0)`` with ``n = (a1 - a0) x (b1 - b0) / |.|``; elsewhere the unsigned
  point-line or point-point distance.

On the remembered side (``d >= 0``) both definitions equal the Euclidean distance between the two
primitives, which is C1 across region boundaries (distance to a convex set), so the penalty energy
is C1 for every non-penetrating configuration. A penetrated vertex (``d < 0``) that slides out of the
face region sees ``d`` jump from ``-delta`` to ``+delta``: the side only has a meaning above the face.
Near-parallel edges (``sin^2`` of the angle below ``PARALLEL_TOLERANCE``) are treated as point-edge
pairs (the line-line normal is undefined there); the distance then differs from the exact one by at
most ``|e| sin(angle)``.

Derivatives of the distance measures are exact, in closed form
(:mod:`sim_core.collision.distance_derivatives`); the forward-mode jet versions
(:func:`_point_point`, :func:`_point_line`, :func:`_signed_volume_distance`, with
:mod:`sim_core.collision.jets`) are the reference the tests compare them with.
"""

from __future__ import annotations

from enum import IntEnum
from typing import NamedTuple

import numpy as np

from sim_core.collision import distance_derivatives as closed_form
from sim_core.collision import jets
from sim_core.collision.jets import Jet

PARALLEL_TOLERANCE = 1.0e-6
"""Edges with ``|ea x eb|^2 < PARALLEL_TOLERANCE |ea|^2 |eb|^2`` are handled as point-edge pairs."""


class PointTriangleRegion(IntEnum):
    """Voronoi region of the closest point on triangle (a, b, c)."""

    FACE = 0
    EDGE_AB = 1
    EDGE_BC = 2
    EDGE_CA = 3
    VERTEX_A = 4
    VERTEX_B = 5
    VERTEX_C = 6


class EdgeEdgeRegion(IntEnum):
    """Which features of edges a = (a0, a1) and b = (b0, b1) hold the closest points."""

    INTERIOR = 0
    A0_EDGE_B = 1
    A1_EDGE_B = 2
    B0_EDGE_A = 3
    B1_EDGE_A = 4
    A0_B0 = 5
    A0_B1 = 6
    A1_B0 = 7
    A1_B1 = 8


class DistanceDerivatives(NamedTuple):
    """Contact distance of a batch of 4-vertex pairs.

    Attributes:
        d: distance in m, shape ``(k,)`` (signed in the face / interior region).
        grad: dd/dz over the 12 local DoFs, shape ``(k, 12)``, or None.
        hess: d^2 d/dz^2, shape ``(k, 12, 12)``, or None.
        region: region code per pair, shape ``(k,)``.
    """

    d: np.ndarray
    grad: np.ndarray | None
    hess: np.ndarray | None
    region: np.ndarray


def _dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.einsum("ki,ki->k", u, v)


_PT_REGION_ORDER = tuple(int(r) for r in (
    PointTriangleRegion.EDGE_BC, PointTriangleRegion.EDGE_CA, PointTriangleRegion.VERTEX_C,
    PointTriangleRegion.EDGE_AB, PointTriangleRegion.VERTEX_B, PointTriangleRegion.VERTEX_A))
"""Region codes in increasing priority of the Voronoi tests (a later test wins, as in Ericson's
early returns): what :func:`_point_triangle_tests` assigns, in this order."""


def _point_triangle_tests(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> tuple:
    """Ericson's dot products and the region codes of points vs triangles (all ``(k,)``)."""
    ab, ac = b - a, c - a
    ap, bp, cp = p - a, p - b, p - c
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4
    tests = (
        (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),  # edge bc
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),  # edge ca
        (d6 >= 0) & (d5 <= d6),  # vertex c
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),  # edge ab
        (d3 >= 0) & (d4 <= d3),  # vertex b
        (d1 <= 0) & (d2 <= 0),  # vertex a
    )
    region = np.full(p.shape[0], int(PointTriangleRegion.FACE), dtype=np.int64)
    for code, mask in zip(_PT_REGION_ORDER, tests):
        region[mask] = code
    return region, d1, d2, d3, d4, d5, d6, va, vb, vc


def point_triangle_region(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """:class:`PointTriangleRegion` codes of the closest points, shape ``(k,)`` (no barycentrics)."""
    return _point_triangle_tests(p, a, b, c)[0]


def point_triangle_closest_point(
    p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Closest point on triangles to points (Ericson 2005, sec. 5.1.5).

    Args:
        p, a, b, c: shape ``(k, 3)``; triangles must be non-degenerate.

    Returns:
        ``(bary, region)``: barycentric coordinates of the closest point ``q = bary @ [a, b, c]``,
        shape ``(k, 3)``; :class:`PointTriangleRegion` codes, shape ``(k,)``.
    """
    region, d1, d2, d3, d4, d5, d6, va, vb, vc = _point_triangle_tests(p, a, b, c)
    R = PointTriangleRegion
    with np.errstate(divide="ignore", invalid="ignore"):
        v_ab = d1 / (d1 - d3)
        w_ca = d2 / (d2 - d6)
        w_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        denom = 1.0 / (va + vb + vc)
    v_face, w_face = vb * denom, vc * denom
    k = p.shape[0]
    bary = np.zeros((k, 3))
    sel = [
        (R.FACE, lambda m: np.stack([1 - v_face[m] - w_face[m], v_face[m], w_face[m]], axis=1)),
        (R.EDGE_AB, lambda m: np.stack([1 - v_ab[m], v_ab[m], 0 * v_ab[m]], axis=1)),
        (R.EDGE_CA, lambda m: np.stack([1 - w_ca[m], 0 * w_ca[m], w_ca[m]], axis=1)),
        (R.EDGE_BC, lambda m: np.stack([0 * w_bc[m], 1 - w_bc[m], w_bc[m]], axis=1)),
    ]
    for code, fill in sel:
        m = region == code
        if np.any(m):
            bary[m] = fill(m)
    bary[region == R.VERTEX_A, 0] = 1.0
    bary[region == R.VERTEX_B, 1] = 1.0
    bary[region == R.VERTEX_C, 2] = 1.0
    return bary, region


def point_triangle_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Unsigned Euclidean distance from points to triangles, shape ``(k,)`` (m)."""
    bary, _ = point_triangle_closest_point(p, a, b, c)
    q = bary[:, 0:1] * a + bary[:, 1:2] * b + bary[:, 2:3] * c
    return np.linalg.norm(p - q, axis=1)


def edge_edge_closest_points(
    a0: np.ndarray, a1: np.ndarray, b0: np.ndarray, b1: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest points of segment pairs (Ericson 2005, sec. 5.1.9), robust to parallel edges.

    Nearly parallel edges (see ``PARALLEL_TOLERANCE``) start from ``s = 0`` so that the result is
    an endpoint-to-edge configuration instead of an ill-conditioned line-line solution.

    Args:
        a0, a1, b0, b1: endpoints, shape ``(k, 3)``; edges must have non-zero length.

    Returns:
        ``(s, t, region)``: closest points ``a0 + s (a1 - a0)`` and ``b0 + t (b1 - b0)`` with s, t
        in [0, 1], shape ``(k,)`` each; :class:`EdgeEdgeRegion` codes, shape ``(k,)``.
    """
    ea, eb, r = a1 - a0, b1 - b0, a0 - b0
    A, E = _dot(ea, ea), _dot(eb, eb)
    B, C, F = _dot(ea, eb), _dot(ea, r), _dot(eb, r)
    denom = A * E - B * B
    parallel = denom < PARALLEL_TOLERANCE * A * E
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(parallel, 0.0, np.clip((B * F - C * E) / denom, 0.0, 1.0))
    t = (B * s + F) / E
    low, high = t < 0.0, t > 1.0
    s = np.where(low, np.clip(-C / A, 0.0, 1.0), np.where(high, np.clip((B - C) / A, 0.0, 1.0), s))
    t = np.clip(t, 0.0, 1.0)
    s_end = np.where(s <= 0.0, 0, np.where(s >= 1.0, 1, -1))
    t_end = np.where(t <= 0.0, 0, np.where(t >= 1.0, 1, -1))
    R = EdgeEdgeRegion
    region = np.full(s.shape, int(R.INTERIOR), dtype=np.int64)
    both = (s_end >= 0) & (t_end >= 0)
    region[both] = R.A0_B0 + 2 * s_end[both] + t_end[both]
    only_s = (s_end >= 0) & (t_end < 0)
    region[only_s] = R.A0_EDGE_B + s_end[only_s]
    only_t = (s_end < 0) & (t_end >= 0)
    region[only_t] = R.B0_EDGE_A + t_end[only_t]
    # an interior solution of nearly parallel edges is replaced by the endpoint-edge one
    region[(region == R.INTERIOR) & parallel] = R.A0_EDGE_B
    return s, t, region


def edge_edge_distance(a0: np.ndarray, a1: np.ndarray, b0: np.ndarray, b1: np.ndarray) -> np.ndarray:
    """Unsigned distance between segments, shape ``(k,)`` (m)."""
    s, t, _ = edge_edge_closest_points(a0, a1, b0, b1)
    return np.linalg.norm(a0 + s[:, None] * (a1 - a0) - b0 - t[:, None] * (b1 - b0), axis=1)


def _point_point(z: np.ndarray, i: np.ndarray, j: np.ndarray, order: int) -> Jet:
    """|z_i - z_j| for per-pair local vertex slots i, j; z of shape (k, 4, 3)."""
    rows = np.arange(z.shape[0])
    pi = jets.variable(z[rows, i], i, 12, order)
    pj = jets.variable(z[rows, j], j, 12, order)
    return jets.norm(pi - pj)


def _point_line(z: np.ndarray, i: np.ndarray, j: np.ndarray, l: np.ndarray, order: int) -> Jet:
    """Distance from z_i to the line through z_j, z_l: sqrt(|(z_i - z_j) x e|^2 / |e|^2)."""
    rows = np.arange(z.shape[0])
    p = jets.variable(z[rows, i], i, 12, order)
    a = jets.variable(z[rows, j], j, 12, order)
    b = jets.variable(z[rows, l], l, 12, order)
    e = b - a
    c = jets.cross(p - a, e)
    return jets.sqrt(jets.multiply(jets.dot(c, c), jets.reciprocal(jets.dot(e, e))))


def _signed_volume_distance(z: np.ndarray, side: np.ndarray, point_first: bool, order: int) -> Jet:
    """side * n.(r) with n the unit normal of a plane or line pair.

    point_first: z = [p, a, b, c], n ~ (b - a) x (c - a), r = p - a (point-plane);
    otherwise z = [a0, a1, b0, b1], n ~ (a1 - a0) x (b1 - b0), r = a0 - b0 (line-line).
    """
    v = [jets.variable(z[:, a], a, 12, order) for a in range(4)]
    if point_first:
        n = jets.cross(v[2] - v[1], v[3] - v[1])
        r = v[0] - v[1]
    else:
        n = jets.cross(v[1] - v[0], v[3] - v[2])
        r = v[0] - v[2]
    return jets.multiply(jets.dot(n, r), jets.reciprocal(jets.norm(n))).scaled(side)


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``u x v`` of ``(k, 3)`` arrays, written as :func:`jets.cross` forms its value."""
    nxt, prv = [1, 2, 0], [2, 0, 1]
    return u[:, nxt] * v[:, prv] - u[:, prv] * v[:, nxt]


def _sum_dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``u . v`` of ``(k, 3)`` arrays, summed as :func:`jets.dot` sums its value."""
    return (u * v).sum(axis=1)


def _distance_values(z: np.ndarray, side: np.ndarray, face: np.ndarray, point_first: bool,
                     line: np.ndarray, line_slots: np.ndarray, corner: np.ndarray, corner_slots: np.ndarray) -> np.ndarray:
    """Contact distance without derivatives (order 0), the same expressions as the jets' values.

    Face / interior: ``side (n . r) / |n|``; point-line: ``sqrt(|(z_i - z_j) x e|^2 / |e|^2)``;
    point-point ``|z_i - z_j|`` (see :func:`_signed_volume_distance`, :func:`_point_line`,
    :func:`_point_point`); plain NumPy, about 5x faster than carrying value-only jets.
    """
    d = np.zeros(z.shape[0])
    if np.any(face):
        zf = z[face]
        if point_first:
            n, r = _cross(zf[:, 2] - zf[:, 1], zf[:, 3] - zf[:, 1]), zf[:, 0] - zf[:, 1]
        else:
            n, r = _cross(zf[:, 1] - zf[:, 0], zf[:, 3] - zf[:, 2]), zf[:, 0] - zf[:, 2]
        d[face] = (_sum_dot(n, r) * (1.0 / np.sqrt(_sum_dot(n, n)))) * side[face]
    if np.any(line):
        rows = np.flatnonzero(line)
        i, j, l = line_slots[:, 0], line_slots[:, 1], line_slots[:, 2]
        a = z[rows, j]
        e = z[rows, l] - a
        c = _cross(z[rows, i] - a, e)
        d[line] = np.sqrt(_sum_dot(c, c) * (1.0 / _sum_dot(e, e)))
    if np.any(corner):
        rows = np.flatnonzero(corner)
        u = z[rows, corner_slots[:, 0]] - z[rows, corner_slots[:, 1]]
        d[corner] = np.sqrt(_sum_dot(u, u))
    return d


def _assemble(k: int, parts: list[tuple[np.ndarray, Jet]], order: int) -> tuple:
    d = np.zeros(k)
    grad = np.zeros((k, 12)) if order >= 1 else None
    hess = np.zeros((k, 12, 12)) if order >= 2 else None
    for mask, jet in parts:
        d[mask] = jet.val
        if grad is not None:
            grad[mask] = jet.grad
        if hess is not None and jet.hess is not None:
            hess[mask] = jet.hess
    return d, grad, hess


# local vertex slots per region: z = [p, a, b, c]
_PT_LINE = {
    PointTriangleRegion.EDGE_AB: (1, 2),
    PointTriangleRegion.EDGE_BC: (2, 3),
    PointTriangleRegion.EDGE_CA: (3, 1),
}
_PT_CORNER = {PointTriangleRegion.VERTEX_A: 1, PointTriangleRegion.VERTEX_B: 2, PointTriangleRegion.VERTEX_C: 3}
# z = [a0, a1, b0, b1]
_EE_LINE = {
    EdgeEdgeRegion.A0_EDGE_B: (0, 2, 3),
    EdgeEdgeRegion.A1_EDGE_B: (1, 2, 3),
    EdgeEdgeRegion.B0_EDGE_A: (2, 0, 1),
    EdgeEdgeRegion.B1_EDGE_A: (3, 0, 1),
}
_EE_CORNER = {
    EdgeEdgeRegion.A0_B0: (0, 2),
    EdgeEdgeRegion.A0_B1: (0, 3),
    EdgeEdgeRegion.A1_B0: (1, 2),
    EdgeEdgeRegion.A1_B1: (1, 3),
}


def _table(region: np.ndarray, table: dict, width: int) -> np.ndarray:
    out = np.zeros((region.shape[0], width), dtype=np.int64)
    for code, slots in table.items():
        out[region == code] = slots
    return out


def point_triangle_contact_distance(z: np.ndarray, side: np.ndarray, order: int = 0) -> DistanceDerivatives:
    """Contact distance of vertex-triangle pairs with its derivatives (module docstring).

    Args:
        z: positions ``[p, a, b, c]`` of each pair, shape ``(k, 4, 3)`` (m).
        side: remembered side (+1 / -1) of p w.r.t. the normal ``(b - a) x (c - a)``, shape ``(k,)``.
        order: 0 value only, 1 with gradient, 2 with Hessian.

    Returns:
        :class:`DistanceDerivatives` with :class:`PointTriangleRegion` codes.
    """
    k = z.shape[0]
    region = point_triangle_region(z[:, 0], z[:, 1], z[:, 2], z[:, 3])
    face = region == PointTriangleRegion.FACE
    if order == 0:
        line = (region >= PointTriangleRegion.EDGE_AB) & (region <= PointTriangleRegion.EDGE_CA)
        corner = region >= PointTriangleRegion.VERTEX_A
        line_slots = np.concatenate([np.zeros((int(line.sum()), 1), np.int64), _table(region[line], _PT_LINE, 2)], axis=1)
        corner_slots = np.stack([np.zeros(int(corner.sum()), np.int64), _table(region[corner], _PT_CORNER, 1)[:, 0]], axis=1)
        d = _distance_values(z, side, face, True, line, line_slots, corner, corner_slots)
        return DistanceDerivatives(d, None, None, region)
    parts = []
    if np.any(face):
        parts.append((face, closed_form.signed_volume(z[face], side[face], True, order)))
    line = (region >= PointTriangleRegion.EDGE_AB) & (region <= PointTriangleRegion.EDGE_CA)
    if np.any(line):
        s = _table(region[line], _PT_LINE, 2)
        parts.append((line, closed_form.point_line(z[line], np.zeros(s.shape[0], np.int64), s[:, 0], s[:, 1], order)))
    corner = region >= PointTriangleRegion.VERTEX_A
    if np.any(corner):
        s = _table(region[corner], _PT_CORNER, 1)[:, 0]
        parts.append((corner, closed_form.point_point(z[corner], np.zeros(s.shape[0], np.int64), s, order)))
    return DistanceDerivatives(*_assemble(k, parts, order), region)


def edge_edge_contact_distance(z: np.ndarray, side: np.ndarray, order: int = 0) -> DistanceDerivatives:
    """Contact distance of edge-edge pairs with its derivatives (module docstring).

    Args:
        z: positions ``[a0, a1, b0, b1]`` of each pair, shape ``(k, 4, 3)`` (m).
        side: remembered sign of ``((a1 - a0) x (b1 - b0)).(a0 - b0)``, shape ``(k,)``.
        order: 0 value only, 1 with gradient, 2 with Hessian.

    Returns:
        :class:`DistanceDerivatives` with :class:`EdgeEdgeRegion` codes.
    """
    k = z.shape[0]
    _, _, region = edge_edge_closest_points(z[:, 0], z[:, 1], z[:, 2], z[:, 3])
    interior = region == EdgeEdgeRegion.INTERIOR
    if order == 0:
        line = (region >= EdgeEdgeRegion.A0_EDGE_B) & (region <= EdgeEdgeRegion.B1_EDGE_A)
        corner = region >= EdgeEdgeRegion.A0_B0
        d = _distance_values(z, side, interior, False, line, _table(region[line], _EE_LINE, 3),
                             corner, _table(region[corner], _EE_CORNER, 2))
        return DistanceDerivatives(d, None, None, region)
    parts = []
    if np.any(interior):
        parts.append((interior, closed_form.signed_volume(z[interior], side[interior], False, order)))
    line = (region >= EdgeEdgeRegion.A0_EDGE_B) & (region <= EdgeEdgeRegion.B1_EDGE_A)
    if np.any(line):
        s = _table(region[line], _EE_LINE, 3)
        parts.append((line, closed_form.point_line(z[line], s[:, 0], s[:, 1], s[:, 2], order)))
    corner = region >= EdgeEdgeRegion.A0_B0
    if np.any(corner):
        s = _table(region[corner], _EE_CORNER, 2)
        parts.append((corner, closed_form.point_point(z[corner], s[:, 0], s[:, 1], order)))
    return DistanceDerivatives(*_assemble(k, parts, order), region)


def point_triangle_side(z: np.ndarray) -> np.ndarray:
    """Side of p w.r.t. the normal ``(b - a) x (c - a)``: +1 or -1 (0 maps to +1), shape ``(k,)``."""
    n = np.cross(z[:, 2] - z[:, 1], z[:, 3] - z[:, 1])
    return np.where(_dot(n, z[:, 0] - z[:, 1]) < 0.0, -1.0, 1.0)


def edge_edge_side(z: np.ndarray) -> np.ndarray:
    """Sign of ``((a1 - a0) x (b1 - b0)).(a0 - b0)`` (0 maps to +1), shape ``(k,)``."""
    n = np.cross(z[:, 1] - z[:, 0], z[:, 3] - z[:, 2])
    return np.where(_dot(n, z[:, 0] - z[:, 2]) < 0.0, -1.0, 1.0)
