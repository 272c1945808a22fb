"""Gauss-Newton on Broyden-updated secant columns (sysid.secant): known linear and nonlinear answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sysid.secant import secant_least_squares


def _counting(fun):
    calls = []

    def residual(u):
        calls.append(np.array(u, dtype=float))
        return fun(u)

    return residual, calls


def test_a_linear_model_is_solved_by_its_probes_and_one_step():
    """For r(u) = A u - b the probe secants are the exact columns, so the first Gauss-Newton step lands
    on the least-squares solution: p probes + 1 step, whatever the probe sizes."""
    rng = np.random.default_rng(0)
    A, b = rng.normal(size=(40, 3)), rng.normal(size=40)
    truth, *_ = np.linalg.lstsq(A, b, rcond=None)
    residual, calls = _counting(lambda u: A @ u - b)
    u0 = np.zeros(3)
    out = secant_least_squares(residual, u0, residual(u0), np.array([0.3, -2.0, 0.01]), np.full(3, -1e3),
                               np.full(3, 1e3), max_evals=4)
    assert len(calls) == 1 + 4 and out.evaluations == 4
    np.testing.assert_allclose(out.u, truth, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(out.jacobian, A, rtol=1e-9, atol=1e-12)
    assert out.cost == pytest.approx(0.5 * float((A @ truth - b) @ (A @ truth - b)))
    assert out.cost_initial == pytest.approx(0.5 * float(b @ b))


def test_broyden_steps_converge_on_a_nonlinear_one_parameter_model():
    """r(u) = w (exp(u) - 0.2) (the residual of a scale searched in log space, optimum log 0.2): from
    u = 0 with a probe of log(1/3) and steps capped at that size, the secant iteration (superlinear)
    reaches the optimum within 1e-8 in at most 8 evaluations and stops there on its step tolerance."""
    w = np.array([1.0, 2.0, -0.5])
    out = secant_least_squares(lambda u: w * (math.exp(u[0]) - 0.2), np.zeros(1), w * 0.8,
                               np.array([math.log(1 / 3)]), np.array([math.log(0.01)]), np.array([math.log(10.0)]),
                               max_evals=12, max_step=np.array([math.log(3.0)]), xtol=1e-9)
    assert out.u[0] == pytest.approx(math.log(0.2), abs=1e-8)
    assert out.status == "converged" and out.evaluations <= 8
    assert min(c for _, c in out.history) == out.cost < 1e-12 * out.cost_initial


def test_bounds_hold_and_a_failed_evaluation_counts_without_breaking_the_search():
    """The optimum (u = 2) lies beyond the upper bound 1: the search ends on the bound. A residual that
    fails (None) past u = 1.5 would only cost its evaluation."""
    def fun(u):
        return None if u[0] > 1.5 else np.array([u[0] - 2.0, 0.5 * (u[0] - 2.0)])

    out = secant_least_squares(fun, np.zeros(1), fun(np.zeros(1)), np.array([0.5]), np.array([-1.0]),
                               np.array([1.0]), max_evals=4)
    assert out.u[0] == pytest.approx(1.0) and out.status == "converged"
    # a probe that fails leaves the start, and says why
    out = secant_least_squares(fun, np.zeros(1), fun(np.zeros(1)), np.array([1.8]), np.array([-1.0]),
                               np.array([3.0]), max_evals=3)
    assert out.status == "no_columns" and out.u[0] == 0.0 and out.evaluations == 1


def test_a_budget_below_the_probe_count_leaves_the_start_and_bad_input_is_refused():
    residual, calls = _counting(lambda u: u - 1.0)
    out = secant_least_squares(residual, np.zeros(2), np.full(2, -1.0), np.ones(2), np.full(2, -5.0),
                               np.full(2, 5.0), max_evals=1)
    assert not calls and out.evaluations == 0 and np.all(out.u == 0.0)
    with pytest.raises(ValueError, match="nonzero"):
        secant_least_squares(residual, np.zeros(1), np.ones(1), np.zeros(1), -np.ones(1), np.ones(1), 2)
    with pytest.raises(ValueError, match="outside the bounds"):
        secant_least_squares(residual, np.full(1, 3.0), np.ones(1), np.ones(1), -np.ones(1), np.ones(1), 2)
