"""Stable Neo-Hookean elasticity of tetrahedral solids (the tactile-sensor gel).

Smith, de Goes, Kim 2018, "Stable Neo-Hookean Flesh Simulation" (ACM TOG 37(2)), eq. 14 with the
rest-stable shift of section 3.4::

    psi(F) = mu/2 (I_C - 3) + lam/2 (J - alpha)^2 - mu/2 log((I_C + 1) / 4) - 9 mu^2 / (32 lam)
    alpha  = 1 + 3 mu / (4 lam)          ( = 1 + mu/lam - mu/(4 lam) )

with ``I_C = tr(F^T F)`` and ``J = det F``. The two constants (``log 4`` and ``9 mu^2/(32 lam)``)
only make ``psi(I) = 0``; they change no force. ``alpha`` makes ``P(I) = 0`` (rest stability).

Lamé reparameterisation (paper section 3.4, re-derived here): expanding ``psi`` to second order in
``H = F - I`` gives ``3 mu/8 (|H|^2 + tr(H H)) + (lam/2 - 5 mu/16) (tr H)^2``, i.e. linear
elasticity with ``mu_LE = 3 mu / 4`` and ``lam_LE = lam - 5 mu / 8``. So, from the user's Young's
modulus ``E`` and Poisson ratio ``nu``::

    mu_LE = E / (2 (1 + nu)),   lam_LE = E nu / ((1 + nu)(1 - 2 nu))
    mu    = 4/3 mu_LE,          lam    = lam_LE + 5/6 mu_LE   (> 0 for every nu in (-1, 0.5))

and the small-strain response equals linear elasticity with the given ``E``, ``nu``.

Discretisation: linear tets, ``F = D_s D_m^{-1}`` with ``D_s = [x1-x0, x2-x0, x3-x0]``; energy
``sum_t V_t psi(F_t)`` with rest volume ``V_t``. PSD projection uses the paper's analytic eigensystem of the
9x9 ``d2psi/dF2`` (section 4.2: 3 twist, 3 flip and 3 scaling modes from a rotation-variant SVD);
negative eigenvalues are clamped (or flipped) and the result is mapped to the 12x12 vertex block
by ``dF/dx`` (a congruence, so the block stays PSD). ``projection="none"`` gives the exact Hessian.
SNH is defined for inverted tets (``J <= 0``): no log of ``J`` appears, so no NaN.
"""

from __future__ import annotations

import copy

import numpy as np

from sim_core.energies.base import HessianBlocks, Projection, scatter_gradient
from sim_core.errors import ConfigError
from sim_core.mesh.validate import validated_tet_volumes
from sim_core.workspace import workspace_of

_PAIRS = ((1, 2), (2, 0), (0, 1))
"""Index pairs (i, j) of the twist/flip modes; the third index of pair k is k."""

_LEVI_CIVITA = np.zeros((3, 3, 3))
for _i, _j, _k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
    _LEVI_CIVITA[_i, _j, _k] = 1.0
    _LEVI_CIVITA[_i, _k, _j] = -1.0


def _d2J_gather() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Non-zeros of d2J/dF_ij dF_kl = eps_ikm eps_jln F_mn in the row-major 9x9 layout.

    Only ``i != k`` and ``j != l`` give a term, and then a single one, ``+-F_mn``: returns the flat
    positions ``9 (3 i + j) + 3 k + l`` (36), the flat index ``3 m + n`` of F and the sign.
    """
    pos, src, sign = [], [], []
    for i, j, k, l in np.ndindex(3, 3, 3, 3):
        for m, n in np.ndindex(3, 3):
            e = _LEVI_CIVITA[i, k, m] * _LEVI_CIVITA[j, l, n]
            if e != 0.0:
                pos.append(9 * (3 * i + j) + 3 * k + l)
                src.append(3 * m + n)
                sign.append(e)
    return np.array(pos), np.array(src), np.array(sign)


_D2J_POS, _D2J_SRC, _D2J_SIGN = _d2J_gather()


def snh_lame_parameters(youngs_modulus: float, poisson_ratio: float) -> tuple[float, float]:
    """SNH Lamé parameters ``(mu, lam)`` in Pa whose linearisation has modulus ``E`` and ratio ``nu``.

    ``mu = 4/3 mu_LE``, ``lam = lam_LE + 5/6 mu_LE`` (Smith et al. 2018, section 3.4).
    """
    E, nu = float(youngs_modulus), float(poisson_ratio)
    mu_le = E / (2.0 * (1.0 + nu))
    lam_le = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return 4.0 / 3.0 * mu_le, lam_le + 5.0 / 6.0 * mu_le


def _snh_lame_derivatives(youngs_modulus: float, poisson_ratio: float, name: str) -> tuple[float, float]:
    """``(d mu / d p, d lam / d p)`` for ``p`` = ``youngs_modulus`` or ``poisson_ratio``."""
    E, nu = float(youngs_modulus), float(poisson_ratio)
    if name == "youngs_modulus":
        mu, lam = snh_lame_parameters(E, nu)
        return mu / E, lam / E
    dmu_le = -E / (2.0 * (1.0 + nu) ** 2)
    dlam_le = E * (1.0 + 2.0 * nu**2) / ((1.0 + nu) * (1.0 - 2.0 * nu)) ** 2
    return 4.0 / 3.0 * dmu_le, dlam_le + 5.0 / 6.0 * dmu_le


def _cofactor(F: np.ndarray) -> np.ndarray:
    """``dJ/dF = cof F``: column j is the cross product of the other two columns (in order)."""
    f0, f1, f2 = F[..., :, 0], F[..., :, 1], F[..., :, 2]
    return np.stack([np.cross(f1, f2), np.cross(f2, f0), np.cross(f0, f1)], axis=-1)


def _rotation_variant_svd(F: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``F = U diag(sigma) V^T`` with ``det U = det V = +1``; ``sigma_3 < 0`` when ``det F < 0``
    (Irving et al. 2004; Smith et al. 2018, section 4). Shapes ``(k,3,3), (k,3), (k,3,3)``."""
    U, sigma, Vh = np.linalg.svd(F)
    V = np.swapaxes(Vh, 1, 2).copy()
    flip_u = np.linalg.det(U) < 0.0
    U[flip_u, :, 2] *= -1.0
    sigma[flip_u, 2] *= -1.0
    flip_v = np.linalg.det(V) < 0.0
    V[flip_v, :, 2] *= -1.0
    sigma[flip_v, 2] *= -1.0
    return U, sigma, V


class StableNeoHookean:
    """Stable Neo-Hookean energy of a set of linear tetrahedra.

    Args:
        tets: global vertex indices, shape ``(k, 4)``, positively oriented at rest.
        x_rest: global rest positions in m, shape ``(n, 3)``.
        youngs_modulus: ``E`` in Pa, > 0 (small-strain modulus).
        poisson_ratio: ``nu``, -1 < nu < 0.5 (small-strain ratio).

    Raises:
        ConfigError: ``E`` not finite and > 0, ``nu`` outside (-1, 0.5).
        MeshError: bad indices, non-finite rest positions, inverted or degenerate rest tets
            (the message names the tet index and its signed volume).
    """

    parameter_names: tuple[str, ...] = ("youngs_modulus", "poisson_ratio")

    def __init__(self, tets: np.ndarray, x_rest: np.ndarray, youngs_modulus: float, poisson_ratio: float) -> None:
        E, nu = float(youngs_modulus), float(poisson_ratio)
        if not (np.isfinite(E) and E > 0):
            raise ConfigError(f"StableNeoHookean youngs_modulus must be finite and > 0 Pa, got {youngs_modulus!r}")
        if not (np.isfinite(nu) and -1.0 < nu < 0.5):
            raise ConfigError(f"StableNeoHookean poisson_ratio must lie in (-1, 0.5), got {poisson_ratio!r}")
        x_rest = np.asarray(x_rest, dtype=float)
        self.tets, self.tet_rest_volume = validated_tet_volumes(x_rest, tets, "StableNeoHookean rest shape")
        self.youngs_modulus = E
        self.poisson_ratio = nu
        self.mu, self.lam = snh_lame_parameters(E, nu)
        self.alpha = 1.0 + 0.75 * self.mu / self.lam
        Dm = self._edge_matrix(x_rest)
        Dm_inv = np.linalg.inv(Dm)
        # tet_dFdx[t, a, j] = dF_ij / dx_{a,i} (same for every i): rows 1..3 are D_m^{-1}, row 0 minus their sum.
        self.tet_dFdx = np.concatenate([-Dm_inv.sum(axis=1, keepdims=True), Dm_inv], axis=1)
        self._dvecF_dx: tuple[np.ndarray, np.ndarray] | None = None  # (tet_dFdx, tet_dvecF_dx) made from it

    @property
    def tet_dvecF_dx(self) -> np.ndarray:
        """:attr:`tet_dFdx` as a matrix, ``(k, 9, 12)``: ``[t, 3 i + j, 3 a + c] = delta_ic tet_dFdx[t, a, j]``
        (``d vec(F) / d x`` of each tet, for the NumPy Hessian). Made at the first read from the current
        ``tet_dFdx`` and kept with it (a new ``tet_dFdx`` object gets a new matrix); the fused kernels do not
        read it (108 floats a tet)."""
        kept = self.__dict__.get("_dvecF_dx")
        if kept is None or kept[0] is not self.tet_dFdx:
            k = self.tet_dFdx.shape[0]
            kept = (self.tet_dFdx, np.einsum("ic,taj->tijac", np.eye(3), self.tet_dFdx).reshape(k, 9, 12))
            self._dvecF_dx = kept
        return kept[1]

    def restricted(self, elements: np.ndarray) -> "StableNeoHookean":
        """The same law on the tets ``elements`` only: a shallow copy with those rows of :attr:`tets`, the rest
        volumes and ``dF/dx`` (and of ``d vec(F)/dx`` where made), and a private workspace (:mod:`sim_core.workspace`).
        Its energy, gradient and Hessian are this potential's restricted to those tets: its Hessian blocks are rows
        ``elements`` of this one's, bit for bit (each tet's block is computed from its own rows alone). For a product
        with a Hessian supported on a few vertices (:meth:`sim_core.adjoint.StepLinearization.support_product`).

        Args:
            elements: tet indices into :attr:`tets`, ``(j,)`` int.
        """
        elements = np.asarray(elements, dtype=np.int64)
        out = copy.copy(self)
        out.__dict__.pop("workspace", None)  # a private memo: the copy's arrays are its own
        out.tets, out.tet_rest_volume, out.tet_dFdx = self.tets[elements], self.tet_rest_volume[elements], self.tet_dFdx[elements]
        kept = self.__dict__.get("_dvecF_dx")
        out._dvecF_dx = None if kept is None or kept[0] is not self.tet_dFdx else (out.tet_dFdx, kept[1][elements])
        return out

    # ------------------------------------------------------------------ kinematics and densities
    def _edge_matrix(self, x: np.ndarray) -> np.ndarray:
        """``D = [x1 - x0, x2 - x0, x3 - x0]`` (edges as columns), shape ``(k, 3, 3)``."""
        p = x[self.tets]
        return np.swapaxes(p[:, 1:] - p[:, :1], 1, 2)

    def deformation_gradient(self, x: np.ndarray) -> np.ndarray:
        """``F = D_s D_m^{-1}`` per tet, shape ``(k, 3, 3)``."""
        p = np.asarray(x, dtype=float)[self.tets]  # (k, 4, 3)
        return np.einsum("kai,kaj->kij", p, self.tet_dFdx)

    def _deformation(self, x: np.ndarray) -> np.ndarray:
        """:meth:`deformation_gradient` kept with ``x`` in the workspace (:mod:`sim_core.workspace`):
        energy, gradient and Hessian of one iterate (the line search's accepted point is the next
        iterate) share it and its invariants."""
        workspace = workspace_of(self)
        # owned by tet_dFdx: copies with the same dF/dx share it, a copy with other dF/dx (the
        # Maxwell branch) does not
        kept = workspace.get(self.tet_dFdx, "deformation")
        if kept is not None and np.array_equal(kept[0], x):
            return kept[1]
        F = self.deformation_gradient(x)
        workspace.put(self.tet_dFdx, "deformation", (np.array(x, dtype=float, copy=True), F, []))
        return F

    def _invariants(self, F: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(I_C, J, cof F)``, shapes ``(k,), (k,), (k, 3, 3)``; memoised for the kept ``F``."""
        kept = workspace_of(self).get(self.tet_dFdx, "deformation")
        memo = kept[2] if kept is not None and kept[1] is F else None
        if memo:
            return memo[0]
        out = (np.einsum("kij,kij->k", F, F), np.linalg.det(F), _cofactor(F))
        if memo is not None:
            memo.append(out)
        return out

    def _psi(self, F: np.ndarray, mu: float, lam: float) -> np.ndarray:
        I_C, J, _ = self._invariants(F)
        alpha = 1.0 + 0.75 * mu / lam
        return (
            0.5 * mu * (I_C - 3.0)
            + 0.5 * lam * (J - alpha) ** 2
            - 0.5 * mu * np.log((I_C + 1.0) / 4.0)
            - 9.0 * mu**2 / (32.0 * lam)
        )

    def _pk1_parts(self, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``P = mu P_mu + lam P_lam`` (P is linear in mu, lam once alpha is substituted).

        ``P_mu = (1 - 1/(I_C + 1)) F - 3/4 cof F``, ``P_lam = (J - 1) cof F``.
        """
        I_C, J, cof = self._invariants(F)
        P_mu = (1.0 - 1.0 / (I_C + 1.0))[:, None, None] * F - 0.75 * cof
        P_lam = (J - 1.0)[:, None, None] * cof
        return P_mu, P_lam

    def first_piola(self, F: np.ndarray) -> np.ndarray:
        """PK1 stress ``P = dpsi/dF`` in Pa, shape ``(k, 3, 3)``.

        ``P = mu (1 - 1/(I_C+1)) F + lam (J - alpha) cof F`` (Smith et al. 2018, eq. 18).
        """
        P_mu, P_lam = self._pk1_parts(F)
        return self.mu * P_mu + self.lam * P_lam

    def _forces_from_pk1(self, x: np.ndarray, P: np.ndarray) -> np.ndarray:
        """``dE/dx_a = V P g_a`` with ``g_a = tet_dFdx[a]``; scattered to shape ``(n, 3)``."""
        element_grad = self.tet_rest_volume[:, None, None] * np.einsum("kij,kaj->kai", P, self.tet_dFdx)
        return scatter_gradient(x.shape[0], self.tets, element_grad)

    def with_lame(self, mu: float, lam: float) -> "StableNeoHookean":
        """A copy with the SNH Lamé parameters ``(mu, lam)`` in Pa (both > 0) in place of the ones of
        its ``E`` and ``nu``, sharing the tets and ``dF/dx`` (so the workspace's deformation memo): the
        shear part of :class:`~sim_core.energies.nodal_pressure.reference.NodalPressureNeoHookean`, whose
        ``lam`` has a Poisson ratio of -1 that ``E``, ``nu`` cannot name. Its ``parameter_gradient``
        stays that of the original's ``E``, ``nu`` and must not be used.

        Raises:
            ConfigError: ``mu`` or ``lam`` not finite and > 0.
        """
        if not (np.isfinite(mu) and mu > 0 and np.isfinite(lam) and lam > 0):
            raise ConfigError(f"StableNeoHookean Lamé parameters must be finite and > 0 Pa, got mu={mu!r}, lam={lam!r}")
        out = copy.copy(self)
        out.mu, out.lam = float(mu), float(lam)
        out.alpha = 1.0 + 0.75 * out.mu / out.lam
        return out

    def d2psi_dF2(self, F: np.ndarray, pressure: np.ndarray | None = None) -> np.ndarray:
        """``d2psi / dF_ij dF_kl``, shape ``(k, 3, 3, 3, 3)`` (symmetric as a 9x9 matrix).

        ``mu (1 - 1/(I_C+1)) I + 2 mu/(I_C+1)^2 F (x) F + lam cof (x) cof + lam (J - alpha) d2J/dF2``
        with ``d2J/dF_ij dF_kl = eps_ikm eps_jln F_mn`` (Smith et al. 2018, eqs. 19-21).
        ``pressure`` ``(k,)`` in Pa, if given, adds ``p d2J/dF2`` per tet (the second derivative of a
        pressure's work ``p J`` at fixed ``p``: the nodal-pressure element's averaged pressure).
        """
        I_C, J, cof = self._invariants(F)
        k = F.shape[0]
        f, c = F.reshape(k, 9), cof.reshape(k, 9)
        A = np.zeros((k, 9, 9))
        A[:, np.arange(9), np.arange(9)] = (self.mu * (1.0 - 1.0 / (I_C + 1.0)))[:, None]
        A += (2.0 * self.mu / (I_C + 1.0) ** 2)[:, None, None] * (f[:, :, None] * f[:, None, :])
        A += self.lam * (c[:, :, None] * c[:, None, :])
        A = A.reshape(k, 81)
        # d2J has 36 non-zeros +-F_mn (see _d2J_gather): a gather instead of a 9x9x9 contraction
        stretch = self.lam * (J - self.alpha) if pressure is None else self.lam * (J - self.alpha) + pressure
        A[:, _D2J_POS] += stretch[:, None] * (_D2J_SIGN * f[:, _D2J_SRC])
        return A.reshape(k, 3, 3, 3, 3)

    def d2psi_dF2_eigensystem(self, F: np.ndarray,
                              pressure: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Analytic eigen-decomposition of the 9x9 ``d2psi/dF2`` (Smith et al. 2018, section 4.2).

        With the rotation-variant SVD ``F = U diag(sigma) V^T`` and ``mu_t = mu (1 - 1/(I_C+1))``:

        - twist ``U (e_i e_j^T - e_j e_i^T) V^T / sqrt 2``: ``mu_t + lam (J - alpha) sigma_k``,
        - flip  ``U (e_i e_j^T + e_j e_i^T) V^T / sqrt 2``: ``mu_t - lam (J - alpha) sigma_k``,
          for ``(i, j, k)`` a cyclic permutation of ``(0, 1, 2)``,
        - scaling ``U diag(z) V^T`` with ``z`` the eigenvectors of the Hessian of ``psi`` in the
          principal stretches: ``mu_t delta_ij + 2 mu sigma_i sigma_j / (I_C+1)^2 + lam dJ_i dJ_j
          + lam (J - alpha) d2J_ij`` (``dJ_i = J / sigma_i`` as a product, ``d2J_ij = sigma_k``).

        Args:
            F: deformation gradients, shape ``(k, 3, 3)``.
            pressure: ``(k,)`` in Pa or None: adds ``p d2J/dF2`` as :meth:`d2psi_dF2` does; the
                eigenvectors are the same, ``p`` joins ``lam (J - alpha)`` in every eigenvalue.

        Returns:
            ``(eigenvalues (k, 9) in Pa, eigenvectors (k, 9, 9))``; column ``m`` of the eigenvector
            array is a unit vector in the row-major flattening ``3 i + j`` of ``F``.
        """
        U, sigma, V = _rotation_variant_svd(F)
        k = F.shape[0]
        I_C = np.sum(sigma**2, axis=1)
        J = np.prod(sigma, axis=1)
        mu_t = self.mu * (1.0 - 1.0 / (I_C + 1.0))
        stretch = self.lam * (J - self.alpha) if pressure is None else self.lam * (J - self.alpha) + pressure
        dJ = np.stack([sigma[:, 1] * sigma[:, 2], sigma[:, 2] * sigma[:, 0], sigma[:, 0] * sigma[:, 1]], axis=1)
        S = (2.0 * self.mu / (I_C + 1.0) ** 2)[:, None, None] * sigma[:, :, None] * sigma[:, None, :]
        S += self.lam * dJ[:, :, None] * dJ[:, None, :]
        S += mu_t[:, None, None] * np.eye(3)
        for c, (i, j) in enumerate(_PAIRS):
            S[:, i, j] += stretch * sigma[:, c]
            S[:, j, i] += stretch * sigma[:, c]
        w_scale, z = np.linalg.eigh(S)
        # outer[t, i, j] = vec(U e_i e_j^T V^T) = U[:, i] (x) V[:, j], shape (k, 3, 3, 9)
        outer = np.einsum("tai,tbj->tijab", U, V).reshape(k, 3, 3, 9)
        values = np.empty((k, 9))
        vectors = np.empty((k, 9, 9))
        values[:, :3] = w_scale
        vectors[:, :, :3] = np.einsum("tiv,tiia->tav", z, outer)
        r = 1.0 / np.sqrt(2.0)
        for c, (i, j) in enumerate(_PAIRS):
            values[:, 3 + c] = mu_t + stretch * sigma[:, c]
            vectors[:, :, 3 + c] = r * (outer[:, i, j] - outer[:, j, i])
            values[:, 6 + c] = mu_t - stretch * sigma[:, c]
            vectors[:, :, 6 + c] = r * (outer[:, i, j] + outer[:, j, i])
        return values, vectors

    def d2psi_dF2_projected(self, F: np.ndarray, projection: Projection,
                            pressure: np.ndarray | None = None) -> np.ndarray:
        """The 9x9 ``d2psi/dF2`` (plus ``p d2J/dF2`` for a ``pressure`` ``(k,)`` in Pa) per tet, ``(k, 9, 9)``:
        exact (``"none"``) or with the negative eigenvalues of :meth:`d2psi_dF2_eigensystem` clamped to 0
        (``"clamp"``) or flipped (``"abs"``).

        Raises:
            ValueError: unknown projection.
        """
        if projection == "none":
            return self.d2psi_dF2(F, pressure).reshape(F.shape[0], 9, 9)
        if projection in ("clamp", "abs"):
            w, Q = self.d2psi_dF2_eigensystem(F, pressure)
            w = np.maximum(w, 0.0) if projection == "clamp" else np.abs(w)
            return np.matmul(Q * w[:, None, :], np.swapaxes(Q, 1, 2))
        raise ValueError(f"unknown PSD projection {projection!r}; use 'none', 'clamp' or 'abs'")

    # ------------------------------------------------------------------ Potential contract
    def energy(self, x: np.ndarray) -> float:
        """Energy ``sum_t V_t psi(F_t)`` in J at positions ``x`` ``(n, 3)`` (0 at rest)."""
        F = self._deformation(x)
        return float(np.dot(self.tet_rest_volume, self._psi(F, self.mu, self.lam)))

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """dE/dx in N, shape ``(n, 3)``: ``V_t P(F_t) (dF/dx)`` summed per vertex."""
        x = np.asarray(x, dtype=float)
        return self._forces_from_pk1(x, self.first_piola(self._deformation(x)))

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """Per-tet 12x12 Hessian blocks in N/m.

        Args:
            x: positions ``(n, 3)``.
            projection: ``"none"`` (exact), ``"clamp"`` or ``"abs"``: applied to the 9x9
                ``d2psi/dF2`` of each tet before mapping ``V (dF/dx)^T A (dF/dx)``.

        Returns:
            :class:`HessianBlocks` with ``vertices = tets`` ``(k, 4)`` and blocks ``(k, 12, 12)``.
        """
        F = self._deformation(x)
        M = self.tet_dvecF_dx
        A = self.d2psi_dF2_projected(F, projection)
        H = np.matmul(np.swapaxes(M, 1, 2), np.matmul(A, M))  # (k, 12, 12) = M^T A M
        H *= self.tet_rest_volume[:, None, None]
        return HessianBlocks(self.tets, H)

    def parameter_gradient(self, x: np.ndarray, name: str) -> np.ndarray:
        """d(dE/dx)/dp for ``p`` in :attr:`parameter_names`, shape ``(n, 3)``.

        ``P = mu P_mu + lam P_lam`` is linear in ``(mu, lam)``, so
        ``dP/dp = dmu/dp P_mu + dlam/dp P_lam`` with the Lamé map of :func:`snh_lame_parameters`.

        Raises:
            KeyError: unknown parameter name.
        """
        if name not in self.parameter_names:
            raise KeyError(f"StableNeoHookean has no parameter {name!r}; known: {self.parameter_names}")
        x = np.asarray(x, dtype=float)
        dmu, dlam = _snh_lame_derivatives(self.youngs_modulus, self.poisson_ratio, name)
        P_mu, P_lam = self._pk1_parts(self._deformation(x))  # F and its invariants kept: one per x for all parameters
        return self._forces_from_pk1(x, dmu * P_mu + dlam * P_lam)
