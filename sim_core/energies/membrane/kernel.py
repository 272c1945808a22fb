"""Saint Venant-Kirchhoff membrane triangles in Taichi: energy, gradient and projected 9x9 blocks.

The same quantities as :class:`sim_core.energies.membrane.reference.StVKMembrane` (the reference and test
oracle), one triangle per thread. With the 3x2 deformation gradient ``F = sum_a x_a (x) D_a``
(``D`` the shape-function gradients in an orthonormal frame of the rest triangle; Sifakis & Barbic,
SIGGRAPH 2012 course, sec. 4), Green strain ``G = (F^T F - I) / 2`` and plane-stress Lame
parameters (Bonet & Wood, ch. 6)::

    E_tri = w (mu tr(G^2) + lam / 2 tr(G)^2),   w = thickness * rest_area,
    P = F S,  S = 2 mu G + lam tr(G) I,           dE/dx_a = w P D_a,
    d2E / dx_ad dx_be = w (D_a.S D_b delta_de + mu Q_db Q_ea + mu (D_a.D_b) (F F^T)_de + lam Q_da Q_eb),

``Q = F D^T``. Blocks are projected in the 6-D complement of the rigid translations (Jacobi).
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel and ti.func annotations as
# objects (string annotations are rejected).

import numpy as np

from sim_core.energies.base import HessianBlocks, Projection
from sim_core.energies.membrane.reference import StVKMembrane
from sim_core.ti_backend import require_backend, serial_loops, ti
from sim_core.ti_kernels.buffers import DeviceArray, upload_constant
from sim_core.ti_kernels.launch import fast_kernel
from sim_core.ti_kernels.linalg import project_psd_translation_free, projection_code


@ti.func
def _triangle_strain(x: ti.types.ndarray(), tris: ti.types.ndarray(), D: ti.types.ndarray(), t: ti.i32):
    """``F`` (3x2) and the Green strain ``G`` (2x2) of triangle ``t``."""
    F = ti.Matrix.zero(ti.f64, 3, 2)
    for a in ti.static(range(3)):
        v = tris[t, a]
        for d, j in ti.static(ti.ndrange(3, 2)):
            F[d, j] += x[v, d] * D[t, a, j]
    G = 0.5 * (F.transpose() @ F - ti.Matrix.identity(ti.f64, 2))
    return F, G


@fast_kernel
def evaluate_stvk_energy(
    x: ti.types.ndarray(), tris: ti.types.ndarray(), D: ti.types.ndarray(), weight: ti.types.ndarray(),
    mu: ti.f64, lam: ti.f64, tri_energy: ti.types.ndarray(),
):
    """``tri_energy[t] = w_t (mu G:G + lam/2 tr(G)^2)`` (J)."""
    ti.loop_config(serialize=ti.static(serial_loops()))  # CPU: serial (a forked replay worker hangs in a parallel loop)
    for t in range(tris.shape[0]):
        F, G = _triangle_strain(x, tris, D, t)
        trG = G[0, 0] + G[1, 1]
        tri_energy[t] = weight[t] * (mu * (G * G).sum() + 0.5 * lam * trG * trG)


@fast_kernel
def evaluate_stvk_gradient(
    x: ti.types.ndarray(), tris: ti.types.ndarray(), D: ti.types.ndarray(), weight: ti.types.ndarray(),
    mu: ti.f64, lam: ti.f64, grad: ti.types.ndarray(),
):
    """``grad[v] += w_t P D_a`` for every corner ``a`` at vertex ``v`` (N); ``grad`` zeroed first."""
    ti.loop_config(serialize=ti.static(serial_loops()))  # CPU: serial (a forked replay worker hangs in a parallel loop)
    for v, d in ti.ndrange(grad.shape[0], 3):
        grad[v, d] = 0.0
    ti.loop_config(serialize=ti.static(serial_loops()))  # CPU: serial (a forked replay worker hangs in a parallel loop)
    for t in range(tris.shape[0]):
        F, G = _triangle_strain(x, tris, D, t)
        trG = G[0, 0] + G[1, 1]
        S = 2.0 * mu * G + lam * trG * ti.Matrix.identity(ti.f64, 2)
        P = F @ S
        for a in ti.static(range(3)):
            v = tris[t, a]
            for d in ti.static(range(3)):
                ti.atomic_add(grad[v, d], weight[t] * (P[d, 0] * D[t, a, 0] + P[d, 1] * D[t, a, 1]))


@fast_kernel
def evaluate_stvk_hessian(
    x: ti.types.ndarray(), tris: ti.types.ndarray(), D: ti.types.ndarray(), weight: ti.types.ndarray(),
    mu: ti.f64, lam: ti.f64, code: ti.i32, blocks: ti.types.ndarray(),
):
    """``blocks[t]``: the 9x9 Hessian of triangle ``t`` (local DoF ``3 a + d``, N/m), projected."""
    ti.loop_config(serialize=ti.static(serial_loops()))  # CPU: serial (a forked replay worker hangs in a parallel loop)
    for t in range(tris.shape[0]):
        F, G = _triangle_strain(x, tris, D, t)
        trG = G[0, 0] + G[1, 1]
        S = 2.0 * mu * G + lam * trG * ti.Matrix.identity(ti.f64, 2)
        Dt = ti.Matrix.zero(ti.f64, 3, 2)
        for a, j in ti.static(ti.ndrange(3, 2)):
            Dt[a, j] = D[t, a, j]
        Q = F @ Dt.transpose()  # Q[d, b] = (F D^T)[d, b]
        DSD = Dt @ S @ Dt.transpose()
        DDt = Dt @ Dt.transpose()
        FFt = F @ F.transpose()
        H = ti.Matrix.zero(ti.f64, 9, 9)
        for a, b in ti.static(ti.ndrange(3, 3)):
            for d, e in ti.static(ti.ndrange(3, 3)):
                val = mu * Q[d, b] * Q[e, a] + mu * DDt[a, b] * FFt[d, e] + lam * Q[d, a] * Q[e, b]
                if ti.static(d == e):
                    val += DSD[a, b]
                H[3 * a + d, 3 * b + e] = weight[t] * val
        project_psd_translation_free(H, code)
        for r, s in ti.ndrange(9, 9):
            blocks[t, r, s] = H[r, s]


class TiStVKMembrane(StVKMembrane):
    """:class:`StVKMembrane` whose energy, gradient and Hessian run as Taichi kernels.

    Construction, validation, parameters and :meth:`parameter_gradient` are the NumPy class's;
    the rest-shape arrays are uploaded to the device once.

    Args:
        triangles, x_rest, youngs_modulus, poisson_ratio, thickness: as :class:`StVKMembrane`.

    Raises:
        ConfigError: as :class:`StVKMembrane`, or the Taichi backend is not initialised.
        MeshError: as :class:`StVKMembrane`.
    """

    def __init__(self, triangles: np.ndarray, x_rest: np.ndarray, youngs_modulus: float, poisson_ratio: float,
                 thickness: float) -> None:
        require_backend("TiStVKMembrane")
        super().__init__(triangles, x_rest, youngs_modulus, poisson_ratio, thickness)
        self._tris_dev = upload_constant(self.triangles, ti.i32)
        self._D_dev = upload_constant(self.triangle_shape_gradient, ti.f64)
        self._weight_dev = upload_constant(self._weight(), ti.f64)
        self._x = DeviceArray(ti.f64)
        self._tri_energy = DeviceArray(ti.f64)
        self._grad = DeviceArray(ti.f64)
        self._blocks = DeviceArray(ti.f64)

    def _args(self, x: np.ndarray) -> tuple:
        return (self._x.upload(x), self._tris_dev, self._D_dev, self._weight_dev, self.mu, self.lam)

    def energy(self, x: np.ndarray) -> float:
        """Membrane energy in J; ``x`` shape ``(n, 3)`` in m."""
        k = self.triangles.shape[0]
        if k == 0:
            return 0.0
        out = self._tri_energy.ensure((k,))
        evaluate_stvk_energy(*self._args(x), out)
        return float(np.sum(out.to_numpy()))

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """dE/dx in N, shape ``(n, 3)``."""
        x = np.asarray(x, dtype=float)
        if self.triangles.shape[0] == 0:
            return np.zeros_like(x)
        g = self._grad.ensure(x.shape)
        evaluate_stvk_gradient(*self._args(x), g)
        return g.to_numpy()

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """9x9 blocks per triangle (local DoF ``3 a + d``), PSD-projected per ``projection``.

        Raises:
            ValueError: unknown projection.
        """
        code = projection_code(projection)
        k = self.triangles.shape[0]
        if k == 0:
            return HessianBlocks(self.triangles, np.zeros((0, 9, 9)))
        out = self._blocks.ensure((k, 9, 9))
        evaluate_stvk_hessian(*self._args(x), code, out)
        return HessianBlocks(self.triangles, out.to_numpy())
