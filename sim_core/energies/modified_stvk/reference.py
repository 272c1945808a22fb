"""The modified Saint Venant-Kirchhoff solid: Green-strain shear with a volumetric energy in ``ln J``.

Per linear tet, with ``F`` the deformation gradient, ``J = det F`` and ``E = (F^T F - I) / 2`` the Green-Lagrange
strain::

    psi(F) = mu tr(E^2) + lam / 2 (ln J)^2,     S = 2 mu E + lam ln(J) C^-1,     P = 2 mu F E + lam ln(J) F^-T,

``mu``, ``lam`` the small-strain Lamé parameters of ``E``, ``nu`` (the "modified Kirchhoff material" of Belytschko,
Liu and Moran, Nonlinear Finite Elements for Continua and Structures, 2000, sec. 5.4.3; Saint Venant-Kirchhoff,
Ogden 1984 sec. 4.4, with its volumetric term ``lam / 2 tr(E)^2`` written in ``J``). At small strain
``E -> eps`` and ``ln J -> tr eps``: linear elasticity with ``E``, ``nu``, as both other gel laws.

Why this law for a soft, nearly incompressible silicone (nu 0.45-0.49): its bulk response is a function of the
volume ratio ``J`` alone, as an elastomer's is (the volumetric-isochoric split of rubber elasticity; Ogden sec. 7.2),
while Saint Venant-Kirchhoff's ``lam tr(E)`` also answers a change of shape at constant volume; the shear response
is Saint Venant-Kirchhoff's Green-strain term, unchanged. That difference decides the pressed gel's slide:

- Simple shear ``gamma`` of a layer keeps ``J = 1`` and has ``tr E = gamma^2 / 2``. Saint Venant-Kirchhoff's normal
  stress on the layer at fixed thickness is ``(mu + lam / 2) gamma^2`` (tensile: the layer pulls the indenter in;
  ``lam / mu = 9`` at nu 0.45, so 5.5 mu gamma^2), which makes a pad's normal force fall when it slides
  (:mod:`sim_core.energies.green_strain`). Here ``ln J = 0`` and the normal stress is the shear term's alone,
  ``S_zz = mu gamma^2``: the same sign, 1 / (1 + lam / (2 mu)) of it (0.18 at nu 0.45, 0.04 at nu 0.49); a
  compressible neo-Hookean solid's is 0, Stable Neo-Hookean's 0.015 of StVK's, and a rubber's is small and of
  either sign (the Poynting effect). The prediction for a pressed pad sliding at constant depth: the normal force
  lies between the Stable Neo-Hookean gel's and the Green-strain gel's, 0.18 of the way from the first towards the
  second, i.e. near the pressed value, as linear elasticity's normal-tangential coupling ((1 - 2 nu) / (2 (1 - nu))
  = 0.09 at nu 0.45, zero when incompressible; Johnson, Contact Mechanics, 1985, sec. 7.1) has it at small strain.
- In compression the energy grows without bound as ``J -> 0`` (``(ln J)^2``), so no tet inverts; uniaxially
  (``F = diag(l, 1, 1)``) ``dP/dl = mu (3 l^2 - 1) + lam (1 - ln l) / l^2 >= lam - mu > 0`` for every ``l`` in
  ``(0, 1]`` when ``lam > mu`` (nu > 1/4): the stress rises monotonically to infinity, where Saint Venant-
  Kirchhoff's peaks at ``l = 1/sqrt 3`` and falls to zero (the collapse at a sliding pad's leading edge).

Derivatives (row-major ``vec F``, index ``3 i + j``; ``G = F^-T``, ``dG_ij / dF_ab = -G_ib G_aj``)::

    dP_ij / dF_ab = delta_ia S'_bj + mu ((F F^T)_ia delta_jb + F_ib F_aj) + lam (G_ij G_ab - ln(J) G_ib G_aj),

with ``S' = 2 mu E``: a symmetric 9x9 per tet, mapped by ``dF/dx`` to 12x12 vertex blocks; the PSD projection clamps
(or flips) the 9x9's negative eigenvalues per tet (:func:`sim_core.energies.base.project_psd`). A tet with
``J <= 0`` has infinite energy (the line search steps back from it) and a NaN gradient (the solver's divergence
error names the step).
"""

from __future__ import annotations

import numpy as np

from sim_core.energies.green_strain.reference import GreenStrainTets


class ModifiedStVKSolid(GreenStrainTets):
    """Modified Saint Venant-Kirchhoff energy of a set of linear tetrahedra (module docstring).

    Args:
        tets, x_rest, youngs_modulus, poisson_ratio: as :class:`~sim_core.energies.green_strain.GreenStrainTets`
            (tets ``(k, 4)``, rest positions ``(n, 3)`` m, small-strain ``E`` in Pa and ``nu``; raising as
            :class:`~sim_core.energies.neohookean.StableNeoHookean` does).

    Attributes:
        per_tet: the Stable Neo-Hookean of the same ``E``, ``nu`` on the same tets, whose ``dF/dx``, rest volumes
            and deformation memo this reads (and the gel's Maxwell branch takes).
        mu, lam: the small-strain Lamé parameters in Pa.
    """

    def _state(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(F, E, ln J, F^-T)`` per tet at ``x`` ``(n, 3)``: shapes ``(k, 3, 3)``, ``(k, 3, 3)``, ``(k,)``,
        ``(k, 3, 3)``; ``ln J`` and ``F^-T`` are NaN where ``J <= 0``."""
        F, E, _ = self._strain(x)
        J = np.linalg.det(F)
        inverted = J <= 0.0
        log_J = np.log(np.where(inverted, 1.0, J))
        log_J[inverted] = np.nan
        safe = np.where(inverted[:, None, None], np.eye(3), F)
        G = np.swapaxes(np.linalg.inv(safe), 1, 2)
        G[inverted] = np.nan
        return F, E, log_J, G

    @staticmethod
    def _pk1(F: np.ndarray, E: np.ndarray, log_J: np.ndarray, G: np.ndarray, mu: float, lam: float) -> np.ndarray:
        """``P = 2 mu F E + lam ln(J) F^-T`` in Pa, ``(k, 3, 3)``."""
        return 2.0 * mu * np.matmul(F, E) + lam * log_J[:, None, None] * G

    def d2psi_dF2(self, x: np.ndarray) -> np.ndarray:
        """The exact 9x9 ``d2psi/dF2`` per tet at ``x`` (module docstring), ``(k, 9, 9)`` in Pa."""
        F, E, log_J, G = self._state(x)
        A = self._shear_d2psi_dF2(F, E)
        A += self.lam * np.einsum("kij,kab->kijab", G, G)
        A -= self.lam * log_J[:, None, None, None, None] * np.einsum("kib,kaj->kijab", G, G)
        return A.reshape(F.shape[0], 9, 9)

    # ------------------------------------------------------------------ Potential contract
    def energy(self, x: np.ndarray) -> float:
        """``sum_t V_t (mu tr(E_t^2) + lam / 2 (ln J_t)^2)`` in J at ``x`` ``(n, 3)`` (0 at rest; ``inf`` where a tet
        has ``J <= 0``)."""
        _, E, log_J, _ = self._state(x)
        if np.isnan(log_J).any():
            return float("inf")
        psi = self.mu * np.einsum("kij,kij->k", E, E) + 0.5 * self.lam * log_J**2
        return float(np.dot(self.tet_rest_volume, psi))

    def exact_blocks(self, x: np.ndarray) -> np.ndarray:
        """The exact 12x12 blocks ``V_t M^T (d2psi/dF2) M`` at ``x`` ``(n, 3)``, ``(k, 12, 12)`` in N/m, contracted by
        hand: the shear term's (:meth:`GreenStrainTets._shear_blocks` with ``S' = 2 mu E``) plus the volume term's,
        with ``h_a = F^-T g_a`` (``g_a`` row ``a`` of ``dF/dx``)::

            lam (h_a)_c (h_b)_d - lam ln(J) (h_b)_c (h_a)_d,

        about half the cost of the 9x9 product."""
        F, E, log_J, G = self._state(x)
        H = self._shear_blocks(F, 2.0 * self.mu * E)
        GH = np.matmul(self.per_tet.tet_dFdx, np.swapaxes(G, 1, 2))  # GH[k, a, c] = g_a . (F^-T)_c
        H += self.lam * GH[:, :, :, None, None] * GH[:, None, None, :, :]
        H -= (self.lam * log_J)[:, None, None, None, None] * (np.swapaxes(GH, 1, 2)[:, None, :, :, None]
                                                               * GH[:, :, None, None, :])
        return H.reshape(F.shape[0], 12, 12) * self.tet_rest_volume[:, None, None]
