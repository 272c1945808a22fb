"""Average-nodal-pressure Stable Neo-Hookean tets (derivatives vs finite differences and the PSD projection:
test_solid_element_derivatives.py): the patch test (a uniform deformation gives Stable Neo-Hookean's energy and
forces), the linearisation against an independent small-strain assembly (tests/support/linear_fe.py), and the
widened Hessian pattern through the solver's assembler."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.assembly import HessianAssembler
from sim_core.energies.neohookean.reference import StableNeoHookean
from sim_core.energies.nodal_pressure.reference import NodalPressureNeoHookean
from sim_core.errors import ConfigError
from sim_core.mesh.tet import tet_box
from tests.sim_core.energies.solid_cases import E_GEL, NU_GEL, deformed, gel_block
from tests.support.fd import dense_hessian, fd_hessian, relative_error
from tests.support.linear_fe import linear_stiffness, nodal_pressure_stiffness


def test_a_uniform_deformation_is_stable_neohookeans_at_large_strain() -> None:
    """The patch test: with every nodal Jacobian equal to the tets', energy and forces are Stable Neo-Hookean's
    with the same E, nu (the split is exact, module docstring); interior vertices carry no force."""
    mesh = tet_box((0.01, 0.01, 0.01), (4, 4, 4), (0.0, 0.0, 0.0))
    A = np.array([[1.2, 0.1, -0.05], [0.02, 0.85, 0.1], [0.0, -0.1, 1.1]])
    x = mesh.x @ A.T + np.array([0.003, -0.001, 0.002])
    pot = NodalPressureNeoHookean(mesh.tets, mesh.x, E_GEL, NU_GEL)
    snh = StableNeoHookean(mesh.tets, mesh.x, E_GEL, NU_GEL)
    assert np.allclose(pot.nodal_jacobian(x), np.linalg.det(A), rtol=1e-12)
    assert pot.energy(x) == pytest.approx(snh.energy(x), rel=1e-12)
    g = pot.gradient(x)
    assert relative_error(g, snh.gradient(x)) < 1e-12
    interior = np.all((mesh.x > 1e-9) & (mesh.x < 0.01 - 1e-9), axis=1)
    assert interior.sum() == 8 and np.abs(g[interior]).max() < 1e-10 * np.abs(g).max()


def test_the_small_strain_stiffness_is_the_independent_linear_nodal_pressure_element() -> None:
    """The rest Hessian equals the linearised element assembled from P1 strain operators (deviatoric Hooke per
    tet, bulk modulus on the nodal volume strains), and differs from the plain P1 stiffness."""
    mesh = gel_block()
    pot = NodalPressureNeoHookean(mesh.tets, mesh.x, E_GEL, NU_GEL)
    H = dense_hessian(pot.hessian(mesh.x, "none"), mesh.x.shape[0])
    assert relative_error(H, nodal_pressure_stiffness(mesh.x, mesh.tets, E_GEL, NU_GEL).toarray()) < 1e-12
    assert relative_error(H, linear_stiffness(mesh.x, mesh.tets, E_GEL, NU_GEL).toarray()) > 0.05


def test_the_widened_pattern_assembles_through_the_solver() -> None:
    """The ring blocks (padded with the node itself) go through the assembler's static pattern unchanged, and
    the pattern holds the vertex pairs two edges apart that the nodal term couples."""
    mesh = gel_block()
    pot = NodalPressureNeoHookean(mesh.tets, mesh.x, E_GEL, NU_GEL)
    x = deformed(mesh.x, 4)
    n = x.shape[0]
    blocks = pot.hessian(x, "none")
    assert blocks.vertices is pot.hessian(mesh.x, "clamp").vertices  # one array: the static pattern is kept
    free = np.ones(3 * n, dtype=bool)
    free[:12] = False
    upper = HessianAssembler(3 * n).assemble_upper([blocks], [], np.zeros(3 * n), free).toarray()
    D = np.diag(free.astype(float))
    expected = np.triu(D @ dense_hessian(blocks, n) @ D + np.diag((~free).astype(float)))
    assert relative_error(upper, expected) < 1e-14
    tet_pairs = {(int(a), int(b)) for t in mesh.tets for a in t for b in t}
    ring_pairs = {(int(a), int(b)) for r in pot.ring for a in r for b in r}
    assert tet_pairs < ring_pairs


def test_the_solvers_two_parts_sum_to_the_element() -> None:
    """The shear part (a Stable Neo-Hookean, for the fused kernel) plus the nodal volume term: the element's
    energy, gradient and exact Hessian; projected apart, their sum is PSD where the exact Hessian is not."""
    mesh = gel_block()
    pot = NodalPressureNeoHookean(mesh.tets, mesh.x, E_GEL, NU_GEL)
    shear, volume = pot.parts()
    assert type(shear) is StableNeoHookean
    x = deformed(mesh.x, 5, 6e-4)
    n = x.shape[0]
    assert shear.energy(x) + volume.energy(x) == pytest.approx(pot.energy(x), rel=1e-12)
    assert relative_error(shear.gradient(x) + volume.gradient(x), pot.gradient(x)) < 1e-12
    exact = dense_hessian(shear.hessian(x, "none"), n) + dense_hessian(volume.hessian(x, "none"), n)
    assert relative_error(exact, dense_hessian(pot.hessian(x, "none"), n)) < 1e-12
    assert relative_error(dense_hessian(volume.hessian(x, "none"), n),
                          fd_hessian(volume.gradient, x, h=1e-9)) < 1e-5
    projected = dense_hessian(shear.hessian(x, "clamp"), n) + dense_hessian(volume.hessian(x, "clamp"), n)
    w = np.linalg.eigvalsh(projected)
    assert np.linalg.eigvalsh(exact).min() < -1e-3 * w.max() and w.min() >= -1e-10 * w.max()


def test_bad_parameters_name_the_element() -> None:
    mesh = gel_block()
    with pytest.raises(ConfigError, match="poisson_ratio"):
        NodalPressureNeoHookean(mesh.tets, mesh.x, E_GEL, 0.5)


def test_a_nodal_pressure_gels_maxwell_branch_is_its_per_tet_neohookean() -> None:
    """The viscoelastic candidate's branch on a nodal-pressure gel is beta times the per-tet Stable Neo-Hookean of
    the same E, nu (at the identity relaxed state)."""
    from sim_core.candidates.gel_viscoelasticity import MaxwellBranch

    mesh = gel_block()
    pot = NodalPressureNeoHookean(mesh.tets, mesh.x, E_GEL, NU_GEL)
    branch = MaxwellBranch(pot, np.tile(np.eye(3), (mesh.tets.shape[0], 1, 1)), 0.5)
    x = deformed(mesh.x, 6)
    assert branch.energy(x) == pytest.approx(0.5 * StableNeoHookean(mesh.tets, mesh.x, E_GEL, NU_GEL).energy(x), rel=1e-12)


def test_the_adjoint_differentiates_a_nodal_pressure_gel() -> None:
    """On test_adjoint's tiny press-slide with the nodal-pressure gel (the solver takes its two parts, the adjoint
    its E, nu derivatives), the reverse-mode gradient of a loss in the gel's E and nu matches central differences of
    the rollout (measured 1e-6 and 3e-6 relative)."""
    from sim_core.adjoint import rollout, rollout_gradient
    from sim_core.simulation import Simulation
    from tests.sim_core.test_adjoint import CONFIG, _controls, _scene

    def make() -> Simulation:
        scene = _scene()
        scene["simulation"]["gel_element"] = "nodal_pressure_neohookean"
        return Simulation.from_scene(scene, solver_config=CONFIG)

    names = ["gel.youngs_modulus", "gel.poisson_ratio"]
    sim = make()
    assert type(sim.solver.elastic.solids["gel"]) is NodalPressureNeoHookean
    C = np.random.default_rng(0).normal(size=(len(_controls()) + 1, sim.model.vertex_count, 3))
    grad = rollout_gradient(sim, rollout(sim, _controls()), lambda tr: (float(np.sum(C * tr.x)), C), names)
    for name in names:
        value = make().get_parameter(name)
        h = 1e-3 * abs(value)
        losses = []
        for v in (value + h, value - h):
            s = make()
            s.set_parameter(name, v)
            losses.append(float(np.sum(C * rollout(s, _controls(), record=False).x)))
        fd = (losses[0] - losses[1]) / (2 * h)
        assert fd != 0.0 and abs(grad.params[name] - fd) < 1e-4 * abs(fd)
