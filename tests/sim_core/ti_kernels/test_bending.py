"""Taichi discrete-shell hinge bending equals the NumPy reference (energy, gradient, projected Hessian)."""

from __future__ import annotations

import copy

import numpy as np

from sim_core.energies.hinge_bending.reference import DiscreteShellBending
from sim_core.mesh.sheet import grid_sheet, sheet_topology
from tests.sim_core.ti_kernels.conftest import assert_projection_active_and_psd, assert_same_potential

D_PAPER = 2e-3  # N m


def _pair(theta_bar=None):
    from sim_core.energies.hinge_bending.kernel import TiDiscreteShellBending

    mesh = grid_sheet((0.04, 0.03), (5, 4), (0.0, 0.0, 0.0))
    hinges = sheet_topology(mesh.triangles).hinges
    return (mesh, DiscreteShellBending(hinges, mesh.x, D_PAPER, theta_bar),
            TiDiscreteShellBending(hinges, mesh.x, D_PAPER, theta_bar))


def test_matches_reference_on_random_deformations(ti_cpu):
    mesh, ref, tik = _pair()
    for seed, amplitude in ((0, 5e-4), (1, 3e-3)):
        x = mesh.x + amplitude * np.random.default_rng(seed).standard_normal(mesh.x.shape)
        assert_same_potential(ref, tik, x)
        assert_projection_active_and_psd(ref, tik, x)


def test_rest_angles_are_read_per_call(ti_cpu):
    mesh, ref, tik = _pair()
    h = ref.hinges.shape[0]
    theta_bar = np.random.default_rng(5).uniform(-1.0, 1.0, h)
    ref2, tik2 = copy.copy(ref), copy.copy(tik)  # as ElasticTerms.bending does
    ref2.hinge_theta_bar = theta_bar
    tik2.hinge_theta_bar = theta_bar
    x = mesh.x + 1e-3 * np.random.default_rng(6).standard_normal(mesh.x.shape)
    assert_same_potential(ref2, tik2, x)
    assert_same_potential(ref, tik, x)  # the original keeps its own (flat) rest angles
    assert abs(tik2.energy(x) - tik.energy(x)) > 0.1 * tik.energy(x)


def test_folded_sheet_and_parameter_gradient(ti_cpu):
    mesh, ref, tik = _pair()
    x = mesh.x.copy()
    fold = x[:, 0] > 0.02
    x[fold, 2] = (x[fold, 0] - 0.02) * np.tan(1.2)  # 1.2 rad fold along x = 0.02
    x += 2e-4 * np.random.default_rng(7).standard_normal(x.shape)
    assert_same_potential(ref, tik, x)
    assert np.array_equal(tik.parameter_gradient(x, "bending_stiffness"),
                          ref.parameter_gradient(x, "bending_stiffness"))
