"""The contact set of a model: which pairs are candidates, their side memory, friction, per step.

Glue between :mod:`sim_core.collision` (broad phase, distances, side memory) and the contact and
friction potentials, as the Newton solver uses them:

- :meth:`ContactSet.begin_step` takes the side memory of the state at ``x^n``;
- :meth:`ContactSet.potentials` returns the penalty potentials (vertex-triangle, edge-edge,
  vertex-plane) for the candidate pairs near an iterate ``x``, with sides fixed for the whole
  step (:func:`step_sides`): a pair above the face (interior) at ``x^n`` keeps its
  remembered side, or takes its side at ``x^n``, so a vertex that slipped through a triangle during
  an iterate is pulled back to the side it came from; any other pair is unsigned;
- :meth:`ContactSet.friction` freezes normal forces and tangent bases at ``x^n`` (lagged IPC friction,
  Li et al. 2020) with the Coulomb coefficient of each pair's two bodies, and records where its rows
  come from (:class:`FrictionRowSource`, for the adjoint);
- :meth:`ContactSet.release_stale_sides` drops, for the rest of the step, the side of a pair that
  has gone round its partner (beside the face / beyond an edge's end with the other geometric
  side): the solver calls it when its line search finds no decrease;
- :meth:`ContactSet.end_step` stores the sides of the pairs active above the face (interior) at the
  converged ``x^{n+1}``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from sim_core.array_pool import ArrayPool
from sim_core.backend import uses_taichi
from sim_core.collision import (CollisionMemory, PairFilter, edge_edge_candidates,
                                vertex_triangle_candidates)
from sim_core.collision.candidates import grouped_box_pairs_hash
from sim_core.collision.pair_geometry import ListGeometry, PairGeometry, pair_geometry
from sim_core.collision.rest_exclusion import RestExclusion
from sim_core.collision.step_sides import step_sides
from sim_core.coulomb_coefficients import CoulombCoefficients
from sim_core.energies.base import FrozenPositionsKey, PenaltyContact, declares
from sim_core.energies.contact.pair_lists import CandidateVertices, lookup_pairs, sheet_vertices_off_solids
from sim_core.energies.contact.reference import (ContactFrames, EdgeEdgeContact, ListRows, PlaneContact,
                                                 VertexTriangleContact,
                                                 concatenate_frames, edge_edge_vertices, vertex_triangle_vertices)
from sim_core.energies.friction.reference import LaggedFriction, smooth_friction_f0
from sim_core.energies.sphere_contact.reference import SphereContact
from sim_core.model import Model, check_broad_phase
from sim_core.unique import sorted_unique
from sim_core.workspace import Workspace


class FrictionRowSource(NamedTuple):
    """Where a run of consecutive rows of a :class:`LaggedFriction` built by :meth:`ContactSet.friction`
    comes from (kept as ``LaggedFriction.row_sources``, in row order, so that the adjoint
    differentiates the frozen frames without searching the pairs again).

    Attributes:
        obstacle: the plane / sphere body name, None for vertex-triangle and edge-edge pairs.
        potential: the step's contact potential of the rows (``VertexTriangleContact``,
            ``EdgeEdgeContact``, ``PlaneContact`` or ``SphereContact``; its sides fixed for the step).
        pair_index: the rows' pair (vertex) indices in ``potential``, int64 shape ``(r,)``.
    """

    obstacle: str | None
    potential: object
    pair_index: np.ndarray


class ContactSet:
    """Per-model contact bookkeeping (see module docstring).

    Args:
        model: the model; reads surfaces, bodies, planes, contact settings and friction table.
        broad_phase: the box-pair search (``spatial_hash``, ``sweep`` or ``kdtree``: same candidate
            lists, see :class:`sim_core.model.ContactSettings`); None takes ``model.contact.broad_phase``.
        backend: the solver's concrete backend (:data:`sim_core.backend.BACKENDS`; ``NewtonSolver.backend``):
            the Taichi contact, friction and broad-phase kernels on ``taichi-cpu`` / ``taichi-cuda``
            (Taichi initialised for it), the NumPy reference on ``numpy``.
        workspace: where the contact and friction potentials keep their evaluations
            (:mod:`sim_core.workspace`; the solver's), or None for one of this contact set's own.

    Attributes:
        taichi: whether this contact set runs the Taichi kernels (``backend`` is a Taichi one).

    Raises:
        ConfigError: an unknown ``broad_phase`` or ``backend``.
    """

    device_sides: bool | None = None
    """On a Taichi backend, the candidate lists' geometry as one int8 code a pair kept where it was measured
    (:func:`~sim_core.energies.contact.sides_kernel.side_codes`) and the step sides placed from it by a launch whose
    sides the pair batch reads where they are (:meth:`_device_pair_sides`), instead of int32 codes decoded on the host
    and the sides sent with every new batch; None: on CUDA. The same sides."""

    def __init__(self, model: Model, broad_phase: str | None = None, backend: str = "numpy",
                 workspace: Workspace | None = None) -> None:
        self.model = model
        self.workspace = Workspace() if workspace is None else workspace
        self.taichi = uses_taichi(backend)
        c = model.contact
        self.broad_phase = check_broad_phase(c.broad_phase if broad_phase is None else broad_phase,
                                             "ContactSet broad_phase")
        self.stiffness, self.eps = float(c.stiffness), float(c.eps)
        self.margin = float(c.candidate_margin)
        self.radius = self.eps + self.margin
        bodies = list(model.bodies.values())
        self.body_names = [b.name for b in bodies]
        self.body_kind = np.array([b.kind for b in bodies])
        self.vertex_body = model.body_of_vertex()
        self._sheet_vertex = (self.body_kind == "sheet")[self.vertex_body]  # the sheet-vs-solid filter's tables
        self.coulomb = CoulombCoefficients(model, self.body_names, self.vertex_body)  # the pairs' Coulomb mu
        self.triangles = np.concatenate([b.triangles for b in bodies]).astype(np.int64)
        self.edges = np.concatenate([b.edges for b in bodies]).astype(np.int64)
        self.surface_vertices = sorted_unique(self.triangles.ravel())
        self._solid_triangle = (self.body_kind == "solid")[self.vertex_body[self.triangles[:, 0]]]
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
        # covers(): the bodies' vertex segments (non-empty bodies in vertex order; each segment runs to
        # the next start, which only widens a body's range) and the body pairs that may collide
        order = [i for i in np.argsort([b.vertex_start for b in bodies], kind="stable")
                 if bodies[i].vertex_stop > bodies[i].vertex_start]
        self._segment_starts = np.array([bodies[i].vertex_start for i in order], dtype=np.int64)
        self._segment_pairs = allowed[np.ix_(order, order)]
        # the rest-distance exclusion never changes: its close pairs, found once
        self.rest_exclusion = RestExclusion(self.filter, self.surface_vertices, self.triangles, self.edges)
        movable = np.concatenate([b.vertices for b in bodies if b.kind != "frozen"] or [np.zeros(0, np.int64)])
        movable = np.intersect1d(sorted_unique(movable), sorted_unique(np.concatenate([self.surface_vertices,
                                                                                     _sheet_vertices(model)])),
                                 assume_unique=True)
        self.planes = [
            (name, PlaneContact(movable, p.normal, p.offset, self.stiffness, self.eps))
            for name, p in model.planes.items()
        ]
        self.spheres = [
            (b.name, SphereContact(movable, b.vertex_start, b.material["radius"], self.stiffness, self.eps))
            for b in bodies if b.kind == "sphere"
        ]
        self.x_prev: np.ndarray | None = None
        self.held_friction_energy = 0.0  # J, of the obstacle rows friction() left out for held vertices
        # vertices held for the step (sleeping bodies, sim_core.sleeping; set by the solver), or None
        self.held: np.ndarray | None = None
        self._held_kept = None  # (candidates, held, candidates without the held pairs apart)
        self._cache = None  # (memory, candidates, potentials, edge-edge candidate rows kept) of the current step
        self._released = _NO_RELEASES  # sorted pair keys (vt, ee) unsigned for the step (release_stale_sides)
        self._candidates = None  # (x at the search, vt pairs, ee pairs): positions only, kept across steps
        self._covered = None  # (x at the search, x, covers' answer) of the last covers() of two frozen arrays
        self._pool = ArrayPool()  # the lists' vertex arrays, reused once no list, potential or cache holds them
        self.min_edge_sine = 0.1
        self._sides_device = None  # (the host sides' array, its device copy or None) of the last _device_pair_sides
        self._rows_device = None  # (the edge-edge rows kept, their KeptRows) of the last _device_pair_sides on CUDA
        # searches look ahead along the step's motion (see _search_position)
        self.lookahead = 0.5
        self.lookahead_cap = 0.25

    # ------------------------------------------------------------------ per step
    def begin_step(self, x_n: np.ndarray, memory: CollisionMemory | None) -> CollisionMemory:
        """Start a step at ``x^n`` with the state's side memory (a fresh one when None)."""
        self.x_prev = np.asarray(x_n, dtype=float)
        self._cache = None
        self._step_table = None  # (memory, x^n, vt pairs, ee pairs, (vt sides, ee rows kept, ee sides)) of the last search
        self._released = _NO_RELEASES
        return memory.copy() if memory is not None else CollisionMemory()

    def _pairs(self, x: np.ndarray, memory: CollisionMemory, x_device=None, segment_start: np.ndarray | None = None
               ) -> tuple[VertexTriangleContact, EdgeEdgeContact]:
        """Contact potentials over the candidate pairs valid at ``x``.

        Candidates are searched with radius ``eps + margin`` and reused while no two elements that
        may collide can have closed a gap by more than ``margin`` since the search (:meth:`covers`),
        so no pair outside the list can have come within ``eps``. The search
        depends on positions only, so it is also reused across steps (the converged positions of
        a step are the next step's ``x^n``); the sides and the near-parallel edge filter, which
        depend on the step's memory and ``x^n``, are redone per step. The search is done at a point
        a little ahead of ``x`` along the step's motion (:meth:`_search_position`), so that it
        usually covers the next step's first iterates too (and, for a line search's trial point, its
        segment's first halving where one search can: ``segment_start``, :meth:`_search_position`).
        """
        candidates = self._without_held_pairs(self._candidate_pairs(x, x_device, segment_start), x, memory)
        cache = getattr(self, "_cache", None)
        if cache is not None and cache[0] is memory and cache[1] is candidates:
            # the step's potentials over these candidates (same pairs, sides and class): reused, not
            # rebuilt; their kept evaluation is matched against x on use
            pots = cache[2]
        else:
            pots, ee_rows = self._search(x, memory, candidates)
            self._cache = (memory, candidates, pots, ee_rows)
        # the previous iterate's potentials were last evaluated at the accepted line-search point,
        # usually this x: reuse that evaluation where the pairs and sides are unchanged
        for new, old in zip(pots, getattr(self, "_last_pots", ())):
            if new is not old:
                new.inherit_evaluation(old)
        self._last_pots = pots
        return pots

    @property
    def search_position(self) -> np.ndarray | None:
        """Positions ``(n, 3)`` (m) of the last broad-phase search (None before the first one)."""
        return None if self._candidates is None else self._candidates[0]

    def covers(self, x_search: np.ndarray | None, x: np.ndarray, x_device=None) -> bool:
        """Whether candidates searched at ``x_search`` still hold every pair within ``eps`` at ``x``.

        The search lists the element pairs whose bounding boxes come within ``eps + margin`` on
        every axis (:mod:`sim_core.collision.candidates`), so a pair left out had, on some axis,
        a gap above ``eps + margin``. With the displacements ``u = x - x_search``, that gap between
        an element of body A and one of body B has closed by at most
        ``c_k(A, B) = max(max_A u_k - min_B u_k, max_B u_k - min_A u_k)`` on axis ``k`` (for A = B,
        the spread of A's displacements). The list covers ``x`` when ``c_k(A, B) <= margin`` for
        every axis and every body pair that may collide: the gap is then still above ``eps``. No
        vertex moving more than ``margin / 2`` is the special case tested first (cheap); the general
        test also covers bodies moving together (a sheet carried along by the gel or translated
        with its contact partner: Forming 51 -> 41 searches per 49 steps, the same states bit for
        bit). The Newton line search evaluates trial points with the iterate's contact potentials
        only while this holds; beyond it a pair missing from the list would make the trial energy
        too low (a penetration the line search cannot see), and Newton then cycles between iterates.

        The answer for two frozen arrays (read-only arrays that own their memory, as the search positions and
        the lockstep solver's iterates are: :func:`~sim_core.energies.base.positions_key`) is kept for the
        next call with the same two objects (a Newton iterate's gradient and energy ask twice: half of the
        calls of a lockstep batch, each reading all copies' positions).

        With ``x_device`` (on a Taichi backend) the displacements are bounded where that array is
        (:class:`~sim_core.ti_kernels.displacement_bounds.DisplacementBounds`: two launches, one small array read
        back, the search positions sent once per search) instead of reading ``x`` on the host; the same answer.

        Args:
            x_search: positions of the search ``(n, 3)`` (m) or None (no search yet: False).
            x: positions ``(n, 3)`` (m); NaN gives False.
            x_device: ``x`` as a float64 Taichi ndarray ``(n, 3)`` (m; device memory on CUDA), or None (the host's
                ``x`` is read). Ignored off the Taichi backends.

        Raises:
            ValueError: ``x_device`` not of ``x``'s shape.
        """
        if x_search is None or x_search.shape != x.shape:
            return False
        if x.size == 0:
            return True
        kept = self._covered
        if kept is not None and kept[0] is x_search and kept[1] is x:
            return kept[2]
        if x_device is not None and self.taichi:
            high, low, largest = self._displacement_bounds(x_search, x_device)
            answer = bool(largest <= 0.5 * self.margin) or self._closing_holds(high, low)
        else:
            answer = self._moved_holds(x - x_search)
        if _frozen(x_search) and _frozen(x):
            self._covered = (x_search, x, answer)
        return answer

    def _moved_holds(self, moved: np.ndarray) -> bool:
        """:meth:`covers`' test on the host from the displacements ``moved`` ``(n, 3)`` (m) since the search: no
        ``|moved|`` above ``margin / 2`` (no ``|moved|`` array), else :meth:`_gaps_hold` (NaN: False)."""
        return bool(np.maximum(moved.max(), -moved.min()) <= 0.5 * self.margin) or self._gaps_hold(moved)

    def _gaps_hold(self, moved: np.ndarray) -> bool:
        """:meth:`covers`' general test: ``c_k(A, B) <= margin`` for every axis and allowed body pair,
        with the displacements ``moved`` ``(n, 3)`` (m) since the search (NaN: False)."""
        starts = self._segment_starts
        if starts.size == 0:
            return True
        high = np.maximum.reduceat(moved, starts, axis=0)  # (bodies, 3): per body and axis
        return self._closing_holds(high, np.minimum.reduceat(moved, starts, axis=0))

    def _closing_holds(self, high: np.ndarray, low: np.ndarray) -> bool:
        """:meth:`_gaps_hold` from the largest and smallest displacements ``(bodies, 3)`` (m) per body segment and
        axis (NaN: False)."""
        if high.size == 0:
            return True
        # [A, B]: A's top moving up to B's bottom; the allowed pairs are symmetric, so [B, A] is read too
        closing = np.max(high[:, None, :] - low[None, :, :], axis=2)
        pairs = self._segment_pairs
        return bool(not pairs.any() or np.max(closing[pairs]) <= self.margin)  # NaN: False

    def _displacement_bounds(self, x_search: np.ndarray, x_device) -> tuple[np.ndarray, np.ndarray, float]:
        """``(high, low, largest)`` of ``x_device - x_search`` per body segment (:meth:`covers`), on the device."""
        bounds = getattr(self, "_bounds", None)
        if bounds is None or bounds.n != len(x_search):
            # optional heavy dependency: Taichi, loaded on a Taichi backend only
            from sim_core.ti_kernels.displacement_bounds import DisplacementBounds

            bounds = self._bounds = DisplacementBounds(len(x_search), self._segment_starts)
        return bounds(x_search, x_device, kept=_frozen(x_search))

    def _candidate_pairs(self, x: np.ndarray, x_device=None, segment_start: np.ndarray | None = None
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(x at the search, vertex-triangle pairs, edge-edge pairs)`` valid at ``x`` (see :meth:`_pairs`;
        ``x_device``: :meth:`covers`'; ``segment_start``: :meth:`_search_position`'). The lists' packed keys, where
        the hash search's sort made them, are kept with them for their :class:`CandidateVertices`
        (:meth:`_list_vertices`)."""
        found = self._candidates
        if found is not None and self.covers(found[0], x, x_device):
            return found
        x_search = self._search_position(x, segment_start)
        search = self._grouped_search()
        rest = self.rest_exclusion if self.rest_exclusion.pair_filter is self.filter else None
        lists = self._candidate_lists(search) if rest is not None else None
        keys = [None, None]  # the lists' packed keys when the search's sort made them (CandidateVertices.keys)
        device_vertices = None  # their int32 vertices where the search's sort left the keys (on CUDA)
        if lists is not None:  # the exclusions and the sheet-vs-solid filter inside the hash / sweep kernel, same lists
            vt, ee = lists.vertex_triangle(x_search, self.radius), lists.edge_edge(x_search, self.radius)
            keys_of = getattr(lists, "keys_of", None)
            if keys_of is not None:
                keys = [keys_of(vt), keys_of(ee)]
                device_vertices = lists.device_vertices(vt, ee)
        else:
            vt = vertex_triangle_candidates(x_search, self.surface_vertices, self.triangles, self.radius,
                                            self.filter, grouped_search=search, rest_exclusion=rest)
            ee = edge_edge_candidates(x_search, self.edges, self.radius, self.filter, grouped_search=search,
                                      rest_exclusion=rest)
            if len(vt) and not self.model.contact.sheet_vertices_vs_solids:
                vt, keys[0] = sheet_vertices_off_solids(vt, keys[0], self._sheet_vertex, self._solid_triangle)
        self._candidates = (x_search, vt, ee)
        self._list_keys = (vt, ee, tuple(keys), device_vertices)
        return self._candidates

    def _without_held_pairs(self, candidates: tuple, x: np.ndarray, memory: CollisionMemory) -> tuple:
        """``candidates`` ``(x at the search, vertex-triangle pairs, edge-edge pairs)`` without the pairs
        whose four vertices are all :attr:`held` (sleeping bodies) and that are apart at ``x`` (unsigned
        distance >= eps, the held vertices' positions all step) and not remembered in ``memory``: such a
        pair has no energy, force or Hessian entry all step, and no memory to keep. The lists are kept
        while the candidates and the held mask are the same objects (a held pair stays apart and
        unremembered while held). ``candidates`` itself when nothing is held."""
        held = self.held
        if held is None:
            return candidates
        kept = self._held_kept
        if kept is not None and kept[0] is candidates and kept[1] is held:
            return kept[2]
        x_search, vt, ee = candidates
        out = []
        # a pair's four vertices all held: its two elements' (a vertex, a triangle or an edge wholly held), two lookups
        # a pair in element tables instead of a gather of every pair's vertices
        held_triangle, held_edge = held[self.triangles].all(axis=1), held[self.edges].all(axis=1)
        for pairs, first, second, kind, remembered in (
                (vt, held, held_triangle, VertexTriangleContact, memory.vertex_triangle),
                (ee, held_edge, held_edge, EdgeEdgeContact, memory.edge_edge)):
            rows = np.flatnonzero(np.take(first, pairs[:, 0]) & np.take(second, pairs[:, 1])) if len(pairs) \
                else np.zeros(0, dtype=np.int64)
            if not len(rows):
                out.append(pairs)
                continue
            elements = self.triangles if kind is VertexTriangleContact else self.edges
            apart = ~kind(pairs[rows], elements, np.zeros(len(rows)), self.stiffness, self.eps).active_mask(x)
            drop = rows[apart & ~remembered.lookup(pairs[rows])[1]]
            keep = np.ones(len(pairs), dtype=bool)
            keep[drop] = False
            out.append(pairs[keep])
        filtered = (x_search, out[0], out[1])
        self._held_kept = (candidates, held, filtered)
        return filtered

    def _candidate_lists(self, search):
        """On the Taichi backend, the candidate lists of this contact set's elements with the
        exclusions in the kernel (made on first use): :class:`sim_core.ti_kernels.hash_candidates.HashCandidates`
        (``spatial_hash``) or :class:`sim_core.ti_kernels.sweep_candidates.SweepCandidates` on
        ``search`` (``sweep``); None otherwise (NumPy backend, ``kdtree``). The vertex-triangle search takes
        :meth:`_vertex_triangle_bodies` (a sheet's vertices off the solids' triangles in the kernel: the lists of
        :func:`~sim_core.energies.contact.pair_lists.sheet_vertices_off_solids`, no host pass)."""
        if not self.taichi or self.broad_phase == "kdtree":
            return None
        lists = getattr(self, "_lists", None)
        if self.broad_phase == "spatial_hash":
            if lists is None or lists[0] != "spatial_hash":
                # optional heavy dependency: Taichi, loaded on a Taichi backend only
                from sim_core.ti_kernels.hash_candidates import HashCandidates

                self._lists = ("spatial_hash", HashCandidates(self.surface_vertices, self.triangles, self.edges,
                                                              self.filter, self.rest_exclusion,
                                                              self._vertex_triangle_bodies()))
        elif lists is None or lists[0] != "sweep" or lists[1].search is not search:
            # optional heavy dependency: Taichi, loaded on a Taichi backend only
            from sim_core.ti_kernels.sweep_candidates import SweepCandidates

            self._lists = ("sweep", SweepCandidates(self.surface_vertices, self.triangles, self.edges, self.filter,
                                                    self.rest_exclusion, search, self._vertex_triangle_bodies()))
        found = self._lists[1]
        found.vt_allowed = self._vertex_triangle_bodies()  # (the setting may have changed since: the same table if not)
        return found

    def _vertex_triangle_bodies(self) -> np.ndarray:
        """The vertex-triangle search's body table ``(bodies, bodies)``, ``[vertex's body, triangle's body]``:
        the filter's, without a sheet's vertices against a solid's triangles unless
        :class:`~sim_core.model.ContactSettings` ``sheet_vertices_vs_solids`` (the pairs
        :func:`~sim_core.energies.contact.pair_lists.sheet_vertices_off_solids` leaves out: a triangle's body is its
        first vertex's, as there), as C-contiguous int32; kept per value of the setting (the same array while it
        holds: the kernels' device copy is sent once)."""
        on = bool(self.model.contact.sheet_vertices_vs_solids)
        kept = getattr(self, "_vt_bodies", None)
        if kept is None or kept[0] != on:
            allowed = np.array(self.filter.body_pair_allowed, dtype=bool)
            if not on:
                allowed &= ~np.outer(self.body_kind == "sheet", self.body_kind == "solid")
            kept = self._vt_bodies = (on, np.ascontiguousarray(allowed, dtype=np.int32))
        return kept[1]

    def _search_position(self, x: np.ndarray, segment_start: np.ndarray | None = None) -> np.ndarray:
        """Where to search for the candidates of ``x`` ``(n, 3)`` (m): a new array
        ``x + clip(lookahead * (x - x^n), -c, c)`` per coordinate, ``c = lookahead_cap * margin``
        (:meth:`_ahead_of`).

        Any search position whose list covers ``x`` is exact (:meth:`covers` is checked at every
        evaluated point, and a point it refuses is searched again), so the position only decides
        how often a search is needed. A search is needed when the iterates have moved so far from
        the last one that a gap may have closed by ``margin`` (a sheet's own spread of motion, or a
        body against another), typically at the first trial point of a step (Forming: 0.6 mm of
        sheet motion per step against a margin of 1 mm). The rest of the step stays near that
        point and the next step moves on in about the same direction, so searching half the step's
        motion so far ahead (at most ``margin / 4`` per coordinate, leaving ``margin / 4`` for the
        rest of this step) lets one search serve the next step's first iterates too (Forming: 1.18
        -> 1.04 searches per step with the ``margin / 2`` test alone). ``x`` itself is always
        covered (``lookahead_cap <= 0.5``); with no step started (``x^n`` unknown) or
        ``lookahead = 0`` the search is at ``x``. The array is read-only (:attr:`search_position`).

        ``segment_start`` ``(n, 3)`` (m): where the line search that evaluates ``x`` started, or None. Its
        trial points lie on the segment from there to ``x`` (a backtrack halves the step), so where that position
        does not cover the segment's first halving ``h = (segment_start + x) / 2`` (:meth:`covers`; then the
        whole segment from ``h`` to ``x``, the test being convex along it), the search is made ahead of the point
        ``3/4`` of the way instead, if its list covers ``x``: one search then serves a backtracked trial too, where
        the position ahead of ``x`` would need a second one. The states are those of any other covering position
        bit for bit: a listed pair beyond ``eps`` adds exact zeros.
        """
        x = np.asarray(x, dtype=float)
        ahead = self._ahead_of(x)
        if segment_start is None or segment_start.shape != x.shape or x.size == 0:
            return ahead
        # h and its displacement from the search in two kept blocks of the pool (fresh memory costs page faults)
        half = self._pool.empty("segment_point", x.shape, np.float64)
        np.add(segment_start, x, out=half)
        half *= 0.5
        if self._moved_holds(np.subtract(half, ahead, out=self._pool.empty("segment_moved", x.shape, np.float64))):
            return ahead
        half += x  # the point 3/4 of the way, in the same block
        half *= 0.5
        between = self._ahead_of(half)
        return between if self.covers(between, x) else ahead

    def _ahead_of(self, x: np.ndarray) -> np.ndarray:
        """:meth:`_search_position` of ``x`` ``(n, 3)`` float64 (m) alone: a new read-only array."""
        if not (0.0 <= self.lookahead_cap <= 0.5):
            raise ValueError(f"ContactSet: lookahead_cap must be in [0, 0.5], got {self.lookahead_cap}")
        if self.x_prev is not None and self.x_prev.shape == x.shape and self.lookahead != 0.0:
            cap = self.lookahead_cap * self.margin
            ahead = np.subtract(x, self.x_prev)  # in place from here: one new array of the stacked positions
            ahead *= self.lookahead
            np.clip(ahead, -cap, cap, out=ahead)
            ahead += x
            x = ahead
        else:
            x = np.array(x, dtype=float, copy=True)
        x.flags.writeable = False  # frozen: covers() keeps its answers for it
        return x

    def _grouped_search(self):
        """The box-pair search of the broad phase (``self.broad_phase``; all give the same pairs):
        ``spatial_hash``: the Taichi hash kernel (:class:`sim_core.ti_kernels.hash_grid.HashSearch`)
        on a Taichi backend (:attr:`taichi`), else NumPy spatial hashes per body pair
        (:func:`sim_core.collision.candidates.grouped_box_pairs_hash`); ``sweep``: the Taichi sweep
        kernel (:class:`sim_core.ti_kernels.broad_phase.SweepSearch`, keeping its sweep axis across this
        contact set's searches) on the Taichi backend; else, and for ``kdtree``, None (the k-d trees of
        :mod:`sim_core.collision.candidates`)."""
        if self.broad_phase == "spatial_hash":
            if not self.taichi:
                return grouped_box_pairs_hash
            if getattr(self, "_hash_search", None) is None:
                # optional heavy dependency: Taichi, loaded on a Taichi backend only
                from sim_core.ti_kernels.hash_grid import HashSearch

                self._hash_search = HashSearch()
            return self._hash_search
        if self.broad_phase == "sweep" and self.taichi:
            if getattr(self, "_sweep_search", None) is None:
                # optional heavy dependency: Taichi, loaded on a Taichi backend only
                from sim_core.ti_kernels.broad_phase import SweepSearch

                self._sweep_search = SweepSearch()
            return self._sweep_search
        return None

    def _pair_classes(self) -> tuple[type, type]:
        """The vertex-triangle and edge-edge potential classes: the Taichi distance kernels
        (:mod:`sim_core.energies.contact.kernel`) on a Taichi backend (:attr:`taichi`), else the NumPy reference."""
        if self.taichi:
            # optional heavy dependency: Taichi, loaded on a Taichi backend only
            from sim_core.energies.contact.kernel import TiEdgeEdgeContact, TiVertexTriangleContact

            return TiVertexTriangleContact, TiEdgeEdgeContact
        return VertexTriangleContact, EdgeEdgeContact

    def _vertex_triangle(self, vt: np.ndarray, sides: np.ndarray,
                         vertices: np.ndarray | None = None) -> VertexTriangleContact:
        """Vertex-triangle penalty over pairs ``vt`` with the step's sides (:func:`step_sides`) and their vertices
        (None: computed); the pairs (this contact set's candidates) and sides (-1, 0, +1 by construction) are not
        checked again (``checked``: no pass over every candidate)."""
        return self._pair_classes()[0](vt, self.triangles, sides, self.stiffness, self.eps, vertices=vertices,
                                       checked=True)

    def _edge_edge(self, ee: np.ndarray, sides: np.ndarray, vertices: np.ndarray | None = None) -> EdgeEdgeContact:
        """Edge-edge penalty over pairs ``ee`` with the step's sides (:func:`step_sides`) and their vertices (None:
        computed); not checked again, as :meth:`_vertex_triangle`."""
        return self._pair_classes()[1](ee, self.edges, sides, self.stiffness, self.eps, vertices=vertices,
                                       checked=True)

    def _pair_geometry(self, x: np.ndarray, vt_vertices: np.ndarray, ee_vertices: np.ndarray,
                       lists: CandidateVertices | None = None) -> PairGeometry:
        """Side-memory geometry (:func:`sim_core.collision.pair_geometry.pair_geometry`) of vertex-triangle
        ``(p, 4)`` and edge-edge ``(q, 4)`` pair vertices at ``x``: on a Taichi backend one
        kernel launch for both kinds (:func:`sim_core.energies.contact.setup_kernel.pair_geometry`; with ``lists``,
        the candidate lists whose vertices these are, their int32 indices, kept on the device once per list), else
        the NumPy reference."""
        if not self.taichi:
            return pair_geometry(x, vt_vertices, ee_vertices)
        # optional heavy dependency: Taichi, loaded on a Taichi backend only
        from sim_core.energies.contact.setup_kernel import pair_geometry as geometry

        if lists is not None:
            return geometry(x, *lists.index_arrays(), device=lists.device)
        return geometry(x, vt_vertices, ee_vertices)

    def _pair_vertices(self, vt: np.ndarray, ee: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Global vertices ``[p, a, b, c]`` ``(p, 4)`` of vertex-triangle pairs ``vt`` ``(p, 2)`` and
        ``[a0, a1, b0, b1]`` ``(q, 4)`` of edge-edge pairs ``ee`` ``(q, 2)`` (the kept ones of the candidate lists)."""
        kept = getattr(self, "_vertices_kept", None)
        if kept is not None and kept.of(vt, ee):
            return kept.vt_vertices, kept.ee_vertices
        return vertex_triangle_vertices(vt, self.triangles), edge_edge_vertices(ee, self.edges)

    def _list_geometry(self, x: np.ndarray, lists: CandidateVertices):
        """The :class:`ListGeometry` of candidate lists ``lists`` at ``x`` ``(n, 3)`` (edge-edge pairs kept above
        :attr:`min_edge_sine`): on a Taichi backend one launch over the lists' kept int32 indices that copies back
        one int32 code a pair (:func:`sim_core.energies.contact.setup_kernel.pair_codes`), or with
        :attr:`device_sides` their :class:`~sim_core.energies.contact.sides_kernel.SideCodes` (one int8 code a pair,
        kept on the device too: its ``rows`` give a :class:`ListGeometry`), else from :meth:`_pair_geometry`; on
        CUDA the launch reads ``x`` where the solver's terms hold it on the device (:meth:`_held_positions`), if they
        do."""
        if not self.taichi:
            return ListGeometry.of(self._pair_geometry(x, lists.vt_vertices, lists.ee_vertices), self.min_edge_sine)
        if self._sides_on_device():
            # optional heavy dependency: Taichi, loaded on a Taichi backend only
            from sim_core.energies.contact.sides_kernel import side_codes

            return side_codes(x, *lists.index_arrays(), self.min_edge_sine, lists.device, self._held_positions(x))
        # optional heavy dependency: Taichi, loaded on a Taichi backend only
        from sim_core.energies.contact.setup_kernel import pair_codes

        return pair_codes(x, *lists.index_arrays(), self.min_edge_sine, lists.device, self._held_positions(x))

    def _held_positions(self, x: np.ndarray):
        """``x`` ``(n, 3)`` where the solver's terms hold it on the device (a float64 Taichi ndarray,
        :func:`~sim_core.ti_kernels.transfer.positions_on_device`: the set-up kernels read it there instead of sending
        it, 14 MB at 1024 Forming copies), or None; asked of frozen positions only, which are matched by identity
        (others by their bytes)."""
        if not (self.taichi and _frozen(x)):
            return None
        # optional heavy dependency: Taichi, loaded on a Taichi backend only
        from sim_core.ti_kernels.transfer import positions_on_device

        return positions_on_device(self.workspace, x)

    def _candidate_geometry(self, x: np.ndarray, vt: np.ndarray, ee: np.ndarray):
        """:meth:`_list_geometry` of the candidate lists ``vt`` ``(p, 2)`` and ``ee`` ``(q, 2)`` at ``x`` ``(n, 3)``;
        the geometry :meth:`end_step` measured of the same candidate lists (the same arrays) at equal positions is
        taken as it is: the converged positions of a step are the next one's ``x^n``, and a step starts with the
        candidate lists it ended with."""
        kept = getattr(self, "_end_geometry", None)
        if (kept is not None and kept[1] is vt and kept[2] is ee and kept[4] == self.min_edge_sine
                and (kept[0] is x or np.array_equal(kept[0], x))):
            return kept[3]
        return self._list_geometry(x, self._list_vertices(vt, ee))

    def _end_geometry_of(self, x: np.ndarray, vt: VertexTriangleContact, vt_active: np.ndarray, ee: EdgeEdgeContact,
                         ee_active: np.ndarray) -> ListGeometry | PairGeometry:
        """:meth:`_list_geometry` at the converged positions ``x`` ``(n, 3)`` of the active pairs, rows
        ``vt_active`` ``(a,)`` of ``vt`` and ``ee_active`` ``(b,)`` of ``ee`` (the step's potentials), taken from
        one measurement of every candidate pair at ``x``, which is kept for the next step's sides at its ``x^n``
        (:meth:`_candidate_geometry`): one launch per step in place of two. The potentials' rows are the
        candidates' rows (the edge-edge ones through the rows :meth:`_search` kept) when they were made from
        the candidate lists themselves (no held pair left out), else the pairs are looked up in the lists."""
        _, vt_list, ee_list = self._candidates  # the lists of the potentials evaluated at x
        lists = self._list_vertices(vt_list, ee_list)
        geo = self._list_geometry(x, lists)
        self._end_geometry = (x if _frozen(x) else np.array(x, dtype=float, copy=True), vt_list, ee_list, geo,
                              self.min_edge_sine)
        cache = self._cache
        if cache is not None and cache[1] is self._candidates and cache[2][0] is vt and cache[2][1] is ee:
            vt_pos, ee_pos = vt_active, cache[3][ee_active]
        else:
            vt_pos, vt_found = lookup_pairs((vt_list, None), vt.pairs[vt_active])
            ee_pos, ee_found = lookup_pairs((ee_list, None), ee.pairs[ee_active])
            if not (np.all(vt_found) and np.all(ee_found)):  # pairs outside the lists (none expected)
                return self._pair_geometry(x, *self._pair_vertices(vt.pairs[vt_active], ee.pairs[ee_active]))
        return geo.rows(vt_pos, ee_pos)

    def _pair_sides(self, x_ref: np.ndarray, memory: CollisionMemory, vt: np.ndarray, ee: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(vt sides, ee rows kept, ee sides)`` of the candidate lists ``vt`` ``(p, 2)`` (vertex-triangle) and ``ee``
        ``(q, 2)`` (edge-edge) at ``x_ref``, shapes ``(p,)``, ``(r,)`` (int64, increasing), ``(q,)``.

        ``vt sides``: the step sides (:func:`step_sides`). Near-parallel edge pairs have no
        well-defined side (the cross product of their directions vanishes) and switch distance
        definitions as they rotate; their contact is carried by the vertex-triangle pairs of the
        same configuration, so they are left out (not among the rows kept, side 0; decided at x^n, so the set
        is fixed within the step). ``ee sides``: the step sides of the kept pairs. On CUDA the rows kept come from the
        device with the pair batch's layout rows (:meth:`_device_pair_sides`, :attr:`_rows_device`).
        """
        geo = self._candidate_geometry(x_ref, vt, ee)
        vt_keys, ee_keys = self._list_vertices(vt, ee).keys()
        block = np.empty(len(vt) + len(ee))  # both kinds' sides in one array: the pair batch's (_search)
        self._sides_device = self._rows_device = None
        if not isinstance(geo, ListGeometry):  # the codes of the device path (_list_geometry)
            if (vt_keys is not None or not len(vt)) and (ee_keys is not None or not len(ee)):
                return self._device_pair_sides(geo, memory, (vt_keys, ee_keys), block)
            geo = geo.geometry()
        vt_sides = step_sides(geo.vt_above, vt, geo.vt_side, memory.vertex_triangle, vt_keys, block[:len(vt)])
        keep = geo.ee_keep
        ee_sides = step_sides(keep & geo.ee_interior, ee, geo.ee_side, memory.edge_edge, ee_keys, block[len(vt):])
        return vt_sides, np.flatnonzero(keep), ee_sides

    def _sides_on_device(self) -> bool:
        """Whether the lists' geometry is their :class:`~sim_core.energies.contact.sides_kernel.SideCodes` and the step
        sides are placed from them (:meth:`_list_geometry`, :meth:`_device_pair_sides`; :attr:`device_sides`)."""
        if not self.taichi:
            return False
        if self.device_sides is not None:
            return bool(self.device_sides)
        # optional heavy dependency: Taichi, loaded on a Taichi backend only
        from sim_core.ti_backend import current_arch

        return current_arch() == "cuda"

    def _device_pair_sides(self, codes, memory: CollisionMemory, keys: tuple, block: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`_pair_sides` from the lists' :class:`~sim_core.energies.contact.sides_kernel.SideCodes` at ``x^n``
        (:func:`~sim_core.energies.contact.sides_kernel.step_sides_of`) with the memory's pairs placed among the lists'
        sorted ``keys`` (a search a remembered pair; ``block`` ``(p + q,)`` the sides' array); on CUDA the sides'
        device copy is kept for the pair batch (:attr:`_sides_device`), and the edge-edge rows kept come with the
        batch's layout rows made on the device (:class:`~sim_core.energies.contact.sides_kernel.KeptRows`, kept as
        :attr:`_rows_device`: no host pass over the edge-edge candidates' codes)."""
        # optional heavy dependency: Taichi, loaded on a Taichi backend only
        from sim_core.energies.contact.sides_kernel import step_sides_of

        p = codes.split
        found = [memory_of.found_in(k) if k is not None else (np.zeros(0, np.int64), np.zeros(0))
                 for memory_of, k in zip((memory.vertex_triangle, memory.edge_edge), keys)]
        got = step_sides_of(codes, (np.concatenate([found[0][0], found[1][0] + p]),
                                    np.concatenate([found[0][1], found[1][1]])), block)
        self._sides_device = (block, got.device)
        rows = got.kept_edge_edge_rows()
        self._rows_device = None if got.kept is None else (rows, got.kept)
        return block[:p], rows, block[p:]

    def _search(self, x: np.ndarray, memory: CollisionMemory, candidates: tuple) -> tuple[tuple, np.ndarray]:
        """Potentials over ``candidates`` with the step's sides (:meth:`_pair_sides`, of every pair in one geometry
        evaluation for both pair kinds; those of the step's last lists when these are the same arrays). Returns the
        two potentials and the rows of the edge-edge candidates the edge-edge potential kept, int64 ``(q,)`` (the
        vertex-triangle potential keeps every candidate, in order). The edge-edge potential's pairs and sides are
        the kept rows of the list and of its sides as :class:`~sim_core.energies.contact.reference.ListRows`
        (gathered where read: the active rows; the pair batch reads the sides by layout row, on CUDA where the
        sides' launch wrote them)."""
        x_ref = self.x_prev if self.x_prev is not None else x
        _, vt, ee = candidates
        table = getattr(self, "_step_table", None)
        if (table is not None and table[0] is memory and table[1] is x_ref and self.x_prev is not None
                and table[2] is vt and table[3] is ee):
            vt_sides, ee_rows, ee_sides = table[4]
        else:
            vt_sides, ee_rows, ee_sides = self._pair_sides(x_ref, memory, vt, ee)
            self._step_table = (memory, x_ref, vt, ee, (vt_sides, ee_rows, ee_sides))
        vt_sides, ee_sides = self._without_released(vt, vt_sides, 0), self._without_released(ee, ee_sides, 1)
        lists = self._list_vertices(vt, ee)
        ee_kept = ListRows(ee, ee_rows)  # the kept rows of the list and of its sides: gathered only where read
        pots = (self._vertex_triangle(vt, vt_sides, lists.vt_vertices),
                self._edge_edge(ee_kept, ListRows(ee_sides, ee_rows), lists.kept_edge_edge_vertices(ee_rows, ee_kept)))
        for pot in pots:
            pot.workspace = self.workspace
        if self.taichi:
            # optional heavy dependency: Taichi, loaded on a Taichi backend only
            from sim_core.energies.contact.batch_kernel import PairBatch

            # one launch evaluates both at each new x; its sides by layout row are both lists' (0 where a pair is left
            # out), the one array of _pair_sides unless a release copied a part
            whole = vt_sides.base if vt_sides.base is not None and vt_sides.base is ee_sides.base else None
            kept = getattr(self, "_sides_device", None)  # the same sides where the sides' launch wrote them
            device = kept[1] if kept is not None and whole is not None and kept[0] is whole else None
            made = getattr(self, "_rows_device", None)  # the layout rows where the kept rows' launch wrote them
            made = made[1] if made is not None and made[0] is ee_rows else None
            PairBatch(*pots, layout=lists.batch_layout(ee_rows, None if made is None else made.rows), sides=whole,
                      device_sides=device, device_rows=None if made is None else made.device)
        return pots, ee_rows

    def _list_vertices(self, vt: np.ndarray, ee: np.ndarray) -> CandidateVertices:
        """The global vertices of candidate lists ``vt`` ``(p, 2)`` and ``ee`` ``(q, 2)``, kept for the last lists
        asked for (the same arrays: a search's lists serve its step's potentials, the end geometry and the next
        step's potentials)."""
        kept = getattr(self, "_vertices_kept", None)
        if kept is None or not kept.of(vt, ee):
            known = getattr(self, "_list_keys", None)  # the search's keys and device vertices (the same arrays)
            same = known is not None and known[0] is vt and known[1] is ee
            kept = self._vertices_kept = CandidateVertices(vt, ee, self.triangles, self.edges,
                                                           keys=known[2] if same else (None, None),
                                                           vertex_count=self.model.vertex_count, pool=self._pool,
                                                           device_vertices=known[3] if same else None)
        return kept

    def _without_released(self, pairs: np.ndarray, sides: np.ndarray, kind: int) -> np.ndarray:
        """``sides`` ``(p,)`` of ``pairs`` ``(p, 2)`` with the step's released pairs of ``kind`` (0
        vertex-triangle, 1 edge-edge; :meth:`release_stale_sides`) unsigned (a copy when any is)."""
        released = self._released
        if not len(released[kind]) or not len(pairs):
            return sides
        out = np.array(sides, dtype=float, copy=True)
        out[np.isin(_pair_keys(pairs), released[kind])] = 0.0
        return out

    def release_stale_sides(self, x: np.ndarray, memory: CollisionMemory) -> int:
        """Unsign, for the rest of the step, the pairs whose side has gone stale at iterate ``x``.

        A side is kept from ``x^n`` so that a vertex that slips through a face during the step is
        pushed back (:func:`step_sides`). But a pair can also get to the other geometric side
        without crossing: a vertex round a triangle's free edge, or an edge past the end of the
        other, where the lines of the two edges cross beyond an end (easy for edge pairs; the
        distance is unsigned there). Such a pair sits beside its face (beyond an edge's end) with
        the other geometric side; were it to enter the face (interior) region, its distance would
        jump from ``+delta`` to ``-delta``: a step in the energy. When Newton converges onto that
        border, no step along the Newton direction decreases the energy and the line search fails
        (folding.yaml, dome held on the fold: a dome edge and a sheet edge 0.61 mm apart, an energy
        step of 5.1 mJ). Releasing those sides removes the step where Newton stands and changes
        nothing at ``x`` itself: there the pairs are beside their face, where the distance is
        unsigned anyway. Pairs above their face (interior) keep their sides, whatever the
        geometry: that is a penetration the side must undo. Released pairs stay unsigned for the
        rest of the step (also through later candidate searches), so the energy changes at most
        once per pair and a step cannot cycle through releases.

        Args:
            x: the current Newton iterate, shape ``(n, 3)`` (m).
            memory: the step's side memory (as given to :meth:`potentials`).

        Returns:
            the number of pairs released now (0: nothing stale, the failure has another cause).
        """
        vt, ee = self._pairs(x, memory)
        sided = [np.flatnonzero(pot.sides != 0.0) for pot in (vt, ee)]
        geo = self._pair_geometry(x, vt.vertices[sided[0]], ee.vertices[sided[1]])
        stale = [sided[0][~geo.vt_above & (geo.vt_side != vt.sides[sided[0]])],
                 sided[1][~geo.ee_interior & (geo.ee_side != ee.sides[sided[1]])]]
        count = sum(len(rows) for rows in stale)
        if count:
            self._released = tuple(np.union1d(keys, _pair_keys(pot.pairs[rows]))
                                   for keys, pot, rows in zip(self._released, (vt, ee), stale))
            self._cache = None  # the next potentials() builds the pairs again, with these sides at 0
        return count

    def potentials(self, x: np.ndarray, x_n: np.ndarray, memory: CollisionMemory, x_device=None,
                   segment_start: np.ndarray | None = None) -> list:
        """Contact potentials for the candidates near iterate ``x`` ``(n, 3)`` (m; planes and spheres included);
        ``x_device``: ``x`` as a float64 Taichi ndarray ``(n, 3)``, where :meth:`covers` then reads it, or None;
        ``segment_start``: where the line search of trial point ``x`` started (:meth:`_search_position`), or None."""
        vt, ee = self._pairs(x, memory, x_device, segment_start)
        return [vt, ee] + [p for _, p in self.planes] + [p for _, p in self.spheres]

    def friction(self, x_n: np.ndarray, dt: float, memory: CollisionMemory,
                 held: np.ndarray | None = None) -> LaggedFriction | None:
        """Lagged friction of the pairs active at ``x^n`` (None when nothing touches or mu = 0).

        ``held``: vertices held at ``x^n`` for the whole step (sleeping bodies, :mod:`sim_core.sleeping`),
        bool ``(n,)``, or None; the rows of a vertex and an obstacle with the vertex held are left out
        (its tangential displacement is zero all step: no force, and the constant energy
        ``mu lam f0(0)`` of each, kept as :attr:`held_friction_energy`)."""
        vt, ee = self._pairs(x_n, memory)
        self.held_friction_energy = 0.0
        eps_u = self.model.contact.eps_v * dt
        obstacle_frames = []
        for name, obstacle in self.planes + self.spheres:
            f = obstacle.contact_frames(x_n)
            mu = self.coulomb.obstacle(name)[self.vertex_body[obstacle.vertices[f.pair_index]]]
            if held is not None and len(f.lam):
                keep = ~held[f.vertices[:, 0]]
                self.held_friction_energy += float(np.sum(mu[~keep] * f.lam[~keep]) * smooth_friction_f0(0.0, eps_u))
                f, mu = ContactFrames(*(a[keep] for a in f)), mu[keep]
            obstacle_frames.append((name, obstacle, f, mu))
        if self.taichi and not any(len(f.lam) for _, _, f, _ in obstacle_frames):
            return self._pair_friction(x_n, dt, vt, ee)
        frames, mus, sources = [], [], []
        # a pair's vertices: [p, a, b, c] / [a0, a1, b0, b1]; column 0 and ``second`` are on its two sides
        for pot, second in ((vt, 1), (ee, 2)):
            f = pot.contact_frames(x_n)
            if len(f.lam):
                frames.append(f)
                mus.append(self.coulomb.between(f.vertices[:, 0], f.vertices[:, second]))
                sources.append(FrictionRowSource(None, pot, f.pair_index))
        for name, obstacle, f, mu in obstacle_frames:
            if len(f.lam):
                frames.append(f)
                mus.append(mu)
                sources.append(FrictionRowSource(name, obstacle, f.pair_index))
        if not frames:
            return None
        mu = np.concatenate(mus)
        if not np.any(mu > 0):
            return None
        all_frames = concatenate_frames(frames)
        friction_class = LaggedFriction
        if self.taichi:
            # optional heavy dependency: Taichi, loaded on a Taichi backend only
            from sim_core.energies.friction.kernel import TiLaggedFriction as friction_class
        friction = friction_class.from_frames(all_frames, mu, x_n, self.model.contact.eps_v, dt)
        friction.workspace = self.workspace
        friction.row_sources = sources  # for the adjoint (sim_core.adjoint_friction.friction_rows)
        return friction

    def _pair_friction(self, x_n: np.ndarray, dt: float, vt: VertexTriangleContact, ee: EdgeEdgeContact
                       ) -> LaggedFriction | None:
        """:meth:`friction` on the Taichi backend when only pair contacts touch: the frames and tangent
        bases of the active pairs of both kinds from one launch
        (:func:`sim_core.energies.contact.setup_kernel.friction_frames`; the values of the pair potentials'
        ``contact_frames`` and of ``tangent_basis``, bit for bit), rows in the same order; on CUDA the rows built and
        kept on the device (:meth:`_device_friction`), the launch reading ``x^n`` where the solver's terms hold it on
        the device (:meth:`_held_positions`), if they do."""
        # optional heavy dependency: Taichi, loaded on a Taichi backend only
        from sim_core.ti_backend import current_arch

        pots = (vt, ee)
        rows = [pot.active_distances(x_n) for pot in pots]
        build = self._device_friction if current_arch() == "cuda" else self._host_rows_friction
        friction = build(x_n, dt, pots, rows)
        if friction is not None:
            friction.workspace = self.workspace
            friction.row_sources = [FrictionRowSource(None, pot, active) for pot, (active, _) in zip(pots, rows)
                                    if len(active)]
        return friction

    def _host_rows_friction(self, x_n: np.ndarray, dt: float, pots: tuple, rows: list) -> LaggedFriction | None:
        """:meth:`_pair_friction`'s rows off CUDA: the active pairs' vertices, sides and Coulomb coefficients on the
        host, their frames from one launch read back (``rows``: each potential's active rows and distances at
        ``x_n``)."""
        # optional heavy dependency: Taichi, loaded on a Taichi backend only
        from sim_core.energies.contact.setup_kernel import friction_frames
        from sim_core.energies.friction.kernel import TiLaggedFriction

        split = len(rows[0][0])
        vertices = np.concatenate([np.take(pot.vertices, active, axis=0) for pot, (active, _) in zip(pots, rows)])
        if not len(vertices):
            return None
        # column 0 and the second side's column (1 for [p, a, b, c], 2 for [a0, a1, b0, b1]): its two sides
        mu = self.coulomb.between(vertices[:, 0], np.concatenate([vertices[:split, 1], vertices[split:, 2]]))
        if not np.any(mu > 0):
            return None
        sides = np.concatenate([pot.sides[active] for pot, (active, _) in zip(pots, rows)])
        weights, normal, tangent = friction_frames(x_n, vertices, sides, split, self._held_positions(x_n))
        lam = np.concatenate([pot.stiffness * (pot.eps - d) for pot, (_, d) in zip(pots, rows)])
        return TiLaggedFriction(vertices, weights, tangent, lam, mu, x_n, self.model.contact.eps_v, dt)

    def _device_friction(self, x_n: np.ndarray, dt: float, pots: tuple, rows: list) -> LaggedFriction | None:
        """:meth:`_pair_friction`'s rows on CUDA, built where the friction's kernels read them
        (:func:`~sim_core.energies.friction.rows_kernel.friction_on_device`: one upload of the active pairs' vertices,
        sides and distances, ``x^n`` read where the solver's terms hold it, nothing read back); None where no body
        pair has a positive Coulomb coefficient (rows of pairs whose coefficient is zero add nothing)."""
        # optional heavy dependency: Taichi, loaded on a Taichi backend only
        from sim_core.energies.friction.rows_kernel import friction_on_device

        table = self.coulomb.table()
        vertices = [pot.active_vertices(x_n) for pot, (active, _) in zip(pots, rows) if len(active)]
        if not vertices or not np.any(table > 0):
            return None
        vt, ee = pots
        return friction_on_device(
            x_n, self._held_positions(x_n), np.concatenate(vertices),
            np.concatenate([pot.sides[active] for pot, (active, _) in zip(pots, rows)]),
            np.concatenate([d for _, d in rows]), len(rows[0][0]), (vt.eps, ee.eps, vt.stiffness, ee.stiffness),
            self.coulomb.vertex_body, table, self.model.contact.eps_v, dt)

    def end_step(self, x: np.ndarray, memory: CollisionMemory) -> CollisionMemory:
        """Remember the sides of the pairs active at the converged positions ``x``.

        Only pairs above the face (interior) are remembered: elsewhere a side has no meaning
        (:func:`step_sides`); a remembered pair keeps its side while it stays so.
        """
        vt, ee = self._pairs(x, memory)
        out = memory.copy()
        vt_active, ee_active = (pot.active_distances(x)[0] if len(pot.pairs) else np.zeros(0, np.int64)
                                for pot in (vt, ee))
        geo = self._end_geometry_of(x, vt, vt_active, ee, ee_active)
        for pot, mem, active, above, geometric in ((vt, out.vertex_triangle, vt_active, geo.vt_above, geo.vt_side),
                                                   (ee, out.edge_edge, ee_active, geo.ee_interior, geo.ee_side)):
            rows = active[above]
            sides = pot.sides[rows]
            # an unsigned pair takes the side of x itself (the potential's resolved_sides)
            mem.update(np.take(pot.pairs, rows, axis=0), np.where(sides == 0.0, geometric[above], sides))
        return out


_NO_RELEASES = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))


def _frozen(x: np.ndarray) -> bool:
    """Whether positions ``x`` are frozen (:meth:`~sim_core.energies.base.FrozenPositionsKey.holds`: keyed by identity,
    as :func:`~sim_core.energies.base.positions_key` keys them: their values cannot change while they exist)."""
    return FrozenPositionsKey.holds(x)


def _pair_keys(pairs: np.ndarray) -> np.ndarray:
    """One int64 key per pair ``(p, 2)`` (both indices < 2**31), the candidate lists' sort order."""
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    return (pairs[:, 0] << 32) | pairs[:, 1]


def _sheet_vertices(model: Model) -> np.ndarray:
    parts = [b.vertices for b in model.bodies.values() if b.kind == "sheet"]
    return np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)


def active_contacts(terms: list, x: np.ndarray) -> list[np.ndarray] | None:
    """The touching contacts of the penalty potentials ``terms`` (as :meth:`ContactSet.potentials`
    returns them) at positions ``x`` ``(n, 3)`` m: per term, the vertex rows of its active entries
    (``d < eps``): ``(a, 4)`` int for a pair potential, ``(a,)`` for a plane or a sphere. None when
    a term is not a :class:`~sim_core.energies.base.PenaltyContact` (a missing-physics candidate's
    stiction, say; its adhesion declares its open pairs).
    Two iterates with equal results have the same penalty terms switched on, so the contact part of
    the Newton matrix changes smoothly between them (:func:`same_active_contacts`)."""
    if not all(declares(p, PenaltyContact) for p in terms):
        return None
    # a pair potential's from its kept evaluation of x (no pass over every candidate pair)
    return [p.active_vertices(x) if isinstance(p, (VertexTriangleContact, EdgeEdgeContact))
            else p.vertices[p.active_mask(x)] for p in terms]


def same_active_contacts(a: list[np.ndarray] | None, b: list[np.ndarray] | None) -> bool:
    """Whether two :func:`active_contacts` results name the same contacts in the same order (False
    when either is None)."""
    if a is None or b is None or len(a) != len(b):
        return False
    return all(u.shape == v.shape and np.array_equal(u, v) for u, v in zip(a, b))
