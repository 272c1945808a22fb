"""Stiction: static friction above kinetic friction, as a lagged potential beside IPC friction.

Candidate ``stiction`` of SYSID.md. The kinetic friction force of a pair is ``mu lam f1(y)``
(:mod:`sim_core.energies.friction.reference`, ``y = |u|`` the tangential slip of the step). Stiction adds a
breakaway bump in the small-slip regime,

    f_s(y) = beta mu lam h(y / eps_s),   h(r) = r exp(1 - r),

which is 0 at rest, peaks at ``beta mu lam`` for ``y = eps_s`` and decays for larger slip (a
Stribeck-type velocity weakening over slip speeds ``y / dt``). With ``eps_s >= eps_u`` the
kinetic term is already saturated at the peak, so the breakaway force is ``(1 + beta) mu lam``:
``beta = mu_s / mu_k - 1`` and ``beta = 0`` is off. The energy of the bump (``int f_s dy``) is

    E = sum_k beta mu_k lam_k eps_s e (1 - (1 + r_k) exp(-r_k)),   r_k = |u_k| / eps_s,

with the same frozen normal forces, tangent bases and closest-point weights as the lagged friction
(Li et al. 2020). Gradient ``beta mu lam a(y) w_j T u`` with ``a(y) = h(r)/y = exp(1 - r)/eps_s``
(finite at y = 0). In the u-plane the Hessian has eigenvalues ``a`` (across the slip) and
``a (1 - r)`` (along it); the second is negative past the peak (velocity weakening) and is clamped
or flipped by the PSD projection.
"""

from __future__ import annotations

import numpy as np

from sim_core.energies.base import HessianBlocks, Projection, scatter_gradient
from sim_core.energies.friction.reference import LaggedFriction
from sim_core.errors import ConfigError


def stiction_bump_energy(y: np.ndarray, eps_s: float) -> np.ndarray:
    """``eps_s e (1 - (1 + r) exp(-r))`` with ``r = y / eps_s`` (m): the integral of ``h``."""
    r = np.asarray(y, dtype=float) / eps_s
    return eps_s * np.e * (1.0 - (1.0 + r) * np.exp(-r))


def stiction_bump_over_x(y: np.ndarray, eps_s: float) -> np.ndarray:
    """``h(y / eps_s) / y = exp(1 - y / eps_s) / eps_s`` (1/m), finite at 0."""
    return np.exp(1.0 - np.asarray(y, dtype=float) / eps_s) / eps_s


class StictionFriction:
    """Stiction bump on top of a lagged friction's frozen pairs (module docstring).

    Args:
        friction: the step's :class:`~sim_core.energies.friction.reference.LaggedFriction` (pairs, lam, mu,
            tangent bases, ``x^n``, ``eps_u``).
        beta: ``mu_s / mu_k - 1`` (dimensionless, >= 0; 0 = off).
        slip_scale: ``eps_s / eps_u`` (>= 1; default 2): slip of the step, in units of the
            friction mollifier width, at which the breakaway force peaks.

    Raises:
        ConfigError: negative or non-finite ``beta``; ``slip_scale`` < 1 or non-finite.
    """

    parameter_names: tuple[str, ...] = ("beta",)

    def __init__(self, friction: LaggedFriction, beta: float, slip_scale: float = 2.0) -> None:
        beta, slip_scale = float(beta), float(slip_scale)
        if not (np.isfinite(beta) and beta >= 0):
            raise ConfigError(f"StictionFriction: beta = mu_s/mu_k - 1 must be finite and >= 0, got {beta}")
        if not (np.isfinite(slip_scale) and slip_scale >= 1.0):
            raise ConfigError(f"StictionFriction: slip_scale = eps_s/eps_u must be >= 1, got {slip_scale}")
        self.friction = friction
        self.vertices = friction.vertices
        self.beta = beta
        self.eps_s = slip_scale * friction.eps_u
        self._coefficient = friction.mu * friction.lam

    def _slip(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u = self.friction.tangential_displacement(x)
        return u, np.linalg.norm(u, axis=1)

    def energy(self, x: np.ndarray) -> float:
        """Stiction energy in J."""
        _, y = self._slip(x)
        return float(self.beta * np.sum(self._coefficient * stiction_bump_energy(y, self.eps_s)))

    def _gradient_with(self, x: np.ndarray, scale: float) -> np.ndarray:
        u, y = self._slip(x)
        a = scale * self._coefficient * stiction_bump_over_x(y, self.eps_s)
        tu = np.einsum("kdi,ki->kd", self.friction.tangent, u) * a[:, None]
        g = self.friction.weights[:, :, None] * tu[:, None, :]
        return scatter_gradient(x.shape[0], self.vertices, g)

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """dE/dx in N (minus the extra static friction force), shape ``(n, 3)``."""
        return self._gradient_with(x, self.beta)

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """Per-pair blocks ``(p, 3m, 3m)``; the u-plane 2x2 Hessian is projected analytically.

        ``H_u = beta mu lam a (I - u u^T / (eps_s y))`` has eigenvalues ``a`` and ``a (1 - r)``.
        """
        p, m = self.vertices.shape
        if p == 0:
            return HessianBlocks.empty(m)
        if projection not in ("none", "clamp", "abs"):
            raise ValueError(f"unknown PSD projection {projection!r}; use 'none', 'clamp' or 'abs'")
        u, y = self._slip(x)
        a = stiction_bump_over_x(y, self.eps_s)
        radial = a * (1.0 - y / self.eps_s)
        if projection == "clamp":
            radial = np.maximum(radial, 0.0)
        elif projection == "abs":
            radial = np.abs(radial)
        safe = np.where(y > 0, y, 1.0)
        uhat = np.where((y > 0)[:, None], u / safe[:, None], 0.0)
        Hu = a[:, None, None] * np.eye(2)[None] + (radial - a)[:, None, None] * uhat[:, :, None] * uhat[:, None, :]
        tan = self.friction.tangent
        H3 = np.einsum("kdi,kij,kej->kde", tan, Hu, tan) * (self.beta * self._coefficient)[:, None, None]
        w = self.friction.weights
        blocks = np.einsum("ka,kb,kde->kadbe", w, w, H3).reshape(p, 3 * m, 3 * m)
        return HessianBlocks(self.vertices, blocks)

    def parameter_gradient(self, x: np.ndarray, name: str) -> np.ndarray:
        """d(dE/dx)/d beta (the energy is linear in beta), N, shape ``(n, 3)``.

        Raises:
            KeyError: ``name`` is not ``"beta"``.
        """
        if name != "beta":
            raise KeyError(f"StictionFriction has no parameter {name!r}; known: {self.parameter_names}")
        return self._gradient_with(x, 1.0)
