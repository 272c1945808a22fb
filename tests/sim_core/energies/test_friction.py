"""Lagged IPC friction: FD derivatives in both regimes, Coulomb magnitude, direction, PSD, mu."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.collision.distances import edge_edge_side
from sim_core.errors import ConfigError
from sim_core.energies.contact.reference import (
    EdgeEdgeContact,
    PlaneContact,
    VertexTriangleContact,
    concatenate_frames,
)
from sim_core.energies.friction.reference import (
    LaggedFriction,
    smooth_friction_f0,
    smooth_friction_f1,
    smooth_friction_f1_over_x,
    tangent_basis,
)
from tests.support.fd import dense_hessian, fd_gradient, fd_hessian, relative_error

DT, EPS_V = 5e-3, 0.01
EPS_U = EPS_V * DT  # 5e-5 m


def _random_friction(rng, p=5, n=12):
    vertices = np.stack([rng.choice(n, size=4, replace=False) for _ in range(p)])
    bary = rng.dirichlet(np.ones(3), size=p)
    weights = np.concatenate([np.ones((p, 1)), -bary], axis=1)
    normal = rng.normal(size=(p, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    lam = rng.uniform(0.5, 3.0, size=p)
    mu = rng.uniform(0.2, 1.0, size=p)
    x_prev = rng.uniform(-0.01, 0.01, size=(n, 3))
    return LaggedFriction(vertices, weights, tangent_basis(normal), lam, mu, x_prev, EPS_V, DT), x_prev


def test_mollifier_is_c1_and_matches_its_derivative():
    y = np.array([0.0, 0.3, 0.9, 0.999999, 1.000001, 2.0]) * EPS_U
    assert smooth_friction_f0(np.array([EPS_U]), EPS_U)[0] == pytest.approx(EPS_U)
    h = 1e-12
    fd = (smooth_friction_f0(y + h, EPS_U) - smooth_friction_f0(y - h, EPS_U)) / (2 * h)
    assert np.allclose(fd[1:], smooth_friction_f1(y, EPS_U)[1:], rtol=1e-5)
    assert np.allclose(smooth_friction_f1(y, EPS_U)[4:], 1.0)
    assert smooth_friction_f1_over_x(np.array([0.0]), EPS_U)[0] == pytest.approx(2 / EPS_U)


@pytest.mark.parametrize("scale, regime", [(0.3 * EPS_U, "mollified"), (20 * EPS_U, "sliding")])
def test_friction_fd_and_psd(scale, regime):
    rng = np.random.default_rng(20 if regime == "sliding" else 21)
    fr, x_prev = _random_friction(rng)
    check_friction_fd_psd_and_mu(fr, x_prev, rng, scale, regime, psd_tol=1e-9)


def check_friction_fd_psd_and_mu(fr, x_prev, rng, scale, regime, psd_tol):
    """Gradient and Hessian of ``fr`` against central differences at a random ``x`` near ``x_prev``
    inside one regime (``"mollified"``: |u| < eps_u, ``"sliding"``: |u| > eps_u), PSD blocks (smallest
    eigenvalue above ``-psd_tol`` times the largest entry) and d gradient / d mu."""
    for _ in range(3):
        x = x_prev + rng.normal(scale=scale, size=x_prev.shape)
        y = np.linalg.norm(fr.tangential_displacement(x), axis=1)
        # stay inside one regime (f0 is only C1 at y = eps_u)
        x_ok = np.all(y < 0.95 * EPS_U) if regime == "mollified" else np.all(y > 1.05 * EPS_U)
        if x_ok:
            break
    assert x_ok
    h = 1e-3 * scale
    g = fr.gradient(x)
    assert relative_error(g, fd_gradient(fr.energy, x, h=h)) < 1e-5
    blocks = fr.hessian(x, "none")
    H = dense_hessian(blocks, x.shape[0])
    assert relative_error(H, fd_hessian(fr.gradient, x, h=h)) < 1e-5
    assert np.min(np.linalg.eigvalsh(blocks.blocks)) > -psd_tol * np.max(np.abs(blocks.blocks))
    # d gradient / d mu with every pair's coefficient moving together
    mu0 = fr.mu.copy()
    fr.mu = mu0 + 1e-6
    gp = fr.gradient(x)
    fr.mu = mu0
    assert relative_error(fr.parameter_gradient(x, "mu"), (gp - g) / 1e-6) < 1e-6


def test_mu_gradient_per_coefficient_matches_fd():
    rng = np.random.default_rng(22)
    fr, x_prev = _random_friction(rng)
    fr.mu[:] = 0.5  # one shared coefficient
    x = x_prev + rng.normal(scale=10 * EPS_U, size=x_prev.shape)
    mask = np.array([True, False, True, False, True])
    dmu = 1e-6
    g0 = fr.gradient(x)
    fr.mu[mask] += dmu
    g1 = fr.gradient(x)
    fr.mu[mask] -= dmu
    assert relative_error(fr.mu_gradient(x, mask), (g1 - g0) / dmu) < 1e-6
    with pytest.raises(KeyError):
        fr.parameter_gradient(x, "lam")


def test_sliding_force_is_coulomb_and_opposes_motion():
    """Vertex on a table, pressed with lam, slid tangentially by more than eps_v dt."""
    k, eps = 1e4, 4e-4
    x_prev = np.array([[0.01, 0.02, 1e-4]])
    table = PlaneContact([0], [0, 0, 1], 0.0, k, eps)
    frames = table.contact_frames(x_prev)
    lam = k * (eps - 1e-4)
    assert frames.lam[0] == pytest.approx(lam)
    mu = 0.4
    fr = LaggedFriction.from_frames(frames, mu, x_prev, EPS_V, DT)
    for slide in ([3e-4, -1e-4, 0.0], [0.0, 2e-3, 0.0], [1e-4, 1e-4, 5e-5]):
        x = x_prev + np.array([slide])
        force = -fr.gradient(x)[0]
        tangential = np.array([slide[0], slide[1], 0.0])
        assert np.linalg.norm(force) == pytest.approx(mu * lam, rel=1e-12)
        assert force @ tangential == pytest.approx(-np.linalg.norm(force) * np.linalg.norm(tangential), rel=1e-12)
        assert abs(force[2]) < 1e-12 * mu * lam  # friction has no normal component
    # mollified regime: force magnitude below Coulomb, still opposing
    x = x_prev + np.array([[0.2 * EPS_U, 0.0, 0.0]])
    force = -fr.gradient(x)[0]
    assert 0 < np.linalg.norm(force) < mu * lam and force[0] < 0


def test_zero_force_for_zero_or_normal_displacement():
    rng = np.random.default_rng(23)
    fr, x_prev = _random_friction(rng)
    assert np.all(fr.gradient(x_prev) == 0.0)
    # moving every vertex of every pair along that pair's normal: no tangential displacement
    x_prev = np.zeros((1, 3))
    fr = LaggedFriction(np.zeros((1, 1), np.int64), np.ones((1, 1)), tangent_basis(np.array([[0, 0, 1.0]])),
                        np.ones(1), 0.5, x_prev, EPS_V, DT)
    assert np.allclose(fr.gradient(np.array([[0, 0, 1e-3]])), 0.0)
    H = fr.hessian(x_prev).blocks[0]
    assert np.allclose(H, 0.5 * (2 / EPS_U) * np.diag([1.0, 1.0, 0.0]))


def test_friction_between_two_sides_is_equal_and_opposite_and_uses_frames():
    """A vertex sliding on a triangle, frames from a vertex-triangle and an edge-edge contact."""
    k, eps = 1e4, 4e-4
    x_prev = np.array([[0.003, 0.003, 2e-4], [0, 0, 0], [0.01, 0, 0], [0, 0.01, 0],
                       [0.0, 0.005, 3e-4], [0.01, 0.005, 3e-4], [0.005, 0.0, 0.0], [0.005, 0.01, 0.0]])
    vt = VertexTriangleContact(np.array([[0, 0]]), np.array([[1, 2, 3]]), np.array([1.0]), k, eps)
    ee = EdgeEdgeContact(np.array([[0, 1]]), np.array([[4, 5], [6, 7]]), edge_edge_side(x_prev[None, 4:8]), k, eps)
    frames = concatenate_frames([vt.contact_frames(x_prev), ee.contact_frames(x_prev)])
    assert frames.vertices.shape == (2, 4) and np.allclose(frames.normal[:, 2], [1.0, 1.0])
    fr = LaggedFriction.from_frames(frames, np.array([0.5, 0.8]), x_prev, EPS_V, DT)
    x = x_prev.copy()
    x[0] += [1e-3, 0, 0]
    x[4:6] += [0, 1e-3, 0]
    g = fr.gradient(x)
    assert np.allclose(g.sum(axis=0), 0.0, atol=1e-12)  # internal forces
    assert -g[0, 0] == pytest.approx(-0.5 * frames.lam[0])
    assert -(g[4, 1] + g[5, 1]) == pytest.approx(-0.8 * frames.lam[1])


def test_friction_errors():
    x = np.zeros((1, 3))
    args = dict(
        vertices=np.zeros((1, 1), np.int64), weights=np.ones((1, 1)), tangent=tangent_basis(np.array([[0, 0, 1.0]])),
        lam=np.ones(1), mu=0.5, x_prev=x, eps_v=EPS_V, dt=DT,
    )
    with pytest.raises(ConfigError, match="mu"):
        LaggedFriction(**{**args, "mu": -0.1})
    with pytest.raises(ConfigError, match="lam"):
        LaggedFriction(**{**args, "lam": np.array([np.nan])})
    with pytest.raises(ConfigError, match="eps_v"):
        LaggedFriction(**{**args, "eps_v": 0.0})
    with pytest.raises(ConfigError, match="dt"):
        LaggedFriction(**{**args, "dt": -1.0})


def test_eps_v_gradient_matches_central_differences_in_both_regimes():
    """d(friction force)/d eps_v against central differences of the gradient in eps_v, with pairs on both
    sides of the mollifier's seam: the mollified pairs carry it, the sliding ones (Coulomb, no eps_v) none."""
    rng = np.random.default_rng(23)
    fr, x_prev = _random_friction(rng, p=8)
    x = x_prev + rng.normal(scale=0.8 * EPS_U, size=x_prev.shape)
    y = np.linalg.norm(fr.tangential_displacement(x), axis=1)
    assert np.any(y < 0.9 * EPS_U) and np.any(y > 1.1 * EPS_U)  # both regimes, away from the seam
    analytic = fr.eps_v_gradient(x)
    h = 1e-6 * EPS_V

    def gradient_at(eps_v):
        return LaggedFriction(fr.vertices, fr.weights, fr.tangent, fr.lam, fr.mu, x_prev, eps_v, DT).gradient(x)

    fd = (gradient_at(EPS_V + h) - gradient_at(EPS_V - h)) / (2 * h)
    assert np.linalg.norm(fd) > 0
    assert relative_error(analytic, fd) < 1e-6
    sliding = LaggedFriction(fr.vertices, fr.weights, fr.tangent, fr.lam, fr.mu, x_prev, 0.01 * EPS_V, DT)
    assert np.all(sliding.eps_v_gradient(x) == 0.0)  # every pair slides: no stick speed in the force
