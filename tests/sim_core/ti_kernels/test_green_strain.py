"""The Green-strain (Saint Venant-Kirchhoff) gel's Taichi kernels equal its NumPy reference.

The Taichi twin (:mod:`sim_core.energies.green_strain.kernel`: energy, gradient, exact / clamped / flipped 12x12
blocks) and the fused Newton-loop part (:mod:`sim_core.energies.green_strain.fused_kernel`: energy, gradient and exact
Hessian into the static pattern's slots, the projected blocks through the same slots) against
:class:`~sim_core.energies.green_strain.reference.GreenStrainSolid` to round-off (1e-10 relative to each array's
scale, the Jacobi eigen-decomposition against LAPACK's) on random deformations, on a compressed block with an
inverted tet (where the exact blocks are indefinite and the projection has work to do), and at rest; the projected
blocks are PSD.
"""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.assembly import HessianAssembler
from sim_core.energies.green_strain.reference import GreenStrainSolid
from tests.sim_core.energies.solid_cases import E_GEL, NU_GEL, deformed, gel_block
from tests.sim_core.ti_kernels.conftest import assert_projection_active_and_psd, assert_same_potential, relative_error


def _pair(nu: float = NU_GEL):
    from sim_core.energies.green_strain.kernel import TiGreenStrainSolid

    mesh = gel_block()
    return mesh, GreenStrainSolid(mesh.tets, mesh.x, E_GEL, nu), TiGreenStrainSolid(mesh.tets, mesh.x, E_GEL, nu)


def _compressed_with_an_inverted_tet(mesh, ref) -> np.ndarray:
    """The block squeezed 25 % in depth, stretched 10 % along x, perturbed, tet 0 inverted (``det F < 0``)."""
    x = deformed(mesh.x, 3, 2e-4) * np.array([1.1, 1.0, 0.75])
    t = mesh.tets[0]
    a, b, c, d = x[t]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n)
    x[t[3]] = d - 2.5 * np.dot(d - a, n) * n
    assert np.linalg.det(ref.deformation_gradient(x)[0]) < 0
    return x


def test_the_taichi_twin_is_the_reference_on_random_deformations(ti_cpu):
    mesh, ref, tik = _pair()
    for seed, amplitude in ((0, 5e-5), (1, 2e-4), (2, 6e-4)):
        assert_same_potential(ref, tik, deformed(mesh.x, seed, amplitude))
    x = deformed(mesh.x, 2, 6e-4)
    assert abs(tik.energy(mesh.x)) < 1e-12 * ref.energy(x)  # zero energy and force at rest
    assert np.max(np.abs(tik.gradient(mesh.x))) < 1e-12 * np.max(np.abs(ref.gradient(x)))
    h_ref, h_ti = ref.hessian(mesh.x, "none").blocks, tik.hessian(mesh.x, "none").blocks
    assert relative_error(h_ti, h_ref) < 1e-12


@pytest.mark.parametrize("nu", [0.3, NU_GEL, 0.49])
def test_the_taichi_twin_is_the_reference_on_compressed_and_inverted_tets(ti_cpu, nu):
    mesh, ref, tik = _pair(nu)
    x = _compressed_with_an_inverted_tet(mesh, ref)
    assert_same_potential(ref, tik, x)
    assert_projection_active_and_psd(ref, tik, x)


def test_the_fused_part_is_the_reference_with_fixed_dofs(ti_cpu):
    """Energy, gradient, exact Hessian and both projections summed through the static pattern of a block whose
    bottom is fixed (rows and columns of fixed DoFs are not stored) equal the reference's blocks assembled."""
    from sim_core.energies.green_strain.fused_kernel import FusedGreenStrainSolid
    from sim_core.fused_elastic import FusedElastic

    mesh = gel_block()
    ref = GreenStrainSolid(mesh.tets, mesh.x, E_GEL, NU_GEL)
    free = np.repeat(mesh.x[:, 2] > 1e-9, 3)
    free[[3 * 30, 3 * 31 + 2]] = False
    fused = FusedElastic([ref])
    assert [type(part) for part in fused._parts] == [FusedGreenStrainSolid]
    asm = HessianAssembler(mesh.x.size)
    fused.bind(asm.static_pattern(fused.block_vertex_arrays(mesh.x), free))
    diag = np.linspace(1.0, 2.0, mesh.x.size)
    for x in (deformed(mesh.x, 5, 3e-4), _compressed_with_an_inverted_tet(mesh, ref)):
        assert fused.energy(x) == pytest.approx(ref.energy(x), rel=1e-12)  # the energy-only kernel
        assert relative_error(fused.gradient(x), ref.gradient(x)) < 1e-12
        assert fused.energy(x) == pytest.approx(ref.energy(x), rel=1e-12)  # kept from the fused evaluation
        H_ref = asm.assemble_upper([ref.hessian(x, "none")], [], diag, free)
        H = asm.assemble_upper_values(fused.pattern, fused.hessian_values(x), [], diag, free)
        assert np.array_equal(H.indptr, H_ref.indptr) and np.array_equal(H.indices, H_ref.indices)
        assert relative_error(H.data, H_ref.data) < 1e-12
        for projection in ("clamp", "abs"):
            P_ref = asm.assemble_upper([ref.hessian(x, projection)], [], diag, free)
            P = asm.assemble_upper_values(fused.pattern, fused.projected_hessian_values(x, projection), [], diag, free)
            assert relative_error(P.data, P_ref.data) < 1e-10, projection
