"""Stiction candidate: FD derivatives, PSD projection, beta gradient, breakaway force (1 + beta) mu lam."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.candidates.stiction import StictionFriction
from sim_core.energies.friction.reference import LaggedFriction, tangent_basis
from sim_core.errors import ConfigError
from tests.support.fd import dense_hessian, fd_gradient, fd_hessian, relative_error

DT, EPS_V = 0.01, 0.01
EPS_U = EPS_V * DT


def _friction(rng, p=4, n=10):
    vertices = np.stack([rng.choice(n, size=4, replace=False) for _ in range(p)])
    bary = rng.dirichlet(np.ones(3), size=p)
    weights = np.concatenate([np.ones((p, 1)), -bary], axis=1)
    normal = rng.normal(size=(p, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    x_prev = rng.uniform(-0.01, 0.01, size=(n, 3))
    fr = LaggedFriction(vertices, weights, tangent_basis(normal), rng.uniform(0.5, 3, p), rng.uniform(0.2, 1, p),
                        x_prev, EPS_V, DT)
    return fr, x_prev


@pytest.mark.parametrize("slip", [0.3, 2.0, 8.0])  # in units of eps_u: before, at and past the peak
def test_gradient_and_hessian_match_finite_differences(slip):
    rng = np.random.default_rng(1)
    fr, x_prev = _friction(rng)
    st = StictionFriction(fr, beta=0.7)
    x = x_prev + rng.normal(scale=slip * EPS_U, size=x_prev.shape)
    assert relative_error(st.gradient(x), fd_gradient(st.energy, x, h=1e-9)) < 1e-5
    H = dense_hessian(st.hessian(x, "none"), x.shape[0])
    assert relative_error(H, fd_hessian(st.gradient, x, h=1e-10)) < 1e-5


def test_projected_blocks_are_psd_and_beta_gradient_is_exact():
    rng = np.random.default_rng(2)
    fr, x_prev = _friction(rng)
    x = x_prev + rng.normal(scale=5 * EPS_U, size=x_prev.shape)
    for proj in ("clamp", "abs"):
        blocks = StictionFriction(fr, 0.5).hessian(x, proj).blocks
        assert np.linalg.eigvalsh(blocks).min() > -1e-9 * np.abs(blocks).max()
    h = 1e-6
    fd = (StictionFriction(fr, 0.3 + h).gradient(x) - StictionFriction(fr, 0.3 - h).gradient(x)) / (2 * h)
    assert relative_error(StictionFriction(fr, 0.0).parameter_gradient(x, "beta"), fd) < 1e-8
    with pytest.raises(KeyError, match="no parameter 'mu'"):
        StictionFriction(fr, 0.3).parameter_gradient(x, "mu")


def test_breakaway_force_is_static_coefficient_and_kinetic_force_is_recovered():
    """One vertex on a fixed point: peak of |friction + stiction| over slip is (1 + beta) mu lam."""
    x_prev = np.zeros((2, 3))
    mu, lam, beta = 0.6, 2.0, 0.4
    fr = LaggedFriction(np.array([[0, 1]]), np.array([[1.0, -1.0]]), tangent_basis(np.array([[0.0, 0.0, 1.0]])),
                        [lam], [mu], x_prev, EPS_V, DT)
    st = StictionFriction(fr, beta)
    slips = np.linspace(0.0, 30 * EPS_U, 3001)
    force = []
    for s in slips:
        x = x_prev.copy()
        x[0, 0] = s
        force.append(np.linalg.norm(fr.gradient(x)[0] + st.gradient(x)[0]))
    force = np.array(force)
    assert force.max() == pytest.approx((1 + beta) * mu * lam, rel=2e-3)
    assert slips[np.argmax(force)] == pytest.approx(2 * EPS_U, rel=0.05)
    assert force[-1] == pytest.approx(mu * lam, rel=0.01)  # kinetic at large slip
    assert np.linalg.norm(StictionFriction(fr, 0.0).gradient(x)) == 0.0


def test_rejects_negative_beta_and_small_slip_scale():
    fr, _ = _friction(np.random.default_rng(0))
    with pytest.raises(ConfigError, match="beta = mu_s/mu_k - 1"):
        StictionFriction(fr, -0.1)
    with pytest.raises(ConfigError, match="slip_scale"):
        StictionFriction(fr, 0.1, slip_scale=0.5)
