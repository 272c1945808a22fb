"""Anisotropic bending candidate: FD derivatives, and different compliance along x and y."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.candidates.anisotropic_bending import AnisotropicBendingCorrection, hinge_grain_cosine
from sim_core.energies.hinge_bending.reference import DiscreteShellBending
from sim_core.errors import ConfigError
from sim_core.mesh.sheet import grid_sheet, sheet_topology
from tests.support.fd import dense_hessian, fd_gradient, fd_hessian, relative_error

D = 0.008


def _sheet(res=(6, 5)):
    mesh = grid_sheet((0.05, 0.04), res)
    hinges = sheet_topology(mesh.triangles).hinges
    return DiscreteShellBending(hinges, mesh.x, D), mesh.x


def _cylinder(x_rest, radius, axis):
    """Isometric wrap of the flat sheet onto a cylinder whose axis is world x (axis=0) or y (axis=1)."""
    x = x_rest.copy()
    s = x_rest[:, 1 - axis]  # arc-length coordinate
    x[:, 1 - axis] = radius * np.sin(s / radius)
    x[:, 2] = radius * (1 - np.cos(s / radius))
    return x


def test_gradient_and_hessian_match_finite_differences():
    bending, x_rest = _sheet((4, 4))
    corr = AnisotropicBendingCorrection(bending, x_rest, beta=0.4)
    rng = np.random.default_rng(5)
    x = x_rest + rng.normal(scale=2e-3, size=x_rest.shape)
    assert relative_error(corr.gradient(x), fd_gradient(corr.energy, x, h=1e-8)) < 1e-5
    H = dense_hessian(corr.hessian(x, "none"), x.shape[0])
    assert relative_error(H, fd_hessian(corr.gradient, x, h=1e-8)) < 1e-5
    assert np.linalg.eigvalsh(corr.hessian(x, "clamp").blocks).min() > -1e-9 * np.abs(H).max()
    h = 1e-6
    fd = (AnisotropicBendingCorrection(bending, x_rest, 0.4 + h).gradient(x)
          - AnisotropicBendingCorrection(bending, x_rest, 0.4 - h).gradient(x)) / (2 * h)
    assert relative_error(AnisotropicBendingCorrection(bending, x_rest, 0.0).parameter_gradient(x, "beta"), fd) < 1e-7


def test_grain_cosine_of_grid_edges():
    bending, x_rest = _sheet()
    c = hinge_grain_cosine(bending.hinges, x_rest)
    assert set(np.round(c, 12)) <= {1.0, -1.0} | set(np.round(c[np.abs(c) < 1], 12))
    assert np.any(c == 1.0) and np.any(c == -1.0)


@pytest.mark.parametrize("beta", [0.3, -0.5])
def test_bending_compliance_differs_along_x_and_y(beta):
    """Cylinder with its axis along x bends the x-parallel hinges: energy x (1 + beta); along y x (1 - beta)."""
    bending, x_rest = _sheet()
    corr = AnisotropicBendingCorrection(bending, x_rest, beta)
    for axis, factor in ((0, 1 + beta), (1, 1 - beta)):
        x = _cylinder(x_rest, 0.05, axis)
        iso = bending.energy(x)
        assert iso > 0
        assert (iso + corr.energy(x)) / iso == pytest.approx(factor, rel=1e-6)


def test_rejects_beta_outside_unit_interval():
    bending, x_rest = _sheet()
    with pytest.raises(ConfigError, match=r"\|beta\| < 1"):
        AnisotropicBendingCorrection(bending, x_rest, 1.0)
