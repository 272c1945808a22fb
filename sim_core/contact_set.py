"""The contact set of a model: which pairs are candidates, their side memory, friction, per step.

Glue between :mod:`sim_core.collision` (broad phase, distances, side memory) and the contact and
friction potentials, as the Newton solver uses them:

- :meth:`ContactSet.begin_step` takes the side memory of the state at ``x^n``;
- :meth:`ContactSet.potentials` returns the penalty potentials (vertex-triangle, edge-edge,
  vertex-plane) for the candidate pairs near an iterate ``x``; a new pair gets the side its vertex
  (edge) had at ``x^n``, a remembered pair keeps its remembered side, so a vertex that slipped
  through a triangle during an iterate is pulled back to the side it came from;
- :meth:`ContactSet.friction` freezes normal forces and tangent bases at ``x^n`` (lagged IPC friction,
  Li et al. 2020) with the Coulomb coefficient of each pair's two bodies;
- :meth:`ContactSet.end_step` stores the sides of the pairs active at the converged ``x^{n+1}``.
"""

from __future__ import annotations

import numpy as np

from sim_core.collision import (
    CollisionMemory,
    EdgeEdgeRegion,
    PointTriangleRegion,
    edge_edge_closest_points,
    point_triangle_region,
    PairFilter,
    edge_edge_candidates,
    edge_edge_side,
    point_triangle_side,
    vertex_triangle_candidates,
)
from sim_core.model import Model
from sim_core.potentials.contact import EdgeEdgeContact, PlaneContact, VertexTriangleContact, concatenate_frames
from sim_core.potentials.friction import LaggedFriction
from sim_core.potentials.sphere_contact import SphereContact


class ContactSet:
    """Per-model contact bookkeeping (see module docstring).

    Args:
        model: the model; reads surfaces, bodies, planes, contact settings and friction table.
    """

    def __init__(self, model: Model) -> None:
        self.model = model
        c = model.contact
        self.stiffness, self.eps = float(c.stiffness), float(c.eps)
        self.margin = float(c.candidate_margin)
        self.radius = self.eps + self.margin
        bodies = list(model.bodies.values())
        self.body_names = [b.name for b in bodies]
        self.body_kind = np.array([b.kind for b in bodies])
        self.vertex_body = model.body_of_vertex()
        self.triangles = np.concatenate([b.triangles for b in bodies]).astype(np.int64)
        self.edges = np.concatenate([b.edges for b in bodies]).astype(np.int64)
        self.surface_vertices = np.unique(self.triangles)
        nb = len(bodies)
        allowed = np.ones((nb, nb), dtype=bool)
        for i, b in enumerate(bodies):
            allowed[i, i] = b.kind == "sheet" and c.self_contact
            for j, o in enumerate(bodies):
                if b.kind == "frozen" and o.kind == "frozen":
                    allowed[i, j] = False
        self.filter = PairFilter(
            vertex_body=self.vertex_body, body_pair_allowed=allowed, x_rest=model.x_rest,
            self_rest_distance=max(2.0 * self.radius, 0.0),
        )
        movable = np.concatenate([b.vertices for b in bodies if b.kind != "frozen"] or [np.zeros(0, np.int64)])
        movable = np.intersect1d(movable, np.concatenate([self.surface_vertices, _sheet_vertices(model)]))
        self.planes = [
            (name, PlaneContact(movable, p.normal, p.offset, self.stiffness, self.eps))
            for name, p in model.planes.items()
        ]
        self.spheres = [
            (b.name, SphereContact(movable, b.vertex_start, b.material["radius"], self.stiffness, self.eps))
            for b in bodies if b.kind == "sphere"
        ]
        self.x_prev: np.ndarray | None = None
        self._cache = None  # (memory, candidates, potentials, sides) of the current step
        self._candidates = None  # (x at the search, vt pairs, ee pairs): positions only, kept across steps
        self.min_edge_sine = 0.1

    # ------------------------------------------------------------------ per step
    def begin_step(self, x_n: np.ndarray, memory: CollisionMemory | None) -> CollisionMemory:
        """Start a step at ``x^n`` with the state's side memory (a fresh one when None)."""
        self.x_prev = np.asarray(x_n, dtype=float)
        self._cache = None
        return memory.copy() if memory is not None else CollisionMemory()

    def _pairs(self, x: np.ndarray, memory: CollisionMemory) -> tuple[VertexTriangleContact, EdgeEdgeContact]:
        """Contact potentials over the candidate pairs valid at ``x``.

        Candidates are searched with radius ``eps + margin`` and reused while no vertex has moved
        more than ``margin / 2`` since the search: two elements then cannot have closed a gap larger
        than ``margin``, so no pair outside the list can have come within ``eps``. The search
        depends on positions only, so it is also reused across steps (the converged positions of
        a step are the next step's ``x^n``); the sides and the near-parallel edge filter, which
        depend on the step's memory and ``x^n``, are redone per step.
        """
        candidates = self._candidate_pairs(x)
        cache = getattr(self, "_cache", None)
        if cache is not None and cache[0] is memory and cache[1] is candidates:
            vt, ee = cache[2]
            vt_sides, ee_sides = cache[3]
            pots = self._vertex_triangle(x, vt.pairs, vt_sides), self._edge_edge(x, ee.pairs, ee_sides)
        else:
            pots, remembered = self._search(x, memory, candidates)
            self._cache = (memory, candidates, pots, remembered)
        # the previous iterate's potentials were last evaluated at the accepted line-search point,
        # usually this x: reuse that evaluation where the pairs and sides are unchanged
        for new, old in zip(pots, getattr(self, "_last_pots", ())):
            new.inherit_evaluation(old)
        self._last_pots = pots
        return pots

    def _candidate_pairs(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(x at the search, vertex-triangle pairs, edge-edge pairs)`` valid at ``x`` (see :meth:`_pairs`)."""
        found = self._candidates
        if found is not None and found[0].shape == x.shape:
            moved = float(np.max(np.abs(x - found[0]))) if x.size else 0.0
            if moved <= 0.5 * self.margin:
                return found
        vt = vertex_triangle_candidates(x, self.surface_vertices, self.triangles, self.radius, self.filter)
        if len(vt) and not self.model.contact.sheet_vertices_vs_solids:
            kv = self.body_kind[self.vertex_body[vt[:, 0]]]
            kt = self.body_kind[self.vertex_body[self.triangles[vt[:, 1], 0]]]
            vt = vt[~((kv == "sheet") & (kt == "solid"))]
        ee = edge_edge_candidates(x, self.edges, self.radius, self.filter)
        self._candidates = (np.array(x, dtype=float, copy=True), vt, ee)
        return self._candidates

    def _vertex_triangle(self, x: np.ndarray, vt: np.ndarray, remembered: np.ndarray) -> VertexTriangleContact:
        """Vertex-triangle penalty over pairs ``vt`` with the side memory applied in the face region.

        A pair whose vertex projects inside its triangle (face region) keeps its remembered side
        (``remembered``, +1/-1: from the state's memory, else the side at x^n), so a vertex that
        slipped through is pulled back. Outside the face region the distance is unsigned and the
        side is taken from the current geometry: remembering it there made a penetrated vertex
        that slides into the face region jump from +delta to -delta, an energy discontinuity the
        line search cannot cross (a vertex wrapping round a sheet's free edge is legitimate).
        """
        if not len(vt):
            return VertexTriangleContact(vt, self.triangles, np.zeros(0), self.stiffness, self.eps)
        tri = self.triangles[vt[:, 1]]
        p, a, b, c = x[vt[:, 0]], x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]]
        region = point_triangle_region(p, a, b, c)
        z = np.concatenate([p[:, None], a[:, None], b[:, None], c[:, None]], axis=1)
        sides = np.where(region == PointTriangleRegion.FACE, remembered, point_triangle_side(z))
        return VertexTriangleContact(vt, self.triangles, sides, self.stiffness, self.eps)

    def _edge_edge(self, x: np.ndarray, ee: np.ndarray, remembered: np.ndarray) -> EdgeEdgeContact:
        """Edge-edge penalty over pairs ``ee`` with the side memory applied in the interior region.

        As for vertex-triangle pairs: a pair whose closest points are interior to both segments
        keeps its remembered side (``remembered``, +1/-1: from the state's memory, else the side at
        x^n), so edges that crossed are pushed back apart. Elsewhere the distance is unsigned and
        the side comes from the current geometry: remembering it there made a pair whose closest
        points enter the segments' interior from outside jump from +delta to -delta.
        """
        if not len(ee):
            return EdgeEdgeContact(ee, self.edges, np.zeros(0), self.stiffness, self.eps)
        z_now = np.concatenate([x[self.edges[ee[:, 0]]], x[self.edges[ee[:, 1]]]], axis=1)
        _, _, region = edge_edge_closest_points(z_now[:, 0], z_now[:, 1], z_now[:, 2], z_now[:, 3])
        sides = np.where(region == EdgeEdgeRegion.INTERIOR, remembered, edge_edge_side(z_now))
        return EdgeEdgeContact(ee, self.edges, sides, self.stiffness, self.eps)

    def _search(self, x: np.ndarray, memory: CollisionMemory, candidates: tuple) -> tuple[tuple, np.ndarray]:
        x_ref = self.x_prev if self.x_prev is not None else x
        _, vt, ee = candidates
        z = np.concatenate([x_ref[vt[:, :1]], x_ref[self.triangles[vt[:, 1]]]], axis=1) if len(vt) else np.zeros((0, 4, 3))
        vt_sides = memory.vertex_triangle.resolve(vt, point_triangle_side(z) if len(vt) else np.zeros(0))
        z = (np.concatenate([x_ref[self.edges[ee[:, 0]]], x_ref[self.edges[ee[:, 1]]]], axis=1)
             if len(ee) else np.zeros((0, 4, 3)))
        if len(ee):
            # Near-parallel edge pairs have no well-defined side (the cross product of their
            # directions vanishes) and switch distance definitions as they rotate; their contact
            # is carried by the vertex-triangle pairs of the same configuration, so they are left
            # out (decided at x^n, so the set is fixed within the step).
            da = x_ref[self.edges[ee[:, 0], 1]] - x_ref[self.edges[ee[:, 0], 0]]
            db = x_ref[self.edges[ee[:, 1], 1]] - x_ref[self.edges[ee[:, 1], 0]]
            sin = np.linalg.norm(np.cross(da, db), axis=1) / (np.linalg.norm(da, axis=1) * np.linalg.norm(db, axis=1))
            keep = sin > self.min_edge_sine
            ee, z = ee[keep], z[keep]
        ee_sides = memory.edge_edge.resolve(ee, edge_edge_side(z) if len(ee) else np.zeros(0))
        return ((self._vertex_triangle(x, vt, vt_sides), self._edge_edge(x, ee, ee_sides)),
                (vt_sides, ee_sides))

    def potentials(self, x: np.ndarray, x_n: np.ndarray, memory: CollisionMemory) -> list:
        """Contact potentials for the candidates near iterate ``x`` (planes and spheres included)."""
        vt, ee = self._pairs(x, memory)
        return [vt, ee] + [p for _, p in self.planes] + [p for _, p in self.spheres]

    def friction(self, x_n: np.ndarray, dt: float, memory: CollisionMemory) -> LaggedFriction | None:
        """Lagged friction of the pairs active at ``x^n`` (None when nothing touches or mu = 0)."""
        vt, ee = self._pairs(x_n, memory)
        frames, mus = [], []
        for pot, first, second in (
            (vt, vt.pairs[:, 0], self.triangles[vt.pairs[:, 1], 0]),
            (ee, self.edges[ee.pairs[:, 0], 0], self.edges[ee.pairs[:, 1], 0]),
        ):
            f = pot.contact_frames(x_n)
            if len(f.lam):
                frames.append(f)
                mus.append(self._mu(first[f.pair_index], second[f.pair_index]))
        for name, obstacle in self.planes + self.spheres:
            f = obstacle.contact_frames(x_n)
            if len(f.lam):
                frames.append(f)
                bodies = self.vertex_body[obstacle.vertices[f.pair_index]]
                mus.append(np.array([self.model.friction_coefficient(self.body_names[b], name) for b in bodies]))
        if not frames:
            return None
        mu = np.concatenate(mus)
        if not np.any(mu > 0):
            return None
        all_frames = concatenate_frames(frames)
        return LaggedFriction.from_frames(all_frames, mu, x_n, self.model.contact.eps_v, dt)

    def _mu(self, vertex_a: np.ndarray, vertex_b: np.ndarray) -> np.ndarray:
        ba, bb = self.vertex_body[vertex_a], self.vertex_body[vertex_b]
        table = np.zeros((len(self.body_names), len(self.body_names)))
        for i, a in enumerate(self.body_names):
            for j, b in enumerate(self.body_names):
                table[i, j] = self.model.friction_coefficient(a, b)
        return table[ba, bb]

    def end_step(self, x: np.ndarray, memory: CollisionMemory) -> CollisionMemory:
        """Remember the sides of the pairs active at the converged positions ``x``."""
        vt, ee = self._pairs(x, memory)
        out = memory.copy()
        act = vt.active_mask(x) if len(vt.pairs) else np.zeros(0, bool)
        out.vertex_triangle.update(vt.pairs[act], vt.sides[act])
        act = ee.active_mask(x) if len(ee.pairs) else np.zeros(0, bool)
        out.edge_edge.update(ee.pairs[act], ee.sides[act])
        return out


def _sheet_vertices(model: Model) -> np.ndarray:
    parts = [b.vertices for b in model.bodies.values() if b.kind == "sheet"]
    return np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)
