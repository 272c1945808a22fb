"""Anisotropic bending (paper/card grain): hinge stiffness ``k_h (1 + beta cos 2 phi_h)``.

Candidate ``anisotropic_bending`` of SYSID.md. ``phi_h`` is the angle between hinge h's rest edge
and the sheet's x axis (in the sheet plane), so edges along x (fold lines along x, i.e. bending
about the x axis) get ``(1 + beta) k_h``, edges along y ``(1 - beta) k_h`` and diagonal edges
``k_h``; ``beta = 0`` is the isotropic discrete shell of
:class:`~sim_core.energies.hinge_bending.reference.DiscreteShellBending` (Grinspun et al. 2003). This is the
lowest angular harmonic of an orthotropic plate (``D(phi) = D_x cos^2 phi + D_y sin^2 phi`` gives
``beta = (D_x - D_y) / (D_x + D_y)``).

The candidate is the *extra* energy added to the sheet's bending (whichever model the sheet uses,
hinge or Kirchhoff; the extra term uses the hinge weights ``k_h`` of the discrete shell),

    E = sum_h beta cos(2 phi_h) k_h (theta_h - theta_bar_h)^2,

whose per-hinge coefficient ``c_h = beta cos(2 phi_h)`` is negative on some hinges. Hessian blocks:
with ``projection="none"`` the exact ``c_h H_h`` (``H_h`` the hinge block of the discrete shell);
otherwise ``max(c_h, 0) P(H_h)`` (``"clamp"``) or ``|c_h| P(H_h)`` (``"abs"``) with ``P`` the PSD
projection, so the solver's matrix stays positive semi-definite whatever the base bending model
(the softening hinges are left to the line search, a quasi-Newton step).
"""

from __future__ import annotations

import numpy as np

from sim_core.energies.base import HessianBlocks, Projection
from sim_core.energies.hinge_bending.reference import DiscreteShellBending
from sim_core.errors import ConfigError


def hinge_grain_cosine(hinges: np.ndarray, x_rest: np.ndarray, grain_axis: np.ndarray | None = None) -> np.ndarray:
    """``cos(2 phi_h)`` of each hinge's rest edge with the grain axis (default world x).

    Args:
        hinges: ``(h, 4)`` global ``[e0, e1, opp0, opp1]``.
        x_rest: rest positions in m, shape ``(n, 3)``.
        grain_axis: unit-able direction in the sheet plane, shape ``(3,)``.

    Returns:
        shape ``(h,)``: ``2 cos^2 phi - 1`` with ``cos phi = |e . a| / (|e| |a|)``.
    """
    axis = np.array([1.0, 0.0, 0.0]) if grain_axis is None else np.asarray(grain_axis, dtype=float)
    e = x_rest[hinges[:, 1]] - x_rest[hinges[:, 0]]
    c = (e @ axis) / (np.linalg.norm(e, axis=1) * np.linalg.norm(axis))
    return 2.0 * c * c - 1.0


class AnisotropicBendingCorrection:
    """The anisotropic part of a sheet's bending energy (module docstring).

    Args:
        bending: a :class:`DiscreteShellBending` of the sheet (hinges, D, rest angles).
        x_rest: rest positions in m, shape ``(n, 3)`` (defines the hinge angles).
        beta: anisotropy, ``-1 < beta < 1`` (0 = off).
        grain_axis: grain direction, shape ``(3,)`` (default world x).

    Raises:
        ConfigError: ``|beta| >= 1`` or non-finite.
    """

    parameter_names: tuple[str, ...] = ("beta",)

    def __init__(self, bending: DiscreteShellBending, x_rest: np.ndarray, beta: float,
                 grain_axis: np.ndarray | None = None) -> None:
        beta = float(beta)
        if not (np.isfinite(beta) and abs(beta) < 1.0):
            raise ConfigError(f"AnisotropicBendingCorrection: beta must satisfy |beta| < 1, got {beta}")
        self.bending = bending
        self.vertices = bending.hinges
        self.beta = beta
        self.hinge_cos2phi = hinge_grain_cosine(bending.hinges, np.asarray(x_rest, dtype=float), grain_axis)

    def energy(self, x: np.ndarray) -> float:
        """Extra bending energy in J (may be negative; the sheet's total is not)."""
        return self.bending._energy_with(x, self.beta * self.hinge_cos2phi * self.bending.hinge_stiffness)

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """dE/dx in N, shape ``(n, 3)``."""
        return self.bending._gradient_with(x, self.beta * self.hinge_cos2phi * self.bending.hinge_stiffness)

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """Per-hinge 12x12 blocks, shape ``(h, 12, 12)`` (module docstring for the projection)."""
        c = self.beta * self.hinge_cos2phi
        if projection == "clamp":
            c = np.maximum(c, 0.0)
        elif projection == "abs":
            c = np.abs(c)
        h = self.bending.hessian(x, projection)
        return HessianBlocks(h.vertices, c[:, None, None] * h.blocks)

    def parameter_gradient(self, x: np.ndarray, name: str) -> np.ndarray:
        """d(dE/dx)/d beta, N, shape ``(n, 3)``.

        Raises:
            KeyError: ``name`` is not ``"beta"``.
        """
        if name != "beta":
            raise KeyError(f"AnisotropicBendingCorrection has no parameter {name!r}; known: {self.parameter_names}")
        return self.bending._gradient_with(x, self.hinge_cos2phi * self.bending.hinge_stiffness)
