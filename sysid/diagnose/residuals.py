"""Residual arithmetic of the diagnosis: whitening, SSE, held-out rows, RMS summaries, effect size.

Pure functions over an observation model (``sysid.observation.ObservationModel`` or anything with
``data(channel)``, ``sigma``, ``residual_weight_root(channel)`` and ``evidence.channels_present``) and channel -> prediction maps;
:mod:`sysid.diagnose.engine` composes them.
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

import numpy as np

from sysid.diagnose import candidates as cands

RMS_KEYS = {"markers_uv": "markers_px", "markers_xyz": "markers_m", "wrench": "wrench_N",
            "sheet_points": "sheet_points_m"}

"""Report key of each channel's RMS (wrench is split into force and torque)."""


def whiten(model: Any, channel: str, a: np.ndarray) -> np.ndarray:
    """Divide the last data axis by the channel noise and multiply each sample by the square root of its weight
    (``ObservationModel.residual_weight_root``: the image tracker's marker weights, 0 for an interpolated marker);
    ``a`` is ``(T, ..., axes)`` or ``(T, ..., axes, q)``."""
    s = model.sigma[channel]
    data_ndim = model.data(channel).ndim
    root = model.residual_weight_root(channel) if channel == "markers_uv" else 1.0  # only pixels carry weights
    if a.ndim > data_ndim:
        extra = (1,) * (a.ndim - data_ndim)
        return a / s.reshape((-1,) + extra) * (root if isinstance(root, float) else root.reshape(root.shape + extra))
    return a / s * root


def residual(model: Any, channel: str, prediction: np.ndarray) -> np.ndarray:
    """Whitened ``data - prediction`` of one channel, shape of the channel's data."""
    return whiten(model, channel, model.data(channel) - prediction)


def holdout_rows(t_s: np.ndarray, blocks: int, span: tuple[float, float]) -> np.ndarray:
    """True on held-out rows: every other of ``2 * blocks`` equal time blocks (the odd ones)."""
    a, b = span
    k = np.clip(((t_s - a) / max(b - a, 1e-12) * 2 * blocks).astype(int), 0, 2 * blocks - 1)
    return (k % 2) == 1


def rms_summary(model: Any, prediction: Mapping[str, np.ndarray]) -> dict[str, float]:
    """RMS of ``data - prediction`` per channel in SI units / px (report keys of :data:`RMS_KEYS`)."""
    out = {}
    for ch, key in RMS_KEYS.items():
        if ch in prediction and ch in model.evidence.channels_present:
            e = model.data(ch) - prediction[ch]
            if ch == "wrench":
                out["wrench_N"] = float(np.sqrt(np.mean(e[:, :3] ** 2)))
                out["torque_Nm"] = float(np.sqrt(np.mean(e[:, 3:] ** 2)))
            else:
                out[key] = float(np.sqrt(np.mean(e ** 2)))
    return out


def sse(model: Any, prediction: Mapping[str, np.ndarray], channels: Sequence[str],
         rows: Mapping[str, np.ndarray] | None) -> tuple[float, int, int]:
    """Whitened SSE over channels (rows selected), number of values and of time samples."""
    sse, n, t = 0.0, 0, 0
    for ch in channels:
        r = residual(model, ch, prediction[ch])
        if rows is not None:
            r = r[rows[ch]]
        sse += float(np.sum(r ** 2))
        n += r.size
        t += r.shape[0]
    return sse, n, t


def explained_fraction(before: float, after: float) -> float:
    """Fraction of the excess energy ``rms^2 - 1`` (whitened) that a refit removes.

    The excess is floored at 5 % of ``before^2`` so that an over-estimated noise level (excess <= 0)
    does not make a tiny improvement look complete.
    """
    excess = max(before ** 2 - 1.0, 0.05 * before ** 2, 1e-12)
    return float((before ** 2 - after ** 2) / excess)


def stream_channels(channel: str, tested: Sequence[str]) -> list[str]:
    """The tested channels that come from the same ROS topic as ``channel`` (e.g. markers xyz/uv)."""
    stream = cands.STREAMS[channel]
    return [c for c in tested if cands.STREAMS[c] == stream]


def heldout_products(model: Any, before: Mapping[str, np.ndarray], after: Mapping[str, np.ndarray],
                     channels: Sequence[str], rows: Mapping[str, np.ndarray] | None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per time sample, ``a_t = sum r_0 . delta``, ``b_t = sum delta . delta``, ``c_t = sum r_0 . r_0``
    and the number of values ``n_t`` (whitened), where ``r_0`` is the residual of ``before`` and
    ``delta = after - before`` (the inputs of :func:`sysid.diagnose.stats.heldout_test`).

    Channels are summed onto the simulation steps their stamps fall in (``model.step_times_ns``), so
    that streams with different stamps make one series; only steps with a selected row are kept.

    Args:
        model: observation model (``data``, ``sigma``, ``evidence.t_ns``, ``step_times_ns``).
        before, after: channel -> prediction (a channel missing from ``after`` is unchanged).
        channels: channels summed.
        rows: channel -> bool rows to use (None: all).

    Returns:
        ``(a, b, c, n)``, each ``(T',)`` (noise units^2; n a count), in time order.
    """
    steps = np.asarray(model.step_times_ns)
    out = np.zeros((4, steps.shape[0]))
    used = np.zeros(steps.shape[0], dtype=bool)
    for ch in channels:
        if ch not in before:
            continue
        r0 = residual(model, ch, before[ch])
        d = whiten(model, ch, after.get(ch, before[ch]) - before[ch])
        T = r0.shape[0]
        per = np.stack([np.sum((r0 * d).reshape(T, -1), axis=1), np.sum((d * d).reshape(T, -1), axis=1),
                        np.sum((r0 * r0).reshape(T, -1), axis=1), np.full(T, float(r0[0].size))])
        idx = np.clip(np.searchsorted(steps, np.asarray(model.evidence.t_ns[ch]), side="left"), 0, steps.shape[0] - 1)
        sel = np.ones(T, dtype=bool) if rows is None else np.asarray(rows[ch], dtype=bool)
        for k in range(4):
            np.add.at(out[k], idx[sel], per[k][sel])
        used[idx[sel]] = True
    return out[0][used], out[1][used], out[2][used], out[3][used]


def mismatch_declared(any_accepted: bool, loud: Sequence[str], heldout_rms_before: float | None,
                      min_excess: float) -> bool:
    """Whether a recording is reported as mismatched (a named effect or "unexplained").

    A named (accepted) effect always is. Otherwise a significant test must sit on a channel whose
    in-sample whitened excess ``mean(r^2) - 1`` exceeds ``min_excess`` (``loud``), *and* the
    held-out part of the recording must carry that excess too: ``heldout_rms_before^2 - 1 >
    min_excess`` (whitened RMS of the baseline on the held-out blocks or recordings, over the
    mismatch channels). The held-out check is the out-of-sample confirmation of the effect size, as
    for the candidates: on the benchmark a nominal recording whose score tests fired with 0.1 of
    in-sample excess had a held-out RMS of 0.995 and was reported "unexplained".

    Args:
        any_accepted: some candidate was accepted.
        loud: mismatch channels with in-sample excess above ``min_excess``.
        heldout_rms_before: held-out whitened RMS of the baseline (noise units; None or NaN when
            unknown, which skips the held-out check).
        min_excess: the effect-size floor in excess mean square (noise units squared).
    """
    if any_accepted:
        return True
    if not loud:
        return False
    if heldout_rms_before is None or not math.isfinite(heldout_rms_before):
        return True
    return heldout_rms_before ** 2 - 1.0 > min_excess
