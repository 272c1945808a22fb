"""Fitting: parameter recovery from recordings of this project's simulator, covariance, Jacobians."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from sim_core.errors import CalibrationError, ConfigError
from sysid.evidence import load_evidence
from sysid.fit import (
    FiniteDifferenceJacobian,
    FitProblem,
    SensitivityJacobian,
    _nuisance_jacobian,
    first_region_scale,
    fit,
    gauss_newton_covariance,
    gauss_newton_step,
    make_jacobian,
    parameter_spec,
)
from sim_core.parameter_coordinates import LOG_SPAN
from sysid.fit_region import held_jacobian
from sysid.observation import ObservationModel, ObservationWarning
from tests.sysid.simbag import DT, PRESS_ONLY, PRESS_SLIDE, TRUE_PARAMS, make_recording


@pytest.fixture(scope="module")
def press_bag(tmp_path_factory):
    """A short noisy press recording (5 steps of 10 ms) made with the true parameters."""
    return make_recording(tmp_path_factory.mktemp("press") / "bag", segments=PRESS_ONLY, seed=1)


# ------------------------------------------------------------------------------------ recovery
def test_recovers_gel_modulus_from_x3_start(press_bag):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = ObservationModel(load_evidence(press_bag), dt=DT)
    true = TRUE_PARAMS["gel.youngs_modulus"]
    result = fit(model, ["gel.youngs_modulus"], initial={"gel.youngs_modulus": 3.0 * true}, jacobian="fd")
    value = result.values["gel.youngs_modulus"]
    assert abs(value / true - 1.0) < 0.05, value
    assert result.status == "converged"
    # white-noise level reached: reduced chi^2 about 1 after, far above before
    m = result.residual_count - 1
    assert result.reduced_chi2 < 1.5 < 2.0 * result.cost_initial / m
    # the fitted model explains the force to about its noise level; the x3 start did not
    assert result.rms_final["wrench"]["rms"] < 0.3 < result.rms_initial["wrench"]["rms"]
    assert result.rms_final["wrench"]["whitened_rms"] < 2.0
    # Gauss-Newton 1-sigma: finite, and the truth lies within 3 sigma
    sigma = result.sigma["gel.youngs_modulus"]
    assert 0.0 < sigma < 0.2 * true and abs(value - true) < 3.0 * max(sigma, 1e-3 * true)
    assert result.correlation.shape == (1, 1) and result.correlation[0, 0] == pytest.approx(1.0)
    assert result.channels == ("markers_xyz", "wrench", "sheet_points")
    costs = [e.cost for e in result.history if e.phase in ("initial", "local")]
    assert min(costs) == pytest.approx(result.cost_final)


@pytest.mark.slow
@pytest.mark.timeout(3600)
def test_recovers_three_parameters_from_poor_start(tmp_path):
    bag = make_recording(tmp_path / "bag", segments=PRESS_SLIDE, seed=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = ObservationModel(load_evidence(bag), dt=DT)
    names = ["sheet.bending_stiffness", "gel.youngs_modulus", "friction.gel_sheet"]
    start = {n: TRUE_PARAMS[n] * f for n, f in zip(names, (3.0, 0.3, 3.0))}
    result = fit(model, names, initial=start, jacobian="auto", max_nfev=40)
    for n in names:
        assert abs(result.values[n] / TRUE_PARAMS[n] - 1.0) < 0.05, (n, result.values[n])
    assert result.correlation.shape == (3, 3)
    assert np.allclose(np.diag(result.correlation), 1.0)


# ------------------------------------------------------------------------------------ pieces
def test_log_coordinates_round_trip_and_bounds():
    spec = parameter_spec("gel.youngs_modulus", 3.0e5)
    assert spec.log and spec.to_u(3.0e5) == 0.0
    assert spec.to_value(math.log(2.0)) == pytest.approx(6.0e5)
    lo, hi = spec.u_bounds
    assert lo == pytest.approx(-math.log(1e3)) and hi == pytest.approx(math.log(1e3))
    nu = parameter_spec("gel.poisson_ratio", 0.45)
    assert not nu.log and nu.to_value(nu.to_u(0.3)) == pytest.approx(0.3) and nu.upper < 0.5
    damping = parameter_spec("damping", 0.0)
    assert not damping.log and damping.lower == 0.0
    with pytest.raises(CalibrationError, match="sheet.yield_angle.*non-finite"):
        parameter_spec("sheet.yield_angle", math.inf)


def test_gauss_newton_covariance_of_linear_model():
    rng = np.random.default_rng(0)
    J = rng.normal(size=(200, 3))
    cov, note = gauss_newton_covariance(J)
    assert note == "ok"
    assert np.allclose(cov @ (J.T @ J), np.eye(3), atol=1e-10)
    # straight-line fit y = a + b t with unit noise: var(b) = 1 / sum (t - mean t)^2
    t = np.linspace(0.0, 1.0, 50)
    cov, _ = gauss_newton_covariance(np.stack([np.ones_like(t), t], axis=1))
    assert cov[1, 1] == pytest.approx(1.0 / np.sum((t - t.mean()) ** 2))
    singular, note = gauss_newton_covariance(np.stack([t, 2.0 * t], axis=1))
    assert singular is None and "not identifiable" in note


class _LinearProblem:
    """r(u) = A u + b with bounds, the interface the finite-difference provider uses."""

    def __init__(self, A, b, lower, upper):
        self.A, self.b = A, b
        self.bounds = (np.asarray(lower, float), np.asarray(upper, float))
        self.names = tuple(f"p{i}" for i in range(A.shape[1]))
        self.calls = 0

    def values(self, u):
        return dict(zip(self.names, u))

    def residual(self, u, phase="local"):
        self.calls += 1
        return self.A @ u + self.b

    def evaluate_many(self, points, phase):
        return [self.residual(p, phase) for p in points]


def test_finite_difference_jacobian_is_exact_for_linear_residuals_and_one_sided_at_bounds():
    rng = np.random.default_rng(1)
    A, b = rng.normal(size=(30, 3)), rng.normal(size=30)
    prob = _LinearProblem(A, b, [-1.0, -1.0, 0.0], [1.0, 1.0, 1.0])
    J = FiniteDifferenceJacobian(step=0.01)(prob, np.array([0.2, -0.3, 0.0]))  # third at its lower bound
    assert np.allclose(J, A, atol=1e-10)
    with pytest.raises(ConfigError, match="step must be > 0"):
        FiniteDifferenceJacobian(step=0.0)


def test_sensitivity_jacobian_matches_finite_differences(press_bag):
    """Cross-check of the two providers on a contact replay (away from the optimum)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = ObservationModel(load_evidence(press_bag), dt=DT)
    names = ["gel.youngs_modulus", "friction.gel_sheet"]
    problem = FitProblem(model, [parameter_spec(n, TRUE_PARAMS[n]) for n in names])
    u = np.array([0.3, -0.2])
    J_fd = FiniteDifferenceJacobian(step=1e-3)(problem, u)
    J_s = SensitivityJacobian()(problem, u)
    assert J_s.shape == J_fd.shape == (model.residual_count, 2)
    for j in range(2):
        err = np.linalg.norm(J_s[:, j] - J_fd[:, j]) / np.linalg.norm(J_fd[:, j])
        assert err < 0.05, (names[j], err)


def test_joint_replay_gives_the_plain_residual_and_the_sensitivity_jacobian(press_bag):
    """``FitProblem(joint=...)``: one replay for residual + Jacobian, equal to the separate ones."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = ObservationModel(load_evidence(press_bag), dt=DT)
    names = ["gel.youngs_modulus", "friction.gel_sheet"]
    specs = [parameter_spec(n, TRUE_PARAMS[n]) for n in names]
    provider = SensitivityJacobian()
    u = np.array([0.3, -0.2])
    plain = FitProblem(model, specs)
    r_plain, J_plain = plain.residual(u), provider(plain, u)
    assert plain.sim_runs == 2
    joint = FitProblem(model, specs, joint=provider.joint)
    r_joint = joint.residual(u, phase="local")
    J_cached = joint.cached_jacobian(u)
    assert joint.sim_runs == 1 and J_cached is not None
    assert provider(joint, u) is J_cached and joint.sim_runs == 1
    np.testing.assert_allclose(r_joint, r_plain, rtol=0, atol=1e-9 * np.abs(r_plain).max())
    np.testing.assert_allclose(J_cached, J_plain, rtol=0, atol=1e-9 * np.abs(J_plain).max())
    # other phases (global search, finite differences) replay without tangents
    joint.residual(u + 0.1, phase="global")
    assert joint.cached_jacobian(u + 0.1) is None
    # only the last few Jacobians and the best point's are kept
    for k in range(4):
        joint.residual(u + 0.01 * (k + 1), phase="local")
    assert len(joint._jacobians) <= FitProblem.JACOBIANS_KEPT + 1
    assert joint.cached_jacobian(joint.best[1]) is not None


def test_a_joint_replay_keeps_the_nuisance_columns_of_a_replay_of_their_own(press_bag):
    """``FitProblem(extra=...)``: the joint replay's tangents carry the held nuisance parameters' columns too, equal
    to those of a separate replay with tangents of every parameter (what the fit's optimum replayed for them before
    session 54), and the fit's nuisance Jacobian at that point then takes them without a replay."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = ObservationModel(load_evidence(press_bag), dt=DT)
    specs = [parameter_spec("gel.youngs_modulus", TRUE_PARAMS["gel.youngs_modulus"])]
    nuisance = {"friction.sheet_table": 0.3, "gel.poisson_ratio": 0.03}
    extra = [parameter_spec(n, model.parameter_value(n)) for n in nuisance]
    provider = SensitivityJacobian()
    u = np.array([0.3])
    joint = FitProblem(model, specs, joint=provider.joint, extra=extra)
    joint.residual(u, phase="local")
    kept, J_fit = joint.extra_jacobian(u), joint.cached_jacobian(u)
    assert kept is not None and kept.shape == (model.residual_count, 2) and joint.sim_runs == 1
    separate = FitProblem(model, specs + extra)
    J = provider(separate, np.concatenate([u, np.zeros(2)]))
    assert np.abs(J[:, 1:]).max() > 0.0
    np.testing.assert_allclose(kept, J[:, 1:], rtol=0, atol=1e-9 * np.abs(J[:, 1:]).max())
    np.testing.assert_allclose(J_fit, J[:, :1], rtol=0, atol=1e-9 * np.abs(J[:, :1]).max())
    notes: list[str] = []
    J_nuisance, runs = _nuisance_jacobian(joint, u, nuisance, 0.01, notes)
    assert runs == 0 and J_nuisance is kept and not notes
    # a warm-started fit's optimum is replayed again (its joint replay was warmed from another)
    joint.warm_start = True
    assert _nuisance_jacobian(joint, u, nuisance, 0.01, notes)[1] == 1


def test_fused_taichi_replay_equals_the_numpy_replay(press_bag):
    """``arch="cpu"``: replays with the fused Taichi elastic kernels give the NumPy residual and
    sensitivity Jacobian to round-off (what ``thinshell sysid`` uses by default)."""
    names = ["gel.youngs_modulus", "friction.gel_sheet"]
    specs = [parameter_spec(n, TRUE_PARAMS[n]) for n in names]
    u = np.array([0.3, -0.2])
    out = {}
    for arch in ("numpy", "cpu"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = ObservationModel(load_evidence(press_bag), dt=DT, arch=arch)
        provider = SensitivityJacobian()
        out[arch] = provider.joint(FitProblem(model, specs, joint=provider.joint), u)[:2]
        sim = model.simulation()
        assert sim.solver.backend == ("numpy" if arch == "numpy" else "taichi-cpu")
        assert (sim.solver._fused is not None) == (arch == "cpu")  # the fused evaluator did the steps
    for a, b in zip(out["numpy"], out["cpu"]):
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-9 * np.abs(a).max())
    with pytest.raises(CalibrationError, match="arch"):
        ObservationModel(load_evidence(press_bag), dt=DT, arch="gpu")


@pytest.mark.parametrize("bounds", [(-LOG_SPAN, LOG_SPAN), (-np.inf, np.inf), ((-LOG_SPAN, -0.2), (np.inf, LOG_SPAN))])
def test_first_trust_region_is_first_step_wide_where_the_reflective_scaling_made_it_a_factor_13_8(bounds):
    """A linear least squares with a direction the data barely see (a column 1e-3 of the other's) and a Gauss-Newton
    step along it of 50: least_squares' trust-region reflective method with ``x_scale = 1`` and the default log
    bounds +-ln(1000) takes a first step of sqrt(ln 1000) = 2.63 along it (the factor 13.8 of nominal_s101's
    bending stiffness, session 51); with :func:`first_region_scale` no coordinate moves more than ``first_step``
    in the first step, whatever the bounds (finite, infinite, one of each)."""
    from scipy.optimize import least_squares

    A = np.array([[1.0, 0.0], [0.0, 1.0e-3], [0.5, 1.0e-3]])
    b = np.array([0.3, 0.05, 0.2])
    lb, ub = (np.broadcast_to(np.asarray(v, dtype=float), (2,)).copy() for v in bounds)
    for first_step in (0.5, 0.2):
        points = []

        def residual(u):
            points.append(np.array(u))
            return A @ u - b

        least_squares(residual, np.zeros(2), jac=lambda u: A, bounds=(lb, ub), method="trf", max_nfev=2,
                      x_scale=first_region_scale(np.zeros(2), lb, ub, first_step))
        step = points[1] - points[0]
        assert np.all(np.abs(step) <= first_step * (1.0 + 1e-9)), (first_step, step)
        if np.all(np.isfinite(lb) == np.isfinite(ub)):  # (one bound finite: the region may be narrower)
            assert np.linalg.norm(step) > 0.5 * first_step  # the region, not the data, bounds the step
    if np.isfinite(lb).all() and np.isfinite(ub).all():
        points = []
        least_squares(lambda u: points.append(np.array(u)) or A @ u - b, np.zeros(2), jac=lambda u: A,
                      bounds=(lb, ub), method="trf", max_nfev=2, x_scale=1.0)
        assert 0.95 * math.sqrt(LOG_SPAN) < np.linalg.norm(points[1]) <= math.sqrt(LOG_SPAN)
        assert math.exp(points[1][1]) > 10.0
    assert first_region_scale(np.zeros(2), lb, ub, None) == 1.0


def test_held_column_leaves_the_gauss_newton_step_where_a_zero_column_sent_the_step_to_the_region_boundary():
    """A held coordinate (the bending stiffness nominal_s101 does not identify) beside two the data see, the residual
    curving along them (a quadratic term 3 |u|^2 times a data column): with the held column zeroed, J is rank
    deficient and least_squares' exact trust-region solver steps to the first region's boundary (0.5 wide) whatever
    the Gauss-Newton step (here 0.02-0.05), a trial that raises the cost and is rejected (on nominal_s101 from the
    scene start: x5.8 the cost, one replay lost, session 52's 49fit2); with :func:`held_jacobian`'s column
    (orthogonal to the residual and the others) the first trial is the Gauss-Newton step (within the
    Coleman-Li scaling's damping), accepted, the fit takes
    fewer evaluations, ends at the same minimum and the held coordinate stays at its start to round-off."""
    from scipy.optimize import least_squares

    rng = np.random.default_rng(0)
    A = rng.normal(size=(200, 3)) * np.array([1.0, 30.0, 20.0])
    b = A @ np.array([0.0, -0.03, 0.05]) + rng.normal(size=200)
    lb, ub = np.full(3, -LOG_SPAN), np.full(3, LOG_SPAN)
    held = np.array([True, False, False])

    def residual(u):
        return A @ u - b + 3.0 * (u[1] ** 2 + u[2] ** 2) * A[:, 1]

    def jacobian(u):
        J = A.copy()
        J[:, 1:] += 6.0 * np.outer(A[:, 1], u[1:])
        return J

    runs = {}
    for mode in ("zero", "held"):
        points = []

        def fun(u):
            points.append(np.array(u))
            return residual(u)

        def jac(u):
            J = jacobian(u)
            if mode == "zero":
                J[:, held] = 0.0
                return J
            return held_jacobian(J, residual(u), held)

        res = least_squares(fun, np.zeros(3), jac=jac, bounds=(lb, ub), method="trf",
                            x_scale=first_region_scale(np.zeros(3), lb, ub, 0.5))
        runs[mode] = (res, points)
    r0, J0 = residual(np.zeros(3)), jacobian(np.zeros(3))
    gn = np.zeros(3)
    gn[1:] = gauss_newton_step(J0[:, 1:], r0)[0]
    assert np.abs(gn).max() < 0.1  # the data ask a short step
    (res_zero, pts_zero), (res_held, pts_held) = runs["zero"], runs["held"]
    cost0 = 0.5 * r0 @ r0
    # zeroed: the first trial on the 0.5 region's boundary, far past Gauss-Newton, and worse than the start
    assert np.abs(pts_zero[1]).max() > 0.4 > 5 * np.abs(gn).max()
    assert 0.5 * np.sum(residual(pts_zero[1]) ** 2) > cost0
    # held column: the first trial is the Gauss-Newton step (to the reflective scaling's damping), and it lowers the cost
    np.testing.assert_allclose(pts_held[1], gn, rtol=0.05, atol=1e-12)
    assert 0.5 * np.sum(residual(pts_held[1]) ** 2) < cost0
    assert res_held.nfev < res_zero.nfev
    np.testing.assert_allclose(res_held.x[1:], res_zero.x[1:], atol=1e-5)
    assert res_held.cost == pytest.approx(res_zero.cost, rel=1e-8)
    assert all(abs(p[0]) < 1e-12 for p in pts_held)
    # the column is orthogonal to the residual and to the other columns, as long as the longest
    Jh = held_jacobian(J0, r0, held)
    assert np.abs(Jh[:, 0] @ np.column_stack([r0, J0[:, 1:]])).max() < 1e-9 * np.linalg.norm(Jh[:, 0]) * np.linalg.norm(r0)
    assert np.linalg.norm(Jh[:, 0]) == pytest.approx(np.linalg.norm(J0, axis=0).max())
    np.testing.assert_array_equal(Jh[:, 1:], J0[:, 1:])
    np.testing.assert_array_equal(held_jacobian(J0, r0, np.zeros(3, dtype=bool)), J0)
    with pytest.raises(CalibrationError, match="3 residuals for 3 parameters"):
        held_jacobian(J0[:3], r0[:3], held)


def test_gauss_newton_step_solves_linear_least_squares():
    rng = np.random.default_rng(3)
    J = rng.normal(size=(50, 3))
    u_true = np.array([0.2, -0.1, 0.05])
    r0 = -J @ u_true + 0.01 * rng.normal(size=50)  # r(u) = r0 + J u
    step, sigma = gauss_newton_step(J, r0)
    np.testing.assert_allclose(step, np.linalg.lstsq(J, -r0, rcond=None)[0], rtol=1e-12)
    np.testing.assert_allclose(sigma, np.sqrt(np.diag(np.linalg.inv(J.T @ J))), rtol=1e-12)
    step, sigma = gauss_newton_step(np.column_stack([J[:, 0], J[:, 0]]), r0)
    assert sigma is None and step.shape == (2,)


def test_stop_rule_ends_within_a_fraction_of_sigma(press_bag):
    """The Gauss-Newton stop (default 0.01 sigma) gives the tolerance-only fit within 0.05 sigma
    (cold-started replays: the path, with its rejected trial, is that of the stop rules alone).

    The replays here are solved as the simulator solves a step by default (1e-4 m/s, the last Newton update not
    applied), whose rounding-level cost noise near the optimum these stop rules are for: solved as sysid's replays are
    (:data:`sysid.observation.REPLAY_TOL_VELOCITY`, the update applied) the objective is smooth and this fit meets no
    rejected trial to stop at (every step lowers the cost to ftol)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = ObservationModel(load_evidence(press_bag), dt=DT)
    config = model.simulation().solver.config
    config.tol_velocity, config.apply_last_update = 1e-4, False
    name = "gel.youngs_modulus"
    start = {name: 3.0 * TRUE_PARAMS[name]}
    strict = fit(model, [name], initial=start, jacobian="sensitivity", warm_start=False, stop_sigma=None, stop_trial_sigma=None,
                 stop_rms=None)
    quick = fit(model, [name], initial=start, jacobian="sensitivity", warm_start=False)
    assert quick.status == strict.status == "converged"
    assert quick.sim_runs <= strict.sim_runs
    assert abs(quick.values[name] - strict.values[name]) < 0.05 * strict.sigma[name]
    assert quick.sigma[name] == pytest.approx(strict.sigma[name], rel=0.05)
    # trial-step stop alone, with a threshold that any rejected trial meets: ends at the first one
    trial = fit(model, [name], initial=start, jacobian="sensitivity", warm_start=False, stop_sigma=None, stop_trial_sigma=1e9,
                stop_rms=None)
    assert trial.status == "converged" and "did not lower the cost" in trial.message
    assert trial.sim_runs < strict.sim_runs
    local = [e.cost for e in trial.history if e.phase in ("initial", "local")]
    assert local[-1] >= min(local) == pytest.approx(trial.cost_final)
    # RMS stop alone, with a threshold that any accepted step meets: ends at the first accepted point
    rms = fit(model, [name], initial=start, jacobian="sensitivity", warm_start=False, stop_sigma=None, stop_trial_sigma=None,
              stop_rms=1.0)
    assert rms.status == "converged" and "lowered the RMS" in rms.message
    costs = [e.cost for e in rms.history if e.phase in ("initial", "local")]
    assert rms.sim_runs < strict.sim_runs and rms.cost_final == min(costs) < costs[0]
    assert sum(c < costs[0] for c in costs) == 1  # stopped at the first point that lowered the cost


def test_jacobian_provider_names():
    assert make_jacobian("fd").name == "fd"
    with pytest.raises(ConfigError, match="unknown jacobian provider 'adjoint'"):
        make_jacobian("adjoint")


def test_missing_markers_fits_remaining_channels_with_warning(tmp_path):
    bag = make_recording(tmp_path / "bag", segments=PRESS_ONLY[:1], seed=3, skip=("markers",))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = ObservationModel(load_evidence(bag), dt=DT)
    msgs = [str(w.message) for w in caught if issubclass(w.category, ObservationWarning)]
    assert any("tactile/markers" in m and "markers_xyz" in m for m in msgs), msgs
    assert model.channels == ("wrench", "sheet_points")
    result = fit(model, ["gel.youngs_modulus"], initial={"gel.youngs_modulus": 6.0e5}, max_nfev=2)
    assert "markers_xyz" not in result.rms_final and result.channels == ("wrench", "sheet_points")
    assert any("fitting without markers_xyz" in w for w in result.warnings)
    assert result.cost_final < result.cost_initial


def test_bad_inputs_are_named(press_bag):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ev = load_evidence(press_bag)
    with pytest.raises(CalibrationError, match="dt must be a positive"):
        ObservationModel(ev, dt=0.0)
    with pytest.raises(CalibrationError, match="channel 'image' cannot be fitted"):
        ObservationModel(ev, dt=DT, channels=["image"])
    model = ObservationModel(ev, dt=DT)
    with pytest.raises(ConfigError, match="unknown parameter 'gel.stiffness'"):
        fit(model, ["gel.stiffness"])
    with pytest.raises(CalibrationError, match="duplicates"):
        fit(model, ["gel.youngs_modulus", "gel.youngs_modulus"])


def test_replay_alignment_matches_simulated_steps(press_bag):
    """Stamps on the simulation grid get the simulated values; the first control is the recorded pose."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = ObservationModel(load_evidence(press_bag), dt=DT)
    trace = model.simulate(TRUE_PARAMS)
    pred = model.predict(trace)
    assert np.array_equal(model.evidence.t_ns["wrench"], trace.t_ns)
    assert np.allclose(pred["wrench"], trace.wrench)
    assert np.allclose(model.controls[0], model.evidence.pose[0])
    # half-step stamps interpolate linearly
    mid = model.align("wrench", trace.wrench)
    assert mid.shape == model.evidence.wrench.shape


def test_warm_start_replays_from_the_best_replay_with_fewer_newton_iterations(press_bag, monkeypatch):
    """FitProblem(warm_start=True): the best replay's vertex positions become the model's warm start;
    a replay at nearby parameters then converges with fewer Newton iterations to a residual within
    the solver tolerance's reach of the cold one; fit() leaves the model's warm start as it found it."""
    import sim_core.solver as solver

    iterations = []
    step = solver.NewtonSolver._single_step

    def counted(self, *args, **kwargs):
        info = step(self, *args, **kwargs)
        iterations.append(info.iterations)
        return info

    monkeypatch.setattr(solver.NewtonSolver, "_single_step", counted)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = ObservationModel(load_evidence(press_bag), dt=DT)
    specs = [parameter_spec("gel.youngs_modulus", 3.0 * TRUE_PARAMS["gel.youngs_modulus"])]
    problem = FitProblem(model, specs, warm_start=True)
    assert model.warm_start is None
    problem.residual(np.zeros(1), phase="initial")
    assert model.warm_start is not None and model.warm_start.shape == (model.step_count + 1, *model.simulation().state.x.shape)
    iterations.clear()
    warm = problem.residual(np.array([-0.05]))
    warm_iterations = sum(iterations)
    model.warm_start = None
    iterations.clear()
    cold = FitProblem(model, specs).residual(np.array([-0.05]))
    assert warm_iterations < sum(iterations)
    assert abs(float(warm @ warm) / float(cold @ cold) - 1.0) < 1e-3
    # fit() restores the model's warm start after its own replays
    model.warm_start = None
    fit(model, ["gel.youngs_modulus"], jacobian="fd", max_nfev=2)
    assert model.warm_start is None
    with pytest.raises(CalibrationError, match="warm start: expected"):
        model.controls_list(np.zeros((2, 3, 3)))


# ------------------------------------------------------------------------------------ replay budget
def test_joint_replay_leaves_the_difference_columns_to_the_accepted_point(press_bag):
    """A joint replay computes the tangent columns only; the sensor offset's forward-difference column
    (a replay) is computed when the Jacobian at that point is asked for, and equals the plain
    provider's column."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = ObservationModel(load_evidence(press_bag), dt=DT)
    names = ["gel.youngs_modulus", "sensor.normal_offset"]
    specs = [parameter_spec(n, model.parameter_value(n)) for n in names]
    provider = SensitivityJacobian()
    u = np.array([0.2, 0.5])
    joint = FitProblem(model, specs, joint=provider.joint)
    joint.residual(u, phase="local")
    partial = joint.cached_jacobian(u)
    assert joint.sim_runs == 1 and np.isnan(partial[:, 1]).all() and np.isfinite(partial[:, 0]).all()
    J = provider(joint, u)
    assert joint.sim_runs == 2 and np.isfinite(J).all()
    assert provider(joint, u) is joint.cached_jacobian(u) and joint.sim_runs == 2  # kept, complete
    plain = FitProblem(model, specs)
    J_plain = provider(plain, u)
    np.testing.assert_allclose(J, J_plain, rtol=0, atol=1e-9 * np.abs(J_plain).max())
    assert np.linalg.norm(J[:, 1]) > 1.0  # the offset moves the residual: the column is not empty


def test_replay_budget_bounds_the_fit_and_gives_the_same_fit_twice(press_bag):
    """``max_replays``: the fit never makes more replays than the budget, stops with status
    ``replay_budget`` at the best point so far, and repeats itself exactly (a count, not seconds);
    a larger budget goes further."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = ObservationModel(load_evidence(press_bag), dt=DT)
    names = ["gel.youngs_modulus", "sensor.normal_offset"]
    start = {"gel.youngs_modulus": 3.0 * TRUE_PARAMS["gel.youngs_modulus"], "sensor.normal_offset": 0.0}
    runs = [fit(model, names, initial=start, jacobian="sensitivity", max_replays=4) for _ in range(2)]
    for r in runs:
        assert r.sim_runs <= 4 and r.status == "replay_budget" and "replay budget" in r.message
        # the start with tangents, the offset's difference column, one trial step
        assert [e.phase for e in r.history][:3] == ["initial", "jacobian", "local"]
        assert r.cost_final < r.cost_initial and r.sigma is not None
    assert runs[0].values == runs[1].values and runs[0].cost_final == runs[1].cost_final
    more = fit(model, names, initial=start, jacobian="sensitivity", max_replays=10)
    assert 4 < more.sim_runs <= 10 and more.cost_final < runs[0].cost_final
    one = fit(model, names, initial=start, jacobian="sensitivity", max_replays=1)  # the start alone, plain
    assert one.sim_runs == 1 and one.status == "replay_budget" and one.values == pytest.approx(start)
    assert one.sigma is None and one.cost_final == one.cost_initial == pytest.approx(runs[0].cost_initial)
    with pytest.raises(ConfigError, match="max_replays must be >= 1"):
        fit(model, names, max_replays=0)


def test_reweighted_channels_enter_at_unit_variance_and_a_gap_channel_does_not_drive_the_fit(press_bag):
    """``reweight_channels``: each channel's noise is scaled by ``max(1, its whitened RMS at the
    start)``, so the start's cost is ``1/2 sum_ch n_ch min(1, rms_ch^2)``; a channel with a gap no
    parameter can follow (a 40-sigma offset on the normal force, with the gel modulus started 3x
    off) then no longer pulls the modulus: it lands nearer the truth than the unweighted fit's."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = ObservationModel(load_evidence(press_bag), dt=DT)
    name = "gel.youngs_modulus"
    true = TRUE_PARAMS[name]
    recorded = model.data

    def with_gap(ch):
        d = recorded(ch)
        if ch == "wrench":
            d = d.copy()
            d[:, 2] += 40.0 * model.sigma["wrench"][2]
        return d

    model.data = with_gap
    start = {name: 3.0 * true}
    plain = fit(model, [name], initial=start, jacobian="sensitivity", max_nfev=8)
    weighted = fit(model, [name], initial=start, jacobian="sensitivity", max_nfev=8, reweight_channels=True)
    assert model.sigma_scale is None and plain.sigma_scale is None  # restored; off by default
    rms0 = {ch: v["whitened_rms"] for ch, v in weighted.rms_initial.items() if ch in model.channels}
    assert weighted.sigma_scale == pytest.approx({ch: max(1.0, r) for ch, r in rms0.items()})
    assert weighted.sigma_scale["wrench"] > 10.0
    n = {ch: model.data(ch).size for ch in model.channels}
    assert weighted.cost_initial == pytest.approx(0.5 * sum(n[ch] * min(1.0, rms0[ch] ** 2) for ch in n), rel=1e-9)
    assert abs(weighted.values[name] / true - 1.0) < abs(plain.values[name] / true - 1.0)
    # ``reweight_channels=T`` (thinshell sysid without the tack layer: T = FOLLOWED_RMS): only the channels the model
    # does not follow at the start (whitened RMS above T) are weighed by their gap; the others keep their noise level
    from sysid.calibration import FOLLOWED_RMS

    above = fit(model, [name], initial=start, max_replays=1, reweight_channels=FOLLOWED_RMS)
    assert above.sigma_scale == pytest.approx({ch: r if r > FOLLOWED_RMS else 1.0 for ch, r in rms0.items()})
    assert above.sigma_scale["wrench"] > 10.0 and min(above.sigma_scale.values()) == 1.0
    assert above.cost_initial == pytest.approx(
        0.5 * sum(n[ch] * (1.0 if rms0[ch] > FOLLOWED_RMS else rms0[ch] ** 2) for ch in n), rel=1e-9)
    # a channel above T alone (no followed channel beside it) keeps its noise level: nothing to rebalance against
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lone = ObservationModel(load_evidence(press_bag), dt=DT, channels=("wrench",))
    lone.data = with_gap
    alone = fit(lone, [name], initial=start, max_replays=1, reweight_channels=FOLLOWED_RMS)
    assert alone.rms_initial["wrench"]["whitened_rms"] > 10.0 and alone.sigma_scale == {"wrench": 1.0}
