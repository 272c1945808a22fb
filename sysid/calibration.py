"""Sensor calibration of a replay: the observation-level half of "calibrate before diagnosing".

A real tactile sensor reports its streams through a calibration that is never exactly the data
sheet's: the wrench through a gain per group of axes, the markers through the scale of the
marker reconstruction, the pixels through the camera intrinsics. Each is an affine map of the
simulator's prediction, so it is fitted in closed form (weighted linear least squares) to a
recording, with no replay (SYSID.md "Diagnosis", step 1):

- wrench: ``F_rec = g_F F_sim`` (one gain on the three forces) and ``T_rec = g_T T_sim`` (one on the
  three torques);
- markers (sensor frame): ``x_rec = x0 + s_xy (x_sim - x0)``, ``y`` alike, ``z_rec = z0 + s_z (z_sim - z0)``
  with ``x0`` the rest position of each marker (the prediction's first sample, before contact);
- pixels: the pinhole ``u = f_x x / (z + d) + c_x``, ``v = f_y y / (z + d) + c_y`` (d the camera
  distance), with ``(f_x, c_x)`` and ``(f_y, c_y)`` fitted to the recording's own marker positions and
  pixels when it has both (the camera maps what the sensor measured; a model gap in the simulated
  marker motion then cannot bias the intrinsics), else to the simulated positions.

Gains and scales are kept within :data:`GAIN_BOUNDS` (a calibration off by more than that is a
different sensor, not a calibration error). The fit uses the rows given (the training part of a
recording); the result is applied to any prediction of the same recording.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Mapping

import numpy as np

from sim_core.errors import CalibrationError, SimulationDivergedError
from sysid.fit import fit

GAIN_BOUNDS = (0.5, 2.0)
"""Range of a fitted gain or marker scale (-)."""


@dataclass(frozen=True)
class SensorCalibration:
    """Observation-level calibration of one tactile sensor (see the module docstring).

    Attributes:
        force_gain, torque_gain: wrench gains (-).
        marker_scale_xy, marker_scale_z: marker displacement scales (-).
        fx, fy: focal lengths, px; cx, cy: principal point, px; distance: camera to the undeformed
            contact surface, m (not fitted).
    """

    force_gain: float = 1.0
    torque_gain: float = 1.0
    marker_scale_xy: float = 1.0
    marker_scale_z: float = 1.0
    fx: float = 300.0
    fy: float = 300.0
    cx: float = 160.0
    cy: float = 120.0
    distance: float = 0.025
    nominal_fx: float = 300.0
    nominal_fy: float = 300.0

    def as_dict(self) -> dict[str, float]:
        """The calibration as a plain dict (JSON)."""
        return {k: float(v) for k, v in asdict(self).items()}

    def apply(self, prediction: Mapping[str, np.ndarray], marker_rest: np.ndarray | None) -> dict[str, np.ndarray]:
        """The calibrated prediction.

        Args:
            prediction: channel -> aligned raw prediction (``markers_xyz`` ``(n, k, 3)`` m,
                ``markers_uv`` ``(n, k, 2)`` px, ``wrench`` ``(n, 6)`` N / N m, ``sheet_points``).
            marker_rest: ``(k, 3)`` rest positions of the markers (m), or None (no marker scale).

        Returns:
            channel -> calibrated array of the same shape (``markers_uv`` recomputed from the
            calibrated ``markers_xyz`` when both are present).
        """
        out = dict(prediction)
        if "wrench" in out:
            w = np.array(out["wrench"], dtype=float)
            w[..., :3] *= self.force_gain
            w[..., 3:] *= self.torque_gain
            out["wrench"] = w
        if "markers_xyz" in out and marker_rest is not None:
            out["markers_xyz"] = scale_markers(out["markers_xyz"], marker_rest, self.marker_scale_xy, self.marker_scale_z)
        if "markers_uv" in out and "markers_xyz" in out:
            out["markers_uv"] = self.project(out["markers_xyz"])
        return out

    def derivative(self, channel: str, d: np.ndarray) -> np.ndarray:
        """The calibrated derivative of ``channel`` from the raw one ``d`` ``(n, ..., axes, p)``.

        Exact for the wrench and the markers (linear maps); for the pixels the focal-length ratio to
        the scene camera is applied (first order: the marker scale's effect on the projection is
        neglected).
        """
        d = np.array(d, dtype=float)
        if channel == "wrench":
            d[..., :3, :] *= self.force_gain
            d[..., 3:, :] *= self.torque_gain
        elif channel == "markers_xyz":
            d[..., :2, :] *= self.marker_scale_xy
            d[..., 2:, :] *= self.marker_scale_z
        elif channel == "markers_uv":
            d[..., 0, :] *= self.fx / self.nominal_fx
            d[..., 1, :] *= self.fy / self.nominal_fy
        return d

    def project(self, xyz: np.ndarray) -> np.ndarray:
        """Pinhole pixels ``(..., 2)`` of sensor-frame points ``xyz`` ``(..., 3)`` (m)."""
        w = xyz[..., 2] + self.distance
        return np.stack([self.fx * xyz[..., 0] / w + self.cx, self.fy * xyz[..., 1] / w + self.cy], axis=-1)


def scale_markers(xyz: np.ndarray, rest: np.ndarray, s_xy: float, s_z: float) -> np.ndarray:
    """Markers ``(n, k, 3)`` with their displacement from ``rest`` ``(k, 3)`` scaled by (s_xy, s_xy, s_z)."""
    scale = np.array([s_xy, s_xy, s_z])
    return rest + (np.asarray(xyz, float) - rest) * scale


MIN_GAIN_INFORMATION = 100.0
"""Whitened energy ``sum (pred / sigma)^2`` a prediction needs before a gain is fitted to it: the
gain's standard error is ``1 / sqrt`` of it (0.1 here). Below, the recording does not determine the
gain (no contact, markers that do not move) and the scene's value 1 is kept."""


def _gain(data: np.ndarray, pred: np.ndarray, sigma: np.ndarray) -> float:
    """Weighted least-squares gain ``g`` of ``data ~ g pred`` (per-axis weights 1/sigma^2), bounded;
    1 when the prediction carries less than :data:`MIN_GAIN_INFORMATION`."""
    d = data / sigma
    p = pred / sigma
    den = float(np.sum(p * p))
    if not math.isfinite(den) or den < MIN_GAIN_INFORMATION:
        return 1.0
    return float(np.clip(np.sum(d * p) / den, *GAIN_BOUNDS))


def _affine(a: np.ndarray, b: np.ndarray) -> tuple[float, float] | None:
    """Least-squares ``(f, c)`` of ``b ~ f a + c`` (flattened); None with fewer than three finite
    samples or no spread in ``a`` (the line is not determined)."""
    a, b = a.reshape(-1), b.reshape(-1)
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 3 or np.ptp(a[ok]) == 0.0:
        return None
    A = np.stack([a[ok], np.ones(int(ok.sum()))], axis=1)
    (f, c), *_ = np.linalg.lstsq(A, b[ok], rcond=None)
    return float(f), float(c)


def fit_sensor_calibration(data: Mapping[str, np.ndarray], prediction: Mapping[str, np.ndarray],
                           sigma: Mapping[str, np.ndarray], marker_rest: np.ndarray | None,
                           nominal: SensorCalibration, rows: Mapping[str, np.ndarray] | None = None,
                           fit_camera: bool = True) -> SensorCalibration:
    """Fit the sensor calibration to a recording (closed form, no replay).

    Args:
        data: channel -> recorded values (shapes as in :meth:`SensorCalibration.apply`).
        prediction: channel -> raw (uncalibrated) aligned prediction.
        sigma: channel -> per-axis noise level (weights).
        marker_rest: ``(k, 3)`` marker rest positions, m (None: no marker scale fitted).
        nominal: the scene's calibration (camera intrinsics and distance; start values).
        rows: channel -> boolean mask of the rows to fit on (the training part); None: all rows.
        fit_camera: fit the camera intrinsics (else keep ``nominal``'s).

    Returns:
        the fitted :class:`SensorCalibration`; an intrinsic pair (f, c) that the rows do not determine
        (fewer than three samples, markers that never move) or whose focal length leaves
        :data:`GAIN_BOUNDS` times the scene's keeps the scene's values.
    """
    def pick(ch: str, arr: np.ndarray) -> np.ndarray:
        return arr if rows is None or ch not in rows else arr[rows[ch]]

    fields: dict[str, Any] = nominal.as_dict()
    if "wrench" in data and "wrench" in prediction:
        d, p, s = pick("wrench", data["wrench"]), pick("wrench", prediction["wrench"]), sigma["wrench"]
        fields["force_gain"] = _gain(d[:, :3], p[:, :3], s[:3])
        fields["torque_gain"] = _gain(d[:, 3:], p[:, 3:], s[3:])
    if "markers_xyz" in data and "markers_xyz" in prediction and marker_rest is not None:
        d = pick("markers_xyz", data["markers_xyz"]) - marker_rest
        p = pick("markers_xyz", prediction["markers_xyz"]) - marker_rest
        s = sigma["markers_xyz"]
        fields["marker_scale_xy"] = _gain(d[..., :2], p[..., :2], s[:2])
        fields["marker_scale_z"] = _gain(d[..., 2:], p[..., 2:], s[2:])
    if fit_camera and "markers_uv" in data:
        xyz = data.get("markers_xyz")
        if xyz is None and "markers_xyz" in prediction:
            xyz = scale_markers(prediction["markers_xyz"], marker_rest, fields["marker_scale_xy"],
                                fields["marker_scale_z"]) if marker_rest is not None else prediction["markers_xyz"]
        if xyz is not None:
            xyz = pick("markers_uv", xyz)
            uv = pick("markers_uv", data["markers_uv"])
            w = xyz[..., 2] + nominal.distance
            for axis, (f_key, c_key) in enumerate((("fx", "cx"), ("fy", "cy"))):
                line = _affine(xyz[..., axis] / w, uv[..., axis])
                ref = getattr(nominal, f_key)
                # an undetermined line or a focal length off by more than the gain bounds keeps the scene's
                if line is not None and GAIN_BOUNDS[0] * ref <= line[0] <= GAIN_BOUNDS[1] * ref:
                    fields[f_key], fields[c_key] = line
    return SensorCalibration(**fields)


# ====================================================================================== calibration
CALIBRATION_PARAMETERS = ("gel.youngs_modulus", "gel.poisson_ratio", "friction.gel_sheet",
                          "sheet.bending_stiffness", "sensor.normal_offset")
"""Simulator parameters fitted by :func:`calibrate` by default: the ones uncertain on any real cell
that a recording of a press or a lift constrains (SYSID.md "Diagnosis", step 1). The sheet-table
friction is left out: on the reference recordings a factor of 2.7 on it changes the replay by less
than the noise (the clamped card does not slide on the table), so it is not identifiable there."""


@dataclass
class CalibrationResult:
    """What :func:`calibrate` fitted.

    Attributes:
        params: fitted simulator parameters (name -> value, SI).
        sensor: the fitted :class:`SensorCalibration`.
        whitened_rms_before, whitened_rms_after: channel -> whitened RMS (noise units) of the
            replay at the scene values with the scene's sensor calibration, and after calibration.
        fit: the :class:`sysid.fit.FitResult` of the simulator parameters (None if not fitted).
        prediction: channel -> the calibrated prediction at ``params`` (aligned to the recording).
        replay_totals: ``{"scene_values": ..., "calibrated": ...}``: how the two replays' steps ended
            (``StepTotals`` as a dict: steps, substep retries, relaxed acceptances).
    """

    params: dict[str, float]
    sensor: SensorCalibration
    whitened_rms_before: dict[str, float]
    whitened_rms_after: dict[str, float]
    fit: Any = None
    prediction: dict[str, np.ndarray] | None = None
    replay_totals: dict[str, Any] | None = None

    def summary(self) -> dict[str, Any]:
        """JSON-ready summary (parameters, sensor calibration, whitened RMS before and after)."""
        out: dict[str, Any] = {"params": dict(self.params), "sensor": self.sensor.as_dict(),
                               "whitened_rms_before": dict(self.whitened_rms_before),
                               "whitened_rms_after": dict(self.whitened_rms_after)}
        if self.fit is not None:
            sigma = getattr(self.fit, "sigma", None) or {}
            out["sigma"] = {k: (None if v is None else float(v)) for k, v in sigma.items()}
            out["status"] = getattr(self.fit, "status", None)
        if self.replay_totals is not None:
            out["replay"] = self.replay_totals
        return out


def nominal_sensor_calibration(model) -> SensorCalibration:
    """The scene's sensor calibration of an :class:`~sysid.observation.ObservationModel` (unit gains)."""
    cam = model.scene["sensors"][model.sensor]["camera"]
    return SensorCalibration(fx=float(cam["fx"]), fy=float(cam["fy"]), cx=float(cam["cx"]), cy=float(cam["cy"]),
                             distance=float(cam["distance"]), nominal_fx=float(cam["fx"]),
                             nominal_fy=float(cam["fy"]))


def whitened_rms(model, prediction: Mapping[str, np.ndarray], channels) -> dict[str, float]:
    """Channel -> whitened RMS (noise units) of ``data - prediction``."""
    out = {}
    for ch in channels:
        if ch in prediction:
            e = (model.data(ch) - prediction[ch]).reshape(-1, model.sigma[ch].shape[0]) / model.sigma[ch]
            out[ch] = float(np.sqrt(np.mean(e ** 2)))
    return out


def calibrate(model, params=CALIBRATION_PARAMETERS, *, rows: Mapping[str, np.ndarray] | None = None,
              max_nfev: int = 8, workers: int = 1, max_time: float | None = None) -> CalibrationResult:
    """Calibrate a replay to its recording: the sensor calibration (closed form) and the simulator
    parameters ``params`` (weighted least squares, :func:`sysid.fit.fit`), alternately.

    Sets ``model.sensor_calibration``, ``model.marker_rest`` and ``model.nominal_normal_offset``
    (the fitted mount offset becomes the replay's nominal), so that every later prediction of the
    model is calibrated.

    Steps: replay at the scene values; fit the sensor calibration to it; fit ``params`` with that
    calibration fixed; fit the sensor calibration again to the best replay. Each fit lowers the
    same weighted cost, so the alternation does not raise it.

    Args:
        model: :class:`~sysid.observation.ObservationModel` of the recording.
        params: simulator parameters to fit (empty: the sensor calibration only).
        rows: channel -> rows of the training part for the sensor calibration (None: all).
        max_nfev: function evaluations of the parameter fit.
        workers: processes for its batched replays.
        max_time: wall-time budget of the parameter fit, s.

    Returns:
        the :class:`CalibrationResult`.

    Raises:
        CalibrationError: the replay at the scene values diverged; the scene has no tactile sensor
            (a task scene: nothing to calibrate).
    """
    if model.sensor is None:
        raise CalibrationError(f"{model.scene_source}: the scene has no tactile sensor, so there is no sensor "
                               "calibration to fit (thinshell sysid fits a task scene's parameters without one)")
    channels = [ch for ch in model.sigma]
    model.sensor_calibration = None
    model.nominal_normal_offset = 0.0
    try:
        trace = model.simulate({})
    except SimulationDivergedError as err:
        raise CalibrationError(f"{model.evidence.source.bag_path}: the replay at the scene values diverged: {err}") from err
    raw = model.predict_raw(trace)
    totals = {"scene_values": _totals(trace)}
    before = whitened_rms(model, raw, channels)
    model.marker_rest = np.asarray(raw["markers_xyz"][0], dtype=float) if "markers_xyz" in raw else None
    data = {ch: model.data(ch) for ch in raw}
    nominal = nominal_sensor_calibration(model)
    model.sensor_calibration = fit_sensor_calibration(data, raw, model.sigma, model.marker_rest, nominal, rows)
    values: dict[str, float] = {}
    result = None
    if params:
        result = fit(model, tuple(params), max_nfev=max_nfev, workers=workers, max_time=max_time)
        values = {k: float(v) for k, v in result.values.items()}
        model.nominal_normal_offset = float(values.get("sensor.normal_offset", 0.0))
        trace = model.simulate(values)
        raw = model.predict_raw(trace)
        totals["calibrated"] = _totals(trace)
        model.sensor_calibration = fit_sensor_calibration(data, raw, model.sigma, model.marker_rest, nominal, rows)
    calibrated = model.sensor_calibration.apply(raw, model.marker_rest)
    after = whitened_rms(model, calibrated, channels)
    totals.setdefault("calibrated", totals["scene_values"])
    return CalibrationResult(values, model.sensor_calibration, before, after, result, dict(calibrated), totals)


def _totals(trace) -> dict[str, Any] | None:
    """A replay's ``StepTotals`` as a JSON-ready dict (None when the trace has none)."""
    t = getattr(trace, "step_totals", None)
    return None if t is None else {k: v for k, v in asdict(t).items()}
