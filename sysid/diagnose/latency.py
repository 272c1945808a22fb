"""Latency's discriminating tests: cross-correlation lags, per-stream delays, the latency tie.

A delay of a stream (its topic stamped ``tau`` late) shows as a lag of the recorded rate of change
behind the predicted one; the refitted delay must agree with that lag before latency is named
(:mod:`sysid.diagnose.engine`, acceptance), and only streams whose own delay agrees share one delay.
Pure functions over an observation model (``data``, ``sigma``) and a diagnosis context
(``prediction``, ``stamps_s``); notes for the report are appended to ``notes``.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from sysid.diagnose import candidates as cands
from sysid.diagnose import locate
from sysid.diagnose.residuals import residual, whiten

SMOOTHING = np.array([0.25, 0.5, 0.25])
"""[1, 2, 1] / 4 smoothing of the whitened rates before the cross-correlation."""


def delays_agree(tau: float, reference: float, period: float) -> bool:
    """``|tau - reference| <= max(1.5 period, reference / 2)`` (s): the tolerance every latency
    comparison uses (a sample and a half, or half the delay itself)."""
    return bool(np.isfinite(tau) and abs(tau - reference) <= max(1.5 * period, 0.5 * abs(reference)))


def xcorr_lags(model: Any, ctx: Any, channels: Sequence[str], notes: list[str]) -> dict[str, float]:
    """Per channel: lag (s) of the recorded rate of change behind the predicted one, from the peak of
    their cross-correlation (:func:`sysid.diagnose.locate.xcorr_lag`; whitened, [1, 2, 1]/4 smoothed).

    Channels with fewer than 12 samples are skipped; a channel whose lag is undefined is noted."""
    out = {}
    for ch in channels:
        t = ctx.stamps_s(ch)
        if t.shape[0] < 12:
            continue
        period = float(np.median(np.diff(t)))
        rates = []
        for y in (ctx.prediction[ch], model.data(ch)):
            d = whiten(model, ch, cands.time_derivative(t, y)).reshape(t.shape[0], -1)
            rates.append(np.apply_along_axis(lambda c: np.convolve(c, SMOOTHING, mode="same"), 0, d))
        try:
            out[ch] = float(locate.xcorr_lag(rates[0], rates[1], period,
                                             min(cands.LATENCY_BOUND_S, 0.25 * (t[-1] - t[0]))))
        except ValueError as err:
            notes.append(f"xcorr lag on {ch}: {err}")
    return out


def xcorr_confirms(model: Any, ctx: Any, tau: float, channels: Sequence[str], notes: list[str]
                   ) -> tuple[dict[str, float], bool]:
    """The discriminating test of a refitted delay ``tau`` (s) on ``channels``: the median
    cross-correlation lag agrees with it (:func:`delays_agree`, median sample period).

    Returns:
        ``(lags per channel, agrees)``.
    """
    lags = xcorr_lags(model, ctx, channels, notes)
    period = float(np.median([np.median(np.diff(ctx.stamps_s(ch))) for ch in channels]))
    lag = float(np.median(list(lags.values()))) if lags else float("nan")
    return lags, delays_agree(lag, tau, period)


def streams_sharing_delay(model: Any, ctx: Any, train: Mapping[str, np.ndarray], strongest: str,
                          channels: Sequence[str], notes: list[str]) -> list[str]:
    """The channels that share one stream delay.

    A latency is a property of a stream (one topic is stamped late), so a stream whose latency
    test fired only because a model gap correlates with ``dy/dt`` must not be delayed with it.
    Each stream's own delay is fitted on its training rows alone and checked against its own
    cross-correlation lag (:func:`xcorr_confirms`, per stream). The reference is the confirmed
    stream whose delay removes most of its SSE (the stream of ``strongest`` when none is
    confirmed); streams whose own delay agrees with the reference's (:func:`delays_agree`) share
    it, the others are left out (noted).
    """
    lat = cands.LatencyCandidate()
    streams: dict[str, list[str]] = {}
    for ch in channels:
        streams.setdefault(cands.STREAMS[ch], []).append(ch)
    taus, gains, confirmed = {}, {}, {}
    for name, chs in streams.items():
        def obj(pred, chs=chs):
            return sum(float(np.sum(residual(model, ch, pred[ch])[train[ch]] ** 2)) for ch in chs)

        rf = lat.refit(ctx, chs, obj)
        taus[name] = float(rf.beta[0])
        gains[name] = obj(ctx.prediction) - obj(rf.prediction)
        period = float(np.median(np.diff(ctx.stamps_s(chs[0]))))
        lags = list(xcorr_lags(model, ctx, chs, notes).values())
        lag = float(np.median(lags)) if lags else float("nan")
        confirmed[name] = delays_agree(lag, taus[name], period)
    good = [n for n in streams if confirmed[n]]
    ref_name = max(good, key=lambda n: gains[n]) if good else cands.STREAMS[strongest]
    ref = taus[ref_name]
    period = float(np.median(np.diff(ctx.stamps_s(streams[ref_name][0]))))
    keep = [name for name, tau in taus.items() if delays_agree(tau, ref, period)]
    left = sorted(set(taus) - set(keep))
    if left:
        notes.append(f"latency: streams {left} left out of the delay (own delays "
                     f"{ {n: round(taus[n], 4) for n in left} } s vs {round(ref, 4)} s on {ref_name}"
                     f"{', confirmed by its cross-correlation lag' if good else ''})")
    return sorted(ch for name in keep for ch in streams[name])


def delay_by_channel(model: Any, ctx: Any, tested: Sequence[str]) -> dict[str, float]:
    """Latency fitted per tested channel except the sheet points (s): the discriminating test
    against gel viscoelasticity (:func:`tie_resolution`)."""
    lat = cands.LatencyCandidate()
    out = {}
    for ch in tested:
        if ch == "sheet_points":
            continue

        def obj(pred: Mapping[str, np.ndarray], ch: str = ch) -> float:
            return float(np.sum(residual(model, ch, pred[ch]) ** 2))

        out[ch] = float(lat.refit(ctx, [ch], obj).beta[0])
    return out


def tie_resolution(delays: Mapping[str, float], xcorr_agrees: bool, period: float = 0.01) -> str | None:
    """Why latency wins its tie with gel viscoelasticity, or None when it does not.

    Latency wins when its cross-correlation test agreed and one delay fits every tactile channel
    (``delays``: :func:`delay_by_channel`): their spread is below ``max(period, |mean| / 4)``.
    """
    taus = [v for ch, v in delays.items() if cands.STREAMS[ch].startswith("tactile")]
    if xcorr_agrees and taus and (max(taus) - min(taus)) < max(period, 0.25 * abs(np.mean(taus))):
        return "one lag fits every tactile channel and matches the cross-correlation lag of recorded vs predicted rates"
    return None

