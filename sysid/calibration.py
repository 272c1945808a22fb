"""Sensor calibration of a replay: the observation-level half of "calibrate before diagnosing".

A real tactile sensor reports its streams through a calibration that is never exactly the data
sheet's: the wrench through a gain and its torques' sign convention and reference point, the markers
through the scale of the marker reconstruction, the pixels through the camera intrinsics. Each is an
affine map of the simulator's prediction, so it is fitted in closed form (weighted linear least
squares) to a recording, with no replay (SYSID.md "Diagnosis", step 1):

- wrench: ``F_rec = g_F F_sim`` (one gain on the three forces) and ``T_rec = s_T g_F T_sim + a x F_rec``:
  the torques are the moment of the same contact forces, so the force gain scales them too; ``a`` (m,
  sensor frame) is the offset of the point the recorded torques are resolved about from the
  simulator's (the moment transport ``T_o' = T_o + (o - o') x F`` of a rigid-body wrench), and
  ``s_T = +-1`` the torques' sign convention: +1 the moment of the force ON the gel, as INTERFACES.md
  and the simulator define it, -1 the moment of its reaction (the force on the touched object) while
  the forces keep the contract's sign. A sensor driver can report either. On the reference
  recordings nominal_s101, nominal_s109 and lens_s106 the fit (each recording alone) gives -1 about a
  point about 2 mm behind the gel's surface (``a = (0.15, 0.01, -2.25)``, ``(-0.10, -0.09, -1.88)``,
  ``(0.13, 0.09, -2.80)`` mm): pressing a flat card, their centre of pressure reads (-0.25, -0.29) mm
  where this simulator's gel and our MuJoCo rebuild of their world (which resolves torques by the
  contract, and gives +1 and ``a`` within 0.2 mm of 0) both read +0.2 to +0.3 mm on each axis (a bias of
  a gel's structured tetrahedral split: 0.19 mm with 2 mm cells, 0.12 mm with 1 mm cells, the same
  anywhere on the card), and while sliding their spin torque ``T_z`` has the opposite sign of the
  replay's. Where a delay or a torque bias dominates the torque's residual (latency_s103,
  force_bias_s107) the fit gives +1. A separate torque gain with the contract's sign alone ends on the
  lower bound of its prior on such recordings;
- markers (sensor frame): ``x_rec = x0 + s_xy (x_sim - x0)``, ``y`` alike, ``z_rec = z0 + s_z (z_sim - z0)``
  with ``x0`` the rest position of each marker (the prediction's first sample, before contact);
- pixels: the pinhole ``u = f_x x / (z + d) + c_x``, ``v = f_y y / (z + d) + c_y`` (d the camera
  distance), with ``(f_x, c_x)`` and ``(f_y, c_y)`` fitted to the recording's own marker positions and
  pixels when it has both (the camera maps what the sensor measured; a model gap in the simulated
  marker motion then cannot bias the intrinsics), else to the simulated positions.

Gains, scales and focal lengths are kept within the sensor's declared prior (:mod:`sysid.gain_prior`:
+-15 % by default, per sensor in the sysid config file): a calibration off by more than that is a model
gap, not a calibration error. A gain the data push past its prior stops on the bound and is flagged, with
the value the data asked for and the likely physical cause (:attr:`CalibrationResult.gain_flags`), so
that a report never presents the bound as the answer. The fit uses the rows given (the training part of a
recording); the result is applied to any prediction of the same recording.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from typing import Any, Callable, Mapping

import numpy as np

from sim_core.errors import CalibrationError, SimulationDivergedError
from sysid.calibration_secant import SECANT_PARAMETERS, SECANT_REPLAYS, FirstReplay, secant_calibration
from sysid.drive_calibration import fit_drive
from sysid.fit import fit
from sysid.gain_prior import GainPrior, gain_flags, load_gain_prior

TORQUE_ARM_BOUND = 5.0e-3
"""Largest offset (m, per sensor-frame axis) of the torque reference point: a quarter of the gel
pad's width (20 mm). A wrench resolved about a point further off is a different sensor frame (a
mount or tool-point error a user must fix), not a calibration error."""


@dataclass(frozen=True)
class SensorCalibration:
    """Observation-level calibration of one tactile sensor (see the module docstring).

    Attributes:
        force_gain: wrench gain (-), on the forces and the torques alike (the moment of the forces).
        torque_sign: sign convention ``s_T`` of the recorded torques (+1: the moment of the force on the
            gel, the simulator's; -1: the moment of its reaction; module docstring).
        torque_arm_x, torque_arm_y, torque_arm_z: offset ``a`` of the point the recorded torques are
            resolved about from the simulator's, m, sensor frame (``T_rec = s_T g_F T_sim + a x F_rec``).
        marker_scale_xy, marker_scale_z: marker displacement scales (-).
        fx, fy: focal lengths, px; cx, cy: principal point, px; distance: camera to the undeformed
            contact surface, m (not fitted).
    """

    force_gain: float = 1.0
    torque_sign: float = 1.0
    torque_arm_x: float = 0.0
    torque_arm_y: float = 0.0
    torque_arm_z: float = 0.0
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
            w[..., 3:] = self.torque_sign * self.force_gain * w[..., 3:] + np.cross(self.torque_arm, w[..., :3])
            out["wrench"] = w
        if "markers_xyz" in out and marker_rest is not None:
            out["markers_xyz"] = scale_markers(out["markers_xyz"], marker_rest, self.marker_scale_xy, self.marker_scale_z)
        if "markers_uv" in out and "markers_xyz" in out:
            out["markers_uv"] = self.project(out["markers_xyz"])
        return out

    def derivative(self, channel: str, d: np.ndarray) -> np.ndarray:
        """The calibrated derivative of ``channel`` from the raw one ``d`` ``(n, ..., axes, p)``.

        Exact for the wrench (``dT = s_T g_F dT_sim + a x g_F dF_sim``) and the markers (linear maps);
        for the pixels the focal-length ratio to the scene camera is applied (first order: the marker scale's effect on the projection is
        neglected).
        """
        d = np.array(d, dtype=float)
        if channel == "wrench":
            d[..., :3, :] *= self.force_gain
            moment = np.cross(self.torque_arm, d[..., :3, :], axisb=-2, axisc=-2)
            d[..., 3:, :] = self.torque_sign * self.force_gain * d[..., 3:, :] + moment
        elif channel == "markers_xyz":
            d[..., :2, :] *= self.marker_scale_xy
            d[..., 2:, :] *= self.marker_scale_z
        elif channel == "markers_uv":
            d[..., 0, :] *= self.fx / self.nominal_fx
            d[..., 1, :] *= self.fy / self.nominal_fy
        return d

    @property
    def torque_arm(self) -> np.ndarray:
        """``(3,)`` the torque reference point's offset ``a``, m, sensor frame."""
        return np.array([self.torque_arm_x, self.torque_arm_y, self.torque_arm_z])

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


def _gain(data: np.ndarray, pred: np.ndarray, sigma: np.ndarray, bounds: tuple[float, float]) -> tuple[float, float | None]:
    """Weighted least-squares gain ``g`` of ``data ~ g pred`` (per-axis weights 1/sigma^2): the value within
    ``bounds`` (the least-squares optimum of a one-parameter quadratic on an interval is the clipped one)
    and the unbounded optimum; ``(1, None)`` when the prediction carries less than
    :data:`MIN_GAIN_INFORMATION` (not fitted)."""
    d = data / sigma
    p = pred / sigma
    den = float(np.sum(p * p))
    if not math.isfinite(den) or den < MIN_GAIN_INFORMATION:
        return 1.0, None
    asked = float(np.sum(d * p) / den)
    return float(np.clip(asked, *bounds)), asked


def _torque_calibration(data: np.ndarray, torque: np.ndarray, force: np.ndarray, gain: float,
                        sigma_t: np.ndarray, sigma_f: np.ndarray) -> tuple[float, np.ndarray]:
    """Weighted least squares of ``T_rec ~ s_T g_F T_sim + a x F`` (module docstring): ``(s_T, a)``.

    Args:
        data, torque: ``(n, 3)`` recorded and simulated torques, N m.
        force: ``(n, 3)`` the calibrated simulated forces, N.
        gain: the force gain ``g_F`` (-), fitted to the forces.
        sigma_t, sigma_f: ``(3,)`` noise levels of the torques and the forces.

    Returns:
        the sign (+1 unless the simulated torques carry :data:`MIN_GAIN_INFORMATION` and -1 gives a
        strictly lower weighted cost: maximum likelihood over a discrete parameter) and the arm ``a``
        ``(3,)`` m (fitted when the forces carry :data:`MIN_GAIN_INFORMATION`, else 0; within
        :data:`TORQUE_ARM_BOUND` per axis by ``scipy.optimize.lsq_linear``: the bounded optimum, not a
        clipped one).
    """
    from scipy.optimize import lsq_linear

    fit_sign = float(np.sum((torque / sigma_t) ** 2)) >= MIN_GAIN_INFORMATION
    fit_arm = float(np.sum((force / sigma_f) ** 2)) >= MIN_GAIN_INFORMATION
    ok = np.all(np.isfinite(np.concatenate([data, torque, force], axis=1)), axis=1)
    if not (fit_sign or fit_arm) or ok.sum() < 2:
        return 1.0, np.zeros(3)
    d, t, f = data[ok], torque[ok], force[ok]
    zero = np.zeros(len(d))
    # (a x F) = (a_y F_z - a_z F_y, a_z F_x - a_x F_z, a_x F_y - a_y F_x): columns of (a_x, a_y, a_z) per axis
    A = np.concatenate([np.stack([zero, f[:, 2], -f[:, 1]], axis=1) / sigma_t[0],
                        np.stack([-f[:, 2], zero, f[:, 0]], axis=1) / sigma_t[1],
                        np.stack([f[:, 1], -f[:, 0], zero], axis=1) / sigma_t[2]], axis=0)
    best = None
    for sign in ((1.0, -1.0) if fit_sign else (1.0,)):
        b = ((d - sign * gain * t) / sigma_t).T.reshape(-1)
        arm = np.zeros(3)
        if fit_arm:
            solution = lsq_linear(A, b, bounds=(-TORQUE_ARM_BOUND, TORQUE_ARM_BOUND))
            # a bound the solver reports active is taken exactly (lsq_linear may stop a rounding error inside it)
            arm = np.where(solution.active_mask != 0, np.sign(solution.active_mask) * TORQUE_ARM_BOUND, solution.x)
        cost = float(np.sum((A @ arm - b) ** 2))
        if best is None or cost < best[0]:
            best = (cost, sign, np.asarray(arm, dtype=float))
    return best[1], best[2]


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
                           fit_camera: bool = True, prior: GainPrior = GainPrior()) -> SensorCalibration:
    """Fit the sensor calibration to a recording (closed form, no replay): :func:`fit_sensor_gains`'s
    calibration."""
    return fit_sensor_gains(data, prediction, sigma, marker_rest, nominal, rows, fit_camera, prior)[0]


def fit_sensor_gains(data: Mapping[str, np.ndarray], prediction: Mapping[str, np.ndarray],
                     sigma: Mapping[str, np.ndarray], marker_rest: np.ndarray | None,
                     nominal: SensorCalibration, rows: Mapping[str, np.ndarray] | None = None,
                     fit_camera: bool = True, prior: GainPrior = GainPrior()) -> tuple[SensorCalibration, dict[str, float]]:
    """Fit the sensor calibration to a recording (closed form, no replay), within the gains' prior.

    Args:
        data: channel -> recorded values (shapes as in :meth:`SensorCalibration.apply`).
        prediction: channel -> raw (uncalibrated) aligned prediction.
        sigma: channel -> per-axis noise level (weights).
        marker_rest: ``(k, 3)`` marker rest positions, m (None: no marker scale fitted).
        nominal: the scene's calibration (camera intrinsics and distance; start values).
        rows: channel -> boolean mask of the rows to fit on (the training part); None: all rows.
        fit_camera: fit the camera intrinsics (else keep ``nominal``'s).
        prior: the gains' prior (:class:`sysid.gain_prior.GainPrior`; focal lengths relative to ``nominal``'s).

    Returns:
        the fitted :class:`SensorCalibration` and, per gain fitted (``force_gain``, ``marker_scale_xy``,
        ``marker_scale_z``, ``fx``, ``fy``), the value the data asked for before the prior bounded it (for
        :func:`sysid.gain_prior.gain_flags`). An intrinsic pair (f, c) that the rows do not determine (fewer than
        three samples, markers that never move) keeps the scene's values; a focal length the data push past its
        prior stops on the bound, with the principal point refitted for it.
    """
    def pick(ch: str, arr: np.ndarray) -> np.ndarray:
        return arr if rows is None or ch not in rows else arr[rows[ch]]

    fields: dict[str, Any] = nominal.as_dict()
    asked: dict[str, float] = {}

    def gain(key: str, d: np.ndarray, p: np.ndarray, s: np.ndarray, bounds_key: str) -> float:
        value, wanted = _gain(d, p, s, prior.bounds(bounds_key))
        if wanted is not None:
            asked[key] = wanted
        return value

    if "wrench" in data and "wrench" in prediction:
        d, p, s = pick("wrench", data["wrench"]), pick("wrench", prediction["wrench"]), sigma["wrench"]
        fields["force_gain"] = gain("force_gain", d[:, :3], p[:, :3], s[:3], "force_gain")
        sign, arm = _torque_calibration(d[:, 3:], p[:, 3:], fields["force_gain"] * p[:, :3], fields["force_gain"],
                                        s[3:], s[:3])
        fields["torque_sign"] = sign
        fields["torque_arm_x"], fields["torque_arm_y"], fields["torque_arm_z"] = (float(a) for a in arm)
    if "markers_xyz" in data and "markers_xyz" in prediction and marker_rest is not None:
        d = pick("markers_xyz", data["markers_xyz"]) - marker_rest
        p = pick("markers_xyz", prediction["markers_xyz"]) - marker_rest
        s = sigma["markers_xyz"]
        fields["marker_scale_xy"] = gain("marker_scale_xy", d[..., :2], p[..., :2], s[:2], "marker_scale")
        fields["marker_scale_z"] = gain("marker_scale_z", d[..., 2:], p[..., 2:], s[2:], "marker_scale")
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
                a, b = xyz[..., axis] / w, uv[..., axis]
                line = _affine(a, b)
                if line is None:  # an undetermined line keeps the scene's
                    continue
                ref = getattr(nominal, f_key)
                low, high = (ref * v for v in prior.bounds("focal"))
                asked[f_key] = line[0]
                f = float(np.clip(line[0], low, high))
                ok = np.isfinite(a) & np.isfinite(b)
                # the principal point for a bounded focal length: the least-squares offset at that slope
                fields[f_key], fields[c_key] = (line if f == line[0] else (f, float(np.mean(b[ok] - f * a[ok]))))
    return SensorCalibration(**fields), asked


def masked_rows(model, rows: Mapping[str, np.ndarray] | None) -> dict[str, np.ndarray] | None:
    """``rows`` (channel -> bool rows to fit on, None: all) less the rows ``model.row_mask`` leaves out (rows that
    contradict their channel's contract: :mod:`sysid.wrench_check`)."""
    mask = model.row_mask or {}
    if not mask:
        return None if rows is None else dict(rows)
    out = {ch: np.asarray(r, dtype=bool) for ch, r in (rows or {}).items()}
    for ch, keep in mask.items():
        keep = np.asarray(keep, dtype=bool)
        out[ch] = keep if ch not in out else out[ch] & keep
    return out


# ====================================================================================== calibration
CALIBRATION_PARAMETERS = ("gel.youngs_modulus", "gel.poisson_ratio", "friction.gel_sheet",
                          "sheet.bending_stiffness", "sensor.normal_offset")
"""Simulator parameters fitted by :func:`calibrate` by default: the ones uncertain on any real cell
that a recording of a press or a lift constrains (SYSID.md "Diagnosis", step 1). The sheet-table
friction is left out: on the reference recordings a factor of 2.7 on it changes the replay by less
than the noise (the clamped card does not slide on the table), so it is not identifiable there. The
contact offset ``eps`` is left out too (on the gel-card pair the same as the sensor's normal offset,
which is fitted)."""

CONTACT_PARAMETERS = ("contact.stiffness", "contact.eps_v")
"""The contact's compliance (``contact.stiffness``, the penalty stiffness k_c: how far the gel-card
and card-table contacts give under load) and the lagged friction's stick regularisation
(``contact.eps_v``, m/s: how fast a sheared gel creeps back under static friction): calibrated on
request (``--params`` with :data:`CALIBRATION_PARAMETERS` and these, and a replay budget that allows
steps). Run to convergence on nominal_s101 they bring every tactile channel under 3 (1.70 / 2.21 /
2.28, 18 replays; docs/benchmarks_log.md), which the default budget does not afford. By default
the stick regularisation alone is fitted after the parameter fit, on a secant
(:mod:`sysid.calibration_secant`, two replays: nominal_s101 2.09 / 2.84 / 2.01); given in ``params``
it is left to the parameter fit instead."""

FOLLOWED_RMS = 3.0
"""Whitened RMS (noise units) above which a calibrated channel is reported as not followed by the
model: issue 23's goal for every tactile channel after calibration."""

CALIBRATION_REPLAYS = 1
"""Default replay budget of the calibration's parameter fit (``thinshell diagnose``, ``thinshell
sysid --calibrate``): the fit's start, a plain replay at the scene values, and no step (a step
needs the start's tangents, one replay per parameter without them and a trial replay). A count and not seconds, so that the calibration, and every
answer read from it, is the same on any machine and under any load. One replay keeps a diagnosis
within the time of the wall-time budget it replaces (about three replays: 46-121 s per reference
recording idle), and gives the answers that budget gave under load (where it cut the fit before its
first step on 7 of 9 reference recordings). A step costs more than the goal allows: with the contact
parameters, 4 replays (one step: the start, two difference columns, a trial) took 66-978 s per
reference recording at load 3-7 on the 2-core VM, and the answers after it needed the per-press
timing sizes (:func:`sysid.diagnose.signatures.timing.timing_size`); docs/benchmarks_log.md,
2026-11-25 (session 34), issue 23. ``--calibration-replays N`` buys steps."""

CALIBRATION_BOUNDS: dict[str, tuple[str, float, float]] = {
    "gel.youngs_modulus": ("factor", 1.0 / 3.0, 3.0),
    "gel.poisson_ratio": ("absolute", 0.3, 0.499),
    "friction.gel_sheet": ("factor", 1.0 / 3.0, 3.0),
    "sheet.bending_stiffness": ("factor", 0.25, 4.0),
    "sensor.normal_offset": ("offset", -5.0e-4, 5.0e-4),
    "contact.stiffness": ("factor", 1.0 / 30.0, 30.0),
    "contact.eps_v": ("factor", 0.01, 10.0),
}
"""Search range of each calibration parameter around the scene's value (its prior), as
``(kind, low, high)``: ``factor`` (times the scene's value), ``absolute`` (SI) or ``offset`` (plus
the scene's value, SI). Chosen from what a data sheet leaves open, not from recordings: a gel's
modulus and a friction coefficient are known to a factor of 3 (neighbouring hardness grades,
surface finish), a card's bending stiffness to a factor of 4 (D ~ t^3: a thickness off by 60 %), an
elastomer's Poisson ratio lies in [0.3, 0.5), the sensor's mount along its normal is known to
0.5 mm; the contact stiffness is a penalty that stands for the contact's compliance, searched within
a factor 30 (from a contact that gives tens of micrometres under a newton to one ten times stiffer
than the scene's), and the stick regularisation within 1 % to 10x the scene's (0.1 mm/s to 0.1 m/s at
the default 0.01 m/s: a creep of 1 um to 1 mm per 10 ms step)."""


def calibration_bounds(model, params) -> dict[str, tuple[float, float]]:
    """Absolute search bounds ``name -> (lower, upper)`` of the calibration parameters ``params``
    around ``model``'s scene values (:data:`CALIBRATION_BOUNDS`; a parameter not listed there keeps
    :func:`sysid.fit.parameter_spec`'s range).

    Raises:
        ConfigError: an unknown parameter name (from ``model.parameter_value``).
    """
    out: dict[str, tuple[float, float]] = {}
    for name in params:
        if name not in CALIBRATION_BOUNDS:
            continue
        kind, low, high = CALIBRATION_BOUNDS[name]
        value = float(model.parameter_value(name))
        if kind == "factor":
            out[name] = (value * low, value * high)
        elif kind == "offset":
            out[name] = (value + low, value + high)
        else:
            out[name] = (low, high)
    return out


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
        replay_totals: ``{"scene_values": ..., "calibrated": ...}``: how the replays' steps ended
            (``StepTotals`` as a dict: steps, substep retries, relaxed acceptances); ``calibrated`` is
            None when the prediction at ``params`` is the fit's own best replay (not replayed again).
        wall_time_s: the calibration's wall time, s.
        secant: the :class:`sysid.calibration_secant.SecantStage` of the parameters without
            tangents (None when none was run).
        not_followed_where: channel -> :func:`not_followed_windows` of each channel above
            :data:`FOLLOWED_RMS` after calibration (None: not computed).
        drive: the :class:`sysid.drive_calibration.DriveCalibration` every replay took (None: the
            kinematic drive, not calibrated).
        gain_prior: the sensor gains' :class:`sysid.gain_prior.GainPrior` (None: not recorded).
        gain_flags: per fitted gain, :func:`sysid.gain_prior.gain_flags` (value, the value the data asked for,
            bounds, whether it stopped on a bound and the likely physical cause).
    """

    params: dict[str, float]
    sensor: SensorCalibration
    whitened_rms_before: dict[str, float]
    whitened_rms_after: dict[str, float]
    fit: Any = None
    prediction: dict[str, np.ndarray] | None = None
    replay_totals: dict[str, Any] | None = None
    wall_time_s: float | None = None
    secant: Any = None
    not_followed_where: dict[str, Any] | None = None
    drive: Any = None
    gain_prior: Any = None
    gain_flags: dict[str, Any] | None = None

    @property
    def gains_at_bound(self) -> list[str]:
        """The gains that stopped on a bound of their prior (their values are not answers)."""
        return [k for k, v in (self.gain_flags or {}).items() if v.get("at_bound")]

    def summary(self) -> dict[str, Any]:
        """JSON-ready summary: parameters, sensor calibration, whitened RMS before and after, and,
        when simulator parameters were fitted, their Gauss-Newton 1-sigma (``sigma``; scaled by the
        residual: ``sigma_scaled``), correlation matrix (``correlation``, in the order of
        ``fitted``), the fit's status, replays and wall time, the weight of each channel in the fit
        (``channel_weights``: ``1 / s^2`` with ``s`` its factor on the noise level, when reweighted)
        and the channels the calibrated model does not follow (``not_followed``: channel -> its
        whitened RMS after calibration, where above :data:`FOLLOWED_RMS`; ``not_followed_where``: where in
        time, :func:`not_followed_windows`)."""
        out: dict[str, Any] = {"params": dict(self.params), "sensor": self.sensor.as_dict(),
                               "whitened_rms_before": dict(self.whitened_rms_before),
                               "whitened_rms_after": dict(self.whitened_rms_after)}
        if self.fit is not None:
            def floats(d):
                return {k: (None if v is None else float(v)) for k, v in (d or {}).items()}
            out["fitted"] = list(getattr(self.fit, "names", ()) or ())
            out["sigma"] = floats(getattr(self.fit, "sigma", None))
            out["sigma_scaled"] = floats(getattr(self.fit, "sigma_scaled", None))
            corr = getattr(self.fit, "correlation", None)
            out["correlation"] = None if corr is None else np.round(np.asarray(corr, dtype=float), 4).tolist()
            out["status"] = getattr(self.fit, "status", None)
            out["fit_replays"] = getattr(self.fit, "sim_runs", None)
            weights = getattr(self.fit, "sigma_scale", None)
            if weights is not None:
                out["channel_weights"] = {ch: 1.0 / float(v) ** 2 for ch, v in weights.items()}
        out["not_followed"] = {ch: float(v) for ch, v in self.whitened_rms_after.items() if v > FOLLOWED_RMS}
        if self.not_followed_where:
            out["not_followed_where"] = self.not_followed_where
        if self.replay_totals is not None:
            out["replay"] = self.replay_totals
        if self.wall_time_s is not None:
            out["wall_time_s"] = float(self.wall_time_s)
        if self.secant is not None:
            out["secant"] = self.secant.summary()
        if self.drive is not None:
            out["drive"] = self.drive.summary()
        if self.gain_prior is not None:
            out["gain_prior"] = self.gain_prior.as_dict()
        if self.gain_flags is not None:
            out["gains"] = self.gain_flags
            out["gains_at_bound"] = self.gains_at_bound
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


GAP_MERGE_S = 0.05
"""Gap (s) across which two runs of samples the calibrated model does not follow are reported as one
window: five samples of the 100 Hz tactile streams (a reporting choice; it moves no fitted value)."""


def not_followed_windows(t: np.ndarray, residual: np.ndarray, sigma: np.ndarray) -> dict[str, Any]:
    """Where a calibrated channel is not followed: the time windows of its samples whose whitened RMS
    (over the sample's markers and axes) exceeds :data:`FOLLOWED_RMS`, and the channel's whitened RMS
    inside and outside them.

    Args:
        t: ``(n,)`` sample times, s from the recording's start.
        residual: ``(n, ...)`` data minus calibrated prediction, last axis the channel's axes.
        sigma: ``(axes,)`` noise level per axis.

    Returns:
        ``{"windows_s": [[t0, t1], ...], "whitened_rms_inside": float | None, "whitened_rms_outside":
        float | None, "fraction_of_samples": float}``; runs separated by less than
        :data:`GAP_MERGE_S` form one window; None where a part holds no sample.
    """
    n = min(len(t), len(residual))
    t = np.asarray(t, dtype=float)[:n]
    e = np.asarray(residual, dtype=float)[:n].reshape(n, -1, len(sigma)) / np.asarray(sigma, dtype=float)
    sq = np.nanmean(e ** 2, axis=(1, 2))
    flagged = np.sqrt(sq) > FOLLOWED_RMS
    windows: list[list[float]] = []
    for k in np.flatnonzero(flagged):
        if windows and t[k] - windows[-1][1] < GAP_MERGE_S:
            windows[-1][1] = float(t[k])
        else:
            windows.append([float(t[k]), float(t[k])])
    inside = np.zeros(len(t), dtype=bool)
    for a, b in windows:
        inside |= (t >= a) & (t <= b)

    def rms(mask):
        return float(np.sqrt(np.nanmean(sq[mask]))) if mask.any() else None

    return {"windows_s": [[round(a, 3), round(b, 3)] for a, b in windows], "whitened_rms_inside": rms(inside),
            "whitened_rms_outside": rms(~inside), "fraction_of_samples": float(inside.mean()) if len(t) else 0.0}


def calibrate(model, params=CALIBRATION_PARAMETERS, *, rows: Mapping[str, np.ndarray] | None = None,
              max_nfev: int = 8, workers: int = 1, max_time: float | None = None, max_replays: int | None = None,
              bounds: Mapping[str, tuple[float, float]] | None = None, sensor_first: bool = False,
              reweight_channels: bool = True, secant_params=SECANT_PARAMETERS,
              secant_replays: int = SECANT_REPLAYS, drive: bool = False,
              secant_first: Callable[[], FirstReplay | None] | None = None,
              secant_before: Callable[[Mapping[str, float]], None] | None = None,
              secant_last: Callable[[Mapping[str, float]], Any] | None = None, batched: bool = False,
              batch_size: int | str | None = None, prior: GainPrior | None = None) -> CalibrationResult:
    """Calibrate a replay to its recording: the simulator parameters ``params`` (weighted least
    squares, :func:`sysid.fit.fit`, within bounds around the scene's values) and the sensor
    calibration (closed form, :func:`fit_sensor_calibration`).

    Sets ``model.sensor_calibration`` and ``model.marker_rest``, and makes the fitted parameters the
    model's nominal (:meth:`~sysid.observation.ObservationModel.set_nominal`; the mount offset
    ``model.nominal_normal_offset``), so that every later replay and prediction of the model is
    calibrated. The fit starts from the scene's values (:meth:`~sysid.observation.ObservationModel.reset_nominal`).

    Steps (default): fit ``params`` from the scene values with the scene's sensor calibration
    (unit gains: the physics, not the sensor, is asked to explain the recording first; the fit's first
    replay, at the scene values, gives the whitened RMS before); fit the sensor calibration to the
    fit's best replay (it takes what the physics cannot: a gain, a marker scale, the
    camera), after the secant stage of the parameters without tangents (``secant_params``, by default
    the stick regularisation ``contact.eps_v``: :func:`sysid.calibration_secant.secant_calibration`,
    ``secant_replays`` plain replays, each judged after its own sensor calibration; its values are
    taken when they lower the stage's cost by more than the replays' numerical noise). The wrench
    gain and the gel's modulus, and the marker scale and the contact's compliance, are nearly
    interchangeable on a press (correlations of 0.97 on the reference recordings when
    fitted together), so the order decides which of them takes a common scale gap; the recordings
    cannot. With ``sensor_first`` the sensor calibration is fitted to the scene-value replay first
    and held during the parameter fit, then fitted again (the gains take the scale gap). Each fit
    lowers the same weighted cost, so neither order raises it.

    Args:
        model: :class:`~sysid.observation.ObservationModel` of the recording.
        params: simulator parameters to fit (empty: the sensor calibration only).
        rows: channel -> rows of the training part for the sensor calibration (None: all).
        max_nfev: function evaluations of the parameter fit.
        workers: processes for its batched replays.
        batched, batch_size: its finite-difference columns replayed as one batch of scene copies
            (:func:`sysid.fit.fit`).
        max_time: wall-time budget of the parameter fit, s (None: none). Its result depends on the
            machine's speed and load.
        max_replays: replay budget of the parameter fit (:func:`sysid.fit.fit`; None: none). The
            default diagnosis bounds its calibration by this count, so that it makes the same
            replays, and reaches the same parameters, on any machine.
        bounds: name -> ``(lower, upper)`` search bounds, SI (None: :func:`calibration_bounds`).
        sensor_first: fit the sensor calibration before the parameters (see above).
        reweight_channels: weigh each channel in the parameter fit by the model's gap at the scene
            values (:func:`sysid.fit.fit` ``reweight_channels``): a channel the model cannot follow
            (the card the gel lifts by a tack the model lacks: whitened RMS 82 on nominal_s109,
            against 2-4 on the tactile channels) would otherwise make the fit's steps, moving the
            contact parameters for a change of its cost within the replays' numerical noise. The
            factors are in the summary (``channel_weights``).
        secant_params: parameters without tangents fitted after ``params`` on secants with the
            sensor calibration projected out (:func:`sysid.calibration_secant.secant_calibration`;
            default the stick regularisation ``contact.eps_v``); those in ``params`` are left to the
            parameter fit. In the summary under ``secant``.
        secant_replays: replay budget of that stage (0: none), a count as ``max_replays``.
        drive: calibrate the effector's drive along the sensor normal first, in closed form
            (:func:`sysid.drive_calibration.fit_drive`, which chooses the compliant or the kinematic drive by
            delta-BIC), and make every replay, the first included, take it
            (:meth:`~sysid.observation.ObservationModel.set_drive_stiffness`; the parameter fit's Jacobian is
            then analytic through the drive, :func:`sysid.replay_drive.drive_sensitivities`); False: the
            recorded pose driven kinematically (the scene's prior).
        secant_first: gives the secant stage's first replay made beforehand (in another process beside
            the fit's start replay: :mod:`sysid.diagnose.probe_worker`), taken only where its parameters
            are bitwise the stage's first ones (:func:`sysid.calibration_secant.secant_calibration` ``first``).
        secant_before: called with the parameters of each of that stage's replays before it is made
            (:func:`sysid.calibration_secant.secant_calibration` ``before``).
        secant_last: makes that stage's last replay (:func:`sysid.calibration_secant.secant_calibration` ``last``;
            ``thinshell sysid``: with the tangents of its fit's first joint replay).
        prior: the sensor gains' prior (None: the sensor's in the packaged sysid config,
            :func:`sysid.gain_prior.load_gain_prior`).

    Returns:
        the :class:`CalibrationResult`.

    Raises:
        CalibrationError: the replay at the scene values diverged; the scene has no tactile sensor
            (a task scene: nothing to calibrate); a scene value outside ``bounds``.
        ConfigError: an unknown parameter name.
    """
    if model.sensor is None:
        raise CalibrationError(f"{model.scene_source}: the scene has no tactile sensor, so there is no sensor "
                               "calibration to fit (thinshell sysid fits a task scene's parameters without one)")
    t_start = time.perf_counter()
    channels = [ch for ch in model.sigma]
    model.sensor_calibration = None
    model.reset_nominal()
    prior = load_gain_prior(model.sensor) if prior is None else prior
    rows = masked_rows(model, rows)
    drive_fit = fit_drive(model) if drive else None
    model.set_drive_stiffness(drive_fit.replay_stiffness if drive_fit is not None else math.inf,
                              drive_fit.replay_damping if drive_fit is not None else 0.0)
    limits = calibration_bounds(model, params) if params and bounds is None else dict(bounds or {})
    totals: dict[str, Any] = {}
    result = None
    if params and not sensor_first:  # the fit's first replay is the one at the scene values
        try:
            result = fit(model, tuple(params), max_nfev=max_nfev, workers=workers, max_time=max_time,
                         max_replays=max_replays, bounds=limits, reweight_channels=reweight_channels,
                         batched=batched, batch_size=batch_size)
        except SimulationDivergedError as err:
            raise CalibrationError(f"{model.evidence.source.bag_path}: the replay at the scene values diverged: {err}") from err
        raw = {ch: np.asarray(v, dtype=float) for ch, v in result.prediction_initial.items()}
        totals["scene_values"] = None  # a replay with tangents: its step totals are not kept
    else:
        try:
            trace = model.simulate({})
        except SimulationDivergedError as err:
            raise CalibrationError(f"{model.evidence.source.bag_path}: the replay at the scene values diverged: {err}") from err
        raw = model.predict_raw(trace)
        totals["scene_values"] = _totals(trace)
    before = whitened_rms(model, raw, channels)
    model.marker_rest = np.asarray(raw["markers_xyz"][0], dtype=float) if "markers_xyz" in raw else None
    data = {ch: model.data(ch) for ch in raw}
    nominal = nominal_sensor_calibration(model)
    values: dict[str, float] = {}
    if params:
        if sensor_first:
            model.sensor_calibration = fit_sensor_calibration(data, raw, model.sigma, model.marker_rest, nominal, rows,
                                                              prior=prior)
            result = fit(model, tuple(params), max_nfev=max_nfev, workers=workers, max_time=max_time,
                         max_replays=max_replays, bounds=limits, reweight_channels=reweight_channels,
                         batched=batched, batch_size=batch_size)
        values = {k: float(v) for k, v in result.values.items()}
        model.set_nominal(values)
        if sensor_first:
            trace = model.simulate(values)
            raw = model.predict_raw(trace)
            totals["calibrated"] = _totals(trace)
        else:  # the fit's best replay, uncalibrated (no sensor calibration was set): no replay again
            raw = {ch: np.asarray(v, dtype=float) for ch, v in result.prediction_final.items()}
            totals["calibrated"] = None
    else:
        totals["calibrated"] = totals["scene_values"]
    stage = None
    secant_names = tuple(n for n in secant_params if n not in tuple(params))
    if secant_names and secant_replays:
        def sensor_calibrated(prediction):
            cal = fit_sensor_calibration(data, prediction, model.sigma, model.marker_rest, nominal, rows, prior=prior)
            return cal.apply(prediction, model.marker_rest)

        stage_bounds = {**calibration_bounds(model, secant_names), **dict(bounds or {})}
        stage = secant_calibration(model, values, raw, sensor_calibrated, secant_names, stage_bounds, secant_replays,
                                   first=secant_first, before=secant_before, last=secant_last)
        if stage.accepted:
            values.update(stage.values)
            model.set_nominal(values)
            raw = stage.raw
            totals["calibrated"] = None
    model.sensor_calibration, asked = fit_sensor_gains(data, raw, model.sigma, model.marker_rest, nominal, rows,
                                                       prior=prior)
    flags = gain_flags(model.sensor_calibration.as_dict(), asked,
                       {"fx": nominal.fx, "fy": nominal.fy}, prior)
    calibrated = model.sensor_calibration.apply(raw, model.marker_rest)
    after = whitened_rms(model, calibrated, channels)
    ev = model.evidence
    where = {}
    for ch in (c for c, v in after.items() if v > FOLLOWED_RMS and c in ev.t_ns):
        y = model.data(ch)
        t = (np.asarray(ev.t_ns[ch], dtype=np.int64)[:len(y)] - ev.start_ns) * 1e-9
        where[ch] = not_followed_windows(t, y - calibrated[ch], model.sigma[ch])
    return CalibrationResult(values, model.sensor_calibration, before, after, result, dict(calibrated), totals,
                             time.perf_counter() - t_start, stage, where, drive_fit, prior, flags)


def kinematic_reference(model, result: CalibrationResult, made=None) -> dict[str, np.ndarray] | None:
    """The calibrated replay with the recorded pose imposed (kinematic) where the calibration's replays went
    through the arm drive (``result.drive`` compliant): one more replay at the calibrated values, through
    the calibrated sensor; None where they were kinematic (the prediction is that replay) or nothing was
    calibrated. A force that leads the gel's own deformation (a damped gel) is read against it
    (:func:`sysid.diagnose.signatures.damping.lead_recording`).

    Args:
        model: the calibrated :class:`~sysid.observation.ObservationModel` (its sensor calibration set).
        result: its :class:`CalibrationResult`.
        made: that replay made elsewhere (a :class:`~sysid.observation.SimTrace` of the kinematic replay at
            ``result.params``, e.g. by :class:`sysid.diagnose.probe_worker.ProbeWorker` beside the calibration's last
            replay), or None: replayed here.

    Returns:
        channel -> calibrated prediction, shaped as ``result.prediction``; or None.

    Raises:
        SimulationDivergedError: the kinematic replay failed.
    """
    if result.drive is None or not result.drive.compliant or model.sensor_calibration is None:
        return None
    if made is not None:
        return dict(model.sensor_calibration.apply(model.predict_raw(made), model.marker_rest))
    stiffness, damping = model.drive_stiffness, model.drive_damping
    model.set_drive_stiffness(math.inf)
    try:
        raw = model.predict_raw(model.simulate(dict(result.params)))
    finally:
        model.set_drive_stiffness(stiffness, damping)
    return dict(model.sensor_calibration.apply(raw, model.marker_rest))


def _totals(trace) -> dict[str, Any] | None:
    """A replay's ``StepTotals`` as a JSON-ready dict (None when the trace has none)."""
    t = getattr(trace, "step_totals", None)
    return None if t is None else {k: v for k, v in asdict(t).items()}
