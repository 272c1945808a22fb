"""Signature test of stiction (static friction above kinetic friction), read off the recording alone.

SYSID.md "Typical signatures": stiction shows as **stick-slip at slide onset**. While the effector
starts a slide the gel's contact surface sticks to the sheet and the tangential load builds up; it
slips once the load reaches the static limit ``mu_s F_n`` and then falls to the kinetic level
``mu_k F_n``. With Coulomb friction (one coefficient) the friction ratio ``q = F_t / F_n`` rises
monotonically to its sliding level; with ``mu_s > mu_k`` it overshoots at breakaway and decays back
(a Stribeck law: the breakaway excess decays over a short slip time).

The test needs no replay: the breakaway shape is relative to the same slide's own sliding level,
so a calibration gap in the friction coefficient or the normal force does not enter.

1. **Slides**: runs where the gel is loaded (compressive normal force above
   :data:`CONTACT_SIGMAS` sigmas of ``F_z``) and the commanded effector moves tangentially faster
   than :data:`SLIDE_FRACTION` of its peak tangential speed in contact, starting with the gel
   already loaded.
2. **Breakaway** of each slide: the first sample at which the gel's contact surface (effector
   position plus the mean marker displacement, in world) moves along the slide at least
   :data:`ONSET_FRACTION` of the command's speed: the end of the stick phase (a slide whose
   surface moves from its first sample has no stick phase and no breakaway).
3. **Shape**: the tangential load is read twice, from independent sensors: the **mean marker
   shear** against the slide (the gel's elastic shear carries the tangential load on the gel: a
   thin elastic layer's surface displacement is proportional to its local traction, so the mean
   over markers covering the pad follows the total tangential force; its noise is the marker
   noise over the square root of the marker count, about ten times below the wrench's relative
   noise on the reference cell) and the **friction ratio** ``q = -F . u / F_n`` of the wrench (u
   the slide direction, F the force on the gel in world). In a window from the breakaway peak
   ``t0`` (the largest value within two tactile periods of the breakaway: the stick's rise before
   it is left out) to :data:`BREAKAWAY_WINDOW_S` after it (or the slide's end), each series is
   fitted by a sliding level with a linear trend, ``a + b (t - t0)``, and by the same plus a
   breakaway decay ``A exp(-(t - t0) / tau)``, ``A > 0``, tau on a grid of half tactile periods up
   to :data:`TAU_MAX_S` (a decay slower than that is a trend of the slide, not a breakaway), each
   sample weighted by its noise from the noise model (the ratio's:
   ``sigma_q = sqrt(sigma_t^2 + q^2 sigma_n^2) / F_n``).
4. **Normal load**: under Coulomb friction the sliding tangential load is ``mu F_n``, so a
   breakaway excess of the shear that the normal force shares is a change of the normal load, not
   static friction. The normal load is fitted on the shear's window with the same ``t0`` and tau,
   read in the wrench's normal force and, where the effector is compliant and its lag follows the
   load, in the effector's lag against the sensor normal (:func:`normal_load_excess`); its relative
   excess is subtracted from the shear's.

The statistic is the whitened SSE the decay removes from both series, each over its window's
dispersion beyond the noise model (:func:`roughness`: the whitened second differences' variance,
floored at 1; a quasi-likelihood F statistic, McCullagh & Nelder, *Generalized Linear Models*, 2nd
ed., section 9.2), summed over breakaways: about chi-square with four degrees of freedom under
Coulomb friction and white noise, a little more for the choice of ``t0`` among a few samples and of
tau on its grid. The dispersion takes in a sliding contact's tactile roughness, which the noise
model leaves out (the mean marker shear of a sliding MuJoCo pad scatters 2-3 times its white-noise
sigma from sample to sample): without it a slow decay that removes 2 % of a rough window's SSE
reads as a breakaway that no held-out sample confirms. The effect size is the normal-load-corrected
relative excess of the tangential load at the strongest breakaway, ``A / a`` of the shear minus that
of the normal force: the macroscopic
``mu_s / mu_k - 1``. It is resolvable when above :data:`RESOLVABLE_SIGMAS` standard deviations of
that difference, propagated from the noise model through both fits (:func:`resolvable_excess`, the
effect-size threshold of :mod:`sysid.diagnose.signatures.null`).

A soft pad slips progressively (partial slip: the lightly loaded edges slip first, the centre
last), so the macroscopic excess is well below the local ``mu_s / mu_k - 1``: on the reference
engine's stiction recording, local 1.66, macroscopic about 11 % (docs/benchmarks_log.md, 2026-11-25).
The wrench alone resolves it only at about 5 noise units; the marker shear at several hundred.

**Sheet yield**: a sheet that yields limits the tangential load it passes to the gel to what its
fold resists, below the friction limit: on a slide toward a clamped edge a plastic card folds ahead of
the pad, the load rises to the yield and falls while the fold grows, a breakaway shape with no
static friction in it (the gel sticks to the card and slides at no friction limit). Where the
recording keeps a resolvable permanent set after release (the bending-plasticity test,
:mod:`sysid.diagnose.signatures.sheet`) and the set's points rose by at least that resolvable size
during a tested slide, the fold formed while sliding: the breakaway is the sheet's yield and the
effect size is 0 (the result's ``reason`` and ``detail["sheet_yield"]`` say so). Stiction and
plasticity together on one slide toward a clamped edge are then read as plasticity alone.

A yield is also read while it happens, without a released window (a kept fold that still touches the
lifted pad leaves none; where the recording does release the sheet and it keeps no resolvable set,
:func:`released_flat`, the sheet did not yield and this reading is not made): past the breakaway's
decay (:data:`TAU_MAX_S` after its peak) to the slide's end, the sheet's crest (its highest point)
rises by at least the resolvable set while the tangential load falls with it. A card carried by the
pad that buckles elastically passes a load that stays at or above its buckling load as the fold
grows (the elastica's post-buckling branch); a card that yields passes what its plastic hinge
resists, ``M_p`` over the fold's lever arm, which falls as the fold rises; friction at the kinetic
level follows the normal load and not the fold. The mean marker shear and the normal force are each
regressed on the crest's height over that part of the slide (:func:`load_against_fold`); the yield
is read where the shear's relative fall over the crest's rise exceeds the normal force's by
:data:`RESOLVABLE_SIGMAS` standard deviations of the difference (each from its regression's residual
dispersion, which takes in the tactile roughness of a sliding contact beyond the white noise model).

Sensitivity: on the reference engine's stiction recording (static/kinetic 1.66, an overshoot of the
mean marker shear 42 um or 5.6 % above the sliding line at its peak) the test names the breakaway with
its overshoot scaled down to 0.3 (statistic 75), not at 0.2 (46) or with the overshoot removed (19):
if the overshoot grows in proportion to ``mu_s / mu_k - 1``, the reference engine's stiction on that
motion is named from about 1.2 (docs/benchmarks_log.md, session 41).

Known limits: a stiction that only raises the sliding level (no breakaway drop within the slide) is
not a breakaway and is not found; nor is one whose pad passes from stick to slip by partial slip with
the tangential load rising monotonically to its sliding level. The MuJoCo world of
``benchmarks/mujoco_world`` switches the pad's friction to kinetic once its contact layer's mean speed
passes 2 mm/s, before the load reaches the static limit, and back to static below 0.5 mm/s: its
press-slides at static/kinetic 1.4-2.0 carry no stiction a recording can show. Each of three rebuilt
with the same seed, motion, materials and noise draws but static = kinetic (its nominal twin) matches
it through press, stick and breakaway to 0.5 marker-noise sigmas (RMS over the markers of the whitened
difference; the calibrated replay's own gap there is 7.5-7.8 sigmas); where the static coefficient
comes back at the slide's end or during it, the twins part by 1.2-3.9 sigmas while sliding and after,
as a tangential load a few per cent higher, which a kinetic coefficient a few per cent higher gives
as well (docs/benchmarks_log.md, sessions 37 and 41). Switched at gross breakaway instead
(``generate --stiction-switch load``) the breakaway shows, and is named on 0/3, 1/3, 2/3 and 3/3 press-slides
at 1.1, 1.25, 1.45 and 1.7 (session 51). Tactile latency or creep on top of stiction
delays the shear against the pose, so the window starts on the shear's rise and the decay is not found.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import chi2 as chi2_law

from sim_core.errors import BagReadError
from sysid.diagnose.signatures.base import Recording, SignatureResult, normal_force, not_applicable
from sysid.diagnose.signatures.sheet import plasticity_test, resolvable_set, set_rise
from sysid.noise import robust_scale
from sysid.runs import segments

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

LAG_CHECK_ALPHA = 1e-3
"""The effector's lag is used as a normal-load measure only if its fit to the wrench's normal force
passes a chi-square goodness-of-fit test at this false-rejection rate."""

RESOLVABLE_SIGMAS = 2.0
"""The normal-load-corrected breakaway excess must exceed this many of its standard deviations."""


@dataclass
class Breakaway:
    """One slide's breakaway and a measure of the tangential load around it.

    Attributes:
        t_command: start of the slide (commanded tangential speed above the slide fraction), s.
        t_slip: first sample where the contact surface follows the command (end of the stick), s.
        t0: start of the fitted window: the largest value of ``q`` within two tactile periods of
            ``t_slip``, s.
        direction: unit slide direction in world, shape ``(2,)``.
        t: sample times of the window, s, shape ``(m,)``.
        q: the series fitted there, shape ``(m,)``: the friction ratio along the slide
            (:func:`breakaways`, wrench time base) or the mean marker shear against the slide, m
            (:func:`shear_breakaway`, marker time base).
        sigma: its noise, shape ``(m,)``.
        t_slide_end: end of the slide, s.
        quantity: what ``q`` is (``"friction_ratio"`` or ``"marker_shear"``).
    """

    t_command: float
    t_slip: float
    t0: float
    direction: np.ndarray
    t: np.ndarray
    q: np.ndarray
    sigma: np.ndarray
    t_slide_end: float = float("inf")
    quantity: str = "friction_ratio"


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


def marker_shear(rec: Recording, direction: np.ndarray, rest_rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean marker shear against a slide and its noise on the marker time base.

    Args:
        rec: recording with ``markers_xyz`` and ``pose``.
        direction: unit slide direction in world, ``(2,)``.
        rest_rows: boolean mask ``(n,)`` of marker samples with the gel unloaded (rest positions: their
            median).

    Returns:
        ``(shear, sigma)``, each ``(n,)``, m: the markers' mean displacement from rest, projected on the
        slide direction in the sensor frame and negated (positive while the sheet's friction holds
        the gel's surface back), and its standard deviation from the marker noise (the per-axis
        sigma over the square root of the marker count: white noise, independent across markers).
    """
    tm = rec.t["markers_xyz"]
    x = np.asarray(rec.data["markers_xyz"], dtype=float)
    disp = (x - np.median(x[rest_rows], axis=0)).mean(axis=1)  # (n, 3) sensor frame
    u3 = np.array([direction[0], direction[1], 0.0])
    s = _rotations(rec, tm).inv().apply(np.tile(u3, (len(tm), 1)))  # slide direction, sensor frame
    sig = np.asarray(rec.sigma["markers_xyz"], dtype=float)[:3]
    sigma = np.sqrt(np.sum((s * sig) ** 2, axis=1) / x.shape[1])
    return -np.sum(disp * s, axis=1), sigma


def _rest_rows(rec: Recording, loaded_w: np.ndarray) -> np.ndarray:
    """Marker samples before the gel is first loaded (at least three: else the first 5 %)."""
    tm = rec.t["markers_xyz"]
    loaded_m = np.interp(tm, rec.t["wrench"], loaded_w.astype(float)) > 0.5
    first = int(np.argmax(loaded_m)) if loaded_m.any() else len(tm)
    rest_rows = np.arange(len(tm)) < first
    if rest_rows.sum() < 3:
        rest_rows = np.arange(len(tm)) < max(3, len(tm) // 20)
    return rest_rows


def _loaded(rec: Recording) -> np.ndarray:
    """Wrench samples with the gel loaded (compressive normal force above :data:`CONTACT_SIGMAS` sigmas)."""
    return normal_force(rec.data["wrench"]) > CONTACT_SIGMAS * float(rec.sigma["wrench"][2])


def shear_breakaway(rec: Recording, b: Breakaway) -> Breakaway | None:
    """The mean marker shear (:func:`marker_shear`) around a breakaway found by :func:`breakaways`.

    The window starts at the largest shear within two tactile periods of ``b.t_slip`` and ends
    :data:`BREAKAWAY_WINDOW_S` later or at the slide's end, loaded marker samples only.

    Returns:
        the breakaway on the marker time base (``quantity="marker_shear"``), or None with fewer than
        :data:`MIN_WINDOW_SAMPLES` samples in the window.
    """
    tm = rec.t["markers_xyz"]
    loaded_w = _loaded(rec)
    loaded_m = np.interp(tm, rec.t["wrench"], loaded_w.astype(float)) > 0.5
    shear, sigma = marker_shear(rec, b.direction, _rest_rows(rec, loaded_w))
    period = rec.tactile_period()
    near = np.nonzero((tm >= b.t_slip - 2.0 * period) & (tm <= b.t_slip + 2.0 * period) & loaded_m)[0]
    if not len(near):
        return None
    t0 = float(tm[near[np.argmax(shear[near])]])
    m = (tm >= t0) & (tm <= min(t0 + BREAKAWAY_WINDOW_S, b.t_slide_end)) & loaded_m
    if m.sum() < MIN_WINDOW_SAMPLES:
        return None
    return Breakaway(b.t_command, b.t_slip, t0, b.direction, tm[m], shear[m], sigma[m], b.t_slide_end, "marker_shear")


def normal_lag(rec: Recording) -> tuple[np.ndarray, float] | None:
    """The effector's lag behind its command against the sensor normal, from its free-space lag.

    A compliant effector (the reference cell's arm: a 3000 N/m Cartesian impedance) is pushed back
    along the sensor normal by the normal force on the gel, so this lag is proportional to ``F_n``
    at time scales above the arm's response (its bandwidth, about 30 Hz there, against the breakaway
    decays of 10-100 ms), with the pose's noise (5 um against a lag of about 2 mm at 6 N: a tenth of
    the wrench's relative noise). A kinematic effector has no lag, and the lag carries no load.

    Returns:
        ``(lag (n,) m on the pose time base, its noise sigma m)``: ``(pose_cmd - pose) . n`` (n the
        sensor normal in world, out of the gel) minus its median before the gel is first loaded;
        None without ``pose_cmd``, a pose noise, or at least three pose samples before the contact.
    """
    if not rec.has("pose_cmd") or "pose" not in rec.sigma:
        return None
    tp = rec.t["pose"]
    pose = np.asarray(rec.data["pose"], dtype=float)
    cmd = np.asarray(rec.data["pose_cmd"], dtype=float)
    if cmd.shape != pose.shape or not np.array_equal(rec.t["pose_cmd"], tp):
        return None
    normal = _rotations(rec, tp).apply(np.tile([0.0, 0.0, 1.0], (len(tp), 1)))
    lag = np.sum((cmd[:, :3] - pose[:, :3]) * normal, axis=1)
    loaded = np.interp(tp, rec.t["wrench"], _loaded(rec).astype(float)) > 0.5
    first = int(np.argmax(loaded)) if loaded.any() else len(tp)
    if first < 3:
        return None
    sig = np.asarray(rec.sigma["pose"], dtype=float)[:3]
    sigma = float(np.sqrt(np.median(np.sum((normal * sig) ** 2, axis=1))))
    if not sigma > 0.0:
        return None
    return lag - float(np.median(lag[:first])), sigma


def normal_load_excess(rec: Recording, b: Breakaway, tau: float) -> tuple[float, float, str]:
    """Relative breakaway excess of the normal load on ``b``'s window, with ``b``'s ``t0`` and ``tau``.

    Two measures of the normal load over the loaded samples from ``b.t0`` to the window's end are
    each fitted by ``a + b (t - t0) + A exp(-(t - t0) / tau)`` weighted by their noise (A of either
    sign): the wrench's normal force, and the effector's lag against the sensor normal
    (:func:`normal_lag`), whose relative excess is the normal force's for a compliant effector. They
    are combined by inverse variance where the lag's excess is the more precise (the lag of a
    kinematic effector has no level: the wrench's alone), unless the lag does not follow the load: a gain and offset fitted from the lag to the wrench's
    normal force over the window leave a residual beyond the wrench noise (chi-square test at
    :data:`LAG_CHECK_ALPHA`), or the two excesses differ by more than three standard deviations of
    their difference. Then the wrench's alone.

    Returns:
        ``(A / a, its standard deviation, source)``, source ``"wrench"`` or ``"wrench+effector lag"``;
        ``(0, inf, "none")`` with ``tau <= 0`` or too few samples.
    """
    if not tau > 0.0:
        return 0.0, float("inf"), "none"
    tw = rec.t["wrench"]
    t_end = b.t[-1] + 0.5 * rec.sample_period("wrench")
    m = (tw >= b.t0) & (tw <= t_end) & _loaded(rec)
    if m.sum() < MIN_WINDOW_SAMPLES:
        return 0.0, float("inf"), "none"
    fn = normal_force(rec.data["wrench"])[m]
    sigma_n = float(rec.sigma["wrench"][2])
    rel_w, sig_w = _relative_excess(decay_columns(tw[m], b.t0, tau), fn, np.full(len(fn), sigma_n))
    lag = normal_lag(rec)
    if lag is None:
        return rel_w, sig_w, "wrench"
    tp = rec.t["pose"]
    mp = (tp >= b.t0) & (tp <= t_end) & (np.interp(tp, tw, _loaded(rec).astype(float)) > 0.5)
    if mp.sum() < MIN_WINDOW_SAMPLES:
        return rel_w, sig_w, "wrench"
    rel_p, sig_p = _relative_excess(decay_columns(tp[mp], b.t0, tau), lag[0][mp], np.full(int(mp.sum()), lag[1]))
    if not (np.isfinite(sig_w) and 0.0 < sig_p < sig_w):
        return rel_w, sig_w, "wrench"  # no lag to speak of (a kinematic effector): nothing to gain
    # the lag must follow the wrench's normal force over the window (a gain and an offset fitted:
    # residual within the wrench noise at the 0.1 % chi-square tail) and agree on the excess
    X = np.stack([np.interp(tw[m], tp, lag[0]), np.ones(int(m.sum()))], axis=1)
    c, *_ = np.linalg.lstsq(X, fn, rcond=None)
    chi2 = float(np.sum(((fn - X @ c) / sigma_n) ** 2))
    follows = chi2 <= chi2_law.ppf(1.0 - LAG_CHECK_ALPHA, int(m.sum()) - 2)
    if not follows or abs(rel_p - rel_w) > 3.0 * np.hypot(sig_p, sig_w):
        return rel_w, sig_w, "wrench"
    w_w, w_p = sig_w ** -2, sig_p ** -2
    return float((w_w * rel_w + w_p * rel_p) / (w_w + w_p)), float((w_w + w_p) ** -0.5), "wrench+effector lag"


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
    loaded_w = _loaded(rec)
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
    rest_rows = _rest_rows(rec, loaded_w)
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
        out.append(Breakaway(t_a, t_slip, t0, u, tw[m], q[m], sigma[m], t_b))
    return out


def _wls(cols: list[np.ndarray], y: np.ndarray, sigma: np.ndarray) -> tuple[float, np.ndarray]:
    X = np.stack(cols, axis=1) / sigma[:, None]
    c, *_ = np.linalg.lstsq(X, y / sigma, rcond=None)
    r = y / sigma - X @ c
    return float(r @ r), c


def _relative_excess(cols: list[np.ndarray], y: np.ndarray, sigma: np.ndarray) -> tuple[float, float]:
    """Relative excess ``A / a`` of the weighted fit ``a + b (t - t0) + A exp(..)`` (``cols`` from
    :func:`decay_columns` with the decay) and its standard deviation from the noise model (the fit's
    covariance ``(X^T W X)^-1`` through the gradient of ``A / a``); ``(0, inf)`` for a level <= 0."""
    X = np.stack(cols, axis=1) / sigma[:, None]
    c, *_ = np.linalg.lstsq(X, y / sigma, rcond=None)
    if not c[0] > 0.0:
        return 0.0, float("inf")
    cov = np.linalg.pinv(X.T @ X)
    grad = np.zeros(len(c))
    grad[0], grad[2] = -c[2] / c[0] ** 2, 1.0 / c[0]
    return float(c[2] / c[0]), float(np.sqrt(max(grad @ cov @ grad, 0.0)))


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


def roughness(b: Breakaway) -> float:
    """Sample-to-sample dispersion of a breakaway window's series over its noise model, floored at 1.

    The variance of the whitened second differences ``(y[i+1] - 2 y[i] + y[i-1]) / sigma`` over 6
    (their variance for white noise of unit variance), read robustly
    (:func:`sysid.noise.robust_scale`: 1.4826 times their median absolute deviation, squared): it
    takes in a sliding contact's roughness beyond the noise model and leaves out the window's slow shape (the breakaway's decay, the level's trend and
    curvature), whose second differences are small but for a few samples at the decay's start.
    1 for a window with fewer than :data:`MIN_WINDOW_SAMPLES` second differences.
    """
    if len(b.q) < MIN_WINDOW_SAMPLES + 2:
        return 1.0
    z = (b.q[2:] - 2.0 * b.q[1:-1] + b.q[:-2]) / b.sigma[1:-1]
    return max(robust_scale(z) ** 2 / 6.0, 1.0)


def decay_statistic(fit: dict, b: Breakaway) -> float:
    """Whitened SSE a breakaway decay removes from a window (:func:`fit_breakaway`) over the window's
    roughness (:func:`roughness`): a quasi-likelihood F statistic (module docstring)."""
    return max(fit["sse0"] - fit["sse1"], 0.0) / roughness(b)


def decay_taus(rec: Recording) -> np.ndarray:
    """Decay times searched: half tactile periods from one period up to :data:`TAU_MAX_S`."""
    period = rec.tactile_period()
    return np.arange(period, TAU_MAX_S + 1e-9, period / 2.0)


def _readable(rec: Recording) -> bool:
    """Whether the recording has the wrench, the pose with a valid orientation and the markers."""
    if not rec.has("wrench", "pose", "markers_xyz"):
        return False
    return bool((np.linalg.norm(np.asarray(rec.data["pose"], dtype=float)[:, 3:7], axis=1) > 0.0).any())


def breakaway_fits(rec: Recording) -> list[dict]:
    """Every breakaway analysed (module docstring, steps 3-4).

    Returns:
        one dict per breakaway of :func:`breakaways`: ``breakaway`` (the friction ratio's window),
        ``shear`` (the marker shear's window, :func:`shear_breakaway`, or None), ``ratio_fit`` and
        ``shear_fit`` (:func:`fit_breakaway`; ``shear_fit`` None without a shear window),
        ``statistic`` (the whitened SSE the decay removes from both series, each over its roughness:
        :func:`decay_statistic`), ``shear_excess`` (the
        shear's ``A / a``) and its standard deviation ``shear_excess_sigma``, ``normal_excess`` and
        ``normal_excess_sigma`` and ``normal_source`` (:func:`normal_load_excess` at the shear's decay
        time), ``excess`` (the normal-load-corrected excess, their difference; 0 when no positive
        decay fits the shear) and ``excess_sigma``.
    """
    taus = decay_taus(rec)
    out = []
    for b in breakaways(rec):
        fq = fit_breakaway(b, taus)
        stat = decay_statistic(fq, b)
        bs = shear_breakaway(rec, b)
        fs = fit_breakaway(bs, taus) if bs is not None else None
        rel_s, sig_s, rel_n, sig_n, source = 0.0, float("inf"), 0.0, float("inf"), "none"
        if bs is not None and fs is not None:
            stat += decay_statistic(fs, bs)
            # the spread of the excess at the fitted decay time (at the grid's shortest one when no
            # positive decay fits: the excess is then 0 and only its resolvable size is reported)
            tau = fs["tau_s"] if fs["tau_s"] > 0.0 else float(taus[0]) if len(taus) else 0.0
            if tau > 0.0:
                rel_s, sig_s = _relative_excess(decay_columns(bs.t, bs.t0, tau), bs.q, bs.sigma)
                rel_n, sig_n, source = normal_load_excess(rec, bs, tau)
            if not fs["tau_s"] > 0.0:
                rel_s = rel_n = 0.0  # no breakaway excess of the shear: nothing to correct
        out.append({"breakaway": b, "shear": bs, "ratio_fit": fq, "shear_fit": fs, "statistic": stat,
                    "shear_excess": rel_s, "shear_excess_sigma": sig_s, "normal_excess": rel_n,
                    "normal_excess_sigma": sig_n, "normal_source": source, "excess": rel_s - rel_n,
                    "excess_sigma": float(np.hypot(sig_s, sig_n))})
    return out


def _strongest(fits: list[dict]) -> int:
    return int(np.argmax([f["statistic"] for f in fits]))


def resolvable_excess(rec: Recording) -> float:
    """Smallest normal-load-corrected breakaway excess the recording resolves: :data:`RESOLVABLE_SIGMAS`
    standard deviations of that excess at the strongest breakaway (noise model propagated through the
    shear's and the normal force's fits); without a breakaway, twice the relative noise of the friction
    ratio on one wrench sample at a ratio of 1 and the median loaded normal force; inf without a
    loaded wrench."""
    fits = breakaway_fits(rec) if _readable(rec) else []
    if fits:
        sigma = fits[_strongest(fits)]["excess_sigma"]
        if np.isfinite(sigma):
            return float(RESOLVABLE_SIGMAS * sigma)
    if not rec.has("wrench"):
        return float("inf")
    fn = normal_force(rec.data["wrench"])
    sig = np.asarray(rec.sigma["wrench"], dtype=float)
    loaded = fn > CONTACT_SIGMAS * float(sig[2])
    if not loaded.any():
        return float("inf")
    return float(RESOLVABLE_SIGMAS * np.hypot(sig[0], sig[2]) / np.median(fn[loaded]))


def sheet_yield(rec: Recording, fits: list[dict]) -> dict | None:
    """Whether the sheet folded for good during a tested slide (module docstring, "Sheet yield").

    Returns:
        None when the recording keeps no resolvable permanent set after release
        (:func:`sysid.diagnose.signatures.sheet.plasticity_test`, size at least
        :func:`sysid.diagnose.signatures.sheet.resolvable_set`) or no slide raised the set's points by
        that size; else ``{"set_m", "rise_m", "slide_s": [t_command, t_slide_end]}`` of the slide
        whose rise is largest.
    """
    if not rec.predicted("sheet_points"):
        return None
    r = plasticity_test(rec)
    floor = resolvable_set(rec)
    if not (r.applicable and r.effect_size >= floor):
        return None
    rises = [(set_rise(rec, r, f["breakaway"].t_command, f["breakaway"].t_slide_end), f) for f in fits]
    rise, f = max(rises, key=lambda x: x[0])
    if rise < floor:
        return None
    return {"set_m": float(r.effect_size), "rise_m": float(rise),
            "slide_s": [float(f["breakaway"].t_command), float(f["breakaway"].t_slide_end)]}


def _slope(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Least-squares slope of ``y`` on ``x`` (with an offset) and its standard error from the
    residual dispersion ``SSE / (n - 2)``; ``(0, inf)`` for fewer than three samples or a constant x."""
    n = len(x)
    dx = x - x.mean()
    sxx = float(dx @ dx)
    if n < 3 or not sxx > 0.0:
        return 0.0, float("inf")
    c1 = float(dx @ (y - y.mean())) / sxx
    r = y - y.mean() - c1 * dx
    return c1, float(np.sqrt(float(r @ r) / (n - 2) / sxx))


def load_against_fold(rec: Recording, fit: dict) -> dict | None:
    """The tangential and normal load regressed on the sheet's crest height past a breakaway's decay
    (module docstring, "Sheet yield").

    Args:
        rec: recording with ``sheet_points`` (world, m), ``markers_xyz``, ``wrench`` and ``pose``.
        fit: one entry of :func:`breakaway_fits` with a shear window.

    Returns:
        None without the sheet, a shear window or :data:`MIN_WINDOW_SAMPLES` loaded marker samples
        from :data:`TAU_MAX_S` past the shear's peak to the slide's end; else ``{"rise_m"`` (the
        crest's rise over that part, m), ``"shear_fall"`` / ``"normal_fall"`` (relative fall of the
        mean marker shear / the normal force over that rise, from their slopes on the crest height;
        positive when falling), ``"fall_sigma"`` (standard deviation of their difference) and
        ``"window_s"``.
    """
    b, bs = fit["breakaway"], fit["shear"]
    if bs is None or not rec.has("sheet_points"):
        return None
    tm, tw = rec.t["markers_xyz"], rec.t["wrench"]
    loaded_w = _loaded(rec)
    loaded_m = np.interp(tm, tw, loaded_w.astype(float)) > 0.5
    m = (tm >= bs.t0 + TAU_MAX_S) & (tm <= b.t_slide_end) & loaded_m
    mw = (tw >= bs.t0 + TAU_MAX_S) & (tw <= b.t_slide_end) & loaded_w
    if m.sum() < MIN_WINDOW_SAMPLES or mw.sum() < MIN_WINDOW_SAMPLES:
        return None
    crest = np.asarray(rec.data["sheet_points"], dtype=float)[..., 2].max(axis=1)  # (n_sheet,) m
    ts = rec.t["sheet_points"]
    h_m, h_w = np.interp(tm[m], ts, crest), np.interp(tw[mw], ts, crest)
    rise = float(h_m[-1] - h_m[0])
    shear, _ = marker_shear(rec, b.direction, _rest_rows(rec, loaded_w))
    fn = normal_force(rec.data["wrench"])[mw]
    c_s, se_s = _slope(h_m, shear[m])
    c_n, se_n = _slope(h_w, fn)
    level_s, level_n = float(np.mean(shear[m])), float(np.mean(fn))
    if not (level_s > 0.0 and level_n > 0.0):
        return None
    fall_s, fall_n = -c_s * rise / level_s, -c_n * rise / level_n
    sigma = float(np.hypot(se_s * abs(rise) / level_s, se_n * abs(rise) / level_n))
    return {"rise_m": rise, "shear_fall": float(fall_s), "normal_fall": float(fall_n), "fall_sigma": sigma,
            "window_s": [float(tm[m][0]), float(tm[m][-1])]}


def released_flat(rec: Recording) -> dict | None:
    """Whether the recording shows the sheet released and without a permanent set: the plasticity test reads
    a released window (:func:`sysid.diagnose.signatures.sheet.plasticity_test` applicable) and finds a set
    under :func:`sysid.diagnose.signatures.sheet.resolvable_set`. A sheet that yielded keeps its fold, so a
    tangential load that fell while a fold rose during the slide was not the sheet yielding there
    (:func:`falling_load_yield` reads the yield only where no released window tells; module docstring,
    "Sheet yield").

    Returns:
        None when the recording has no released window to read or keeps a resolvable set; else
        ``{"set_m", "resolvable_m"}``.
    """
    if not rec.predicted("sheet_points") or "sheet_points" not in rec.sigma:
        return None
    r = plasticity_test(rec)
    floor = resolvable_set(rec)
    if not r.applicable or r.effect_size >= floor:
        return None
    return {"set_m": float(r.effect_size), "resolvable_m": float(floor)}


def falling_load_yield(rec: Recording, fits: list[dict]) -> dict | None:
    """Whether the tangential load fell as the sheet's fold rose past a breakaway's decay (module
    docstring, "Sheet yield"): the crest rose by at least
    :func:`sysid.diagnose.signatures.sheet.resolvable_set` and the shear's relative fall exceeds the
    normal force's by :data:`RESOLVABLE_SIGMAS` standard deviations of the difference.

    Returns:
        None when no breakaway shows it; else :func:`load_against_fold`'s dict of the breakaway
        whose fall is largest, with ``"slide_s"``.
    """
    if not rec.has("sheet_points") or "sheet_points" not in rec.sigma:
        return None
    floor = resolvable_set(rec)
    best = None
    for f in fits:
        lf = load_against_fold(rec, f)
        if lf is None or lf["rise_m"] < floor:
            continue
        excess = lf["shear_fall"] - lf["normal_fall"]
        if excess > RESOLVABLE_SIGMAS * lf["fall_sigma"] and (best is None or excess > best[0]):
            best = (excess, {**lf, "slide_s": [float(f["breakaway"].t_command), float(f["breakaway"].t_slide_end)]})
    return None if best is None else best[1]


def stiction_test(rec: Recording) -> SignatureResult:
    """Breakaway overshoot of the tangential load at slide onset, beyond the normal load's (module
    docstring)."""
    effect = "stiction"
    if not rec.has("wrench", "pose", "markers_xyz"):
        return not_applicable(effect, "needs the wrench, the effector pose and the marker positions")
    if not _readable(rec):
        return not_applicable(effect, "the effector pose has no valid orientation (all-zero quaternions)")
    fits = breakaway_fits(rec)
    if not fits:
        return not_applicable(effect, "no slide under load in which the gel's contact surface slips")
    k = _strongest(fits)
    events = []
    for f in fits:
        b, fq, fs = f["breakaway"], f["ratio_fit"], f["shear_fit"]
        events.append({"t_command_s": b.t_command, "t_slip_s": b.t_slip, "direction": b.direction.tolist(),
                       "samples": int(len(b.t)), "statistic": f["statistic"],
                       "ratio_statistic": decay_statistic(fq, b), "kinetic_ratio": fq["level"],
                       "ratio_excess": fq["excess"] / fq["level"] if fq["level"] > 0.0 else 0.0,
                       "ratio_roughness": roughness(b),
                       "shear_statistic": decay_statistic(fs, f["shear"]) if fs else 0.0,
                       "shear_roughness": roughness(f["shear"]) if fs else 1.0,
                       "shear_samples": int(len(f["shear"].t)) if fs else 0,
                       "shear_level_m": fs["level"] if fs else 0.0, "decay_s": fs["tau_s"] if fs else 0.0,
                       "shear_excess": f["shear_excess"], "normal_excess": f["normal_excess"],
                       "normal_excess_sigma": f["normal_excess_sigma"], "normal_source": f["normal_source"],
                       "relative_excess": f["excess"],
                       "relative_excess_sigma": f["excess_sigma"]})
    best = fits[k]
    size = max(float(best["excess"]), 0.0)
    detail = {"breakaways": events, "resolvable_excess": RESOLVABLE_SIGMAS * float(best["excess_sigma"])}
    reason = ""
    yielded = sheet_yield(rec, fits) if size > 0.0 else None
    flat = released_flat(rec) if size > 0.0 and yielded is None else None
    falling = falling_load_yield(rec, fits) if size > 0.0 and yielded is None and flat is None else None
    if yielded is not None:
        detail["sheet_yield"] = yielded
        set_mm = 1e3 * yielded["set_m"]
        size, reason = 0.0, (f"the sheet folded for good while sliding (its set of {set_mm:.3g} mm rose "
                             f"{1e3 * yielded['rise_m']:.3g} mm during the slide): the tangential load's drop is the "
                             "sheet yielding, not static friction")
    elif flat is not None:
        detail["sheet_released_flat"] = flat
    elif falling is not None:
        detail["sheet_yield"] = falling
        size, reason = 0.0, (f"the tangential load kept falling as the sheet's fold rose after the breakaway "
                             f"({100 * falling['shear_fall']:.3g} % over a {1e3 * falling['rise_m']:.3g} mm rise, the "
                             f"normal load {100 * falling['normal_fall']:.3g} %): the sheet yielding limits the load, "
                             "not static friction")
    windows = [[float(f["breakaway"].t[0]), float(f["breakaway"].t[-1])] for f in fits]
    return SignatureResult(
        effect=effect, statistic=float(sum(f["statistic"] for f in fits)), effect_size=size,
        effect_unit="(mu_s / mu_k - 1 at breakaway, beyond the normal load)",
        estimate={"static_over_kinetic": 1.0 + size, "kinetic_ratio": best["ratio_fit"]["level"],
                  "decay_s": best["shear_fit"]["tau_s"] if best["shear_fit"] else 0.0},
        windows_s=windows, channels=["markers_xyz", "wrench"], markers=[], detail=detail, reason=reason)
