"""Taichi Stable Neo-Hookean equals the NumPy reference (energy, gradient, projected Hessian)."""

from __future__ import annotations

import numpy as np

from sim_core.energies.neohookean.reference import StableNeoHookean
from sim_core.mesh.tet import tet_box
from tests.sim_core.ti_kernels.conftest import assert_projection_active_and_psd, assert_same_potential

E_GEL, NU_GEL = 3e5, 0.2


def _pair(nu: float = NU_GEL):
    from sim_core.energies.neohookean.kernel import TiStableNeoHookean

    mesh = tet_box((0.01, 0.01, 0.01), (3, 3, 3), (0.0, 0.0, 0.0))  # 48 tets
    return mesh, StableNeoHookean(mesh.tets, mesh.x, E_GEL, nu), TiStableNeoHookean(mesh.tets, mesh.x, E_GEL, nu)


def test_matches_reference_on_random_deformations(ti_cpu):
    mesh, ref, tik = _pair()
    for seed, amplitude in ((0, 5e-4), (1, 2e-3), (2, 4e-3)):
        x = mesh.x + amplitude * np.random.default_rng(seed).standard_normal(mesh.x.shape)
        assert_same_potential(ref, tik, x)
    # rest: repeated singular values (sigma = 1, 1, 1); energy and forces are round-off there
    g_scale = np.max(np.abs(ref.gradient(x)))
    assert abs(tik.energy(mesh.x)) < 1e-12 * ref.energy(x)
    assert np.max(np.abs(tik.gradient(mesh.x))) < 1e-12 * g_scale
    for projection in ("none", "clamp"):
        h_ref, h_ti = ref.hessian(mesh.x, projection).blocks, tik.hessian(mesh.x, projection).blocks
        assert np.max(np.abs(h_ti - h_ref)) < 1e-10 * np.max(np.abs(h_ref))


def test_matches_reference_with_inverted_and_stretched_tets(ti_cpu):
    mesh, ref, tik = _pair(nu=0.45)
    x = mesh.x + 5e-4 * np.random.default_rng(3).standard_normal(mesh.x.shape)
    t = mesh.tets[0]
    a, b, c, d = x[t]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n)
    x[t[3]] = d - 2.5 * np.dot(d - a, n) * n  # tet 0 inverted (J < 0: sigma_3 < 0)
    x = x * np.array([1.3, 1.0, 0.8])  # anisotropic stretch: distinct singular values
    assert np.linalg.det(ref.deformation_gradient(x)[0]) < 0
    assert_same_potential(ref, tik, x)
    assert_projection_active_and_psd(ref, tik, x)


def test_parameter_gradient_and_rigid_motion(ti_cpu):
    mesh, ref, tik = _pair()
    x = mesh.x + 1e-3 * np.random.default_rng(4).standard_normal(mesh.x.shape)
    assert np.array_equal(tik.parameter_gradient(x, "poisson_ratio"), ref.parameter_gradient(x, "poisson_ratio"))
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    moved = x @ R.T + np.array([0.1, -0.2, 0.05])
    assert abs(tik.energy(moved) - tik.energy(x)) < 1e-9 * tik.energy(x)
    g, g_moved = tik.gradient(x), tik.gradient(moved)
    assert np.max(np.abs(g_moved - g @ R.T)) < 1e-9 * np.max(np.abs(g))
