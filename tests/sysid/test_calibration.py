"""Sensor calibration (sysid.calibration): closed-form fits recover known gains, scales and intrinsics."""

from __future__ import annotations

import numpy as np
import pytest

from sysid.calibration import GAIN_BOUNDS, SensorCalibration, fit_sensor_calibration, scale_markers


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
    truth = SensorCalibration(force_gain=0.8, torque_gain=1.3, marker_scale_xy=0.9, marker_scale_z=1.2,
                              fx=310.0, fy=295.0, cx=158.0, cy=121.5, distance=0.025)
    prediction = {"markers_xyz": xyz, "wrench": wrench, "markers_uv": nominal.project(xyz)}
    data = truth.apply(prediction, rest)
    sigma = {"markers_xyz": np.array([1.5e-5, 1.5e-5, 2e-5]), "wrench": np.array([0.1, 0.1, 0.2, 4e-4, 4e-4, 4e-4]),
             "markers_uv": np.array([0.15, 0.15])}
    fitted = fit_sensor_calibration(data, prediction, sigma, rest, nominal)
    for key in ("force_gain", "torque_gain", "marker_scale_xy", "marker_scale_z", "fx", "fy", "cx", "cy"):
        assert getattr(fitted, key) == pytest.approx(getattr(truth, key), rel=1e-9), key
    calibrated = fitted.apply(prediction, rest)
    for ch in data:
        np.testing.assert_allclose(calibrated[ch], data[ch], atol=1e-9)


def test_gains_are_bounded_and_rows_select_the_training_part():
    rng = np.random.default_rng(1)
    rest, xyz, wrench = _synthetic(rng)
    nominal = SensorCalibration()
    data = {"wrench": 10.0 * wrench}
    sigma = {"wrench": np.array([1.0, 1.0, 1.0, 1e-4, 1e-4, 1e-4])}
    fitted = fit_sensor_calibration(data, {"wrench": wrench}, sigma, None, nominal)
    assert fitted.force_gain == GAIN_BOUNDS[1] and fitted.torque_gain == GAIN_BOUNDS[1]
    # only the first half is the training part: its gain is 0.7, the other half's 1.4
    data = {"wrench": np.concatenate([0.7 * wrench[:100], 1.4 * wrench[100:]])}
    rows = {"wrench": np.arange(200) < 100}
    fitted = fit_sensor_calibration(data, {"wrench": wrench}, sigma, None, nominal, rows)
    assert fitted.force_gain == pytest.approx(0.7)


def test_a_prediction_below_the_noise_keeps_the_scene_gain():
    rng = np.random.default_rng(3)
    rest, xyz, wrench = _synthetic(rng)
    # the markers barely move (1 um against 15 um noise): the recording does not determine the scales
    still = rest + (xyz - rest) * 0.01
    data = {"markers_xyz": rest + rng.normal(size=xyz.shape) * 15e-6, "wrench": 0.6 * wrench}
    sigma = {"markers_xyz": np.array([15e-6, 15e-6, 20e-6]), "wrench": np.array([1.0, 1.0, 1.0, 1e-4, 1e-4, 1e-4])}
    fitted = fit_sensor_calibration(data, {"markers_xyz": still, "wrench": wrench}, sigma, rest, SensorCalibration())
    assert fitted.marker_scale_xy == 1.0 and fitted.marker_scale_z == 1.0
    assert fitted.force_gain == pytest.approx(0.6)


def test_derivative_matches_finite_difference_of_apply():
    rng = np.random.default_rng(2)
    rest, xyz, wrench = _synthetic(rng, n=5, k=4)
    cal = SensorCalibration(force_gain=0.7, torque_gain=1.1, marker_scale_xy=0.9, marker_scale_z=1.3)
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


def test_undetermined_or_implausible_intrinsics_keep_the_scene_camera():
    nominal = SensorCalibration(fx=300.0, fy=300.0, cx=160.0, cy=120.0, distance=0.025)
    still = np.zeros((10, 1, 3))  # one marker that never moves: no spread, the line is undetermined
    data = {"markers_xyz": still, "markers_uv": np.full((10, 1, 2), 150.0)}
    fitted = fit_sensor_calibration(data, {}, {}, None, nominal)
    assert (fitted.fx, fitted.cx, fitted.fy, fitted.cy) == (300.0, 160.0, 300.0, 120.0)
    rng = np.random.default_rng(3)
    rest, xyz, _ = _synthetic(rng)
    far = SensorCalibration(fx=900.0, fy=300.0, cx=160.0, cy=120.0, distance=0.025)  # fx x3: outside the bounds
    fitted = fit_sensor_calibration({"markers_xyz": xyz, "markers_uv": far.project(xyz)}, {}, {}, None, nominal)
    assert fitted.fx == 300.0 and fitted.cx == 160.0
    assert fitted.fy == pytest.approx(300.0) and fitted.cy == pytest.approx(120.0)
