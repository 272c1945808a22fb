"""Viscous (mass-proportional) damping as an incremental potential.

Implicit Euler with a drag force ``f_i = -c m_i v_i`` (air drag / Rayleigh mass damping, c in 1/s)
is the minimisation of E = sum_i c m_i / (2 dt) |x_i - x_i^n|^2, since v = (x - x^n)/dt.
"""

from __future__ import annotations

import numpy as np

from sim_core.energies.base import HessianBlocks, Projection
from sim_core.errors import ConfigError


class ViscousDamping:
    """Mass-proportional damping potential.

    Args:
        vertex_mass: kg, shape ``(n,)``.
        x_prev: positions at the start of the step ``x^n`` (m), shape ``(n, 3)``.
        damping: coefficient c in 1/s, >= 0.
        dt: time step in s.

    Raises:
        ConfigError: negative or non-finite damping, non-positive dt.
    """

    parameter_names: tuple[str, ...] = ("damping",)

    def __init__(self, vertex_mass: np.ndarray, x_prev: np.ndarray, damping: float, dt: float) -> None:
        if not np.isfinite(damping) or damping < 0:
            raise ConfigError(f"damping must be finite and >= 0 (1/s), got {damping}")
        if not dt > 0:
            raise ConfigError(f"time step dt must be > 0, got {dt}")
        self.vertex_mass = np.asarray(vertex_mass, dtype=float)
        self.x_prev = np.asarray(x_prev, dtype=float)
        self.damping = float(damping)
        self.dt = float(dt)

    def energy(self, x: np.ndarray) -> float:
        """Energy in J."""
        d = x - self.x_prev
        return float(0.5 * self.damping / self.dt * np.sum(self.vertex_mass[:, None] * d * d))

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """``c m (x - x^n) / dt``, shape ``(n, 3)``."""
        return self.damping / self.dt * self.vertex_mass[:, None] * (x - self.x_prev)

    def hessian_diagonal(self) -> np.ndarray:
        """Diagonal ``c m_i / dt`` per DoF, shape ``(3 n,)``."""
        return np.repeat(self.damping / self.dt * self.vertex_mass, 3)

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """Per-vertex 3x3 blocks (the solver uses :meth:`hessian_diagonal`)."""
        n = self.vertex_mass.shape[0]
        blocks = np.einsum("k,ij->kij", self.damping / self.dt * self.vertex_mass, np.eye(3))
        return HessianBlocks(np.arange(n, dtype=np.int64)[:, None], blocks)

    def parameter_gradient(self, x: np.ndarray, name: str) -> np.ndarray:
        """d gradient / d damping, shape ``(n, 3)``."""
        if name != "damping":
            raise KeyError(name)
        return self.vertex_mass[:, None] * (x - self.x_prev) / self.dt
