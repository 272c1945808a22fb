"""Gel viscoelasticity: a standard linear solid (Zener) model of the elastomer.

Candidate ``gel_viscoelasticity`` of SYSID.md. The gel's Stable Neo-Hookean energy (modulus E) is
the equilibrium spring; a Maxwell branch in parallel adds ``beta`` times the same energy density
evaluated on the elastic part of a multiplicative split ``F = F_e F_r`` (Sidoroff 1974; Reese &
Govindjee 1998), where the per-tet internal variable ``F_r`` is the branch's relaxed rest state:

    E_branch = beta sum_t V_t psi_SNH(F_t F_r,t^{-1}; E, nu).

``beta`` is the ratio of the branch stiffness to the equilibrium stiffness (instantaneous modulus
``(1 + beta) E``, relaxed modulus ``E``), ``beta = 0`` is off. Since ``F F_r^{-1} = D_s (F_r D_m)^{-1}``
the branch is a Stable Neo-Hookean potential whose rest edge matrix is ``F_r D_m`` (rest volume
kept), so its gradient and PSD-projected Hessian are those of
:class:`~sim_core.energies.neohookean.reference.StableNeoHookean`, scaled by ``beta``.

After each converged step the relaxed state flows towards the current deformation (exact
exponential integration of ``dF_r/dt = (F - F_r) / tau`` with ``F`` held over the step):

    F_r <- F_r + (1 - exp(-dt / tau)) (F - F_r),

so at constant indentation the branch stress, hence the extra contact force, decays like
``exp(-t / tau)`` in the small-strain limit, and the markers creep.
"""

from __future__ import annotations

import numpy as np

from sim_core.energies.base import HessianBlocks, Projection
from sim_core.energies.green_strain.reference import GreenStrainSolid
from sim_core.energies.neohookean.reference import StableNeoHookean
from sim_core.energies.nodal_pressure.reference import NodalPressureNeoHookean
from sim_core.errors import ConfigError


class MaxwellBranch:
    """The Maxwell branch of the standard linear solid on a gel (module docstring).

    Args:
        solid: the gel's equilibrium :class:`StableNeoHookean` (tets, rest shape, E, nu); a
            :class:`NodalPressureNeoHookean` or :class:`~sim_core.energies.green_strain.GreenStrainSolid` gel gets the
            branch of its per-tet Stable Neo-Hookean (``per_tet``).
        tet_relaxed_F: relaxed rest states ``F_r`` per tet, shape ``(k, 3, 3)`` (identity = the
            undeformed gel); must be invertible.
        beta: branch-to-equilibrium stiffness ratio (>= 0; 0 = off).

    Raises:
        ConfigError: negative / non-finite ``beta``, ``tet_relaxed_F`` of the wrong shape,
            non-finite or singular (the message names the tet index).
    """

    parameter_names: tuple[str, ...] = ("beta",)

    def __init__(self, solid: StableNeoHookean | NodalPressureNeoHookean | GreenStrainSolid, tet_relaxed_F: np.ndarray,
                 beta: float) -> None:
        beta = float(beta)
        if not (np.isfinite(beta) and beta >= 0):
            raise ConfigError(f"MaxwellBranch: stiffness ratio beta must be finite and >= 0, got {beta}")
        k = solid.tets.shape[0]
        Fr = np.asarray(tet_relaxed_F, dtype=float)
        if Fr.shape != (k, 3, 3):
            raise ConfigError(f"MaxwellBranch: tet_relaxed_F shape {Fr.shape} != ({k}, 3, 3)")
        det = np.linalg.det(Fr) if k else np.zeros(0)
        bad = np.flatnonzero(~np.isfinite(det) | (det <= 1e-6))
        if bad.size:
            raise ConfigError(f"MaxwellBranch: relaxed state of tet {int(bad[0])} is singular or inverted "
                              f"(det F_r = {det[bad[0]]:.3g})")
        self.beta = beta
        # the branch of a nodal-pressure or Green-strain gel is the per-tet Stable Neo-Hookean of its E, nu (beta of it)
        solid = getattr(solid, "per_tet", solid)
        self.tets = solid.tets
        self.vertices = solid.tets
        branch = object.__new__(StableNeoHookean)
        branch.__dict__.update(solid.__dict__)
        Fr_inv = np.linalg.inv(Fr)
        # dF_e/dx = (dF/dx) F_r^{-1}: tet_dFdx[t, a, j] -> sum_l tet_dFdx[t, a, l] F_r^{-1}[t, l, j].
        branch.tet_dFdx = np.einsum("tal,tlj->taj", solid.tet_dFdx, Fr_inv)
        self.branch = branch
        self._equivalent: StableNeoHookean | None = None

    def elastic_equivalent(self) -> StableNeoHookean:
        """The branch as one :class:`StableNeoHookean` with the same energy, gradient and Hessian (exact
        and PSD-projected, ``beta >= 0``): the branch potential with rest volumes ``beta V_t``. The
        solver evaluates it in the fused Stable Neo-Hookean kernel with the gel's own term
        (:mod:`sim_core.fused_elastic`) instead of through this class's NumPy methods and the dynamic
        Hessian merge or a reference part; the same elements, so the same sparsity pattern. Built once
        per branch."""
        if self._equivalent is None:
            eq = object.__new__(StableNeoHookean)
            eq.__dict__.update(self.branch.__dict__)
            eq.tet_rest_volume = self.beta * self.branch.tet_rest_volume
            self._equivalent = eq
        return self._equivalent

    def elastic_deformation(self, x: np.ndarray) -> np.ndarray:
        """``F_e = F F_r^{-1}`` per tet, shape ``(k, 3, 3)``."""
        return self.branch.deformation_gradient(x)

    def energy(self, x: np.ndarray) -> float:
        """Branch energy in J."""
        return self.beta * self.branch.energy(x) if self.beta else 0.0

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """dE/dx in N, shape ``(n, 3)``."""
        return self.beta * self.branch.gradient(x)

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """Per-tet 12x12 blocks ``beta V (dF_e/dx)^T d2psi (dF_e/dx)``, projected as in SNH."""
        h = self.branch.hessian(x, projection)
        return HessianBlocks(h.vertices, self.beta * h.blocks)

    def parameter_gradient(self, x: np.ndarray, name: str) -> np.ndarray:
        """d(dE/dx)/d beta = the branch force at unit ratio, N, shape ``(n, 3)``.

        Raises:
            KeyError: ``name`` is not ``"beta"``.
        """
        if name != "beta":
            raise KeyError(f"MaxwellBranch has no parameter {name!r}; known: {self.parameter_names}")
        return self.branch.gradient(x)


def relax_state(tet_relaxed_F: np.ndarray, F: np.ndarray, dt: float, tau: float) -> np.ndarray:
    """One step of the relaxation ``F_r <- F_r + (1 - exp(-dt/tau)) (F - F_r)``.

    Args:
        tet_relaxed_F: ``F_r`` at the start of the step, shape ``(k, 3, 3)``.
        F: deformation gradients at the end of the step, shape ``(k, 3, 3)``.
        dt: step in s (> 0).
        tau: relaxation time in s (> 0).

    Returns:
        the new ``F_r``, shape ``(k, 3, 3)`` (a new array).

    Raises:
        ConfigError: non-positive or non-finite ``dt`` or ``tau``.
    """
    if not (np.isfinite(dt) and dt > 0):
        raise ConfigError(f"relax_state: dt must be finite and > 0 s, got {dt}")
    if not (np.isfinite(tau) and tau > 0):
        raise ConfigError(f"relax_state: relaxation time tau must be finite and > 0 s, got {tau}")
    a = -np.expm1(-dt / tau)
    Fr = np.asarray(tet_relaxed_F, dtype=float)
    return Fr + a * (np.asarray(F, dtype=float) - Fr)
