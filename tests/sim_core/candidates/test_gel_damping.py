"""The gel's Kelvin-Voigt dashpot (candidate ``gel_damping``): the force of a strain rate, none at rest."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.candidates import CandidateHook
from sim_core.candidates.gel_damping import kelvin_voigt_branch
from sim_core.energies.neohookean.reference import StableNeoHookean
from sim_core.errors import ConfigError
from sim_core.mesh.tet import tet_box
from tests.support.fd import fd_hessian, relative_error

E, NU = 3e5, 0.45


def _gel():
    mesh = tet_box((0.01, 0.008, 0.004), (2, 2, 2))
    return StableNeoHookean(mesh.tets, mesh.x, E, NU), mesh.x


def test_force_is_alpha_times_the_stiffness_times_the_velocity():
    """Kelvin-Voigt: over a step from ``x^n`` at velocity ``v`` the dashpot's force is ``alpha K v``
    (K the gel's tangent stiffness, by finite differences of its elastic force) to first order in the
    increment ``v dt`` (2e-3 strain here) and in the strain at ``x^n`` (the dashpot's stiffness is the
    gel's at rest carried by ``F^n``; 0.3 % here), so within 1 %."""
    solid, x_rest = _gel()
    rng = np.random.default_rng(2)
    x_prev = x_rest @ np.diag([1.001, 0.9995, 0.997]).T + rng.normal(scale=2e-6, size=x_rest.shape)
    v = rng.normal(scale=4e-4, size=x_rest.shape)  # m/s: 4 um a step, 2e-3 strain across the 2 mm layers
    alpha, dt = 0.02, 0.01
    f = kelvin_voigt_branch(solid, x_prev, alpha, dt).gradient(x_prev + v * dt)
    K = fd_hessian(solid.gradient, x_prev, h=1e-9)
    expected = alpha * (K @ v.reshape(-1)).reshape(v.shape)
    assert relative_error(f, expected) < 1e-2


def test_no_force_without_motion_and_none_when_off():
    solid, x_rest = _gel()
    x_prev = x_rest @ np.diag([1.02, 0.99, 0.97]).T
    np.testing.assert_allclose(kelvin_voigt_branch(solid, x_prev, 0.05, 0.01).gradient(x_prev), 0.0, atol=1e-12)
    np.testing.assert_array_equal(kelvin_voigt_branch(solid, x_prev, 0.0, 0.01).gradient(x_prev + 1e-4), 0.0)
    with pytest.raises(ConfigError, match="alpha"):
        kelvin_voigt_branch(solid, x_prev, -0.01, 0.01)
    with pytest.raises(ConfigError, match="dt"):
        kelvin_voigt_branch(solid, x_prev, 0.01, 0.0)


def test_hook_adds_one_dashpot_per_gel_only_when_set():
    solid, x_rest = _gel()

    class Elastic:
        solids = {"gel": solid}

    assert CandidateHook({}).damping_terms(None, x_rest, 0.01, Elastic()) == []
    (term,) = CandidateHook({"gel_damping": 0.03}).damping_terms(None, x_rest, 0.01, Elastic())
    assert term.beta == pytest.approx(3.0)
