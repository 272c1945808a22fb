"""Robust covariance of a least-squares fit (sysid.covariance) against statsmodels and by simulation."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.errors import CalibrationError, ConfigError
from sysid.covariance import (andrews_bandwidth, bin_scores, block_bootstrap_covariance, hac_covariance, nuisance_covariance,
                              residual_times_s, robust_covariance, time_bins)


def _ar1(rng: np.random.Generator, n: int, rho: float) -> np.ndarray:
    e = rng.standard_normal(n)
    out = np.empty(n)
    out[0] = e[0] / np.sqrt(1.0 - rho ** 2)
    for i in range(1, n):
        out[i] = rho * out[i - 1] + e[i]
    return out


def _regression(rng: np.random.Generator, n: int = 400, rho: float = 0.8):
    """Linear regression y = X b + e with AR(1) regressors and errors; X plays the whitened Jacobian."""
    X = np.column_stack([np.ones(n), _ar1(rng, n, 0.7), _ar1(rng, n, 0.5)])
    y = X @ np.array([1.0, -0.5, 2.0]) + _ar1(rng, n, rho)
    b = np.linalg.lstsq(X, y, rcond=None)[0]
    return X, y - X @ b, b


@pytest.mark.parametrize("lag", [0, 3, 12])
def test_hac_equals_statsmodels_newey_west(lag: int) -> None:
    """One residual per time bin: the sandwich is statsmodels' HAC (Bartlett kernel, no small-sample
    correction) to round-off, for a fixed lag window."""
    sm = pytest.importorskip("statsmodels.api")
    X, r, _ = _regression(np.random.default_rng(1))
    t = np.arange(X.shape[0]) * 0.01
    ours = hac_covariance(-X, r, t, bin_s=0.01, lag=lag)  # J = dr/db = -X: the sign cancels in the sandwich
    ref = sm.OLS(X @ np.zeros(3) + r, X).fit(cov_type="HAC", cov_kwds={"maxlags": lag, "use_correction": False})
    np.testing.assert_allclose(ours.covariance_u, ref.cov_params(), rtol=1e-10, atol=1e-14)
    assert ours.lag_bins == lag and ours.bins == X.shape[0]


def test_hac_lag_zero_is_white_sandwich_and_iid_unit_noise_gives_formal_sigma() -> None:
    """With white unit-variance residuals the sandwich is (J^T J)^-1 within its sampling error (~1/sqrt(T))."""
    rng = np.random.default_rng(2)
    n = 4000
    J = rng.standard_normal((n, 2))
    r = rng.standard_normal(n)
    r -= J @ np.linalg.lstsq(J, r, rcond=None)[0]
    cov = hac_covariance(J, r, np.arange(n) * 0.01, 0.01)
    assert cov.lag_bins <= 3  # Andrews' window of white scores is short
    np.testing.assert_allclose(cov.inflation, 1.0, atol=0.08)


def test_scores_of_several_residuals_per_bin_are_summed() -> None:
    """Residuals sharing a time bin (the axes of one sample, or two channels' samples) form one score."""
    J = np.array([[1.0, 0.0], [0.0, 2.0], [1.0, 1.0]])
    r = np.array([2.0, 3.0, -1.0])
    g = bin_scores(J, r, np.array([0, 0, 2]))
    np.testing.assert_allclose(g, [[2.0, 6.0], [0.0, 0.0], [-1.0, -1.0]])


def test_times_of_a_multirate_residual_vector() -> None:
    """A channel of 3 axes at 100 Hz beside one of 2 axes at 200 Hz: each element gets its sample's time."""
    stamps = {"a": np.array([0, 10_000_000]), "b": np.array([0, 5_000_000, 10_000_000])}
    t = residual_times_s(stamps, {"a": 6, "b": 6}, ["a", "b"])
    np.testing.assert_allclose(t, [0, 0, 0, 0.01, 0.01, 0.01, 0, 0, 0.005, 0.005, 0.01, 0.01])
    np.testing.assert_array_equal(time_bins(t, 0.01), [0, 0, 0, 1, 1, 1, 0, 0, 0, 0, 1, 1])
    with pytest.raises(CalibrationError, match="channel a: 5 residuals"):
        residual_times_s(stamps, {"a": 5, "b": 6}, ["a", "b"])


def test_robust_sigma_covers_under_ar1_errors_where_the_formal_one_does_not() -> None:
    """Monte Carlo: regression with strongly correlated errors (rho = 0.9). The formal 2-sigma interval of
    the slope covers the truth far less than 95 %; the HAC and block-bootstrap ones come close to it."""
    rng = np.random.default_rng(3)
    n, truth = 500, 2.0
    hits = {"formal": 0, "hac": 0, "block_bootstrap": 0}
    trials = 150
    for k in range(trials):
        x = _ar1(rng, n, 0.9)
        X = np.column_stack([np.ones(n), x])
        y = X @ np.array([0.0, truth]) + _ar1(rng, n, 0.9)
        b = np.linalg.lstsq(X, y, rcond=None)[0]
        r = y - X @ b
        s2 = r @ r / (n - 2)
        t = np.arange(n) * 0.01
        J = -X / np.sqrt(s2)  # whiten by the residual level, as the fit whitens by the noise level
        sig = {"formal": np.sqrt(np.linalg.inv(J.T @ J)[1, 1]),
               "hac": np.sqrt(robust_covariance("hac", J, r / np.sqrt(s2), t, 0.01).covariance_u[1, 1]),
               "block_bootstrap": np.sqrt(robust_covariance("block_bootstrap", J, r / np.sqrt(s2), t, 0.01,
                                                            seed=k).covariance_u[1, 1])}
        for name, s in sig.items():
            hits[name] += abs(b[1] - truth) <= 2.0 * s
    cover = {k: v / trials for k, v in hits.items()}
    assert cover["formal"] < 0.75, cover
    assert cover["hac"] > 0.85, cover
    assert cover["block_bootstrap"] > 0.85, cover


def test_bootstrap_agrees_with_hac_on_correlated_scores() -> None:
    """Both estimate the same long-run variance: within the bootstrap's and the kernel's differences (30 %)."""
    X, r, _ = _regression(np.random.default_rng(4), n=3000, rho=0.8)
    t = np.arange(X.shape[0]) * 0.005
    hac = hac_covariance(-X, r, t, 0.005)
    boot = block_bootstrap_covariance(-X, r, t, 0.005, seed=1)
    np.testing.assert_allclose(np.sqrt(np.diag(boot.covariance_u)), np.sqrt(np.diag(hac.covariance_u)), rtol=0.3)
    assert hac.lag_bins > 3  # correlated scores widen Andrews' window
    assert boot.lag_bins == hac.lag_bins


def test_andrews_window_grows_with_correlation() -> None:
    rng = np.random.default_rng(5)
    lags = [andrews_bandwidth(_ar1(rng, 2000, rho)[:, None]) for rho in (0.0, 0.5, 0.9)]
    assert lags[0] < lags[1] < lags[2]


def test_errors_name_what_failed() -> None:
    J = np.ones((10, 2))
    with pytest.raises(CalibrationError, match="singular"):
        hac_covariance(J, np.ones(10), np.arange(10.0), 1.0)
    with pytest.raises(ConfigError, match="unknown robust covariance method 'jackknife'"):
        robust_covariance("jackknife", np.eye(3), np.ones(3), np.arange(3.0), 1.0)
    with pytest.raises(CalibrationError, match="bin width"):
        time_bins(np.arange(3.0), 0.0)


def test_nuisance_shift_is_exact_for_a_linear_model_and_its_covariance_is_the_propagated_prior() -> None:
    """y = X b + z phi with phi held at a wrong value: the fitted b moves by exactly A (phi_held - phi_true),
    A = -(X^T X)^-1 X^T J_phi with J_phi = dr/dphi = -z; the prior 1-sigma s gives Cov = A s^2 A^T."""
    rng = np.random.default_rng(6)
    n = 200
    X = np.column_stack([np.ones(n), rng.standard_normal(n)])
    z = np.sin(np.linspace(0.0, 3.0, n)) + 0.3 * rng.standard_normal(n)
    b_true, phi_true, phi_held = np.array([1.0, 2.0]), 0.7, 0.2
    y = X @ b_true + z * phi_true
    b_fit = np.linalg.lstsq(X, y - z * phi_held, rcond=None)[0]
    cov, A = nuisance_covariance(-X, -z[:, None], np.array([0.25]))
    np.testing.assert_allclose(b_fit - b_true, -A[:, 0] * (phi_true - phi_held), rtol=1e-10)
    np.testing.assert_allclose(cov, np.outer(A[:, 0], A[:, 0]) * 0.25 ** 2, rtol=1e-12)
    with pytest.raises(CalibrationError, match="nuisance Jacobian"):
        nuisance_covariance(-X, -z[:, None], np.array([0.25, 0.1]))


def test_a_positive_parameter_whose_robust_interval_reaches_zero_is_held_by_the_search() -> None:
    """The fit's search rule (``hold_unidentified``): ``value - 2 sigma_robust <= 0`` marks a log-coordinate
    parameter; a linear one (an offset, which may be negative) is never judged, and nothing is without a robust
    sigma. What a fit reports is judged by sysid.identifiability (tests/sysid/test_identifiability.py)."""
    from sim_core.parameter_coordinates import ParameterSpec
    from sysid.covariance import not_identified

    specs = [ParameterSpec("a", 1.0, True, 1e-3, 1e3), ParameterSpec("b", 1.0, True, 1e-3, 1e3),
             ParameterSpec("c", 0.0, False, -1.0, 1.0)]
    values = {"a": 0.1, "b": 2.0, "c": 0.01}
    assert not_identified(specs, values, {"a": 0.05, "b": 0.99, "c": 1.0}) == ("a",)   # 0.1 - 0.1 reaches 0
    assert not_identified(specs, values, {"a": 0.049, "b": 1.0, "c": 1.0}) == ("b",)
    assert not_identified(specs, values, None) == ()


def test_the_reported_robust_covariance_is_no_better_than_the_white_noise_allows() -> None:
    """A sandwich below the Gauss-Newton covariance (scores that cancel: few bins, a long window) is floored at it,
    combination by combination; one above it is kept."""
    rng = np.random.default_rng(4)
    J = rng.standard_normal((200, 2))
    t = np.arange(200) * 0.01
    H_inv = np.linalg.inv(J.T @ J)
    low = hac_covariance(J, 0.2 * rng.standard_normal(200), t, 0.01)
    high = hac_covariance(J, 3.0 * rng.standard_normal(200), t, 0.01)
    assert np.all(low.inflation < 1.0) and np.all(high.inflation > 1.0)
    floored = low.floored(J)
    assert np.all(np.linalg.eigvalsh(floored.covariance_u - H_inv) > -1e-12 * np.abs(H_inv).max())
    assert floored.inflation == pytest.approx(np.ones(2), rel=1e-9)
    assert high.floored(J).covariance_u == pytest.approx(high.covariance_u, rel=1e-9)
