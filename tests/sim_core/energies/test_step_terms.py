"""The step's quadratic and linear terms of the incremental potential: inertia, gravity and viscous
damping. Gradient and Hessian against central finite differences, the closed forms, and the
parameter derivatives the adjoint uses."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.energies.damping.reference import ViscousDamping
from sim_core.energies.gravity.reference import GravityPotential
from sim_core.energies.inertia.reference import InertiaPotential
from sim_core.errors import ConfigError
from tests.support.fd import dense_hessian, fd_gradient, fd_hessian, relative_error

RNG = np.random.default_rng(7)
N = 5
MASS = RNG.uniform(1e-4, 3e-3, N)  # kg
X_PREV = RNG.normal(scale=0.01, size=(N, 3))  # m
DT = 0.005


def _terms():
    x_hat = X_PREV + DT * RNG.normal(scale=0.05, size=(N, 3))
    return [InertiaPotential(MASS, x_hat, DT), GravityPotential(MASS, np.array([0.0, 0.3, -9.81])),
            ViscousDamping(MASS, X_PREV, 12.0, DT)]


@pytest.mark.parametrize("index", [0, 1, 2], ids=["inertia", "gravity", "damping"])
def test_gradient_and_hessian_match_finite_differences(index):
    term = _terms()[index]
    x = X_PREV + RNG.normal(scale=2e-4, size=(N, 3))
    g = term.gradient(x)
    assert relative_error(g, fd_gradient(term.energy, x, h=1e-6)) < 1e-5
    H = dense_hessian(term.hessian(x), N) if term.hessian(x).blocks.size else np.zeros((3 * N, 3 * N))
    H_fd = fd_hessian(term.gradient, x, h=1e-6)
    if np.max(np.abs(H_fd)) == 0.0:  # gravity is linear in x
        assert np.max(np.abs(H)) == 0.0
    else:
        assert relative_error(H, H_fd) < 1e-5
        assert np.min(np.linalg.eigvalsh(H)) >= 0.0
    if hasattr(term, "hessian_diagonal"):
        np.testing.assert_allclose(term.hessian_diagonal(), np.diag(H), rtol=1e-15)


def test_closed_forms_and_the_damping_parameter_derivative():
    inertia, gravity, damping = _terms()
    x = X_PREV + 1e-3
    np.testing.assert_allclose(inertia.gradient(inertia.x_hat), 0.0)  # minimum at the prediction
    np.testing.assert_allclose(gravity.gradient(x), -MASS[:, None] * gravity.gravity[None, :])
    # implicit Euler drag force -c m v with v = (x - x^n) / dt
    np.testing.assert_allclose(-damping.gradient(x), -12.0 * MASS[:, None] * (x - X_PREV) / DT)
    h = 1e-4
    up, down = (ViscousDamping(MASS, X_PREV, 12.0 + s, DT).gradient(x) for s in (h, -h))
    assert relative_error(damping.parameter_gradient(x, "damping"), (up - down) / (2 * h)) < 1e-8
    with pytest.raises(KeyError):
        damping.parameter_gradient(x, "mass_scale")


def test_invalid_values_are_named():
    with pytest.raises(ConfigError, match="damping must be finite and >= 0"):
        ViscousDamping(MASS, X_PREV, -1.0, DT)
    with pytest.raises(ConfigError, match="time step dt must be > 0"):
        InertiaPotential(MASS, X_PREV, 0.0)
    with pytest.raises(ConfigError, match="vertex masses must be finite"):
        InertiaPotential(-MASS, X_PREV, DT)
    with pytest.raises(ConfigError, match="gravity must be finite"):
        GravityPotential(MASS, np.array([0.0, np.nan, -9.81]))


def test_gravity_gradient_is_a_new_array_of_the_formula_every_call():
    """The constant gradient is computed once and copied: each call returns a new array equal, bit for
    bit, to ``-m g`` times ones of ``x``'s shape (a caller may modify its array in place)."""
    gravity = GravityPotential(MASS, np.array([0.0, 0.3, -9.81]))
    x = X_PREV + 1e-3
    reference = -MASS[:, None] * gravity.gravity[None, :] * np.ones_like(x)
    first = gravity.gradient(x)
    first += 1.0
    second = gravity.gradient(x + 0.5)
    assert second.tobytes() == reference.tobytes() and not np.shares_memory(first, second)
    assert gravity.parameter_gradient(x, "mass_scale").tobytes() == reference.tobytes()
    with pytest.raises(ValueError):  # another shape is computed for that shape (and fails to broadcast)
        gravity.gradient(np.zeros((N + 1, 3)))


def test_gravity_gradient_rows_are_the_kept_constant_and_the_step_terms_keep_their_formulas():
    """Gravity's ``gradient_rows`` (SparseGradient) is ``(None, -m g)``, the kept constant itself (equal to
    :meth:`gradient` bit for bit, not a copy); inertia and gravity energies and the inertia gradient are their
    formulas bit for bit, in the formulas' order of operations."""
    inertia, gravity, _ = _terms()
    x = X_PREV + np.random.default_rng(2).normal(scale=1e-3, size=X_PREV.shape)
    vertices, rows = gravity.gradient_rows(x)
    assert vertices is None and rows.tobytes() == gravity.gradient(x).tobytes()
    assert gravity.gradient_rows(x)[1] is rows
    d = x - inertia.x_hat
    assert inertia.energy(x) == float(0.5 / DT**2 * np.sum(MASS[:, None] * d * d))
    assert inertia.gradient(x).tobytes() == (MASS[:, None] * (x - inertia.x_hat) / DT**2).tobytes()
    assert gravity.energy(x) == float(-np.sum(MASS[:, None] * x * gravity.gravity[None, :]))
