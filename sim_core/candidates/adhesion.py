"""Adhesion of a tacky gel: a cohesive (traction-separation) law between gel and sheet.

Candidate ``adhesion`` of SYSID.md. Each gel contact-face vertex p within reach of a sheet triangle
at the start of the step forms a lagged pair: closest point ``q = sum_j b_j x_j`` on the triangle,
unit normal ``n`` (from q to p) and barycentric weights ``b`` frozen at ``x^n`` (as the lagged
friction of Li et al. 2020 freezes its frames). The opening of the pair beyond the contact offset is

    s(x) = n . (p - sum_j b_j x_j) - eps,

linear in x. The energy is an exponential cohesive law (Xu & Needleman 1994, normal part) that is
zero while the pair is pressed (s <= 0):

    E = sum_k beta delta e (1 - (1 + r_k) exp(-r_k)),   r_k = max(s_k, 0) / delta,

so the tensile force on lift-off ``beta r exp(1 - r)`` rises from 0, peaks at the bond strength
``beta`` (N per pair) at an opening ``delta`` and decays: the bond breaks with the work of
separation ``e beta delta`` per pair. ``beta = 0`` is off. Hessian per pair
``phi''(s) (b (x) b) (x) n n^T`` with ``phi'' = (beta/delta)(1 - r) exp(1 - r)`` (rank one; the
projection clamps / flips ``phi''`` past the peak).

Bond memory (:func:`bonded_pairs`, :func:`bonded_after`): a gel vertex that touched the sheet
(opening below the reach at the end of a step) stays bonded while its opening stays below the
release opening (``ADHESION_RELEASE_FRACTION`` delta in the hook: the traction has fallen to 9 % of
its peak and 96 % of the work of separation is spent, so dropping the pair is the end of the
softening branch, not a jump); a bonded vertex gets its lagged pair at the next step although it is
no longer in contact, so a tacky gel can carry a light card up for several steps, as a real one
does. A vertex that was never in contact (or was released) forms no pair across a gap (the card
that buckled away from the gel is not pulled). The set is the state ``candidate_state["adhesion"]``
(sorted global gel vertex indices); it depends on positions only, not on ``beta``.

Shear (anchored bonds, :func:`anchored_pairs`, :func:`anchored_after`): a bond holds the sheet's
material point it formed on, not whichever point is nearest now. When a gel vertex first bonds, the
closest point's sheet triangle and barycentric weights are its anchor (state
``candidate_state["adhesion_anchor_triangle"]`` ``(b,)`` and ``["adhesion_anchor_weights"]`` ``(b, 3)``,
aligned with the bonded vertices); every later step pairs the vertex with that anchor, ``n`` the
anchored triangle's unit normal at ``x^n`` (towards the gel vertex). The tangential opening is
``t = |P d|`` with ``d = p - sum_j b_j x_j`` and ``P = I - n n^T``, and the energy is Xu & Needleman's
coupled cohesive potential (Xu & Needleman 1994, "Numerical simulations of fast crack growth in
brittle solids", J. Mech. Phys. Solids 42(9), 1397-1434: the exponential normal-tangential potential)
with equal normal and tangential works (``q = 1``, where it no longer depends on ``r``):

    E = sum_k beta delta e (1 - (1 + r_k) exp(-r_k - t_k^2 / delta_t^2)),

which is the normal law above at ``t = 0``; its shear stiffness at rest is ``2 e beta delta / delta_t^2``
per pair and the peak shear traction ``sqrt(2 e) beta delta / delta_t`` at ``t = delta_t / sqrt 2``.
A bond breaks past the release opening in either direction (``s`` or ``t delta / delta_t`` above it).
Shear is opt-in (``adhesion.shear``, the candidate setting of ``delta_t``; None, the default, is the
normal-only law above). With normal-only bonds a card hanging from the gel slides along it: on a lift-and-fold
the card stays a straight ramp where the recorded one arches (nominal_s109 at the engine's values: sheet points
whitened RMS 32, 6 mm mean error in the fold's hold). Rigid shear bonds (``delta_t = delta``) carry the card back
with the gel and arch it too high (41 on nominal_s109, 58 on the own MuJoCo world's nominal_s301, against 32
and 13 normal-only): the reference world's tack bonds are soft springs that lag the gel by 5-12 mm;
docs/benchmarks_log.md, session 52.

Shear compliance (:data:`ShearLaw`, ``adhesion.shear_stiffness``): the coupled law ties the bond's shear
stiffness to its normal strength (a bond soft in shear is weak in shear and lets the card go as it pivots). A
real gel's adhesive layer is a thin compliant film: it holds the anchored point with a finite tangential
stiffness however weak the normal bond. With ``k_t`` (N/m per bonded pair) the energy is the normal law above plus
a linear tangential spring on the anchored bonds,

    E = sum_k beta delta e (1 - (1 + r_k) exp(-r_k)) + k_t t_k^2 / 2,

``t_k = |P_k d_k|`` with the lagged ``P = I - n n^T`` (fixed within the step), so the shear part is exactly
quadratic in x: gradient ``k_t P d`` and Hessian ``k_t P`` per pair, PSD. The bond breaks at the normal release
opening or the peel (``adhesion.release_time``), not in shear. ``k_t`` is a parameter of the recording: the fit
reads it from the carried card (:mod:`sysid.diagnose.tack`).

Normal compliance (``adhesion.normal_ratio`` ``rho``, with the layer): the layer's bonds are linear springs along the
normal too, stiffness ``k_n = rho k_t`` per pair, in place of the cohesive law,

    E = sum_k k_n max(s_k, 0)^2 / 2 + k_t t_k^2 / 2,

so at ``rho = 1`` each bond is an isotropic spring between the gel vertex and its anchored sheet point (held off by
the contact offset), gradient ``k_n max(s, 0) n + k_t P d``, Hessian ``k_n [s > 0] n n^T + k_t P``. A bond stiff along
the normal (the cohesive law's ``e beta / delta``, ~1,100 N/m a pair at the layer's strength against ``k_t`` ~3 N/m)
holds the carried patch flat on the gel face, so the card leaves the pad at the gel's slope whatever it carries; a
real adhesive layer (fibrils, a soft film) stretches along the normal as it does in shear, and lets the patch tilt
under the card's bending moment. The bond then breaks where its normal force reaches ``beta`` (release opening
``beta / k_n``, :meth:`sim_core.candidates.hook.CandidateHook.setting`) or at the peel.
"""

from __future__ import annotations

import numpy as np

from sim_core.collision import vertex_triangle_candidates
from sim_core.collision.distances import point_triangle_closest_point
from sim_core.energies.base import HessianBlocks, Projection, scatter_gradient
from sim_core.errors import ConfigError


def _nearest_pairs(x_prev: np.ndarray, gel_vertices: np.ndarray, sheet_triangles: np.ndarray,
                   eps: float, reach: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`adhesion_pairs` plus each pair's row in ``sheet_triangles``, ``(p,)`` int64."""
    pairs = vertex_triangle_candidates(x_prev, gel_vertices, sheet_triangles, eps + reach)
    empty = (np.zeros((0, 4), np.int64), np.zeros((0, 4)), np.zeros((0, 3)), np.zeros(0, np.int64))
    if pairs.shape[0] == 0:
        return empty
    tri = sheet_triangles[pairs[:, 1]]
    p, a, b, c = x_prev[pairs[:, 0]], x_prev[tri[:, 0]], x_prev[tri[:, 1]], x_prev[tri[:, 2]]
    bary, _ = point_triangle_closest_point(p, a, b, c)
    q = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c
    dist = np.linalg.norm(p - q, axis=1)
    order = np.lexsort((dist, pairs[:, 0]))
    first = np.ones(order.size, bool)
    first[1:] = pairs[order[1:], 0] != pairs[order[:-1], 0]
    keep = order[first]
    keep = keep[(dist[keep] - eps < reach) & (dist[keep] > 1e-12)]
    if keep.size == 0:
        return empty
    vertices = np.concatenate([pairs[keep, :1], tri[keep]], axis=1)
    weights = np.concatenate([np.ones((keep.size, 1)), -bary[keep]], axis=1)
    normal = (p[keep] - q[keep]) / dist[keep, None]
    return vertices, weights, normal, pairs[keep, 1].astype(np.int64)


def adhesion_pairs(x_prev: np.ndarray, gel_vertices: np.ndarray, sheet_triangles: np.ndarray,
                   eps: float, reach: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lagged gel-vertex / sheet-triangle pairs whose opening at ``x_prev`` is below ``reach``.

    Args:
        x_prev: positions at the start of the step, m, shape ``(n, 3)``.
        gel_vertices: global indices of the gel's contact-face vertices, shape ``(v,)``.
        sheet_triangles: global sheet triangles, shape ``(t, 3)``.
        eps: contact offset in m.
        reach: largest opening ``s`` (m) at which a pair is formed.

    Returns:
        ``(vertices (p, 4) [gel vertex, a, b, c], weights (p, 4) [1, -b_a, -b_b, -b_c],
        normal (p, 3))``; each gel vertex keeps only its nearest triangle.
    """
    return _nearest_pairs(x_prev, gel_vertices, sheet_triangles, eps, reach)[:3]


def bonded_pairs(x_prev: np.ndarray, gel_vertices: np.ndarray, sheet_triangles: np.ndarray, eps: float,
                 reach: float, release: float, bonded: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pairs of the gel vertices in contact (opening below ``reach``) and of the bonded ones (below ``release``).

    Args:
        x_prev, gel_vertices, sheet_triangles, eps, reach: as :func:`adhesion_pairs`.
        release: release opening in m (>= ``reach``): a bonded vertex keeps a pair up to it.
        bonded: global indices of the bonded gel vertices (state; module docstring), shape ``(b,)``.

    Returns:
        ``(vertices (p, 4), weights (p, 4), normal (p, 3))`` as :func:`adhesion_pairs`.
    """
    v, w, n = adhesion_pairs(x_prev, gel_vertices, sheet_triangles, eps, max(reach, release))
    if v.shape[0] == 0:
        return v, w, n
    s = np.einsum("kd,kd->k", np.einsum("kj,kjd->kd", w, x_prev[v]), n) - eps
    keep = (s < reach) | (np.isin(v[:, 0], np.asarray(bonded, dtype=np.int64)) & (s < release))
    return v[keep], w[keep], n[keep]


def bonded_after(x: np.ndarray, gel_vertices: np.ndarray, sheet_triangles: np.ndarray, eps: float,
                 reach: float, release: float, bonded: np.ndarray) -> np.ndarray:
    """The bonded gel vertices after a step that ended at ``x``: those in contact (opening below
    ``reach``) and the previously ``bonded`` ones whose opening is still below ``release``.

    Returns:
        sorted global gel vertex indices, int64, shape ``(b',)``.
    """
    v, _, _ = bonded_pairs(x, gel_vertices, sheet_triangles, eps, reach, release, bonded)
    return np.unique(v[:, 0]).astype(np.int64)


Anchors = tuple[np.ndarray, np.ndarray, np.ndarray]
"""Anchored bonds: ``(gel vertex (b,) int64, sheet triangle row (b,) int64, barycentric weights (b, 3))``."""


def no_anchors() -> Anchors:
    """An empty :data:`Anchors`."""
    return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3))


def _anchored_geometry(x: np.ndarray, sheet_triangles: np.ndarray, anchors: Anchors, side: np.ndarray | None = None
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pairs of anchored bonds at ``x``: ``(vertices (b, 4), weights (b, 4), unit normal (b, 3) of the anchored
    triangle towards the gel vertex (or along ``side`` (b,) +-1 when given), d = p - q (b, 3))``."""
    gel, tri_row, bary = anchors
    tri = sheet_triangles[tri_row]
    a, b, c = x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]]
    q = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c
    d = x[gel] - q
    nrm = np.cross(b - a, c - a)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    sign = np.where(np.einsum("kd,kd->k", nrm, d) >= 0.0, 1.0, -1.0) if side is None else side
    vertices = np.concatenate([gel[:, None], tri], axis=1)
    weights = np.concatenate([np.ones((gel.size, 1)), -bary], axis=1)
    return vertices, weights, nrm * sign[:, None], d


def anchored_pairs(x_prev: np.ndarray, gel_vertices: np.ndarray, sheet_triangles: np.ndarray, eps: float,
                   reach: float, anchors: Anchors) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The step's pairs: each anchored bond with its anchor (module docstring, shear), and the gel vertices in
    contact that hold no anchor yet with their nearest point (:func:`adhesion_pairs`).

    Args:
        x_prev, gel_vertices, sheet_triangles, eps, reach: as :func:`adhesion_pairs`.
        anchors: the bonds of the state (:data:`Anchors`).

    Returns:
        ``(vertices (p, 4), weights (p, 4), normal (p, 3))`` as :func:`adhesion_pairs`.
    """
    v, w, n = adhesion_pairs(x_prev, gel_vertices, sheet_triangles, eps, reach)
    if anchors[0].size == 0:
        return v, w, n
    new = ~np.isin(v[:, 0], anchors[0])
    av, aw, an, _ = _anchored_geometry(x_prev, sheet_triangles, anchors)
    return (np.concatenate([av, v[new]]), np.concatenate([aw, w[new]]), np.concatenate([an, n[new]]))


def anchored_after(x: np.ndarray, gel_vertices: np.ndarray, sheet_triangles: np.ndarray, eps: float, reach: float,
                   release: float, release_shear: float, anchors: Anchors) -> Anchors:
    """The bonds after a step that ended at ``x``: the anchored ones whose normal opening is still below
    ``release`` and tangential opening below ``release_shear``, and a new anchor (the nearest point) for each
    gel vertex in contact (opening below ``reach``) that holds none.

    Returns:
        :data:`Anchors`, sorted by gel vertex.
    """
    gel, tri_row, bary = anchors
    if gel.size:
        _, _, n, d = _anchored_geometry(x, sheet_triangles, anchors)
        s_n = np.einsum("kd,kd->k", d, n) - eps
        t = np.linalg.norm(d - np.einsum("kd,kd->k", d, n)[:, None] * n, axis=1)
        held = (s_n < release) & (t < release_shear)
        gel, tri_row, bary = gel[held], tri_row[held], bary[held]
    v, w, _, rows = _nearest_pairs(x, gel_vertices, sheet_triangles, eps, reach)
    new = ~np.isin(v[:, 0], gel)
    gel = np.concatenate([gel, v[new, 0]])
    tri_row = np.concatenate([tri_row, rows[new]])
    bary = np.concatenate([bary, -w[new, 1:]])
    order = np.argsort(gel, kind="stable")
    return gel[order].astype(np.int64), tri_row[order].astype(np.int64), bary[order]


class LaggedAdhesion:
    """Cohesive gel-sheet adhesion over lagged pairs (module docstring).

    Args:
        vertices: ``(p, 4)`` global indices ``[gel vertex, a, b, c]``.
        weights: ``(p, 4)`` weights ``[1, -b_a, -b_b, -b_c]`` of the sheet point (nearest or anchored).
        normal: ``(p, 3)`` unit normals from the sheet point to the gel vertex.
        eps: contact offset in m (> 0): the opening is measured from it.
        beta: bond strength per pair in N (>= 0; 0 = off).
        delta: opening at peak force in m (> 0).
        delta_t: tangential length ``delta_t`` of the coupled law in m (> 0), or None: normal bonds only.
        k_shear: tangential stiffness ``k_t`` of the compliant layer in N/m per pair (>= 0; module docstring,
            shear compliance), or None. Exclusive with ``delta_t``.
        normal_ratio: ``rho``, the layer's normal over its shear stiffness (> 0; module docstring, normal
            compliance), or None: the cohesive normal law. Needs ``k_shear``.

    Raises:
        ConfigError: negative / non-finite ``beta`` or ``k_shear``, non-positive ``delta``, ``delta_t`` or ``eps``,
            both ``delta_t`` and ``k_shear``, ``normal_ratio`` non-positive or without ``k_shear``, bad shapes.
    """

    parameter_names: tuple[str, ...] = ("beta",)
    """``("beta",)``, and ``"k_shear"`` on bonds with the compliant layer."""

    candidate_parameters = {"candidate.adhesion": "beta", "candidate.adhesion.shear_stiffness": "k_shear"}
    """The model's global parameter of each local one (:meth:`parameter_gradient`): the forward tangents and the
    adjoint take a candidate's parameters through it (:meth:`sim_core.adjoint.StepLinearization.parameter_rhs`)."""

    def __init__(self, vertices: np.ndarray, weights: np.ndarray, normal: np.ndarray, eps: float,
                 beta: float, delta: float, delta_t: float | None = None, k_shear: float | None = None,
                 normal_ratio: float | None = None) -> None:
        beta, delta, eps = float(beta), float(delta), float(eps)
        if not (np.isfinite(beta) and beta >= 0):
            raise ConfigError(f"LaggedAdhesion: bond strength beta must be finite and >= 0 N, got {beta}")
        if not (np.isfinite(delta) and delta > 0):
            raise ConfigError(f"LaggedAdhesion: delta (opening at peak force) must be > 0 m, got {delta}")
        if not (np.isfinite(eps) and eps > 0):
            raise ConfigError(f"LaggedAdhesion: contact eps must be > 0 m, got {eps}")
        if delta_t is not None and not (np.isfinite(delta_t) and delta_t > 0):
            raise ConfigError(f"LaggedAdhesion: delta_t (tangential length) must be > 0 m, got {delta_t}")
        if k_shear is not None and not (np.isfinite(k_shear) and k_shear >= 0):
            raise ConfigError(f"LaggedAdhesion: k_shear (tangential stiffness) must be finite and >= 0 N/m, "
                              f"got {k_shear}")
        if k_shear is not None and delta_t is not None:
            raise ConfigError("LaggedAdhesion: give the coupled law's delta_t or the compliant layer's k_shear, "
                              "not both")
        if normal_ratio is not None and not (k_shear is not None and np.isfinite(normal_ratio) and normal_ratio > 0):
            raise ConfigError(f"LaggedAdhesion: normal_ratio (the layer's normal over shear stiffness) must be finite, "
                              f"> 0 and come with k_shear, got {normal_ratio} with k_shear {k_shear}")
        self.normal_ratio = None if normal_ratio is None else float(normal_ratio)
        self.vertices = np.asarray(vertices, dtype=np.int64).reshape(-1, 4)
        p = self.vertices.shape[0]
        self.weights = np.asarray(weights, dtype=float).reshape(p, 4)
        self.normal = np.asarray(normal, dtype=float).reshape(p, 3)
        self.eps, self.beta, self.delta = eps, beta, delta
        self.delta_t = None if delta_t is None else float(delta_t)
        self.k_shear = None if k_shear is None else float(k_shear)
        if self.k_shear is not None:
            self.parameter_names = ("beta", "k_shear")

    def _d(self, x: np.ndarray) -> np.ndarray:
        """``d = sum_j w_j x_j`` (gel vertex minus sheet point) per pair in m, shape ``(p, 3)``."""
        return np.einsum("kj,kjd->kd", self.weights, x[self.vertices])

    def opening(self, x: np.ndarray) -> np.ndarray:
        """``s = n . (sum_j w_j x_j) - eps`` per pair in m, shape ``(p,)``."""
        return np.einsum("kd,kd->k", self._d(x), self.normal) - self.eps

    def active_mask(self, x: np.ndarray) -> np.ndarray:
        """Whether each pair is open (``s > 0``) at ``x`` ``(n, 3)`` m, ``(p,)`` bool: its normal Hessian part
        is non-zero there and switches off where the pair closes, as a penalty contact's switches on below its
        offset (:class:`~sim_core.energies.base.PenaltyContact`: the simplified Newton test compares the
        open pairs of two iterates, :func:`sim_core.contact_set.active_contacts`)."""
        return self.opening(x) > 0.0

    def _terms(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(r (p,), tangential part of d (p, 3), tt = t^2 / delta_t^2 (p,), g = exp(-r - tt) (p,))``."""
        d = self._d(x)
        dn = np.einsum("kd,kd->k", d, self.normal)
        r = np.maximum(dn - self.eps, 0.0) / self.delta
        if self.delta_t is None:
            return r, np.zeros_like(d), np.zeros_like(r), np.exp(-r)
        dt = d - dn[:, None] * self.normal
        tt = np.einsum("kd,kd->k", dt, dt) / self.delta_t ** 2
        return r, dt, tt, np.exp(-r - tt)

    def energy(self, x: np.ndarray) -> float:
        """Adhesion energy in J (0 when every pair is pressed without shear, negative of the work of separation)."""
        r, _, _, g = self._terms(x)
        if self.normal_ratio is None:
            out = float(self.beta * self.delta * np.e * np.sum(1.0 - (1.0 + r) * g))
        else:
            out = 0.5 * self.normal_ratio * self.k_shear * float(np.sum((r * self.delta) ** 2))
        if self.k_shear is not None:
            dt = self._shear_opening(x)
            out += 0.5 * self.k_shear * float(np.einsum("kd,kd->", dt, dt))
        return out

    def _shear_opening(self, x: np.ndarray) -> np.ndarray:
        """``P d`` per pair in m (the lagged normal's projector), shape ``(p, 3)``."""
        d = self._d(x)
        return d - np.einsum("kd,kd->k", d, self.normal)[:, None] * self.normal

    def _normal_force(self, r: np.ndarray, beta: float, k_shear: float | None) -> tuple[np.ndarray, np.ndarray]:
        """The pair's normal force ``f`` (N) and its slope in the opening ``df/ds`` (N/m) at ``r = max(s, 0) / delta``
        (``(p,)`` each; the coupled law's shear factor aside): the cohesive law's ``beta e r e^-r``, or the layer's
        normal spring ``rho k_t max(s, 0)`` (module docstring, normal compliance)."""
        open_ = (r > 0).astype(float)
        if self.normal_ratio is not None:
            k_n = self.normal_ratio * float(k_shear or 0.0)
            return k_n * r * self.delta, k_n * open_
        g = np.exp(-r)
        return beta * np.e * r * g, beta * np.e * (1.0 - r) * g * open_ / self.delta

    def _gradient_with(self, x: np.ndarray, beta: float, k_shear: float | None = None) -> np.ndarray:
        r, dt, _, g = self._terms(x)
        # dE/dd = beta e r g n + beta delta e (1 + r) g 2 P d / delta_t^2
        f = beta * np.e * r * g if self.delta_t is not None else self._normal_force(r, beta, k_shear)[0]
        gd = f[:, None] * self.normal
        if self.delta_t is not None:
            gd = gd + (2.0 * beta * self.delta * np.e * (1.0 + r) * g / self.delta_t ** 2)[:, None] * dt
        if k_shear:
            gd = gd + k_shear * self._shear_opening(x)
        return scatter_gradient(x.shape[0], self.vertices, self.weights[:, :, None] * gd[:, None, :])

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """dE/dx in N (the bond force is its negative), shape ``(n, 3)``."""
        return self._gradient_with(x, self.beta, self.k_shear)

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """Blocks ``(w w^T) (x) H_d`` with ``H_d`` the 3 x 3 Hessian of the pair's energy in ``d`` (projected per
        pair: a rank-one ``w w^T`` keeps it PSD), of the open pairs (every pair with shear), shape ``(a, 12, 12)``."""
        if projection not in ("none", "clamp", "abs"):
            raise ValueError(f"unknown PSD projection {projection!r}; use 'none', 'clamp' or 'abs'")
        r, dt, _, g = self._terms(x)
        act = np.flatnonzero(r > 0) if self.delta_t is None and self.k_shear is None else np.arange(r.size)
        if act.size == 0:
            return HessianBlocks.empty(4)
        r, dt, g, n = r[act], dt[act], g[act], self.normal[act]
        A = self.beta * self.delta * np.e
        open_ = (r > 0).astype(float)
        gn = open_[:, None] * n / self.delta  # grad r
        H = self._normal_force(r, self.beta, self.k_shear)[1][:, None, None] * np.einsum("ki,kj->kij", n, n)
        if self.delta_t is not None:
            H = (A * (1.0 - r) * g)[:, None, None] * np.einsum("ki,kj->kij", gn, gn)
            gT = 2.0 * dt / self.delta_t ** 2  # grad of t^2 / delta_t^2
            P = np.eye(3)[None] - np.einsum("ki,kj->kij", n, n)
            H = H + (A * -r * g)[:, None, None] * (np.einsum("ki,kj->kij", gn, gT) + np.einsum("ki,kj->kij", gT, gn))
            H = H + (A * -(1.0 + r) * g)[:, None, None] * np.einsum("ki,kj->kij", gT, gT)
            H = H + (A * (1.0 + r) * g * 2.0 / self.delta_t ** 2)[:, None, None] * P
        if self.k_shear is not None:
            H = H + self.k_shear * (np.eye(3)[None] - np.einsum("ki,kj->kij", n, n))
        if projection != "none":
            lam, V = np.linalg.eigh(H)
            lam = np.maximum(lam, 0.0) if projection == "clamp" else np.abs(lam)
            H = np.einsum("kij,kj,klj->kil", V, lam, V)
        w = self.weights[act]
        blocks = np.einsum("ka,kb,kij->kaibj", w, w, H).reshape(act.size, 12, 12)
        return HessianBlocks(self.vertices[act], blocks)

    def normal_state_jacobian(self, x: np.ndarray, x_prev: np.ndarray) -> np.ndarray:
        """d(dE/dd)/d(x^n) of each pair through its lagged normal: ``(p, 3, 9)``, the columns the x, y, z of the
        pair's sheet triangle's vertices at ``x_prev`` (``vertices[:, 1:]``), N/m.

        The normal ``n`` is frozen at ``x^n`` (module docstring); an anchored bond's is its triangle's unit normal
        there, so ``dn = sign (I - n n^T) dc / |c|`` with ``c = (b - a) x (c - a)``. Pairs whose normal is not
        their triangle's (a new pair whose nearest point lies on an edge or a vertex, where ``n`` is along
        ``d(x^n)`` and the weights move with ``x^n`` too) and the coupled law's (``delta_t``) are held (zeros),
        as the contact pair set is. The pair's gradient in ``d`` is ``f(r) n + k_t P d`` (``f = beta e r e^-r``,
        ``r = max(n.d - eps, 0) / delta``; the layer's normal spring ``f = rho k_t max(n.d - eps, 0)``), so
        ``d/dn = (df/ds) n d^T + f I - k_t (n d^T + (n.d) I)``.
        Without this column the forward tangents of a carried card were 26-40 % off central differences after
        two steps of lift (tests/sim_core/test_adhesion_tangents.py, session 55)."""
        p = self.vertices.shape[0]
        out = np.zeros((p, 3, 9))
        if p == 0 or self.delta_t is not None:
            return out
        tri = self.vertices[:, 1:]
        a, b, c = x_prev[tri[:, 0]], x_prev[tri[:, 1]], x_prev[tri[:, 2]]
        e1, e2 = b - a, c - a
        cr = np.cross(e1, e2)
        length = np.linalg.norm(cr, axis=1)
        nf = cr / np.where(length > 0, length, 1.0)[:, None]
        cos = np.einsum("kd,kd->k", nf, self.normal)
        face = (np.abs(cos) > 1.0 - 1e-9) & (length > 0)
        if not face.any():
            return out
        n, d = self.normal, self._d(x)
        dn_dc = (np.sign(cos) / np.where(length > 0, length, 1.0))[:, None, None] * (
            np.eye(3)[None] - np.einsum("ki,kj->kij", nf, nf))
        dc = np.concatenate([_skew(e2) - _skew(e1), -_skew(e2), _skew(e1)], axis=2)  # dc/d(a, b, c), (p, 3, 9)
        dn_d = np.einsum("kd,kd->k", d, n)
        r = np.maximum(dn_d - self.eps, 0.0) / self.delta
        f, fp = self._normal_force(r, self.beta, self.k_shear)
        nd = np.einsum("ki,kj->kij", n, d)
        A = fp[:, None, None] * nd + f[:, None, None] * np.eye(3)[None]
        if self.k_shear:
            A = A - self.k_shear * (nd + dn_d[:, None, None] * np.eye(3)[None])
        out[face] = np.matmul(A, np.matmul(dn_dc, dc))[face]
        return out

    def normal_state_product(self, x: np.ndarray, x_prev: np.ndarray, dxn: np.ndarray) -> np.ndarray:
        """``d(dE/dx)/d(x^n) dxn`` through the lagged normals (:meth:`normal_state_jacobian`); ``dxn`` ``(n, 3, r)``,
        result ``(n, 3, r)``."""
        out = np.zeros(dxn.shape)
        if self.vertices.shape[0] == 0:
            return out
        J = self.normal_state_jacobian(x, x_prev)
        gd = np.matmul(J, dxn[self.vertices[:, 1:]].reshape(J.shape[0], 9, -1))  # (p, 3, r)
        np.add.at(out, self.vertices.reshape(-1), (self.weights[:, :, None, None] * gd[:, None]).reshape(
            -1, 3, dxn.shape[2]))
        return out

    def normal_state_vjp(self, x: np.ndarray, x_prev: np.ndarray, w: np.ndarray) -> np.ndarray:
        """The transpose of :meth:`normal_state_product`: ``w^T d(dE/dx)/d(x^n)``, ``w`` ``(n, 3)``, result
        ``(n, 3)``."""
        out = np.zeros(w.shape)
        if self.vertices.shape[0] == 0:
            return out
        J = self.normal_state_jacobian(x, x_prev)
        wd = np.einsum("ka,kad->kd", self.weights, w[self.vertices])  # (p, 3)
        np.add.at(out, self.vertices[:, 1:].reshape(-1), np.einsum("kij,ki->kj", J, wd).reshape(-1, 3))
        return out

    def parameter_gradient(self, x: np.ndarray, name: str) -> np.ndarray:
        """d(dE/dx)/d ``name`` (linear in either): ``"beta"`` dimensionless force per N (zero with the layer's
        normal spring), ``"k_shear"`` m (the shear openings ``P d``, plus ``rho max(s, 0) n`` with the normal spring,
        scattered), shape ``(n, 3)``.

        Raises:
            KeyError: ``name`` not in :attr:`parameter_names`.
        """
        if name == "beta":
            return self._gradient_with(x, 1.0)
        if name == "k_shear" and name in self.parameter_names:
            shear = self._shear_opening(x)
            if self.normal_ratio is not None:
                shear = shear + (self.normal_ratio * np.maximum(self.opening(x), 0.0))[:, None] * self.normal
            return scatter_gradient(x.shape[0], self.vertices, self.weights[:, :, None] * shear[:, None, :])
        raise KeyError(f"LaggedAdhesion has no parameter {name!r}; known: {self.parameter_names}")


def _skew(v: np.ndarray) -> np.ndarray:
    """``[v]_x`` per row (``[v]_x u = v x u``), ``(p, 3)`` -> ``(p, 3, 3)``."""
    out = np.zeros((v.shape[0], 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return out
