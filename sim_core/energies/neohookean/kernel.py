"""Stable Neo-Hookean tetrahedra in Taichi: energy, gradient and projected 12x12 Hessian blocks.

The same quantities as :class:`sim_core.energies.neohookean.reference.StableNeoHookean` (the reference and
test oracle), one tet per thread (Smith, de Goes, Kim 2018, "Stable Neo-Hookean Flesh Simulation"):

    psi = mu/2 (I_C - 3) + lam/2 (J - alpha)^2 - mu/2 log((I_C + 1) / 4) - 9 mu^2 / (32 lam),
    P   = mu (1 - 1/(I_C + 1)) F + lam (J - alpha) cof F                       (eq. 18),

and the Hessian from the paper's analytic eigensystem of d2psi/dF2 (section 4.2: three twist, three
flip and three scaling modes from the rotation-variant SVD ``F = U diag(sigma) V^T``), with the
eigenvalues filtered per projection and mapped to the vertices: ``H = V_t sum_m f(w_m) y_m y_m^T``,
``y_m = (dvecF/dx)^T q_m``. The rotation-variant SVD is computed from a Jacobi eigen-decomposition
of ``F^T F`` (V) and a Gram-Schmidt QR of ``F V`` with ``u_2 = u_0 x u_1`` (so ``det U = +1`` and
``sigma_2 < 0`` for inverted tets), accurate to float64 round-off (``ti.svd`` runs a fixed
number of Sifakis iterations and reconstructs F only to about 1e-10).
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel and ti.func annotations as
# objects (string annotations are rejected).

import numpy as np

from sim_core.energies.base import HessianBlocks, Projection
from sim_core.energies.neohookean.reference import StableNeoHookean
from sim_core.ti_backend import require_backend, serial_loops, ti
from sim_core.ti_kernels.buffers import DeviceArray, upload_constant
from sim_core.ti_kernels.launch import fast_kernel
from sim_core.ti_kernels.linalg import cofactor, filter_eigenvalue, jacobi_eigh, matmul, projection_code

_INV_SQRT2 = float(1.0 / np.sqrt(2.0))


@ti.func
def _tet_deformation_gradient(x: ti.types.ndarray(), tets: ti.types.ndarray(), dFdx: ti.types.ndarray(), t: ti.i32):
    """``F_ij = sum_a x_{a,i} dFdx[t, a, j]`` (3x3)."""
    F = ti.Matrix.zero(ti.f64, 3, 3)
    for a in ti.static(range(4)):
        v = tets[t, a]
        for i, j in ti.static(ti.ndrange(3, 3)):
            F[i, j] += x[v, i] * dFdx[t, a, j]
    return F


@ti.func
def _rotation_variant_svd(F):
    """``F = U diag(sigma) V^T`` with ``det U = det V = +1``, ``sigma_0 >= sigma_1 >= |sigma_2|``."""
    C = matmul(F.transpose(), F)
    V = ti.Matrix.zero(ti.f64, 3, 3)
    jacobi_eigh(C, V)
    lam = ti.Vector([C[0, 0], C[1, 1], C[2, 2]])
    # sort eigenvalues of F^T F descending, swapping the columns of V with them
    for p in ti.static(range(2)):
        for q in ti.static(range(p + 1, 3)):
            if lam[q] > lam[p]:
                tmp = lam[p]
                lam[p] = lam[q]
                lam[q] = tmp
                for k in ti.static(range(3)):
                    vkp = V[k, p]
                    V[k, p] = V[k, q]
                    V[k, q] = vkp
    if V.determinant() < 0.0:
        for k in ti.static(range(3)):
            V[k, 2] = -V[k, 2]
    B = matmul(F, V)
    b0 = ti.Vector([B[0, 0], B[1, 0], B[2, 0]])
    b1 = ti.Vector([B[0, 1], B[1, 1], B[2, 1]])
    b2 = ti.Vector([B[0, 2], B[1, 2], B[2, 2]])
    u0 = ti.Vector([1.0, 0.0, 0.0])
    n0 = b0.norm()
    if n0 > 0.0:
        u0 = b0 / n0
    w1 = b1 - u0.dot(b1) * u0
    n1 = w1.norm()
    u1 = ti.Vector([0.0, 0.0, 0.0])
    if n1 > 1e-300 and n1 > 1e-15 * n0:
        u1 = w1 / n1
    else:
        # any unit vector orthogonal to u0 (F has rank <= 1 here)
        axis = ti.Vector([1.0, 0.0, 0.0])
        if ti.abs(u0[0]) > 0.5:
            axis = ti.Vector([0.0, 1.0, 0.0])
        u1 = u0.cross(axis).normalized()
    u2 = u0.cross(u1)
    U = ti.Matrix.cols([u0, u1, u2])
    sigma = ti.Vector([u0.dot(b0), u1.dot(b1), u2.dot(b2)])
    return U, sigma, V


@fast_kernel
def evaluate_snh_energy(
    x: ti.types.ndarray(), tets: ti.types.ndarray(), dFdx: ti.types.ndarray(), vol: ti.types.ndarray(),
    mu: ti.f64, lam: ti.f64, tet_energy: ti.types.ndarray(),
):
    """``tet_energy[t] = V_t psi(F_t)`` (J)."""
    alpha = 1.0 + 0.75 * mu / lam
    ti.loop_config(serialize=ti.static(serial_loops()))  # CPU: serial (a forked replay worker hangs in a parallel loop)
    for t in range(tets.shape[0]):
        F = _tet_deformation_gradient(x, tets, dFdx, t)
        I_C = (F * F).sum()
        J = F.determinant()
        psi = (0.5 * mu * (I_C - 3.0) + 0.5 * lam * (J - alpha) ** 2
               - 0.5 * mu * ti.log((I_C + 1.0) / 4.0) - 9.0 * mu * mu / (32.0 * lam))
        tet_energy[t] = vol[t] * psi


@fast_kernel
def evaluate_snh_gradient(
    x: ti.types.ndarray(), tets: ti.types.ndarray(), dFdx: ti.types.ndarray(), vol: ti.types.ndarray(),
    mu: ti.f64, lam: ti.f64, grad: ti.types.ndarray(),
):
    """``grad[v] += V_t P(F_t) g_a`` for every tet corner ``a`` at vertex ``v`` (N); ``grad`` zeroed first."""
    alpha = 1.0 + 0.75 * mu / lam
    ti.loop_config(serialize=ti.static(serial_loops()))  # CPU: serial (a forked replay worker hangs in a parallel loop)
    for v, d in ti.ndrange(grad.shape[0], 3):
        grad[v, d] = 0.0
    ti.loop_config(serialize=ti.static(serial_loops()))  # CPU: serial (a forked replay worker hangs in a parallel loop)
    for t in range(tets.shape[0]):
        F = _tet_deformation_gradient(x, tets, dFdx, t)
        I_C = (F * F).sum()
        J = F.determinant()
        P = mu * (1.0 - 1.0 / (I_C + 1.0)) * F + lam * (J - alpha) * cofactor(F)
        for a in ti.static(range(4)):
            v = tets[t, a]
            for i in ti.static(range(3)):
                acc = 0.0
                for j in ti.static(range(3)):
                    acc += P[i, j] * dFdx[t, a, j]
                ti.atomic_add(grad[v, i], vol[t] * acc)


@ti.func
def isotropic_projected_block(U, sigma, V, S: ti.template(), twist, flip, dFdx: ti.template(), vol: ti.template(),
                              code: ti.i32, t: ti.i32, blocks: ti.template()):
    """``blocks[t] = V_t sum_m f(w_m) y_m y_m^T`` (12x12, N/m) of tet ``t`` from the analytic eigensystem of an
    isotropic energy's ``d2psi/dF2`` (Smith, de Goes, Kim 2019, "Analytic Eigensystems for Isotropic Distortion
    Energies", ACM TOG 38(1); Smith et al. 2018, sec. 4.2): three scaling modes ``U diag(z_m) V^T`` from the
    eigenvectors ``z_m`` of the 3x3 ``S = d2psi/dsigma2`` (diagonalised here, in place), and per pair ``(i, j)``
    (third index ``k``) a twist ``U (e_i e_j^T - e_j e_i^T) V^T / sqrt 2`` of eigenvalue ``twist[k]`` and a flip
    ``U (e_i e_j^T + e_j e_i^T) V^T / sqrt 2`` of eigenvalue ``flip[k]``; ``f`` the projection ``code``
    (:func:`~sim_core.ti_kernels.linalg.filter_eigenvalue`), ``y_m = (dvecF/dx)^T q_m``. ``U, sigma, V``: the
    rotation-variant SVD of ``F`` (:func:`_rotation_variant_svd`)."""
    Z = ti.Matrix.zero(ti.f64, 3, 3)
    jacobi_eigh(S, Z)
    # h[a, :] = V^T g_a with g_a = dFdx[t, a]
    h = ti.Matrix.zero(ti.f64, 4, 3)
    for a in ti.static(range(4)):
        for i in ti.static(range(3)):
            acc = 0.0
            for j in ti.static(range(3)):
                acc += V[j, i] * dFdx[t, a, j]
            h[a, i] = acc
    Y = ti.Matrix.zero(ti.f64, 12, 9)  # column m: (dvecF/dx)^T q_m
    w = ti.Vector.zero(ti.f64, 9)
    for m in ti.static(range(3)):
        w[m] = filter_eigenvalue(S[m, m], code)
        for a in ti.static(range(4)):
            for c in ti.static(range(3)):
                Y[3 * a + c, m] = (Z[0, m] * U[c, 0] * h[a, 0] + Z[1, m] * U[c, 1] * h[a, 1]
                                   + Z[2, m] * U[c, 2] * h[a, 2])
    for k in ti.static(range(3)):
        i = ti.static((1, 2, 0)[k])
        j = ti.static((2, 0, 1)[k])
        w[3 + k] = filter_eigenvalue(twist[k], code)
        w[6 + k] = filter_eigenvalue(flip[k], code)
        for a in ti.static(range(4)):
            for c in ti.static(range(3)):
                p = U[c, i] * h[a, j]
                q = U[c, j] * h[a, i]
                Y[3 * a + c, 3 + k] = _INV_SQRT2 * (p - q)
                Y[3 * a + c, 6 + k] = _INV_SQRT2 * (p + q)
    for r in range(12):
        for s in range(r, 12):
            acc = 0.0
            for m in ti.static(range(9)):
                acc += Y[r, m] * w[m] * Y[s, m]
            acc *= vol[t]
            blocks[t, r, s] = acc
            blocks[t, s, r] = acc


@ti.func
def _snh_projected_block(x: ti.template(), tets: ti.template(), dFdx: ti.template(), vol: ti.template(), mu: ti.f64,
                         lam: ti.f64, code: ti.i32, t: ti.i32, blocks: ti.template()):
    """``blocks[t] = V_t sum_m f(w_m) y_m y_m^T`` (12x12, N/m) of tet ``t`` from the analytic eigensystem
    (:func:`isotropic_projected_block`; twist ``mu_t + lam (J - alpha) sigma_k``, flip ``mu_t - lam (J - alpha)
    sigma_k``, Smith et al. 2018, eqs. 27-28)."""
    alpha = 1.0 + 0.75 * mu / lam
    F = _tet_deformation_gradient(x, tets, dFdx, t)
    U, sigma, V = _rotation_variant_svd(F)
    I_C = sigma.dot(sigma)
    J = sigma[0] * sigma[1] * sigma[2]
    mu_t = mu * (1.0 - 1.0 / (I_C + 1.0))
    stretch = lam * (J - alpha)
    dJ = ti.Vector([sigma[1] * sigma[2], sigma[2] * sigma[0], sigma[0] * sigma[1]])
    S = (2.0 * mu / (I_C + 1.0) ** 2) * sigma.outer_product(sigma) + lam * dJ.outer_product(dJ)
    for i in ti.static(range(3)):
        S[i, i] += mu_t
    # pairs (i, j) of the twist/flip modes; the third index c: (1, 2) -> 0, (2, 0) -> 1, (0, 1) -> 2
    S[1, 2] += stretch * sigma[0]
    S[2, 1] += stretch * sigma[0]
    S[2, 0] += stretch * sigma[1]
    S[0, 2] += stretch * sigma[1]
    S[0, 1] += stretch * sigma[2]
    S[1, 0] += stretch * sigma[2]
    twist = ti.Vector([mu_t + stretch * sigma[0], mu_t + stretch * sigma[1], mu_t + stretch * sigma[2]])
    flip = ti.Vector([mu_t - stretch * sigma[0], mu_t - stretch * sigma[1], mu_t - stretch * sigma[2]])
    isotropic_projected_block(U, sigma, V, S, twist, flip, dFdx, vol, code, t, blocks)


@fast_kernel
def evaluate_snh_hessian(
    x: ti.types.ndarray(), tets: ti.types.ndarray(), dFdx: ti.types.ndarray(), vol: ti.types.ndarray(),
    mu: ti.f64, lam: ti.f64, code: ti.i32, blocks: ti.types.ndarray(),
):
    """``blocks[t] = V_t sum_m f(w_m) y_m y_m^T`` (12x12, N/m) from the analytic eigensystem, every tet."""
    ti.loop_config(serialize=ti.static(serial_loops()))  # CPU: serial (a forked replay worker hangs in a parallel loop)
    for t in range(tets.shape[0]):
        _snh_projected_block(x, tets, dFdx, vol, mu, lam, code, t, blocks)


@fast_kernel
def evaluate_snh_hessian_rows(
    x: ti.types.ndarray(), tets: ti.types.ndarray(), dFdx: ti.types.ndarray(), vol: ti.types.ndarray(),
    mu: ti.f64, lam: ti.f64, code: ti.i32, rows: ti.types.ndarray(dtype=ti.i32, ndim=1), count: ti.i32,
    blocks: ti.types.ndarray(),
):
    """:func:`evaluate_snh_hessian` of the tets ``t = rows[r]``, ``r < count`` only (the other blocks left as they
    are): the blocks a projection of some copies' tets adds."""
    ti.loop_config(serialize=ti.static(serial_loops()))  # CPU: serial (a forked replay worker hangs in a parallel loop)
    for r in range(count):
        _snh_projected_block(x, tets, dFdx, vol, mu, lam, code, rows[r], blocks)


class TetSolidKernels:
    """Mixin of a tet solid's Taichi twin (before its NumPy class in the bases): energy, gradient and Hessian blocks
    from the kernels named by :attr:`energy_kernel`, :attr:`gradient_kernel` and :attr:`hessian_kernel` (each
    ``(x, tets, dFdx, vol, mu, lam, [code,] out)``, the NumPy class's ``mu``, ``lam``); construction, validation,
    parameters and ``parameter_gradient`` are the NumPy class's, whose rest-shape arrays (``tets``, ``tet_dFdx``,
    ``tet_rest_volume``) are uploaded to the device once.

    Raises:
        ConfigError: as the NumPy class, or the Taichi backend is not initialised
            (:func:`sim_core.ti_backend.init_backend`).
        MeshError: as the NumPy class.
    """

    energy_kernel = staticmethod(evaluate_snh_energy)
    gradient_kernel = staticmethod(evaluate_snh_gradient)
    hessian_kernel = staticmethod(evaluate_snh_hessian)
    restricted = None
    """No restriction to some tets (the NumPy class's ``restricted``): a copy would keep the whole mesh's device arrays,
    so :meth:`sim_core.adjoint.StepLinearization.support_product` builds a Taichi twin's blocks whole."""

    def __init__(self, tets: np.ndarray, x_rest: np.ndarray, youngs_modulus: float, poisson_ratio: float) -> None:
        require_backend(type(self).__name__)
        super().__init__(tets, x_rest, youngs_modulus, poisson_ratio)
        self._tets_dev = upload_constant(self.tets, ti.i32)
        self._dFdx_dev = upload_constant(self.tet_dFdx, ti.f64)
        self._vol_dev = upload_constant(self.tet_rest_volume, ti.f64)
        self._x = DeviceArray(ti.f64)
        self._tet_energy = DeviceArray(ti.f64)
        self._grad = DeviceArray(ti.f64)
        self._blocks = DeviceArray(ti.f64)

    def energy(self, x: np.ndarray) -> float:
        """Energy ``sum_t V_t psi(F_t)`` in J at positions ``x`` ``(n, 3)``."""
        k = self.tets.shape[0]
        if k == 0:
            return 0.0
        out = self._tet_energy.ensure((k,))
        self.energy_kernel(self._x.upload(x), self._tets_dev, self._dFdx_dev, self._vol_dev, self.mu, self.lam, out)
        return float(np.sum(out.to_numpy()))

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """dE/dx in N, shape ``(n, 3)``."""
        x = np.asarray(x, dtype=float)
        if self.tets.shape[0] == 0:
            return np.zeros_like(x)
        g = self._grad.ensure(x.shape)
        self.gradient_kernel(self._x.upload(x), self._tets_dev, self._dFdx_dev, self._vol_dev, self.mu, self.lam, g)
        return g.to_numpy()

    def hessian(self, x: np.ndarray, projection: Projection = "clamp") -> HessianBlocks:
        """Per-tet 12x12 Hessian blocks in N/m (``projection`` as the NumPy class's ``hessian``).

        Raises:
            ValueError: unknown projection.
        """
        code = projection_code(projection)
        k = self.tets.shape[0]
        if k == 0:
            return HessianBlocks(self.tets, np.zeros((0, 12, 12)))
        out = self._blocks.ensure((k, 12, 12))
        self.hessian_kernel(self._x.upload(x), self._tets_dev, self._dFdx_dev, self._vol_dev, self.mu, self.lam,
                            code, out)
        return HessianBlocks(self.tets, out.to_numpy())


class TiStableNeoHookean(TetSolidKernels, StableNeoHookean):
    """:class:`StableNeoHookean` whose energy, gradient and Hessian run as Taichi kernels (:class:`TetSolidKernels`:
    :func:`evaluate_snh_energy`, :func:`evaluate_snh_gradient`, :func:`evaluate_snh_hessian`).

    Args:
        tets, x_rest, youngs_modulus, poisson_ratio: as :class:`StableNeoHookean`.

    Raises:
        ConfigError: as :class:`StableNeoHookean`, or the Taichi backend is not initialised
            (:func:`sim_core.ti_backend.init_backend`).
        MeshError: as :class:`StableNeoHookean`.
    """
