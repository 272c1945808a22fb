"""Where the mismatch is: time windows, channels, markers; and the lag of a delayed stream.

- Time windows: the per-sample explained energy of a candidate's refit,
  ``d_t = sum_s r_ts^2 - (r_ts - J_ts beta)^2`` (whitened residual r before / after), is cut into
  segments of constant mean by PELT (Killick, Fearnhead & Eckley 2012; the ``ruptures`` package,
  cost ``l2``, penalty ``3 var(d) log T`` -- a BIC-type penalty on the noise level of d estimated
  from its first differences). Segments whose mean explained energy is significantly positive
  (mean > 3 standard errors) are the windows; adjacent ones are merged.
- Markers: share of each marker in the explained energy; a marker is named when its share exceeds
  ``1/k`` by 2 standard deviations of the shares (k markers), or, when the explained energy is
  spread over all markers (a global effect), all markers above the median are named.
- Lag: the integer-lag cross-correlation of the mean-removed signals with a parabolic refinement
  of its peak (Jacovitti & Scarano 1993), for the residual/input check of a latency.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from sysid.diagnose.residuals import residual, whiten
from sysid.noise import robust_scale


def explained_energy(r: np.ndarray, delta_prediction: np.ndarray) -> np.ndarray:
    """Per-sample explained energy of a refit.

    Args:
        r: whitened residual before the refit, ``(T, ...)``.
        delta_prediction: whitened change of the prediction by the refit, ``(T, ...)``.

    Returns:
        ``(T,)``: ``sum r^2 - (r - delta)^2`` over all non-time axes (> 0 where the refit helps).
    """
    r = np.asarray(r, dtype=float).reshape(r.shape[0], -1)
    d = np.asarray(delta_prediction, dtype=float).reshape(r.shape[0], -1)
    return np.sum(r ** 2 - (r - d) ** 2, axis=1)


def change_points(signal: np.ndarray, min_size: int = 5, penalty: float | None = None) -> list[int]:
    """Segment ends (exclusive indices, last = T) of a piecewise-constant-mean fit of ``signal (T,)`` (PELT, l2).

    Args:
        signal: ``(T,)``.
        min_size: shortest segment, samples.
        penalty: PELT penalty (default ``3 s^2 log T``, s the robust noise scale of the signal).
    """
    import ruptures

    x = np.asarray(signal, dtype=float).reshape(-1)
    T = x.shape[0]
    if T < 2 * min_size:
        return [T]
    if penalty is None:
        s = robust_scale(np.diff(x)) / np.sqrt(2.0)
        s = s if np.isfinite(s) and s > 0 else float(np.std(x)) or 1.0
        penalty = 3.0 * s * s * np.log(T)
    algo = ruptures.Pelt(model="l2", min_size=min_size, jump=1).fit(x.reshape(-1, 1))
    return [int(b) for b in algo.predict(pen=penalty)]


def windows_from_energy(t_s: np.ndarray, energy: np.ndarray, min_size: int = 5, z: float = 3.0
                        ) -> list[tuple[float, float]]:
    """Time windows where the explained energy is significantly positive.

    Args:
        t_s: stamps ``(T,)``, s.
        energy: per-sample explained energy ``(T,)`` (:func:`explained_energy`).
        min_size: shortest segment, samples.
        z: a segment is kept when its mean exceeds z standard errors (noise scale from first differences).

    Returns:
        sorted, merged ``[(start_s, end_s), ...]``.
    """
    t = np.asarray(t_s, dtype=float)
    e = np.asarray(energy, dtype=float)
    ends = change_points(e, min_size=min_size)
    s = robust_scale(np.diff(e)) / np.sqrt(2.0)
    if not (np.isfinite(s) and s > 0):
        s = float(np.std(e)) or 1.0
    out: list[tuple[float, float]] = []
    start = 0
    for end in ends:
        seg = e[start:end]
        if seg.size and seg.mean() > z * s / np.sqrt(seg.size):
            a, b = float(t[start]), float(t[end - 1])
            if out and start > 0 and abs(out[-1][1] - float(t[start - 1])) < 1e-12:
                out[-1] = (out[-1][0], b)
            else:
                out.append((a, b))
        start = end
    return out


def marker_attribution(r: np.ndarray, delta_prediction: np.ndarray, rows: np.ndarray | None = None) -> list[int]:
    """Markers that carry the explained energy.

    Args:
        r: whitened marker residual ``(T, k, axes)``.
        delta_prediction: whitened prediction change ``(T, k, axes)``.
        rows: time samples to use (the located windows), default all.

    Returns:
        sorted marker indices.
    """
    r = np.asarray(r, dtype=float)
    d = np.asarray(delta_prediction, dtype=float)
    if rows is not None and np.any(rows):
        r, d = r[rows], d[rows]
    per_marker = np.sum(r ** 2 - (r - d) ** 2, axis=(0, 2))
    total = float(np.sum(np.clip(per_marker, 0.0, None)))
    k = per_marker.shape[0]
    if total <= 0.0:
        return []
    share = np.clip(per_marker, 0.0, None) / total
    sd = float(np.std(share))
    named = np.nonzero(share > 1.0 / k + 2.0 * sd)[0]
    if named.size == 0:
        named = np.nonzero(share > np.median(share))[0]
    return [int(i) for i in named]


def xcorr_lag(reference: np.ndarray, delayed: np.ndarray, period_s: float, max_lag_s: float) -> float:
    """Delay of ``delayed`` behind ``reference`` from the peak of their cross-correlation.

    Args:
        reference: ``(T,)`` or ``(T, c)`` (columns are summed in the correlation).
        delayed: same shape, sampled on the same uniform grid.
        period_s: sampling period, s.
        max_lag_s: largest |lag| searched, s.

    Returns:
        lag in s (> 0: ``delayed`` lags behind), refined between samples by a parabola through the peak.

    Raises:
        ValueError: shape mismatch or a search range leaving fewer than 3 overlapping samples.
    """
    a = np.asarray(reference, dtype=float)
    b = np.asarray(delayed, dtype=float)
    if a.shape != b.shape:
        raise ValueError(f"reference {a.shape} and delayed {b.shape} differ in shape")
    a = a.reshape(a.shape[0], -1)
    b = b.reshape(b.shape[0], -1)
    a = a - a.mean(axis=0)
    b = b - b.mean(axis=0)
    T = a.shape[0]
    L = int(round(max_lag_s / period_s))
    if T - L < 3:
        raise ValueError(f"a lag search of +-{max_lag_s} s leaves fewer than 3 of {T} samples")
    lags = np.arange(-L, L + 1)
    c = np.empty(lags.shape[0])
    for i, lag in enumerate(lags):
        if lag >= 0:
            x, y = a[:T - lag], b[lag:]
        else:
            x, y = a[-lag:], b[:T + lag]
        c[i] = np.sum(x * y) / np.sqrt(np.sum(x * x) * np.sum(y * y))
    i = int(np.argmax(c))
    frac = 0.0
    if 0 < i < c.shape[0] - 1:
        den = c[i - 1] - 2.0 * c[i] + c[i + 1]
        if den < 0.0:
            frac = 0.5 * (c[i - 1] - c[i + 1]) / den
    return float((lags[i] + frac) * period_s)


def locate_refit(model: Any, ctx: Any, refit: Any, channels: Sequence[str], t0: float
                 ) -> tuple[list[tuple[float, float]], list[int]]:
    """Windows and markers where a refit explains the residual.

    Per channel in ``channels`` that the refit predicts: :func:`explained_energy` of the whitened
    nominal residual by the whitened prediction change, summed over channels on the first one's
    stamps; windows from :func:`windows_from_energy`, shifted by ``t0`` (s: replay start relative to
    the recording's first pose); markers by :func:`marker_attribution` on the first marker channel.

    Returns:
        ``(windows [(start, end) in s], marker indices)``, both empty when no channel applies.
    """
    windows: list[tuple[float, float]] = []
    markers: list[int] = []
    energy_t, energy = None, None
    for ch in channels:
        if ch not in refit.prediction:
            continue
        r = residual(model, ch, ctx.prediction[ch])
        d = whiten(model, ch, refit.prediction[ch] - ctx.prediction[ch])
        e = explained_energy(r, d)
        t = ctx.stamps_s(ch)
        if energy is None:
            energy_t, energy = t, e
        else:
            energy = energy + np.interp(energy_t, t, e)
        if ch in ("markers_xyz", "markers_uv") and not markers:
            markers = marker_attribution(r, d)
    if energy is not None:
        windows = [(a + t0, b + t0) for a, b in windows_from_energy(energy_t, energy)]
    return windows, markers
