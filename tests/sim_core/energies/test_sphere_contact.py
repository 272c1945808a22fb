"""Rigid-sphere penalty contact (sim_core.energies.sphere_contact.reference)."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.energies.base import project_psd
from sim_core.energies.sphere_contact.reference import SphereContact
from sim_core.errors import ConfigError
from tests.sim_core.energies.test_contact import EPS, K, _check_potential
from tests.support.fd import dense_hessian

R = 5e-3


def _scene(seed=21):
    """Centre (vertex 0, off the origin) and 8 vertices at distances -eps..2 eps from the sphere."""
    rng = np.random.default_rng(seed)
    center = np.array([0.001, -0.002, 0.006])
    dirs = rng.normal(size=(8, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    d = np.array([-0.9, -0.5, -0.1, 0.2, 0.6, 0.95, 1.5, 2.0]) * EPS
    x = np.vstack([center, center + (R + d)[:, None] * dirs])
    return x, d


def test_sphere_contact_force_is_radial_with_the_reaction_on_the_centre():
    x, d = _scene()
    pot = SphereContact(np.arange(1, 9), 0, R, K, EPS)
    assert np.allclose(pot.distance(x), d)
    force = -pot.gradient(x)
    n = (x[1:] - x[0]) / np.linalg.norm(x[1:] - x[0], axis=1, keepdims=True)
    expect = np.where(d < EPS, K * (EPS - d), 0.0)
    assert np.allclose(force[1:], expect[:, None] * n)
    assert np.allclose(force[0], -force[1:].sum(axis=0))  # Newton's third law on the rigid sphere
    frames = pot.contact_frames(x)
    assert np.allclose(frames.lam, expect[d < EPS]) and np.allclose(frames.normal, n[d < EPS])
    rel = np.einsum("kj,kjd->kd", frames.weights, x[frames.vertices])  # x_i - c
    assert np.allclose(np.einsum("kd,kd->k", rel, frames.normal), R + d[d < EPS])


def test_sphere_contact_fd_and_closed_form_projections():
    x, d = _scene(22)
    pot = SphereContact(np.arange(1, 9), 0, R, K, EPS)
    _check_potential(pot, x, int(np.sum(d < EPS)))
    exact = pot.hessian(x, "none").blocks
    for projection in ("clamp", "abs"):
        closed = pot.hessian(x, projection).blocks
        assert np.allclose(closed, project_psd(exact, projection), atol=1e-9 * K)
    # translating sphere and vertices together changes nothing: rigid-translation null space
    H = dense_hessian(pot.hessian(x, "none"), x.shape[0])
    t = np.tile([0.3, -0.2, 0.9], x.shape[0])
    assert np.allclose(H @ t, 0.0, atol=1e-9 * K)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: SphereContact(np.arange(1, 3), 0, 0.0, K, EPS), "radius"),
        (lambda: SphereContact(np.arange(1, 3), 0, R, np.inf, EPS), "stiffness"),
        (lambda: SphereContact(np.arange(0, 3), 0, R, K, EPS), "centre vertex 0"),
    ],
)
def test_sphere_contact_constructor_errors(make, match):
    with pytest.raises(ConfigError, match=match):
        make()


def test_vertex_at_the_centre_is_a_clear_error():
    x = np.zeros((2, 3))
    with pytest.raises(ConfigError, match="vertex 1 is at the sphere's centre"):
        SphereContact([1], 0, R, K, EPS).gradient(x)
