"""Held-out evaluation of refits: one code path for held-out time blocks and held-out recordings.

SYSID.md recipe step 6: a refit is accepted only when the held-out data improve. The held-out data
are either the odd time blocks of the recording itself (:func:`block_fold`) or other recordings
(:func:`bag_folds`, ``thinshell diagnose BAG --heldout BAG2 ...``: each is replayed once at the
nominal parameters and once per physics refit). Either way a :class:`HeldoutFold` holds the nominal
prediction of the held-out data and each refit's prediction *change* on it, so that a combination of
refits at any scales is evaluated to first order (``before + sum_e scale_e change_e``), the same
combination the report's in-sample augmented model uses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from sysid.diagnose.residuals import explained_fraction, heldout_products, sse

Products = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


@dataclass
class HeldoutFold:
    """One held-out data set and the refits' prediction changes on it.

    Attributes:
        model: observation model of the data (``data``, ``sigma``, stamps).
        before: channel -> prediction at the nominal parameters, shape of the channel's data.
        rows: channel -> bool rows that are held out, ``(T_ch,)``; None: all rows.
        changes: effect -> channel -> prediction change of its refit (same shapes as ``before``).
    """

    model: Any
    before: dict[str, np.ndarray]
    rows: dict[str, np.ndarray] | None
    changes: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)

    def predict(self, scales: Mapping[str, float], channels: Sequence[str]) -> dict[str, np.ndarray]:
        """``before + sum_e scales[e] changes[e]`` on the fold's ``channels``."""
        out = {ch: np.array(self.before[ch], dtype=float, copy=True) for ch in channels if ch in self.before}
        for e, s in scales.items():
            for ch, d in self.changes.get(e, {}).items():
                if ch in out and s:
                    out[ch] = out[ch] + s * d
        return out


def block_fold(model: Any, prediction: Mapping[str, np.ndarray], train: Mapping[str, np.ndarray],
               refits: Mapping[str, Any]) -> HeldoutFold:
    """The held-out time blocks of the recording itself (rows where ``train`` is False).

    Args:
        model: the recording's observation model.
        prediction: channel -> nominal prediction.
        train: channel -> bool training rows.
        refits: effect -> refit (``prediction``: channel -> refitted prediction).
    """
    changes = {e: {ch: np.asarray(p) - prediction[ch] for ch, p in rf.prediction.items() if ch in prediction}
               for e, rf in refits.items()}
    return HeldoutFold(model, {ch: np.asarray(p) for ch, p in prediction.items()},
                       {ch: ~np.asarray(v, dtype=bool) for ch, v in train.items()}, changes)


def bag_folds(models: Sequence[Any], theta: Mapping[str, float], refits: Mapping[str, Any], tested: Sequence[str],
              sigma: Mapping[str, np.ndarray], replay: Callable[[Any, list], list],
              context: Callable[..., Any], apply_observation: Callable[[Any, Any, dict], None],
              notes: list[str] | None = None) -> list[HeldoutFold]:
    """Held-out recordings, each replayed at ``theta`` and at every physics refit's parameters.

    Args:
        models: observation models of the held-out recordings.
        theta: nominal (fitted) simulator parameters.
        refits: effect -> refit (``sim_params``, ``prediction`` channels, observation params).
        tested: channels the diagnosis tests.
        sigma: channel -> noise level of the primary recording (the held-out recordings are
            whitened with it: same sensors).
        replay: ``replay(model, parameter_sets) -> [(trace, prediction) | None]``.
        context: ``context(model, theta, trace, prediction, channels)`` -> diagnosis context (for
            observation-level refits: latency, lens, bias).
        apply_observation: applies an observation-level refit to a prediction in place (no-op for
            physics refits).
        notes: receives a line for a recording or refit that cannot be replayed.

    Returns:
        One :class:`HeldoutFold` per recording whose nominal replay finished (rows None: all held out).
        A refit whose replay diverges on a recording contributes no change there (noted).
    """
    out = []
    names = list(refits)
    for m in models:
        m.sigma.update({ch: v for ch, v in sigma.items() if ch in m.sigma})
        sets = [dict(theta)] + [{**theta, **(refits[e].sim_params or {})} for e in names]
        physics = [i for i, s in enumerate(sets[1:]) if s != sets[0]]
        reps = replay(m, [sets[0]] + [sets[1 + i] for i in physics])
        if reps[0] is None:
            if notes is not None:
                notes.append("a held-out recording's nominal replay diverged; left out of the held-out data")
            continue
        trace, p0 = reps[0]
        chans = tuple(c for c in tested if c in m.evidence.channels_present)
        by_refit = dict(zip(physics, reps[1:]))
        hctx = context(m, dict(theta), trace, p0, chans)
        fold = HeldoutFold(m, {ch: np.asarray(p0[ch]) for ch in chans}, None)
        for i, e in enumerate(names):
            rep = by_refit.get(i, reps[0])
            if rep is None:
                if notes is not None:
                    notes.append(f"{e}: refit replay diverged on a held-out recording; no change counted there")
                rep = reps[0]
            p1 = dict(rep[1])
            apply_observation(hctx, refits[e], p1)
            fold.changes[e] = {ch: np.asarray(p1[ch]) - fold.before[ch] for ch in refits[e].prediction if ch in chans}
        out.append(fold)
    return out


def evaluate(folds: Sequence[HeldoutFold], base: Mapping[str, float], scales: Mapping[str, float],
             channels: Sequence[str]) -> tuple[float, float, Products, dict[str, Products]]:
    """Held-out whitened RMS of the ``base`` and ``scales`` combinations and the products of their difference.

    Args:
        folds: held-out data.
        base, scales: effect -> scale of the combinations compared (``{}``: nominal).
        channels: channels evaluated (each fold uses those it has).

    Returns:
        ``(rms_before, rms_after, (a, b, c, n), per_channel)``: RMS in noise units over all folds'
        held-out values; the per-time products of :func:`residuals.heldout_products` (``before`` =
        ``base``, ``after`` = ``scales``) concatenated over folds, over all channels and per channel.
    """
    s0 = s1 = 0.0
    n = 0
    both: list[Products] = []
    per: dict[str, list[Products]] = {}
    for f in folds:
        chans = [ch for ch in channels if ch in f.before]
        p0, p1 = f.predict(base, chans), f.predict(scales, chans)
        a0, n0, _ = sse(f.model, p0, chans, f.rows)
        a1, _, _ = sse(f.model, p1, chans, f.rows)
        s0, s1, n = s0 + a0, s1 + a1, n + n0
        both.append(heldout_products(f.model, p0, p1, chans, f.rows))
        for ch in chans:
            per.setdefault(ch, []).append(heldout_products(f.model, p0, p1, [ch], f.rows))

    def cat(parts: list[Products]) -> Products:
        return tuple(np.concatenate([p[i] for p in parts]) if parts else np.zeros(0) for i in range(4))

    return (float(math.sqrt(s0 / max(n, 1))), float(math.sqrt(s1 / max(n, 1))), cat(both),
            {ch: cat(v) for ch, v in per.items()})


@dataclass(frozen=True)
class ChannelEffect:
    """A refit's held-out effect size on the channels whose held-out data support its change.

    Attributes:
        channels: the supporting channels (those ``supports`` accepts), in the order given.
        rms_before, rms_after: root of the mean over those channels of each channel's held-out mean
            square (whitened SSE over its value count), before and after (noise units; nan without channels).
        gain: sum over those channels of the mean square removed (noise variance units; 0 without channels).
    """

    channels: tuple[str, ...]
    rms_before: float
    rms_after: float
    gain: float

    def figures(self) -> dict[str, Any]:
        """The engine's decision entries: ``explained_fraction`` of the supporting channels' excess
        (:func:`sysid.diagnose.residuals.explained_fraction`), ``supported_ms_removed`` (their mean
        square removed), ``supported_on``, ``supported_rms`` (before, after) and ``effect_gain``; without
        a supporting channel the fraction and the mean square removed are 0 and ``supported_rms`` is empty."""
        if not self.channels:
            return {"explained_fraction": 0.0, "supported_ms_removed": 0.0, "supported_on": [], "supported_rms": [],
                    "effect_gain": 0.0}
        return {"explained_fraction": explained_fraction(self.rms_before, self.rms_after),
                "supported_ms_removed": self.rms_before ** 2 - self.rms_after ** 2, "supported_on": list(self.channels),
                "supported_rms": [self.rms_before, self.rms_after], "effect_gain": self.gain}


def supported_effect(per_channel: Mapping[str, Products], supports: Callable[[Products], bool]) -> ChannelEffect:
    """Held-out effect size of a refit with every supporting channel weighted equally.

    Pooled over values, a channel of many values (the sheet's points: 69 x 3 per sample in the own-simulator
    benchmark, two thirds of the held-out values) outweighs one of few (the wrench's 6) that carries the
    same evidence in noise units; weighted equally, a channel whose held-out data do not support the
    refit's change at all (the main job's wrench, supported scale 0.11 with a whitened mean square of 21:
    a channel the calibrated model does not follow) cancels the others' evidence. Here each channel's
    held-out mean square counts once, on the channels whose held-out data support the change
    (``supports``: the one-sided held-out test of :func:`sysid.diagnose.stats.heldout_test` rejecting a
    zero scale); a channel the change makes significantly worse is refuted separately (the engine's
    channel consistency test).

    Args:
        per_channel: channel -> per-time products ``(a, b, c, n)`` of :func:`evaluate` (before: ``c``,
            after: ``c - 2 a + b``).
        supports: products -> whether that channel's held-out data support the change.

    Returns:
        :class:`ChannelEffect` (no channel: rms nan, gain 0).
    """
    chans, before, after = [], [], []
    for ch, (a, b, c, n) in per_channel.items():
        if not (np.any(b) and supports((a, b, c, n))):
            continue
        values = max(float(np.sum(n)), 1.0)
        chans.append(ch)
        before.append(float(np.sum(c)) / values)
        after.append(float(np.sum(c) - 2.0 * np.sum(a) + np.sum(b)) / values)
    if not chans:
        return ChannelEffect((), math.nan, math.nan, 0.0)
    return ChannelEffect(tuple(chans), math.sqrt(max(float(np.mean(before)), 0.0)),
                         math.sqrt(max(float(np.mean(after)), 0.0)), float(np.sum(before) - np.sum(after)))


def leave_one_event_out(t: np.ndarray, y: np.ndarray, yp: np.ndarray, sigma: float, windows: Sequence[Sequence[float]],
                        grid: Sequence[tuple[float, ...]], transformed) -> dict[str, Any]:
    """A timing model fitted on all contact events but one and evaluated on that one, for every event.

    In each event's window the recorded signal is regressed on the model's prediction with a gain and
    an offset per window, fitted before and after alike (the amplitude gap between the calibrated replay
    and the recording is not the timing effect).

    Args:
        t: sample times, s, ``(n,)``.
        y, yp: recorded and replayed signal ``(n,)`` (normal force N or mean marker depth m).
        sigma: its noise, same unit.
        windows: the events' windows ``[t0, t1]`` s.
        grid: the model's parameter values searched.
        transformed: parameter value -> the model's prediction ``(n,)``.

    Returns:
        ``theta`` (best on all events), ``per_event`` (best on the others, per held-out event), ``rms``
        (whitened, at ``theta`` on all events), ``heldout_rms_before`` (the replay ``yp`` itself) and
        ``heldout_rms_after``.
    """
    masks = [(t >= a) & (t <= b) for a, b in windows]
    preds: dict[tuple[float, ...], np.ndarray] = {}

    def sse(theta, rows, pred=None) -> float:
        if pred is None:
            pred = preds.setdefault(theta, np.asarray(transformed(theta), dtype=float))
        total = 0.0
        for m in masks:
            mm = m & rows
            if mm.sum() < 3:
                continue
            X = np.stack([pred[mm], np.ones(int(mm.sum()))], axis=1)
            c, *_ = np.linalg.lstsq(X, y[mm], rcond=None)
            total += float(np.sum(((y[mm] - X @ c) / sigma) ** 2))
        return total

    before, after, thetas = [], [], []
    for i, m in enumerate(masks):
        train = np.zeros(len(t), bool)
        for j, mj in enumerate(masks):
            if j != i:
                train |= mj
        if not train.any():
            train = m
        best = min(grid, key=lambda th: sse(th, train))
        thetas.append(best)
        before.append(sse(None, m, pred=yp))
        after.append(sse(best, m))
    n_held = sum(int(m.sum()) for m in masks)
    all_rows = np.any(masks, axis=0) if masks else np.ones(len(t), bool)
    best_all = min(grid, key=lambda th: sse(th, all_rows))
    return {"theta": best_all, "per_event": [list(th) for th in thetas],
            "rms": math.sqrt(sse(best_all, all_rows) / max(int(all_rows.sum()), 1)),
            "heldout_rms_before": math.sqrt(sum(before) / max(n_held, 1)),
            "heldout_rms_after": math.sqrt(sum(after) / max(n_held, 1))}
