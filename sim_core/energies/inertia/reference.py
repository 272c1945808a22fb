"""Inertia term of the incremental potential (implicit Euler as minimisation).

E_inertia(x) = sum_i m_i / (2 dt^2) |x_i - x_hat_i|^2,  x_hat = x^n + dt v^n
(DESIGN.md "Time stepping"; e.g. Li et al. 2020, IPC, eq. 2). Its Hessian is the diagonal
m_i / dt^2 and is passed to the assembler as a diagonal rather than as blocks.
"""

from __future__ import annotations

import numpy as np

from sim_core.energies.base import HessianBlocks, Projection
from sim_core.errors import ConfigError


class InertiaPotential:
    """Kinetic part of the incremental potential.

    Args:
        vertex_mass: lumped masses in kg, shape ``(n,)``, >= 0.
        x_hat: predicted positions ``x^n + dt v^n`` in m, shape ``(n, 3)``.
        dt: time step in s, > 0.

    Raises:
        ConfigError: non-positive ``dt``, negative or non-finite masses, shape mismatch.
    """

    parameter_names: tuple[str, ...] = ("mass_scale",)

    def __init__(self, vertex_mass: np.ndarray, x_hat: np.ndarray, dt: float) -> None:
        vertex_mass = np.asarray(vertex_mass, dtype=float)
        if not dt > 0:
            raise ConfigError(f"time step dt must be > 0, got {dt}")
        if np.any(~np.isfinite(vertex_mass)) or np.any(vertex_mass < 0):
            raise ConfigError("vertex masses must be finite and >= 0")
        if x_hat.shape != (vertex_mass.shape[0], 3):
            raise ConfigError(f"x_hat shape {x_hat.shape} does not match {vertex_mass.shape[0]} vertices")
        self.vertex_mass = vertex_mass
        self.x_hat = np.asarray(x_hat, dtype=float)
        self.dt = float(dt)

    def energy(self, x: np.ndarray) -> float:
        """Energy in J."""
        d = x - self.x_hat
        products = self.vertex_mass[:, None] * d  # (m d) d entry by entry, in place: the same sum, a temporary less
        products *= d
        return float(0.5 / self.dt**2 * np.sum(products))

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """Gradient ``m (x - x_hat) / dt^2``, shape ``(n, 3)`` (a new array, computed in place: the same values)."""
        g = np.subtract(x, self.x_hat)
        np.multiply(self.vertex_mass[:, None], g, out=g)
        g /= self.dt**2
        return g

    def hessian_diagonal(self) -> np.ndarray:
        """Diagonal of the Hessian ``m_i / dt^2`` per DoF, shape ``(3 n,)``."""
        return np.repeat(self.vertex_mass / self.dt**2, 3)

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """Per-vertex 3x3 blocks (for completeness; the solver uses :meth:`hessian_diagonal`)."""
        n = self.vertex_mass.shape[0]
        blocks = np.einsum("k,ij->kij", self.vertex_mass / self.dt**2, np.eye(3))
        return HessianBlocks(np.arange(n, dtype=np.int64)[:, None], blocks)

    def parameter_gradient(self, x: np.ndarray, name: str) -> np.ndarray:
        """d gradient / d s for a uniform mass scale s (masses m -> s m) at s = 1."""
        if name != "mass_scale":
            raise KeyError(name)
        return self.gradient(x)
