"""Viscoelastic gel candidate (standard linear solid): FD derivatives, relaxation at constant strain."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.candidates.gel_viscoelasticity import MaxwellBranch, relax_state
from sim_core.energies.neohookean.reference import StableNeoHookean
from sim_core.errors import ConfigError
from sim_core.mesh.tet import tet_box
from tests.support.fd import dense_hessian, fd_gradient, fd_hessian, relative_error

E, NU = 3e5, 0.45


def _gel():
    mesh = tet_box((0.01, 0.008, 0.004), (2, 2, 2))
    return StableNeoHookean(mesh.tets, mesh.x, E, NU), mesh.x


def test_gradient_and_hessian_match_finite_differences():
    solid, x_rest = _gel()
    rng = np.random.default_rng(4)
    Fr = np.eye(3) + rng.normal(scale=0.05, size=(solid.tets.shape[0], 3, 3))
    branch = MaxwellBranch(solid, Fr, beta=0.8)
    x = x_rest + rng.normal(scale=3e-4, size=x_rest.shape)
    assert relative_error(branch.gradient(x), fd_gradient(branch.energy, x, h=1e-8)) < 1e-5
    H = dense_hessian(branch.hessian(x, "none"), x.shape[0])
    assert relative_error(H, fd_hessian(branch.gradient, x, h=1e-9)) < 1e-5
    assert np.linalg.eigvalsh(branch.hessian(x, "clamp").blocks).min() > -1e-6 * np.abs(H).max()
    h = 1e-6
    fd = (MaxwellBranch(solid, Fr, 0.8 + h).gradient(x) - MaxwellBranch(solid, Fr, 0.8 - h).gradient(x)) / (2 * h)
    assert relative_error(MaxwellBranch(solid, Fr, 0.0).parameter_gradient(x, "beta"), fd) < 1e-7


def test_branch_is_stress_free_in_its_relaxed_state_and_equals_snh_at_identity():
    solid, x_rest = _gel()
    k = solid.tets.shape[0]
    F = np.diag([1.02, 0.99, 0.97])
    x = x_rest @ F.T
    relaxed = MaxwellBranch(solid, np.tile(F, (k, 1, 1)), beta=1.0)
    assert np.abs(relaxed.gradient(x)).max() < 1e-10
    fresh = MaxwellBranch(solid, np.tile(np.eye(3), (k, 1, 1)), beta=0.5)
    assert np.allclose(fresh.gradient(x), 0.5 * solid.gradient(x), rtol=1e-12, atol=1e-14)


def test_force_relaxes_exponentially_at_constant_indentation():
    """Hold a 1 % compression: total force starts at (1 + beta) x the relaxed force, excess ~ exp(-t/tau)."""
    solid, x_rest = _gel()
    k = solid.tets.shape[0]
    beta, tau, dt = 0.6, 0.2, 0.01
    x = x_rest.copy()
    x[:, 2] *= 0.99
    Fr = np.tile(np.eye(3), (k, 1, 1))
    F = solid.deformation_gradient(x)
    f_eq = np.linalg.norm(solid.gradient(x))
    totals = []
    for _ in range(60):
        totals.append(np.linalg.norm(solid.gradient(x) + MaxwellBranch(solid, Fr, beta).gradient(x)))
        Fr = relax_state(Fr, F, dt, tau)
    totals = np.array(totals)
    assert totals[0] / f_eq == pytest.approx(1 + beta, rel=0.01)
    assert np.all(np.diff(totals) < 0)
    excess = (totals - f_eq) / (totals[0] - f_eq)
    t = dt * np.arange(60)
    assert np.allclose(excess, np.exp(-t / tau), atol=0.01)


def test_rejects_bad_parameters():
    solid, _ = _gel()
    k = solid.tets.shape[0]
    with pytest.raises(ConfigError, match="beta must be finite and >= 0"):
        MaxwellBranch(solid, np.tile(np.eye(3), (k, 1, 1)), -0.1)
    Fr = np.tile(np.eye(3), (k, 1, 1))
    Fr[2] = 0.0
    with pytest.raises(ConfigError, match="tet 2 is singular"):
        MaxwellBranch(solid, Fr, 0.1)
    with pytest.raises(ConfigError, match="relaxation time tau"):
        relax_state(Fr, Fr, 0.01, 0.0)
