"""The split-sample test of a fitted parameter over the recording's motion phases (sysid.split_sample)."""

from __future__ import annotations

import numpy as np
import pytest

from sysid.covariance import andrews_bandwidth, bin_scores, time_bins
from sysid.split_sample import motion_phases, split_test, split_threshold
from sysid.identifiability import NULL_SIGMAS, judge, split_verdict
from sim_core.parameter_coordinates import ParameterSpec

PHASES = [(0.0, 1.0), (1.0, 2.0), (2.0, 3.0)]
NAMES = ("a", "b")


def _problem(rng, shift_b_in_last: float = 0.0, rho: float = 0.0):
    """A linear least-squares problem over 3 s (100 residuals a 10 ms bin): two parameters, noise AR(1) ``rho`` in time;
    the second parameter's true value ``shift_b_in_last`` higher in the last phase. Returns ``J, r`` at the fit."""
    t = np.repeat(np.arange(300) * 0.01, 4)
    J = np.stack([np.sin(7.0 * t) + 1.5, np.cos(3.0 * t) * (t + 0.5)], axis=1) * 3.0
    e = rng.normal(size=300)
    n = np.empty(300)
    n[0] = e[0]
    for k in range(1, 300):
        n[k] = rho * n[k - 1] + np.sqrt(1.0 - rho ** 2) * e[k]
    noise = np.repeat(n, 4) + 0.3 * rng.normal(size=t.size)
    y = noise + J[:, 1] * shift_b_in_last * (t >= 2.0)  # data = model(u*) + noise, with b off in the last phase
    u = np.linalg.lstsq(J, y, rcond=None)[0]
    return J, J @ u - y, t, u


@pytest.mark.parametrize("rho", [0.0, 0.8])
def test_the_split_statistic_is_unit_normal_under_the_model(rho):
    """Where the data are the model plus noise (white, or correlated in time: AR(1) 0.8 a bin), each phase's ``z`` has
    standard deviation ~1 over 400 recordings, and the rule excludes one constant in about its level (the one-sided
    2.3 % of NULL_SIGMAS, family-wise): at most 6 %."""
    rng = np.random.default_rng(3)
    zs, flagged = [], 0
    for _ in range(400):
        J, r, t, _ = _problem(rng, rho=rho)
        lag = andrews_bandwidth(bin_scores(J, r, time_bins(t, 0.01)))  # as the fit's robust covariance picks it
        tests = split_test(NAMES, J, r, t, 0.01, lag, PHASES)
        zs.append([tests[n].z for n in NAMES])
        flagged += not tests["b"].stable
    zs = np.asarray(zs)
    assert np.std(zs, axis=0) == pytest.approx(np.ones((2, 3)), abs=0.2 if rho else 0.1), np.std(zs, axis=0)
    assert flagged / 400 <= 0.06, flagged


def test_a_parameter_that_moves_between_phases_is_not_one_constant():
    """The second parameter 0.3 higher in the last phase (its fit's 1-sigma ~0.04 there): the test excludes one
    constant for it (the phase's left-out estimate moves by 1/3 of the shift, many sigma), and
    :func:`split_verdict` reports it not identified with an interval that holds both phases' values."""
    rng = np.random.default_rng(5)
    J, r, t, u_hat = _problem(rng, shift_b_in_last=0.3)
    tests = split_test(NAMES, J, r, t, 0.01, 0, PHASES)
    assert not tests["b"].stable and max(abs(z) for z in tests["b"].z) > 3 * split_threshold(3)
    specs = [ParameterSpec(n, 0.0, False, -10.0, 10.0) for n in NAMES]  # u = the value
    cov = np.linalg.inv(J.T @ J)
    sig = {n: float(np.sqrt(cov[j, j])) for j, n in enumerate(NAMES)}
    values = {n: float(u_hat[j]) for j, n in enumerate(NAMES)}
    intervals = split_verdict(specs, u_hat, judge(specs, values, sig, {n: (-5.0, 5.0) for n in NAMES}), tests)
    assert not intervals["b"].identified and intervals["b"].unstable
    assert intervals["b"].upper - intervals["b"].lower > 4.0 * 2.0 * sig["b"]
    assert "NOT IDENTIFIED as one constant" in intervals["b"].words()
    assert intervals["b"].summary()["split"]["stable"] is False
    # the fit's compromise of a b that is 0 for 2 s and 0.3 for 1 s: both lie inside what is reported
    assert intervals["b"].lower < 0.0 and intervals["b"].upper > 0.3, (values, intervals["b"])


def test_split_threshold_is_the_null_level_spread_over_phases():
    """One phase: the two-sided test at half the one-sided 2.3 % tail of NULL_SIGMAS each side (2.28 sigma); the
    threshold grows with the phases (Bonferroni)."""
    from scipy.stats import norm

    assert 2.0 * norm.sf(split_threshold(1)) == pytest.approx(norm.sf(NULL_SIGMAS))
    assert split_threshold(1) < split_threshold(3) < split_threshold(6)
    assert split_threshold(0) == np.inf


def test_motion_phases_follow_the_recorded_path():
    """Approach and press (one move down), hold, lift, fold back, hold, at a 10 ms bin with 10 um pose noise: five
    phases, their boundaries within two bins of the path's."""
    rng = np.random.default_rng(0)
    t = np.arange(0.0, 3.0, 0.005)
    knots = [(0.0, (0, 0, 10e-3)), (0.6, (0, 0, 0)), (1.2, (0, 0, 0)), (1.6, (0, 0, 6e-3)), (2.2, (-8e-3, 0, 6e-3)),
             (3.0, (-8e-3, 0, 6e-3))]
    kt = np.array([k for k, _ in knots])
    kp = np.array([p for _, p in knots], dtype=float)
    path = np.stack([np.interp(t, kt, kp[:, a]) for a in range(3)], axis=1) + rng.normal(0.0, 1e-5, (t.size, 3))
    phases = motion_phases(t, path, 0.01)
    starts = [a for a, _ in phases]
    assert len(phases) == 5, phases
    for got, want in zip(starts[1:], (0.6, 1.2, 1.6, 2.2)):
        assert abs(got - want) <= 0.025, phases
    assert phases[0][0] == 0.0 and phases[-1][1] >= t[-1]
