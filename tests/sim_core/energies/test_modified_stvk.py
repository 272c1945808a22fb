"""The modified Saint Venant-Kirchhoff gel element (``simulation.gel_element: modified_stvk``): linear elasticity at
small strain against the independent P1 assembly, the closed forms of a block in simple shear, in confined
compression and in uniaxial compression (where Saint Venant-Kirchhoff collapses and this law does not), an inverted
tet's infinite energy, the element chosen by name, and the gel candidates on it. Its derivatives against finite
differences and its PSD projection: test_solid_element_derivatives.py."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import brentq

from sim_core.energies.green_strain import GreenStrainSolid, linear_lame_parameters
from sim_core.energies.modified_stvk import ModifiedStVKSolid
from sim_core.mesh.tet import tet_box
from tests.sim_core.energies.solid_cases import E_GEL, NU_GEL, assert_chosen_by_name, deformed, gel_block
from tests.support.fd import dense_hessian, relative_error
from tests.support.linear_fe import linear_stiffness

SIZE = (0.01, 0.01, 0.004)
"""The homogeneously deformed block's edges in m (x, y, z)."""


def block_loads(pot, stretches: tuple[float, float, float]) -> tuple[float, float, float]:
    """The block of :data:`SIZE` (3 x 3 x 3 vertices) stretched homogeneously by ``diag(stretches)``: the loads in N
    on its +x, +y and +z faces (dE/dx summed over their vertices: ``P_ii`` times the rest face area, interior
    vertices in balance)."""
    mesh = tet_box(SIZE, (3, 3, 3), (0.0, 0.0, 0.0))
    g = pot(mesh).gradient(mesh.x * np.asarray(stretches))
    return tuple(float(g[np.isclose(mesh.x[:, i], SIZE[i]), i].sum()) for i in range(3))


def modified(mesh):
    return ModifiedStVKSolid(mesh.tets, mesh.x, E_GEL, NU_GEL)


def green(mesh):
    return GreenStrainSolid(mesh.tets, mesh.x, E_GEL, NU_GEL)


MU, LAM = linear_lame_parameters(E_GEL, NU_GEL)
AREA_Z = SIZE[0] * SIZE[1]


def test_the_small_strain_stiffness_is_linear_elasticity() -> None:
    """At rest the Hessian equals the independent P1 assembly of linear elasticity with the same E, nu (1e-12)."""
    mesh = gel_block()
    reference = linear_stiffness(mesh.x, mesh.tets, E_GEL, NU_GEL).toarray()
    H = dense_hessian(modified(mesh).hessian(mesh.x, "none"), mesh.x.shape[0])
    assert relative_error(H, reference) < 1e-12


def test_simple_shear_keeps_the_volume_term_out_of_the_layers_normal_stress() -> None:
    """A block in simple shear ``x = X + gamma Z e_x`` keeps ``J = 1``: ``psi = mu (g^2/2 + g^4/4)`` (closed form) and
    the normal load on the layer at fixed thickness is ``S_zz A = mu g^2 A``, the shear term's alone:
    ``mu / (mu + lam / 2)`` = 0.18 of Saint Venant-Kirchhoff's at nu 0.45 (its ``lam tr(E)`` answers the shear)."""
    mesh = tet_box(SIZE, (3, 3, 3), (0.0, 0.0, 0.0))
    pot, stvk = modified(mesh), green(mesh)
    top = np.isclose(mesh.x[:, 2], SIZE[2])
    for g in (0.05, 0.15, 0.3):
        x = mesh.x + np.outer(g * mesh.x[:, 2], [1.0, 0.0, 0.0])
        assert pot.energy(x) == pytest.approx(MU * (g**2 / 2 + g**4 / 4) * AREA_Z * SIZE[2], rel=1e-12)
        normal = pot.gradient(x)[top, 2].sum()
        assert normal == pytest.approx(MU * g**2 * AREA_Z, rel=1e-10)
        assert normal / stvk.gradient(x)[top, 2].sum() == pytest.approx(MU / (MU + LAM / 2), rel=1e-10)


def test_confined_compression_stress_rises_without_bound_where_saint_venant_kirchhoffs_collapses() -> None:
    """Confined (uniaxial-strain) compression ``F = diag(1, 1, l)``: ``P_zz = mu l (l^2 - 1) + lam ln(l) / l``
    (closed form, to 1e-10), monotone in ``l`` and without bound as ``l -> 0``; Saint Venant-Kirchhoff's
    ``(lam + 2 mu) l (l^2 - 1) / 2`` peaks at ``l = 1/sqrt 3`` and falls back to 0. The lateral confining stress is
    ``P_xx = lam ln(l)`` (closed form)."""
    stretches = np.linspace(0.05, 0.99, 48)
    loads = np.array([block_loads(modified, (1.0, 1.0, l)) for l in stretches])
    expected_zz = MU * stretches * (stretches**2 - 1) + LAM * np.log(stretches) / stretches
    assert loads[:, 2] == pytest.approx(expected_zz * AREA_Z, rel=1e-10)
    assert loads[:, 0] == pytest.approx(LAM * np.log(stretches) * SIZE[1] * SIZE[2], rel=1e-10)
    assert np.all(np.diff(loads[:, 2]) > 0)  # compression rises as l falls
    stvk = np.array([block_loads(green, (1.0, 1.0, l))[2] for l in stretches])
    assert stretches[np.argmin(stvk)] == pytest.approx(1 / np.sqrt(3), abs=0.02)
    assert loads[0, 2] < 20 * stvk.min()  # at l = 0.05: > 20x the largest compressive load StVK can carry


def test_uniaxial_compression_against_the_lateral_stretch_of_zero_side_load() -> None:
    """Uniaxial stress along z (sides free): ``F = diag(s, s, l)`` with ``s`` the root of
    ``P_xx = mu s (s^2 - 1) + lam ln(l s^2) / s = 0`` (closed form of the law, solved by bisection); the block's side
    loads vanish there and the top's is ``P_zz = mu l (l^2 - 1) + lam ln(l s^2) / l``. The small-strain slope is
    Young's modulus, the lateral stretch's ``-nu``; at 50 % compression ``J = l s^2 = 0.868`` (nu 0.45)."""
    for l in (0.999, 0.9, 0.7, 0.5, 0.3):
        s = brentq(lambda s: MU * s * (s * s - 1) + LAM * np.log(l * s * s) / s, 1.0, 3.0, xtol=1e-14)
        side_x, side_y, top = block_loads(modified, (s, s, l))
        p_zz = MU * l * (l * l - 1) + LAM * np.log(l * s * s) / l
        assert top == pytest.approx(p_zz * AREA_Z, rel=1e-9)
        assert abs(side_x) < 1e-9 * abs(top) and abs(side_y) < 1e-9 * abs(top)
        if l == 0.999:
            assert p_zz / (l - 1) == pytest.approx(E_GEL, rel=2e-3)
            assert (s - 1) / (l - 1) == pytest.approx(-NU_GEL, rel=2e-3)
        if l == 0.5:
            assert 0.85 < l * s * s < 0.89  # J = 0.868: the bulk modulus' (ln J)^2 holds the volume


def test_an_inverted_tet_has_infinite_energy() -> None:
    """``J <= 0`` in any tet: energy ``inf`` (the Newton line search steps back), the gradient at its vertices NaN."""
    mesh = tet_box(SIZE, (3, 3, 3), (0.0, 0.0, 0.0))
    pot = modified(mesh)
    x = mesh.x * np.array([1.0, 1.0, -0.1])
    assert pot.energy(x) == np.inf
    assert np.isnan(pot.gradient(x)).any()
    assert np.isfinite(pot.energy(mesh.x * np.array([1.0, 1.0, 1e-3])))


def test_the_gel_element_is_chosen_by_name() -> None:
    """``model.meta["solid_element"] = "modified_stvk"`` gives the solid this law (energy at a deformed state to
    1e-12); an unknown name is an error naming it."""
    assert_chosen_by_name("modified_stvk", modified, "modified_stkv")

def test_the_gel_candidates_take_the_per_tet_branch() -> None:
    """The Maxwell branch (gel viscoelasticity) of this gel is that of its per-tet Stable Neo-Hookean of the same
    E, nu, as for the other gel laws."""
    from sim_core.candidates.gel_viscoelasticity import MaxwellBranch

    mesh = gel_block()
    pot = modified(mesh)
    x, relaxed = deformed(mesh.x, 6), pot.deformation_gradient(deformed(mesh.x, 7))
    assert MaxwellBranch(pot, relaxed, 0.4).energy(x) == pytest.approx(
        MaxwellBranch(pot.per_tet, relaxed, 0.4).energy(x), rel=1e-12)
