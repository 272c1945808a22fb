"""Taichi StVK membrane equals the NumPy reference (energy, gradient, projected Hessian)."""

from __future__ import annotations

import numpy as np

from sim_core.energies.membrane.reference import StVKMembrane
from sim_core.mesh.sheet import grid_sheet
from tests.sim_core.ti_kernels.conftest import assert_projection_active_and_psd, assert_same_potential


def _pair():
    from sim_core.energies.membrane.kernel import TiStVKMembrane

    mesh = grid_sheet((0.04, 0.03), (5, 4), (0.0, 0.0, 0.0))  # 24 triangles
    args = (mesh.triangles, mesh.x, 3e9, 0.3, 3e-4)
    return mesh, StVKMembrane(*args), TiStVKMembrane(*args)


def test_matches_reference_on_random_deformations(ti_cpu):
    mesh, ref, tik = _pair()
    for seed, amplitude in ((0, 3e-4), (1, 2e-3)):
        x = mesh.x + amplitude * np.random.default_rng(seed).standard_normal(mesh.x.shape)
        assert_same_potential(ref, tik, x)


def test_compressed_sheet_projection(ti_cpu):
    mesh, ref, tik = _pair()
    # in-plane compression to 70 %: StVK membrane Hessian is indefinite (buckling modes)
    x = mesh.x * np.array([0.7, 0.75, 1.0]) + 2e-4 * np.random.default_rng(2).standard_normal(mesh.x.shape)
    assert_same_potential(ref, tik, x)
    assert_projection_active_and_psd(ref, tik, x)


def test_parameter_gradient_is_the_reference(ti_cpu):
    mesh, ref, tik = _pair()
    x = mesh.x + 1e-3 * np.random.default_rng(3).standard_normal(mesh.x.shape)
    for name in ref.parameter_names:
        assert np.allclose(tik.parameter_gradient(x, name), ref.parameter_gradient(x, name), rtol=1e-10, atol=0)
