"""Discrete Kirchhoff plate bending with a Poisson ratio: a per-triangle shape operator from hinge angles.

The hinge energy of :mod:`sim_core.energies.hinge_bending.reference` (Grinspun et al. 2003) penalises each
dihedral angle on its own; it has no Gaussian-curvature term, so anticlastic (saddle) modes cost
almost nothing and a clamped strip sags too far. This module builds, per triangle T, the discrete
shape operator of Grinspun, Gingold, Reisman, Zorin 2006 ("Computing discrete shape operators on
general meshes", Eurographics, the edge-based operator)

    S_T = sum_{i in edges of T} theta_i |e_i| / (2 A_T) t_i t_i^T,

(t_i the in-plane unit normal of edge i, all rest quantities from ``x_rest``) and integrates the
Kirchhoff plate energy density (Timoshenko & Woinowsky-Krieger, "Theory of Plates and Shells", ch. 1)

    psi(S) = (D / 2) [nu tr(S)^2 + (1 - nu) tr(S^2)] = (D / 2) s^T K s,
    s = (S_xx, S_xy, S_yy),  K = [[1, 0, nu], [0, 2 (1 - nu), 0], [nu, 0, 1]],

over the rest area, with theta - theta_bar in place of theta. With s = Q_T theta_T (Q_T constant,
3x3) the energy of T is

    E_T = (D / 2) A_T d^T W_T d,  d = theta_T - theta_bar_T,  W_T = Q_T^T K Q_T.

Calibration (derived, and checked in the tests): a sheet mapped isometrically onto a cylinder of
radius R has theta = l_perp / R on the edges parallel to the axis (l_perp the spacing of those
edges) and 0 elsewhere, so each triangle of an axis-aligned grid has S_T = diag(1/R, 0) exactly
and E = (D / 2) R^-2 area. On a grid whose cells all have the same diagonal (``pattern="regular"``)
a uniform curvature S gives theta_h = h (S_yy + S_xy), theta_v = h (S_xx + S_xy),
theta_d = -sqrt(2) h S_xy, and S_T = S exactly for every S: cylinders in any direction, spheres
(psi = D (1 + nu) k^2) and saddles (psi = D (1 - nu) k^2). On the checkerboard grid
(``pattern="alternating"``) the axis-parallel edges do not see S_xy, and S_T = S -+ S_xy I
alternates between the two cell types: axis-aligned curvature (cylinders along x or y, spheres,
the saddle k (x^2 - y^2) / 2) is exact, off-axis bending is too stiff by the factor
1 + 2 (1 + nu) sin^2(phi) cos^2(phi) (phi: angle of the bending direction to the x axis; 1.49 at
30 degrees for nu = 0.3), and a pure twist S = [[0, k], [k, 0]] (the saddle at 45 degrees) costs
2 D k^2 instead of D (1 - nu) k^2, 2 / (1 - nu) = 2.86x for nu = 0.3 (a clamped strip under an end torque
twists 2.76x too little; on the ``"regular"`` grid 1.10x; tests/sim_core/energies/test_card_known_answers.py).
The operator is nevertheless *stable*: the area average of S_T over a
patch is the integrated curvature measure of the patch (Cohen-Steiner & Morvan 2003), so by
convexity of psi no pattern of folds is cheaper than the smooth surface it approximates. (A
least-squares fit of S_T to its three angles, exact for uniform curvature on any mesh, is not: on
the checkerboard grid it reads crossing diagonal folds as an alternating twist, a spurious soft mode
that made a cantilever 1.5x too compliant.)

Boundary edges (no neighbour, no angle): the angle is left free and eliminated by minimising E_T
over it (static condensation), W_T = R^T (Q^T K Q) R restricted to the interior edges, with
R = I - C (Q^T K Q) and C the inverse of the boundary-boundary block. This is the natural boundary
condition of a free plate edge (zero bending moment M_nn): a narrow strip with nu > 0 curves
anticlastically and bends with the beam stiffness D (1 - nu^2) = E t^3 / 12. A clamped edge is
modelled by fixing the vertices of the first row of cells (its hinges then measure the slope).

Derivatives: dE/dx = sum_i (dE/dtheta_i) dtheta_i/dx, and per triangle the 18x18 Hessian
sum_ij 2 M_ij grad theta_i grad theta_j^T + sum_i (dE_T/dtheta_i) hess theta_i, M_T = (D / 2) A_T W_T,
over the triangle's three vertices and the (up to three) opposite vertices of its neighbours, with
the closed-form derivatives of theta from :mod:`sim_core.energies.hinge_bending.reference`.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from sim_core.energies.base import HessianBlocks, Projection, scatter_gradient
from sim_core.energies.hinge_bending.reference import dihedral_angle, dihedral_angle_gradient, dihedral_angle_hessian
from sim_core.energies.membrane.reference import project_psd_translation_free
from sim_core.errors import ConfigError, MeshError
from sim_core.mesh.validate import validate_triangles, validate_vertices
from sim_core.workspace import workspace_of


def plate_energy_matrix(poisson_ratio: float) -> np.ndarray:
    """K with psi = (D / 2) s^T K s = (D / 2)[nu tr(S)^2 + (1 - nu) tr(S^2)], s = (S_xx, S_xy, S_yy); (3, 3)."""
    nu = poisson_ratio
    return np.array([[1.0, 0.0, nu], [0.0, 2.0 * (1.0 - nu), 0.0], [nu, 0.0, 1.0]])


_PLATE_ENERGY_MATRIX_DNU = np.array([[0.0, 0.0, 1.0], [0.0, -2.0, 0.0], [1.0, 0.0, 0.0]])
"""dK/dnu of :func:`plate_energy_matrix`."""


def triangle_hinge_map(triangles: np.ndarray, hinges: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hinge of each triangle edge and the local slots of the hinge vertices.

    Edge k of triangle (v0, v1, v2) is v_{k+1} v_{k+2} (opposite v_k). The triangle's local vertex
    slots are 0, 1, 2 for v0, v1, v2 and 3 + k for the neighbour's vertex opposite edge k.

    Args:
        triangles: shape ``(t, 3)``.
        hinges: ``[e0, e1, opp0, opp1]``, shape ``(h, 4)``.

    Returns:
        ``triangle_hinge`` ``(t, 3)`` hinge index per edge or -1 (boundary edge),
        ``triangle_opposite`` ``(t, 3)`` global index of the neighbour's opposite vertex or -1,
        ``hinge_slots`` ``(t, 3, 4)`` local slot of each hinge vertex (-1 on boundary edges).

    Raises:
        MeshError: a hinge whose edge is not an edge of exactly two triangles, or whose edge is
            shared by a triangle that is not one of the hinge's two triangles (the message names both).
    """
    t = triangles.shape[0]
    n = int(max(triangles.max(initial=-1), hinges.max(initial=-1))) + 1
    a = triangles[:, [1, 2, 0]]
    b = triangles[:, [2, 0, 1]]
    tri_key = np.minimum(a, b) * n + np.maximum(a, b)  # (t, 3)
    hinge_key = np.minimum(hinges[:, 0], hinges[:, 1]) * n + np.maximum(hinges[:, 0], hinges[:, 1])
    order = np.argsort(hinge_key, kind="stable")
    sorted_keys = hinge_key[order]
    if sorted_keys.size and np.any(sorted_keys[1:] == sorted_keys[:-1]):
        i = int(order[np.flatnonzero(sorted_keys[1:] == sorted_keys[:-1])[0]])
        raise MeshError(f"KirchhoffBending: hinge {i} {hinges[i].tolist()} duplicates another hinge's edge")
    pos = np.clip(np.searchsorted(sorted_keys, tri_key), 0, max(len(sorted_keys) - 1, 0))
    found = sorted_keys[pos] == tri_key if sorted_keys.size else np.zeros(tri_key.shape, bool)
    tri_hinge = np.where(found, order[pos] if sorted_keys.size else -1, -1)

    opposite = np.full((t, 3), -1, dtype=np.int64)
    slots = np.full((t, 3, 4), -1, dtype=np.int64)
    for k in range(3):
        rows = np.flatnonzero(tri_hinge[:, k] >= 0)
        hk = hinges[tri_hinge[rows, k]]
        own = triangles[rows, k]
        is0, is1 = hk[:, 2] == own, hk[:, 3] == own
        bad = np.flatnonzero(~(is0 | is1))
        if bad.size:
            r = int(rows[bad[0]])
            raise MeshError(
                f"KirchhoffBending: triangle {r} {triangles[r].tolist()} shares the edge of hinge "
                f"{int(tri_hinge[r, k])} {hinges[tri_hinge[r, k]].tolist()} but is not one of its triangles"
            )
        opposite[rows, k] = np.where(is0, hk[:, 3], hk[:, 2])
        for j in range(2):  # e0, e1 are vertices k+1, k+2 of the triangle in some order
            slots[rows, k, j] = np.where(hk[:, j] == triangles[rows, (k + 1) % 3], (k + 1) % 3, (k + 2) % 3)
        slots[rows, k, 2] = np.where(is0, k, 3 + k)
        slots[rows, k, 3] = np.where(is0, 3 + k, k)
    count = np.bincount(tri_hinge[tri_hinge >= 0], minlength=hinges.shape[0])
    bad = np.flatnonzero(count != 2)
    if bad.size:
        i = int(bad[0])
        raise MeshError(
            f"KirchhoffBending: hinge {i} {hinges[i].tolist()} is an edge of {int(count[i])} triangle(s), expected 2"
        )
    return tri_hinge, opposite, slots


def shape_operator_matrix(x_rest: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Q_T of the edge-based shape operator: (S_xx, S_xy, S_yy) = Q_T theta_T (module docstring).

    Column k belongs to edge k (v_{k+1} v_{k+2}) and is |e_k| / (2 A_T) (t_x^2, t_x t_y, t_y^2) of the
    edge's in-plane unit normal t in a 2-D orthonormal frame of the rest triangle (x axis along
    v1 - v0, normal (v1 - v0) x (v2 - v0)).

    Args:
        x_rest: rest positions in m, shape ``(n, 3)``.
        triangles: shape ``(t, 3)``, non-degenerate at rest.

    Returns:
        Q, shape ``(t, 3, 3)`` in 1/m.
    """
    X = x_rest[triangles]
    e_x = X[:, 1] - X[:, 0]
    n = np.cross(e_x, X[:, 2] - X[:, 0])
    area = 0.5 * np.linalg.norm(n, axis=1)
    e_x = e_x / np.linalg.norm(e_x, axis=1)[:, None]
    e_y = np.cross(n / (2.0 * area)[:, None], e_x)
    Q = np.zeros((triangles.shape[0], 3, 3))
    for k in range(3):
        e = X[:, (k + 2) % 3] - X[:, (k + 1) % 3]
        le = np.linalg.norm(e, axis=1)
        tx, ty = -np.einsum("ti,ti->t", e, e_y) / le, np.einsum("ti,ti->t", e, e_x) / le
        Q[:, :, k] = (le / (2.0 * area))[:, None] * np.stack([tx * tx, tx * ty, ty * ty], axis=1)
    return Q


class KirchhoffBending:
    """Discrete Kirchhoff plate bending energy with Poisson ratio (see the module docstring).

    E = sum_T (D / 2) A_T d_T^T W_T d_T,  d_T = theta_T - theta_bar_T (the three edge hinges of T).

    Args:
        triangles: global vertex indices of the sheet, shape ``(t, 3)``, consistently oriented.
        hinges: ``[e0, e1, opp0, opp1]`` of the sheet's interior edges, shape ``(h, 4)``
            (:func:`sim_core.mesh.sheet.sheet_topology`).
        x_rest: rest positions of the global vertex array in m, shape ``(n, 3)``.
        bending_stiffness: D in N m (plate: D = E t^3 / (12 (1 - nu^2))), finite and >= 0.
        poisson_ratio: nu, -1 < nu <= 0.5.
        hinge_theta_bar: rest dihedral angles in rad, shape ``(h,)``; default the angles of
            ``x_rest`` (stress-free rest shape).

    Attributes:
        triangle_hinge: hinge index of each triangle edge or -1, shape ``(t, 3)``.
        triangle_weight: W_T (module docstring), shape ``(t, 3, 3)`` in 1/m^2, zero rows/columns
            on boundary edges.
        triangle_stiffness: M_T = (D / 2) A_T W_T in J/rad^2, shape ``(t, 3, 3)``.
        hinge_stiffness_matrix: sparse symmetric ``(h, h)`` K_h with E = d^T K_h d, d = theta - theta_bar
            (so dE/dtheta = 2 K_h d); the coupled counterpart of DiscreteShellBending's diagonal
            ``hinge_stiffness``.

    Raises:
        ConfigError: D negative or not finite; nu outside (-1, 0.5]; bad ``hinge_theta_bar``.
        MeshError: bad triangle/hinge arrays (the message names the element), a hinge that is not
            an edge of the triangles, a degenerate rest triangle.
    """

    parameter_names: tuple[str, ...] = ("bending_stiffness", "poisson_ratio")

    def __init__(
        self,
        triangles: np.ndarray,
        hinges: np.ndarray,
        x_rest: np.ndarray,
        bending_stiffness: float,
        poisson_ratio: float,
        hinge_theta_bar: np.ndarray | None = None,
    ) -> None:
        D, nu = float(bending_stiffness), float(poisson_ratio)
        if not (np.isfinite(D) and D >= 0):
            raise ConfigError(f"KirchhoffBending: bending_stiffness must be finite and >= 0 N m, got {bending_stiffness}")
        if not (-1.0 < nu <= 0.5):
            raise ConfigError(f"KirchhoffBending: poisson_ratio must satisfy -1 < nu <= 0.5, got {poisson_ratio}")
        x_rest = validate_vertices(x_rest, "KirchhoffBending rest shape")
        triangles = validate_triangles(x_rest, triangles, "KirchhoffBending")
        hinges = np.asarray(hinges)
        if hinges.ndim != 2 or hinges.shape[1] != 4:
            raise MeshError(f"KirchhoffBending: hinges must have shape (h, 4), got {hinges.shape}")
        hinges = hinges.astype(np.int64)
        bad = np.flatnonzero(np.any((hinges < 0) | (hinges >= x_rest.shape[0]), axis=1))
        if bad.size:
            i = int(bad[0])
            raise MeshError(f"KirchhoffBending: hinge {i} {hinges[i].tolist()} has a vertex index out of range")
        self.triangles, self.hinges = triangles, hinges
        self.bending_stiffness, self.poisson_ratio = D, nu
        self.vertex_count = x_rest.shape[0]
        self.triangle_hinge, self.triangle_opposite, self._slots = triangle_hinge_map(triangles, hinges)
        self.triangle_rest_area = 0.5 * np.linalg.norm(
            np.cross(x_rest[triangles[:, 1]] - x_rest[triangles[:, 0]], x_rest[triangles[:, 2]] - x_rest[triangles[:, 0]]),
            axis=1,
        )
        self._Q = shape_operator_matrix(x_rest, triangles)
        self._known = self.triangle_hinge >= 0
        self.triangle_weight, self._triangle_weight_dnu = self._weights(nu)
        self.triangle_stiffness = (0.5 * D * self.triangle_rest_area)[:, None, None] * self.triangle_weight
        self.hinge_stiffness_matrix = self._hinge_matrix(self.triangle_stiffness)
        # d K_h / dp per parameter name, built on first use (constant: D and nu are fixed at
        # construction; one dict shared by the copies that replace the rest angles)
        self._parameter_matrices: dict[str, sp.csr_matrix] = {}

        self._scatter_kept: list = []  # _hinge_scatter, made at the first NumPy Hessian (shared by the copies)

        # Hessian block vertices: the triangle + the neighbour opposite each edge (own vertex k on
        # a boundary edge k, whose rows stay zero).
        self.block_vertices = np.where(self._known, self.triangle_opposite, triangles)
        self.block_vertices = np.concatenate([triangles, self.block_vertices], axis=1)

        if hinge_theta_bar is None:
            theta_bar = dihedral_angle(x_rest[hinges]) if len(hinges) else np.zeros(0)
        else:
            theta_bar = np.asarray(hinge_theta_bar, dtype=float)
            if theta_bar.shape != (len(hinges),):
                raise ConfigError(f"KirchhoffBending: hinge_theta_bar shape {theta_bar.shape} != ({len(hinges)},)")
            if not np.all(np.isfinite(theta_bar)):
                raise ConfigError("KirchhoffBending: hinge_theta_bar has non-finite values")
        self.hinge_theta_bar = theta_bar

    def _weights(self, nu: float) -> tuple[np.ndarray, np.ndarray]:
        """W_T condensed over boundary edges (0 on their rows/columns) and dW_T/dnu.

        With W = Q^T K Q, C the inverse of its boundary-boundary block and R = I - C W, the
        condensed form is R^T W R; since R minimises over the boundary angles, its derivative is
        R^T (Q^T dK/dnu Q) R (envelope theorem).
        """
        W = np.einsum("tik,ij,tjl->tkl", self._Q, plate_energy_matrix(nu), self._Q)
        dW = np.einsum("tik,ij,tjl->tkl", self._Q, _PLATE_ENERGY_MATRIX_DNU, self._Q)
        boundary = ~self._known
        bb = boundary[:, :, None] & boundary[:, None, :]
        C = np.where(bb, np.linalg.inv(np.where(bb, W, np.eye(3))), 0.0)
        R = np.eye(3) - C @ W
        kk = self._known[:, :, None] & self._known[:, None, :]
        Rt = np.swapaxes(R, 1, 2)
        return np.where(kk, Rt @ W @ R, 0.0), np.where(kk, Rt @ dW @ R, 0.0)

    @property
    def _hinge_scatter(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
        """:meth:`_hessian_scatter`, made at the first read and kept in a list that the copies replacing the rest
        angles share (the fused kernels do not read it: 3 x 144 int64 a triangle)."""
        if not self._scatter_kept:
            self._scatter_kept.extend(self._hessian_scatter())
        return self._scatter_kept

    def _hessian_scatter(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
        """Per triangle edge k, where each hinge's derivatives go in the triangle's 18-DoF arrays.

        Returns, for k = 0, 1, 2: ``rows`` (triangles with a hinge on edge k), ``hinge`` (that
        hinge), ``grad_index`` ``(m, 12)`` flat positions in the ``(t, 3, 18)`` array of hinge-angle
        gradients and ``hess_index`` ``(m, 144)`` flat positions in the ``(t, 18, 18)`` Hessian.
        Within one k the positions are distinct, so a fancy-indexed ``+=`` accumulates correctly.
        """
        out = []
        for k in range(3):
            rows = np.flatnonzero(self._known[:, k])
            slots = self._slots[rows, k]  # (m, 4) local vertex slot of each hinge vertex
            dof = (3 * slots[:, :, None] + np.arange(3)).reshape(-1, 12)
            grad_index = (rows[:, None] * 3 + k) * 18 + dof
            hess_index = (rows[:, None, None] * 18 + dof[:, :, None]) * 18 + dof[:, None, :]
            out.append((rows, self.triangle_hinge[rows, k], grad_index, hess_index.reshape(-1, 144)))
        return out

    def _hinge_matrix(self, M: np.ndarray) -> sp.csr_matrix:
        """Sum per-triangle (3, 3) forms over the hinges of their edges -> sparse (h, h)."""
        h = self.hinges.shape[0]
        th = self.triangle_hinge
        ok = self._known[:, :, None] & self._known[:, None, :]
        rows = np.broadcast_to(th[:, :, None], M.shape)[ok]
        cols = np.broadcast_to(th[:, None, :], M.shape)[ok]
        return sp.csr_matrix((M[ok], (rows, cols)), shape=(h, h))

    def theta(self, x: np.ndarray) -> np.ndarray:
        """Signed dihedral angle of every hinge in rad, shape ``(h,)``; ``x`` shape ``(n, 3)``."""
        return self._hinge_kinematics(x)[1].copy()

    def theta_stiffness(self) -> sp.csr_matrix:
        """``A = d^2E/dtheta^2 = 2 K_h`` (:attr:`hinge_stiffness_matrix`) in J/rad^2, sparse ``(h, h)``."""
        return sp.csr_matrix(2.0 * self.hinge_stiffness_matrix)

    def theta_stiffness_product(self, v: np.ndarray) -> np.ndarray:
        """``A v`` (:meth:`theta_stiffness`) for ``v`` of shape ``(h, r)``, without copying ``K_h``
        (equal to ``theta_stiffness() @ v`` bit for bit: doubling is exact)."""
        return 2.0 * (self.hinge_stiffness_matrix @ v)

    def theta_gradient(self, x: np.ndarray) -> np.ndarray:
        """``dtheta/dx`` of every hinge, shape ``(h, 4, 3)`` (1/m, over ``hinges``' vertices), at
        ``x`` (n, 3); kept with the angles of ``x`` (:meth:`theta`, gradient and Hessian share them)."""
        return self._hinge_kinematics(x, gradient=True)[2]

    def _hinge_kinematics(self, x: np.ndarray, gradient: bool = False) -> tuple:
        """``(X (h, 4, 3), theta (h,), dtheta/dx (h, 4, 3) or None)`` at ``x``, kept with a copy of
        ``x`` in the workspace (:mod:`sim_core.workspace`) so that energy, gradient and Hessian of one
        iterate share them (they do not depend on the rest angles, which copies of this potential
        replace)."""
        workspace = workspace_of(self)
        kept = workspace.get(self.hinges, "hinge_kinematics")  # owned by the hinges: copies share it
        if kept is None or not np.array_equal(kept[0], x):
            X = x[self.hinges]
            kept = workspace.put(self.hinges, "hinge_kinematics", (np.array(x, dtype=float, copy=True),
                                                                   [X, dihedral_angle(X), None]))
        values = kept[1]
        if gradient and values[2] is None:
            values[2] = dihedral_angle_gradient(values[0])
        return tuple(values)

    def _triangle_deviation(self, theta: np.ndarray) -> np.ndarray:
        """theta_T - theta_bar_T per triangle edge, 0 on boundary edges; shape ``(t, 3)``."""
        d = theta - self.hinge_theta_bar
        return np.where(self._known, d[np.maximum(self.triangle_hinge, 0)], 0.0)

    def triangle_energy(self, x: np.ndarray) -> np.ndarray:
        """Bending energy of each triangle in J, shape ``(t,)``."""
        d = self._triangle_deviation(self.theta(x))
        return np.einsum("tk,tkl,tl->t", d, self.triangle_stiffness, d)

    def energy(self, x: np.ndarray) -> float:
        """Bending energy in J."""
        d = self._hinge_kinematics(x)[1] - self.hinge_theta_bar
        return float(d @ (self.hinge_stiffness_matrix @ d))

    def _gradient_with(self, x: np.ndarray, hinge_matrix: sp.csr_matrix) -> np.ndarray:
        _, theta, grad_h = self._hinge_kinematics(x, gradient=True)
        d = theta - self.hinge_theta_bar
        g_theta = 2.0 * (hinge_matrix @ d)
        return scatter_gradient(x.shape[0], self.hinges, g_theta[:, None, None] * grad_h)

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """dE/dx = sum_h 2 (K_h d)_h dtheta_h/dx in N, shape ``(n, 3)``."""
        return self._gradient_with(x, self.hinge_stiffness_matrix)

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """Per-triangle 18x18 blocks over ``block_vertices`` (t, 6), PSD-projected.

        H_T = sum_ij 2 M_ij grad theta_i grad theta_j^T + sum_i 2 (M d)_i hess theta_i; the sum over
        triangles is the exact Hessian. Projection in the translation-free subspace
        (:func:`~sim_core.energies.membrane.reference.project_psd_translation_free`, equal to
        :func:`~sim_core.energies.base.project_psd` of each block).
        """
        t = self.triangles.shape[0]
        X, theta, grad_h = self._hinge_kinematics(x, gradient=True)  # grad_h (h, 4, 3)
        d = self._triangle_deviation(theta)
        g_theta = 2.0 * np.einsum("tkl,tl->tk", self.triangle_stiffness, d)  # dE_T/dtheta_k
        hess_h = dihedral_angle_hessian(X)  # (h, 12, 12)
        G = np.zeros(t * 3 * 18)
        H = np.zeros(t * 18 * 18)
        for k, (rows, hk, grad_index, hess_index) in enumerate(self._hinge_scatter):
            G[grad_index] = grad_h[hk].reshape(-1, 12)
            H[hess_index] += g_theta[rows, k, None] * hess_h[hk].reshape(-1, 144)
        G = G.reshape(t, 3, 18)
        H = H.reshape(t, 18, 18)
        H += 2.0 * np.matmul(np.swapaxes(G, 1, 2), np.matmul(self.triangle_stiffness, G))
        return HessianBlocks(self.block_vertices, project_psd_translation_free(H, projection))

    def parameter_gradient(self, x: np.ndarray, name: str) -> np.ndarray:
        """d(dE/dx)/dp for p = ``bending_stiffness`` (E is linear in D) or ``poisson_ratio``; ``(n, 3)``.

        Raises:
            KeyError: ``name`` is not in :attr:`parameter_names`.
        """
        K = self._parameter_matrices.get(name)
        if K is None:
            if name == "bending_stiffness":
                M = (0.5 * self.triangle_rest_area)[:, None, None] * self.triangle_weight
            elif name == "poisson_ratio":
                M = (0.5 * self.bending_stiffness * self.triangle_rest_area)[:, None, None] * self._triangle_weight_dnu
            else:
                raise KeyError(f"KirchhoffBending has no parameter {name!r}; known: {self.parameter_names}")
            K = self._parameter_matrices[name] = self._hinge_matrix(M)
        return self._gradient_with(x, K)
