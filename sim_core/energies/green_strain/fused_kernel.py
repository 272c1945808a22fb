"""Saint Venant-Kirchhoff tets in one Taichi kernel: energy, gradient and exact Hessian into CSR slots.

The fused counterpart of :class:`sim_core.energies.green_strain.reference.GreenStrainSolid` (the reference and test
oracle) for the Newton loop, as :mod:`sim_core.energies.neohookean.fused_kernel` is the Stable Neo-Hookean gel's: one
launch per iteration computes, per tet, with ``E = (F^T F - I) / 2``, ``S = 2 mu E + lam tr(E) I``, ``B = F F^T``
and ``g_a`` row ``a`` of ``tet_dFdx`` (Bonet and Wood, Nonlinear Continuum Mechanics for FE Analysis, 2nd ed.,
eq. 6.8; the tet form of :mod:`sim_core.energies.membrane.fused_stvk_kernel`'s triangles)::

    E_t = V (mu tr(E^2) + lam / 2 tr(E)^2),        dE_t/dx_a = V F S g_a,
    H[3a+c, 3b+d] = V (delta_cd g_a.S g_b + mu (g_a.g_b) B_cd + mu (g_b.F_c)(g_a.F_d) + lam (g_a.F_c)(g_b.F_d)),

``F_c`` row ``c`` of ``F`` (the exact, unprojected blocks ``V M^T (d2psi/dF2) M`` of the kernel module's docstring
contracted by hand), added straight into the values of the solver's static sparsity pattern through the packed
upper slot table (:func:`sim_core.ti_kernels.block_projection.upper_slot_table`). The PSD-projected blocks, which the
solver asks for when PARDISO's Cholesky refuses the exact matrix, are the Taichi twin's
(:func:`sim_core.energies.green_strain.kernel.evaluate_green_strain_hessian`: the 9x9 ``d2psi/dF2`` projected by
Jacobi). Serial loops on the CPU: sums in element order, bitwise reproducible run to run.
"""

# No ``from __future__ import annotations`` here: Taichi reads kernel and ti.func annotations as
# objects (string annotations are rejected).

import numpy as np

from sim_core.energies.green_strain.kernel import (evaluate_green_strain_hessian, evaluate_green_strain_hessian_rows,
                                                   green_strain_psi, green_strain_stress)
from sim_core.energies.neohookean.fused_kernel import (FusedStableNeoHookean, _tet_state, add_projected_with,
                                                      evaluate_with, free_corners)
from sim_core.ti_backend import serial_loops, ti
from sim_core.ti_kernels import linalg
from sim_core.ti_kernels.block_projection import add_upper_entry, upper_index
from sim_core.ti_kernels.launch import summing_kernel

_F64_1, _F64_2, _F64_3, _I32_2 = linalg.F64_1, linalg.F64_2, linalg.F64_3, linalg.I32_2


@summing_kernel
def green_strain_energy(x: _F64_2, tets: _I32_2, dFdx: _F64_3, vol: _F64_1, mu: ti.f64, lam: ti.f64,
                        energy: _F64_1):
    """``sum_t V_t psi(F_t)`` in J."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for t in range(tets.shape[0]):
        F, _G = _tet_state(x, tets, dFdx, t)
        E, tr, _S = green_strain_stress(F, mu, lam)
        energy[t % energy.shape[0]] += vol[t] * green_strain_psi(E, tr, mu, lam)


@ti.func
def _add_entry(values: ti.template(), upper: ti.template(), t, a, b, c: ti.template(), d: ti.template(),
               lGF: ti.template(), muGF: ti.template(), GF: ti.template(), B: ti.template(), mgg, sgg, V):
    """Add ``H[3a+c, 3b+d]`` (module docstring) through the packed slot table, if it is stored:
    ``(lam (g_a.F_c)(g_b.F_d) + mu (g_b.F_c)(g_a.F_d) + mgg B_cd + [c = d] sgg) V`` with ``mgg = mu g_a.g_b``,
    ``sgg = g_a.S g_b`` (the local matrices by reference: a ``ti.func`` copies its other arguments)."""
    slot = upper[t, upper_index(12, 3 * a + c, 3 * b + d)]
    if slot != -1:  # entries of fixed DoFs are not computed
        h = lGF[a, c] * GF[b, d] + muGF[b, c] * GF[a, d] + mgg * B[c, d]
        if ti.static(c == d):
            h += sgg
        add_upper_entry(values, slot, h * V)


@summing_kernel
def green_strain_energy_gradient_hessian(
    x: _F64_2, tets: _I32_2, dFdx: _F64_3, vol: _F64_1, upper: _I32_2, mu: ti.f64, lam: ti.f64,
    grad: _F64_2, values: _F64_1,
    energy: _F64_1,
):
    """Energy (J, returned); adds the forces to ``grad`` (n, 3) in N and the exact Hessian entries (N/m) to
    ``values`` through the packed upper slot table ``upper`` (t, 78) (module docstring). Corners without a free DoF
    are skipped (their entries are not stored)."""
    ti.loop_config(serialize=ti.static(serial_loops()))
    for t in range(tets.shape[0]):
        F, G = _tet_state(x, tets, dFdx, t)
        E, tr, S = green_strain_stress(F, mu, lam)
        V = vol[t]
        energy[t % energy.shape[0]] += V * green_strain_psi(E, tr, mu, lam)
        GP = G @ (F @ S).transpose()  # GP[a, i] = (F S g_a)_i
        for a in ti.static(range(4)):
            v = tets[t, a]
            for i in ti.static(range(3)):
                grad[v, i] += V * GP[a, i]
        GF = G @ F.transpose()  # GF[a, c] = g_a . F_c
        GS = G @ S  # GS[a, :] = S g_a (S symmetric)
        B = F @ F.transpose()
        lGF = lam * GF  # the left factors of the entries' products, formed once per tet
        muGF = mu * GF
        free = free_corners(upper, t)  # per corner: has a free DoF
        for a in range(4):
            if free[a] == 1:
                ga = ti.Vector([G[a, 0], G[a, 1], G[a, 2]])
                sa = ti.Vector([GS[a, 0], GS[a, 1], GS[a, 2]])
                for b in range(a, 4):
                    if free[b] == 1:
                        gb = ti.Vector([G[b, 0], G[b, 1], G[b, 2]])
                        mgg = mu * ga.dot(gb)
                        sgg = sa.dot(gb)
                        if b == a:  # the diagonal block: its upper triangle
                            for c, d in ti.static(ti.ndrange(3, 3)):
                                if ti.static(c <= d):
                                    _add_entry(values, upper, t, a, a, c, d, lGF, muGF, GF, B, mgg, sgg, V)
                        else:
                            for c, d in ti.static(ti.ndrange(3, 3)):
                                _add_entry(values, upper, t, a, b, c, d, lGF, muGF, GF, B, mgg, sgg, V)


def remote_evaluate(args: tuple, x: np.ndarray, grad: np.ndarray, values: np.ndarray) -> float:
    """:meth:`FusedGreenStrainSolid.evaluate` from its ``offload_recipe`` arguments ``(tets, dFdx, vol, upper, mu,
    lam)``: energy in J (returned), the gradient (N) added to ``grad`` ``(n, 3)`` and the exact Hessian (N/m) to
    ``values`` (the function an :class:`~sim_core.elastic_worker.ElasticWorker` runs)."""
    return evaluate_with(green_strain_energy_gradient_hessian, args, x, grad, values)


def remote_add_projected(args: tuple, x: np.ndarray, grad: np.ndarray, values: np.ndarray) -> float:
    """:meth:`FusedGreenStrainSolid.add_projected` from its ``offload_projected_recipe`` arguments ``(tets, dFdx,
    vol, slots, mu, lam, projection code)``: the projected Hessian blocks (N/m) added into ``values``; returns 0.0."""
    return add_projected_with(evaluate_green_strain_hessian, args, x, values)


class FusedGreenStrainSolid(FusedStableNeoHookean):
    """Fused Newton-loop evaluation of a :class:`~sim_core.energies.green_strain.reference.GreenStrainSolid` (module
    docstring): the Stable Neo-Hookean part's
    slot tables, device copies, offload recipes and projected-Hessian routes with this law's kernels.

    Args:
        potential: the reference potential (its tets, ``tet_dFdx``, rest volumes and Lamé parameters ``mu``,
            ``lam`` are read once).

    Raises:
        ConfigError: the Taichi backend is not initialised (:func:`sim_core.ti_backend.init_backend`).
    """

    energy_kernel = staticmethod(green_strain_energy)
    evaluate_kernel = staticmethod(green_strain_energy_gradient_hessian)
    projected_kernel = staticmethod(evaluate_green_strain_hessian)
    projected_rows_kernel = staticmethod(evaluate_green_strain_hessian_rows)
    remote_module = __name__
