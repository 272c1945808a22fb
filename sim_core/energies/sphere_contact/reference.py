"""Penalty contact between vertices and a rigid sphere whose centre is a (kinematic) vertex.

A rigid spherical indenter is represented exactly by its centre ``c`` and radius ``R`` instead of
a faceted surface mesh: the signed distance of a vertex ``x_i`` to the sphere is

    d_i = |x_i - c| - R,

smooth everywhere outside the centre, so Newton sees no facet edges (a faceted indenter makes the
contact normal jump as a gel vertex slides from one facet to the next, and Newton's active set
chatters on a fine gel surface). Energy per vertex, as for every penalty pair in
:mod:`sim_core.energies.contact.reference` (DESIGN.md "Contact"): ``E = k_c / 2 (d - eps)^2`` for
``d < eps``, else 0.

Derivatives with ``r = |x_i - c|``, ``n = (x_i - c) / r`` and ``P = I - n n^T``:
``grad_{x_i} d = n``, ``grad_c d = -n``, ``hess d = [[P, -P], [-P, P]] / r``, so the 6 x 6 Hessian of
``E`` over ``(x_i, c)`` is ``[[A, -A], [-A, A]]`` with ``A = k_c n n^T + k_c (d - eps) / r P``. Its
eigenvalues are ``2 k_c`` (normal), ``2 k_c (d - eps) / r`` (twice, tangential; negative in
contact) and 0 (rigid translation of the pair), so the PSD projection is in closed form: ``clamp``
drops the tangential term, ``abs`` flips its sign.
"""

from __future__ import annotations

import numpy as np

from sim_core.energies.base import HessianBlocks, Projection, sum_by_copy
from sim_core.energies.contact.reference import ContactFrames
from sim_core.errors import ConfigError


class SphereContact:
    """Penalty between ``vertices`` and the sphere of radius ``radius`` centred at ``x[center]``.

    Args:
        vertices: global indices of the vertices that may touch the sphere, shape ``(v,)``.
        center: global index of the sphere's centre vertex (kinematic: fixed or effector-driven).
        radius: sphere radius R in m (> 0).
        stiffness: penalty stiffness k_c in N/m (> 0).
        eps: contact offset in m (> 0).

    Raises:
        ConfigError: non-positive or non-finite radius, stiffness or eps; the centre listed among
            ``vertices``.
    """

    parameter_names: tuple[str, ...] = ("stiffness",)

    def __init__(self, vertices: np.ndarray, center: int, radius: float, stiffness: float, eps: float):
        for label, value in (("radius", radius), ("stiffness", stiffness), ("eps", eps)):
            if not (np.isfinite(value) and value > 0):
                raise ConfigError(f"SphereContact: {label} must be finite and > 0, got {value}")
        self.vertices = np.asarray(vertices, dtype=np.int64).reshape(-1)
        self.center = int(center)
        if np.any(self.vertices == self.center):
            raise ConfigError(f"SphereContact: the centre vertex {self.center} is listed as a contact vertex")
        self.radius = float(radius)
        self.stiffness = float(stiffness)
        self.eps = float(eps)

    def _geometry(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Offsets ``x_i - c`` (v, 3), their lengths r (v,) and signed distances d (v,), m."""
        rel = x[self.vertices] - x[self.center]
        r = np.linalg.norm(rel, axis=1)
        return rel, r, r - self.radius

    def distance(self, x: np.ndarray) -> np.ndarray:
        """Signed distance ``|x_i - c| - R`` of every vertex in m, shape ``(v,)``."""
        return self._geometry(x)[2]

    def active_mask(self, x: np.ndarray) -> np.ndarray:
        """Vertices with ``d < eps``, bool shape ``(v,)``."""
        return self.distance(x) < self.eps

    def _active(self, x: np.ndarray):
        rel, r, d = self._geometry(x)
        act = np.flatnonzero(d < self.eps)
        if np.any(r[act] <= 1e-12 * self.radius):
            bad = int(self.vertices[act][np.argmin(r[act])])
            raise ConfigError(f"SphereContact: vertex {bad} is at the sphere's centre (no contact normal)")
        return act, rel[act] / r[act, None], r[act], d[act]

    def energy(self, x: np.ndarray) -> float:
        """Penalty energy in J."""
        gap = np.minimum(self.distance(x) - self.eps, 0.0)
        return float(0.5 * self.stiffness * np.sum(gap * gap))

    def copy_energies(self, x: np.ndarray, copy_of_vertex: np.ndarray, copy_count: int) -> np.ndarray:
        """:meth:`energy` split by the copy of each vertex, J ``(copy_count,)`` (capability
        :class:`~sim_core.energies.base.CopyEnergies`; the sphere's centre is of the same copy)."""
        gap = np.minimum(self.distance(x) - self.eps, 0.0)
        return 0.5 * self.stiffness * sum_by_copy(copy_of_vertex, self.vertices, gap * gap, copy_count)

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """``k_c (d - eps) n`` on each active vertex and minus their sum on the centre, N, ``(n, 3)``."""
        act, n, _, d = self._active(x)
        f = self.stiffness * (d - self.eps)[:, None] * n
        g = np.zeros_like(x, dtype=float)
        np.add.at(g, self.vertices[act], f)
        g[self.center] -= f.sum(axis=0)
        return g

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """Blocks ``[[A, -A], [-A, A]]`` over ``(x_i, c)`` of the active vertices, shape ``(a, 6, 6)``.

        ``A = k_c n n^T + s k_c (d - eps) / r (I - n n^T)`` with ``s = 1`` (``none``), ``0``
        (``clamp``) or ``-1`` (``abs``): the closed-form projection (module docstring).
        """
        act, n, r, d = self._active(x)
        nn = n[:, :, None] * n[:, None, :]
        sign = {"none": 1.0, "clamp": 0.0, "abs": -1.0}[projection]
        a = self.stiffness * nn + (sign * self.stiffness * (d - self.eps) / r)[:, None, None] * (np.eye(3) - nn)
        blocks = np.empty((act.size, 6, 6))
        blocks[:, :3, :3] = a
        blocks[:, 3:, 3:] = a
        blocks[:, :3, 3:] = -a
        blocks[:, 3:, :3] = -a
        pairs = np.stack([self.vertices[act], np.full(act.size, self.center, dtype=np.int64)], axis=1)
        return HessianBlocks(pairs, blocks)

    def parameter_gradient(self, x: np.ndarray, name: str) -> np.ndarray:
        """d(dE/dx)/d(stiffness) = ``(d - eps) n`` (and the reaction on the centre), m, ``(n, 3)``."""
        if name != "stiffness":
            raise KeyError(name)
        return self.gradient(x) / self.stiffness

    def contact_frames(self, x: np.ndarray) -> ContactFrames:
        """Active vertices against the centre: weights ``(1, -1)``, outward normal, ``k_c (eps - d)``."""
        act, n, _, d = self._active(x)
        pairs = np.stack([self.vertices[act], np.full(act.size, self.center, dtype=np.int64)], axis=1)
        weights = np.tile([1.0, -1.0], (act.size, 1))
        return ContactFrames(pairs, weights, n, self.stiffness * (self.eps - d), act)
