"""Lagged smoothed Coulomb friction after IPC (Li et al., "Incremental Potential Contact", SIGGRAPH 2020).

Per active pair k (frozen at the start of the step, from the closest-point configuration at x^n):
normal force magnitude ``lam_k`` (N), orthonormal tangent basis ``T_k`` (3 x 2) and closest-point
weights ``w_kj``. The relative tangential displacement over the step is
``u_k = T_k^T sum_j w_kj (x_j - x^n_j)`` (m, shape (2,)) and the energy
``E = sum_k mu_k lam_k f0(|u_k|)`` with the C1 mollifier of IPC (eq. 14-15, ``eps_u = eps_v dt``):

    f0(y) = -y^3 / (3 eps_u^2) + y^2 / eps_u + eps_u / 3   for y < eps_u,   y otherwise;
    f1(y) = f0'(y) = 2 y / eps_u - y^2 / eps_u^2            for y < eps_u,   1 otherwise.

Gradient: ``mu lam (f1(y)/y) w_j T u``; its magnitude is ``mu lam`` in the sliding regime
(y >= eps_u), i.e. the Coulomb force. Hessian (PSD by construction, no projection needed):
``mu lam w_i w_j T [ (f1/y) I + ((f1' y - f1) / y^3) u u^T ] T^T``; in the u-plane its eigenvalues are
``f1/y`` and ``f1'``, both >= 0 for y in [0, eps_u] and for y > eps_u (``1/y`` and 0).
"""

from __future__ import annotations

import numpy as np

from sim_core.energies.base import HessianBlocks, Projection, scatter_gradient, sum_by_copy
from sim_core.energies.contact.reference import ContactFrames
from sim_core.errors import ConfigError


def smooth_friction_f0(y: np.ndarray, eps_u: float) -> np.ndarray:
    """IPC mollified |u|: ``f0(y)`` (m), C1 at ``y = eps_u``."""
    y = np.asarray(y, dtype=float)
    return np.where(y < eps_u, -(y**3) / (3 * eps_u**2) + y * y / eps_u + eps_u / 3, y)


def smooth_friction_f1(y: np.ndarray, eps_u: float) -> np.ndarray:
    """``f0'(y)`` (dimensionless), 1 in the sliding regime."""
    y = np.asarray(y, dtype=float)
    return np.where(y < eps_u, 2 * y / eps_u - y * y / eps_u**2, 1.0)


def smooth_friction_f1_over_x(y: np.ndarray, eps_u: float) -> np.ndarray:
    """``f1(y) / y`` (1/m), finite at ``y = 0`` (``2 / eps_u``)."""
    y = np.asarray(y, dtype=float)
    with np.errstate(divide="ignore"):
        return np.where(y < eps_u, 2 / eps_u - y / eps_u**2, 1.0 / np.maximum(y, eps_u))


def smooth_friction_f1_over_x_eps_derivative(y: np.ndarray, eps_u: float) -> np.ndarray:
    """``d(f1(y) / y) / d eps_u`` (1/m^2): ``-2 / eps_u^2 + 2 y / eps_u^3`` mollified (``y < eps_u``; ``<= 0``,
    zero at the seam), 0 sliding (``f1 / y = 1 / y`` there holds no ``eps_u``)."""
    y = np.asarray(y, dtype=float)
    return np.where(y < eps_u, -2.0 / eps_u**2 + 2.0 * y / eps_u**3, 0.0)


def smooth_friction_f2_x_minus_f1_over_x3(y: np.ndarray, eps_u: float) -> np.ndarray:
    """``(f1'(y) y - f1(y)) / y^3`` (1/m^3): ``-1 / (eps_u^2 y)`` mollified, ``-1 / y^3`` sliding.

    Multiplies ``u u^T`` (of size y^2), so its value at ``y = 0`` is irrelevant; 0 is returned there.
    """
    y = np.asarray(y, dtype=float)
    safe = np.where(y > 0, y, 1.0)
    return np.where(y <= 0, 0.0, np.where(y < eps_u, -1.0 / (eps_u**2 * safe), -1.0 / safe**3))


def tangent_basis(normal: np.ndarray) -> np.ndarray:
    """Orthonormal tangent bases ``T`` of unit normals, shape ``(p, 3, 2)`` (columns t1, t2).

    t1 = normalise(n x a) with ``a`` the coordinate axis least aligned with n, t2 = n x t1.
    """
    normal = np.asarray(normal, dtype=float).reshape(-1, 3)
    axis = np.eye(3)[np.argmin(np.abs(normal), axis=1)]
    t1 = np.cross(normal, axis)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normal, t1)
    return np.stack([t1, t2], axis=2)


class LaggedFriction:
    """IPC lagged friction over a set of frozen contact pairs (module docstring).

    Args:
        vertices: global vertex indices per pair, shape ``(p, m)``.
        weights: closest-point weights per pair, shape ``(p, m)`` (first side +, second side -).
        tangent: tangent bases ``T``, shape ``(p, 3, 2)`` (orthonormal columns).
        lam: frozen normal force magnitudes in N, shape ``(p,)`` (>= 0).
        mu: friction coefficients per pair, shape ``(p,)`` or scalar (>= 0).
        x_prev: positions at the start of the step ``x^n`` in m, shape ``(n, 3)``.
        eps_v: velocity threshold of the mollifier in m/s (> 0; ThinShellLab 0.01).
        dt: time step in s (> 0).

    Raises:
        ConfigError: negative/NaN mu or lam, non-positive eps_v or dt, shape mismatch.
    """

    parameter_names: tuple[str, ...] = ("mu",)
    psd_hessian = True
    """:meth:`hessian` is PSD by construction, the same blocks for every ``projection`` (the lockstep batch's projected
    retry takes the exact blocks where they are, :meth:`sim_core.batch.lockstep.LockstepSolver._term_hessian`)."""

    def __init__(
        self,
        vertices: np.ndarray,
        weights: np.ndarray,
        tangent: np.ndarray,
        lam: np.ndarray,
        mu: np.ndarray | float,
        x_prev: np.ndarray,
        eps_v: float,
        dt: float,
    ) -> None:
        self.vertices = np.asarray(vertices, dtype=np.int64)
        p = self.vertices.shape[0]
        self.weights = np.asarray(weights, dtype=float).reshape(self.vertices.shape)
        self.tangent = np.asarray(tangent, dtype=float).reshape(p, 3, 2)
        self.lam = np.asarray(lam, dtype=float).reshape(p)
        self.mu = np.broadcast_to(np.asarray(mu, dtype=float), (p,)).copy()
        if not (np.all(np.isfinite(self.mu)) and np.all(self.mu >= 0)):
            raise ConfigError("LaggedFriction: friction coefficients mu must be finite and >= 0")
        if not (np.all(np.isfinite(self.lam)) and np.all(self.lam >= 0)):
            raise ConfigError("LaggedFriction: normal forces lam must be finite and >= 0 (N)")
        if not (np.isfinite(eps_v) and eps_v > 0):
            raise ConfigError(f"LaggedFriction: eps_v must be finite and > 0 (m/s), got {eps_v}")
        if not (np.isfinite(dt) and dt > 0):
            raise ConfigError(f"LaggedFriction: time step dt must be > 0 (s), got {dt}")
        self.x_prev = np.asarray(x_prev, dtype=float)
        self.eps_v = float(eps_v)
        self.dt = float(dt)
        self.eps_u = self.eps_v * self.dt

    @classmethod
    def from_frames(
        cls, frames: ContactFrames, mu: np.ndarray | float, x_prev: np.ndarray, eps_v: float, dt: float
    ) -> "LaggedFriction":
        """Freeze the contact frames evaluated at ``x_prev`` (see ``contact_frames`` of the contact
        potentials and :func:`~sim_core.energies.contact.reference.concatenate_frames`)."""
        return cls(frames.vertices, frames.weights, tangent_basis(frames.normal), frames.lam, mu, x_prev, eps_v, dt)

    def tangential_displacement(self, x: np.ndarray) -> np.ndarray:
        """``u = T^T sum_j w_j (x_j - x^n_j)`` in m, shape ``(p, 2)``."""
        rel = np.einsum("kj,kjd->kd", self.weights, x[self.vertices] - self.x_prev[self.vertices])
        return np.einsum("kdi,kd->ki", self.tangent, rel)

    def energy(self, x: np.ndarray) -> float:
        """Friction dissipation potential in J."""
        y = np.linalg.norm(self.tangential_displacement(x), axis=1)
        return float(np.sum(self.mu * self.lam * smooth_friction_f0(y, self.eps_u)))

    def copy_energies(self, x: np.ndarray, copy_of_vertex: np.ndarray, copy_count: int) -> np.ndarray:
        """:meth:`energy` split by the copy of each pair's first vertex, J ``(copy_count,)`` (capability
        :class:`~sim_core.energies.base.CopyEnergies`; the pairs' terms on the host)."""
        if not self.vertices.shape[0]:
            return np.zeros(copy_count)
        y = np.linalg.norm(self.tangential_displacement(x), axis=1)
        return sum_by_copy(copy_of_vertex, self.vertices[:, 0], self.mu * self.lam * smooth_friction_f0(y, self.eps_u),
                           copy_count)

    def _pair_gradient(self, x: np.ndarray, coefficient: np.ndarray) -> np.ndarray:
        """``coefficient f1(y)/y w_j T u`` per pair vertex, shape ``(p, m, 3)``."""
        u = self.tangential_displacement(x)
        y = np.linalg.norm(u, axis=1)
        scale = coefficient * smooth_friction_f1_over_x(y, self.eps_u)
        tu = np.einsum("kdi,ki->kd", self.tangent, u) * scale[:, None]
        return self.weights[:, :, None] * tu[:, None, :]

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """dE/dx in N (minus the friction force), shape ``(n, 3)``."""
        return scatter_gradient(x.shape[0], self.vertices, self._pair_gradient(x, self.mu * self.lam))

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """Per-pair blocks ``(p, 3m, 3m)``, PSD by construction (``projection`` is not needed)."""
        p, m = self.vertices.shape
        if p == 0:
            return HessianBlocks.empty(m)
        u = self.tangential_displacement(x)
        y = np.linalg.norm(u, axis=1)
        Hu = smooth_friction_f1_over_x(y, self.eps_u)[:, None, None] * np.eye(2)[None] + (
            smooth_friction_f2_x_minus_f1_over_x3(y, self.eps_u)[:, None, None] * u[:, :, None] * u[:, None, :]
        )
        H3 = np.einsum("kdi,kij,kej->kde", self.tangent, Hu, self.tangent) * (self.mu * self.lam)[:, None, None]
        blocks = np.einsum("ka,kb,kde->kadbe", self.weights, self.weights, H3).reshape(p, 3 * m, 3 * m)
        return HessianBlocks(self.vertices, blocks)

    def mu_gradient(self, x: np.ndarray, pair_mask: np.ndarray | None = None) -> np.ndarray:
        """d(dE/dx)/d mu for one coefficient shared by the pairs in ``pair_mask`` (default: all).

        Args:
            x: positions in m, shape ``(n, 3)``.
            pair_mask: bool shape ``(p,)`` selecting the pairs whose mu is the parameter (e.g. the
                pairs of one body pair, ``friction.gel_sheet``).

        Returns:
            shape ``(n, 3)``, in N.
        """
        coefficient = self.lam if pair_mask is None else self.lam * np.asarray(pair_mask, dtype=float)
        return scatter_gradient(x.shape[0], self.vertices, self._pair_gradient(x, coefficient))

    def eps_v_gradient(self, x: np.ndarray) -> np.ndarray:
        """d(dE/dx)/d eps_v, the friction force's derivative in the mollifier's stick speed, shape ``(n, 3)``, N s/m.

        Per pair ``mu lam dt d(f1(y)/y)/d eps_u w_j T u`` (``eps_u = eps_v dt``,
        :func:`smooth_friction_f1_over_x_eps_derivative`): only the mollified pairs (``|u| < eps_u``) carry it;
        ``lam``, ``T`` and ``w`` are frozen at ``x^n`` and hold no ``eps_v``. The implicit-function tangent of a
        step in ``contact.eps_v`` takes it as its ``dg/dp``
        (:meth:`sim_core.adjoint.StepLinearization.parameter_rhs`)."""
        u = self.tangential_displacement(x)
        y = np.linalg.norm(u, axis=1)
        scale = self.mu * self.lam * self.dt * smooth_friction_f1_over_x_eps_derivative(y, self.eps_u)
        tu = np.einsum("kdi,ki->kd", self.tangent, u) * scale[:, None]
        return scatter_gradient(x.shape[0], self.vertices, self.weights[:, :, None] * tu[:, None, :])

    def parameter_gradient(self, x: np.ndarray, name: str) -> np.ndarray:
        """d(dE/dx)/d mu with every pair's coefficient moving together, shape ``(n, 3)``."""
        if name != "mu":
            raise KeyError(name)
        return self.mu_gradient(x)
