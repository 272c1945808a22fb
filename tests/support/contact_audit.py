"""An audit of surface crossings, independent of the solver's contact set (for no-tunnelling tests).

:class:`CrossingAudit` takes every vertex-triangle and edge-edge pair between the surfaces of the
bodies it is given (a body with itself: self-contact, with the contact set's rest-distance
exclusion), and checks each step ``x^n -> x^{n+1}`` of a rollout with its own bookkeeping:

* signed distance: a pair in the face region (vertex-triangle) or with both closest points interior
  (edge-edge, not near-parallel: sine of the angle >= 0.1 at both ends of the step) at ``x^n`` and
  within ``reach`` of it takes its geometric side at ``x^n``
  (:func:`~sim_core.collision.distances.point_triangle_side` / ``edge_edge_side``), and its contact
  distance at ``x^{n+1}`` (:func:`~sim_core.collision.distances.point_triangle_contact_distance` /
  ``edge_edge_contact_distance``, the contact potentials' distance) must stay > 0. A primitive that
  passes through another within one step (positions linear in time) was within twice the largest
  vertex move of the step at ``x^n``; :meth:`CrossingAudit.step` widens ``reach`` to 2.5 times that
  move when it is larger;
* intersection: no edge of one surface pierces a triangle of the other at ``x^{n+1}`` (segment /
  triangle test, Moller & Trumbore 1997). Two intersecting triangle meshes always have such an edge,
  so this catches a crossing that the signed distance misses (a vertex that comes round a triangle's
  border onto its far side);
* activity: the number of pairs with contact distance below ``eps`` at ``x^{n+1}`` (the pairs that
  push), so that a test can prove that the surfaces actually touched.

Sides are the audit's own (taken at every ``x^n``), never the solver's side memory, so a wrong
side in the memory cannot hide a crossing from it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim_core.collision.distances import (
    EdgeEdgeRegion,
    PointTriangleRegion,
    edge_edge_contact_distance,
    edge_edge_distance,
    edge_edge_side,
    point_triangle_contact_distance,
    point_triangle_distance,
    point_triangle_side,
)
from sim_core.model import Model


@dataclass
class AuditStep:
    """Result of one audited step (distances in m).

    Attributes:
        min_signed_distance: smallest contact distance at ``x^{n+1}`` over the pairs with a side
            (face / interior region within ``reach`` at ``x^n``), inf when there is none.
        min_distance: smallest contact distance at ``x^{n+1}`` over all pairs (unsigned where the
            pair has no side).
        active_pairs: pairs with contact distance < eps at ``x^{n+1}``.
        intersections: edge-triangle piercings at ``x^{n+1}``.
        max_displacement: largest move of an audited vertex in the step.
    """

    min_signed_distance: float
    min_distance: float
    active_pairs: int
    intersections: int
    max_displacement: float


def _pairs_between(first, second, same: bool) -> np.ndarray:
    """All index pairs ``(i, j)`` of ``range(first) x range(second)`` (``i < j`` when ``same``)."""
    i, j = np.meshgrid(np.arange(first), np.arange(second), indexing="ij")
    i, j = i.reshape(-1), j.reshape(-1)
    if same:
        keep = i < j
        i, j = i[keep], j[keep]
    return np.stack([i, j], axis=1)


class CrossingAudit:
    """Crossing audit of body pairs of a model (see module docstring).

    Args:
        model: the model (surfaces, rest positions, contact eps and candidate margin).
        body_pairs: ``(a, b)`` body names; ``a == b`` audits self-contact of a sheet (pairs closer
            than ``2 (eps + candidate_margin)`` at rest are excluded, as
            :class:`sim_core.contact_set.ContactSet` does).
        reach: pairs within this distance at ``x^n`` (m) get a side for the step (at least 2.5 times
            the step's largest move of an audited vertex).
    """

    def __init__(self, model: Model, body_pairs: list[tuple[str, str]], reach: float = 3e-3) -> None:
        self.eps = float(model.contact.eps)
        self.reach = float(reach)
        rest = model.x_rest
        exclusion = 2.0 * (model.contact.eps + model.contact.candidate_margin)
        vt, ee, et = [], [], []
        for a, b in body_pairs:
            A, B = model.bodies[a], model.bodies[b]
            same = a == b
            for P, Q in ((A, B),) if same else ((A, B), (B, A)):
                verts = np.unique(P.triangles)
                p = _pairs_between(len(verts), len(Q.triangles), False)
                vt.append(np.concatenate([verts[p[:, 0], None], Q.triangles[p[:, 1]]], axis=1))
                p = _pairs_between(len(P.edges), len(Q.triangles), False)
                et.append(np.concatenate([P.edges[p[:, 0]], Q.triangles[p[:, 1]]], axis=1))
            p = _pairs_between(len(A.edges), len(B.edges), same)
            ee.append(np.concatenate([A.edges[p[:, 0]], B.edges[p[:, 1]]], axis=1))
        vt, ee, et = (np.concatenate(v).astype(np.int64) for v in (vt, ee, et))
        # topological neighbours: a vertex of its triangle, edges sharing a vertex
        vt = vt[np.all(vt[:, 1:] != vt[:, :1], axis=1)]
        ee = ee[~np.any(ee[:, :2, None] == ee[:, None, 2:], axis=(1, 2))]
        et = et[~np.any(et[:, :2, None] == et[:, None, 2:], axis=(1, 2))]
        self_vt = model.body_of_vertex()[vt[:, 0]] == model.body_of_vertex()[vt[:, 1]]
        self_ee = model.body_of_vertex()[ee[:, 0]] == model.body_of_vertex()[ee[:, 2]]
        self_et = model.body_of_vertex()[et[:, 0]] == model.body_of_vertex()[et[:, 2]]
        r = rest
        d_vt = point_triangle_distance(r[vt[:, 0]], r[vt[:, 1]], r[vt[:, 2]], r[vt[:, 3]])
        d_ee = edge_edge_distance(r[ee[:, 0]], r[ee[:, 1]], r[ee[:, 2]], r[ee[:, 3]])
        # an edge and a triangle are neighbours at rest when one of the edge's vertices is close to it
        d_et = np.minimum(point_triangle_distance(r[et[:, 0]], r[et[:, 2]], r[et[:, 3]], r[et[:, 4]]),
                          point_triangle_distance(r[et[:, 1]], r[et[:, 2]], r[et[:, 3]], r[et[:, 4]]))
        self.vertex_triangle = vt[~(self_vt & (d_vt < exclusion))]
        self.edge_edge = ee[~(self_ee & (d_ee < exclusion))]
        self.edge_triangle = et[~(self_et & (d_et < exclusion))]
        self.vertices = np.unique(np.concatenate([self.vertex_triangle.reshape(-1), self.edge_edge.reshape(-1)]))
        self.history: list[AuditStep] = []

    @staticmethod
    def _signed(z_n: np.ndarray, z: np.ndarray, kind: str, reach: float) -> tuple[np.ndarray, np.ndarray]:
        """Contact distances at ``z`` with sides from ``z_n`` (the pairs with a side, also returned as
        a mask) or else from ``z`` itself (unsigned: ``|d|``)."""
        if kind == "vt":
            at_n = point_triangle_contact_distance(z_n, np.ones(len(z_n)))
            sided = (at_n.region == PointTriangleRegion.FACE) & (np.abs(at_n.d) < reach)
            side = np.where(sided, point_triangle_side(z_n), point_triangle_side(z))
            d = point_triangle_contact_distance(z, side).d
        else:
            # near-parallel edges have no side (the cross product of their directions is noise): the
            # contact set leaves them to the vertex-triangle pairs (ContactSet.min_edge_sine), and so
            # does the audit (two parallel grid edges 6.7 mm apart in a flat sheet read -6.7 mm once
            # their cross product changed sign); a real crossing still shows as a piercing
            at_n = edge_edge_contact_distance(z_n, np.ones(len(z_n)))
            sided = ((at_n.region == EdgeEdgeRegion.INTERIOR) & (np.abs(at_n.d) < reach)
                     & (_edge_sine(z_n) >= MIN_EDGE_SINE) & (_edge_sine(z) >= MIN_EDGE_SINE))
            side = np.where(sided, edge_edge_side(z_n), edge_edge_side(z))
            d = edge_edge_contact_distance(z, side).d
        return d, sided

    def step(self, x_n: np.ndarray, x: np.ndarray) -> AuditStep:
        """Audit the step ``x_n -> x`` (positions ``(n, 3)``, m); the result is also kept in ``history``."""
        move = float(np.max(np.linalg.norm(x[self.vertices] - x_n[self.vertices], axis=1)))
        reach = max(self.reach, 2.5 * move)
        d_vt, s_vt = self._signed(x_n[self.vertex_triangle], x[self.vertex_triangle], "vt", reach)
        d_ee, s_ee = self._signed(x_n[self.edge_edge], x[self.edge_edge], "ee", reach)
        signed = np.concatenate([d_vt[s_vt], d_ee[s_ee]])
        both = np.concatenate([d_vt, d_ee])
        result = AuditStep(
            min_signed_distance=float(signed.min()) if signed.size else np.inf,
            min_distance=float(both.min()) if both.size else np.inf,
            active_pairs=int(np.count_nonzero(both < self.eps)),
            intersections=int(np.count_nonzero(segment_triangle_intersections(x, self.edge_triangle))),
            max_displacement=move,
        )
        self.history.append(result)
        return result

    def summary(self) -> dict:
        """Extremes over the audited steps: ``min_signed_distance``, ``min_distance`` (m),
        ``max_active_pairs``, ``intersections`` (total), ``active_steps`` (steps with a pair < eps)."""
        h = self.history
        return {
            "min_signed_distance": min(s.min_signed_distance for s in h),
            "min_distance": min(s.min_distance for s in h),
            "max_active_pairs": max(s.active_pairs for s in h),
            "intersections": sum(s.intersections for s in h),
            "active_steps": sum(s.active_pairs > 0 for s in h),
        }


MIN_EDGE_SINE = 0.1
"""Edge pairs with a smaller sine of their angle have no side in the audit (the contact set's
``min_edge_sine``)."""


def _edge_sine(z: np.ndarray) -> np.ndarray:
    """Sine of the angle between the edges of ``[a0, a1, b0, b1]`` configurations ``(k, 4, 3)``."""
    da, db = z[:, 1] - z[:, 0], z[:, 3] - z[:, 2]
    return np.linalg.norm(np.cross(da, db), axis=1) / (np.linalg.norm(da, axis=1) * np.linalg.norm(db, axis=1))


def segment_triangle_intersections(x: np.ndarray, edge_triangle: np.ndarray) -> np.ndarray:
    """Mask ``(k,)``: whether segment ``x[e0] x[e1]`` crosses triangle ``x[a] x[b] x[c]`` for rows
    ``[e0, e1, a, b, c]`` of ``edge_triangle`` (Moller & Trumbore 1997, with the segment parameter in
    [0, 1]; a segment in the triangle's plane counts as no crossing)."""
    z = x[edge_triangle]
    p, q, a, b, c = (z[:, i] for i in range(5))
    d = q - p
    e1, e2 = b - a, c - a
    h = np.cross(d, e2)
    det = np.einsum("ki,ki->k", e1, h)
    scale = np.linalg.norm(d, axis=1) * np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1)
    ok = np.abs(det) > 1e-12 * scale
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = p - a
    u = inv * np.einsum("ki,ki->k", s, h)
    qv = np.cross(s, e1)
    v = inv * np.einsum("ki,ki->k", d, qv)
    t = inv * np.einsum("ki,ki->k", e2, qv)
    return ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)
