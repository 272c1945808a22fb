"""Signature tests of the tactile stream's timing: latency and gel viscoelastic lag.

Both effects change *when* the tactile channels respond to the effector's motion, not how much,
so they are read at the contact events of the calibrated nominal replay (the normal force rising
through, or falling through, a fraction of its peak), where the response changes fastest and an
amplitude gap between simulator and recording matters least: in a window around each event the
recorded normal force is regressed on a transformed prediction with a free gain and offset,

* delay (latency, SYSID.md "residual about -tau dy/dt on every channel of a stream"):
  ``y(t - tau)``;
* first-order lag (gel viscoelasticity, "markers creep at constant indentation, force relaxes"):
  ``(1 - a) y + a L_tau y`` with ``L_tau`` the first-order low-pass of time constant tau,

over a grid of tau. A release's window reaches :data:`RELEASE_TAIL_S` further into the free gel,
where a lag leaves its exponential tail and the replay predicts no force. The statistic of each is
the whitened SSE it removes against ``tau = 0`` summed over the events. Both are sized in one unit,
the mean delay of the response (the first moment of the impulse response: ``tau`` for the delay,
``a tau`` for the lag), so that a timing read off the events names neither more readily because of
the model it is read with.

The two are told apart by their shape (a pure delay moves a step, a lag rounds it and leaves an
exponential tail; SYSID.md: "latency delays every channel of a stream by the same amount at every
frequency and shows no creep on plateaus") with a paired test of the two non-nested fits (Vuong
1989, Econometrica 57(2) 307-333, with the variance of the likelihood ratio from the noise model):
the difference of the two best fits' whitened SSEs, less the lag's extra parameter per event, over
its standard deviation under the noise model, ``2 sqrt(phi D)``, with ``D`` the whitened squared
distance between the two fitted curves and ``phi`` the residual's dispersion at the scale of
:data:`SHAPE_BLOCK_S` (the residual of a replay read through a filter of that span is correlated
over it): about standard normal when both shapes fit the events equally well
(:func:`paired_shape_z`). For short delays the two shapes agree to first order in ``tau d/dt``,
their curves nearly coincide and ``z`` stays small whatever the stream's timing. Vuong's own
estimate of that variance, the spread of the difference over blocks (:func:`shape_z`, reported
beside it), counts the shape's signal as noise where it sits in a few blocks (a release's tail),
which caps it near the square root of their number.

Without a wrench the mean marker depth is used in the same way.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import savgol_filter

from sysid.diagnose.signatures.base import (Recording, SignatureResult, dispersion, mean_marker_depth, normal_force,
                                            not_applicable)

EVENT_FRACTION = 0.2
"""Contact events: the predicted normal force crossing this fraction of its peak."""

WINDOW_BEFORE_S = 0.15
WINDOW_AFTER_S = 0.3
"""Window around an event, s (before / after the crossing on a rising event; mirrored on a
falling one)."""

TAU_MAX_S = 0.3
"""Largest delay or time constant searched, s."""

MAX_LAG_FRACTION = 1.0
"""Largest share ``a`` of the response that follows the first-order lag: a share, at most one (a
larger one gives the response a negative instantaneous part, a shape that mimics a delay). Where the
unconstrained fit of a time constant gives a share outside ``[0, MAX_LAG_FRACTION]``, the fit is
read at the nearer bound (the constrained least-squares optimum of two columns lies on the
boundary), so that a long lag whose share comes out a little above one is not dropped."""


def low_pass(t: np.ndarray, y: np.ndarray, tau: float) -> np.ndarray:
    """First-order low-pass ``tau dy_f/dt = y - y_f`` (exact for piecewise-constant input), along
    axis 0; ``tau <= 0`` returns a copy."""
    y = np.asarray(y, dtype=float)
    if tau <= 0.0:
        return y.copy()
    out = np.empty_like(y)
    out[0] = y[0]
    a = 1.0 - np.exp(-np.diff(np.asarray(t, dtype=float)) / tau)
    for i in range(1, len(y)):
        out[i] = out[i - 1] + a[i - 1] * (y[i] - out[i - 1])
    return out


def delayed(t: np.ndarray, y: np.ndarray, tau: float) -> np.ndarray:
    """``y(t - tau)`` by linear interpolation along axis 0 (held at the first sample before it)."""
    y = np.asarray(y, dtype=float)
    flat = y.reshape(len(y), -1)
    out = np.stack([np.interp(t - tau, t, flat[:, j]) for j in range(flat.shape[1])], axis=1)
    return out.reshape(y.shape)


def first_order(t: np.ndarray, y: np.ndarray, tau: float, a: float) -> np.ndarray:
    """``(1 - a) y + a L_tau y`` along axis 0."""
    return (1.0 - a) * np.asarray(y, dtype=float) + a * low_pass(t, y, tau)


HYSTERESIS = 0.5
"""A contact event's crossing counts only when the signal then leaves the level by this fraction
of it before crossing back (below ``(1 - HYSTERESIS)`` of the level after a falling crossing, above
``(1 + HYSTERESIS)`` of it after a rising one): a Schmitt trigger, so that the replay's
step-to-step roughness near the level (its contact solve at the 0.01 s replay step) does not split
one press into several overlapping events."""


def _crossings(t: np.ndarray, y: np.ndarray, level: float) -> list[tuple[float, int, int]]:
    """Crossings of ``level`` as ``[(time s, +1 / -1, sample index before it)]``, linear interpolation."""
    above = y > level
    d = np.diff(above.astype(np.int8))
    out = []
    for i in np.nonzero(d)[0]:
        y0, y1 = y[i], y[i + 1]
        f = (level - y0) / (y1 - y0) if y1 != y0 else 0.0
        out.append((float(t[i] + f * (t[i + 1] - t[i])), int(d[i]), int(i)))
    return out


def contact_events(t: np.ndarray, y_pred: np.ndarray, fraction: float = EVENT_FRACTION,
                   hysteresis: float = HYSTERESIS) -> list[tuple[float, int]]:
    """Crossings of ``fraction`` of the peak of ``y_pred`` as ``[(time s, +1 rising / -1 falling)]``.

    A pair of crossings that encloses only a shallow excursion (the signal dips below the level but
    not below ``(1 - hysteresis)`` of it, or rises above it but not above ``(1 + hysteresis)`` of
    it) is dropped: roughness around the level, not a contact event (:data:`HYSTERESIS`).
    """
    y_pred = np.asarray(y_pred, dtype=float)
    peak = float(np.max(y_pred)) if len(y_pred) else 0.0
    if not peak > 0.0:
        return []
    level = fraction * peak
    cross = _crossings(np.asarray(t, dtype=float), y_pred, level)
    while len(cross) > 1:
        # relative depth of the excursion between each pair of neighbouring crossings
        depth = []
        for (_, dj, ij), (_, _, ik) in zip(cross[:-1], cross[1:]):
            seg = y_pred[ij + 1: ik + 1]
            depth.append((seg.max() - level) / level if dj > 0 else (level - seg.min()) / level)
        j = int(np.argmin(depth))
        if depth[j] >= hysteresis:
            break
        del cross[j: j + 2]  # the shallowest excursion first: the crossings that remain are the outer ones
    return [(tc, d) for tc, d, _ in cross]


MIN_WINDOW_SAMPLES = 10
"""An event window with fewer samples is not read."""


RELEASE_TAIL_S = TAU_MAX_S
"""Extra free side of a falling event's window in the delay and lag fits, s: the largest delay or
time constant searched. A stream delayed or lagged by ``tau`` moves a release ``tau`` into the free
side, where the replay predicts no force and a first-order lag leaves its exponential tail (the part
of the response by which a lag differs from a delay; on the ramp before it the two agree, both
shifting it by the mean delay); the window then keeps ``WINDOW_BEFORE_S`` of free gel beyond the
shifted release, as it does beyond an unshifted one. A rising event needs no extension: its response
moves into the contact side, which already reaches ``WINDOW_AFTER_S`` = ``TAU_MAX_S``."""


def event_windows(t: np.ndarray, y_pred: np.ndarray,
                  release_tail_s: float = 0.0) -> list[tuple[float, int, float, float, np.ndarray]]:
    """The window read around each contact event of the replay (:func:`contact_events`):
    ``[(time s, +1 rising / -1 falling, window start s, window end s, mask (n,))]``, reaching
    ``WINDOW_BEFORE_S`` before the event into the free side and ``WINDOW_AFTER_S`` into the contact;
    windows with fewer than ``MIN_WINDOW_SAMPLES`` samples are left out.

    Args:
        t: sample times, s, shape ``(n,)``.
        y_pred: predicted signal, shape ``(n,)``.
        release_tail_s: extra free side after a falling event, s (:data:`RELEASE_TAIL_S` for the
            delay and lag fits), never reaching into the next event's window.
    """
    out = []
    events = contact_events(t, y_pred)
    for k, (te, direction) in enumerate(events):
        lo, hi = (te - WINDOW_BEFORE_S, te + WINDOW_AFTER_S) if direction > 0 else (te - WINDOW_AFTER_S, te + WINDOW_BEFORE_S)
        if direction < 0 and release_tail_s > 0.0:
            limit = events[k + 1][0] - WINDOW_BEFORE_S if k + 1 < len(events) else np.inf
            hi = max(hi, min(hi + release_tail_s, limit))
        m = (t >= lo) & (t <= hi)
        if m.sum() >= MIN_WINDOW_SAMPLES:
            out.append((te, direction, lo, hi, m))
    return out


def _fit(y: np.ndarray, cols: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Residual and coefficients of ``y`` regressed on ``cols`` and a constant."""
    X = np.stack(cols + [np.ones_like(y)], axis=1)
    c, *_ = np.linalg.lstsq(X, y, rcond=None)
    return y - X @ c, c


def _sse(y: np.ndarray, cols: list[np.ndarray]) -> tuple[float, np.ndarray]:
    r, c = _fit(y, cols)
    return float(r @ r), c


SHAPE_BLOCK_S = 0.05
"""Block length of the shape test, s: the span of the filter through which the replay is read
(:data:`REPLAY_SMOOTH_S`), over which the windows' residuals are correlated."""


def paired_shape_z(sse_difference: float, curve_distance: float, phi: float, extra_params: int) -> float:
    """Paired test of two non-nested least-squares fits ``f_1`` (e.g. the delay) and ``f_2`` (the
    lag) of one whitened series ``y``: ``z = (SSE_1 - SSE_2 - phi k) / (2 sqrt(phi D))``, > 0 when
    the second fits better.

    ``SSE_1 - SSE_2 = ||y - f_1||^2 - ||y - f_2||^2`` is the deterministic part (zero when the truth
    is as far from either fit) plus ``2 <e, f_2 - f_1>``, whose variance under noise ``e`` of
    variance ``phi`` per sample is ``4 phi D`` with ``D = ||f_2 - f_1||^2``; ``k``, the second fit's
    extra parameters, is what it gains on noise alone (Akaike's correction, in quasi-likelihood units
    ``phi``). Vuong (1989), Econometrica 57(2) 307-333, sec. 5, with the variance from the noise model.

    Args:
        sse_difference: ``SSE_1 - SSE_2``, whitened.
        curve_distance: ``D``, the whitened squared distance between the two fitted curves.
        phi: the residual's dispersion (>= 1, :func:`~sysid.diagnose.signatures.base.dispersion`).
        extra_params: ``k``.

    Returns:
        ``z``; 0 when the two curves lie within the noise of the extra parameters of each other
        (``D <= phi k``: the fits are observationally equivalent, Vuong's sec. 4 pretest, and
        neither shape is preferred).
    """
    if not curve_distance > phi * extra_params or not curve_distance > 0.0:
        return 0.0
    return float((sse_difference - phi * extra_params) / (2.0 * np.sqrt(phi * curve_distance)))


def shape_z(block_sums: np.ndarray) -> float:
    """Vuong's statistic (Vuong 1989) of two non-nested fits from per-block sums of the pointwise
    difference of their whitened squared residuals ``(B,)``: ``sum / (sqrt(B) std)``, > 0 when the
    second fit is better; 0 with fewer than two blocks or no difference."""
    d = np.asarray(block_sums, dtype=float)
    if len(d) < 2:
        return 0.0
    sd = float(np.std(d, ddof=1))
    return float(d.sum() / (np.sqrt(len(d)) * sd)) if sd > 0.0 else 0.0


REPLAY_SMOOTH_S = 0.05
"""Span of the quadratic Savitzky-Golay filter through which the timing fits read the replay, s:
longer than the replay's step (0.01 s by default), whose contact solve leaves step-to-step
roughness on the predicted force. Read raw, that roughness favours the first-order lag (which
smooths it away) over a pure delay (which keeps it) whatever the recording's timing; through the
filter both shapes see the same replay. The damping test reads it through the same span
(:data:`sysid.diagnose.signatures.damping.RATE_WINDOW_S`)."""


def smoothed_replay(t: np.ndarray, y: np.ndarray, span_s: float = REPLAY_SMOOTH_S) -> np.ndarray:
    """``y`` through a quadratic Savitzky-Golay filter over ``span_s`` (Savitzky & Golay 1964),
    along axis 0, on the uniform time base ``t`` (s); a series shorter than the filter is returned
    as a copy.

    Args:
        t: sample times, s, shape ``(n,)``.
        y: samples, shape ``(n, ...)``.
        span_s: filter span, s (at least 5 samples, odd).
    """
    y = np.asarray(y, dtype=float)
    if len(y) < 3:
        return y.copy()
    dt = float(np.median(np.diff(np.asarray(t, dtype=float))))
    w = max(5, int(round(span_s / dt)) if dt > 0 else 5)
    w = w if w % 2 == 1 else w + 1
    return savgol_filter(y, w, 2, axis=0) if len(y) >= w else y.copy()


def timing_signal(rec: Recording) -> tuple[str, np.ndarray, np.ndarray, np.ndarray, float] | None:
    """The signal the timing tests read: ``(channel, t (n,) s, recorded (n,), predicted (n,), sigma)``:
    the compressive normal force (N) when the wrench is recorded and predicted, else the mean marker
    depth (m); None without either."""
    if rec.predicted("wrench"):
        t = rec.t["wrench"]
        return ("wrench", t, normal_force(rec.data["wrench"]), normal_force(rec.prediction["wrench"]),
                float(rec.sigma["wrench"][2]))
    if rec.predicted("markers_xyz"):
        t = rec.t["markers_xyz"]
        k = rec.data["markers_xyz"].shape[1]
        return ("markers_xyz", t, mean_marker_depth(rec.data["markers_xyz"]),
                mean_marker_depth(rec.prediction["markers_xyz"]),
                float(rec.sigma["markers_xyz"][2]) / np.sqrt(k))
    return None


def timing_fits(rec: Recording, taus: np.ndarray | None = None) -> dict | None:
    """Delay and first-order fits at every contact event.

    Returns:
        None without a predicted normal force or marker depth, else a dict with ``channel``,
        ``events`` (one dict per event: time, direction, window, whitened SSE at tau = 0, best delay
        and its SSE, best first-order tau / fraction, its mean delay ``a tau`` and its SSE), the
        summed SSEs, ``shape_z`` (:func:`paired_shape_z` of the best delay against the best lag
        over every event: > 0 when the lag fits better) and ``shape_z_blocks`` (:func:`shape_z`,
        Vuong's estimate of the same from the spread over blocks).
    """
    sig = timing_signal(rec)
    if sig is None:
        return None
    channel, t, y, yp, sigma = sig
    yp = smoothed_replay(t, yp)
    if taus is None:
        taus = np.arange(0.0, TAU_MAX_S + 1e-9, max(rec.sample_period(channel) / 2.0, 1e-3))
    events, blocks = [], []
    distance, block_sq, fitted, params = 0.0, 0.0, 0, 0
    lp_cache = {tau: low_pass(t, yp, tau) for tau in taus[1:]}
    for te, direction, lo, hi, m in event_windows(t, yp, RELEASE_TAIL_S):
        s0, _ = _sse(y[m], [yp[m]])
        sd = [(s0, 0.0)]
        for tau in taus[1:]:
            sd.append((_sse(y[m], [np.interp(t - tau, t, yp)[m]])[0], float(tau)))
        best_d = min(sd)
        sl = [(s0, 0.0, 0.0)]
        for tau in taus[1:]:
            s, c = _sse(y[m], [yp[m], lp_cache[tau][m]])
            tot = c[0] + c[1]
            a = float(c[1] / tot) if tot != 0.0 else 0.0
            if 0.0 <= a <= MAX_LAG_FRACTION:  # a lag, not a lead
                sl.append((s, float(tau), a))
            elif a > MAX_LAG_FRACTION:
                # the constrained optimum lies on the nearer bound (a share below 0: ``s0``, listed)
                col = (1.0 - MAX_LAG_FRACTION) * yp[m] + MAX_LAG_FRACTION * lp_cache[tau][m]
                sl.append((_sse(y[m], [col])[0], float(tau), MAX_LAG_FRACTION))
        best_l = min(sl)
        # pointwise difference of the two best fits (delay minus lag), whitened, summed per block
        r_d, _ = _fit(y[m], [np.interp(t - best_d[1], t, yp)[m]])
        lag = yp[m] if best_l[1] <= 0.0 else (1.0 - best_l[2]) * yp[m] + best_l[2] * lp_cache[best_l[1]][m]
        r_l, _ = _fit(y[m], [lag])
        diff = (r_d ** 2 - r_l ** 2) / sigma ** 2
        per_block = max(1, int(round(SHAPE_BLOCK_S / rec.sample_period(channel))))
        starts = np.arange(0, len(diff), per_block)
        blocks.extend(np.add.reduceat(diff, starts).tolist())
        # the two fitted curves differ by r_d - r_l; the better fit's residual, summed per block, gives
        # the dispersion at the block scale (a block of white noise sums to a variance of its length)
        distance += float(np.sum((r_d - r_l) ** 2)) / sigma ** 2
        best_r = r_l if best_l[0] < best_d[0] else r_d
        block_sq += float(np.sum(np.add.reduceat(best_r / sigma, starts) ** 2))
        fitted += int(m.sum())
        params += 4  # a gain, an offset, a time constant and, for the lag, its share
        events.append({"t_s": te, "direction": "rising" if direction > 0 else "falling", "window_s": [lo, hi],
                       "samples": int(m.sum()), "sse0": s0 / sigma ** 2, "delay_s": best_d[1], "sse_delay": best_d[0] / sigma ** 2,
                       "lag_tau_s": best_l[1], "lag_fraction": best_l[2], "lag_delay_s": best_l[1] * best_l[2],
                       "sse_lag": best_l[0] / sigma ** 2})
    return {"channel": channel, "events": events,
            "samples": int(sum(e["samples"] for e in events)),
            "sse0": float(sum(e["sse0"] for e in events)),
            "sse_delay": float(sum(e["sse_delay"] for e in events)),
            "sse_lag": float(sum(e["sse_lag"] for e in events)),
            "shape_z": paired_shape_z(sum(e["sse_delay"] - e["sse_lag"] for e in events), distance,
                                      dispersion(block_sq, fitted, params) if fitted > params else 1.0, len(events)),
            "shape_z_blocks": shape_z(np.asarray(blocks))}


def press_sizes(events: list[dict], key: str) -> list[float]:
    """The size of a timing effect per press: the mean of ``key`` (an event's delay or lag time
    constant, s) over the press's rising event and the falling event that follows it; an event
    without its partner (a recording that begins or ends in contact) is a press of its own.

    Why the mean: the calibrated replay's depth gap (where contact begins and how the force grows
    with depth: the sensor offset, the contact's compliance, the gel's modulus, each fitted on a
    recording whose tactile streams may lag) moves a press's rising crossing and its falling one in
    opposite directions (a contact that begins later ends earlier), while a latency or a lag of the
    stream moves both the same way; the mean keeps the stream's timing and cancels the depth gap to
    first order. A 40 ms latency on nominal_s109 read through a replay calibrated with a 16 um
    shallower mount gave 12.5 ms on the rise and 37.5 ms on the fall (30 / 30 ms through the
    scene-value replay).
    """
    events = sorted(events, key=lambda e: e["t_s"])
    out, i = [], 0
    while i < len(events):
        e = events[i]
        if e["direction"] == "rising" and i + 1 < len(events) and events[i + 1]["direction"] == "falling":
            out.append(0.5 * (float(e[key]) + float(events[i + 1][key])))
            i += 2
        else:
            out.append(float(e[key]))
            i += 1
    return out


def timing_size(events: list[dict], key: str) -> float:
    """Effect size of a timing effect, s: the smallest press size (:func:`press_sizes`), and 0 unless
    every event is delayed (``key`` > 0 at each: an effect of the stream moves every event, a gap on
    one side of a press alone is not one)."""
    if not events or min(float(e[key]) for e in events) <= 0.0:
        return 0.0
    return float(min(press_sizes(events, key)))


def explained_share(sse0: float, sse_fit: float, samples: float) -> float:
    """Share of the event windows' excess energy ``sse0 - samples`` (whitened SSE beyond the noise's
    expectation) that a fit removes, ``(sse0 - sse_fit) / (sse0 - samples)``, in [0, 1]: a fit that removes more
    than the excess (the noise's share included) explains all of it, and where the windows hold no excess
    (``sse0 <= samples``) the share is 1 if the fit removes anything (the statistic, not this share, then
    decides) and 0 otherwise (session 51: it read 1e11-1e13 there, the excess floored at 1e-12)."""
    removed = max(float(sse0) - float(sse_fit), 0.0)
    excess = float(sse0) - float(samples)
    if removed <= 0.0:
        return 0.0
    return float(min(removed / excess, 1.0)) if excess > 0.0 else 1.0


def timing_tests(rec: Recording) -> tuple[SignatureResult, SignatureResult]:
    """The latency and the gel viscoelasticity results from one set of :func:`timing_fits`."""
    fits = timing_fits(rec)
    if fits is None:
        reason = "needs a predicted wrench or marker positions (a calibrated replay)"
        return not_applicable("latency", reason), not_applicable("gel_viscoelasticity", reason)
    ev = fits["events"]
    if not ev:
        reason = "the replay predicts no contact event"
        return not_applicable("latency", reason), not_applicable("gel_viscoelasticity", reason)
    windows = [e["window_s"] for e in ev]
    delays = np.array([e["delay_s"] for e in ev])
    lag_taus = np.array([e["lag_tau_s"] for e in ev])
    detail = {"channel": fits["channel"], "events": ev, "samples": fits["samples"], "sse0": fits["sse0"],
              "explained_delay": explained_share(fits["sse0"], fits["sse_delay"], fits["samples"]),
              "explained_lag": explained_share(fits["sse0"], fits["sse_lag"], fits["samples"]),
              "sse_delay": fits["sse_delay"],
              "sse_lag": fits["sse_lag"],
              # shape: the paired z, > 0 when the first-order lag fits the events better than a pure delay
              "shape_z": fits["shape_z"], "shape_z_blocks": fits["shape_z_blocks"]}
    lat = SignatureResult(effect="latency", statistic=max(fits["sse0"] - fits["sse_delay"], 0.0),
                          effect_size=timing_size(ev, "delay_s"), effect_unit="s (smallest press delay)",
                          estimate={"latency_s": float(np.median(delays))}, windows_s=windows,
                          channels=["markers_xyz", "markers_uv", "wrench"],
                          detail=dict(detail, delays_s=delays.tolist(), press_delays_s=press_sizes(ev, "delay_s")))
    frac = float(np.median([e["lag_fraction"] for e in ev]))
    visco = SignatureResult(effect="gel_viscoelasticity", statistic=max(fits["sse0"] - fits["sse_lag"], 0.0),
                            effect_size=timing_size(ev, "lag_delay_s"),
                            effect_unit="s (smallest press mean delay a tau)",
                            estimate={"tau_s": float(np.median(lag_taus)), "fraction": frac}, windows_s=windows,
                            channels=["markers_xyz", "markers_uv", "wrench"],
                            detail=dict(detail, taus_s=lag_taus.tolist(), press_taus_s=press_sizes(ev, "lag_tau_s"),
                                        press_lag_delays_s=press_sizes(ev, "lag_delay_s")))
    return lat, visco
