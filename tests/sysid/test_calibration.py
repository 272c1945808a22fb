"""Sensor calibration (sysid.calibration): closed-form fits recover known gains, scales and intrinsics."""

from __future__ import annotations

import numpy as np
import pytest

from sysid.calibration import SensorCalibration, fit_sensor_calibration, fit_sensor_gains, scale_markers
from sysid.gain_prior import GainPrior, gain_flags


def _synthetic(rng, n=200, k=12):
    rest = np.zeros((k, 3))
    rest[:, 0] = np.linspace(-0.008, 0.008, k)
    rest[:, 1] = np.linspace(-0.006, 0.006, k)[::-1]
    disp = rng.normal(scale=[1e-4, 1e-4, 5e-5], size=(n, k, 3))
    disp[:, :, 2] = -np.abs(disp[:, :, 2])
    xyz = rest + disp
    wrench = rng.normal(size=(n, 6)) * np.array([2, 2, 5, 1e-3, 1e-3, 1e-3])
    return rest, xyz, wrench


def test_recovers_known_calibration_exactly():
    rng = np.random.default_rng(0)
    rest, xyz, wrench = _synthetic(rng)
    nominal = SensorCalibration(fx=300.0, fy=300.0, cx=160.0, cy=120.0, distance=0.025)
    truth = SensorCalibration(force_gain=0.88, torque_sign=-1.0, torque_arm_x=-7e-4, torque_arm_y=4e-4,
                              torque_arm_z=2e-3, marker_scale_xy=0.9, marker_scale_z=1.12,
                              fx=310.0, fy=295.0, cx=158.0, cy=121.5, distance=0.025)
    prediction = {"markers_xyz": xyz, "wrench": wrench, "markers_uv": nominal.project(xyz)}
    data = truth.apply(prediction, rest)
    sigma = {"markers_xyz": np.array([1.5e-5, 1.5e-5, 2e-5]), "wrench": np.array([0.1, 0.1, 0.2, 4e-4, 4e-4, 4e-4]),
             "markers_uv": np.array([0.15, 0.15])}
    fitted = fit_sensor_calibration(data, prediction, sigma, rest, nominal)
    for key in ("force_gain", "torque_sign", "torque_arm_x", "torque_arm_y", "torque_arm_z", "marker_scale_xy",
                "marker_scale_z", "fx", "fy", "cx", "cy"):
        assert getattr(fitted, key) == pytest.approx(getattr(truth, key), rel=1e-7), key
    calibrated = fitted.apply(prediction, rest)
    for ch in data:
        np.testing.assert_allclose(calibrated[ch], data[ch], atol=1e-9)


def test_gains_stop_on_their_prior_flagged_with_a_cause_and_rows_select_the_training_part():
    """A recording 10x the prediction asks for a force gain of 10: the gain stops on the prior's upper bound
    (default +-15 %), and the flag says so, with the value asked for and a physical cause, so that no report
    takes 1.15 for the sensor's gain; a wider prior declared for the sensor moves the bound; a gain inside the
    prior is not flagged."""
    rng = np.random.default_rng(1)
    rest, xyz, wrench = _synthetic(rng)
    nominal = SensorCalibration()
    data = {"wrench": 10.0 * wrench}
    sigma = {"wrench": np.array([1.0, 1.0, 1.0, 1e-4, 1e-4, 1e-4])}
    fitted, asked = fit_sensor_gains(data, {"wrench": wrench}, sigma, None, nominal)
    assert fitted.force_gain == 1.15 and asked["force_gain"] == pytest.approx(10.0)
    flag = gain_flags(fitted.as_dict(), asked, {}, GainPrior())["force_gain"]
    assert flag["at_bound"] == "high" and flag["bounds"] == [0.85, 1.15]
    assert "data asked for 10" in flag["cause"] and "too compliant in the model" in flag["cause"]
    wide = GainPrior(force_gain=0.5)
    assert fit_sensor_calibration({"wrench": 0.6 * wrench}, {"wrench": wrench}, sigma, None, nominal,
                                  prior=wide).force_gain == pytest.approx(0.6)
    low, asked = fit_sensor_gains({"wrench": 0.6 * wrench}, {"wrench": wrench}, sigma, None, nominal)
    flag = gain_flags(low.as_dict(), asked, {}, GainPrior())["force_gain"]
    assert low.force_gain == 0.85 and flag["at_bound"] == "low" and "too stiff" in flag["cause"]
    # only the first half is the training part: its gain is 0.9, the other half's 1.1
    data = {"wrench": np.concatenate([0.9 * wrench[:100], 1.1 * wrench[100:]])}
    rows = {"wrench": np.arange(200) < 100}
    fitted, asked = fit_sensor_gains(data, {"wrench": wrench}, sigma, None, nominal, rows)
    assert fitted.force_gain == pytest.approx(0.9)
    assert gain_flags(fitted.as_dict(), asked, {}, GainPrior())["force_gain"]["at_bound"] is None


def test_torque_reference_offset_is_the_moment_transport_and_is_bounded():
    """A wrench resolved about a point offset by ``a`` from the simulator's: the recorded torques are
    ``T + a x F`` (rigid-body moment transport; checked here against r x F summed over point forces),
    and the closed form recovers ``a`` with the gains; an offset beyond TORQUE_ARM_BOUND ends on it;
    forces below the noise leave it at 0."""
    from sysid.calibration import TORQUE_ARM_BOUND

    rng = np.random.default_rng(5)
    points, forces = rng.normal(scale=3e-3, size=(50, 4, 3)), rng.normal(size=(50, 4, 3))
    a = np.array([6e-4, -9e-4, 1.5e-3])
    sim = np.concatenate([forces.sum(1), np.cross(points, forces).sum(1)], axis=1)
    recorded = np.concatenate([forces.sum(1), np.cross(points + a, forces).sum(1)], axis=1)
    np.testing.assert_allclose(SensorCalibration(torque_arm_x=a[0], torque_arm_y=a[1], torque_arm_z=a[2])
                               .apply({"wrench": sim}, None)["wrench"], recorded, rtol=1e-12, atol=1e-15)
    sigma = {"wrench": np.array([0.1, 0.1, 0.2, 4e-4, 4e-4, 4e-4])}
    fitted = fit_sensor_calibration({"wrench": recorded}, {"wrench": sim}, sigma, None, SensorCalibration())
    np.testing.assert_allclose(fitted.torque_arm, a, rtol=1e-8)
    assert fitted.torque_sign == 1.0 and fitted.force_gain == pytest.approx(1.0)
    far = np.concatenate([forces.sum(1), np.cross(points + 3.0 * TORQUE_ARM_BOUND, forces).sum(1)], axis=1)
    fitted = fit_sensor_calibration({"wrench": far}, {"wrench": sim}, sigma, None, SensorCalibration())
    np.testing.assert_allclose(fitted.torque_arm, TORQUE_ARM_BOUND, rtol=1e-6)
    quiet = {"wrench": sim * np.array([1e-3, 1e-3, 1e-3, 1.0, 1.0, 1.0])}  # forces at 1 % of the noise
    fitted = fit_sensor_calibration(quiet, quiet, sigma, None, SensorCalibration())
    assert np.all(fitted.torque_arm == 0.0) and fitted.torque_sign == 1.0


def test_torque_sign_convention_of_a_reaction_wrench_is_recovered_not_absorbed_by_a_bound():
    """Known answer: a sensor that reports the moment of the reaction (the force on the touched object,
    ``-sum (r - a) x g f``) about a point offset by ``a``, while its forces keep the contract's sign
    (``g sum f``, on the gel). The calibration recovers the sign -1, the gain g (on forces and torques
    alike: the moment of the same forces) and ``a`` exactly; a recording that follows the contract
    keeps +1, and so does one whose torques the recording does not determine. A separate torque gain
    with the contract's sign (the calibration before) ends on the lower bound of its prior on such a
    recording, as it did on every reference recording."""
    from scipy.optimize import lsq_linear

    rng = np.random.default_rng(7)
    points, forces = rng.normal(scale=3e-3, size=(60, 5, 3)), rng.normal(size=(60, 5, 3))
    a, g = np.array([-4e-4, 3e-4, -2.5e-3]), 0.9
    sim = np.concatenate([forces.sum(1), np.cross(points, forces).sum(1)], axis=1)
    reaction = np.concatenate([g * forces.sum(1), np.cross(points - a, -g * forces).sum(1)], axis=1)
    sigma = {"wrench": np.array([0.1, 0.1, 0.2, 4e-4, 4e-4, 4e-4])}
    fitted = fit_sensor_calibration({"wrench": reaction}, {"wrench": sim}, sigma, None, SensorCalibration())
    assert fitted.torque_sign == -1.0 and fitted.force_gain == pytest.approx(g, rel=1e-9)
    np.testing.assert_allclose(fitted.torque_arm, a, rtol=1e-7)
    np.testing.assert_allclose(fitted.apply({"wrench": sim}, None)["wrench"], reaction, rtol=1e-9, atol=1e-12)
    d = rng.normal(size=(4, 6, 2))  # the derivative carries the sign and the gain
    np.testing.assert_allclose(fitted.derivative("wrench", d)[:, 3:, :],
                               -g * d[:, 3:, :] + np.cross(a, g * d[:, :3, :], axisb=-2, axisc=-2), rtol=1e-12)
    contract = np.concatenate([g * forces.sum(1), np.cross(points + a, g * forces).sum(1)], axis=1)
    fitted = fit_sensor_calibration({"wrench": contract}, {"wrench": sim}, sigma, None, SensorCalibration())
    assert fitted.torque_sign == 1.0
    np.testing.assert_allclose(fitted.torque_arm, a, rtol=1e-7)
    quiet = {"wrench": sim * np.array([1.0, 1.0, 1.0, 1e-3, 1e-3, 1e-3])}  # torques at 1 % of the noise
    assert fit_sensor_calibration(quiet, quiet, sigma, None, SensorCalibration()).torque_sign == 1.0
    # a separate torque gain on the contract's sign, with the arm: the bounded optimum is on the bound
    zero = np.zeros(len(sim))
    f = g * sim[:, :3]
    arm_cols = [np.stack([zero, f[:, 2], -f[:, 1]], 1), np.stack([-f[:, 2], zero, f[:, 0]], 1),
                np.stack([f[:, 1], -f[:, 0], zero], 1)]
    A = np.concatenate([np.concatenate([sim[:, 3 + k:4 + k], arm_cols[k]], 1) / 4e-4 for k in range(3)])
    low, high = GainPrior().bounds("force_gain")
    bounded = lsq_linear(A, (reaction[:, 3:] / 4e-4).T.reshape(-1), bounds=([low, -1, -1, -1], [high, 1, 1, 1]))
    assert bounded.x[0] == pytest.approx(low)


def test_not_followed_windows_locate_a_gap_and_split_the_rms():
    """Known answer: white noise (unit whitened RMS) on 63 markers x 2 axes at 100 Hz, plus a common
    offset of 8 sigma on u over 2.60-3.80 s (nominal_s109's tack lift, in kind): one window at those
    times, RMS inside sqrt((64 + 1 + 1) / 2) and about 1 outside; a 40 ms dip inside stays one window."""
    from sysid.calibration import not_followed_windows

    rng = np.random.default_rng(11)
    t = np.arange(0, 4.5, 0.01)
    sigma = np.array([0.15, 0.15])
    residual = rng.normal(size=(len(t), 63, 2)) * sigma
    gap = (t >= 2.6 - 1e-9) & (t <= 3.8 + 1e-9)
    residual[gap, :, 0] += 8.0 * sigma[0]
    residual[(t > 3.0) & (t < 3.04), :, 0] -= 8.0 * sigma[0]  # 3 samples back in the noise
    where = not_followed_windows(t, residual, sigma)
    assert len(where["windows_s"]) == 1
    np.testing.assert_allclose(where["windows_s"][0], [2.6, 3.8], atol=1e-9)
    assert where["whitened_rms_inside"] == pytest.approx(np.sqrt((64 + 2) / 2 * (118 / 121) + 3 / 121), rel=0.05)
    assert where["whitened_rms_outside"] == pytest.approx(1.0, rel=0.03)
    assert where["fraction_of_samples"] == pytest.approx(121 / len(t), rel=1e-9)
    quiet = not_followed_windows(t, rng.normal(size=(len(t), 63, 2)) * sigma, sigma)
    assert quiet["windows_s"] == [] and quiet["whitened_rms_inside"] is None


def test_a_prediction_below_the_noise_keeps_the_scene_gain():
    rng = np.random.default_rng(3)
    rest, xyz, wrench = _synthetic(rng)
    # the markers barely move (1 um against 15 um noise): the recording does not determine the scales
    still = rest + (xyz - rest) * 0.01
    data = {"markers_xyz": rest + rng.normal(size=xyz.shape) * 15e-6, "wrench": 0.9 * wrench}
    sigma = {"markers_xyz": np.array([15e-6, 15e-6, 20e-6]), "wrench": np.array([1.0, 1.0, 1.0, 1e-4, 1e-4, 1e-4])}
    fitted = fit_sensor_calibration(data, {"markers_xyz": still, "wrench": wrench}, sigma, rest, SensorCalibration())
    assert fitted.marker_scale_xy == 1.0 and fitted.marker_scale_z == 1.0
    assert fitted.force_gain == pytest.approx(0.9)


def test_derivative_matches_finite_difference_of_apply():
    rng = np.random.default_rng(2)
    rest, xyz, wrench = _synthetic(rng, n=5, k=4)
    cal = SensorCalibration(force_gain=0.7, torque_sign=-1.0, torque_arm_x=1e-3, torque_arm_y=-2e-3, torque_arm_z=5e-4,
                            marker_scale_xy=0.9, marker_scale_z=1.3)
    d = rng.normal(size=(5, 6, 1))
    h = 1e-6
    fd = (cal.apply({"wrench": wrench + h * d[..., 0]}, None)["wrench"] - cal.apply({"wrench": wrench}, None)["wrench"]) / h
    np.testing.assert_allclose(cal.derivative("wrench", d)[..., 0], fd, rtol=1e-6)
    dm = rng.normal(size=(5, 4, 3, 1)) * 1e-5
    fd = (scale_markers(xyz + h * dm[..., 0] / 1e-5, rest, 0.9, 1.3) - scale_markers(xyz, rest, 0.9, 1.3)) / h * 1e-5
    np.testing.assert_allclose(cal.derivative("markers_xyz", dm)[..., 0], fd, rtol=1e-6, atol=1e-12)


def test_calibrate_lowers_the_weighted_cost_and_sets_the_model(tmp_path):
    """End to end on the bundled recording (short, coarse gel): calibration never raises the cost."""
    from sysid.calibration import calibrate
    from sysid.evidence import load_evidence
    from sysid.observation import ObservationModel
    from tests.sysid.conftest import reference_bag

    ev = load_evidence(reference_bag("nominal_s101"))
    model = ObservationModel(ev, dt=0.01, t_max=1.2, simulation={"gel_resolution": [4, 3, 2]}, arch="cpu")
    result = calibrate(model, ("gel.youngs_modulus", "sensor.normal_offset"), max_nfev=3)
    assert model.sensor_calibration is result.sensor
    assert model.nominal_normal_offset == result.params["sensor.normal_offset"]

    def cost(rms):
        return sum(rms[ch] ** 2 * model.data(ch).size for ch in model.channels)

    assert cost(result.whitened_rms_after) < cost(result.whitened_rms_before)
    summary = result.summary()
    assert set(summary) >= {"params", "sensor", "whitened_rms_before", "whitened_rms_after"}


def test_undetermined_intrinsics_keep_the_scene_camera_and_an_implausible_focal_stops_on_its_prior():
    """A line the data do not determine keeps the scene's intrinsics; a focal length 3x the scene's stops on
    its prior's bound (1.15x by default), flagged, with the principal point refitted at that slope."""
    nominal = SensorCalibration(fx=300.0, fy=300.0, cx=160.0, cy=120.0, distance=0.025)
    still = np.zeros((10, 1, 3))  # one marker that never moves: no spread, the line is undetermined
    data = {"markers_xyz": still, "markers_uv": np.full((10, 1, 2), 150.0)}
    fitted = fit_sensor_calibration(data, {}, {}, None, nominal)
    assert (fitted.fx, fitted.cx, fitted.fy, fitted.cy) == (300.0, 160.0, 300.0, 120.0)
    rng = np.random.default_rng(3)
    rest, xyz, _ = _synthetic(rng)
    far = SensorCalibration(fx=900.0, fy=300.0, cx=160.0, cy=120.0, distance=0.025)  # fx x3: outside the prior
    fitted, asked = fit_sensor_gains({"markers_xyz": xyz, "markers_uv": far.project(xyz)}, {}, {}, None, nominal)
    a = xyz[..., 0] / (xyz[..., 2] + 0.025)
    assert fitted.fx == pytest.approx(345.0) and fitted.cx == pytest.approx(160.0 + 555.0 * a.mean())
    assert asked["fx"] == pytest.approx(900.0)
    flags = gain_flags(fitted.as_dict(), asked, {"fx": 300.0, "fy": 300.0}, GainPrior())
    assert flags["fx"]["at_bound"] == "high" and flags["fy"]["at_bound"] is None
    assert fitted.fy == pytest.approx(300.0) and fitted.cy == pytest.approx(120.0)


# ------------------------------------------------------------------ contact parameters of the calibration
CONTACT_TRUTH = {"contact.stiffness": 6.0e3, "contact.eps_v": 2.0e-3}
"""A contact 3.3x more compliant than the scene's (2e4 N/m) and a stick regularisation 5x narrower
than its (0.01 m/s): the known answer of the recordings below."""


def _contact_recording(out_dir, segments, truth=CONTACT_TRUTH):
    """A noisy recording of the bench card made with ``truth`` (default :data:`CONTACT_TRUTH`); its
    scene file holds the simulator's default contact (the nominal a real cell's scene would hold)."""
    from tests.sysid.simbag import CARD_SCENE, add_noise, simulate_streams, targets_from_segments, write_bag

    scene = dict(CARD_SCENE)
    targets = targets_from_segments(np.asarray(scene["effectors"]["ee"]["initial_pose"]), segments)
    return write_bag(out_dir, scene, add_noise(simulate_streams(scene, truth, targets), seed=4))


@pytest.fixture(scope="module")
def contact_press(tmp_path_factory):
    """A press (5 steps of 10 ms)."""
    from tests.sysid.simbag import PRESS_ONLY

    return _contact_recording(tmp_path_factory.mktemp("contact_press") / "bag", PRESS_ONLY)


@pytest.fixture(scope="module")
def contact_slip(tmp_path_factory):
    """A press, the gel slips 2 mm over the card, then holds still (the sheared gel creeps back at a
    rate set by the stick regularisation): 19 steps of 10 ms."""
    from tests.sysid.simbag import PRESS_SLIDE

    return _contact_recording(tmp_path_factory.mktemp("contact_slip") / "bag",
                              (*PRESS_SLIDE[:2], ((0.0, 0.0, 0.0), 8)))


STICK_TRUTH = {"contact.eps_v": 2.5e-3}
"""A stick regularisation 4x narrower than the scene's (0.01 m/s), the contact stiffness the scene's."""


@pytest.fixture(scope="module")
def stick_slip(tmp_path_factory):
    """contact_slip's motion, recorded with :data:`STICK_TRUTH`."""
    from tests.sysid.simbag import PRESS_SLIDE

    return _contact_recording(tmp_path_factory.mktemp("stick_slip") / "bag", (*PRESS_SLIDE[:2], ((0.0, 0.0, 0.0), 8)),
                              STICK_TRUTH)


def test_secant_stage_recovers_a_known_stick_regularisation(stick_slip):
    """Known answer: the calibration's secant stage (the probe at 1/3 of the scene's eps_v, then
    Broyden-updated Gauss-Newton steps with the sensor calibration refitted to each replay) moves a
    stick regularisation 4x narrower than the scene's to within 25 % of the truth in at most four
    replays (found: +21 %, converged after two), and lowers the tactile channels' whitened RMS; with
    no replays it leaves the scene's value. The stage gives every channel one vote
    (:func:`sysid.calibration_secant.secant_calibration`), not the noise-level weights that are the
    maximum-likelihood ones where the model is exact, as it nearly is here: that costs accuracy on
    this recording (the vote weights' optimum is 10 of its scaled 1-sigma from the truth) and keeps the
    card's 273 points from outvoting the tactile channels on the reference recordings."""
    from sysid.calibration import calibrate

    model = _model(stick_slip)
    assert model.parameter_value("contact.eps_v") == pytest.approx(0.01)
    result = calibrate(model, (), secant_replays=4)
    stage = result.summary()["secant"]
    assert stage["fitted"] == ["contact.eps_v"] and stage["replays"] <= 4
    assert result.params["contact.eps_v"] == pytest.approx(STICK_TRUTH["contact.eps_v"], rel=0.25), stage
    assert model.parameter_value("contact.eps_v") == result.params["contact.eps_v"]
    assert stage["cost_final"] < stage["cost_initial"]
    for ch in ("markers_xyz", "wrench"):
        assert result.whitened_rms_after[ch] < result.whitened_rms_before[ch], (ch, result.summary())
    model = _model(stick_slip)
    result = calibrate(model, (), secant_replays=0)
    assert "contact.eps_v" not in result.params and "secant" not in result.summary()


def _model(bag):
    import warnings

    from sysid.evidence import load_evidence
    from sysid.observation import ObservationModel
    from tests.sysid.simbag import DT

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ObservationModel(load_evidence(bag), dt=DT)


def test_contact_stiffness_column_matches_central_differences(contact_press):
    """The calibration's Jacobian column of the contact stiffness (forward sensitivities through the
    penalty's stiffness derivative) against central differences of the replayed residual, away from
    the truth."""
    from sysid.fit import FiniteDifferenceJacobian, FitProblem, SensitivityJacobian, parameter_spec

    model = _model(contact_press)
    names = ["contact.stiffness", "gel.youngs_modulus"]
    problem = FitProblem(model, [parameter_spec(n, model.parameter_value(n)) for n in names])
    u = np.array([-0.4, 0.1])
    J_fd = FiniteDifferenceJacobian(step=1e-3)(problem, u)
    J_s = SensitivityJacobian()(problem, u)
    for j, name in enumerate(names):
        norm = np.linalg.norm(J_fd[:, j])
        assert norm > 1.0, (name, norm)  # the recording sees it: a 1 % change moves the residual
        assert np.linalg.norm(J_s[:, j] - J_fd[:, j]) / norm < 0.05, name


def test_stick_regularisation_column_is_the_tangent_of_the_replay(contact_slip, monkeypatch):
    """``contact.eps_v``'s column is the replay's implicit-function tangent (the lagged friction's
    :meth:`~sim_core.energies.friction.reference.LaggedFriction.eps_v_gradient`, no replay of its own), also when
    it is the only parameter: the column of the replay sysid makes (its steps solved to
    :data:`sysid.observation.REPLAY_TOL_VELOCITY`) against central differences of replays whose steps are solved to
    1e-8 m/s (the simulator's default 1e-4 m/s makes a replay rough in eps_v at the 5-15 % level of this column;
    measured: relative error 1e-4 at 1 % steps, below 1e-5 at 0.1 %), at two stick speeds. The lagged normal forces,
    bases and weights are of ``x^n``, so nothing of them leaves the tangent inexact. Measured at eps_v x 0.55: 7e-6
    (replays at 1e-7 m/s); with the last update applied (1e-5 m/s) 1.6e-3 where the tangent took the Newton matrix
    of the iterate before the result, 9e-8 + 6e-7 at the result's exact matrix."""
    import sysid.observation as observation
    from sysid.fit import FitProblem, SensitivityJacobian, parameter_spec
    from sysid.jacobians import DIFFERENCE_PARAMETERS

    assert "contact.eps_v" not in DIFFERENCE_PARAMETERS
    name = "contact.eps_v"
    model = _model(contact_slip)
    problem = FitProblem(model, [parameter_spec(name, model.parameter_value(name))])
    model.simulation()  # the replay's solver, at the replay tolerance
    monkeypatch.setattr(observation, "REPLAY_TOL_VELOCITY", 1e-8)
    converged = _model(contact_slip)
    reference = FitProblem(converged, [parameter_spec(name, converged.parameter_value(name))])
    assert converged.simulation().solver.config.tol_velocity == 1e-8 < model.simulation().solver.config.tol_velocity
    h = 1e-3
    for u in (np.array([-0.6]), np.array([0.0])):
        runs = problem.sim_runs
        J = SensitivityJacobian()(problem, u)
        assert problem.sim_runs == runs + 1  # the column came with the residual's replay
        central = (reference.residual(u + h) - reference.residual(u - h)) / (2.0 * h)
        assert np.linalg.norm(central) > 10.0  # the recording sees it
        assert np.linalg.norm(J[:, 0] - central) / np.linalg.norm(central) < 1e-3, u


def test_calibration_recovers_a_known_contact_stiffness_and_stick_regularisation(contact_slip):
    """Known answer: on a recording this simulator made with a softer contact and a narrower stick zone
    than its scene says, the calibration finds both (within 3 scaled sigma and 10 %; found: -2.0 % and
    +2.6 %), reports their 1-sigma and correlation, and leaves the sensor calibration at unit gains.
    The model is exact here, so the noise levels are the right weights: the channels are not
    reweighted by the start's gap (with them reweighted: -1.2 % and +10.7 %, the wrench's weight set
    by a start 3.3x too stiff)."""
    from sysid.calibration import calibrate

    model = _model(contact_slip)
    assert model.parameter_value("contact.stiffness") == pytest.approx(2.0e4)
    result = calibrate(model, tuple(CONTACT_TRUTH), max_nfev=12, reweight_channels=False)
    summary = result.summary()
    for (name, true), rel in zip(CONTACT_TRUTH.items(), (0.10, 0.10)):
        value, sigma = result.params[name], summary["sigma"][name]
        assert value == pytest.approx(true, rel=rel), (name, value, summary)
        assert sigma is not None and 0.0 < sigma < 0.5 * true, (name, sigma)
        assert abs(value - true) < 3.0 * max(summary["sigma_scaled"][name], 0.02 * true), (name, value, sigma)
    assert summary["fitted"] == list(CONTACT_TRUTH)
    corr = np.asarray(summary["correlation"])
    assert corr.shape == (2, 2) and np.allclose(np.diag(corr), 1.0) and abs(corr[0, 1]) < 0.95
    assert result.sensor.force_gain == pytest.approx(1.0, abs=0.05)
    assert result.whitened_rms_after["wrench"] < 1.5 < result.whitened_rms_before["wrench"]


def test_calibration_bounds_follow_the_scene_and_narrow_the_search():
    from sysid.calibration import CALIBRATION_BOUNDS, CALIBRATION_PARAMETERS, CONTACT_PARAMETERS, calibration_bounds
    from sysid.fit import bounded_spec, parameter_spec
    from sim_core.errors import CalibrationError

    class _Scene:
        values = {"gel.youngs_modulus": 3.0e5, "gel.poisson_ratio": 0.45, "friction.gel_sheet": 0.8,
                  "sheet.bending_stiffness": 0.008, "sensor.normal_offset": 0.0, "contact.stiffness": 2.0e4,
                  "contact.eps_v": 0.01}

        def parameter_value(self, name):
            return self.values[name]

    assert set(CALIBRATION_PARAMETERS) | set(CONTACT_PARAMETERS) <= set(CALIBRATION_BOUNDS)
    b = calibration_bounds(_Scene(), CALIBRATION_PARAMETERS + CONTACT_PARAMETERS)
    assert b["gel.youngs_modulus"] == pytest.approx((1.0e5, 9.0e5))
    assert b["contact.stiffness"] == pytest.approx((2.0e4 / 30.0, 6.0e5))
    assert b["contact.eps_v"] == pytest.approx((1.0e-4, 0.1))
    assert b["sensor.normal_offset"] == pytest.approx((-5.0e-4, 5.0e-4))
    assert b["gel.poisson_ratio"] == (0.3, 0.499)
    for name, value in _Scene.values.items():  # every scene value lies inside its own bounds
        spec = bounded_spec(parameter_spec(name, value), b[name])
        lo, hi = spec.u_bounds
        assert lo < spec.to_u(value) < hi and spec.to_value(lo) == pytest.approx(b[name][0])
    with pytest.raises(CalibrationError, match="outside its bounds"):
        bounded_spec(parameter_spec("contact.stiffness", 2.0e4), (3.0e4, 5.0e4))
    with pytest.raises(CalibrationError, match="leave no range"):
        bounded_spec(parameter_spec("contact.stiffness", 2.0e4), (5.0e4, 3.0e4))


def test_calibrated_values_become_the_replays_nominal(contact_press):
    from sim_core.errors import ConfigError

    model = _model(contact_press)
    model.set_nominal({"contact.stiffness": 1.0e4, "sensor.normal_offset": 1.0e-5})
    assert model.parameter_value("contact.stiffness") == 1.0e4 and model.nominal_normal_offset == 1.0e-5
    assert model.prepare({}).get_parameter("contact.stiffness") == 1.0e4
    assert model.prepare({"contact.stiffness": 3.0e3}).get_parameter("contact.stiffness") == 3.0e3
    with pytest.raises(ConfigError, match="must be > 0"):  # nothing changes on a bad value
        model.set_nominal({"gel.youngs_modulus": 2.0e5, "contact.stiffness": -1.0})
    with pytest.raises(ConfigError, match="unknown parameter"):
        model.set_nominal({"contact.stifness": 1.0})
    assert model.parameter_value("gel.youngs_modulus") == 3.0e5
    model.reset_nominal()
    assert model.parameter_value("contact.stiffness") == 2.0e4 and model.nominal_normal_offset == 0.0
    assert model.prepare({}).get_parameter("contact.stiffness") == 2.0e4


def test_sysid_fit_starts_from_the_calibrated_model(contact_press, tmp_path):
    """``thinshell sysid --calibrate``: the calibration parameters other than the fitted ones are
    calibrated first (as ``thinshell diagnose`` does), and the fit replays with their values.

    The sensor gains are held at the calibration's (``--fixed-gains``): with them refitted to every replay (the
    default) this 50 ms press leaves the modulus and the force gain one direction (330 kPa +- 210 kPa robust),
    so only held gains let the modulus check the calibrated contact stiffness."""
    from sysid.fit_recording import FitOptions, fit_recording

    options = FitOptions(params=("gel.youngs_modulus",), calibration_params=("contact.stiffness", "gel.youngs_modulus"),
                         max_nfev=4, calibration_max_replays=12, profile_gains=False)
    outcome = fit_recording(contact_press, tmp_path / "out", options)
    cal = outcome.document["diagnostics"]["sensor_calibration"]
    assert cal["fitted"] == ["contact.stiffness"]  # the fitted parameter is not calibrated beforehand
    k = cal["params"]["contact.stiffness"]
    assert k == pytest.approx(CONTACT_TRUTH["contact.stiffness"], rel=0.15)
    assert outcome.result.model.parameter_value("contact.stiffness") == k
    assert outcome.result.values["gel.youngs_modulus"] == pytest.approx(3.0e5, rel=0.05)
