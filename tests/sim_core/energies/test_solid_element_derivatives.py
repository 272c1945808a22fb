"""The solid elements beside Stable Neo-Hookean (nodal pressure, Green strain, modified Saint Venant-Kirchhoff):
gradient and Hessian against central differences of the energy and gradient, E / nu derivatives against central differences, and the PSD projection
(negative eigenvalues where strains of order 0.5 make the exact Hessian indefinite; none changed at rest, where the
small-strain response is exact). The element-specific checks are in test_nodal_pressure.py,
test_green_strain.py and test_modified_stvk.py."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.energies.green_strain import GreenStrainSolid
from sim_core.energies.modified_stvk import ModifiedStVKSolid
from sim_core.energies.neohookean.reference import StableNeoHookean
from sim_core.energies.nodal_pressure.reference import NodalPressureNeoHookean
from tests.sim_core.energies.solid_cases import E_GEL, NU_GEL, deformed, gel_block
from tests.support.fd import dense_hessian, fd_gradient, fd_hessian, relative_error

ELEMENTS = [NodalPressureNeoHookean, GreenStrainSolid, ModifiedStVKSolid]

INDEFINITE = {ModifiedStVKSolid: 3e-4}
"""Noise amplitude (m) of the projection test's state where 6e-4 inverts a tet (this law's energy is infinite there)."""


@pytest.mark.parametrize("element", ELEMENTS)
@pytest.mark.parametrize("nu", [0.2, 0.45, 0.49])
def test_gradient_and_hessian_match_finite_differences(element, nu: float) -> None:
    mesh = gel_block()
    pot = element(mesh.tets, mesh.x, E_GEL, nu)
    x = deformed(mesh.x, 1)
    assert relative_error(pot.gradient(x), fd_gradient(pot.energy, x, h=1e-8)) < 1e-5
    H = dense_hessian(pot.hessian(x, "none"), x.shape[0])
    assert relative_error(H, fd_hessian(pot.gradient, x, h=1e-9)) < 1e-5
    assert np.allclose(H, H.T, rtol=0, atol=1e-9 * np.abs(H).max())


@pytest.mark.parametrize("element", ELEMENTS)
@pytest.mark.parametrize("name", ["youngs_modulus", "poisson_ratio"])
def test_parameter_gradient_matches_finite_differences(element, name: str) -> None:
    mesh = gel_block()
    x = deformed(mesh.x, 2)
    base = {"youngs_modulus": E_GEL, "poisson_ratio": NU_GEL}
    step = 1e-6 * base[name]

    def gradient_at(value: float) -> np.ndarray:
        return element(mesh.tets, mesh.x, **{**base, name: value}).gradient(x)

    fd = (gradient_at(base[name] + step) - gradient_at(base[name] - step)) / (2 * step)
    pot = element(mesh.tets, mesh.x, E_GEL, NU_GEL)
    assert relative_error(pot.parameter_gradient(x, name), fd) < 1e-6
    with pytest.raises(KeyError, match="density"):
        pot.parameter_gradient(x, "density")


@pytest.mark.parametrize("element", ELEMENTS)
@pytest.mark.parametrize("projection", ["clamp", "abs"])
def test_the_projected_hessian_is_psd_where_the_exact_one_is_not(element, projection: str) -> None:
    mesh = gel_block()
    pot = element(mesh.tets, mesh.x, E_GEL, NU_GEL)
    x = deformed(mesh.x, 3, INDEFINITE.get(element, 6e-4))
    exact = np.linalg.eigvalsh(dense_hessian(pot.hessian(x, "none"), x.shape[0]))
    projected = np.linalg.eigvalsh(dense_hessian(pot.hessian(x, projection), x.shape[0]))
    assert exact.min() < -1e-3 * exact.max()
    assert projected.min() >= -1e-10 * projected.max()
    rest_exact = dense_hessian(pot.hessian(mesh.x, "none"), x.shape[0])
    assert relative_error(dense_hessian(pot.hessian(mesh.x, projection), x.shape[0]), rest_exact) < 1e-12


@pytest.mark.parametrize("element", [StableNeoHookean, GreenStrainSolid, ModifiedStVKSolid])
def test_a_law_restricted_to_some_tets_gives_their_blocks_bit_for_bit(element) -> None:
    """``restricted`` (the drive step's support product builds the tets under the effector only,
    :meth:`sim_core.adjoint.StepLinearization.support_product`): the exact and projected blocks of the chosen tets,
    their gradient and energy, equal the whole law's restricted to them, and the whole law's memo is left alone."""
    mesh = gel_block()
    pot = element(mesh.tets, mesh.x, E_GEL, NU_GEL)
    x = deformed(mesh.x, 4)
    full = pot.hessian(x, "none")
    _ = pot.tet_dvecF_dx if element is StableNeoHookean else pot.per_tet.tet_dvecF_dx  # a kept d vec(F)/dx, sliced too
    chosen = np.flatnonzero(np.arange(len(mesh.tets)) % 3 == 1)
    part = pot.restricted(chosen)
    for projection in ("none", "clamp"):
        blocks = part.hessian(x, projection)
        assert np.array_equal(blocks.vertices, mesh.tets[chosen])
        assert np.array_equal(blocks.blocks, pot.hessian(x, projection).blocks[chosen])
    alone = element(mesh.tets[chosen], mesh.x, E_GEL, NU_GEL)  # the same tets built on their own
    assert np.allclose(part.gradient(x), alone.gradient(x), rtol=0, atol=1e-12 * np.abs(alone.gradient(x)).max())
    assert part.energy(x) == pytest.approx(alone.energy(x), rel=1e-12)
    assert np.array_equal(pot.hessian(x, "none").blocks, full.blocks)  # the whole law unchanged after it


def test_the_taichi_twins_are_not_restricted() -> None:
    """A Taichi twin's kernels read the whole mesh's device arrays: a copy with some tets' host arrays would pair them
    wrongly, so the twins offer no ``restricted`` (the support product then builds their blocks whole)."""
    from sim_core.energies.green_strain.kernel import TiGreenStrainSolid
    from sim_core.energies.neohookean.kernel import TiStableNeoHookean

    assert TiStableNeoHookean.restricted is None and TiGreenStrainSolid.restricted is None
