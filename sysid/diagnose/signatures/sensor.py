"""Signature tests of the sensor's own observation chain, read off the recording alone.

* **Lens distortion** (SYSID.md: "static radial pattern growing like r^3 from the optical centre,
  present even without contact"): the recording holds both the markers' 3-D positions and their
  pixels, so the camera can be checked against itself. The pixels are regressed on the pinhole
  projection of the recorded positions, ``u = f_x x_n (1 + k1 r^2 + k2 r^4) + c_x`` (OpenCV's radial
  model, ``x_n = x / (z + d)``); the statistic is the whitened SSE that the radial terms remove
  beyond the intrinsics (``f_x, f_y, c_x, c_y`` refitted in both), about chi-square(2) without
  distortion. The residual's noise is the pixel noise plus the position noise carried through the
  projection.
* **Force bias** (SYSID.md: "slowly varying offset on the wrench only, present without contact"):
  where the gel touches nothing (no predicted contact, with a margin, recorded markers at rest, no
  recorded sheet hanging on the gel: :func:`sheet_on_gel_rows`, and not relaxing from a release:
  :func:`relaxing_rows`) the true wrench is zero, so an offset and a linear drift per axis are
  fitted to the recorded wrench there; the statistic is the whitened SSE they remove, about
  chi-square(12) with no bias.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from sysid.diagnose.signatures.base import (Recording, SignatureResult, dilate, marker_displacement,
                                            not_applicable, predicted_contact)
from sysid.diagnose.signatures.timing import TAU_MAX_S
from sysid.runs import segments

FREE_MARGIN_S = 0.1
"""Margin around predicted contact that is not counted as free gel, s (transients of approach and
release)."""

REST_DISPLACEMENT = 1.5
"""Whitened RMS marker displacement below which the recorded gel counts as at rest (noise alone
gives about 1)."""

RELAXATION_S = TAU_MAX_S
"""Time after a release during which the gel is still relaxing, s: the slowest relaxation the
diagnosis models (the timing tests' largest time constant,
:data:`~sysid.diagnose.signatures.timing.TAU_MAX_S`). A viscoelastic gel released from a load
``F`` still carries ``F exp(-t / tau)`` a time ``t`` after the release, in the wrench (which reads
the whole gel) before the markers' whole-grid displacement resolves it; after one slowest time
constant, at most ``exp(-1)`` of it remains."""


def _normalised(xyz: np.ndarray, d: float) -> tuple[np.ndarray, np.ndarray]:
    w = xyz[..., 2] + d
    return xyz[..., 0] / w, xyz[..., 1] / w


def lens_design(xyz: np.ndarray, camera: tuple[float, float, float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Design matrices of the pixel model in its linear parameters.

    Args:
        xyz: marker positions, sensor frame, m, shape ``(n, k, 3)``.
        camera: ``(fx, fy, cx, cy, d)``.

    Returns:
        ``(A_u, A_v)``, each ``(n*k, 4)``: columns ``[x_n, 1, f x_n r^2, f x_n r^4]`` for u (``y_n``
        for v, ``f`` the nominal focal length) so that ``u = A_u @ [fx, cx, k1, k2]`` with the
        distortion terms scaled by the nominal focal length.
    """
    fx, fy, _, _, d = camera
    xn, yn = _normalised(xyz, d)
    r2 = xn ** 2 + yn ** 2
    one = np.ones_like(xn)
    A_u = np.stack([xn, one, fx * xn * r2, fx * xn * r2 * r2], axis=-1).reshape(-1, 4)
    A_v = np.stack([yn, one, fy * yn * r2, fy * yn * r2 * r2], axis=-1).reshape(-1, 4)
    return A_u, A_v


def lens_test(rec: Recording) -> SignatureResult:
    """Radial distortion of the tactile camera from the recording's own positions and pixels."""
    effect = "lens_distortion"
    if not rec.has("markers_xyz", "markers_uv"):
        return not_applicable(effect, "needs both marker positions (x y z) and pixels (u v)")
    xyz = np.asarray(rec.data["markers_xyz"], dtype=float)
    uv = np.asarray(rec.data["markers_uv"], dtype=float)
    if xyz.shape[:2] != uv.shape[:2]:
        return not_applicable(effect, f"marker positions {xyz.shape} and pixels {uv.shape} differ in samples")
    fx, fy, _, _, d = rec.camera
    sx, sy, sz = rec.sigma["markers_xyz"]
    su, sv = rec.sigma["markers_uv"]
    # noise of u - u(xyz): pixel noise plus the position noise through the projection (d u / d x = fx / w)
    w = float(np.median(xyz[..., 2])) + d
    var_u = su ** 2 + (fx / w) ** 2 * sx ** 2
    var_v = sv ** 2 + (fy / w) ** 2 * sy ** 2
    A_u, A_v = lens_design(xyz, rec.camera)
    u, v = uv[..., 0].reshape(-1), uv[..., 1].reshape(-1)
    sse0 = 0.0
    for A, y, var in ((A_u, u, var_u), (A_v, v, var_v)):
        c0, *_ = np.linalg.lstsq(A[:, :2], y, rcond=None)
        sse0 += float(np.sum((y - A[:, :2] @ c0) ** 2) / var)
    # the distortion coefficients are shared by u and v: one joint fit of [fx, cx, fy, cy, k1, k2]
    n = A_u.shape[0]
    J = np.zeros((2 * n, 6))
    J[:n, 0:2] = A_u[:, :2] / np.sqrt(var_u)
    J[n:, 2:4] = A_v[:, :2] / np.sqrt(var_v)
    J[:n, 4:6] = A_u[:, 2:] / np.sqrt(var_u)
    J[n:, 4:6] = A_v[:, 2:] / np.sqrt(var_v)
    y = np.concatenate([u / np.sqrt(var_u), v / np.sqrt(var_v)])
    c, *_ = np.linalg.lstsq(J, y, rcond=None)
    r1 = y - J @ c
    sse1 = float(r1 @ r1)
    k1, k2 = float(c[4]), float(c[5])
    # amplitude of the radial pattern at the markers' largest radius, px
    xn, yn = _normalised(xyz, d)
    r2 = xn ** 2 + yn ** 2
    r2max = float(np.quantile(r2, 0.99))
    amp = float(max(fx, fy) * np.sqrt(r2max) * abs(k1 * r2max + k2 * r2max ** 2))
    # markers with the largest share of the removed pattern
    res_before = np.stack([(u - A_u[:, :2] @ np.array([c[0], c[1]])), (v - A_v[:, :2] @ np.array([c[2], c[3]]))], -1)
    per_marker = np.sqrt(np.mean(res_before.reshape(xyz.shape[0], xyz.shape[1], 2) ** 2, axis=(0, 2)))
    top = np.argsort(per_marker)[::-1][: max(3, xyz.shape[1] // 8)]
    t = rec.t["markers_uv"]
    return SignatureResult(
        effect=effect, statistic=max(sse0 - sse1, 0.0), effect_size=amp, effect_unit="px",
        estimate={"k1": k1, "k2": k2}, windows_s=[[float(t[0]), float(t[-1])]], channels=["markers_uv"],
        markers=sorted(top.tolist()),
        detail={"whitened_rms_pinhole": float(np.sqrt(sse0 / (2 * n))), "whitened_rms_radial": float(np.sqrt(sse1 / (2 * n))),
                "fx": float(c[0]), "cx": float(c[1]), "fy": float(c[2]), "cy": float(c[3]), "samples": int(n)})


def sheet_on_gel_rows(rec: Recording, channel: str) -> np.ndarray | None:
    """Samples where the recorded sheet touches or hangs on the gel, from the sheet points and the
    effector pose alone: some sheet point in front of the gel's face (within the markers' radius of
    the sensor axis) lies nearer the face than to where it started, along the face's normal.

    The gel's face is the plane through the effector's position ``x_e`` normal to its z axis ``n``
    (the sensor normal, pointing from the gel to what it touches: the markers' sensor frame is the
    effector's, mounted along that normal, and their rest positions, the first marker sample, lie on
    that face); its extent the largest radius of those rest positions about the axis. A sheet point
    ``p`` with start position ``p_0`` (the first sheet sample) has risen toward the gel by
    ``h = (p_0 - p) . n`` and lies ``g = (p - x_e) . n`` in front of the face. The sheet is on the
    gel where some point within the face's radius of its axis, and no more than that radius behind
    the face (a sheet pressed into the gel or wrapped round its edge), has ``h > g``: it lies beyond
    the midway between its start and the face. A resting sheet under a hovering pad has ``h`` at the
    noise and ``g`` the hover height; a sheet pressed by the gel has ``g <= 0``; a sheet carried by a
    tacked gel has ``h`` the lift and ``g`` the bonds' stretch; a sheet that only slid in its plane
    does not rise, so it is never counted. The markers' whole-grid displacement does not see a
    sheet hanging on a few tacked points of the gel (a lift-and-fold's hold); this does.

    Args:
        rec: the recording (``sheet_points``, ``pose`` and ``markers_xyz`` recorded).
        channel: the channel whose samples are returned.

    Returns:
        boolean mask ``(n,)`` on ``rec.t[channel]``, or None without those three channels.
    """
    if not rec.has("sheet_points", "pose", "markers_xyz"):
        return None
    ts = rec.t["sheet_points"]
    x = np.asarray(rec.data["sheet_points"], dtype=float)                  # (n, p, 3) world
    pose = np.asarray(rec.data["pose"], dtype=float)
    tp = rec.t["pose"]
    pos = np.stack([np.interp(ts, tp, pose[:, j]) for j in range(3)], axis=1)                  # (n, 3)
    nearest = np.clip(np.searchsorted(tp, ts), 0, len(tp) - 1)
    n = Rotation.from_quat(pose[nearest, 3:7]).apply(np.array([0.0, 0.0, 1.0]))               # (n, 3)
    rest = np.asarray(rec.data["markers_xyz"], dtype=float)[0]
    radius = float(np.max(np.linalg.norm(rest[:, :2], axis=1)))
    rel = x - pos[:, None, :]
    gap = np.einsum("npk,nk->np", rel, n)
    lateral = np.linalg.norm(rel - gap[..., None] * n[:, None, :], axis=2)
    rise = np.einsum("npk,nk->np", x[:1] - x, n)
    on = np.any((lateral <= radius) & (gap > -radius) & (rise > gap), axis=1)
    return np.interp(rec.t[channel], ts, on.astype(float)) > 0.0


def relaxing_rows(t: np.ndarray, engaged: np.ndarray, loaded: np.ndarray,
                  relaxation_s: float = RELAXATION_S) -> np.ndarray:
    """Samples within ``relaxation_s`` after a release: the last engaged sample of each run of
    engaged samples that holds a load (:func:`free_gel_rows`: a predicted contact or a sheet on the
    gel, not a marker-noise excursion at rest).

    Args:
        t: sample times, s, shape ``(n,)``.
        engaged: samples where the gel is loaded or deformed (contact, sheet on the gel, markers off
            rest), undilated, shape ``(n,)``.
        loaded: samples where the gel carries a load (a subset of ``engaged``), shape ``(n,)``.
        relaxation_s: how long a release relaxes, s (:data:`RELAXATION_S`).

    Returns:
        boolean mask ``(n,)``, True in ``(t_release, t_release + relaxation_s]`` after each release.
    """
    t = np.asarray(t, dtype=float)
    engaged = np.asarray(engaged, dtype=bool)
    loaded = np.asarray(loaded, dtype=bool)
    out = np.zeros(len(t), dtype=bool)
    # a run of the margin-dilated mask joins a load and the markers' return to rest that follows it
    for i0, i1 in segments(dilate(engaged, t, FREE_MARGIN_S)):
        if not loaded[i0:i1].any():
            continue
        t_release = t[i0 + int(np.flatnonzero(engaged[i0:i1])[-1])]
        out |= (t > t_release) & (t <= t_release + relaxation_s)
    return out


def free_gel_rows(rec: Recording) -> np.ndarray | None:
    """Wrench samples where the gel touches nothing: no predicted contact within
    :data:`FREE_MARGIN_S`, when markers are recorded, markers at rest, when the sheet is tracked, no
    sheet on the gel (:func:`sheet_on_gel_rows`) within :data:`FREE_MARGIN_S`, and not within
    :data:`RELAXATION_S` after a release (:func:`relaxing_rows`): the end of a predicted contact or of
    a sheet on the gel, or of the markers' return to rest that follows it (without a replay or a
    tracked sheet, the end of any run of markers off rest).

    Returns:
        boolean mask on ``rec.t["wrench"]``, or None when contact cannot be told (no replay and no
        markers).
    """
    tw = rec.t["wrench"]
    contact = predicted_contact(rec, "wrench")
    disp = marker_displacement(rec)
    if contact is None and disp is None:
        return None
    loads = [m for m in (contact, sheet_on_gel_rows(rec, "wrench")) if m is not None]
    loaded = np.any(loads, axis=0) if loads else np.zeros(len(tw), dtype=bool)
    engaged = loaded.copy()
    if disp is not None:
        engaged |= np.interp(tw, rec.t["markers_xyz"], (disp > REST_DISPLACEMENT).astype(float)) > 0.0
    if not loads:
        loaded = engaged
    return ~dilate(engaged, tw, FREE_MARGIN_S) & ~relaxing_rows(tw, engaged, loaded)


def force_bias_basis(t: np.ndarray, t_ref: float) -> np.ndarray:
    """Offset and drift basis ``[1, t - t_ref]``, shape ``(n, 2)``."""
    t = np.asarray(t, dtype=float)
    return np.stack([np.ones_like(t), t - t_ref], axis=1)


def force_bias_test(rec: Recording, min_samples: int = 20) -> SignatureResult:
    """Offset and drift of the wrench where the gel touches nothing."""
    effect = "force_bias"
    if not rec.has("wrench"):
        return not_applicable(effect, "needs the wrench")
    free = free_gel_rows(rec)
    if free is None:
        return not_applicable(effect, "cannot tell where the gel is free (no replay and no marker positions)")
    if int(free.sum()) < min_samples:
        return not_applicable(effect, f"only {int(free.sum())} wrench samples without contact (need {min_samples})")
    tw = rec.t["wrench"]
    w = np.asarray(rec.data["wrench"], dtype=float)[free] / rec.sigma["wrench"]
    t_ref = float(np.mean(tw[free]))
    X = force_bias_basis(tw[free], t_ref)
    coef, *_ = np.linalg.lstsq(X, w, rcond=None)
    fitted = X @ coef
    stat = float(np.sum(fitted ** 2))
    size = float(np.sqrt(np.mean(fitted ** 2)))
    sig = rec.sigma["wrench"]
    windows = [[float(tw[i0]), float(tw[i1 - 1])] for i0, i1 in segments(free)]
    return SignatureResult(
        effect=effect, statistic=stat, effect_size=size, effect_unit="noise sigma (RMS over axes)",
        estimate={**{f"offset_{a}": float(coef[0, i] * sig[i]) for i, a in enumerate(AXES)},
                  **{f"drift_{a}_per_s": float(coef[1, i] * sig[i]) for i, a in enumerate(AXES)},
                  "t_ref_s": t_ref},
        windows_s=windows, channels=["wrench"],
        detail={"free_samples": int(free.sum()), "offset_sigma": [float(v) for v in coef[0]],
                "drift_sigma_per_s": [float(v) for v in coef[1]]})


AXES = ("Fx", "Fy", "Fz", "Tx", "Ty", "Tz")


def apply_force_bias(wrench: np.ndarray, t: np.ndarray, estimate: dict[str, float]) -> np.ndarray:
    """A predicted wrench with the fitted offset and drift added, shape ``(n, 6)``."""
    X = force_bias_basis(t, float(estimate["t_ref_s"]))
    coef = np.array([[estimate[f"offset_{a}"] for a in AXES], [estimate[f"drift_{a}_per_s"] for a in AXES]])
    return np.asarray(wrench, dtype=float) + X @ coef


def apply_lens(xyz: np.ndarray, camera: tuple[float, float, float, float, float], estimate: dict[str, float]) -> np.ndarray:
    """Pixels of marker positions through the camera with the fitted intrinsics and radial terms,
    shape ``(n, k, 2)`` px (intrinsics from ``estimate`` when present, else ``camera``)."""
    fx, fy, cx, cy, d = camera
    fx = estimate.get("fx", fx)
    fy = estimate.get("fy", fy)
    cx = estimate.get("cx", cx)
    cy = estimate.get("cy", cy)
    xn, yn = _normalised(np.asarray(xyz, dtype=float), d)
    r2 = xn ** 2 + yn ** 2
    f = 1.0 + estimate.get("k1", 0.0) * r2 + estimate.get("k2", 0.0) * r2 * r2
    return np.stack([fx * xn * f + cx, fy * yn * f + cy], axis=-1)
