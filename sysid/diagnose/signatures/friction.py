"""Signature test of stiction (static friction above kinetic friction), read off the recording alone.

SYSID.md "Typical signatures": stiction shows as **stick-slip at slide onset**. While the effector
starts a slide the gel's contact surface sticks to the sheet and the tangential load builds up; it
slips once the load reaches the static limit ``mu_s F_n`` and then falls to the kinetic level
``mu_k F_n``. With Coulomb friction (one coefficient) the friction ratio ``q = F_t / F_n`` rises
monotonically to its sliding level; with ``mu_s > mu_k`` it overshoots at breakaway and decays back
(a Stribeck law: the breakaway excess decays over a short slip time).

The test therefore needs no replay (the breakaway shape is relative to the same slide's own sliding
level, so a calibration gap in the friction coefficient or the normal force does not enter):

1. **Slides**: runs where the gel is loaded (compressive normal force above
   :data:`CONTACT_SIGMAS` sigmas of ``F_z``) and the commanded effector moves tangentially faster
   than :data:`SLIDE_FRACTION` of its peak tangential speed in contact, starting with the gel
   already loaded.
2. **Breakaway** of each slide: the first sample at which the gel's contact surface (effector
   position plus the mean marker displacement, in world) moves along the slide at least
   :data:`ONSET_FRACTION` of the command's speed: the end of the stick phase (a slide whose
   surface moves from its first sample has no stick phase and no breakaway).
3. **Shape**: in a window from the breakaway peak ``t0`` (the largest ratio within two tactile
   periods of the breakaway: the stick's rise before it is left out) to
   :data:`BREAKAWAY_WINDOW_S` after it (or the slide's end), the friction ratio along the slide
   ``q = -F . u / F_n`` (u the slide direction, F the force on the gel in world) is fitted by a
   sliding level with a linear trend, ``a + b (t - t0)``, and by the same plus a breakaway decay
   ``A exp(-(t - t0) / tau)``, ``A > 0``, tau on a grid of half tactile periods up to
   :data:`TAU_MAX_S` (a decay slower than that is a trend of the slide, not a breakaway). Each
   sample is weighted by the ratio's noise from the wrench noise model,
   ``sigma_q = sqrt(sigma_t^2 + q^2 sigma_n^2) / F_n``.

The statistic is the whitened SSE the decay removes, summed over breakaways (a likelihood-ratio
statistic, about chi-square with two degrees of freedom under Coulomb friction and white noise, a
little more for the choice of ``t0`` among a few samples and of tau on its grid); the
effect size is the relative breakaway excess ``A / a = mu_s / mu_k - 1`` of the strongest breakaway.
The excess is resolvable when it exceeds twice the ratio's relative noise on one sample
(:func:`resolvable_excess`, the effect-size threshold of :mod:`sysid.diagnose.signatures.null`).

Known limit: a contact that slips progressively (partial slip over a large soft pad: the edges slip
first) spreads the breakaway over the stick phase and shows a much smaller macroscopic excess than
the local ``mu_s / mu_k`` (docs/benchmarks_log.md, 2026-11-25: the reference engine's stiction
recording with ``mu_s / mu_k = 1.66`` shows a 5-10 % excess, statistic 5.7, below the threshold).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from sim_core.errors import BagReadError
from sysid.diagnose.signatures.base import Recording, SignatureResult, normal_force, not_applicable, segments

CONTACT_SIGMAS = 5.0
"""The gel is loaded where the compressive normal force exceeds this many sigmas of ``F_z``."""

SLIDE_FRACTION = 0.2
"""A slide: the commanded tangential speed above this fraction of its peak while loaded."""

ONSET_FRACTION = 0.5
"""Breakaway: the contact surface moves at this fraction of the command's speed."""

BREAKAWAY_WINDOW_S = 0.3
"""Window after the breakaway in which the sliding level and the decay are fitted, s."""

TAU_MAX_S = 0.1
"""Slowest breakaway decay searched, s."""

MIN_WINDOW_SAMPLES = 5
"""A breakaway window with fewer wrench samples is not tested."""

TREND_MIN_SAMPLES = 10
"""The sliding level gets a linear trend only in windows of at least this many samples (a short
slide's window fits a constant level)."""

RESOLVABLE_SIGMAS = 2.0
"""The breakaway excess must exceed this many relative sigmas of the ratio on one sample."""


@dataclass
class Breakaway:
    """One slide's breakaway and the friction ratio around it.

    Attributes:
        t_command: start of the slide (commanded tangential speed above the slide fraction), s.
        t_slip: first sample where the contact surface follows the command (end of the stick), s.
        t0: start of the fitted window: the largest ratio within two tactile periods of ``t_slip``, s.
        direction: unit slide direction in world, shape ``(2,)``.
        t: wrench sample times of the window, s, shape ``(m,)``.
        q: friction ratio along the slide there, shape ``(m,)``.
        sigma: its noise, shape ``(m,)``.
    """

    t_command: float
    t_slip: float
    t0: float
    direction: np.ndarray
    t: np.ndarray
    q: np.ndarray
    sigma: np.ndarray


def _rotations(rec: Recording, t: np.ndarray) -> Rotation:
    """Sensor-to-world rotations of the effector at times ``t`` (the pose sample at or after each).

    Raises:
        BagReadError: no pose sample has a non-zero orientation quaternion.
    """
    tp = rec.t["pose"]
    quat = np.asarray(rec.data["pose"], dtype=float)[:, 3:7]
    idx = np.clip(np.searchsorted(tp, t), 0, len(tp) - 1)
    q = quat[idx]
    bad = ~(np.linalg.norm(q, axis=1) > 0.0)
    if bad.all():
        raise BagReadError(f"{rec.name or 'recording'}: pose: no valid orientation quaternion (all zero)")
    q[bad] = q[~bad][0]  # a zero quaternion (dropped sample) takes the first valid orientation
    return Rotation.from_quat(q)  # (x, y, z, w), scipy's convention


def friction_ratio(rec: Recording, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Friction ratio along a slide and its noise on the wrench time base.

    Args:
        rec: recording with ``wrench`` and ``pose``.
        direction: unit slide direction in world, ``(2,)``.

    Returns:
        ``(q, sigma)``, each ``(n,)``: ``q = -F . u / F_n`` (F the force on the gel in world, u the
        direction; positive while the sheet's friction resists the slide) and its standard deviation
        from the wrench noise (``nan`` where ``F_n <= 0``).
    """
    tw = rec.t["wrench"]
    w = np.asarray(rec.data["wrench"], dtype=float)
    rot = _rotations(rec, tw)
    u3 = np.array([direction[0], direction[1], 0.0])
    s = rot.inv().apply(np.tile(u3, (len(tw), 1)))  # the slide direction in the sensor frame
    f_along = np.sum(w[:, :3] * s, axis=1)
    fn = normal_force(w)
    sig = np.asarray(rec.sigma["wrench"], dtype=float)[:3]
    # F_n = -F_z (sensor frame)
    var_t = np.sum((s * sig) ** 2, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = np.where(fn > 0, -f_along / fn, np.nan)
        sigma = np.where(fn > 0, np.sqrt(var_t + (q * sig[2]) ** 2) / fn, np.nan)
    return q, sigma


def _surface_along(rec: Recording, direction: np.ndarray, rest_rows: np.ndarray) -> np.ndarray:
    """World position along ``direction`` of the gel's mean contact-surface point (effector
    position plus the mean marker displacement), on the marker time base, m."""
    tm = rec.t["markers_xyz"]
    x = np.asarray(rec.data["markers_xyz"], dtype=float)
    disp = (x - np.median(x[rest_rows], axis=0)).mean(axis=1)  # (n, 3) sensor frame
    disp_w = _rotations(rec, tm).apply(disp)[:, :2]
    pose = np.asarray(rec.data["pose"], dtype=float)
    ee = np.stack([np.interp(tm, rec.t["pose"], pose[:, j]) for j in range(2)], axis=1)
    return (ee + disp_w) @ direction


def breakaways(rec: Recording) -> list[Breakaway]:
    """Every slide's breakaway (module docstring, steps 1-2).

    Returns:
        one :class:`Breakaway` per slide whose contact surface slips inside the slide with at
        least :data:`MIN_WINDOW_SAMPLES` wrench samples in its window; empty without slides.
    """
    cmd_ch = "pose_cmd" if rec.has("pose_cmd") else "pose"
    tp = rec.t[cmd_ch]
    cmd = np.asarray(rec.data[cmd_ch], dtype=float)[:, :2]
    tw = rec.t["wrench"]
    fn = normal_force(rec.data["wrench"])
    loaded_w = fn > CONTACT_SIGMAS * float(rec.sigma["wrench"][2])
    if not loaded_w.any():
        return []
    # backward differences: the motion that ends at each sample (a step of a target sequence
    # belongs to the sample it leads to, so a press between two slides splits them)
    v_cmd = np.zeros_like(cmd)
    v_cmd[1:] = np.diff(cmd, axis=0) / np.diff(tp)[:, None]
    speed = np.linalg.norm(v_cmd, axis=1)
    loaded_p = np.interp(tp, tw, loaded_w.astype(float)) > 0.5
    peak = float(speed[loaded_p].max()) if loaded_p.any() else 0.0
    if not peak > 0.0:
        return []
    tm = rec.t["markers_xyz"]
    loaded_m = np.interp(tm, tw, loaded_w.astype(float)) > 0.5
    first = int(np.argmax(loaded_m)) if loaded_m.any() else len(tm)
    rest_rows = np.arange(len(tm)) < first
    if rest_rows.sum() < 3:
        rest_rows = np.arange(len(tm)) < max(3, len(tm) // 20)
    period = rec.tactile_period()
    out = []
    for i0, i1 in segments(loaded_p & (speed > SLIDE_FRACTION * peak)):
        if i1 - i0 < 3 or i0 == 0 or not loaded_p[i0 - 1]:
            continue  # too short, or a slide that starts before the gel is loaded (touchdown while sliding)
        mean_v = v_cmd[i0:i1].mean(axis=0)
        if not np.linalg.norm(mean_v) > 0.0:
            continue
        u = mean_v / np.linalg.norm(mean_v)
        t_a, t_b = float(tp[i0]), float(tp[i1 - 1])
        surf = _surface_along(rec, u, rest_rows)
        v_s = np.gradient(surf, tm)
        v_c = np.interp(tm, tp, v_cmd @ u)
        inside = (tm >= t_a) & (tm <= t_b)
        slip = np.nonzero(inside & (v_s >= ONSET_FRACTION * v_c) & (v_c > 0.0))[0]
        if not len(slip) or slip[0] == np.argmax(inside):
            continue  # the contact sticks through the whole slide, or slips from its start (no stick)
        t_slip = float(tm[slip[0]])
        q, sigma = friction_ratio(rec, u)
        # the breakaway peak ends the stick: the largest ratio within two tactile periods of the
        # detected slip (the stick's rise before it is not part of the fitted window)
        near = np.nonzero((tw >= t_slip - 2.0 * period) & (tw <= t_slip + 2.0 * period) & loaded_w & np.isfinite(q))[0]
        if not len(near):
            continue
        t0 = float(tw[near[np.argmax(q[near])]])
        t_end = min(t0 + BREAKAWAY_WINDOW_S, t_b)
        m = (tw >= t0) & (tw <= t_end) & loaded_w & np.isfinite(q)
        if m.sum() < MIN_WINDOW_SAMPLES:
            continue
        out.append(Breakaway(t_a, t_slip, t0, u, tw[m], q[m], sigma[m]))
    return out


def _wls(cols: list[np.ndarray], y: np.ndarray, sigma: np.ndarray) -> tuple[float, np.ndarray]:
    X = np.stack(cols, axis=1) / sigma[:, None]
    c, *_ = np.linalg.lstsq(X, y / sigma, rcond=None)
    r = y / sigma - X @ c
    return float(r @ r), c


def decay_columns(t: np.ndarray, t0: float, tau: float) -> list[np.ndarray]:
    """Design columns ``[1, t - t0, exp(-(t - t0) / tau)]`` of the breakaway model (tau <= 0:
    without the decay; the trend ``t - t0`` only with at least :data:`TREND_MIN_SAMPLES` samples,
    else a zero column)."""
    dt = np.asarray(t, dtype=float) - t0
    cols = [np.ones_like(dt), dt if len(dt) >= TREND_MIN_SAMPLES else np.zeros_like(dt)]
    if tau > 0.0:
        cols.append(np.exp(-np.maximum(dt, 0.0) / tau))
    return cols


def fit_breakaway(b: Breakaway, taus: np.ndarray, rows: np.ndarray | None = None) -> dict:
    """Sliding level alone and with a breakaway decay, fitted to a breakaway window.

    Args:
        b: the breakaway.
        taus: decay times searched, s.
        rows: the window's samples used (None: all).

    Returns:
        dict with ``sse0`` / ``sse1`` (whitened), ``level`` (a), ``trend`` (b, 1/s), ``excess`` (A,
        >= 0), ``tau_s`` (0 when no positive decay fits) and ``coef0`` / ``coef1``.
    """
    rows = np.ones(len(b.t), bool) if rows is None else rows
    t, y, s = b.t[rows], b.q[rows], b.sigma[rows]
    sse0, c0 = _wls(decay_columns(t, b.t0, 0.0), y, s)
    best = (sse0, 0.0, np.array([c0[0], c0[1], 0.0]))
    for tau in taus:
        sse, c = _wls(decay_columns(t, b.t0, float(tau)), y, s)
        if c[2] > 0.0 and sse < best[0]:
            best = (sse, float(tau), c)
    sse1, tau, c1 = best
    return {"sse0": sse0, "sse1": sse1, "level": float(c1[0]), "trend": float(c1[1]), "excess": float(c1[2]),
            "tau_s": tau, "coef0": c0, "coef1": c1}


def decay_taus(rec: Recording) -> np.ndarray:
    """Decay times searched: half tactile periods from one period up to :data:`TAU_MAX_S`."""
    period = rec.tactile_period()
    return np.arange(period, TAU_MAX_S + 1e-9, period / 2.0)


def _readable(rec: Recording) -> bool:
    """Whether the recording has the wrench, the pose with a valid orientation and the markers."""
    if not rec.has("wrench", "pose", "markers_xyz"):
        return False
    return bool((np.linalg.norm(np.asarray(rec.data["pose"], dtype=float)[:, 3:7], axis=1) > 0.0).any())


def resolvable_excess(rec: Recording) -> float:
    """Smallest relative breakaway excess the recording resolves: :data:`RESOLVABLE_SIGMAS` times the
    friction ratio's relative noise on one sample, at the median of the breakaway windows (twice the
    noise at a ratio of 1 and the median loaded normal force without slides)."""
    bs = breakaways(rec) if _readable(rec) else []
    if bs:
        rel = np.concatenate([b.sigma / np.maximum(np.abs(b.q), 1e-6) for b in bs])
        return float(RESOLVABLE_SIGMAS * np.median(rel))
    if not rec.has("wrench"):
        return float("inf")
    fn = normal_force(rec.data["wrench"])
    sig = np.asarray(rec.sigma["wrench"], dtype=float)
    loaded = fn > CONTACT_SIGMAS * float(sig[2])
    if not loaded.any():
        return float("inf")
    return float(RESOLVABLE_SIGMAS * np.hypot(sig[0], sig[2]) / np.median(fn[loaded]))


def stiction_test(rec: Recording) -> SignatureResult:
    """Breakaway overshoot of the friction ratio at slide onset (module docstring)."""
    effect = "stiction"
    if not rec.has("wrench", "pose", "markers_xyz"):
        return not_applicable(effect, "needs the wrench, the effector pose and the marker positions")
    if not _readable(rec):
        return not_applicable(effect, "the effector pose has no valid orientation (all-zero quaternions)")
    bs = breakaways(rec)
    if not bs:
        return not_applicable(effect, "no slide under load in which the gel's contact surface slips")
    taus = decay_taus(rec)
    fits = [fit_breakaway(b, taus) for b in bs]
    stats = [max(f["sse0"] - f["sse1"], 0.0) for f in fits]
    rel = [f["excess"] / f["level"] if f["level"] > 0.0 else 0.0 for f in fits]
    k = int(np.argmax(stats))
    events = [{"t_command_s": b.t_command, "t_slip_s": b.t_slip, "direction": b.direction.tolist(),
               "samples": int(len(b.t)), "statistic": s, "kinetic_ratio": f["level"], "excess": f["excess"],
               "relative_excess": r, "decay_s": f["tau_s"], "trend_per_s": f["trend"]}
              for b, f, s, r in zip(bs, fits, stats, rel)]
    best = fits[k]
    return SignatureResult(
        effect=effect, statistic=float(sum(stats)), effect_size=max(float(rel[k]), 0.0),
        effect_unit="(mu_s / mu_k - 1 at breakaway)",
        estimate={"static_over_kinetic": 1.0 + max(float(rel[k]), 0.0), "kinetic_ratio": best["level"],
                  "decay_s": best["tau_s"]},
        windows_s=[[float(b.t[0]), float(b.t[-1])] for b in bs], channels=["wrench", "markers_xyz"], markers=[],
        detail={"breakaways": events, "resolvable_excess": resolvable_excess(rec)})
