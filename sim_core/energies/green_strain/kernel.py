"""Saint Venant-Kirchhoff tetrahedra in Taichi: energy, gradient and projected 12x12 Hessian blocks.

The same quantities as :class:`sim_core.energies.green_strain.reference.GreenStrainSolid` (the reference and test
oracle), one tet per thread, float64. With ``F`` the deformation gradient, ``E = (F^T F - I) / 2`` the Green strain
and ``S = 2 mu E + lam tr(E) I`` (Bonet and Wood, Nonlinear Continuum Mechanics for FE Analysis, 2nd ed., eq. 6.8)::

    psi = mu tr(E^2) + lam / 2 tr(E)^2,        P = F S,
    d2psi / dF_ij dF_ab = delta_ia S_bj + mu ((F F^T)_ia delta_jb + F_ib F_aj) + lam F_ij F_ab      (vec F: 3 i + j),

and the Hessian from the analytic eigensystem of ``d2psi/dF2`` (Smith, de Goes, Kim 2019, "Analytic Eigensystems
for Isotropic Distortion Energies", ACM TOG 38(1)): in the singular values ``sigma`` of the rotation-variant SVD
``F = U diag(sigma) V^T`` (``sigma_2 < 0`` for an inverted tet; ``psi`` is even in each)::

    psi = mu / 4 sum_i (sigma_i^2 - 1)^2 + lam / 8 (I_C - 3)^2,           I_C = sum_i sigma_i^2,
    d2psi / dsigma_i dsigma_j = delta_ij (mu (3 sigma_i^2 - 1) + lam / 2 (I_C - 3)) + lam sigma_i sigma_j,
    twist_k = (psi_i + psi_j) / (sigma_i + sigma_j) = mu (sigma_i^2 - sigma_i sigma_j + sigma_j^2 - 1) + c,
    flip_k  = (psi_i - psi_j) / (sigma_i - sigma_j) = mu (sigma_i^2 + sigma_i sigma_j + sigma_j^2 - 1) + c,

with ``c = lam / 2 (I_C - 3)``, ``psi_i = d psi / d sigma_i`` and ``(i, j, k)`` a cyclic triple (polynomials: no
division by coinciding singular values); each eigenvalue is filtered per projection and the modes mapped to the
vertices as the Stable Neo-Hookean kernel's (:func:`sim_core.energies.neohookean.kernel.isotropic_projected_block`).
The reference projects the 9x9 matrix numerically; the two agree to round-off (one projection of one symmetric
matrix). Loops are serial on the CPU (``serial_loops``): sums into shared vertices in element order, reproducible bit
for bit.
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel and ti.func annotations as
# objects (string annotations are rejected).

from sim_core.energies.green_strain.reference import GreenStrainSolid
from sim_core.energies.neohookean.kernel import (TetSolidKernels, _rotation_variant_svd, _tet_deformation_gradient,
                                                isotropic_projected_block)
from sim_core.ti_backend import serial_loops, ti
from sim_core.ti_kernels.launch import fast_kernel
from sim_core.ti_kernels.linalg import matmul


@ti.func
def green_strain_stress(F, mu: ti.f64, lam: ti.f64):
    """``(E, tr E, S)`` of a 3x3 ``F``: Green strain, its trace and the second Piola-Kirchhoff stress (Pa)."""
    E = 0.5 * (matmul(F.transpose(), F) - ti.Matrix.identity(ti.f64, 3))
    tr = E[0, 0] + E[1, 1] + E[2, 2]
    S = 2.0 * mu * E + lam * tr * ti.Matrix.identity(ti.f64, 3)
    return E, tr, S


@ti.func
def green_strain_psi(E, tr, mu: ti.f64, lam: ti.f64):
    """``psi = mu tr(E^2) + lam / 2 tr(E)^2`` (J/m^3) of a symmetric ``E`` and its trace."""
    return mu * (E * E).sum() + 0.5 * lam * tr * tr


@fast_kernel
def evaluate_green_strain_energy(
    x: ti.types.ndarray(), tets: ti.types.ndarray(), dFdx: ti.types.ndarray(), vol: ti.types.ndarray(),
    mu: ti.f64, lam: ti.f64, tet_energy: ti.types.ndarray(),
):
    """``tet_energy[t] = V_t psi(F_t)`` (J)."""
    ti.loop_config(serialize=ti.static(serial_loops()))  # CPU: serial (a forked replay worker hangs in a parallel loop)
    for t in range(tets.shape[0]):
        F = _tet_deformation_gradient(x, tets, dFdx, t)
        E, tr, _ = green_strain_stress(F, mu, lam)
        tet_energy[t] = vol[t] * green_strain_psi(E, tr, mu, lam)


@fast_kernel
def evaluate_green_strain_gradient(
    x: ti.types.ndarray(), tets: ti.types.ndarray(), dFdx: ti.types.ndarray(), vol: ti.types.ndarray(),
    mu: ti.f64, lam: ti.f64, grad: ti.types.ndarray(),
):
    """``grad[v] += V_t (F_t S_t) g_a`` for every tet corner ``a`` at vertex ``v`` (N); ``grad`` zeroed first."""
    ti.loop_config(serialize=ti.static(serial_loops()))  # CPU: serial (a forked replay worker hangs in a parallel loop)
    for v, d in ti.ndrange(grad.shape[0], 3):
        grad[v, d] = 0.0
    ti.loop_config(serialize=ti.static(serial_loops()))  # CPU: serial (a forked replay worker hangs in a parallel loop)
    for t in range(tets.shape[0]):
        F = _tet_deformation_gradient(x, tets, dFdx, t)
        _, _, S = green_strain_stress(F, mu, lam)
        P = matmul(F, S)
        for a in ti.static(range(4)):
            v = tets[t, a]
            for i in ti.static(range(3)):
                acc = 0.0
                for j in ti.static(range(3)):
                    acc += P[i, j] * dFdx[t, a, j]
                ti.atomic_add(grad[v, i], vol[t] * acc)


@ti.func
def _green_strain_projected_block(x: ti.template(), tets: ti.template(), dFdx: ti.template(), vol: ti.template(),
                                  mu: ti.f64, lam: ti.f64, code: ti.i32, t: ti.i32, blocks: ti.template()):
    """``blocks[t] = V_t sum_m f(w_m) y_m y_m^T`` (12x12, N/m) of tet ``t`` from the analytic eigensystem of
    ``psi(sigma)`` (module docstring; :func:`~sim_core.energies.neohookean.kernel.isotropic_projected_block`)."""
    F = _tet_deformation_gradient(x, tets, dFdx, t)
    U, sigma, V = _rotation_variant_svd(F)
    s2 = sigma * sigma
    c = 0.5 * lam * (s2.sum() - 3.0) - mu
    S = lam * sigma.outer_product(sigma)
    for i in ti.static(range(3)):
        S[i, i] += 3.0 * mu * s2[i] + c
    # pair (i, j) of mode k: (1, 2), (2, 0), (0, 1)
    twist = ti.Vector.zero(ti.f64, 3)
    flip = ti.Vector.zero(ti.f64, 3)
    for k in ti.static(range(3)):
        i = ti.static((1, 2, 0)[k])
        j = ti.static((2, 0, 1)[k])
        base = mu * (s2[i] + s2[j]) + c
        twist[k] = base - mu * sigma[i] * sigma[j]
        flip[k] = base + mu * sigma[i] * sigma[j]
    isotropic_projected_block(U, sigma, V, S, twist, flip, dFdx, vol, code, t, blocks)


@fast_kernel
def evaluate_green_strain_hessian(
    x: ti.types.ndarray(), tets: ti.types.ndarray(), dFdx: ti.types.ndarray(), vol: ti.types.ndarray(),
    mu: ti.f64, lam: ti.f64, code: ti.i32, blocks: ti.types.ndarray(),
):
    """``blocks[t] = V_t M^T f(A) M`` (12x12, N/m) of every tet (:func:`_green_strain_projected_block`)."""
    ti.loop_config(serialize=ti.static(serial_loops()))  # CPU: serial (a forked replay worker hangs in a parallel loop)
    for t in range(tets.shape[0]):
        _green_strain_projected_block(x, tets, dFdx, vol, mu, lam, code, t, blocks)


@fast_kernel
def evaluate_green_strain_hessian_rows(
    x: ti.types.ndarray(), tets: ti.types.ndarray(), dFdx: ti.types.ndarray(), vol: ti.types.ndarray(),
    mu: ti.f64, lam: ti.f64, code: ti.i32, rows: ti.types.ndarray(dtype=ti.i32, ndim=1), count: ti.i32,
    blocks: ti.types.ndarray(),
):
    """:func:`evaluate_green_strain_hessian` of the tets ``t = rows[r]``, ``r < count`` only (the other blocks left
    as they are): the blocks a projection of some copies' tets adds."""
    ti.loop_config(serialize=ti.static(serial_loops()))  # CPU: serial (a forked replay worker hangs in a parallel loop)
    for r in range(count):
        _green_strain_projected_block(x, tets, dFdx, vol, mu, lam, code, rows[r], blocks)


class TiGreenStrainSolid(TetSolidKernels, GreenStrainSolid):
    """:class:`GreenStrainSolid` whose energy, gradient and Hessian run as Taichi kernels
    (:class:`~sim_core.energies.neohookean.kernel.TetSolidKernels`: :func:`evaluate_green_strain_energy`,
    :func:`evaluate_green_strain_gradient`, :func:`evaluate_green_strain_hessian`).

    Args:
        tets, x_rest, youngs_modulus, poisson_ratio: as :class:`GreenStrainSolid`.

    Raises:
        ConfigError: as :class:`GreenStrainSolid`, or the Taichi backend is not initialised
            (:func:`sim_core.ti_backend.init_backend`).
        MeshError: as :class:`GreenStrainSolid`.
    """

    energy_kernel = staticmethod(evaluate_green_strain_energy)
    gradient_kernel = staticmethod(evaluate_green_strain_gradient)
    hessian_kernel = staticmethod(evaluate_green_strain_hessian)
