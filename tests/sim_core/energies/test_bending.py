"""Discrete-shell bending: finite differences, dihedral-angle convention, cylinder energy, plasticity."""

from __future__ import annotations

import re

import numpy as np
import pytest

from sim_core.energies.base import project_psd
from sim_core.errors import ConfigError, MeshError
from sim_core.mesh.sheet import grid_sheet, sheet_topology
from sim_core.energies.hinge_bending.reference import (
    DiscreteShellBending,
    dihedral_angle,
    dihedral_angle_gradient,
    dihedral_angle_hessian,
    plastic_update,
)
from tests.sim_core.energies.sheet_configs import (
    FOLD_ANGLE,
    deformed_configurations,
    folded_sheet,
    random_rigid_motion,
    small_sheet,
)
from tests.support.fd import dense_hessian, fd_gradient, fd_hessian, relative_error

D = 2.5e-3  # N m


def _hinge(angle: float) -> np.ndarray:
    """One hinge on the edge x0 = 0 -> x1 = e_x; both wings rise by angle/2 towards +z.

    Flat (angle 0) the wings lie at y = +1 (opp0) and y = -1 (opp1): triangle (x0, x1, opp0) is
    counter-clockwise seen from +z, so the normal side is +z.
    """
    a = 0.5 * angle
    return np.array(
        [[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.3, np.cos(a), np.sin(a)], [0.7, -np.cos(a), np.sin(a)]]]
    )


@pytest.mark.parametrize("angle", [0.3, -0.3, 1.4, -2.0, 2.9, -2.9])
def test_theta_of_folded_hinge_equals_fold_angle_with_sign(angle):
    assert dihedral_angle(_hinge(angle))[0] == pytest.approx(angle, abs=1e-12)
    assert dihedral_angle(_hinge(0.0))[0] == pytest.approx(0.0, abs=1e-15)


def test_theta_of_folded_grid_sheet():
    mesh = small_sheet()
    topo = sheet_topology(mesh.triangles)
    bend = DiscreteShellBending(topo.hinges, mesh.x, D)
    assert np.allclose(bend.theta(mesh.x), 0.0, atol=1e-15)
    theta = bend.theta(folded_sheet(mesh))
    # Hinges across x = 0.1 fold by +FOLD_ANGLE (wing rises to +z), across x = 0.2 by -FOLD_ANGLE.
    ex = mesh.x[topo.hinges[:, :2], 0]
    on_left = np.all(np.isclose(ex, 0.1), axis=1)
    on_right = np.all(np.isclose(ex, 0.2), axis=1)
    assert on_left.sum() == 2 and on_right.sum() == 2
    assert np.allclose(theta[on_left], FOLD_ANGLE, atol=1e-12)
    assert np.allclose(theta[on_right], -FOLD_ANGLE, atol=1e-12)
    assert np.allclose(theta[~on_left & ~on_right], 0.0, atol=1e-12)


@pytest.mark.parametrize("config", ["perturbed", "folded"])
def test_theta_gradient_and_hessian_match_finite_differences(config):
    mesh = small_sheet()
    hinges = sheet_topology(mesh.triangles).hinges
    x = deformed_configurations(mesh)[config]
    X = x[hinges]
    if config == "folded":
        assert np.max(np.abs(dihedral_angle(X))) > 1.5
    g = dihedral_angle_gradient(X)
    H = dihedral_angle_hessian(X)
    for k in range(len(hinges)):
        xk = X[k]
        g_fd = fd_gradient(lambda y: float(dihedral_angle(y[None])[0]), xk)
        H_fd = fd_hessian(lambda y: dihedral_angle_gradient(y[None])[0], xk)
        assert relative_error(g[k], g_fd) < 1e-6
        assert relative_error(H[k], H_fd) < 1e-5


@pytest.mark.parametrize("config", ["perturbed", "folded"])
def test_energy_gradient_and_hessian_match_finite_differences(config):
    mesh = small_sheet()
    hinges = sheet_topology(mesh.triangles).hinges
    rng = np.random.default_rng(3)
    bend = DiscreteShellBending(hinges, mesh.x, D, 0.3 * rng.standard_normal(len(hinges)))
    x = deformed_configurations(mesh)[config]
    g = bend.gradient(x)
    assert relative_error(g, fd_gradient(bend.energy, x)) < 1e-5
    H = dense_hessian(bend.hessian(x, "none"), len(x))
    assert relative_error(H, fd_hessian(bend.gradient, x)) < 1e-5


@pytest.mark.parametrize("projection", ["clamp", "abs"])
def test_projected_blocks_are_psd_and_equal_full_projection(projection):
    mesh = small_sheet()
    hinges = sheet_topology(mesh.triangles).hinges
    bend = DiscreteShellBending(hinges, mesh.x, D)
    x = deformed_configurations(mesh)["folded"]
    raw = bend.hessian(x, "none").blocks
    assert np.min(np.linalg.eigvalsh(raw)) < -1e-6 * np.max(np.abs(raw))  # the test is not vacuous
    blocks = bend.hessian(x, projection)
    assert np.array_equal(blocks.vertices, hinges)
    w = np.linalg.eigvalsh(blocks.blocks)
    assert np.min(w) >= -1e-12 * np.max(np.abs(w))
    assert relative_error(blocks.blocks, project_psd(raw, projection)) < 1e-10


def test_zero_energy_and_gradient_at_flat_rest():
    mesh = small_sheet()
    bend = DiscreteShellBending(sheet_topology(mesh.triangles).hinges, mesh.x, D, None)
    assert np.allclose(bend.hinge_theta_bar, 0.0)
    assert bend.energy(mesh.x) == 0.0
    assert np.max(np.abs(bend.gradient(mesh.x))) < 1e-15


def test_default_rest_angles_are_those_of_a_curved_rest_shape():
    mesh = small_sheet()
    hinges = sheet_topology(mesh.triangles).hinges
    x_rest = folded_sheet(mesh, 0.5, -0.8)
    bend = DiscreteShellBending(hinges, x_rest, D)
    assert bend.energy(x_rest) == pytest.approx(0.0, abs=1e-20)
    assert np.max(np.abs(bend.gradient(x_rest))) < 1e-12
    assert bend.energy(mesh.x) > 0.0


def test_energy_is_invariant_under_rigid_motion():
    mesh = small_sheet()
    bend = DiscreteShellBending(sheet_topology(mesh.triangles).hinges, mesh.x, D)
    for x in deformed_configurations(mesh).values():
        e = bend.energy(x)
        assert e > 0
        assert bend.energy(random_rigid_motion(x)) == pytest.approx(e, rel=1e-10)


def test_parameter_gradient_matches_finite_difference_in_stiffness():
    mesh = small_sheet()
    hinges = sheet_topology(mesh.triangles).hinges
    x = deformed_configurations(mesh)["folded"]
    h = 1e-6 * D
    plus = DiscreteShellBending(hinges, mesh.x, D + h).gradient(x)
    minus = DiscreteShellBending(hinges, mesh.x, D - h).gradient(x)
    analytic = DiscreteShellBending(hinges, mesh.x, D).parameter_gradient(x, "bending_stiffness")
    assert relative_error(analytic, (plus - minus) / (2 * h)) < 1e-7
    with pytest.raises(KeyError, match="thickness"):
        DiscreteShellBending(hinges, mesh.x, D).parameter_gradient(x, "thickness")


def _cylinder(x: np.ndarray, radius: float, axis_angle: float) -> np.ndarray:
    """Isometric map of the plane z = 0 onto a cylinder of ``radius`` whose axis makes ``axis_angle``
    with the y axis (arc length along u = (cos a, sin a), axis along v)."""
    u = np.array([np.cos(axis_angle), np.sin(axis_angle)])
    v = np.array([-np.sin(axis_angle), np.cos(axis_angle)])
    s, t = x[:, :2] @ u, x[:, :2] @ v
    return np.stack([radius * np.sin(s / radius) * u[0] + t * v[0],
                     radius * np.sin(s / radius) * u[1] + t * v[1],
                     radius * (1.0 - np.cos(s / radius))], axis=1)


@pytest.mark.parametrize("pattern", ["alternating", "regular"])
def test_cylinder_bending_energy_is_kirchhoff_plate_energy(pattern):
    """Sheet Lx x Ly = 0.1 x 0.06 m, 41 x 25 vertices, bent isometrically about the y axis with R = 0.05 m.

    Quads map to planar rectangles, so theta = dx / R exactly on the hinges parallel to the axis and 0
    elsewhere: E = (nx - 2)(ny - 1) (D/2) (dy/dx) (dx/R)^2 = (D/2) R^-2 area (nx - 2)/(nx - 1).
    Asserted: that identity to 1e-9, and E within 3 % of the Kirchhoff value (D/2) R^-2 Lx Ly.
    """
    (lx, ly), (nx, ny), radius = (0.1, 0.06), (41, 25), 0.05
    mesh = grid_sheet((lx, ly), (nx, ny), (-0.05, -0.03, 0.0), pattern)
    bend = DiscreteShellBending(sheet_topology(mesh.triangles).hinges, mesh.x, D)
    energy = bend.energy(_cylinder(mesh.x, radius, 0.0))
    kirchhoff = 0.5 * D / radius**2 * lx * ly
    assert energy == pytest.approx(kirchhoff * (nx - 2) / (nx - 1), rel=1e-9)
    assert energy == pytest.approx(kirchhoff, rel=0.03)
    # The y-bend (axis along x) is the same by symmetry of the grid.
    energy_y = bend.energy(_cylinder(mesh.x, radius, np.pi / 2))
    assert energy_y == pytest.approx(kirchhoff * (ny - 2) / (ny - 1), rel=1e-9)


def test_cylinder_energy_anisotropy_of_alternating_grid_is_bounded():
    """A cylinder axis oblique to the grid costs more (dihedral-angle energies are mesh dependent):
    measured 1.23x at 22.5 deg and 1.49x at 45 deg on a 41 x 41 alternating grid; asserted within 1.6x."""
    mesh = grid_sheet((0.1, 0.1), (41, 41), (-0.05, -0.05, 0.0), "alternating")
    bend = DiscreteShellBending(sheet_topology(mesh.triangles).hinges, mesh.x, D)
    radius = 0.05
    kirchhoff = 0.5 * D / radius**2 * 0.01
    for angle in (np.pi / 8, np.pi / 4):
        ratio = bend.energy(_cylinder(mesh.x, radius, angle)) / kirchhoff
        assert 1.0 < ratio < 1.6


def test_hinge_weight_uses_rest_geometry():
    """A rectangular grid cell dx x dy: hinges on y-parallel edges weigh dy^2 / (dx dy) = dy / dx."""
    mesh = grid_sheet((0.4, 0.1), (5, 3), pattern="regular")  # dx = 0.1, dy = 0.05
    topo = sheet_topology(mesh.triangles)
    bend = DiscreteShellBending(topo.hinges, mesh.x, D)
    e = mesh.x[topo.hinges[:, 1]] - mesh.x[topo.hinges[:, 0]]
    along_y = np.isclose(e[:, 0], 0.0)
    along_x = np.isclose(e[:, 1], 0.0)
    assert np.allclose(bend.hinge_weight[along_y], 0.05 / 0.1)
    assert np.allclose(bend.hinge_weight[along_x], 0.1 / 0.05)
    assert np.allclose(bend.hinge_stiffness, 0.5 * D * bend.hinge_weight)


def test_plastic_update():
    theta = np.array([0.2, 1.0, -1.0, 0.6, -0.1, 3.0])
    theta_bar = np.array([0.0, 0.0, 0.0, 0.1, 0.3, 3.5])
    new = plastic_update(theta, theta_bar, 0.5)
    # |d| = 0.2 (keep), 1.0 (-> 0.5), 1.0 (-> -0.5), 0.5 (not > yield: keep), 0.4 (keep), 0.5 (keep)
    assert np.allclose(new, [0.0, 0.5, -0.5, 0.1, 0.3, 3.5])
    assert np.all(np.abs(theta - new) <= 0.5 + 1e-15)
    assert np.array_equal(plastic_update(theta, theta_bar, np.inf), theta_bar)
    assert np.allclose(plastic_update(theta, theta_bar, 0.0), theta)
    assert plastic_update(theta, theta_bar, 0.5) is not theta_bar


def test_plastic_update_rejects_bad_input():
    with pytest.raises(ConfigError, match="yield_angle"):
        plastic_update(np.zeros(2), np.zeros(2), -0.1)
    with pytest.raises(ConfigError, match="yield_angle"):
        plastic_update(np.zeros(2), np.zeros(2), float("nan"))
    with pytest.raises(ConfigError, match="shape"):
        plastic_update(np.zeros(2), np.zeros(3), 0.5)


def test_constructor_validation():
    mesh = small_sheet()
    hinges = sheet_topology(mesh.triangles).hinges
    with pytest.raises(ConfigError, match="bending_stiffness"):
        DiscreteShellBending(hinges, mesh.x, -1.0)
    with pytest.raises(ConfigError, match="bending_stiffness"):
        DiscreteShellBending(hinges, mesh.x, float("nan"))
    with pytest.raises(ConfigError, match="hinge_theta_bar shape"):
        DiscreteShellBending(hinges, mesh.x, D, np.zeros(len(hinges) + 1))
    with pytest.raises(MeshError, match="hinge 2 .* out of range"):
        bad = hinges.copy()
        bad[2, 3] = 99
        DiscreteShellBending(bad, mesh.x, D)
    x = mesh.x.copy()
    x[hinges[4, 3]] = 0.5 * (x[hinges[4, 0]] + x[hinges[4, 1]])  # collapse one wing onto the edge
    pair = hinges[[0, 4]]
    assert not set(pair[0]) & {hinges[4, 3]}
    with pytest.raises(MeshError, match=re.escape(f"hinge 1 {hinges[4].tolist()} is degenerate")):
        DiscreteShellBending(pair, x, D)


def test_dihedral_angle_equals_the_np_cross_formula_bit_for_bit():
    """The row cross product of ``dihedral_angle`` gives the values of the ``np.cross`` form."""
    from sim_core.energies.hinge_bending.reference import _dot, dihedral_angle

    rng = np.random.default_rng(11)
    for count in (1, 2, 7, 293, 1000):
        X = rng.normal(size=(count, 4, 3)) * rng.uniform(1e-4, 1.0)
        X[0, 3] = X[0, 2]  # a flat hinge among them
        x0, x1, x2, x3 = X[:, 0], X[:, 1], X[:, 2], X[:, 3]
        e = x1 - x0
        n0, n1 = np.cross(e, x2 - x0), np.cross(x3 - x0, e)
        expected = np.arctan2(_dot(np.cross(n1, n0), e / np.linalg.norm(e, axis=1)[:, None]), _dot(n0, n1))
        theta = dihedral_angle(X)
        assert theta.dtype == np.float64 and theta.shape == (count,)
        np.testing.assert_array_equal(theta, expected)
