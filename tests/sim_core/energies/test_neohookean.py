"""Stable Neo-Hookean: derivatives vs finite differences, PSD projection, invariances, linearisation."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.energies.base import project_psd
from sim_core.energies.neohookean.reference import StableNeoHookean, snh_lame_parameters
from sim_core.errors import ConfigError, MeshError
from sim_core.mesh.tet import box_face_vertices, tet_box
from tests.support.fd import dense_hessian, fd_gradient, fd_hessian, relative_error

E_GEL, NU_GEL = 3e5, 0.2  # ThinShellLab sensor gel


def _small_block():
    """2 x 2 x 2 cells of 5 mm (48 tets, 27 vertices)."""
    return tet_box((0.01, 0.01, 0.01), (3, 3, 3), (0.0, 0.0, 0.0))


def _deformed(x: np.ndarray, seed: int, amplitude: float = 1.5e-3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return x + amplitude * rng.standard_normal(x.shape)


def _inverted_configuration(mesh):
    """Random deformation plus one tet whose apex is pushed through its opposite face."""
    x = _deformed(mesh.x, 3, 5e-4)
    t = mesh.tets[0]
    a, b, c, d = x[t]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n)
    x[t[3]] = d - 2.5 * np.dot(d - a, n) * n  # reflect d well past the plane of (a, b, c)
    return x


def _signed_volume(x, t):
    return np.dot(np.cross(x[t[1]] - x[t[0]], x[t[2]] - x[t[0]]), x[t[3]] - x[t[0]]) / 6


def _rotation(seed: int) -> np.ndarray:
    q, r = np.linalg.qr(np.random.default_rng(seed).standard_normal((3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


@pytest.mark.parametrize("nu", [0.2, 0.45, -0.3])
@pytest.mark.parametrize("config", ["random", "inverted"])
def test_gradient_and_hessian_match_finite_differences(nu: float, config: str) -> None:
    mesh = _small_block()
    snh = StableNeoHookean(mesh.tets, mesh.x, E_GEL, nu)
    x = _deformed(mesh.x, 1) if config == "random" else _inverted_configuration(mesh)
    if config == "inverted":
        assert _signed_volume(x, mesh.tets[0]) < 0
    g = snh.gradient(x)
    assert relative_error(g, fd_gradient(snh.energy, x, h=1e-7)) < 1e-5
    H = dense_hessian(snh.hessian(x, "none"), x.shape[0])
    assert relative_error(H, fd_hessian(snh.gradient, x, h=1e-8)) < 1e-5
    assert np.allclose(H, H.T, rtol=0, atol=1e-9 * np.abs(H).max())


@pytest.mark.parametrize("projection", ["clamp", "abs"])
def test_projected_blocks_are_psd_and_match_numerical_projection(projection: str) -> None:
    mesh = _small_block()
    snh = StableNeoHookean(mesh.tets, mesh.x, E_GEL, 0.45)
    x = _inverted_configuration(mesh)
    blocks = snh.hessian(x, projection).blocks
    w = np.linalg.eigvalsh(blocks)
    assert w.min() >= -1e-10 * np.abs(w).max()
    # the unprojected blocks have negative eigenvalues here, so the projection did something
    assert np.linalg.eigvalsh(snh.hessian(x, "none").blocks).min() < -1e-3 * np.abs(w).max()
    # analytic eigensystem == numerical eigen-projection of d2psi/dF2 mapped by dF/dx
    F = snh.deformation_gradient(x)
    A = project_psd(snh.d2psi_dF2(F).reshape(-1, 9, 9), projection)
    M = snh.tet_dvecF_dx
    reference = snh.tet_rest_volume[:, None, None] * np.swapaxes(M, 1, 2) @ A @ M
    assert relative_error(blocks, reference) < 1e-9


def test_d2psi_equals_the_levi_civita_formula() -> None:
    # d2psi_dF2 gathers the 36 non-zeros of d2J; reference: the full eps_ikm eps_jln F_mn contraction
    from sim_core.energies.neohookean.reference import _LEVI_CIVITA, _cofactor

    mesh = _small_block()
    snh = StableNeoHookean(mesh.tets, mesh.x, E_GEL, 0.3)
    rng = np.random.default_rng(8)
    F = np.eye(3) + 0.4 * rng.standard_normal((30, 3, 3))
    F[0], F[1] = np.diag([1.2, 0.8, -0.3]), 0.0
    I_C = np.einsum("kij,kij->k", F, F)
    J, cof = np.linalg.det(F), _cofactor(F)
    d2J = np.einsum("ikm,jln,tmn->tijkl", _LEVI_CIVITA, _LEVI_CIVITA, F)
    reference = (
        (snh.mu * (1.0 - 1.0 / (I_C + 1.0)))[:, None, None, None, None] * np.eye(9).reshape(3, 3, 3, 3)
        + (2.0 * snh.mu / (I_C + 1.0) ** 2)[:, None, None, None, None] * np.einsum("tij,tkl->tijkl", F, F)
        + snh.lam * np.einsum("tij,tkl->tijkl", cof, cof)
        + (snh.lam * (J - snh.alpha))[:, None, None, None, None] * d2J
    )
    assert np.array_equal(snh.d2psi_dF2(F), reference)


def test_analytic_eigensystem_reconstructs_d2psi() -> None:
    mesh = _small_block()
    snh = StableNeoHookean(mesh.tets, mesh.x, E_GEL, 0.3)
    rng = np.random.default_rng(7)
    F = np.eye(3) + 0.4 * rng.standard_normal((20, 3, 3))
    F[0] = np.diag([1.2, 0.8, -0.3])  # inverted
    F[1] = np.eye(3)  # rest: repeated singular values
    F[2] = 0.0  # fully collapsed
    w, Q = snh.d2psi_dF2_eigensystem(F)
    assert np.allclose(np.swapaxes(Q, 1, 2) @ Q, np.eye(9), atol=1e-12)
    A = snh.d2psi_dF2(F).reshape(-1, 9, 9)
    assert relative_error((Q * w[:, None, :]) @ np.swapaxes(Q, 1, 2), A) < 1e-12


def test_zero_energy_and_gradient_at_rest() -> None:
    mesh = _small_block()
    snh = StableNeoHookean(mesh.tets, mesh.x, E_GEL, NU_GEL)
    assert abs(snh.energy(mesh.x)) < 1e-12 * E_GEL * 1e-6
    g_scale = E_GEL * 0.01**2
    assert np.max(np.abs(snh.gradient(mesh.x))) < 1e-12 * g_scale
    assert snh.energy(_deformed(mesh.x, 2)) > 0


def test_rigid_motion_invariance() -> None:
    mesh = _small_block()
    snh = StableNeoHookean(mesh.tets, mesh.x, E_GEL, NU_GEL)
    x = _deformed(mesh.x, 4)
    R = _rotation(5)
    y = x @ R.T + np.array([0.3, -1.0, 2.0])
    assert snh.energy(y) == pytest.approx(snh.energy(x), rel=1e-10)
    assert relative_error(snh.gradient(y), snh.gradient(x) @ R.T) < 1e-9
    assert snh.energy(mesh.x @ R.T + 5.0) == pytest.approx(0.0, abs=1e-12)
    Rb = np.kron(np.eye(4), R)
    Hx, Hy = snh.hessian(x, "none").blocks, snh.hessian(y, "none").blocks
    assert relative_error(Hy, Rb @ Hx @ Rb.T) < 1e-9


def _face_force(snh, x, mesh, axis: int) -> float:
    """Net external force (= dE/dx) along ``axis`` on the max face of that axis, N."""
    return float(np.sum(snh.gradient(x)[box_face_vertices(mesh, axis, "max"), axis]))


@pytest.mark.parametrize("nu", [0.2, 0.45, -0.5])
def test_small_strain_matches_linear_elasticity(nu: float) -> None:
    E = 1e5
    L = np.array([0.02, 0.03, 0.01])
    mesh = tet_box(L, (3, 4, 3), (0.0, 0.0, 0.0))
    snh = StableNeoHookean(mesh.tets, mesh.x, E, nu)
    eps = 1e-5
    area_z = L[0] * L[1]
    mu_le = E / (2 * (1 + nu))
    lam_le = E * nu / ((1 + nu) * (1 - 2 * nu))
    # uniaxial strain: sigma_zz = (lam + 2 mu) eps, sigma_xx = lam eps
    x = mesh.x * np.array([1.0, 1.0, 1.0 + eps])
    assert _face_force(snh, x, mesh, 2) == pytest.approx((lam_le + 2 * mu_le) * eps * area_z, rel=1e-2)
    assert _face_force(snh, x, mesh, 0) == pytest.approx(lam_le * eps * L[1] * L[2], rel=1e-2)
    # uniaxial stress: lateral contraction nu eps gives sigma_zz = E eps and free lateral faces
    x = mesh.x * np.array([1.0 - nu * eps, 1.0 - nu * eps, 1.0 + eps])
    f_z = _face_force(snh, x, mesh, 2)
    assert f_z == pytest.approx(E * eps * area_z, rel=1e-2)
    assert abs(_face_force(snh, x, mesh, 0)) < 1e-2 * abs(f_z)
    # energy density E eps^2 / 2
    assert snh.energy(x) == pytest.approx(0.5 * E * eps**2 * np.prod(L), rel=1e-2)


def test_lame_reparameterisation() -> None:
    mu, lam = snh_lame_parameters(3e5, 0.2)
    mu_le, lam_le = 3e5 / 2.4, 3e5 * 0.2 / (1.2 * 0.6)
    assert mu == pytest.approx(4 / 3 * mu_le)
    assert lam == pytest.approx(lam_le + 5 / 6 * mu_le)
    mesh = _small_block()
    snh = StableNeoHookean(mesh.tets, mesh.x, 3e5, 0.2)
    assert snh.alpha == pytest.approx(1 + mu / lam - mu / (4 * lam))


@pytest.mark.parametrize("name,h", [("youngs_modulus", 10.0), ("poisson_ratio", 1e-6)])
def test_parameter_gradient_matches_finite_differences(name: str, h: float) -> None:
    mesh = _small_block()
    x = _deformed(mesh.x, 6)
    params = {"youngs_modulus": E_GEL, "poisson_ratio": 0.3}
    snh = StableNeoHookean(mesh.tets, mesh.x, **params)
    plus = StableNeoHookean(mesh.tets, mesh.x, **{**params, name: params[name] + h})
    minus = StableNeoHookean(mesh.tets, mesh.x, **{**params, name: params[name] - h})
    fd = (plus.gradient(x) - minus.gradient(x)) / (2 * h)
    assert relative_error(snh.parameter_gradient(x, name), fd) < 1e-6
    with pytest.raises(KeyError, match="density"):
        snh.parameter_gradient(x, "density")


def test_no_nan_for_inverted_and_collapsed_configurations() -> None:
    mesh = _small_block()
    snh = StableNeoHookean(mesh.tets, mesh.x, E_GEL, NU_GEL)
    for x in (-mesh.x, np.zeros_like(mesh.x), mesh.x * np.array([1.0, 1.0, 0.0])):
        assert np.isfinite(snh.energy(x))
        assert np.all(np.isfinite(snh.gradient(x)))
        for projection in ("none", "clamp"):
            assert np.all(np.isfinite(snh.hessian(x, projection).blocks))
    # a fully inverted (mirrored) block stores energy and is pushed back
    assert snh.energy(mesh.x * np.array([1.0, 1.0, -1.0])) > 0


@pytest.mark.parametrize(
    "E,nu,match",
    [(0.0, 0.3, "youngs_modulus"), (float("nan"), 0.3, "youngs_modulus"), (1e5, 0.5, "poisson_ratio"),
     (1e5, -1.0, "poisson_ratio"), (1e5, float("nan"), "poisson_ratio")],
)
def test_invalid_material_raises(E: float, nu: float, match: str) -> None:
    mesh = _small_block()
    with pytest.raises(ConfigError, match=match):
        StableNeoHookean(mesh.tets, mesh.x, E, nu)


def test_inverted_rest_tet_raises_naming_it() -> None:
    mesh = _small_block()
    tets = mesh.tets.copy()
    tets[5] = tets[5][[0, 2, 1, 3]]
    with pytest.raises(MeshError, match=r"tet 5 .*inverted \(signed volume -"):
        StableNeoHookean(tets, mesh.x, E_GEL, NU_GEL)


def test_unknown_projection_raises() -> None:
    mesh = _small_block()
    snh = StableNeoHookean(mesh.tets, mesh.x, E_GEL, NU_GEL)
    with pytest.raises(ValueError, match="projection"):
        snh.hessian(mesh.x, "flip")


def test_kept_deformation_is_reused_only_at_equal_positions() -> None:
    # energy, gradient and Hessian of one x share F and its invariants; an in-place change of x
    # or a copy with other dF/dx (as the Maxwell branch makes) recomputes them
    mesh = _small_block()
    snh = StableNeoHookean(mesh.tets, mesh.x, E_GEL, 0.3)
    fresh = StableNeoHookean(mesh.tets, mesh.x, E_GEL, 0.3)
    x = _deformed(mesh.x, 9)
    e, g, h = snh.energy(x), snh.gradient(x), snh.hessian(x, "none").blocks
    assert e == fresh.energy(x.copy())
    assert np.array_equal(g, fresh.gradient(x.copy())) and np.array_equal(h, fresh.hessian(x.copy(), "none").blocks)
    x[3] += 1e-4  # in place
    assert snh.energy(x) == StableNeoHookean(mesh.tets, mesh.x, E_GEL, 0.3).energy(x)
    clone = object.__new__(StableNeoHookean)
    clone.__dict__.update(snh.__dict__)
    clone.tet_dFdx = 1.1 * snh.tet_dFdx
    assert clone.energy(x) != snh.energy(x)


def test_dvecF_dx_is_the_matrix_of_the_current_dFdx() -> None:
    # tet_dvecF_dx[t, 3 i + j, 3 a + c] = delta_ic tet_dFdx[t, a, j], made at the first read from the tet_dFdx then
    # held; a copy whose tet_dFdx is replaced (a Maxwell branch) reads the matrix of its own
    mesh = _small_block()
    snh = StableNeoHookean(mesh.tets, mesh.x, E_GEL, 0.3)

    def matrix(dFdx):
        M = np.zeros((dFdx.shape[0], 9, 12))
        for i in range(3):
            for j in range(3):
                for a in range(4):
                    M[:, 3 * i + j, 3 * a + i] = dFdx[:, a, j]
        return M

    M = snh.tet_dvecF_dx
    assert M.shape == (mesh.tets.shape[0], 9, 12) and snh.tet_dvecF_dx is M
    np.testing.assert_array_equal(M, matrix(snh.tet_dFdx))
    clone = object.__new__(StableNeoHookean)
    clone.__dict__.update(snh.__dict__)
    clone.tet_dFdx = 1.1 * snh.tet_dFdx
    np.testing.assert_array_equal(clone.tet_dvecF_dx, matrix(clone.tet_dFdx))
    assert snh.tet_dvecF_dx is M
