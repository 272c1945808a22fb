"""Scoring of diagnoses against labelled recordings: confusion matrix, top-1 accuracy per strength,
false alarms, located-window IoU and held-out RMS reduction (SYSID.md "Benchmark protocol").

Shared by the own-simulator benchmark (:mod:`benchmarks.diagnose_bench`) and the reference sets of
another engine (:mod:`benchmarks.reference_bench`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np


@dataclass
class Recording:
    """One labelled recording of the set."""

    name: str
    label: str
    in_library: bool
    target_strength: float
    strength: float
    magnitude: float
    windows_s: list[tuple[float, float]]
    path: Path | None = None
    streams: dict = field(default_factory=dict, repr=False)
    heldout: list[Path] = field(default_factory=list)
    """Companion recordings (same effect, same magnitude, independent noise) used as the held-out data."""



# ============================================================================ scoring
def top1(report: Mapping[str, Any]) -> str:
    """The first name of ``explained_by`` (``none`` when empty)."""
    names = report.get("explained_by") or []
    return str(names[0]) if names else "none"


def interval_iou(a: Sequence[Sequence[float]], b: Sequence[Sequence[float]]) -> float:
    """IoU of two unions of closed intervals (s); 0 when either is empty."""
    def norm(ws):
        out: list[list[float]] = []
        for lo, hi in sorted((float(x), float(y)) for x, y in ws if float(y) >= float(x)):
            if out and lo <= out[-1][1]:
                out[-1][1] = max(out[-1][1], hi)
            else:
                out.append([lo, hi])
        return out

    A, B = norm(a), norm(b)
    if not A or not B:
        return 0.0
    inter = sum(max(0.0, min(x1, y1) - max(x0, y0)) for x0, x1 in A for y0, y1 in B)
    union = sum(x1 - x0 for x0, x1 in A) + sum(y1 - y0 for y0, y1 in B) - inter
    return inter / union if union > 0 else 0.0


def heldout_excess_reduction(before: float, after: float) -> float:
    """``1 - e_after / e_before`` of the held-out *excess* RMS ``e = sqrt(max(rms^2 - 1, 0))`` (whitened,
    the part above the noise; the noise floor 1 cannot be removed by any model). ``e_before`` is floored
    at ``sqrt(0.05) rms_before`` (as :func:`sysid.diagnose.residuals.explained_fraction`)."""
    e0 = math.sqrt(max(before ** 2 - 1.0, 0.05 * before ** 2))
    return 1.0 - math.sqrt(max(after ** 2 - 1.0, 0.0)) / e0


def score(recordings: Sequence[Recording], reports: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Confusion matrix, top-1 accuracy per strength, false alarms, window IoU, held-out RMS reduction."""
    truth = [r.label if r.in_library or r.label == "none" else "unexplained" for r in recordings]
    pred = [top1(rep) for rep in reports]
    labels = sorted(set(truth) | set(pred))
    confusion = {t: {p: 0 for p in labels} for t in labels}
    for t, p in zip(truth, pred):
        confusion[t][p] += 1
    per_strength: dict[str, dict[str, float]] = {}
    for k in sorted({r.target_strength for r in recordings if r.label != "none"}):
        idx = [i for i, r in enumerate(recordings) if r.label != "none" and r.target_strength == k]
        hits = sum(pred[i] == truth[i] for i in idx)
        per_strength[f"{k:g}"] = {"accuracy": hits / len(idx), "count": len(idx),
                                  "mean_strength": float(np.mean([recordings[i].strength for i in idx]))}
    nominal = [i for i, r in enumerate(recordings) if r.label == "none"]
    alarms = [bool((reports[i].get("mismatch") or {}).get("detected")) or pred[i] != "none" for i in nominal]
    ious, reductions, excess_reductions = [], [], []
    for rec, rep in zip(recordings, reports):
        if rec.label == "none":
            continue
        ious.append(interval_iou((rep.get("mismatch") or {}).get("windows_s") or [], rec.windows_s))
        refit = rep.get("refit") or {}
        before, after = refit.get("heldout_rms_before"), refit.get("heldout_rms_after")
        if before is not None and after is not None and before > 0 and top1(rep) not in ("none", "unexplained"):
            reductions.append(1.0 - float(after) / float(before))
            excess_reductions.append(heldout_excess_reduction(float(before), float(after)))
    return {
        "recordings": len(recordings), "labels": labels, "confusion": confusion,
        "top1_accuracy": per_strength,
        "false_alarm_rate": float(np.mean(alarms)) if alarms else None,
        "window_iou_mean": float(np.mean(ious)) if ious else None,
        "heldout_rms_reduction_mean": float(np.mean(reductions)) if reductions else None,
        "heldout_excess_reduction_mean": float(np.mean(excess_reductions)) if excess_reductions else None,
        "per_recording": [{"name": r.name, "truth": t, "top1": p, "strength": round(r.strength, 3)}
                          for r, t, p in zip(recordings, truth, pred)],
    }


def format_score(result: Mapping[str, Any]) -> str:
    """Human-readable tables of :func:`score`."""
    labels = list(result["confusion"])
    w = max(len(s) for s in labels) + 2
    lines = ["confusion (rows: truth, columns: top-1)", " " * w + "".join(f"{s[:10]:>11}" for s in labels)]
    for t in labels:
        lines.append(f"{t:<{w}}" + "".join(f"{result['confusion'][t][p]:>11}" for p in labels))
    for k, v in result["top1_accuracy"].items():
        lines.append(f"top-1 at x{k}: {v['accuracy']:.2f} ({v['count']} recordings, mean strength {v['mean_strength']:.2f})")
    for key in ("false_alarm_rate", "window_iou_mean", "heldout_rms_reduction_mean", "heldout_excess_reduction_mean"):
        v = result[key]
        lines.append(f"{key}: {'n/a' if v is None else f'{v:.3f}'}")
    return "\n".join(lines)
