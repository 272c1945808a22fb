"""Sheet damping candidate: derivatives, sheet-only support, routing through the hook."""

import numpy as np
import pytest

from sim_core.candidates import CandidateHook, SheetDamping
from sim_core.errors import ConfigError
from tests.support.fd import dense_hessian, fd_gradient, fd_hessian, relative_error


def _term(beta=3.0):
    rng = np.random.default_rng(0)
    mass = rng.uniform(0.5, 2.0, 6)
    x_prev = rng.normal(size=(6, 3))
    return SheetDamping(np.array([1, 3, 4]), mass, x_prev, beta, 0.01), x_prev, rng


def test_gradient_and_hessian_match_finite_differences():
    term, x_prev, rng = _term()
    x = x_prev + 1e-3 * rng.normal(size=x_prev.shape)
    g = term.gradient(x)
    assert relative_error(g, fd_gradient(term.energy, x, h=1e-6)) < 1e-5
    H = dense_hessian(term.hessian(x), x.shape[0])
    assert relative_error(H, fd_hessian(term.gradient, x, h=1e-6)) < 1e-5
    assert np.linalg.eigvalsh(H).min() >= 0.0
    blocks = term.hessian(x).blocks
    assert blocks.shape == (3, 3, 3)
    np.testing.assert_allclose(blocks[:, 0, 0] * (x[[1, 3, 4], 0] - x_prev[[1, 3, 4], 0]), g[[1, 3, 4], 0])


def test_only_the_given_vertices_are_damped_and_parameter_gradient_is_linear():
    term, x_prev, rng = _term(beta=2.0)
    x = x_prev + rng.normal(size=x_prev.shape)
    g = term.gradient(x)
    assert np.all(g[[0, 2, 5]] == 0.0)
    np.testing.assert_allclose(term.parameter_gradient(x, "beta") * 2.0, g)
    with pytest.raises(KeyError):
        term.parameter_gradient(x, "damping")


def test_invalid_values_raise():
    with pytest.raises(ConfigError):
        SheetDamping(np.array([0]), np.ones(1), np.zeros((1, 3)), -1.0, 0.01)
    with pytest.raises(ConfigError):
        CandidateHook({"damping": -2.0})


def test_hook_builds_the_term_only_when_set():
    class Body:
        def __init__(self, kind, vertices):
            self.kind, self.vertices = kind, np.asarray(vertices)

    class Model:
        bodies = {"sheet": Body("sheet", [0, 1]), "gel": Body("solid", [2, 3])}

        def vertex_mass(self):
            return np.ones(4)

    x_prev = np.zeros((4, 3))
    assert CandidateHook({}).damping_terms(Model(), x_prev, 0.01) == []
    (term,) = CandidateHook({"damping": 5.0}).damping_terms(Model(), x_prev, 0.01)
    assert term.ids.tolist() == [0, 1]
