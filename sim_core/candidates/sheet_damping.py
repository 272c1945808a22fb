"""Damping of the sheet's motion: viscous drag ``f_i = -beta m_i v_i`` on the sheet vertices only.

Candidate ``damping`` of SYSID.md (air drag and internal friction of the card; beta in 1/s, 0 =
off). The model's global ``damping`` parameter is mass-proportional over *every* body, so it also
drags the gel, which the effector drives: its signature is then dominated by the gel lagging the
effector (a wrench and marker change that gel viscoelasticity and a force bias also produce),
not by the sheet's motion that a missing sheet damping leaves in the data. This candidate acts on
the sheets alone. As :class:`~sim_core.energies.damping.reference.ViscousDamping`, implicit Euler with the
drag is the minimisation of

    E = beta / (2 dt) sum_{i in sheets} m_i |x_i - x_i^n|^2,      v_i = (x_i - x_i^n) / dt.
"""

from __future__ import annotations

import numpy as np

from sim_core.energies.base import HessianBlocks, Projection, scatter_gradient
from sim_core.errors import ConfigError


def sheet_vertices(model) -> np.ndarray:
    """Global indices of every sheet body's vertices, shape ``(k,)`` int64 (empty without a sheet)."""
    parts = [np.asarray(b.vertices, dtype=np.int64).reshape(-1) for b in model.bodies.values() if b.kind == "sheet"]
    return np.unique(np.concatenate(parts)) if parts else np.zeros(0, np.int64)


class SheetDamping:
    """Viscous drag on a subset of vertices (module docstring).

    Args:
        vertices: damped vertices, shape ``(k,)``.
        vertex_mass: kg of every vertex, shape ``(n,)``.
        x_prev: ``x^n`` in m, shape ``(n, 3)``.
        beta: drag coefficient in 1/s, >= 0.
        dt: step in s, > 0.

    Raises:
        ConfigError: negative / non-finite beta, non-positive dt.
    """

    parameter_names: tuple[str, ...] = ("beta",)

    def __init__(self, vertices: np.ndarray, vertex_mass: np.ndarray, x_prev: np.ndarray, beta: float,
                 dt: float) -> None:
        beta = float(beta)
        if not (np.isfinite(beta) and beta >= 0.0):
            raise ConfigError(f"SheetDamping: beta must be finite and >= 0 (1/s), got {beta}")
        if not dt > 0:
            raise ConfigError(f"SheetDamping: time step dt must be > 0, got {dt}")
        self.ids = np.asarray(vertices, dtype=np.int64).reshape(-1)
        self.vertices = self.ids[:, None]
        self.mass = np.asarray(vertex_mass, dtype=float)[self.ids]
        self.x_prev = np.asarray(x_prev, dtype=float)
        self.beta, self.dt = beta, float(dt)

    def energy(self, x: np.ndarray) -> float:
        """Energy in J."""
        d = x[self.ids] - self.x_prev[self.ids]
        return float(0.5 * self.beta / self.dt * np.sum(self.mass[:, None] * d * d))

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """``beta m (x - x^n) / dt`` on the damped vertices, N, shape ``(n, 3)``."""
        g = self.beta / self.dt * self.mass[:, None] * (x[self.ids] - self.x_prev[self.ids])
        return scatter_gradient(x.shape[0], self.vertices, g)

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """Per-vertex 3x3 blocks ``beta m_i / dt I`` (PSD), shape ``(k, 3, 3)``."""
        return HessianBlocks(self.vertices, np.einsum("k,ij->kij", self.beta / self.dt * self.mass, np.eye(3)))

    def parameter_gradient(self, x: np.ndarray, name: str) -> np.ndarray:
        """d(dE/dx)/d beta, N s, shape ``(n, 3)``.

        Raises:
            KeyError: ``name`` is not ``"beta"``.
        """
        if name != "beta":
            raise KeyError(f"SheetDamping has no parameter {name!r}; known: {self.parameter_names}")
        g = self.mass[:, None] * (x[self.ids] - self.x_prev[self.ids]) / self.dt
        return scatter_gradient(x.shape[0], self.vertices, g)
