"""Discrete-shell bending energy (Grinspun, Hirani, Desbrun, Schroeder 2003) and bending plasticity.

A hinge ``[e0, e1, opp0, opp1]`` (``sim_core.mesh.sheet.sheet_topology``) is the pair of triangles
T0 = (x0, x1, x2) and T1 = (x1, x0, x3) with x0 = e0, x1 = e1, x2 = opp0, x3 = opp1; their normals
are n0 = (x1 - x0) x (x2 - x0) and n1 = (x3 - x0) x (x1 - x0). The signed dihedral angle is

    theta = atan2(e_hat . (n1 x n0), n0 . n1),

0 for a flat hinge and positive when the two wings fold towards the normal side (the side n0 and
n1 point to). Energy (Grinspun et al. 2003, with rest edge length |e| and rest areas A0, A1):

    E = sum_h (D / 2) * c |e|^2 / (A0 + A1) * (theta - theta_bar)^2,   c = HINGE_WEIGHT_CONSTANT = 1.

Grinspun et al. use c = 3 (|e| / h_e with h_e a third of the mean triangle height), which matches
the integral of (2 H)^2 when every edge carries the same curvature (a sphere). For cylindrical
bending, the mode that matters for paper and cloth, only one edge direction in three bends: a sheet
mapped isometrically onto a cylinder of radius R has dihedral angles theta = dx / R exactly on the
edges parallel to the axis and 0 elsewhere, so c = 3 gives 3 * (D / 2) R^-2 * area on both
right-triangle grids and equilateral meshes. c = 1 gives the Kirchhoff plate energy
(D / 2) R^-2 * area (exact for axis-aligned cylinders on ``grid_sheet`` meshes up to the boundary
row, about 1.2x / 1.5x for a cylinder axis at 22.5 / 45 degrees on the alternating grid), so that
D = E t^3 / (12 (1 - nu^2)) of a real plate can be entered directly.

The gradient of theta is the closed form of Bridson, Marino, Fedkiw 2003 (also Tamstorf &
Grinspun 2013): with m_i = n_i / |n_i|^2,

    dtheta/dx2 = |e| m0,   dtheta/dx3 = |e| m1,
    dtheta/dx0 = ((x2 - x1).e / |e|) m0 + ((x3 - x1).e / |e|) m1,
    dtheta/dx1 = -((x2 - x0).e / |e|) m0 - ((x3 - x0).e / |e|) m1.

Its Hessian is the exact derivative of this expression (product rule with
dm_i = (I - 2 n_hat_i n_hat_i^T) dn_i / |n_i|^2 and dn_i linear in dx), evaluated in closed form.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from sim_core.energies.base import HessianBlocks, Projection, scatter_gradient
from sim_core.energies.membrane.reference import cross_matrix, project_psd_translation_free
from sim_core.errors import ConfigError, MeshError
from sim_core.mesh.validate import validate_vertices

HINGE_WEIGHT_CONSTANT = 1.0
"""c in the hinge weight c |e|^2 / (A0 + A1): 1 reproduces the Kirchhoff energy of cylindrical
bending (see the module docstring; Grinspun et al. 2003 use 3)."""


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("hi,hi->h", a, b)


def dihedral_angle(X: np.ndarray) -> np.ndarray:
    """Signed dihedral angles of hinges.

    Args:
        X: hinge vertex positions ``[x0, x1, x2, x3]`` in m, shape ``(h, 4, 3)``.

    Returns:
        theta in rad, shape ``(h,)``, in (-pi, pi] (see the module docstring for the sign).
    """
    x0, x1, x2, x3 = X[:, 0], X[:, 1], X[:, 2], X[:, 3]
    e = x1 - x0
    n0 = _cross(e, x2 - x0)
    n1 = _cross(x3 - x0, e)
    e_hat = e / np.linalg.norm(e, axis=1)[:, None]
    return np.arctan2(_dot(_cross(n1, n0), e_hat), _dot(n0, n1))


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``u x v`` of ``(h, 3)`` arrays: ``np.cross``'s products and differences into a new C-ordered
    array (the same values and layout, so the same sums after it) without its axis handling
    (about 25 in place of 60 us on 300 rows)."""
    out = np.empty((u.shape[0], 3))
    np.subtract(u[:, 1] * v[:, 2], u[:, 2] * v[:, 1], out=out[:, 0])
    np.subtract(u[:, 2] * v[:, 0], u[:, 0] * v[:, 2], out=out[:, 1])
    np.subtract(u[:, 0] * v[:, 1], u[:, 1] * v[:, 0], out=out[:, 2])
    return out


def _theta_gradient_parts(X: np.ndarray):
    """Pieces shared by the gradient and Hessian of theta."""
    x0, x1, x2, x3 = X[:, 0], X[:, 1], X[:, 2], X[:, 3]
    e = x1 - x0
    le = np.linalg.norm(e, axis=1)
    n0 = np.cross(e, x2 - x0)
    n1 = np.cross(x3 - x0, e)
    q0, q1 = _dot(n0, n0), _dot(n1, n1)
    m0, m1 = n0 / q0[:, None], n1 / q1[:, None]
    zero = np.zeros_like(le)
    # dtheta/dx_v = C0[v] m0 + C1[v] m1.
    C0 = np.stack([_dot(x2 - x1, e) / le, -_dot(x2 - x0, e) / le, le, zero], axis=1)
    C1 = np.stack([_dot(x3 - x1, e) / le, -_dot(x3 - x0, e) / le, zero, le], axis=1)
    return e, le, n0, n1, q0, q1, m0, m1, C0, C1


def dihedral_angle_gradient(X: np.ndarray) -> np.ndarray:
    """dtheta/dx of hinges (Bridson et al. 2003), shape ``(h, 4, 3)`` in rad/m; ``X`` ``(h, 4, 3)``."""
    *_, m0, m1, C0, C1 = _theta_gradient_parts(X)
    return C0[:, :, None] * m0[:, None, :] + C1[:, :, None] * m1[:, None, :]


def _d_projection_coefficient(X: np.ndarray, p: int, q: int, e: np.ndarray, le: np.ndarray) -> np.ndarray:
    """d/dx_w of c = (x_p - x_q) . e / |e| (e = x1 - x0), shape ``(h, 4, 3)``."""
    d = X[:, p] - X[:, q]
    c = _dot(d, e) / le
    e_hat = e / le[:, None]
    sign_e = np.array([-1.0, 1.0, 0.0, 0.0])  # de/dx_w = sign_e[w] I
    out = sign_e[None, :, None] * (d / le[:, None] - (c / le)[:, None] * e_hat)[:, None, :]
    out[:, p] += e / le[:, None]
    out[:, q] -= e / le[:, None]
    return out


def dihedral_angle_hessian(X: np.ndarray) -> np.ndarray:
    """d^2 theta / dx^2 of hinges in closed form, shape ``(h, 12, 12)`` in rad/m^2.

    H[v i, w j] = m0_i dC0_v/dx_wj + C0_v dm0_i/dx_wj + (same for triangle 1), with
    dm = (I - 2 n_hat n_hat^T) / |n|^2 dn and dn/dx_a = [x_{a-1} - x_{a+1}]_x over each triangle's
    own vertex cycle. The result is symmetrised (it is symmetric up to rounding).

    Args:
        X: hinge vertex positions, shape ``(h, 4, 3)``.
    """
    h = X.shape[0]
    e, le, n0, n1, q0, q1, m0, m1, C0, C1 = _theta_gradient_parts(X)
    x0, x1, x2, x3 = X[:, 0], X[:, 1], X[:, 2], X[:, 3]
    e_hat = e / le[:, None]

    dC0 = np.zeros((h, 4, 4, 3))
    dC1 = np.zeros((h, 4, 4, 3))
    dC0[:, 0] = _d_projection_coefficient(X, 2, 1, e, le)
    dC0[:, 1] = -_d_projection_coefficient(X, 2, 0, e, le)
    dC0[:, 2, 0], dC0[:, 2, 1] = -e_hat, e_hat
    dC1[:, 0] = _d_projection_coefficient(X, 3, 1, e, le)
    dC1[:, 1] = -_d_projection_coefficient(X, 3, 0, e, le)
    dC1[:, 3, 0], dC1[:, 3, 1] = -e_hat, e_hat

    # dn0/dx_w over T0 = (x0, x1, x2); dn1/dx_w over T1 = (x1, x0, x3); shape (h, 3, 4, 3).
    dn0 = np.zeros((h, 3, 4, 3))
    dn1 = np.zeros((h, 3, 4, 3))
    dn0[:, :, 0], dn0[:, :, 1], dn0[:, :, 2] = (
        cross_matrix(x2 - x1), cross_matrix(x0 - x2), cross_matrix(x1 - x0)
    )
    dn1[:, :, 1], dn1[:, :, 0], dn1[:, :, 3] = (
        cross_matrix(x3 - x0), cross_matrix(x1 - x3), cross_matrix(x0 - x1)
    )
    eye = np.eye(3)
    P0 = (eye - 2.0 * np.einsum("hi,hj->hij", n0, n0) / q0[:, None, None]) / q0[:, None, None]
    P1 = (eye - 2.0 * np.einsum("hi,hj->hij", n1, n1) / q1[:, None, None]) / q1[:, None, None]
    dm0 = np.matmul(P0, dn0.reshape(h, 3, 12))  # (h, 3, 12)
    dm1 = np.matmul(P1, dn1.reshape(h, 3, 12))

    # H[v, i, (w j)]: rows (v, i), columns (w, j).
    H = m0[:, None, :, None] * dC0.reshape(h, 4, 1, 12)
    H += C0[:, :, None, None] * dm0[:, None, :, :]
    H += m1[:, None, :, None] * dC1.reshape(h, 4, 1, 12)
    H += C1[:, :, None, None] * dm1[:, None, :, :]
    H = H.reshape(h, 12, 12)
    return 0.5 * (H + np.swapaxes(H, 1, 2))


def plastic_update(theta: np.ndarray, theta_bar: np.ndarray, yield_angle: float) -> np.ndarray:
    """Bending plasticity: move rest angles that are exceeded by more than the yield angle.

    Where |theta - theta_bar| > yield_angle, theta_bar <- theta - yield_angle * sign(theta - theta_bar)
    (ThinShellLab, Wang et al. 2024; DESIGN.md); elsewhere theta_bar is kept. ``yield_angle = inf``
    is purely elastic.

    Args:
        theta: current dihedral angles in rad, shape ``(h,)``.
        theta_bar: rest angles in rad, shape ``(h,)``.
        yield_angle: yield angle in rad, >= 0 (inf allowed).

    Returns:
        new rest angles, shape ``(h,)`` (a new array).

    Raises:
        ConfigError: negative or NaN ``yield_angle``, shape mismatch.
    """
    theta = np.asarray(theta, dtype=float)
    theta_bar = np.asarray(theta_bar, dtype=float)
    y = float(yield_angle)
    if not y >= 0:
        raise ConfigError(f"plastic_update: yield_angle must be >= 0 rad (inf = elastic), got {yield_angle}")
    if theta.shape != theta_bar.shape:
        raise ConfigError(f"plastic_update: theta shape {theta.shape} != theta_bar shape {theta_bar.shape}")
    d = theta - theta_bar
    return np.where(np.abs(d) > y, theta - y * np.sign(d), theta_bar)


class DiscreteShellBending:
    """Discrete-shell bending energy over the hinges of a sheet (see the module docstring).

    The per-hinge weight ``(D / 2) * c |e|^2 / (A0 + A1)`` (c = :data:`HINGE_WEIGHT_CONSTANT`) uses
    the REST edge length and rest triangle areas (not ThinShellLab's constant dx^2 / 3).

    Args:
        hinges: global vertex indices ``[e0, e1, opp0, opp1]``, shape ``(h, 4)``.
        x_rest: rest positions of the global vertex array in m, shape ``(n, 3)``.
        bending_stiffness: D in N m (bending stiffness per unit width; a plate has
            D = E t^3 / (12 (1 - nu^2))), finite and >= 0.
        hinge_theta_bar: rest dihedral angles in rad, shape ``(h,)``; default: the dihedral angles
            of ``x_rest`` (0 for a flat sheet), i.e. the rest shape is stress free.

    Attributes:
        hinge_weight: ``c |e|^2 / (A0 + A1)`` per hinge (dimensionless), shape ``(h,)``.
        hinge_stiffness: ``(D / 2) * hinge_weight`` per hinge in J/rad^2, shape ``(h,)``.

    Raises:
        ConfigError: D negative or not finite; ``hinge_theta_bar`` of the wrong shape or not finite.
        MeshError: bad hinge array (shape, index range, repeated vertex) or a degenerate rest hinge
            (zero-length edge or zero-area triangle); the message names the hinge index.
    """

    parameter_names: tuple[str, ...] = ("bending_stiffness",)

    def __init__(
        self,
        hinges: np.ndarray,
        x_rest: np.ndarray,
        bending_stiffness: float,
        hinge_theta_bar: np.ndarray | None = None,
    ) -> None:
        D = float(bending_stiffness)
        if not (np.isfinite(D) and D >= 0):
            raise ConfigError(
                f"DiscreteShellBending: bending_stiffness must be finite and >= 0 N m, got {bending_stiffness}"
            )
        x_rest = validate_vertices(x_rest, "DiscreteShellBending rest shape")
        hinges = np.asarray(hinges)
        if hinges.ndim != 2 or hinges.shape[1] != 4:
            raise MeshError(f"DiscreteShellBending: hinges must have shape (h, 4), got {hinges.shape}")
        hinges = hinges.astype(np.int64)
        bad = np.flatnonzero(np.any((hinges < 0) | (hinges >= x_rest.shape[0]), axis=1))
        if bad.size:
            i = int(bad[0])
            raise MeshError(f"DiscreteShellBending: hinge {i} {hinges[i].tolist()} has a vertex index out of range")
        s = np.sort(hinges, axis=1)
        bad = np.flatnonzero(np.any(s[:, 1:] == s[:, :-1], axis=1))
        if bad.size:
            i = int(bad[0])
            raise MeshError(f"DiscreteShellBending: hinge {i} {hinges[i].tolist()} repeats a vertex")
        self.hinges = hinges
        self.bending_stiffness = D

        X = x_rest[hinges]
        e = X[:, 1] - X[:, 0]
        le = np.linalg.norm(e, axis=1)
        a0 = 0.5 * np.linalg.norm(np.cross(e, X[:, 2] - X[:, 0]), axis=1)
        a1 = 0.5 * np.linalg.norm(np.cross(X[:, 3] - X[:, 0], e), axis=1)
        tol = 1e-8 * le**2
        bad = np.flatnonzero((le <= 0) | (a0 <= tol) | (a1 <= tol))
        if bad.size:
            i = int(bad[0])
            raise MeshError(
                f"DiscreteShellBending: hinge {i} {hinges[i].tolist()} is degenerate at rest "
                f"(edge length {le[i]:.3e} m, areas {a0[i]:.3e}, {a1[i]:.3e} m^2)"
            )
        self.hinge_rest_length = le
        self.hinge_rest_area = a0 + a1
        self.hinge_weight = HINGE_WEIGHT_CONSTANT * le**2 / (a0 + a1)
        self.hinge_stiffness = 0.5 * D * self.hinge_weight

        if hinge_theta_bar is None:
            theta_bar = dihedral_angle(X) if len(hinges) else np.zeros(0)
        else:
            theta_bar = np.asarray(hinge_theta_bar, dtype=float)
            if theta_bar.shape != (len(hinges),):
                raise ConfigError(
                    f"DiscreteShellBending: hinge_theta_bar shape {theta_bar.shape} != ({len(hinges)},)"
                )
            if not np.all(np.isfinite(theta_bar)):
                raise ConfigError("DiscreteShellBending: hinge_theta_bar has non-finite values")
        self.hinge_theta_bar = theta_bar

    def theta(self, x: np.ndarray) -> np.ndarray:
        """Signed dihedral angle of every hinge in rad, shape ``(h,)``; ``x`` shape ``(n, 3)``."""
        return dihedral_angle(x[self.hinges])

    def theta_gradient(self, x: np.ndarray) -> np.ndarray:
        """``dtheta/dx`` of every hinge, shape ``(h, 4, 3)`` (1/m, over ``hinges``' vertices), at ``x`` ``(n, 3)``."""
        return dihedral_angle_gradient(x[self.hinges])

    def theta_stiffness(self) -> sp.csr_matrix:
        """``A = d^2E/dtheta^2 = diag(2 hinge_stiffness)`` in J/rad^2, sparse ``(h, h)``."""
        return sp.diags(2.0 * np.asarray(self.hinge_stiffness)).tocsr()

    def theta_stiffness_product(self, v: np.ndarray) -> np.ndarray:
        """``A v`` (:meth:`theta_stiffness`) for ``v`` of shape ``(h, r)``."""
        return self.theta_stiffness() @ v

    def energy(self, x: np.ndarray) -> float:
        """Bending energy in J."""
        return self._energy_with(x, self.hinge_stiffness)

    def _energy_with(self, x: np.ndarray, stiffness: np.ndarray) -> float:
        """``sum_h stiffness_h (theta_h - theta_bar_h)^2`` in J (``stiffness`` ``(h,)`` in J/rad^2, any sign)."""
        d = self.theta(x) - self.hinge_theta_bar
        return float(np.dot(stiffness, d * d))

    def _gradient_with(self, x: np.ndarray, stiffness: np.ndarray) -> np.ndarray:
        """The gradient of :meth:`_energy_with`, N, shape ``(n, 3)``."""
        X = x[self.hinges]
        d = dihedral_angle(X) - self.hinge_theta_bar
        g = (2.0 * stiffness * d)[:, None, None] * dihedral_angle_gradient(X)
        return scatter_gradient(x.shape[0], self.hinges, g)

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """dE/dx = 2 k_h (theta - theta_bar) dtheta/dx in N, shape ``(n, 3)``."""
        return self._gradient_with(x, self.hinge_stiffness)

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """12x12 blocks 2 k_h (dtheta dtheta^T + (theta - theta_bar) d^2theta), PSD-projected.

        The projection is done in the translation-free 9-D subspace
        (:func:`~sim_core.energies.membrane.reference.project_psd_translation_free`), which equals
        :func:`~sim_core.energies.base.project_psd` of the 12x12 block.
        """
        X = x[self.hinges]
        d = dihedral_angle(X) - self.hinge_theta_bar
        gt = dihedral_angle_gradient(X).reshape(-1, 12)
        H = np.einsum("hi,hj->hij", gt, gt) + d[:, None, None] * dihedral_angle_hessian(X)
        H *= (2.0 * self.hinge_stiffness)[:, None, None]
        return HessianBlocks(self.hinges, project_psd_translation_free(H, projection))

    def parameter_gradient(self, x: np.ndarray, name: str) -> np.ndarray:
        """d(dE/dx)/dD, shape ``(n, 3)`` (the energy is linear in D).

        Raises:
            KeyError: ``name`` is not ``"bending_stiffness"``.
        """
        if name != "bending_stiffness":
            raise KeyError(f"DiscreteShellBending has no parameter {name!r}; known: {self.parameter_names}")
        return self._gradient_with(x, 0.5 * self.hinge_weight)
