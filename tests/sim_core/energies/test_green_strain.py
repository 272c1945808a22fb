"""Saint Venant-Kirchhoff tets (the Green-strain gel element): the linearisation against the independent P1 assembly
(tests/support/linear_fe.py), the closed-form energy and normal stress of a uniformly sheared block, where it parts
from Stable Neo-Hookean, the element chosen by name, and the gel candidates on it. Its derivatives against finite
differences and its PSD projection: test_solid_element_derivatives.py."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.energies.green_strain import GreenStrainSolid, linear_lame_parameters
from sim_core.energies.neohookean.reference import StableNeoHookean
from sim_core.mesh.tet import tet_box
from tests.sim_core.energies.solid_cases import E_GEL, NU_GEL, assert_chosen_by_name, deformed, gel_block
from tests.support.fd import dense_hessian, relative_error
from tests.support.linear_fe import linear_stiffness


def test_the_small_strain_stiffness_is_linear_elasticity_as_stable_neohookeans() -> None:
    """At rest both laws are linear elasticity with the same E, nu: the Hessians equal the independent P1 assembly."""
    mesh = gel_block()
    n = mesh.x.shape[0]
    reference = linear_stiffness(mesh.x, mesh.tets, E_GEL, NU_GEL).toarray()
    H = dense_hessian(GreenStrainSolid(mesh.tets, mesh.x, E_GEL, NU_GEL).hessian(mesh.x, "none"), n)
    assert relative_error(H, reference) < 1e-12
    H_snh = dense_hessian(StableNeoHookean(mesh.tets, mesh.x, E_GEL, NU_GEL).hessian(mesh.x, "none"), n)
    assert relative_error(H_snh, reference) < 1e-12


def test_simple_shear_energy_and_the_normal_stress_that_thins_the_layer() -> None:
    """A block in uniform simple shear ``x = X + gamma Z e_x``: ``E = [[0, 0, g/2], [0, 0, 0], [g/2, 0, g^2/2]]``, so
    ``psi = mu (g^2/2 + g^4/4) + lam g^4/8`` (closed form) and the second Piola-Kirchhoff stress normal to the
    layer is ``S_zz = (mu + lam/2) g^2`` > 0: holding the thickness takes a tensile load; at zero normal load the
    sheared layer thins (what the pressed gel does in a slide). Stable Neo-Hookean's normal stress at the same shear
    is tensile too but 0.015 of it at nu 0.45 (its bulk term sees no volume change: simple shear keeps ``J = 1``)."""
    mesh = tet_box((0.01, 0.01, 0.004), (3, 3, 3), (0.0, 0.0, 0.0))
    pot = GreenStrainSolid(mesh.tets, mesh.x, E_GEL, NU_GEL)
    mu, lam = linear_lame_parameters(E_GEL, NU_GEL)
    volume = 0.01 * 0.01 * 0.004
    for g in (0.05, 0.15, 0.3):
        x = mesh.x + np.outer(g * mesh.x[:, 2], [1.0, 0.0, 0.0])
        psi = mu * (g**2 / 2 + g**4 / 4) + lam * g**4 / 8
        assert pot.energy(x) == pytest.approx(psi * volume, rel=1e-12)
        # the top face's normal load at fixed thickness: dE/dz summed over the top vertices = S_zz A (P_zz = S_zz)
        top = np.isclose(mesh.x[:, 2], 0.004)
        normal = pot.gradient(x)[top, 2].sum()
        assert normal == pytest.approx((mu + lam / 2) * g**2 * 0.01 * 0.01, rel=1e-10)
        snh_normal = StableNeoHookean(mesh.tets, mesh.x, E_GEL, NU_GEL).gradient(x)[top, 2].sum()
        assert 0 < snh_normal < 0.03 * normal


def test_the_gel_element_is_chosen_by_name() -> None:
    """``model.meta["solid_element"] = "green_strain"`` gives the solid this law (its energy at a sheared state is
    Saint Venant-Kirchhoff's, not Stable Neo-Hookean's); an unknown name is an error naming it."""
    assert_chosen_by_name("green_strain", lambda mesh: GreenStrainSolid(mesh.tets, mesh.x, E_GEL, NU_GEL),
                          "green_strian")

def test_the_gel_candidates_take_the_green_strain_gels_per_tet_branch() -> None:
    """The Maxwell branch (gel viscoelasticity) and the Kelvin-Voigt dashpot (gel damping) of a Green-strain gel are
    those of its per-tet Stable Neo-Hookean of the same E, nu, as for the nodal-pressure gel."""
    from sim_core.candidates.gel_damping import kelvin_voigt_branch
    from sim_core.candidates.gel_viscoelasticity import MaxwellBranch

    mesh = gel_block()
    green = GreenStrainSolid(mesh.tets, mesh.x, E_GEL, NU_GEL)
    x, x_prev = deformed(mesh.x, 6), deformed(mesh.x, 7)
    relaxed = green.deformation_gradient(x_prev)
    assert relative_error(relaxed, green.per_tet.deformation_gradient(x_prev)) == 0.0
    assert MaxwellBranch(green, relaxed, 0.4).energy(x) == pytest.approx(
        MaxwellBranch(green.per_tet, relaxed, 0.4).energy(x), rel=1e-12)
    assert kelvin_voigt_branch(green, x_prev, 0.02, 0.01).energy(x) == pytest.approx(
        kelvin_voigt_branch(green.per_tet, x_prev, 0.02, 0.01).energy(x), rel=1e-12)
