"""Saint Venant-Kirchhoff tetrahedra: a solid whose elasticity is written in the Green strain.

Per linear tet, with ``F`` the deformation gradient and ``E = (F^T F - I) / 2`` the Green-Lagrange strain::

    psi(F) = mu tr(E^2) + lam / 2 tr(E)^2,        S = 2 mu E + lam tr(E) I,        P = F S,

``mu``, ``lam`` the small-strain Lamé parameters of ``E``, ``nu`` (Ogden, Non-linear Elastic Deformations, 1984,
sec. 4.4; Bonet and Wood, Nonlinear Continuum Mechanics for FE Analysis, 2nd ed., eq. 6.8). At small strain it is
linear elasticity with ``E``, ``nu``, as Stable Neo-Hookean (:mod:`sim_core.energies.neohookean`) is; the two laws
part at second order in the strain. The part that matters for a pressed and sheared gel at nu -> 0.5: in simple
shear ``gamma`` the Green strain has ``E_zz = gamma^2 / 2`` with no change of volume, so ``lam tr(E)`` puts a
compressive stress of order ``lam gamma^2 / 2`` normal to the sheared layer (``lam / mu = 9`` at nu 0.45), and in
compression the law softens (``S_zz -> 0`` as the stretch falls to ``1 / sqrt 3`` uniaxially). This is the
constitutive law of MuJoCo's flex solids (``plugin/elasticity/solid.cc``: the squared edge-length changes times a
metric ``mu tr(T_i T_j) + lam tr(T_i) tr(T_j)``, i.e. StVK on linear tets), the engine of the reference recordings.
It is here to measure what that law does to a pressed, sliding gel (docs/known_answers.md, "the slide"), not as a
default.

Derivatives (row-major ``vec F``, index ``3 i + j``)::

    dP_ij / dF_ab = delta_ia S_bj + mu ((F F^T)_ia delta_jb + F_ib F_aj) + lam F_ij F_ab,

a symmetric 9x9 per tet, mapped by ``dF/dx`` to 12x12 vertex blocks (the exact ones contracted in closed form,
:meth:`GreenStrainSolid.exact_blocks`); the PSD projection clamps (or flips) its negative eigenvalues per tet
(:func:`sim_core.energies.base.project_psd`, numerically here; the Taichi kernels use StVK's analytic eigensystem in
the singular values, :mod:`sim_core.energies.green_strain.kernel`). Inverted tets are not barriered (StVK's energy
does not grow without bound as ``det F -> 0``); the pressed gel's strains (< 15 %) are far from it.
"""

from __future__ import annotations

import copy

import numpy as np

from sim_core.energies.base import BorrowedWorkspace, HessianBlocks, Projection, project_psd
from sim_core.energies.neohookean.reference import StableNeoHookean


def linear_lame_parameters(youngs_modulus: float, poisson_ratio: float) -> tuple[float, float]:
    """Small-strain Lamé parameters ``(mu, lam)`` in Pa of ``E`` (Pa), ``nu``."""
    E, nu = float(youngs_modulus), float(poisson_ratio)
    return E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


def _linear_lame_derivatives(youngs_modulus: float, poisson_ratio: float, name: str) -> tuple[float, float]:
    """``(d mu / d p, d lam / d p)`` for ``p`` = ``youngs_modulus`` or ``poisson_ratio``."""
    E, nu = float(youngs_modulus), float(poisson_ratio)
    if name == "youngs_modulus":
        mu, lam = linear_lame_parameters(E, nu)
        return mu / E, lam / E
    return -E / (2.0 * (1.0 + nu) ** 2), E * (1.0 + 2.0 * nu**2) / ((1.0 + nu) * (1.0 - 2.0 * nu)) ** 2


class GreenStrainTets(BorrowedWorkspace):
    """What the Green-strain solids share: a set of linear tetrahedra hosted by the Stable Neo-Hookean of the same
    ``E``, ``nu`` (``dF/dx``, rest volumes, deformation memo), the small-strain Lamé parameters, the Green strain and
    the Hessian of the shear term ``mu tr(E^2)``, and gradient, Hessian and parameter gradient from a law's ``_state``,
    ``_pk1``, ``d2psi_dF2`` and ``exact_blocks`` (:class:`GreenStrainSolid`,
    :class:`sim_core.energies.modified_stvk.ModifiedStVKSolid`). Not a potential itself (no energy).

    Args:
        tets, x_rest, youngs_modulus, poisson_ratio: as :class:`StableNeoHookean`'s (tets ``(k, 4)``, rest
            positions ``(n, 3)`` m, small-strain ``E`` in Pa and ``nu``), and raising as it does.

    Attributes:
        per_tet: the Stable Neo-Hookean of the same ``E``, ``nu`` on the same tets, whose ``dF/dx``, rest volumes
            and deformation memo this reads (and the gel's Maxwell branch takes).
        mu, lam: the small-strain Lamé parameters in Pa.
    """

    parameter_names: tuple[str, ...] = ("youngs_modulus", "poisson_ratio")
    _host = "per_tet"

    def __init__(self, tets: np.ndarray, x_rest: np.ndarray, youngs_modulus: float, poisson_ratio: float) -> None:
        self.per_tet = StableNeoHookean(tets, x_rest, youngs_modulus, poisson_ratio)  # validates E, nu, the mesh
        self.youngs_modulus, self.poisson_ratio = self.per_tet.youngs_modulus, self.per_tet.poisson_ratio
        self.mu, self.lam = linear_lame_parameters(self.youngs_modulus, self.poisson_ratio)
        self.tets, self.tet_rest_volume = self.per_tet.tets, self.per_tet.tet_rest_volume

    @property
    def tet_dFdx(self) -> np.ndarray:
        """``dF/dx`` per tet, ``(k, 4, 3)`` in 1/m (the per-tet Stable Neo-Hookean's: the fused kernel reads it)."""
        return self.per_tet.tet_dFdx

    def deformation_gradient(self, x: np.ndarray) -> np.ndarray:
        """``F`` per tet at ``x`` ``(n, 3)``, shape ``(k, 3, 3)`` (the gel candidates' relaxed states read it)."""
        return self.per_tet.deformation_gradient(x)

    def restricted(self, elements: np.ndarray) -> "GreenStrainTets":
        """The same law on the tets ``elements`` ``(j,)`` only (:meth:`StableNeoHookean.restricted` of its
        :attr:`per_tet`, whose arrays this law reads): its Hessian blocks are rows ``elements`` of this one's, bit for
        bit."""
        out = copy.copy(self)
        out.per_tet = self.per_tet.restricted(elements)
        out.tets, out.tet_rest_volume = out.per_tet.tets, out.per_tet.tet_rest_volume
        return out

    def _strain(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(F, E, tr E)`` per tet at ``x`` ``(n, 3)``: shapes ``(k, 3, 3)``, ``(k, 3, 3)``, ``(k,)``."""
        F = self.per_tet._deformation(np.asarray(x, dtype=float))
        E = 0.5 * (np.matmul(np.swapaxes(F, 1, 2), F) - np.eye(3))
        return F, E, np.trace(E, axis1=1, axis2=2)

    def _shear_d2psi_dF2(self, F: np.ndarray, E: np.ndarray) -> np.ndarray:
        """``d2/dF2`` of ``mu tr(E^2)``, ``(k, 3, 3, 3, 3)`` in Pa (index ``[k, i, j, a, b]``)::

            delta_ia (2 mu E)_bj + mu ((F F^T)_ia delta_jb + F_ib F_aj)."""
        eye = np.eye(3)
        A = np.einsum("ia,kbj->kijab", eye, 2.0 * self.mu * E)
        A += self.mu * np.einsum("kia,jb->kijab", np.matmul(F, np.swapaxes(F, 1, 2)), eye)
        A += self.mu * np.einsum("kib,kaj->kijab", F, F)
        return A


    def _shear_blocks(self, F: np.ndarray, S: np.ndarray) -> np.ndarray:
        """The 12x12 blocks (per unit rest volume) of ``mu tr(E^2)``'s curvature terms plus the stress term of the
        second Piola-Kirchhoff stress ``S`` ``(k, 3, 3)``, shape ``(k, 4, 3, 4, 3)`` (``[k, a, c, b, d]``; ``g_a`` row
        ``a`` of ``dF/dx``, ``F_c`` row ``c`` of ``F``, ``B = F F^T``)::

            delta_cd g_a.S g_b + mu (g_a.g_b) B_cd + mu (g_b.F_c)(g_a.F_d)."""
        G = self.per_tet.tet_dFdx
        Gt = np.swapaxes(G, 1, 2)
        GF = np.matmul(G, np.swapaxes(F, 1, 2))  # GF[k, a, c] = g_a . F_c
        # H[k, a, c, b, d] by broadcasting, term by term as in the formula
        H = self.mu * np.swapaxes(GF, 1, 2)[:, None, :, :, None] * GF[:, :, None, None, :]
        H += (self.mu * np.matmul(G, Gt))[:, :, None, :, None] * np.matmul(F, np.swapaxes(F, 1, 2))[:, None, :, None, :]
        H += np.matmul(np.matmul(G, S), Gt)[:, :, None, :, None] * np.eye(3)[None, None, :, None, :]
        return H

    # ------------------------------------------------------------------ Potential contract (the laws' shared part)
    def gradient(self, x: np.ndarray) -> np.ndarray:
        """dE/dx in N, shape ``(n, 3)``: ``V_t P(F_t) dF/dx`` summed per vertex (``P`` the law's ``_pk1`` of its
        ``_state``)."""
        x = np.asarray(x, dtype=float)
        return self.per_tet._forces_from_pk1(x, self._pk1(*self._state(x), self.mu, self.lam))

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """Per-tet 12x12 blocks in N/m: ``V_t (dF/dx)^T A (dF/dx)`` with ``A`` the law's 9x9 ``d2psi/dF2`` exact
        (``"none"``: contracted in closed form, the law's ``exact_blocks``) or with its negative eigenvalues clamped /
        flipped (``"clamp"`` / ``"abs"``).

        Raises:
            ValueError: unknown projection.
        """
        if projection == "none":
            return HessianBlocks(self.tets, self.exact_blocks(x))
        A = project_psd(self.d2psi_dF2(x), projection)
        M = self.per_tet.tet_dvecF_dx
        H = np.matmul(np.swapaxes(M, 1, 2), np.matmul(A, M)) * self.tet_rest_volume[:, None, None]
        return HessianBlocks(self.tets, H)

    def parameter_gradient(self, x: np.ndarray, name: str) -> np.ndarray:
        """d(dE/dx)/dp for ``p`` in :attr:`parameter_names`, shape ``(n, 3)`` (``P`` is linear in ``mu``, ``lam``).

        Raises:
            KeyError: unknown parameter name.
        """
        if name not in self.parameter_names:
            raise KeyError(f"{type(self).__name__} has no parameter {name!r}; known: {self.parameter_names}")
        x = np.asarray(x, dtype=float)
        dmu, dlam = _linear_lame_derivatives(self.youngs_modulus, self.poisson_ratio, name)
        return self.per_tet._forces_from_pk1(x, self._pk1(*self._state(x), dmu, dlam))


class GreenStrainSolid(GreenStrainTets):
    """Saint Venant-Kirchhoff energy of a set of linear tetrahedra (module docstring).

    Args:
        tets, x_rest, youngs_modulus, poisson_ratio: as :class:`GreenStrainTets` (and :class:`StableNeoHookean`).

    Attributes:
        per_tet, mu, lam: as :class:`GreenStrainTets`.
    """

    def _state(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(F, E, tr E)`` per tet at ``x`` (:meth:`GreenStrainTets._strain`): the arguments of :meth:`_pk1`."""
        return self._strain(x)

    @staticmethod
    def _pk1(F: np.ndarray, E: np.ndarray, trace: np.ndarray, mu: float, lam: float) -> np.ndarray:
        """``P = F (2 mu E + lam tr(E) I)`` in Pa, ``(k, 3, 3)``."""
        return np.matmul(F, 2.0 * mu * E + lam * trace[:, None, None] * np.eye(3))

    def d2psi_dF2(self, x: np.ndarray) -> np.ndarray:
        """The exact 9x9 ``d2psi/dF2`` per tet at ``x`` (module docstring), ``(k, 9, 9)`` in Pa."""
        F, E, trace = self._strain(x)
        A = self._shear_d2psi_dF2(F, E)
        A += np.einsum("ia,k,bj->kijab", np.eye(3), self.lam * trace, np.eye(3))
        A += self.lam * np.einsum("kij,kab->kijab", F, F)
        return A.reshape(F.shape[0], 9, 9)

    # ------------------------------------------------------------------ Potential contract
    def energy(self, x: np.ndarray) -> float:
        """``sum_t V_t (mu tr(E_t^2) + lam / 2 tr(E_t)^2)`` in J at ``x`` ``(n, 3)`` (0 at rest)."""
        _, E, trace = self._strain(x)
        psi = self.mu * np.einsum("kij,kij->k", E, E) + 0.5 * self.lam * trace**2
        return float(np.dot(self.tet_rest_volume, psi))

    def exact_blocks(self, x: np.ndarray) -> np.ndarray:
        """The exact 12x12 blocks ``V_t M^T (d2psi/dF2) M`` at ``x`` ``(n, 3)``, ``(k, 12, 12)`` in N/m, contracted by
        hand (``g_a`` row ``a`` of ``dF/dx``, ``F_c`` row ``c`` of ``F``, ``B = F F^T``; the module docstring's
        ``d2psi/dF2``)::

            H[3a+c, 3b+d] = V (delta_cd g_a.S g_b + mu (g_a.g_b) B_cd + mu (g_b.F_c)(g_a.F_d) + lam (g_a.F_c)(g_b.F_d)),

        the fused kernel's entries (:mod:`sim_core.energies.green_strain.fused_kernel`); a fifth of the cost of the
        9x9 product (the sensitivities' exact Hessian takes it every step)."""
        F, E, trace = self._strain(x)
        H = self._shear_blocks(F, 2.0 * self.mu * E + self.lam * trace[:, None, None] * np.eye(3))
        GF = np.matmul(self.per_tet.tet_dFdx, np.swapaxes(F, 1, 2))  # GF[k, a, c] = g_a . F_c
        H += self.lam * GF[:, :, :, None, None] * GF[:, None, None, :, :]
        return H.reshape(F.shape[0], 12, 12) * self.tet_rest_volume[:, None, None]
