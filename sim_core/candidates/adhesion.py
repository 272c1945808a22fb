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
"""

from __future__ import annotations

import numpy as np

from sim_core.collision import vertex_triangle_candidates
from sim_core.collision.distances import point_triangle_closest_point
from sim_core.energies.base import HessianBlocks, Projection, scatter_gradient
from sim_core.errors import ConfigError


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
    pairs = vertex_triangle_candidates(x_prev, gel_vertices, sheet_triangles, eps + reach)
    empty = (np.zeros((0, 4), np.int64), np.zeros((0, 4)), np.zeros((0, 3)))
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
    return vertices, weights, normal


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


class LaggedAdhesion:
    """Cohesive gel-sheet adhesion over lagged pairs (module docstring).

    Args:
        vertices: ``(p, 4)`` global indices ``[gel vertex, a, b, c]``.
        weights: ``(p, 4)`` closest-point weights ``[1, -b_a, -b_b, -b_c]``.
        normal: ``(p, 3)`` unit normals from the sheet point to the gel vertex.
        eps: contact offset in m (> 0): the opening is measured from it.
        beta: bond strength per pair in N (>= 0; 0 = off).
        delta: opening at peak force in m (> 0).

    Raises:
        ConfigError: negative / non-finite ``beta``, non-positive ``delta`` or ``eps``, bad shapes.
    """

    parameter_names: tuple[str, ...] = ("beta",)

    def __init__(self, vertices: np.ndarray, weights: np.ndarray, normal: np.ndarray, eps: float,
                 beta: float, delta: float) -> None:
        beta, delta, eps = float(beta), float(delta), float(eps)
        if not (np.isfinite(beta) and beta >= 0):
            raise ConfigError(f"LaggedAdhesion: bond strength beta must be finite and >= 0 N, got {beta}")
        if not (np.isfinite(delta) and delta > 0):
            raise ConfigError(f"LaggedAdhesion: delta (opening at peak force) must be > 0 m, got {delta}")
        if not (np.isfinite(eps) and eps > 0):
            raise ConfigError(f"LaggedAdhesion: contact eps must be > 0 m, got {eps}")
        self.vertices = np.asarray(vertices, dtype=np.int64).reshape(-1, 4)
        p = self.vertices.shape[0]
        self.weights = np.asarray(weights, dtype=float).reshape(p, 4)
        self.normal = np.asarray(normal, dtype=float).reshape(p, 3)
        self.eps, self.beta, self.delta = eps, beta, delta

    def opening(self, x: np.ndarray) -> np.ndarray:
        """``s = n . (sum_j w_j x_j) - eps`` per pair in m, shape ``(p,)``."""
        rel = np.einsum("kj,kjd->kd", self.weights, x[self.vertices])
        return np.einsum("kd,kd->k", rel, self.normal) - self.eps

    def active_mask(self, x: np.ndarray) -> np.ndarray:
        """Whether each pair is open (``s > 0``) at ``x`` ``(n, 3)`` m, ``(p,)`` bool: its Hessian block is
        non-zero there and switches off where the pair closes, as a penalty contact's switches on below its
        offset (:class:`~sim_core.energies.base.PenaltyContact`: the simplified Newton test compares the
        open pairs of two iterates, :func:`sim_core.contact_set.active_contacts`)."""
        return self.opening(x) > 0.0

    def _r(self, x: np.ndarray) -> np.ndarray:
        return np.maximum(self.opening(x), 0.0) / self.delta

    def energy(self, x: np.ndarray) -> float:
        """Adhesion energy in J (0 when every pair is pressed, negative of the work of separation)."""
        r = self._r(x)
        return float(self.beta * self.delta * np.e * np.sum(1.0 - (1.0 + r) * np.exp(-r)))

    def _gradient_with(self, x: np.ndarray, beta: float) -> np.ndarray:
        r = self._r(x)
        force = beta * r * np.exp(1.0 - r)  # phi'(s), N
        g = (force[:, None, None] * self.weights[:, :, None]) * self.normal[:, None, :]
        return scatter_gradient(x.shape[0], self.vertices, g)

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """dE/dx in N: ``phi'(s) w_j n`` (the tensile bond force is its negative), shape ``(n, 3)``."""
        return self._gradient_with(x, self.beta)

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """Blocks ``phi''(s) (w w^T) (x) n n^T`` of the open pairs, shape ``(a, 12, 12)``."""
        if projection not in ("none", "clamp", "abs"):
            raise ValueError(f"unknown PSD projection {projection!r}; use 'none', 'clamp' or 'abs'")
        s = self.opening(x)
        act = np.flatnonzero(s > 0)
        if act.size == 0:
            return HessianBlocks.empty(4)
        r = s[act] / self.delta
        k = self.beta / self.delta * (1.0 - r) * np.exp(1.0 - r)
        if projection == "clamp":
            k = np.maximum(k, 0.0)
        elif projection == "abs":
            k = np.abs(k)
        wn = (self.weights[act][:, :, None] * self.normal[act][:, None, :]).reshape(act.size, 12)
        return HessianBlocks(self.vertices[act], k[:, None, None] * wn[:, :, None] * wn[:, None, :])

    def parameter_gradient(self, x: np.ndarray, name: str) -> np.ndarray:
        """d(dE/dx)/d beta (linear in beta), dimensionless force per N, shape ``(n, 3)``.

        Raises:
            KeyError: ``name`` is not ``"beta"``.
        """
        if name != "beta":
            raise KeyError(f"LaggedAdhesion has no parameter {name!r}; known: {self.parameter_names}")
        return self._gradient_with(x, 1.0)
