"""Signature test of damping in the gel: the contact force leads the deformation.

A Kelvin-Voigt (stiffness-proportional, Rayleigh) damped gel carries ``F = k (x + tau dx/dt)``,
which to first order is ``k x(t + tau)``: the force runs *ahead* of the elastic response by the
damping time constant, by an amount proportional to the deformation rate, and adds nothing on
quasi-static segments (SYSID.md "damping — residual proportional to velocity, nothing in
quasi-static segments"). It is read where the rate is largest, at the contact events of the
calibrated nominal replay (press and release), with the windows of
:mod:`sysid.diagnose.signatures.timing`: in each window the recorded normal force is regressed on
the replay's Kelvin-Voigt contact force ``y ~ a + b max(y_pred + tau dy_pred/dt, 0)`` (free gain and
offset per window: the amplitude gap between simulator and recording is not the effect), over a
grid of ``tau >= 0``; the replay's value and rate are read by a Savitzky-Golay filter
(:func:`kelvin_voigt`). The contact pushes only: on a release the damping force opposes the gel's
recovery, and where it exceeds the elastic force the surfaces part and the force is zero, not
tensile (:func:`contact_force`).

* statistic: the whitened SSE a common lead removes against ``tau = 0`` summed over the events (a
  likelihood-ratio statistic in noise units), divided by the windows' dispersion after the lead,
  ``max(1, SSE_lead / (n - p))`` (``n`` samples, ``p`` = a gain and an offset per window and the
  lead): a quasi-likelihood F statistic (McCullagh & Nelder 1989, *Generalized Linear Models*,
  2nd ed., sec. 9.2). Where the replay leaves a gap the lead does not explain (a nominal model is
  never exactly right), the residual's variance exceeds the noise model's and the lead's drop is
  judged against that variance, not against the sensor noise alone (:func:`dispersion`);
* effect size: the smallest press's mean lead over its rising and falling events, with every
  event leading (:func:`~sysid.diagnose.signatures.timing.timing_size`: a damping time constant
  leads every event; a lead at one event only is the model's gap there, and a depth gap of the
  calibrated replay moves a press's two events apart), s;
* estimate: the common lead, the damping time constant beyond the replay's own, s.

A Kelvin-Voigt gel's force leads its own deformation, not the deformation's timing: where the
recorded gel's deformation (the mean marker depth) itself runs ahead of the replay's at an event by
at least the smallest lead named (the damping size threshold,
:func:`~sysid.diagnose.signatures.null.timing_size_threshold`), the replay reaches or leaves that
deformation later than the recording (e.g. its buckled card keeps pushing the lifting pad), and the
force's lead there is that gap: the event is left out of the statistic and the size
(:func:`deformation_lead`). Where it runs *behind* the replay's by as much at a release and the card under
the pad does too (the replay lets go of the gel and the card early), the force's lead over the replay is the
gel's lead less that gap, and the release is read against the replay re-timed to the recorded deformation
(:func:`retimed_releases`): the force's lead over the gel's own deformation. Only where the gel carries the
pad's travel on the release as on the press (:func:`gel_share`; where a card lifted with the pad carries it,
the release's timing is the card's, whose bending differs between engines).

Through the calibrated arm drive (:mod:`sysid.replay_drive`) the replay's pad is not the recorded pose:
in series with the arm's spring ``k_s`` a damped gel of contact stiffness ``k_c`` moves its *deformation*
``tau k_c / (k_s + k_c)`` behind the undamped replay's and its force only ``tau k_s / (k_s + k_c)``
ahead of it (to first order in ``tau d/dt``: ``x = k_s c / (k_s + k_c (1 + tau s))``, ``F = k_c (1 + tau
s) x``), a tenth of the lead for a 3 N/mm arm on a 35-40 N/mm contact. The lead over the gel's own
deformation is read, as without the drive, against the calibrated replay with the recorded pose
imposed (:attr:`~sysid.diagnose.signatures.base.Recording.reference`, :func:`lead_recording`).

Confusable effects read the same windows with the opposite sign: latency delays every event by the
same time (``tau < 0`` here), a first-order lag (gel viscoelasticity) rounds and delays it; neither
gives a lead at every event, so the three are told apart by the sign of the shift.

Without a wrench the mean marker depth is used in the same way (:func:`timing.timing_signal`).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.signal import savgol_filter

from sysid.diagnose.signatures.base import (Recording, SignatureResult, dispersion, mean_marker_depth, normal_force,
                                            not_applicable)
from sysid.diagnose.signatures.null import SIZE_TOLERANCE, timing_size_threshold
from sysid.diagnose.signatures.sheet import RESOLVABLE_SET_SIGMAS
from sysid.diagnose.signatures.timing import (TAU_MAX_S, delayed, event_windows, press_sizes, timing_signal,
                                              timing_size)

EFFECT = "damping"

RATE_WINDOW_S = 0.05
"""Span of the quadratic Savitzky-Golay filter that reads the replay's value and rate, s. Longer
than the replay's step (0.01 s by default: its contact solve leaves step-to-step roughness on the
predicted force, which a derivative amplifies), and a third of the event windows' shorter side
(:data:`~sysid.diagnose.signatures.timing.WINDOW_BEFORE_S`), so that a press or release ramp keeps
its rate."""


def _savgol_window(t: np.ndarray, span_s: float) -> int:
    """Odd number of samples covering ``span_s`` on the (uniform) time base ``t``, at least 5."""
    dt = float(np.median(np.diff(t)))
    w = int(round(span_s / dt)) if dt > 0 else 5
    w = max(w, 5)
    return w if w % 2 == 1 else w + 1


def kelvin_voigt(t: np.ndarray, y: np.ndarray, tau: float, span_s: float = RATE_WINDOW_S) -> np.ndarray:
    """``y + tau dy/dt`` along axis 0, value and rate read by a quadratic Savitzky-Golay filter
    over ``span_s`` (:func:`scipy.signal.savgol_filter`; Savitzky & Golay 1964): the force of a
    Kelvin-Voigt element of time constant ``tau`` s whose elastic part is ``y``, to first order
    ``y(t + tau)``, a lead of ``tau``.

    Args:
        t: uniform sample times, s, shape ``(n,)``.
        y: elastic response, shape ``(n, ...)``.
        tau: time constant, s (0: the filtered ``y``).
        span_s: filter span, s; a series shorter than the filter is differentiated by central
            differences instead.
    """
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    if len(y) < 3:
        return y.copy()
    w = _savgol_window(t, span_s)
    if len(y) < w:
        return y + tau * np.gradient(y, t, axis=0)
    dt = float(np.median(np.diff(t)))
    value = savgol_filter(y, w, 2, axis=0)
    if tau == 0.0:
        return value
    return value + tau * savgol_filter(y, w, 2, deriv=1, delta=dt, axis=0)


def contact_force(t: np.ndarray, y: np.ndarray, tau: float, span_s: float = RATE_WINDOW_S) -> np.ndarray:
    """Contact force of a Kelvin-Voigt gel whose elastic force is ``y`` (>= 0, pressing):
    ``max(y + tau dy/dt, 0)`` along axis 0 (:func:`kelvin_voigt`). A contact pushes only: on a
    release the damping force opposes the gel's recovery, and once it exceeds the elastic force the
    gel's surface lags behind the lifting pad and the contact force is zero (Signorini condition).

    Args:
        t: uniform sample times, s, shape ``(n,)``.
        y: elastic (replay) normal force, N, shape ``(n, ...)``.
        tau: damping time constant, s.
        span_s: span of the rate filter, s.
    """
    return np.maximum(kelvin_voigt(t, y, tau, span_s), 0.0)


def _window_sse(y: np.ndarray, x: np.ndarray) -> float:
    X = np.stack([x, np.ones_like(x)], axis=1)
    c, *_ = np.linalg.lstsq(X, y, rcond=None)
    r = y - X @ c
    return float(r @ r)


def lead_recording(rec: Recording) -> Recording:
    """The recording with the replay the lead is read against (module docstring): the calibrated replay
    with the recorded pose imposed (``rec.reference``) where the prediction went through the arm drive,
    else ``rec`` itself; its early releases re-timed to the recorded deformation (:func:`retimed_releases`)."""
    return retimed_releases(rec)[0]


def _kinematic(rec: Recording) -> Recording:
    """``rec`` with the replay the lead is read against as its prediction (the reference where there is one)."""
    return rec if rec.reference is None else dataclasses.replace(rec, prediction=rec.reference, reference=None)


def lead_fits(rec: Recording, taus: np.ndarray | None = None) -> dict | None:
    """Whitened SSE of every contact event's window against the replay's Kelvin-Voigt contact force
    (:func:`contact_force`) for each time constant.

    Args:
        rec: recording with its calibrated replay.
        taus: time constants searched, s, ascending from 0 (default: 0 to ``TAU_MAX_S`` in half sample periods).

    Returns:
        None without a predicted normal force or marker depth, else a dict with ``channel``,
        ``taus_s`` (m,), ``sse`` (events, m) whitened SSE per event and lead, and ``events`` (one dict
        per event: time, direction, window, samples, SSE at 0, best lead and its SSE).
    """
    sig = timing_signal(rec)
    if sig is None:
        return None
    channel, t, y, yp, sigma = sig
    if taus is None:
        taus = np.arange(0.0, TAU_MAX_S + 1e-9, max(rec.sample_period(channel) / 2.0, 1e-3))
    shifted = [contact_force(t, yp, float(tau)) for tau in taus]
    events, sse = [], []
    for te, direction, lo, hi, m in event_windows(t, yp):
        row = np.array([_window_sse(y[m], z[m]) for z in shifted]) / sigma ** 2
        i = int(np.argmin(row))
        sse.append(row)
        events.append({"t_s": te, "direction": "rising" if direction > 0 else "falling", "window_s": [lo, hi],
                       "samples": int(m.sum()), "sse0": float(row[0]), "lead_s": float(taus[i]),
                       "sse_lead": float(row[i])})
    return {"channel": channel, "taus_s": np.asarray(taus, dtype=float),
            "sse": np.array(sse).reshape(len(events), len(taus)), "events": events}


SHIFT_STEP_S = 1e-3
"""Grid step of the deformation's shift search (:func:`deformation_lead`), s: a numerical resolution,
a tenth of the markers' 10 ms sample period (the replay's depth is interpolated between samples)."""


def deformation_lead(rec: Recording, window: tuple[float, float] | list[float]) -> float | None:
    """How far the recorded gel's deformation runs ahead of the replay's in ``window``, s: the shift
    ``s`` (in ``[-TAU_MAX_S, TAU_MAX_S]``, step :data:`SHIFT_STEP_S`) whose replay ``depth_pred(t + s)``
    fits the recorded mean marker depth best with a free gain and offset (> 0: the recording ahead;
    the smallest ``|s|`` among equal fits). None without recorded and predicted markers or with fewer
    than three marker samples in the window.

    Args:
        rec: recording with its calibrated replay.
        window: ``[t0, t1]``, s.
    """
    if not rec.predicted("markers_xyz"):
        return None
    tm = rec.t["markers_xyz"]
    return _best_shift(tm, mean_marker_depth(rec.data["markers_xyz"]), mean_marker_depth(rec.prediction["markers_xyz"]),
                       window)


def _best_shift(t: np.ndarray, y: np.ndarray, y_pred: np.ndarray,
                window: tuple[float, float] | list[float]) -> float | None:
    """The shift ``s`` (in ``[-TAU_MAX_S, TAU_MAX_S]``, step :data:`SHIFT_STEP_S`) whose ``y_pred(t + s)`` fits
    ``y`` best in ``window`` with a free gain and offset (the smallest ``|s|`` among equal fits), s; None with
    fewer than three samples in the window. ``t``, ``y``, ``y_pred``: shape ``(n,)``."""
    m = (t >= window[0]) & (t <= window[1])
    if m.sum() < 3:
        return None
    shifts = np.arange(-TAU_MAX_S, TAU_MAX_S + 1e-12, SHIFT_STEP_S)
    sse = np.array([_window_sse(y[m], np.interp(t[m] + sh, t, y_pred)) for sh in shifts])
    best = np.flatnonzero(sse <= sse.min() * (1.0 + 1e-12))
    return float(shifts[best[np.argmin(np.abs(shifts[best]))]])


CARD_POINTS = 20
"""Sheet points whose height the card's timing is read from (:func:`card_lead`): those the replay moves most
in the window, about the pad's footprint on the scenes' 21 x 13 card grid."""


def card_lead(rec: Recording, window: tuple[float, float] | list[float]) -> float | None:
    """How far the recorded card runs ahead of the replay's in ``window``, s: :func:`deformation_lead`'s shift
    search on the mean height (``z``, world) of the :data:`CARD_POINTS` sheet points whose replayed height
    spans most in the window (> 0: the recording ahead). None without recorded and predicted sheet points,
    or where the replay's card moves less in the window than the tracking resolves
    (:data:`~sysid.diagnose.signatures.sheet.RESOLVABLE_SET_SIGMAS` sheet sigmas): a card lying still is no
    timing reference.

    Args:
        rec: recording with its calibrated replay.
        window: ``[t0, t1]``, s.
    """
    if not rec.predicted("sheet_points"):
        return None
    ts = rec.t["sheet_points"]
    m = (ts >= window[0]) & (ts <= window[1])
    if m.sum() < 3:
        return None
    height = np.asarray(rec.data["sheet_points"], dtype=float)[:, :, 2]
    height_pred = np.asarray(rec.prediction["sheet_points"], dtype=float)[:, :, 2]
    points = np.argsort(np.ptp(height_pred[m], axis=0))[-CARD_POINTS:]
    card, card_pred = height[:, points].mean(axis=1), height_pred[:, points].mean(axis=1)
    if np.ptp(card_pred[m]) < RESOLVABLE_SET_SIGMAS * float(rec.sigma["sheet_points"][2]):
        return None
    return _best_shift(ts, card, card_pred, window)


RAMP_FRACTIONS = (0.1, 0.9)
"""The part of an event window where the replay's normal force ramps, as fractions of the window's largest
replay force: where the gel's share of the pad's travel is read (:func:`gel_share`). Inside it a press or a
release moves the pad along the sensor normal; a slide begins only once the press has ramped."""

CARRIED_SHARE = 0.5
"""Smallest ratio of the gel's share of the pad's travel on a release to its share on the press before it
(:func:`gel_share`) at which the release is re-timed to the recorded deformation (:func:`retimed_releases`).
On the press the card lies on the table and the pad's travel goes into the gel; on a release whose share
falls below half of that, the pad travels further than the gel unloads (a card lifted with the pad, or
buckled under it, carries the travel), and the release's timing is the card's, whose bending and buckling
differ between engines (docs/benchmarks_log.md, session 40, 23card): its deformation is no timing
reference for the gel. A majority criterion, not a value fitted to recordings."""


def _ramp(rec: Recording, window: tuple[float, float] | list[float]) -> tuple[np.ndarray, np.ndarray] | None:
    """Marker-sample rows of ``window`` where the replay's normal force ramps (within :data:`RAMP_FRACTIONS`
    of the window's largest) and where it is loaded (at least the lower fraction), as boolean masks over
    ``rec.t["markers_xyz"]``; None where fewer than two samples ramp."""
    tm = rec.t["markers_xyz"]
    force = np.interp(tm, rec.t["wrench"], normal_force(rec.prediction["wrench"]))
    m = (tm >= window[0]) & (tm <= window[1])
    if not m.any() or not np.max(force[m]) > 0.0:
        return None
    low, high = (f * float(np.max(force[m])) for f in RAMP_FRACTIONS)
    ramp = m & (force >= low) & (force <= high)
    return (ramp, m & (force >= low)) if ramp.sum() >= 2 else None


def _pad_position(rec: Recording) -> np.ndarray:
    """The recorded pad position at the marker samples, m, shape ``(n, 3)``."""
    return np.stack([np.interp(rec.t["markers_xyz"], rec.t["pose"], rec.data["pose"][:, k]) for k in range(3)],
                    axis=1)


def press_direction(rec: Recording, window: tuple[float, float] | list[float]) -> np.ndarray | None:
    """Unit direction ``(3,)`` the recorded pad travels while the replay's force ramps up in a press's
    ``window`` (:func:`_ramp`): the sensor normal, a press moving the pad into the card before any slide.
    None without a recorded pose, predicted markers and wrench, a ramp, or travel."""
    if not (rec.predicted("markers_xyz", "wrench") and rec.has("pose")):
        return None
    rows = _ramp(rec, window)
    if rows is None:
        return None
    ramp = np.flatnonzero(rows[0])
    position = _pad_position(rec)
    chord = position[ramp[-1]] - position[ramp[0]]
    length = float(np.linalg.norm(chord))
    return chord / length if length > 0.0 else None


def gel_share(rec: Recording, window: tuple[float, float] | list[float], normal: np.ndarray) -> float | None:
    """Share of the pad's travel along ``normal`` that the replay's gel takes in ``window``: the least-squares
    slope of the replay's mean marker depth on the recorded pad position (``rec.data["pose"]``) along
    ``normal`` (:func:`press_direction`), over the window's samples whose replay normal force is at least the
    lower of :data:`RAMP_FRACTIONS` of its largest (-; 0.6-1.1 where the gel carries the pad's travel on a
    card lying on the table, under 0.15 where a card lifted with the pad carries it, on every development
    recording of docs/benchmarks_log.md, session 41, 23damp). None without a recorded pose, predicted
    markers and wrench, a ramp, or travel along ``normal``.

    Args:
        rec: recording with its calibrated replay.
        window: ``[t0, t1]``, s.
        normal: unit direction ``(3,)``.
    """
    if not (rec.predicted("markers_xyz", "wrench") and rec.has("pose")):
        return None
    rows = _ramp(rec, window)
    if rows is None:
        return None
    loaded = rows[1]
    travel = _pad_position(rec)[loaded] @ np.asarray(normal, dtype=float)
    if not np.ptp(travel) > 0.0:
        return None
    depth = mean_marker_depth(np.asarray(rec.prediction["markers_xyz"])[loaded])
    X = np.stack([travel - travel.mean(), np.ones_like(travel)], axis=1)
    return float(abs(np.linalg.lstsq(X, depth, rcond=None)[0][0]))


def retimed_releases(rec: Recording) -> tuple[Recording, list[dict]]:
    """The recording with the replay the lead is read against (``rec.reference`` where the prediction went
    through the arm drive), each of its *early* releases re-timed to the recorded deformation.

    A release where the recorded gel's deformation (mean marker depth) runs *behind* the replay's by at least
    the smallest lead named (:func:`deformation_lead` <= ``-timing_size_threshold``) may be one where the
    replay lets go of the gel earlier than the recording does, in deformation as in force: the force's lead
    over the replay there is then the gel's lead less that gap. Two conditions tell it from a damped gel's own
    slow recovery (which delays the markers too) and from a calibration's depth gap at the gel alone:

    * the card under the pad moves in the window and runs behind the replay's by the resolution too
      (:func:`card_lead`): the replay that lets go of the gel early lets go of the card early, a timing
      reference that gel damping cannot move later (a damped gel parts from the card earlier, not later);
    * the gel carries the pad's travel on the release as on the press before it (:func:`gel_share` ratio >=
      :data:`CARRIED_SHARE`): where a card lifted with the pad carries it, the release's timing is the card's,
      whose bending and buckling differ between engines.

    Such a release is read against the replay delayed by the gap (``y_pred(t + s)``, ``s`` the deformation
    lead, from the release window's start to the next event window's): the lead is the force's lead over the
    gel's own deformation, as a Kelvin-Voigt gel's is. The mirror of a release whose deformation runs *ahead*
    (the replay lets go late), which :func:`damping_test` leaves out. Presses are not re-timed: there the
    recorded marker depth runs 13-35 ms behind the replay's on every MuJoCo recording, nominal or not
    (docs/benchmarks_log.md, session 37, 23damp), so it is no timing reference. Only where the lead is read
    on the force.

    Args:
        rec: recording with its calibrated replay.

    Returns:
        ``(recording, retimed)``: the recording (``rec`` itself, or its kinematic view, where nothing is
        re-timed) and one dict per re-timed release (``t_s``, ``window_s``, ``deformation_lead_s``,
        ``card_lead_s``, ``gel_share``: the release's share over the press's; ``segment_s``: the re-timed
        span, its end None at the recording's end).
    """
    base = _kinematic(rec)
    sig = timing_signal(base)
    if sig is None or sig[0] != "wrench" or base.prediction is None:
        return base, []
    _, t, _, yp, _ = sig
    resolution = timing_size_threshold(base) * (1.0 - SIZE_TOLERANCE)
    windows = event_windows(t, yp)
    shifts, normal, press_share = [], None, None
    for k, (te, direction, lo, hi, _) in enumerate(windows):
        if direction > 0:
            normal = press_direction(base, (lo, hi))
            press_share = None if normal is None else gel_share(base, (lo, hi), normal)
            continue
        lead = deformation_lead(base, (lo, hi))
        if lead is None or lead > -resolution or normal is None or not (press_share or 0.0) > 0.0:
            continue
        share = gel_share(base, (lo, hi), normal)
        card = card_lead(base, (lo, hi))
        if share is None or share / press_share < CARRIED_SHARE or card is None or card > -resolution:
            continue
        end = float(windows[k + 1][2]) if k + 1 < len(windows) else None
        shifts.append({"t_s": float(te), "window_s": [float(lo), float(hi)], "segment_s": [float(lo), end],
                       "deformation_lead_s": float(lead), "card_lead_s": float(card),
                       "gel_share": float(share / press_share)})
    if not shifts:
        return base, []
    prediction = {}
    for ch, values in base.prediction.items():
        values = np.asarray(values, dtype=float)
        out = values.copy()
        for e in shifts:
            start, end = e["segment_s"]
            rows = (base.t[ch] >= start) & (base.t[ch] < (np.inf if end is None else end))
            out[rows] = delayed(base.t[ch], values, -e["deformation_lead_s"])[rows]
        prediction[ch] = out
    return dataclasses.replace(base, prediction=prediction), shifts


def damping_test(rec: Recording) -> SignatureResult:
    """Gel damping from the lead of the recorded contact force over the calibrated replay with the recorded
    pose imposed, early releases re-timed (:func:`retimed_releases`; module docstring: statistic, effect size,
    estimate)."""
    rec, retimed = retimed_releases(rec)
    fits = lead_fits(rec)
    if fits is None:
        return not_applicable(EFFECT, "needs a predicted wrench or marker positions (a calibrated replay)")
    ev = fits["events"]
    if not ev:
        return not_applicable(EFFECT, "the replay predicts no contact event")
    resolution = timing_size_threshold(rec) * (1.0 - SIZE_TOLERANCE)
    for e in ev:
        # the deformation's own timing is read from the markers only when the lead is read on the force
        # and only on a release (module docstring)
        reads = fits["channel"] == "wrench" and e["direction"] == "falling"
        e["deformation_lead_s"] = deformation_lead(rec, e["window_s"]) if reads else None
    read = np.array([e["deformation_lead_s"] is None or e["deformation_lead_s"] < resolution for e in ev])
    if not read.any():
        return SignatureResult(effect=EFFECT, statistic=0.0, effect_size=0.0, effect_unit="s (smallest press lead)",
                               windows_s=[e["window_s"] for e in ev], detail={"events": ev},
                               reason="the recorded deformation runs ahead of the replay's at every event: "
                                      "the force's lead is the replay's timing gap, not damping")
    held = [e for e, r in zip(ev, read) if not r]
    ev = [e for e, r in zip(ev, read) if r]
    total = fits["sse"][read].sum(axis=0)
    j = int(np.argmin(total))
    lead = float(fits["taus_s"][j])
    leads = np.array([e["lead_s"] for e in ev])
    samples = int(sum(e["samples"] for e in ev))
    removed = max(float(total[0] - total[j]), 0.0)
    excess = max(float(total[0]) - samples, 1e-12)
    # a gain and an offset per window, and the common lead
    phi = dispersion(float(total[j]), samples, 2 * len(ev) + 1)
    detail = {"channel": fits["channel"], "events": ev, "samples": samples, "sse0": float(total[0]),
              "sse_lead": float(total[j]), "sse_removed": removed, "dispersion": phi, "leads_s": leads.tolist(),
              "press_leads_s": press_sizes(ev, "lead_s"), "explained_lead": float((total[0] - total[j]) / excess),
              "events_left_out": held, "releases_retimed": retimed}
    return SignatureResult(effect=EFFECT, statistic=removed / phi,
                           effect_size=timing_size(ev, "lead_s"), effect_unit="s (smallest press lead)",
                           estimate={"tau_s": lead}, windows_s=[e["window_s"] for e in ev],
                           channels=["wrench"] if fits["channel"] == "wrench" else ["markers_xyz"], detail=detail)
