"""Membrane (in-plane stretching) energies of thin shells.

Two models, both vectorised over all elements:

* :class:`StVKMembrane`: Saint Venant-Kirchhoff membrane in plane stress, parameterised by Young's
  modulus, Poisson ratio and thickness so real sheet materials can be entered (e.g. Bonet & Wood,
  "Nonlinear Continuum Mechanics for Finite Element Analysis", ch. 6; the 3x2 deformation gradient
  of a triangle as in Sifakis & Barbic, "FEM simulation of 3D deformable solids", SIGGRAPH 2012
  course, sec. 4).
* :class:`SpringMembrane`: ThinShellLab's edge-length + triangle-area penalty
  ``K_l (1 - l/l0)^2 l0 + K_a (1 - A/A0)^2 A0`` (Wang et al., ICLR 2024, public code).
"""

from __future__ import annotations

import numpy as np

from sim_core.energies.base import HessianBlocks, Projection, project_psd, scatter_gradient
from sim_core.errors import ConfigError, MeshError
from sim_core.mesh.validate import validate_triangles, validate_vertices


def cross_matrix(v: np.ndarray) -> np.ndarray:
    """Skew matrices ``[v]_x`` with ``[v]_x w = v x w``; ``v`` shape ``(..., 3)`` -> ``(..., 3, 3)``."""
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def project_psd_translation_free(blocks: np.ndarray, projection: Projection = "clamp") -> np.ndarray:
    """:func:`project_psd` for element Hessians of translation-invariant energies, done in 3 m - 3 dims.

    An energy that depends only on differences of its m vertices has the 3 rigid translations in the
    null space of its Hessian, so with ``B`` an orthonormal basis of their complement,
    ``H = B (B^T H B) B^T`` and projecting ``B^T H B`` gives exactly the projection of ``H`` at about
    2/3 of the eigen-decomposition cost.

    Args:
        blocks: shape ``(k, 3 m, 3 m)``, symmetric, with ``H @ t = 0`` for every translation ``t``.
        projection: as in :func:`project_psd`.

    Returns:
        shape ``(k, 3 m, 3 m)``.
    """
    if projection == "none" or blocks.shape[0] == 0:
        return blocks
    n = blocks.shape[1]
    translations = np.tile(np.eye(3), (n // 3, 1)) / np.sqrt(n // 3)
    w, v = np.linalg.eigh(np.eye(n) - translations @ translations.T)
    basis = v[:, w > 0.5]  # (3 m, 3 m - 3)
    reduced = project_psd(basis.T @ blocks @ basis, projection)
    return basis @ reduced @ basis.T


def plane_stress_lame(youngs_modulus: float, poisson_ratio: float) -> tuple[float, float]:
    """Plane-stress Lame parameters ``mu = E / (2 (1 + nu))``, ``lam = E nu / (1 - nu^2)`` in Pa."""
    E, nu = youngs_modulus, poisson_ratio
    return E / (2.0 * (1.0 + nu)), E * nu / (1.0 - nu * nu)


class StVKMembrane:
    """Saint Venant-Kirchhoff membrane on a triangle mesh (plane stress).

    Per triangle, with ``F`` the 3x2 deformation gradient with respect to an orthonormal 2-D frame
    of the rest triangle and ``G = (F^T F - I) / 2`` the Green strain:

        E_tri = thickness * rest_area * (mu tr(G^2) + lam / 2 tr(G)^2),
        mu = E / (2 (1 + nu)),  lam = E nu / (1 - nu^2)   (plane-stress Lame parameters).

    First Piola stress ``P = F S`` with ``S = 2 mu G + lam tr(G) I``; the 9x9 Hessian blocks are
    exact (no finite differences) and PSD-projected with :func:`project_psd` (in the
    translation-free subspace, :func:`project_psd_translation_free`).

    Args:
        triangles: global vertex indices, shape ``(t, 3)``.
        x_rest: rest positions of the (global) vertex array in m, shape ``(n, 3)``.
        youngs_modulus: E in Pa, > 0.
        poisson_ratio: nu, -1 < nu < 0.5.
        thickness: sheet thickness in m, > 0.

    Raises:
        ConfigError: E or thickness not finite and > 0, nu outside (-1, 0.5).
        MeshError: bad vertex array or indices, or a degenerate rest triangle (names its index).
    """

    parameter_names: tuple[str, ...] = ("youngs_modulus", "poisson_ratio", "thickness")

    def __init__(
        self,
        triangles: np.ndarray,
        x_rest: np.ndarray,
        youngs_modulus: float,
        poisson_ratio: float,
        thickness: float,
    ) -> None:
        E, nu, h = float(youngs_modulus), float(poisson_ratio), float(thickness)
        if not (np.isfinite(E) and E > 0):
            raise ConfigError(f"StVKMembrane: youngs_modulus must be finite and > 0 Pa, got {youngs_modulus}")
        if not (np.isfinite(nu) and -1.0 < nu < 0.5):
            raise ConfigError(f"StVKMembrane: poisson_ratio must lie in (-1, 0.5), got {poisson_ratio}")
        if not (np.isfinite(h) and h > 0):
            raise ConfigError(f"StVKMembrane: thickness must be finite and > 0 m, got {thickness}")
        x_rest = validate_vertices(x_rest, "StVKMembrane rest shape")
        self.triangles = validate_triangles(x_rest, triangles, "StVKMembrane rest shape")
        self.youngs_modulus, self.poisson_ratio, self.thickness = E, nu, h
        self.mu, self.lam = plane_stress_lame(E, nu)

        X = x_rest[self.triangles]  # (t, 3 vertices, 3)
        e1, e2 = X[:, 1] - X[:, 0], X[:, 2] - X[:, 0]
        n = np.cross(e1, e2)
        n_norm = np.linalg.norm(n, axis=1)
        self.triangle_rest_area = 0.5 * n_norm
        l1 = np.linalg.norm(e1, axis=1)
        t1 = e1 / l1[:, None]
        t2 = np.cross(n / n_norm[:, None], t1)
        # Rest edge matrix in the frame (t1, t2): Dm = [[a, b], [0, c]]; Bm = Dm^-1.
        a, b, c = l1, np.einsum("ij,ij->i", e2, t1), np.einsum("ij,ij->i", e2, t2)
        if np.any(c <= 0):
            bad = int(np.flatnonzero(c <= 0)[0])
            raise MeshError(f"StVKMembrane: rest triangle {bad} is degenerate")
        bm = np.zeros((len(a), 2, 2))
        bm[:, 0, 0], bm[:, 0, 1], bm[:, 1, 1] = 1.0 / a, -b / (a * c), 1.0 / c
        # Shape-function gradients: F = sum_a x_a (x) D_a, D (t, 3 vertices, 2).
        self.triangle_shape_gradient = np.stack([-(bm[:, 0] + bm[:, 1]), bm[:, 0], bm[:, 1]], axis=1)

    def _deformation(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """F (t,3,2), Green strain G (t,2,2) and tr(G) (t,)."""
        F = np.einsum("tad,taj->tdj", x[self.triangles], self.triangle_shape_gradient)
        G = 0.5 * (np.einsum("tdj,tdk->tjk", F, F) - np.eye(2))
        return F, G, G[:, 0, 0] + G[:, 1, 1]

    def _weight(self) -> np.ndarray:
        return self.thickness * self.triangle_rest_area

    def energy(self, x: np.ndarray) -> float:
        """Membrane energy in J; ``x`` shape ``(n, 3)`` in m."""
        _, G, trG = self._deformation(x)
        psi = self.mu * np.einsum("tjk,tjk->t", G, G) + 0.5 * self.lam * trG**2
        return float(np.dot(self._weight(), psi))

    def _gradient_for(self, x: np.ndarray, mu: float, lam: float) -> np.ndarray:
        F, G, trG = self._deformation(x)
        S = 2.0 * mu * G + lam * trG[:, None, None] * np.eye(2)
        P = np.einsum("tdj,tjk->tdk", F, S)
        g = np.einsum("t,taj,tdj->tad", self._weight(), self.triangle_shape_gradient, P)
        return scatter_gradient(x.shape[0], self.triangles, g)

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """dE/dx in N, shape ``(n, 3)``: per triangle ``thickness A0 P D^T``."""
        return self._gradient_for(x, self.mu, self.lam)

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """9x9 blocks per triangle (local DoF ``3 a + d``), PSD-projected per ``projection``.

        d^2 psi / dF_dj dF_ek = delta_de S_jk + mu F_dk F_ej + mu (F F^T)_de delta_jk + lam F_dj F_ek,
        contracted with the shape-function gradients on both sides.
        """
        F, G, trG = self._deformation(x)
        D = self.triangle_shape_gradient
        S = 2.0 * self.mu * G + self.lam * trG[:, None, None] * np.eye(2)
        Q = np.einsum("tdj,tbj->tdb", F, D)  # Q[d, b] = (F D^T)[d, b]
        DSD = np.einsum("taj,tjk,tbk->tab", D, S, D)
        DDt = np.einsum("taj,tbj->tab", D, D)
        FFt = np.einsum("tdj,tej->tde", F, F)
        eye3 = np.eye(3)
        H = (
            np.einsum("tab,de->tadbe", DSD, eye3)
            + self.mu * np.einsum("tdb,tea->tadbe", Q, Q)
            + self.mu * np.einsum("tab,tde->tadbe", DDt, FFt)
            + self.lam * np.einsum("tda,teb->tadbe", Q, Q)
        )
        H = self._weight()[:, None, None] * H.reshape(-1, 9, 9)
        return HessianBlocks(self.triangles, project_psd_translation_free(H, projection))

    def parameter_gradient(self, x: np.ndarray, name: str) -> np.ndarray:
        """d(dE/dx)/d(parameter), shape ``(n, 3)``.

        ``youngs_modulus`` and ``thickness`` scale the energy linearly; for ``poisson_ratio``
        dmu/dnu = -E / (2 (1 + nu)^2) and dlam/dnu = E (1 + nu^2) / (1 - nu^2)^2.

        Raises:
            KeyError: ``name`` is not one of :attr:`parameter_names`.
        """
        if name == "youngs_modulus":
            return self.gradient(x) / self.youngs_modulus
        if name == "thickness":
            return self.gradient(x) / self.thickness
        if name == "poisson_ratio":
            E, nu = self.youngs_modulus, self.poisson_ratio
            dmu = -E / (2.0 * (1.0 + nu) ** 2)
            dlam = E * (1.0 + nu * nu) / (1.0 - nu * nu) ** 2
            return self._gradient_for(x, dmu, dlam)
        raise KeyError(f"StVKMembrane has no parameter {name!r}; known: {self.parameter_names}")


class SpringMembrane:
    """ThinShellLab's membrane: edge-length and triangle-area penalties.

        E = sum_edges K_l (1 - l / l0)^2 l0 + sum_triangles K_a (1 - A / A0)^2 A0

    with rest lengths ``l0`` and rest areas ``A0`` (ThinShellLab uses K_l = K_a = 1000; units of
    K_l are N, of K_a N/m).

    :meth:`hessian` returns one block set with three vertices per element: first the triangles
    (9x9 area blocks), then the edges as elements ``[a, b, b]`` whose third-vertex rows and columns
    are zero (6x6 edge blocks, projected before padding).

    Args:
        triangles: global vertex indices, shape ``(t, 3)``.
        edges: global vertex index pairs, shape ``(e, 2)`` (e.g. ``sheet_topology(...).edges``).
        x_rest: rest positions in m, shape ``(n, 3)``.
        k_length: K_l >= 0.
        k_area: K_a >= 0.

    Raises:
        ConfigError: a stiffness negative or not finite.
        MeshError: bad indices, degenerate rest triangle, or zero-length rest edge (names its index).
    """

    parameter_names: tuple[str, ...] = ("k_length", "k_area")

    def __init__(
        self, triangles: np.ndarray, edges: np.ndarray, x_rest: np.ndarray, k_length: float, k_area: float
    ) -> None:
        for key, value in (("k_length", k_length), ("k_area", k_area)):
            if not (np.isfinite(float(value)) and float(value) >= 0):
                raise ConfigError(f"SpringMembrane: {key} must be finite and >= 0, got {value}")
        x_rest = validate_vertices(x_rest, "SpringMembrane rest shape")
        self.triangles = validate_triangles(x_rest, triangles, "SpringMembrane rest shape")
        edges = np.asarray(edges)
        if edges.ndim != 2 or edges.shape[1] != 2:
            raise MeshError(f"SpringMembrane: edges must have shape (e, 2), got {edges.shape}")
        edges = edges.astype(np.int64)
        out = np.flatnonzero(np.any((edges < 0) | (edges >= x_rest.shape[0]), axis=1))
        if out.size:
            raise MeshError(f"SpringMembrane: edge {int(out[0])} {edges[out[0]].tolist()} has an index out of range")
        self.edges = edges
        # Hessian block vertices: triangles, then each edge padded to 3 vertices (one array for the
        # life of the potential, so the assembler's cached sparsity pattern is reused)
        self._block_vertices = np.concatenate(
            [self.triangles, np.stack([edges[:, 0], edges[:, 1], edges[:, 1]], axis=1)], axis=0)
        self.k_length, self.k_area = float(k_length), float(k_area)
        self.edge_rest_length = np.linalg.norm(x_rest[edges[:, 1]] - x_rest[edges[:, 0]], axis=1)
        if np.any(self.edge_rest_length <= 0):
            bad = int(np.flatnonzero(self.edge_rest_length <= 0)[0])
            raise MeshError(f"SpringMembrane: rest edge {bad} {edges[bad].tolist()} has zero length")
        X = x_rest[self.triangles]
        self.triangle_rest_area = 0.5 * np.linalg.norm(np.cross(X[:, 1] - X[:, 0], X[:, 2] - X[:, 0]), axis=1)

    def _edge_terms(self, x: np.ndarray):
        d = x[self.edges[:, 1]] - x[self.edges[:, 0]]
        length = np.linalg.norm(d, axis=1)
        return d / length[:, None], length

    def _area_terms(self, x: np.ndarray):
        X = x[self.triangles]
        n = np.cross(X[:, 1] - X[:, 0], X[:, 2] - X[:, 0])
        n_norm = np.linalg.norm(n, axis=1)
        n_hat = n / n_norm[:, None]
        # dA/dx_a = 1/2 n_hat x (x_{a-1} - x_{a+1});  dn/dx_a = [x_{a-1} - x_{a+1}]_x.
        w = X[:, [2, 0, 1]] - X[:, [1, 2, 0]]
        dA = 0.5 * np.cross(n_hat[:, None, :], w)
        return X, n_norm, n_hat, w, dA

    def _parts(self, x: np.ndarray, k_length: float, k_area: float) -> tuple[float, np.ndarray]:
        u, length = self._edge_terms(x)
        l0 = self.edge_rest_length
        _, n_norm, _, _, dA = self._area_terms(x)
        A, A0 = 0.5 * n_norm, self.triangle_rest_area
        energy = k_length * np.sum((1.0 - length / l0) ** 2 * l0) + k_area * np.sum((1.0 - A / A0) ** 2 * A0)
        dl = 2.0 * k_length * (length - l0) / l0
        dAe = 2.0 * k_area * (A - A0) / A0
        g = scatter_gradient(x.shape[0], self.edges, np.stack([-dl[:, None] * u, dl[:, None] * u], axis=1))
        g += scatter_gradient(x.shape[0], self.triangles, dAe[:, None, None] * dA)
        return float(energy), g

    def energy(self, x: np.ndarray) -> float:
        """Energy in J; ``x`` shape ``(n, 3)`` in m."""
        return self._parts(x, self.k_length, self.k_area)[0]

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """dE/dx in N, shape ``(n, 3)``."""
        return self._parts(x, self.k_length, self.k_area)[1]

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """Triangle blocks then padded edge blocks (see class docstring), PSD-projected.

        Edge: f(l) = K_l (l - l0)^2 / l0, H_edge = f'' u u^T + f' (I - u u^T) / l on [[+, -], [-, +]].
        Area: g(A) = K_a (A - A0)^2 / A0, H = g'' dA dA^T + g' d^2A with
        d^2A = (J^T (I - n_hat n_hat^T) J / |n| + d^2(n_hat . n)) / 2, J = dn/dx.
        """
        u, length = self._edge_terms(x)
        l0 = self.edge_rest_length
        f1 = 2.0 * self.k_length * (length - l0) / l0
        f2 = 2.0 * self.k_length / l0
        uu = np.einsum("ei,ej->eij", u, u)
        h3 = f2[:, None, None] * uu + (f1 / length)[:, None, None] * (np.eye(3) - uu)
        he = np.zeros((len(l0), 2, 3, 2, 3))
        he[:, 0, :, 0, :] = h3
        he[:, 1, :, 1, :] = h3
        he[:, 0, :, 1, :] = -h3
        he[:, 1, :, 0, :] = -h3
        he = project_psd_translation_free(he.reshape(-1, 6, 6), projection)
        edge_blocks = np.zeros((len(l0), 9, 9))
        edge_blocks[:, :6, :6] = he

        X, n_norm, n_hat, w, dA = self._area_terms(x)
        A, A0 = 0.5 * n_norm, self.triangle_rest_area
        g1 = 2.0 * self.k_area * (A - A0) / A0
        g2 = 2.0 * self.k_area / A0
        J = np.concatenate(
            [cross_matrix(w[:, 0]), cross_matrix(w[:, 1]), cross_matrix(w[:, 2])], axis=2
        )  # (t, 3, 9)
        proj = (np.eye(3) - np.einsum("ti,tj->tij", n_hat, n_hat)) / n_norm[:, None, None]
        d2A = np.einsum("tia,tij,tjb->tab", J, proj, J)
        # n_hat . n is a sum of n_hat . (x_a x x_{a+1}); its block (a, a+1) is -[n_hat]_x.
        skew = cross_matrix(n_hat)
        quad = np.zeros((len(A0), 3, 3, 3, 3))
        for a in range(3):
            b = (a + 1) % 3
            quad[:, a, :, b, :] = -skew
            quad[:, b, :, a, :] = skew
        d2A = 0.5 * (d2A + quad.reshape(-1, 9, 9))
        dAf = dA.reshape(-1, 9)
        ht = g2[:, None, None] * np.einsum("ti,tj->tij", dAf, dAf) + g1[:, None, None] * d2A
        ht = project_psd_translation_free(ht, projection)

        return HessianBlocks(self._block_vertices, np.concatenate([ht, edge_blocks], axis=0))

    def parameter_gradient(self, x: np.ndarray, name: str) -> np.ndarray:
        """d(dE/dx)/dK for ``k_length`` or ``k_area`` (the energy is linear in each), shape ``(n, 3)``.

        Raises:
            KeyError: unknown ``name``.
        """
        if name == "k_length":
            return self._parts(x, 1.0, 0.0)[1]
        if name == "k_area":
            return self._parts(x, 0.0, 1.0)[1]
        raise KeyError(f"SpringMembrane has no parameter {name!r}; known: {self.parameter_names}")
