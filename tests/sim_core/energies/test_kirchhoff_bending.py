"""Discrete Kirchhoff plate bending: finite differences, plate energies of uniform curvature, cantilever."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.builder import ModelBuilder
from sim_core.elastic import ElasticTerms
from sim_core.energies.base import project_psd
from sim_core.energies.hinge_bending.reference import DiscreteShellBending, plastic_update
from sim_core.energies.kirchhoff_bending.reference import KirchhoffBending
from sim_core.errors import ConfigError, MeshError
from sim_core.mesh.sheet import grid_sheet, sheet_topology
from sim_core.simulation import Simulation
from sim_core.solver import SolverConfig
from tests.sim_core.energies.sheet_configs import deformed_configurations, random_rigid_motion, small_sheet
from tests.support.fd import dense_hessian, fd_gradient, fd_hessian, relative_error

D = 2.5e-3  # N m
NU = 0.3
G = 9.81


def _bending(mesh, nu: float = NU, D: float = D, theta_bar=None) -> KirchhoffBending:
    return KirchhoffBending(mesh.triangles, sheet_topology(mesh.triangles).hinges, mesh.x, D, nu, theta_bar)


def _interior_density(bend: KirchhoffBending, x: np.ndarray) -> float:
    """Energy per rest area (J/m^2) of the triangles with three interior edges."""
    interior = np.all(bend.triangle_hinge >= 0, axis=1)
    return float(bend.triangle_energy(x)[interior].sum() / bend.triangle_rest_area[interior].sum())


def _cylinder(x: np.ndarray, radius: float, phi: float) -> np.ndarray:
    """Isometric map of the flat sheet onto a cylinder bending along direction (cos phi, sin phi)."""
    c, a = np.array([np.cos(phi), np.sin(phi)]), np.array([-np.sin(phi), np.cos(phi)])
    p = x[:, :2] - x[:, :2].mean(axis=0)
    u, v = p @ c, p @ a
    out = np.zeros_like(x)
    out[:, :2] = np.outer(radius * np.sin(u / radius), c) + np.outer(v, a)
    out[:, 2] = radius * (1.0 - np.cos(u / radius))
    return out


@pytest.mark.parametrize("pattern", ["alternating", "regular"])
@pytest.mark.parametrize("config", ["perturbed", "folded"])
def test_gradient_and_hessian_match_finite_differences(pattern, config):
    mesh = small_sheet(pattern)
    bend = _bending(mesh)
    x = deformed_configurations(mesh, seed=3)[config]
    assert bend.energy(x) > 0
    assert bend.energy(x) == pytest.approx(bend.triangle_energy(x).sum(), rel=1e-12)
    assert relative_error(bend.gradient(x), fd_gradient(bend.energy, x)) < 1e-5
    H = dense_hessian(bend.hessian(x, "none"), x.shape[0])
    assert relative_error(H, fd_hessian(bend.gradient, x)) < 1e-5


def test_projected_blocks_are_psd_and_equal_project_psd():
    mesh = small_sheet()
    bend = _bending(mesh)
    x = deformed_configurations(mesh, seed=4)["folded"]
    raw = bend.hessian(x, "none")
    clamped = bend.hessian(x, "clamp")
    assert raw.blocks.shape == (mesh.triangles.shape[0], 18, 18)
    assert np.min(np.linalg.eigvalsh(raw.blocks)) < -1e-6 * np.max(np.abs(raw.blocks))  # projection matters
    w = np.linalg.eigvalsh(clamped.blocks)
    assert np.min(w) > -1e-9 * np.max(w)
    np.testing.assert_allclose(clamped.blocks, project_psd(raw.blocks, "clamp"), atol=1e-9 * np.max(np.abs(raw.blocks)))
    # boundary padding: the slot of a missing neighbour repeats a triangle vertex with zero rows
    pad = np.argwhere(bend.triangle_hinge < 0)
    t, k = pad[0]
    assert clamped.vertices[t, 3 + k] == mesh.triangles[t, k]
    assert np.all(raw.blocks[t, 9 + 3 * k: 12 + 3 * k] == 0.0)
    assert np.max(np.abs(clamped.blocks[t, 9 + 3 * k: 12 + 3 * k])) < 1e-12 * np.max(np.abs(raw.blocks))


def test_zero_energy_and_gradient_at_rest_and_for_curved_rest_shape():
    mesh = small_sheet()
    bend = _bending(mesh)
    assert bend.energy(mesh.x) == 0.0
    assert np.max(np.abs(bend.gradient(mesh.x))) == 0.0
    curved = deformed_configurations(mesh, seed=5)["folded"]
    rest_curved = KirchhoffBending(mesh.triangles, sheet_topology(mesh.triangles).hinges, curved, D, NU)
    assert rest_curved.energy(curved) == pytest.approx(0.0, abs=1e-20)
    assert np.max(np.abs(rest_curved.gradient(curved))) < 1e-14
    assert np.max(np.abs(rest_curved.theta(curved) - rest_curved.hinge_theta_bar)) < 1e-14


def test_rigid_motion_invariance():
    mesh = small_sheet()
    bend = _bending(mesh)
    x = deformed_configurations(mesh, seed=6)["perturbed"]
    y = random_rigid_motion(x, seed=7)
    R = np.linalg.lstsq(np.c_[x - x.mean(0)], y - y.mean(0), rcond=None)[0].T
    assert bend.energy(y) == pytest.approx(bend.energy(x), rel=1e-10)
    np.testing.assert_allclose(bend.gradient(y), bend.gradient(x) @ R.T, atol=1e-10 * np.max(np.abs(bend.gradient(x))))


@pytest.mark.parametrize("nu", [0.0, 0.3])
def test_cylinder_energy_density_and_anisotropy(nu):
    """D/2 kappa^2 per area on interior triangles of a 41 x 41 grid (dx 2.5 mm, R = 0.5 m).

    Regular grid: exact in every direction. Checkerboard grid: exact along the axes, off-axis too
    stiff by 1 + 2 (1 + nu) sin^2 phi cos^2 phi (module docstring; 1.375 / 1.49 at 30 degrees).
    """
    R = 0.5
    expected = 0.5 * D / R**2
    for pattern in ("regular", "alternating"):
        mesh = grid_sheet((0.1, 0.1), (41, 41), pattern=pattern)
        bend = _bending(mesh, nu)
        for phi in (0.0, np.pi / 2, np.pi / 6):
            ratio = _interior_density(bend, _cylinder(mesh.x, R, phi)) / expected
            anisotropy = 1.0 if pattern == "regular" else 1.0 + 2.0 * (1.0 + nu) * (np.sin(phi) * np.cos(phi)) ** 2
            assert ratio == pytest.approx(anisotropy, rel=1e-4), (pattern, phi, ratio)
            if pattern == "regular" or phi != np.pi / 6:
                assert abs(ratio - 1.0) < 0.02


@pytest.mark.parametrize("pattern", ["regular", "alternating"])
def test_sphere_and_saddle_match_continuum_plate_energy(pattern):
    """psi = (D/2)[nu tr(S)^2 + (1 - nu) tr(S^2)]: sphere D (1 + nu) k^2, saddle D (1 - nu) k^2.

    41 x 41 grid over 0.1 m (dx 2.5 mm), k = 1 /m (slopes <= 0.05); interior triangles.
    """
    k = 1.0
    mesh = grid_sheet((0.1, 0.1), (41, 41), (-0.05, -0.05, 0.0), pattern=pattern)
    bend = _bending(mesh)
    px, py = mesh.x[:, 0], mesh.x[:, 1]
    shapes = {"sphere": (0.5 * k * (px**2 + py**2), D * (1 + NU) * k**2),
              "saddle": (0.5 * k * (px**2 - py**2), D * (1 - NU) * k**2)}
    if pattern == "regular":  # the rotated saddle has S_xy only: exact on the regular grid
        shapes["twist"] = (k * px * py, D * (1 - NU) * k**2)
    density = {}
    for name, (z, expected) in shapes.items():
        x = mesh.x.copy()
        x[:, 2] = z
        density[name] = _interior_density(bend, x)
        assert density[name] == pytest.approx(expected, rel=0.01), name
    # the Gaussian-curvature term: sphere / saddle = (1 + nu) / (1 - nu) (a hinge energy gives ~1)
    assert density["sphere"] / density["saddle"] == pytest.approx((1 + NU) / (1 - NU), rel=1e-3)


@pytest.mark.parametrize("name", ["bending_stiffness", "poisson_ratio"])
def test_parameter_gradient_matches_finite_differences(name):
    mesh = small_sheet()
    x = deformed_configurations(mesh, seed=8)["perturbed"]
    bend = _bending(mesh)
    h = {"bending_stiffness": 1e-6 * D, "poisson_ratio": 1e-6}[name]
    value = {"bending_stiffness": D, "poisson_ratio": NU}[name]

    def grad_at(p):
        kw = {"D": D, "nu": NU}
        kw["D" if name == "bending_stiffness" else "nu"] = p
        return _bending(mesh, **kw).gradient(x)

    fd = (grad_at(value + h) - grad_at(value - h)) / (2 * h)
    assert relative_error(bend.parameter_gradient(x, name), fd) < 1e-5
    with pytest.raises(KeyError, match="no parameter 'thickness'"):
        bend.parameter_gradient(x, "thickness")


def test_hinge_stiffness_matrix_gives_energy_and_angle_gradient():
    mesh = small_sheet()
    bend = _bending(mesh)
    x = deformed_configurations(mesh, seed=9)["folded"]
    d = bend.theta(x) - bend.hinge_theta_bar
    K = bend.hinge_stiffness_matrix.toarray()
    np.testing.assert_allclose(K, K.T, atol=1e-15 * np.max(np.abs(K)))
    assert np.min(np.linalg.eigvalsh(K)) > -1e-12 * np.max(np.abs(K))
    assert d @ K @ d == pytest.approx(bend.energy(x), rel=1e-12)


def test_invalid_input_is_rejected_with_named_element():
    mesh = small_sheet()
    hinges = sheet_topology(mesh.triangles).hinges
    with pytest.raises(ConfigError, match="poisson_ratio must satisfy"):
        KirchhoffBending(mesh.triangles, hinges, mesh.x, D, 0.7)
    with pytest.raises(ConfigError, match="bending_stiffness must be finite"):
        KirchhoffBending(mesh.triangles, hinges, mesh.x, -1.0, NU)
    with pytest.raises(ConfigError, match=r"hinge_theta_bar shape \(3,\)"):
        KirchhoffBending(mesh.triangles, hinges, mesh.x, D, NU, np.zeros(3))
    with pytest.raises(MeshError, match=r"hinge \d+ .* is an edge of 1 triangle\(s\), expected 2"):
        KirchhoffBending(mesh.triangles[1:], hinges, mesh.x, D, NU)
    with pytest.raises(MeshError, match="hinge 1 .* is an edge of 0 triangle"):
        KirchhoffBending(mesh.triangles, np.r_[hinges[:1], [[0, 11, 1, 2]]], mesh.x, D, NU)


def test_plasticity_through_elastic_terms_and_model_choice():
    mesh = small_sheet()
    mat = {"youngs_modulus": 1e8, "poisson_ratio": NU, "thickness": 1e-3, "density": 500.0,
           "bending_stiffness": D, "yield_angle": 0.5}
    b = ModelBuilder()
    b.add_sheet("sheet", mesh, mat)
    model = b.finalize()
    terms = ElasticTerms(model)
    h = model.bodies["sheet"].hinges.shape[0]
    pot = terms.bending("sheet", np.zeros(h))
    assert isinstance(pot, KirchhoffBending) and pot.poisson_ratio == NU
    assert isinstance(ElasticTerms(model, "hinge").bending("sheet", np.zeros(h)), DiscreteShellBending)
    b.add_sheet("other", grid_sheet((0.1, 0.1), (3, 3), (0, 0, 1.0)), mat)
    two = b.finalize(meta={"bending_model": {"other": "hinge"}})
    assert isinstance(ElasticTerms(two).bending("sheet", None), KirchhoffBending)
    assert isinstance(ElasticTerms(two).bending("other", None), DiscreteShellBending)
    with pytest.raises(ConfigError, match="unknown bending_model 'shell'"):
        ElasticTerms(model, "shell")
    local = [name for _, name in terms.parameter_terms("sheet.poisson_ratio", {"sheet": np.zeros(h)})]
    assert local == ["poisson_ratio", "poisson_ratio"]  # membrane and bending
    x = deformed_configurations(mesh, seed=2)["folded"]
    new = terms.plastic_update(x, {"sheet": np.zeros(h)})["sheet"]
    np.testing.assert_allclose(new, plastic_update(pot.theta(x), np.zeros(h), 0.5))
    assert np.any(new != 0.0)
    clone = terms.bending("sheet", new)
    assert clone.energy(x) < pot.energy(x)


def _cantilever_tip_ratio(nx: int, ny: int, nu: float, pattern: str) -> float:
    """Tip sag of a 0.1 x 0.01 m strip clamped at x = 0 (vertex columns 0 and 1 fixed) / q L^4 / (8 D).

    One implicit step with dt = 10 s is a quasi-static solve. The fixed columns 0 and 1 make the
    central-difference slope (w_1 - w_0) / dx vanish, i.e. the discrete clamp is at x = dx / 2, so
    L_eff = L - dx / 2 (the hinge at x = dx carries the root moment).
    """
    L, W, rho, t, D_plate = 0.1, 0.01, 1000.0, 1e-3, 0.1
    mesh = grid_sheet((L, W), (nx, ny), (0.0, 0.0, 0.0), pattern=pattern)
    ix = np.arange(nx * ny) % nx
    b = ModelBuilder()
    mat = {"youngs_modulus": 1e9, "poisson_ratio": nu, "thickness": t, "density": rho, "bending_stiffness": D_plate}
    b.add_sheet("sheet", mesh, mat, fixed=np.nonzero(ix <= 1)[0])
    sim = Simulation(b.finalize(gravity=(0, 0, -G)), dt=10.0, solver_config=SolverConfig(tol_velocity=1e-9))
    assert isinstance(sim.solver.elastic.bending("sheet", None), KirchhoffBending)
    sim.step()
    L_eff = L - 0.5 * L / (nx - 1)
    w_beam = rho * t * G * L_eff**4 / (8 * D_plate)
    assert w_beam / L < 0.02  # small deflection
    return float(-sim.state.x[ix == nx - 1, 2].mean() / w_beam)


@pytest.mark.parametrize("pattern", ["alternating", "regular"])
def test_cantilever_tip_deflection_matches_euler_bernoulli(pattern):
    """Narrow strip, 41 x 5 vertices (dx = dy = 2.5 mm), nu = 0: a beam of stiffness D; within 5 %.

    (The hinge energy gives 1.29x here.) With nu = 0.3 the free long edges curve anticlastically and
    the strip bends as a beam of stiffness D (1 - nu^2) = E t^3 / 12, within 5 % (the clamp, which
    suppresses anticlastic curvature near x = 0, makes it slightly stiffer).
    """
    ratio = _cantilever_tip_ratio(41, 5, 0.0, pattern)
    assert abs(ratio - 1.0) < 0.05, ratio
    ratio_nu = _cantilever_tip_ratio(41, 5, NU, pattern) * (1.0 - NU**2)
    assert abs(ratio_nu - 1.0) < 0.05, ratio_nu
    assert ratio_nu < 1.0


def test_kept_hinge_angles_are_reused_only_at_equal_positions():
    # energy, gradient and Hessian of one x share the hinge angles and their gradients; an
    # in-place change of x recomputes them, and theta() hands out a copy
    mesh = small_sheet()
    bend, fresh = _bending(mesh), _bending(mesh)
    x = deformed_configurations(mesh, seed=4)["folded"].copy()
    e, g, h = bend.energy(x), bend.gradient(x), bend.hessian(x, "none").blocks
    assert e == fresh.energy(x.copy()) and np.array_equal(g, fresh.gradient(x.copy()))
    assert np.array_equal(h, fresh.hessian(x.copy(), "none").blocks)
    bend.theta(x)[:] = 0.0  # a caller's change does not reach the kept angles
    assert bend.energy(x) == e
    x[5] += 1e-4
    assert bend.energy(x) == _bending(mesh).energy(x) != e


def test_theta_gradient_and_kept_parameter_matrices():
    # theta_gradient is dtheta/dx of the hinges at x; the parameter matrices kept on first use
    # belong to the potential's own D and nu (a copy with new rest angles shares them, another
    # potential does not), so a later call equals a fresh potential's
    from sim_core.energies.hinge_bending.reference import dihedral_angle_gradient

    mesh = small_sheet()
    x = deformed_configurations(mesh, seed=8)["perturbed"]
    bend = _bending(mesh)
    np.testing.assert_array_equal(bend.theta_gradient(x), dihedral_angle_gradient(x[bend.hinges]))
    first = {n: bend.parameter_gradient(x, n) for n in ("bending_stiffness", "poisson_ratio")}
    stiffer = _bending(mesh, D=2 * D)
    for name, g in first.items():
        assert np.array_equal(bend.parameter_gradient(x, name), g)
        assert np.array_equal(_bending(mesh).parameter_gradient(x, name), g)
    np.testing.assert_allclose(stiffer.parameter_gradient(x, "poisson_ratio"), 2 * first["poisson_ratio"],
                               rtol=1e-12, atol=1e-12 * np.abs(first["poisson_ratio"]).max())
