"""Gravity: E = - sum_i m_i g . x_i (DESIGN.md incremental potential)."""

from __future__ import annotations

import numpy as np

from sim_core.energies.base import HessianBlocks, Projection
from sim_core.errors import ConfigError


class GravityPotential:
    """Potential energy of lumped masses in a uniform field.

    Args:
        vertex_mass: masses in kg, shape ``(n,)``.
        gravity: acceleration in m/s^2, shape ``(3,)`` (e.g. ``[0, 0, -9.81]``).

    Raises:
        ConfigError: non-finite gravity.
    """

    parameter_names: tuple[str, ...] = ("mass_scale",)

    def __init__(self, vertex_mass: np.ndarray, gravity: np.ndarray) -> None:
        self.vertex_mass = np.asarray(vertex_mass, dtype=float)
        self.gravity = np.asarray(gravity, dtype=float).reshape(3)
        if not np.all(np.isfinite(self.gravity)):
            raise ConfigError(f"gravity must be finite, got {self.gravity.tolist()}")
        self._gradient: np.ndarray | None = None  # the constant gradient, once computed

    def energy(self, x: np.ndarray) -> float:
        """Energy in J."""
        products = self.vertex_mass[:, None] * x  # (m x) g entry by entry, summed: one temporary, not two
        products *= self.gravity[None, :]
        return float(-np.sum(products))

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """``-m g`` per vertex, shape ``(n, 3)`` (a new array; the constant is computed on the first call
        for ``x``'s shape and dtype and copied afterwards)."""
        return self._constant_gradient(x).copy()

    def gradient_rows(self, x: np.ndarray) -> tuple[None, np.ndarray]:
        """``(None, -m g)``: :meth:`gradient` as the kept constant itself, not a copy (capability
        :class:`~sim_core.energies.base.SparseGradient`: the caller only reads it)."""
        return None, self._constant_gradient(x)

    def _constant_gradient(self, x: np.ndarray) -> np.ndarray:
        kept = self._gradient
        if kept is None or kept.shape != np.shape(x) or kept.dtype != np.result_type(self.vertex_mass, x):
            kept = self._gradient = -self.vertex_mass[:, None] * self.gravity[None, :] * np.ones_like(x)
        return kept

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """Zero (the energy is linear)."""
        return HessianBlocks.empty(1)

    def parameter_gradient(self, x: np.ndarray, name: str) -> np.ndarray:
        """d gradient / d s for a uniform mass scale s at s = 1."""
        if name != "mass_scale":
            raise KeyError(name)
        return self.gradient(x)
