"""Semi-synthetic validation recordings: data-level effects applied to real recordings.

A recording of another engine (or of a real cell) that lacks an effect is read through
:func:`sysid.bagio.open_bag`, one data-level effect is applied to its recorded streams, and the
result is written back as a bag of the same contract (:class:`sysid.bagio.BagWriter`, same topics,
stamps, frames and ``scene.yaml``). The diagnosis then meets the effect on a recording whose
nominal model is *not* exactly this simulator's: the test of generalisation the reference set
(nine recordings, one motion per data effect) cannot give on its own.

Why this is independent of the diagnosis: every effect here is written from its physical or
sensor description (README of the reference set, SYSID.md "Typical signatures") on the
*recorded* streams, without the simulator, the calibration, or any code of
:mod:`sysid.diagnose` (this module imports neither): a delay is a shift of the stamps' values, a
lens is OpenCV's radial model on the pixels, a force bias is an offset, a drift and a slow
sinusoid, a creep a first-order relaxation of the tactile response. The diagnosis's candidate
models are fitted to the *calibrated replay*; here nothing is replayed, so a candidate that only
matches its own simulator cannot pass by construction.

Effects (``apply_effect``), each on the tactile streams only (markers ``x y z u v`` and the
wrench; the effector pose, its command and the tracked sheet are left as recorded):

* ``latency`` (``latency_s``): every tactile sample carries the value recorded ``latency_s``
  earlier (linear interpolation in time; an exact shift of samples, white noise unchanged, when
  ``latency_s`` is a multiple of the stream's period), the first value held before that.
* ``lens`` (``k1``, ``k2``): radial distortion of the pixels about the principal point,
  ``u' = c_x + (u - c_x)(1 + k1 r^2 + k2 r^4)``, ``r^2 = ((u - c_x)/f_x)^2 + ((v - c_y)/f_y)^2``
  with the scene camera (OpenCV's model in normalised coordinates, the reference set's
  convention); positions untouched.
* ``force_bias`` (``offset``, ``drift_per_s``, ``wobble_amp``, ``wobble_period_s``,
  ``wobble_phase``; six values each, N and N m): added to the wrench,
  ``b(t) = offset + drift t + wobble_amp sin(2 pi t / period + phase)``, t from the recording's
  start (the reference set's force-bias labels). :func:`force_bias_params` draws them for a scale
  in noise sigmas.
* ``gel_creep`` (``tau_s``, ``fraction``): the tactile response relaxes with a first-order lag,
  ``y' = y + fraction (L_tau y_s - y_s)``, ``L_tau`` the first-order low-pass of time constant tau
  and ``y_s`` the recording smoothed over :data:`CREEP_SMOOTH_S` (so that the recorded noise is kept
  and not low-passed: the added increment carries under half a noise sigma of smoothed noise, and
  the stream's noise level stays within about 15 %).

``visibility`` of each written recording is the whitened RMS of the change per channel (noise
sigmas estimated from the recording itself, :func:`sysid.noise.estimate_noise`; for the latency
and the creep, less the mean square the same operator gives white noise of that level, since what
it does to the recorded noise is no part of the effect),
the figure the reference set's labels give.

``python -m benchmarks.synthetic_effects OUT_DIR`` writes the validation set of
:data:`DEFAULT_PLAN` from the shared reference recordings, with a ``labels.yaml`` in the reference
set's format (``python -m benchmarks.diagnose_bench --labelled OUT_DIR`` reads it).
"""

from __future__ import annotations

import argparse
import math
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import yaml
from scipy.signal import savgol_filter

from sysid.bagio import BagContents, BagWriter, open_bag
from sysid.noise import estimate_noise

TACTILE_ROLES = ("markers", "wrench")
"""Roles whose streams the tactile effects change."""

EFFECTS = ("none", "latency", "lens", "force_bias", "gel_creep")
"""Data-level effects :func:`apply_effect` knows (``none``: rewritten unchanged, a control)."""

VARIANT = {"none": "nominal", "latency": "latency", "lens": "lens", "force_bias": "force_bias",
           "gel_creep": "gel_creep"}
"""Effect -> variant name of the reference set's labels."""

CREEP_SMOOTH_S = 0.05
"""Span of the quadratic Savitzky-Golay smoother whose low-pass increment the creep adds, s."""

AXES = ("Fx", "Fy", "Fz", "Tx", "Ty", "Tz")


# ================================================================================ effects
def delayed(t_ns: np.ndarray, values: np.ndarray, latency_s: float) -> np.ndarray:
    """``values`` observed ``latency_s`` late: the value at ``t - latency_s``, along axis 0.

    Args:
        t_ns: stamps, int ns, shape ``(n,)``, increasing.
        values: samples, shape ``(n, ...)``.
        latency_s: delay, s (>= 0).

    Returns:
        array of the shape of ``values``; samples before ``t_0 + latency_s`` hold the first value.

    Raises:
        ValueError: negative latency.
    """
    if latency_s < 0.0:
        raise ValueError(f"latency must be >= 0 s, got {latency_s}")
    t = (np.asarray(t_ns, dtype=np.int64) - int(t_ns[0])) * 1e-9
    v = np.asarray(values, dtype=float)
    flat = v.reshape(len(v), -1)
    out = np.empty_like(flat)
    for j in range(flat.shape[1]):
        out[:, j] = np.interp(t - latency_s, t, flat[:, j])
    return out.reshape(v.shape)


def radial_distortion(uv: np.ndarray, camera: Mapping[str, float], k1: float, k2: float = 0.0) -> np.ndarray:
    """Pixels through a radial lens about the principal point (OpenCV's model).

    Args:
        uv: pixels, shape ``(..., 2)``, px.
        camera: ``fx fy cx cy`` (px).
        k1, k2: radial coefficients of ``1 + k1 r^2 + k2 r^4`` (r in normalised coordinates).

    Returns:
        distorted pixels, shape of ``uv``.
    """
    uv = np.asarray(uv, dtype=float)
    fx, fy, cx, cy = (float(camera[k]) for k in ("fx", "fy", "cx", "cy"))
    xn, yn = (uv[..., 0] - cx) / fx, (uv[..., 1] - cy) / fy
    r2 = xn ** 2 + yn ** 2
    g = 1.0 + k1 * r2 + k2 * r2 * r2
    return np.stack([cx + fx * xn * g, cy + fy * yn * g], axis=-1)


def force_bias_params(scale_sigma: float, sigma: np.ndarray, rng: np.random.Generator) -> dict[str, Any]:
    """Random force-bias parameters of a given scale, in noise sigmas of each wrench axis.

    Per axis: offset of ``scale`` times sigma times a random sign and a factor in [0.5, 1]; a drift
    of up to ``scale / 2`` sigmas per second either way; a wobble of 0.05-0.3 ``scale`` sigmas with a
    period of 3-6 s (the ranges of the reference set's ``force_bias_s107`` labels relative to its
    ``bias_scale_sigma``).

    Args:
        scale_sigma: bias scale, noise sigmas.
        sigma: wrench noise per axis, shape ``(6,)``, N and N m.
        rng: random generator.

    Returns:
        ``offset``, ``drift_per_s``, ``wobble_amp``, ``wobble_phase`` (lists of 6) and ``wobble_period_s``.
    """
    s = float(scale_sigma) * np.asarray(sigma, dtype=float)
    sign = rng.choice([-1.0, 1.0], size=6)
    return {"offset": (sign * s * rng.uniform(0.5, 1.0, 6)).tolist(),
            "drift_per_s": (s * rng.uniform(-0.5, 0.5, 6)).tolist(),
            "wobble_amp": (s * rng.uniform(0.05, 0.3, 6)).tolist(),
            "wobble_period_s": float(rng.uniform(3.0, 6.0)),
            "wobble_phase": rng.uniform(0.0, 2.0 * math.pi, 6).tolist()}


def force_bias(t_s: np.ndarray, params: Mapping[str, Any]) -> np.ndarray:
    """The bias ``offset + drift t + wobble_amp sin(2 pi t / period + phase)``, shape ``(n, 6)``.

    Raises:
        ValueError: a parameter without six values, or a non-positive period.
    """
    t = np.asarray(t_s, dtype=float)[:, None]
    vec = {}
    for key in ("offset", "drift_per_s", "wobble_amp", "wobble_phase"):
        vec[key] = np.asarray(params[key], dtype=float)
        if vec[key].shape != (6,):
            raise ValueError(f"force_bias: {key} needs 6 values (Fx Fy Fz Tx Ty Tz), got {vec[key].shape}")
    period = float(params["wobble_period_s"])
    if not period > 0.0:
        raise ValueError(f"force_bias: wobble_period_s must be > 0, got {period}")
    return (vec["offset"] + vec["drift_per_s"] * t
            + vec["wobble_amp"] * np.sin(2.0 * math.pi * t / period + vec["wobble_phase"]))


def low_pass(t_s: np.ndarray, y: np.ndarray, tau: float) -> np.ndarray:
    """First-order low-pass ``tau dx/dt = y - x`` along axis 0, started at rest on the first sample;
    exact for an input linear between samples (first-order hold): over a step ``h`` with
    ``e = exp(-h / tau)``, ``x1 = e x0 + (1 - e) y0 + (y1 - y0) (1 - tau (1 - e) / h)``."""
    y = np.asarray(y, dtype=float)
    out = np.empty_like(y)
    out[0] = y[0]
    h = np.diff(np.asarray(t_s, dtype=float))
    e = np.exp(-h / tau)
    g = 1.0 - tau * (1.0 - e) / h
    for i in range(1, len(y)):
        out[i] = e[i - 1] * out[i - 1] + (1.0 - e[i - 1]) * y[i - 1] + g[i - 1] * (y[i] - y[i - 1])
    return out


def smoothed(t_ns: np.ndarray, values: np.ndarray, span_s: float = CREEP_SMOOTH_S) -> np.ndarray:
    """``values`` smoothed along axis 0 by a quadratic Savitzky-Golay filter over ``span_s`` s
    (at least 5 samples; a series shorter than the filter is returned as a copy)."""
    y = np.asarray(values, dtype=float)
    t = np.asarray(t_ns, dtype=np.int64)
    dt = float(np.median(np.diff(t))) * 1e-9 if len(t) > 1 else span_s
    w = max(5, int(round(span_s / dt)) | 1)
    return savgol_filter(y, w, 2, axis=0) if len(y) > w else y.copy()


def creep(t_ns: np.ndarray, values: np.ndarray, tau_s: float, fraction: float) -> np.ndarray:
    """A first-order creep of fraction ``fraction`` and time constant ``tau_s`` added to a noisy stream.

    ``y' = y + fraction (L_tau y_s - y_s)``: the response's share ``fraction`` follows its
    input with a first-order lag (a standard linear solid read at constant load: instantaneous part
    ``1 - fraction``, creeping part ``fraction``), computed on the recording smoothed by a quadratic
    Savitzky-Golay filter over :data:`CREEP_SMOOTH_S` so that the recorded white noise is not
    low-passed (the increment carries under half a sigma of smoothed noise).

    Raises:
        ValueError: ``tau_s <= 0`` or ``fraction`` outside [0, 1].
    """
    if not tau_s > 0.0:
        raise ValueError(f"gel_creep: tau_s must be > 0, got {tau_s}")
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"gel_creep: fraction must be in [0, 1], got {fraction}")
    t = (np.asarray(t_ns, dtype=np.int64) - int(t_ns[0])) * 1e-9
    y = np.asarray(values, dtype=float)
    ys = smoothed(t_ns, y)
    return y + fraction * (low_pass(t, ys, tau_s) - ys)


# ================================================================================ bags
@dataclass
class Synthetic:
    """One recording with an effect applied.

    Attributes:
        values: role -> new samples (shape of the source series' values).
        params: the effect's parameters (JSON-ready).
        visibility: channel -> whitened RMS of the change (``markers_xyz``, ``markers_uv``,
            ``wrench``, and ``wrench_axes`` per axis).
    """

    values: dict[str, np.ndarray]
    params: dict[str, Any] = field(default_factory=dict)
    visibility: dict[str, Any] = field(default_factory=dict)


def _camera(contents: BagContents) -> Mapping[str, float]:
    scene = contents.scene
    if scene is None or not scene.sensors:
        raise ValueError(f"{contents.path}: no scene.yaml with a sensor beside the bag (the lens needs the camera)")
    cam = next(iter(scene.sensors.values())).camera
    return {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy}


def _xyz_uv(series: Any) -> tuple[np.ndarray, np.ndarray]:
    names = series.field_names
    try:
        xyz = series.values[..., [names.index(c) for c in "xyz"]]
        uv = series.values[..., [names.index(c) for c in "uv"]]
    except ValueError as err:
        raise ValueError(f"topic {series.topic}: markers need fields x y z u v, have {names}") from err
    return xyz, uv


def _visibility(contents: BagContents, change: Mapping[str, np.ndarray],
                noise_change: Mapping[str, np.ndarray] | None = None) -> dict[str, Any]:
    """Whitened RMS of the effect's ``change`` (role -> new minus recorded values); with
    ``noise_change`` (the same operator applied to white noise of the recording's level) its mean
    square is subtracted: the part of the change that is the recorded noise's own."""
    out: dict[str, Any] = {}
    noise_change = noise_change or {}

    def rms(d: np.ndarray, s: np.ndarray, role: str, cols: list[int] | None, axis=None) -> Any:
        ms = np.mean((d / s) ** 2, axis=axis)
        if role in noise_change:
            dn = noise_change[role] if cols is None else noise_change[role][..., cols]
            ms = np.maximum(ms - np.mean((dn / s) ** 2, axis=axis), 0.0)
        return np.sqrt(ms)

    m = contents.series.get("markers")
    if m is not None:
        xyz0, uv0 = _xyz_uv(m)
        names = m.field_names
        for ch, a, cols in (("markers_xyz", xyz0, [names.index(c) for c in "xyz"]),
                            ("markers_uv", uv0, [names.index(c) for c in "uv"])):
            s = estimate_noise(m.t_ns, a)
            out[ch] = float(rms(change["markers"][..., cols], s, "markers", cols))
    w = contents.series.get("wrench")
    if w is not None:
        s = estimate_noise(w.t_ns, w.values)
        out["wrench"] = float(rms(change["wrench"], s, "wrench", None))
        out["wrench_axes"] = [float(v) for v in rms(change["wrench"], s, "wrench", None, axis=0)]
    return out


def apply_effect(contents: BagContents, effect: str, params: Mapping[str, Any] | None = None,
                 rng: np.random.Generator | None = None) -> Synthetic:
    """Apply one data-level effect to a read recording's tactile streams.

    Args:
        contents: the recording (:func:`sysid.bagio.open_bag`), with ``markers`` (fields x y z u v)
            and ``wrench``.
        effect: one of :data:`EFFECTS`.
        params: the effect's parameters: ``latency_s``; ``k1`` (and ``k2``); ``scale_sigma`` or the
            full force-bias set (:func:`force_bias`); ``tau_s`` and ``fraction``.
        rng: random generator for the force bias drawn from ``scale_sigma``.

    Returns:
        :class:`Synthetic` with every role's values (unchanged roles are the recorded arrays).

    Raises:
        ValueError: unknown effect, missing parameter or stream (names them).
    """
    if effect not in EFFECTS:
        raise ValueError(f"unknown effect {effect!r} (known: {', '.join(EFFECTS)})")
    params = dict(params or {})
    for role in TACTILE_ROLES:
        if role not in contents.series:
            raise ValueError(f"{contents.path}: no {role} stream (the effects act on the tactile streams)")
    values = {role: np.array(s.values, dtype=float) for role, s in contents.series.items()}
    m, w = contents.series["markers"], contents.series["wrench"]
    try:
        if effect == "latency":
            lat = float(params["latency_s"])
            values["markers"] = delayed(m.t_ns, m.values, lat)
            values["wrench"] = delayed(w.t_ns, w.values, lat)
        elif effect == "lens":
            names = m.field_names
            _, uv = _xyz_uv(m)
            iu, iv = names.index("u"), names.index("v")
            k1, k2 = float(params["k1"]), float(params.get("k2", 0.0))
            params = {"k1": k1, "k2": k2}
            duv = radial_distortion(uv, _camera(contents), k1, k2)
            values["markers"][..., iu], values["markers"][..., iv] = duv[..., 0], duv[..., 1]
        elif effect == "force_bias":
            if "offset" not in params:
                rng = rng if rng is not None else np.random.default_rng()
                scale = float(params["scale_sigma"])
                params = {"scale_sigma": scale, **force_bias_params(scale, estimate_noise(w.t_ns, w.values), rng)}
            t = (w.t_ns - int(contents.start_ns)) * 1e-9
            values["wrench"] = values["wrench"] + force_bias(t, params)
        elif effect == "gel_creep":
            tau, frac = float(params["tau_s"]), float(params["fraction"])
            values["markers"] = creep(m.t_ns, m.values, tau, frac)
            values["wrench"] = creep(w.t_ns, w.values, tau, frac)
    except KeyError as err:
        raise ValueError(f"effect {effect}: missing parameter {err.args[0]!r}") from err
    change = {role: values[role] - contents.series[role].values for role in TACTILE_ROLES}
    noise_change = None
    if effect in ("latency", "gel_creep"):
        # what the operator does to the recorded noise is no part of the effect: subtract what it
        # does to white noise of the recording's level
        noise_rng = np.random.default_rng(0)
        noise_change = {}
        for role in TACTILE_ROLES:
            s = contents.series[role]
            n = noise_rng.standard_normal(s.values.shape) * estimate_noise(s.t_ns, s.values)
            noise_change[role] = (delayed(s.t_ns, n, lat) if effect == "latency" else creep(s.t_ns, n, tau, frac)) - n
    return Synthetic(values, dict(params), _visibility(contents, change, noise_change))


def write_like(contents: BagContents, values: Mapping[str, np.ndarray], out_dir: str | Path,
               force: bool = False) -> Path:
    """Write ``values`` as a bag with ``contents``' topics, stamps, frames and ``scene.yaml``.

    Only the role topics are written (pose, pose_cmd, markers, wrench, sheet_points, clock; an
    image topic is not: its markers are in ``markers``).

    Raises:
        BagExistsError: ``out_dir`` exists (and not ``force``).
        ValueError: a role's values whose sample count differs from its stamps'.
    """
    order = [r for r in ("pose", "pose_cmd", "markers", "wrench", "sheet_points", "clock") if r in contents.series]
    events = []
    for role in order:
        s = contents.series[role]
        v = values.get(role, s.values)
        if len(v) != len(s.t_ns):
            raise ValueError(f"{role}: {len(v)} samples for {len(s.t_ns)} stamps")
        events.extend((int(t), order.index(role), i) for i, t in enumerate(s.t_ns))
    events.sort()
    scene = contents.scene_path if contents.scene_path is not None and Path(contents.scene_path).is_file() else None
    with BagWriter(out_dir, scene=scene, force=force) as bag:
        for t, k, i in events:
            role = order[k]
            s = contents.series[role]
            v = values.get(role, s.values)
            if role in ("pose", "pose_cmd"):
                bag.write_pose(s.topic, t, v[i], s.frame_id or "world")
            elif role == "wrench":
                bag.write_wrench(s.topic, t, v[i], s.frame_id)
            elif role == "markers":
                names = s.field_names
                xyz = v[i][:, [names.index(c) for c in "xyz"]]
                extra = {n: v[i][:, j] for j, n in enumerate(names) if n not in "xyz"}
                bag.write_points(s.topic, t, xyz, s.frame_id, extra_fields=extra or None)
            elif role == "sheet_points":
                bag.write_points(s.topic, t, v[i][:, :3], s.frame_id or "world")
            else:
                bag.write_clock(t, s.topic)
    return Path(out_dir)


# ================================================================================ the set
@dataclass(frozen=True)
class Item:
    """One recording of the validation set: ``effect`` with ``params`` applied to ``source``."""

    name: str
    source: str
    effect: str
    params: Mapping[str, Any]
    seed: int = 0


def _item(source: str, effect: str, level: str, params: Mapping[str, Any], seed: int = 0) -> Item:
    return Item(f"{effect}_{level}_{source}", source, effect, dict(params), seed)


def _source_items(source: str, *, control: bool = False, latency_s: Sequence[float] = (), k1: Sequence[float] = (),
                  scale_sigma: Sequence[tuple[float, int]] = (), tau_s: Sequence[float] = ()) -> tuple[Item, ...]:
    """The items of one source recording, in the order: the control, the latencies, the lens distortions,
    the force biases, the gel creeps; each named ``<effect>_<level>_<source>`` with the level written
    from its magnitude (``40ms``, ``k1m077``, ``3p5``, ``tau130``).

    Args:
        source: the source recording's name.
        control: whether to add the control (no effect).
        latency_s: transport delays [s].
        k1: radial lens distortion coefficients [-].
        scale_sigma: force biases as ``(bias in units of the force noise sigma, seed)`` pairs.
        tau_s: time constants of full first-order gel creeps (fraction 1) [s].
    """
    items = [_item(source, "none", "control", {})] if control else []
    items += [_item(source, "latency", f"{round(s * 1e3)}ms", {"latency_s": s}) for s in latency_s]
    items += [_item(source, "lens", f"k1{'p' if k >= 0 else 'm'}{round(abs(k) * 1e3):03d}", {"k1": k}) for k in k1]
    items += [_item(source, "force_bias", f"{b:g}".replace(".", "p"), {"scale_sigma": b}, seed=seed)
              for b, seed in scale_sigma]
    items += [_item(source, "gel_creep", f"tau{round(t * 1e3):03d}", {"tau_s": t, "fraction": 1.0}) for t in tau_s]
    return tuple(items)


DEFAULT_PLAN: tuple[Item, ...] = (
    # lift_fold (none of the nine reference recordings has a data effect on a lift), three magnitudes
    # each around the reference recordings' own (latency 40 ms, k1 -0.077, bias 3.5 sigma, creep tau
    # 0.13 s): half, once and 1.5-2 times. The creep is a full first-order lag (fraction 1): the lag
    # fitted to gel_creep_s108 takes a share of 0.97-1.0 of the response.
    *_source_items("nominal_s109", latency_s=(0.04,), k1=(-0.077,), scale_sigma=((3.5, 1),), tau_s=(0.13,)),
    *_source_items("nominal_s109", control=True, latency_s=(0.02,), k1=(-0.04,), scale_sigma=((1.75, 2),),
                   tau_s=(0.065,)),
    *_source_items("plastic_s102", latency_s=(0.04,)),
    # press_slide at the low end (the reference set has each at about once its visibility)
    *_source_items("nominal_s101", latency_s=(0.02,), k1=(0.04,), scale_sigma=((1.75, 3),), tau_s=(0.065,)),
    *_source_items("nominal_s101", control=True),
    # the large end on the lift
    *_source_items("nominal_s109", latency_s=(0.06,), k1=(0.15,), scale_sigma=((7.0, 4),), tau_s=(0.26,)),
)
"""The validation set written by ``python -m benchmarks.synthetic_effects`` (in this order: the
diagnosis runner takes them one by one)."""

WIDE_PLAN: tuple[Item, ...] = (
    # press-slides of the independent MuJoCo world (benchmarks/mujoco_world: other seeds, material
    # jitter up to 10 %, a slide along +x on nominal_s201 and a diagonal one on nominal_s202), at
    # magnitudes drawn around and beyond the reference recordings' own: latency 25-60 ms (reference
    # 40 ms), |k1| 0.03-0.12 of either sign (-0.077), force bias 2-6 sigma (3.5), full creeps of tau
    # 0.06-0.25 s (0.13 s)
    *_source_items("nominal_s201", control=True, latency_s=(0.025, 0.045), k1=(0.03, -0.06),
                   scale_sigma=((2.0, 11), (4.5, 12)), tau_s=(0.25, 0.10)),
    *_source_items("nominal_s202", control=True, latency_s=(0.06, 0.035), k1=(-0.12, 0.08),
                   scale_sigma=((6.0, 13), (3.0, 14)), tau_s=(0.06, 0.18)),
    # the reference press-slide at the magnitudes the default plan does not cover
    *_source_items("nominal_s101", latency_s=(0.03,), k1=(-0.12,), scale_sigma=((6.0, 15),), tau_s=(0.18,)),
    # lifts
    *_source_items("nominal_s109", latency_s=(0.025, 0.035), k1=(0.03, -0.12), scale_sigma=((2.0, 16),),
                   tau_s=(0.06, 0.18)),
    *_source_items("plastic_s102", k1=(0.06,), scale_sigma=((4.0, 17),), tau_s=(0.10,)),
)
"""A wider set: the data effects on press-slides of the independent MuJoCo world and on the
reference recordings, over the magnitude ranges a hidden set of the reference's kind may use
(``python -m benchmarks.synthetic_effects OUT --plan wide --source REF_DIR --source MUJOCO_DIR``)."""

LIFT_PLAN: tuple[Item, ...] = (
    # lift-and-folds of the independent MuJoCo world (benchmarks/mujoco_world: nominal_s301, 8 tack
    # bonds; plastic_s302, yield 0.0005) and the reference's nominal_s109, and one MuJoCo press-slide
    # (nominal_s213), at the low end of the magnitudes and the signs the wide plan leaves out:
    # latencies of 15-30 ms, positive k1 from 0.02, force biases of 1.5-4 sigma, creeps of 0.04-0.25 s
    *_source_items("nominal_s301", control=True, latency_s=(0.015, 0.02, 0.03), k1=(0.03, 0.05, -0.03),
                   scale_sigma=((1.5, 21), (2.5, 22), (4.0, 23)), tau_s=(0.05, 0.10, 0.20)),
    *_source_items("nominal_s109", latency_s=(0.015, 0.03), k1=(0.05,), scale_sigma=((1.5, 24), (3.0, 25)),
                   tau_s=(0.10, 0.25)),
    *_source_items("plastic_s302", latency_s=(0.03,), k1=(0.04,), scale_sigma=((3.0, 26),), tau_s=(0.13,)),
    *_source_items("nominal_s213", control=True, latency_s=(0.015, 0.02), k1=(0.02,), scale_sigma=((1.5, 27),),
                   tau_s=(0.04,)),
)
"""Lifts and the low end (``python -m benchmarks.synthetic_effects OUT --plan lift --source REF_DIR
--source MUJOCO_LIFT_DIR --source MUJOCO_SLIDE_DIR``)."""

PLANS = {"default": DEFAULT_PLAN, "wide": WIDE_PLAN, "lift": LIFT_PLAN}
"""Plans by name (``--plan``)."""


def _find_source(source_dirs: Sequence[Path], name: str) -> tuple[Path, dict[str, Any]]:
    """The first recording ``name`` among ``source_dirs`` and its label there (``{}`` without one).

    Raises:
        FileNotFoundError: ``name`` in none of them.
    """
    for d in source_dirs:
        if (d / name).exists():
            labels_path = d / "labels.yaml"
            labels = yaml.safe_load(labels_path.read_text()) if labels_path.is_file() else {}
            return d / name, (labels or {}).get(name, {}) or {}
    raise FileNotFoundError(f"source recording {name} in none of {', '.join(str(d) for d in source_dirs)}")


def make_set(source_dir: str | Path | Sequence[str | Path], out_dir: str | Path, plan: Sequence[Item] = DEFAULT_PLAN,
             force: bool = False) -> dict[str, Any]:
    """Write the validation set and its ``labels.yaml`` (the reference set's format).

    Each label keeps the variant, ``kind: data``, the magnitude, the effect's parameters, the
    source recording, its motion (from the source set's ``labels.yaml`` when present), the
    source's own variant (a physics effect already there) and the visibility.

    Args:
        source_dir: directory of the source recordings, or several (a source is read from the
            first that holds it).
        out_dir: directory of the set.
        plan: the recordings to write.
        force: replace existing bags.

    Returns:
        the labels written (name -> dict).

    Raises:
        FileNotFoundError: a source recording missing.
        BagExistsError: an output bag exists (and not ``force``).
    """
    dirs = [Path(source_dir)] if isinstance(source_dir, (str, Path)) else [Path(d) for d in source_dir]
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    labels: dict[str, Any] = {}
    for item in plan:
        src, src_label = _find_source(dirs, item.source)
        contents = open_bag(src, skip_roles=("image",))
        syn = apply_effect(contents, item.effect, item.params, np.random.default_rng(item.seed))
        dst = out_dir / item.name
        if dst.exists() and force:
            shutil.rmtree(dst)
        write_like(contents, syn.values, dst, force=force)
        magnitude = ({} if item.effect == "none" else
                     {k: v for k, v in syn.params.items() if k in ("latency_s", "k1", "scale_sigma", "tau_s")})
        labels[item.name] = {
            "bag": item.name, "variant": VARIANT[item.effect], "kind": "data" if item.effect != "none" else "none",
            "seed": item.seed, "magnitude": magnitude or None,
            "effect_params": {k: v for k, v in syn.params.items() if k not in magnitude} or None,
            "source": item.source, "source_variant": src_label.get("variant"),
            "motion": {"kind": (src_label.get("motion") or {}).get("kind")},
            "visibility": syn.visibility}
    (out_dir / "labels.yaml").write_text(yaml.safe_dump(labels, sort_keys=False))
    return labels


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m benchmarks.synthetic_effects OUT_DIR [--source DIR] [--force]``."""
    p = argparse.ArgumentParser(prog="python -m benchmarks.synthetic_effects", description=__doc__.split("\n")[0])
    p.add_argument("out", type=Path, help="directory of the validation set")
    p.add_argument("--source", type=Path, action="append",
                   help="directory the sources are read from (repeatable; the first holding a source is used; "
                        "default the shared reference set)")
    p.add_argument("--plan", choices=sorted(PLANS), default="default", help="which set to write")
    p.add_argument("--force", action="store_true", help="replace existing bags")
    args = p.parse_args(argv)
    sources = args.source or [Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "reference_bags"]
    labels = make_set(sources, args.out, PLANS[args.plan], force=args.force)
    for name, lab in labels.items():
        vis = ", ".join(f"{k} {v:.2f}" for k, v in lab["visibility"].items() if not isinstance(v, list))
        print(f"{name}: {lab['variant']} {lab['magnitude']} on {lab['source']} ({lab['motion']['kind']}); {vis}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
