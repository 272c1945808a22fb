"""Turn a run's true signals into the contract's streams: rates, frames, averaging, effects, noise.

Pure numpy. Follows the reference README's "What is in every bag":

* 200 Hz: ``ee/pose``, ``ee/pose_cmd``, ``tactile/wrench``, ``/clock``; 100 Hz: ``tactile/markers``,
  ``sheet/points``; stamps k / rate from 0 while not past the motion's end.
* Sensor frame ``tactile`` = effector frame, orientation (x y z w) = (1 0 0 0) in world:
  ``p_s = R (p_w - p_ee)`` with ``R = diag(1, -1, -1)``.
* Tactile samples (wrench, markers) are the mean of the steps in the last 5 ms (exposure).
* Markers: bilinear interpolation of the gel's bottom-layer vertices at the 9 x 7 marker rest
  positions (2 mm grid), z = 0 at rest; pixels through the pinhole of ``camera``.
* Noise (1 sigma, white): markers x, y 15 um, z 20 um, u, v 0.15 px; force x, y 0.10 N, z 0.20 N;
  torque 4e-4 N m; ee position 5 um; sheet points 50 um.

Data-level effects (``effects``): ``tactile_latency_s`` (tactile streams show the value that long
ago, the first value held before), ``k1`` (radial lens distortion of the pixels in normalised
coordinates, ``u' = c_x + (u - c_x)(1 + k1 r^2)``), ``gel_creep_tau_s`` (the tactile response
follows a first-order lag of that time constant), ``force_bias`` (``offset + drift t + wobble_amp
sin(2 pi t / period + phase)`` added to the wrench).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

R_SENSOR = np.diag([1.0, -1.0, -1.0])
"""Rotation world -> sensor frame (180 deg about x)."""

SENSOR_QUAT_XYZW = (1.0, 0.0, 0.0, 0.0)
NOISE = {"marker_xy": 15e-6, "marker_z": 20e-6, "uv": 0.15, "force_xy": 0.10, "force_z": 0.20,
         "torque": 4e-4, "ee": 5e-6, "sheet": 50e-6}
FAST_HZ, SLOW_HZ, EXPOSURE_S = 200.0, 100.0, 0.005


@dataclass
class Streams:
    """Contract streams: stamps (ns) and values (SI) per topic role."""

    t_fast_ns: np.ndarray
    t_slow_ns: np.ndarray
    pose: np.ndarray          # (Nf, 3) measured ee position, world
    pose_cmd: np.ndarray      # (Nf, 3)
    wrench: np.ndarray        # (Nf, 6) sensor frame
    markers: np.ndarray       # (Ns, 63, 5) x y z u v, sensor frame
    sheet: np.ndarray         # (Ns, 273, 3) world


def marker_weights(gel_rest_xy: np.ndarray, grid_counts, marker_grid, pitch: float) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear weights (63, n_bottom) mapping gel bottom vertices to markers, and marker rest xy in the
    effector frame (world-aligned), m, shape (63, 2). Marker i = iy * mx + ix in the SENSOR frame."""
    gnx, gny = grid_counts
    xs = np.unique(np.round(gel_rest_xy[:, 0], 12))
    ys = np.unique(np.round(gel_rest_xy[:, 1], 12))
    mx, my = marker_grid
    w = np.zeros((mx * my, gnx * gny))
    rest = np.zeros((mx * my, 2))
    for iy in range(my):
        for ix in range(mx):
            i = iy * mx + ix
            sx, sy = (ix - (mx - 1) / 2) * pitch, (iy - (my - 1) / 2) * pitch
            wx, wy = sx, -sy  # sensor -> effector (world-aligned) frame
            rest[i] = (wx, wy)
            jx = min(np.searchsorted(xs, wx) - 1, gnx - 2)
            jy = min(np.searchsorted(ys, wy) - 1, gny - 2)
            ax = (wx - xs[jx]) / (xs[jx + 1] - xs[jx])
            ay = (wy - ys[jy]) / (ys[jy + 1] - ys[jy])
            for dx, dy, c in ((0, 0, (1 - ax) * (1 - ay)), (1, 0, ax * (1 - ay)), (0, 1, (1 - ax) * ay), (1, 1, ax * ay)):
                w[i, (jy + dy) * gnx + jx + dx] += c
    return w, rest


def _exposure_mean(t: np.ndarray, y: np.ndarray, t_out: np.ndarray) -> np.ndarray:
    """Mean of the samples with t in (t_out - EXPOSURE_S, t_out] (the first sample alone at t_out = 0)."""
    c = np.concatenate([np.zeros((1,) + y.shape[1:]), np.cumsum(y, axis=0)])
    hi = np.searchsorted(t, t_out + 1e-9, side="right")
    lo = np.searchsorted(t, t_out - EXPOSURE_S + 1e-9, side="right")
    lo = np.minimum(lo, hi - 1)
    return (c[hi] - c[lo]) / (hi - lo).reshape((-1,) + (1,) * (y.ndim - 1))


def _delayed(t: np.ndarray, y: np.ndarray, lag: float) -> np.ndarray:
    if lag <= 0:
        return y
    idx = np.searchsorted(t, t - lag + 1e-9, side="right") - 1
    return y[np.maximum(idx, 0)]


def _first_order_lag(t: np.ndarray, y: np.ndarray, tau: float) -> np.ndarray:
    out = np.empty_like(y)
    out[0] = y[0]
    for k in range(1, len(t)):
        a = np.exp(-(t[k] - t[k - 1]) / tau)
        out[k] = a * out[k - 1] + (1 - a) * y[k]
    return out


def pixels(xyz: np.ndarray, cam: Mapping[str, float], k1: float = 0.0) -> np.ndarray:
    """Pinhole pixels (u, v) of sensor-frame points (..., 3), with radial distortion ``k1`` (normalised coords)."""
    d = cam["distance"]
    xn, yn = xyz[..., 0] / (xyz[..., 2] + d), xyz[..., 1] / (xyz[..., 2] + d)
    g = 1.0 + k1 * (xn * xn + yn * yn)
    return np.stack([cam["fx"] * xn * g + cam["cx"], cam["fy"] * yn * g + cam["cy"]], axis=-1)


def observe(rec: Any, scene: Mapping[str, Any], duration_s: float, effects: Mapping[str, Any],
            rng: np.random.Generator) -> Streams:
    """Streams of the contract from a :class:`benchmarks.mujoco_world.world.Recording`."""
    tac = scene["sensors"]["tactile"]
    t = rec.t
    w_m, rest_xy = marker_weights(rec.gel_bottom_rest[:, :2], _grid_counts(rec), tac["marker_grid"],
                                  float(tac["marker_pitch"]))
    # true tactile signals at every step, sensor frame
    gel_rest_off = rec.gel_bottom[0] - rec.ee[0]            # includes the contact-radius offset
    marker_rest_w = w_m @ gel_rest_off                        # (63, 3) effector frame at rest
    mk_w = np.einsum("mg,tgc->tmc", w_m, rec.gel_bottom) - rec.ee[:, None, :]
    disp_w = mk_w - marker_rest_w[None]
    mk_s = (np.c_[rest_xy, np.zeros(len(rest_xy))] + disp_w) @ R_SENSOR.T
    wrench_s = np.c_[rec.wrench[:, :3] @ R_SENSOR.T, rec.wrench[:, 3:] @ R_SENSOR.T]
    lat = float(effects.get("tactile_latency_s", 0.0) or 0.0)
    mk_s, wrench_s = _delayed(t, mk_s, lat), _delayed(t, wrench_s, lat)
    tau = effects.get("gel_creep_tau_s")
    if tau:
        mk_s = _first_order_lag(t, mk_s, float(tau))
        wrench_s = _first_order_lag(t, wrench_s, float(tau))
    n_fast = int(np.floor(duration_s * FAST_HZ + 1e-9)) + 1
    n_slow = int(np.floor(duration_s * SLOW_HZ + 1e-9)) + 1
    tf = np.arange(n_fast) / FAST_HZ
    ts = np.arange(n_slow) / SLOW_HZ
    kf = np.searchsorted(t, tf - 1e-9)
    ks = np.searchsorted(t, ts - 1e-9)
    wrench = _exposure_mean(t, wrench_s, tf)
    bias = effects.get("force_bias")
    if bias:
        ph = 2 * np.pi * tf[:, None] / bias["wobble_period_s"] + np.asarray(bias["wobble_phase"])
        wrench = wrench + np.asarray(bias["offset"]) + np.asarray(bias["drift_per_s"]) * tf[:, None] \
            + np.asarray(bias["wobble_amp"]) * np.sin(ph)
    xyz = _exposure_mean(t, mk_s, ts)
    uv = pixels(xyz, tac["camera"], float(effects.get("k1", 0.0) or 0.0))
    sig = np.array([NOISE["force_xy"], NOISE["force_xy"], NOISE["force_z"]] + [NOISE["torque"]] * 3)
    wrench = wrench + rng.normal(size=wrench.shape) * sig
    xyz = xyz + rng.normal(size=xyz.shape) * np.array([NOISE["marker_xy"], NOISE["marker_xy"], NOISE["marker_z"]])
    uv = uv + rng.normal(size=uv.shape) * NOISE["uv"]
    pose = rec.ee[kf] + rng.normal(size=(n_fast, 3)) * NOISE["ee"]
    sheet = rec.sheet[ks] + rng.normal(size=rec.sheet[ks].shape) * NOISE["sheet"]
    return Streams((tf * 1e9).round().astype(np.int64), (ts * 1e9).round().astype(np.int64), pose, rec.cmd[kf],
                   wrench, np.concatenate([xyz, uv], axis=-1), sheet)


def _grid_counts(rec: Any) -> tuple[int, int]:
    xy = rec.gel_bottom_rest[:, :2]
    return len(np.unique(np.round(xy[:, 0], 12))), len(np.unique(np.round(xy[:, 1], 12)))
