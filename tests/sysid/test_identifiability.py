"""Whether a recording identifies a fitted parameter (sysid.identifiability): the cost's profile against the null.

Known answers: for residuals linear in the parameters the profile statistic at the robust 2-sigma end is exactly the
threshold (the rule is the HAC interval there); a parameter the residual does not see is reported NOT IDENTIFIED with
its prior range; a parameter whose cost flattens past a threshold (a friction above stick: the tangent at the fit sees
a slope the cost does not keep) is identified by the linearised rule and not by its replayed profile, whose interval
then reaches the prior's bound on the flat side and covers the truth. And through ``sysid.fit.fit`` on this
simulator's own press recording: the gel modulus identified with its interval covering the truth, the gel-card
friction (a press without a slide barely loads it) with an interval several times as wide, holding the truth.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from sim_core.errors import CalibrationError
from sim_core.parameter_coordinates import ParameterSpec
from sysid.covariance import hac_covariance
from sysid.identifiability import (NULL_SIGMAS, judge, not_identified_note, prior_ranges, profile_direction,
                                   profile_intervals, profile_z)

DT = 0.01


def _ar1(rng: np.random.Generator, n: int, rho: float = 0.5) -> np.ndarray:
    x = np.zeros(n)
    w = rng.standard_normal(n)
    for i in range(1, n):
        x[i] = rho * x[i - 1] + w[i]
    return x


class _Problem:
    """A two-parameter regression ``y = a x1 + s(b) x2 + AR(1) noise`` in linear coordinates, fitted by Gauss-Newton."""

    def __init__(self, seed: int, s=lambda b: b, ds=lambda b: np.ones_like(b), gain2: float = 1.0, truth=(1.0, 0.8)):
        rng = np.random.default_rng(seed)
        self.m = 800
        self.t = np.arange(self.m) * DT
        self.x1 = np.sin(3.0 * self.t) + 0.2
        self.x2 = gain2 * (np.cos(1.3 * self.t) + 0.3 * self.t)
        self.s, self.ds = s, ds
        self.truth = truth
        self.y = self.model(np.asarray(truth, dtype=float)) + _ar1(rng, self.m)  # whitened: at least unit noise
        self.specs = [ParameterSpec("a", 0.0, False, -10.0, 10.0, 1.0), ParameterSpec("b", 0.0, False, -3.0, 3.0, 1.0)]

    def model(self, u: np.ndarray) -> np.ndarray:
        return u[0] * self.x1 + self.s(u[1]) * self.x2

    def residual(self, u: np.ndarray) -> np.ndarray:
        return self.model(np.asarray(u, dtype=float)) - self.y

    def jacobian(self, u: np.ndarray) -> np.ndarray:
        return np.stack([self.x1, self.ds(u[1]) * self.x2], axis=1)

    def fit(self, u0=(0.5, 0.5)) -> np.ndarray:
        u = np.asarray(u0, dtype=float)
        for _ in range(50):
            J, r = self.jacobian(u), self.residual(u)
            step = np.linalg.lstsq(J, -r, rcond=None)[0]
            u = u + step
            if np.max(np.abs(step)) < 1e-12:
                break
        return u

    def judged(self, prior, replays: int):
        u = self.fit()
        J, e = self.jacobian(u), self.residual(u)
        rob = hac_covariance(J, e, self.t, DT)
        values = {s.name: s.to_value(float(x)) for s, x in zip(self.specs, u)}
        sigma = {s.name: float(np.sqrt(rob.covariance_u[k, k])) * s.scale for k, s in enumerate(self.specs)}
        linear = judge(self.specs, values, sigma, prior)
        calls = []

        def residual(x):
            calls.append(np.array(x))
            return self.residual(x)

        return u, linear, profile_intervals(residual, self.specs, u, J, e, rob, linear, self.t, DT, replays), calls


def test_for_a_linear_residual_the_profile_statistic_at_the_robust_two_sigma_end_is_the_threshold():
    p = _Problem(seed=3)
    u = p.fit()
    J, e = p.jacobian(u), p.residual(u)
    rob = hac_covariance(J, e, p.t, DT)
    for j in range(2):
        s = math.sqrt(rob.covariance_u[j, j])
        v = profile_direction(J, j)
        assert v[j] == 1.0
        for sign in (-1.0, 1.0):
            z, dcost = profile_z(p.residual(u + sign * 2.0 * s * v), e, np.delete(J, j, axis=1), p.t, DT,
                                 rob.lag_bins)
            assert z == pytest.approx(NULL_SIGMAS, rel=1e-9)
            assert dcost > 0.0


def test_an_identified_parameter_keeps_its_robust_interval_and_it_covers_the_truth():
    """Linear residuals: the replayed profile closes each side at the first point, so the interval is the robust one,
    identified, and over 60 noise draws it covers the truth about as often as the HAC interval does with 800 AR(1)
    samples (at least 85 % asserted)."""
    prior = {"a": (1.0 / 3.0, 3.0), "b": (0.8 / 3.0, 2.4)}
    hits = 0
    for seed in range(60):
        p = _Problem(seed)
        u, linear, out, calls = p.judged(prior, replays=2)
        for name, truth in zip(("a", "b"), p.truth):
            iv = out[name]
            assert iv.identified and iv.source == "profile" and len(iv.points) == 2
            assert iv.lower == pytest.approx(linear[name].lower) and iv.upper == pytest.approx(linear[name].upper)
            hits += iv.lower <= truth <= iv.upper
        assert len(calls) == 4
    assert hits >= 0.85 * 120, hits


def test_a_parameter_the_residual_does_not_see_is_not_identified_and_reported_with_its_prior_range():
    prior = {"a": (0.0, 3.0), "b": (0.1, 2.4)}
    p = _Problem(seed=1, gain2=1e-6)
    u, linear, out, calls = p.judged(prior, replays=2)
    assert not out["b"].identified and out["b"].open_below and out["b"].open_above
    assert (out["b"].lower, out["b"].upper) == prior["b"]
    assert out["a"].identified and out["a"].lower <= p.truth[0] <= out["a"].upper
    assert len(calls) == 2  # only the identified parameter's profile is replayed
    note = not_identified_note(out["b"])
    assert note.startswith("b is not identified by this recording") and "prior range [0.1, 2.4]" in note


def test_a_parameter_whose_cost_flattens_past_a_threshold_is_not_identified_on_the_flat_side():
    """``s(b) = min(b, 0.83)``, smoothed over 0.01: the truth 0.8 just below the threshold, as a friction just below
    the stick threshold of a contact that a larger friction holds as well. The tangent at the fit sees the full slope,
    so the robust sigma is tight and the linearised rule identifies ``b``; above the threshold the cost no longer
    changes, the replayed profile stays within the null's spread up to the prior's bound, and ``b`` is reported NOT
    IDENTIFIED, open above, its interval from the closed lower side to the prior's bound, covering the truth."""
    knee, width = 0.83, 0.01

    def s(b):
        return knee - width * np.logaddexp(0.0, (knee - b) / width)

    def ds(b):
        return 1.0 / (1.0 + np.exp(-(knee - b) / width))

    prior = {"a": (1.0 / 3.0, 3.0), "b": (0.27, 2.4)}
    for seed in (0, 1):  # fits that land below the threshold (where the tangent is steep)
        p = _Problem(seed, s=s, ds=ds)
        u, linear, out, calls = p.judged(prior, replays=3)
        b = out["b"]
        assert u[1] < knee and linear["b"].identified and linear["b"].upper < 1.0, linear["b"]
        assert not b.identified and b.open_above and not b.open_below, b
        assert b.upper == prior["b"][1] and b.lower == pytest.approx(linear["b"].lower)
        assert b.lower <= p.truth[1] <= b.upper
        above = [pt for pt in b.points if pt.delta_u > 0]
        assert len(above) == 3 and above[-1].value == pytest.approx(prior["b"][1])  # the side's last replay
        assert all(pt.z < NULL_SIGMAS for pt in above)
        assert out["a"].identified


def test_prior_ranges_are_a_data_sheets_and_bad_ones_are_named():
    table = {"gel.youngs_modulus": ("factor", 1.0 / 3.0, 3.0), "gel.poisson_ratio": ("absolute", 0.3, 0.499),
             "sensor.normal_offset": ("offset", -5e-4, 5e-4), "bad": ("ratio", 1.0, 2.0)}
    got = prior_ranges({"gel.youngs_modulus": 3e5, "gel.poisson_ratio": 0.45, "sensor.normal_offset": 0.0,
                        "other": 1.0}, {k: v for k, v in table.items() if k != "bad"})
    assert got == {"gel.youngs_modulus": pytest.approx((1e5, 9e5)), "gel.poisson_ratio": (0.3, 0.499),
                   "sensor.normal_offset": (-5e-4, 5e-4)}
    with pytest.raises(CalibrationError, match="bad: unknown kind"):
        prior_ranges({"bad": 1.0}, table)
    with pytest.raises(CalibrationError, match="does not contain its start"):
        prior_ranges({"gel.poisson_ratio": 0.2}, table)


@pytest.fixture(scope="module")
def press_bag(tmp_path_factory):
    from tests.sysid.simbag import PRESS_ONLY, make_recording

    return make_recording(tmp_path_factory.mktemp("press") / "bag", segments=PRESS_ONLY, seed=1)


def test_a_press_identifies_the_gel_modulus_and_gives_the_friction_it_barely_loads_a_wide_interval(press_bag):
    from sysid.calibration import CALIBRATION_BOUNDS
    from sysid.evidence import load_evidence
    from sysid.fit import DEFAULT_NUISANCE, fit
    from sysid.observation import ObservationModel
    from tests.sysid.simbag import TRUE_PARAMS

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = ObservationModel(load_evidence(press_bag), dt=DT)
    names = ("gel.youngs_modulus", "friction.gel_sheet")
    start = {n: 1.3 * TRUE_PARAMS[n] for n in names}
    result = fit(model, names, initial=start, jacobian="fd", robust="hac",
                 prior=prior_ranges(start, CALIBRATION_BOUNDS), profile_replays=2)
    E, mu = (result.intervals[n] for n in names)
    assert E.identified and E.lower <= TRUE_PARAMS["gel.youngs_modulus"] <= E.upper, E
    assert E.source == "profile" and len(E.points) >= 2
    assert mu.prior == pytest.approx((0.8 * 1.3 / 3, 0.8 * 1.3 * 3))
    # a press without a slide barely loads the friction: its robust 2-sigma reaches the prior's lower bound, and the
    # replayed profile (the others re-fitted) decides each side: the interval holds the truth, several times as wide
    # (relative) as the modulus'
    assert mu.lower <= TRUE_PARAMS["friction.gel_sheet"] <= mu.upper, mu
    assert mu.source == "profile" and result.intervals["friction.gel_sheet"].points
    assert (mu.upper - mu.lower) / mu.value > 3.0 * (E.upper - E.lower) / E.value
    assert result.profile_runs == sum(len(iv.points) for iv in result.intervals.values())
    # with the nuisance priors (the contact's stiffness, the gel's Poisson ratio) the modulus of four pressed steps is
    # no longer separated from the contact's compliance: its interval widens with them, and still holds the truth
    wide = fit(model, names, initial=start, jacobian="fd", robust="hac", nuisance=DEFAULT_NUISANCE,
               prior=prior_ranges(start, CALIBRATION_BOUNDS), profile_replays=1)
    assert wide.robust.method == "hac+nuisance"
    for name in names:
        iv = wide.intervals[name]
        assert iv.lower <= min(result.intervals[name].lower, TRUE_PARAMS[name]), (name, iv)
        assert iv.upper >= TRUE_PARAMS[name], (name, iv)



def test_a_fit_that_stopped_short_of_the_minimum_is_named_by_a_cheaper_profile_point():
    """A fit left 3 robust sigma short of the minimum in ``a``: the profile point toward the minimum costs less than
    the fit, which the warning says (the value is where the fit stopped)."""
    from sysid.identifiability import lower_cost_note

    p = _Problem(seed=2)
    u = p.fit()
    J0, e0 = p.jacobian(u), p.residual(u)
    s_a = math.sqrt(hac_covariance(J0, e0, p.t, DT).covariance_u[0, 0])
    u_short = u - np.array([3.0 * s_a, 0.0])
    J, e = p.jacobian(u_short), p.residual(u_short)
    rob = hac_covariance(J, e, p.t, DT)
    values = {s.name: s.to_value(float(x)) for s, x in zip(p.specs, u_short)}
    sigma = {s.name: float(np.sqrt(rob.covariance_u[k, k])) for k, s in enumerate(p.specs)}
    prior = {"a": (1.0 / 3.0, 3.0), "b": (0.8 / 3.0, 2.4)}
    out = profile_intervals(p.residual, p.specs, u_short, J, e, rob, judge(p.specs, values, sigma, prior), p.t, DT, 2)
    note = lower_cost_note(out["a"])
    assert note is not None and note.startswith("a: a point of its profile at")
    assert lower_cost_note(judge(p.specs, values, sigma, prior)["a"]) is None  # no replayed point, nothing claimed


def test_a_nuisance_part_wider_than_the_prior_opens_the_side_without_overflow():
    """The propagated nuisance priors' part of a parameter can exceed its whole prior range (a near-zero column makes
    ``A = -(J^T J)^-1 J^T J_phi`` large): the side is then open, its end the prior's bound (a log parameter's width of
    1e4 search units once overflowed ``exp``)."""
    from sysid.covariance import RobustCovariance

    p = _Problem(seed=0)
    p.specs = [ParameterSpec("a", 1.0, True, 1e-3, 1e3), ParameterSpec("b", 0.0, False, -3.0, 3.0, 1.0)]
    u = p.fit()  # a's log coordinate: the model is linear in u, the value exp(u)
    J, e = p.jacobian(u), p.residual(u)
    rob = hac_covariance(J, e, p.t, DT)
    big = RobustCovariance("hac+nuisance", rob.covariance_u + np.diag([1e8, 0.0]), rob.lag_bins, rob.bin_s, rob.bins,
                           rob.inflation, 0, rob.covariance_u, {"phi": 1.0}, {"phi": np.zeros(2)})
    values = {s.name: s.to_value(float(x)) for s, x in zip(p.specs, u)}
    sigma = {s.name: float(np.sqrt(big.covariance_u[k, k])) * (values[s.name] if s.log else 1.0)
             for k, s in enumerate(p.specs)}
    prior = {"a": (values["a"] / 3.0, values["a"] * 3.0), "b": (0.8 / 3.0, 2.4)}
    out = profile_intervals(p.residual, p.specs, u, J, e, big, judge(p.specs, values, sigma, prior), p.t, DT, 2)
    assert out["a"].open_below and out["a"].open_above and (out["a"].lower, out["a"].upper) == pytest.approx(prior["a"])
    assert out["b"].identified


def test_a_gel_law_the_recording_does_not_part_from_the_other_widens_the_values_it_moves():
    """Where the other gel law fitted better but within the null's spread (not decided), a value that law puts
    outside the chosen law's interval is not identified apart from the law, its interval widened to hold the other
    law's value with the same relative half-widths; a decided choice, or a value inside, changes nothing."""
    from sysid.identifiability import Interval, law_verdict

    def iv(name, value, lo, hi):
        return Interval(name, value, lo, hi, (value / 3.0, value * 3.0), True, False, False)

    intervals = {"gel.youngs_modulus": iv("gel.youngs_modulus", 2.2e5, 1.65e5, 2.79e5),
                 "friction.gel_sheet": iv("friction.gel_sheet", 0.75, 0.65, 0.85)}
    fitted = {"stable_neohookean": {"gel.youngs_modulus": 2.7e5, "friction.gel_sheet": 0.78},
              "green_strain": {"gel.youngs_modulus": 2.94e5, "friction.gel_sheet": 0.79}}
    out = law_verdict(intervals, "stable_neohookean", "green_strain", False, fitted)
    modulus = out["gel.youngs_modulus"]
    assert not modulus.identified and modulus.law["other_value"] == 2.94e5
    assert modulus.lower == 1.65e5 and modulus.upper == pytest.approx(2.94e5 * 2.79 / 2.2)
    assert modulus.lower < 2.94e5 < modulus.upper and "apart from the gel's law" in modulus.words()
    assert modulus.summary()["law"]["other"] == "green_strain"
    assert out["friction.gel_sheet"] is intervals["friction.gel_sheet"]  # 0.79 inside [0.65, 0.85]
    assert law_verdict(intervals, "stable_neohookean", "green_strain", True, fitted) == intervals
