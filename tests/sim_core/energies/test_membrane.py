"""Membrane energies: StVK (E, nu, thickness) and ThinShellLab's spring membrane."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.energies.base import project_psd
from sim_core.errors import ConfigError, MeshError
from sim_core.mesh.sheet import sheet_topology
from sim_core.energies.membrane.reference import (
    SpringMembrane,
    StVKMembrane,
    plane_stress_lame,
    project_psd_translation_free,
)
from tests.sim_core.energies.sheet_configs import deformed_configurations, random_rigid_motion, small_sheet
from tests.support.fd import dense_hessian, fd_gradient, fd_hessian, relative_error

E, NU, THICKNESS = 3.0e6, 0.3, 2.0e-4
K_L, K_A = 1000.0, 800.0


def _stvk(mesh, **kw):
    args = {"youngs_modulus": E, "poisson_ratio": NU, "thickness": THICKNESS} | kw
    return StVKMembrane(mesh.triangles, mesh.x, **args)


def _spring(mesh, k_length=K_L, k_area=K_A):
    return SpringMembrane(mesh.triangles, sheet_topology(mesh.triangles).edges, mesh.x, k_length, k_area)


MEMBRANES = {"stvk": _stvk, "spring": _spring}


@pytest.mark.parametrize("kind", MEMBRANES)
@pytest.mark.parametrize("config", ["perturbed", "folded"])
def test_gradient_and_hessian_match_finite_differences(kind, config):
    mesh = small_sheet()
    membrane = MEMBRANES[kind](mesh)
    x = deformed_configurations(mesh)[config]
    assert relative_error(membrane.gradient(x), fd_gradient(membrane.energy, x)) < 1e-5
    H = dense_hessian(membrane.hessian(x, "none"), len(x))
    assert relative_error(H, fd_hessian(membrane.gradient, x)) < 1e-5


@pytest.mark.parametrize("kind", MEMBRANES)
def test_projected_blocks_are_psd(kind):
    mesh = small_sheet()
    membrane = MEMBRANES[kind](mesh)
    # Compressed configuration: indefinite raw blocks.
    x = 0.7 * deformed_configurations(mesh)["perturbed"]
    raw = membrane.hessian(x, "none").blocks
    assert np.min(np.linalg.eigvalsh(raw)) < -1e-6 * np.max(np.abs(raw))
    for projection in ("clamp", "abs"):
        blocks = membrane.hessian(x, projection).blocks
        w = np.linalg.eigvalsh(blocks)
        assert np.min(w) >= -1e-12 * np.max(np.abs(w))


def test_translation_free_projection_equals_full_projection():
    mesh = small_sheet()
    raw = _stvk(mesh).hessian(0.7 * deformed_configurations(mesh)["perturbed"], "none").blocks
    for projection in ("clamp", "abs"):
        assert relative_error(project_psd_translation_free(raw, projection), project_psd(raw, projection)) < 1e-10
    assert project_psd_translation_free(raw, "none") is raw


@pytest.mark.parametrize("kind", MEMBRANES)
def test_zero_energy_and_gradient_at_rest(kind):
    mesh = small_sheet()
    membrane = MEMBRANES[kind](mesh)
    assert membrane.energy(mesh.x) == pytest.approx(0.0, abs=1e-20)
    assert np.max(np.abs(membrane.gradient(mesh.x))) < 1e-9


@pytest.mark.parametrize("kind", MEMBRANES)
def test_energy_is_invariant_under_rigid_motion(kind):
    mesh = small_sheet()
    membrane = MEMBRANES[kind](mesh)
    x = deformed_configurations(mesh)["perturbed"]
    e = membrane.energy(x)
    assert e > 0
    assert membrane.energy(random_rigid_motion(x)) == pytest.approx(e, rel=1e-10)
    assert membrane.energy(random_rigid_motion(mesh.x)) == pytest.approx(0.0, abs=1e-9 * e)


def test_stvk_uniaxial_stretch_of_one_triangle():
    """Stretch by s along an in-plane direction u: G = (s^2 - 1)/2 u u^T, so
    E = t A (mu + lam/2) ((s^2 - 1)/2)^2."""
    rng = np.random.default_rng(7)
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    x_rest = np.array([[0.0, 0.0, 0.0], [0.04, 0.01, 0.0], [0.012, 0.03, 0.0]]) @ q.T + 0.1
    tri = np.array([[0, 1, 2]])
    membrane = StVKMembrane(tri, x_rest, E, NU, THICKNESS)
    area = 0.5 * np.linalg.norm(np.cross(x_rest[1] - x_rest[0], x_rest[2] - x_rest[0]))
    u = q @ np.array([np.cos(0.4), np.sin(0.4), 0.0])  # in the triangle's plane
    mu, lam = E / (2 * (1 + NU)), E * NU / (1 - NU**2)
    for s in (1.1, 0.8, 1.5):
        x = x_rest + (s - 1.0) * np.outer((x_rest - x_rest[0]) @ u, u)
        g = 0.5 * (s * s - 1.0)
        assert membrane.energy(x) == pytest.approx(THICKNESS * area * (mu + 0.5 * lam) * g * g, rel=1e-12)
    assert plane_stress_lame(E, NU) == pytest.approx((mu, lam))


def test_spring_membrane_uniform_scaling():
    """x -> s x: E = K_l (1 - s)^2 sum l0 + K_a (1 - s^2)^2 sum A0."""
    mesh = small_sheet()
    membrane = _spring(mesh)
    s = 1.15
    expected = (
        K_L * (1 - s) ** 2 * membrane.edge_rest_length.sum()
        + K_A * (1 - s * s) ** 2 * membrane.triangle_rest_area.sum()
    )
    assert membrane.energy(s * mesh.x) == pytest.approx(expected, rel=1e-12)
    assert membrane.edge_rest_length.sum() == pytest.approx(3 * 0.3 + 4 * 0.2 + 6 * np.sqrt(0.02))
    assert membrane.triangle_rest_area.sum() == pytest.approx(0.06)


@pytest.mark.parametrize("name", ["youngs_modulus", "poisson_ratio", "thickness"])
def test_stvk_parameter_gradient_matches_finite_difference(name):
    mesh = small_sheet()
    x = deformed_configurations(mesh)["perturbed"]
    base = {"youngs_modulus": E, "poisson_ratio": NU, "thickness": THICKNESS}
    h = 1e-6 * base[name]
    plus = _stvk(mesh, **{name: base[name] + h}).gradient(x)
    minus = _stvk(mesh, **{name: base[name] - h}).gradient(x)
    analytic = _stvk(mesh).parameter_gradient(x, name)
    assert relative_error(analytic, (plus - minus) / (2 * h)) < 1e-6


@pytest.mark.parametrize("name", ["k_length", "k_area"])
def test_spring_parameter_gradient_matches_finite_difference(name):
    mesh = small_sheet()
    x = deformed_configurations(mesh)["perturbed"]
    base = {"k_length": K_L, "k_area": K_A}
    h = 1e-3
    plus = _spring(mesh, **(base | {name: base[name] + h})).gradient(x)
    minus = _spring(mesh, **(base | {name: base[name] - h})).gradient(x)
    analytic = _spring(mesh).parameter_gradient(x, name)
    assert relative_error(analytic, (plus - minus) / (2 * h)) < 1e-7


def test_unknown_parameter_raises_key_error():
    mesh = small_sheet()
    with pytest.raises(KeyError, match="bending_stiffness"):
        _stvk(mesh).parameter_gradient(mesh.x, "bending_stiffness")
    with pytest.raises(KeyError, match="youngs_modulus"):
        _spring(mesh).parameter_gradient(mesh.x, "youngs_modulus")


def test_spring_hessian_layout():
    mesh = small_sheet()
    membrane = _spring(mesh)
    blocks = membrane.hessian(deformed_configurations(mesh)["perturbed"], "clamp")
    t, e = len(mesh.triangles), len(membrane.edges)
    assert blocks.vertices.shape == (t + e, 3) and blocks.blocks.shape == (t + e, 9, 9)
    assert np.array_equal(blocks.vertices[:t], mesh.triangles)
    assert np.array_equal(blocks.vertices[t:, :2], membrane.edges)
    assert np.all(blocks.blocks[t:, 6:, :] == 0.0) and np.all(blocks.blocks[t:, :, 6:] == 0.0)


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"youngs_modulus": 0.0}, "youngs_modulus"),
        ({"youngs_modulus": float("nan")}, "youngs_modulus"),
        ({"poisson_ratio": 0.5}, "poisson_ratio"),
        ({"poisson_ratio": -1.0}, "poisson_ratio"),
        ({"thickness": -1e-4}, "thickness"),
    ],
)
def test_stvk_rejects_bad_parameters(kw, match):
    with pytest.raises(ConfigError, match=match):
        _stvk(small_sheet(), **kw)


def test_membranes_reject_degenerate_rest_triangles():
    mesh = small_sheet()
    x = mesh.x.copy()
    t = mesh.triangles[3]
    x[t[2]] = 0.5 * (x[t[0]] + x[t[1]])  # collapse triangle 3 onto its first edge
    with pytest.raises(MeshError, match="triangle 3 .* degenerate"):
        StVKMembrane(mesh.triangles, x, E, NU, THICKNESS)
    with pytest.raises(MeshError, match="triangle 3 .* degenerate"):
        SpringMembrane(mesh.triangles, np.zeros((0, 2), dtype=np.int64), x, K_L, K_A)
    with pytest.raises(ConfigError, match="k_area"):
        SpringMembrane(mesh.triangles, np.zeros((0, 2), dtype=np.int64), mesh.x, K_L, -1.0)
    with pytest.raises(MeshError, match="edge 0 .* out of range"):
        SpringMembrane(mesh.triangles, np.array([[0, 40]]), mesh.x, K_L, K_A)
