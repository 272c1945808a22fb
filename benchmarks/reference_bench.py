"""``python -m benchmarks.diagnose_bench --labelled DIR`` on a reference set: recordings made by another
engine, labelled in a ``labels.yaml`` (``../shared/data/reference_bags``), diagnosed with the
signature stage of ``thinshell diagnose``'s pipeline both alone and against a baseline null, leave one out.
Each recording's premise (:func:`sysid.diagnose.pipeline.premise`) is reported beside it: a recording for which
the pipeline would take the score stage (its pose is its command) is logged and marked ``stage: score`` in
the reports, as its figures here are not the pipeline's.

Alone, each recording is diagnosed with the default thresholds (nothing from the other recordings
enters its decision). With baselines, each recording's null is calibrated on the set's nominal
recordings other than itself (leave one out): what a lab would get by declaring its other normal
recordings with ``thinshell diagnose BAG --baseline ...``. Each recording is read, calibrated and
replayed once; the two decisions reuse it.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable

import yaml

from sysid.diagnose.pipeline import premise
from sysid.diagnose.signature_engine import Prepared, SignatureSettings, diagnose_one, prepare
from benchmarks.diagnose_scoring import Recording, format_score, score

VARIANT_EFFECT = {"nominal": "none", "plastic": "bending_plasticity", "latency": "latency", "damped": "damping",
                  "stiction": "stiction", "lens": "lens_distortion", "force_bias": "force_bias",
                  "gel_creep": "gel_viscoelasticity", "adhesion": "adhesion", "anisotropic": "anisotropic_bending"}
"""Variant names of a reference set's labels -> effect vocabulary (SYSID.md)."""


def is_reference_set(directory: str | Path) -> bool:
    """Whether ``directory`` holds a reference set's ``labels.yaml``."""
    return (Path(directory) / "labels.yaml").is_file()


def load_reference_set(directory: str | Path) -> list[Recording]:
    """The labelled recordings of a reference set.

    Raises:
        FileNotFoundError: no ``labels.yaml`` or a listed recording missing (names the path).
        ValueError: a variant with no effect name (names the recording).
    """
    directory = Path(directory)
    index = directory / "labels.yaml"
    if not index.is_file():
        raise FileNotFoundError(f"{index}: no labels.yaml")
    labels = yaml.safe_load(index.read_text()) or {}
    recs = []
    for name, item in labels.items():
        path = directory / str(item.get("bag", name))
        if not path.exists():
            raise FileNotFoundError(f"{index}: recording {name!r} not found at {path}")
        variant = str(item.get("variant"))
        if variant not in VARIANT_EFFECT:
            raise ValueError(f"{index}: {name}: variant {variant!r} has no effect name ({', '.join(VARIANT_EFFECT)})")
        mag = item.get("magnitude") or {}
        magnitude = float(next(iter(mag.values()))) if isinstance(mag, dict) and mag else 0.0
        recs.append(Recording(name, VARIANT_EFFECT[variant], True, 1.0, magnitude, magnitude, [], path=path))
    return recs


def bench_reference(directory: str | Path, settings: SignatureSettings | None = None,
                    log: Callable[[str], None] = lambda s: None) -> dict[str, Any]:
    """Diagnose every recording of a reference set alone and with a leave-one-out baseline null.

    Returns:
        ``{"alone": score, "baseline_loo": score, "reports": {...}, "wall_s": ...}`` where each score
        is :func:`benchmarks.diagnose_bench.score`'s (confusion matrix, top-1 accuracy, false alarms).
    """
    settings = settings or SignatureSettings()
    recs = load_reference_set(directory)
    t0 = time.perf_counter()
    prepared: dict[str, Prepared] = {}
    stages = {r.name: premise(r.path, settings).stage for r in recs}
    for r in recs:
        if stages[r.name] != "signatures":
            log(f"{r.name}: thinshell diagnose would take the {stages[r.name]} stage (its pose is its command); "
                "its signature-stage figures here are not the pipeline's")
        log(f"calibrating and replaying {r.name} ...")
        prepared[r.name] = prepare(r.path, settings)
    alone, loo = [], []
    for r in recs:
        doc, _ = diagnose_one(r.path, settings=settings, prepared=prepared[r.name])
        alone.append(doc)
        base = [prepared[o.name] for o in recs if o.label == "none" and o.name != r.name]
        doc_b, _ = diagnose_one(r.path, settings=settings, prepared=prepared[r.name], baseline_prepared=base)
        loo.append(doc_b)
        log(f"{r.name} ({r.label}): alone {doc['explained_by']}, with baselines {doc_b['explained_by']}")
    return {"alone": score(recs, alone), "baseline_loo": score(recs, loo),
            "reports": {r.name: {"alone": a["explained_by"], "baseline_loo": b["explained_by"], "stage": stages[r.name],
                                 "calibrated_rms": a["baseline"]["whitened_rms_after"],
                                 "scene_rms": a["baseline"]["whitened_rms_before"],
                                 "heldout_rms_before": a["refit"]["heldout_rms_before"],
                                 "heldout_rms_after": a["refit"]["heldout_rms_after"],
                                 "replay": a["baseline"]["calibration"].get("replay"),
                                 "wall_s": a["extra"]["wall_time_s"]}
                        for r, a, b in zip(recs, alone, loo)},
            "wall_s": time.perf_counter() - t0}


def format_reference(result: dict[str, Any]) -> str:
    """Both confusion matrices and the per-recording answers as text."""
    lines = ["== alone (default thresholds) =="]
    lines.append(format_score(result["alone"]))
    lines.append("== with the other nominal recordings as --baseline (leave one out) ==")
    lines.append(format_score(result["baseline_loo"]))
    lines.append("== per recording ==")
    for name, rep in result["reports"].items():
        rms = ", ".join(f"{ch} {rep['scene_rms'].get(ch, float('nan')):.2f} -> {v:.2f}"
                        for ch, v in rep["calibrated_rms"].items())
        ho = ("n/a" if rep["heldout_rms_before"] is None else f"{rep['heldout_rms_before']:.3g}") + " -> " + \
            ("n/a" if rep["heldout_rms_after"] is None else f"{rep['heldout_rms_after']:.3g}")
        replay = (rep.get("replay") or {}).get("scene_values") or {}
        lines.append(f"{name}: alone {rep['alone']}, baselines {rep['baseline_loo']}; held-out RMS {ho}; "
                     f"calibration (whitened RMS) {rms}; replay at the scene values: {replay.get('steps')} steps, "
                     f"{replay.get('retries')} substep retries, {replay.get('relaxed_steps')} relaxed; {rep['wall_s']:.0f} s")
    lines.append(f"wall time {result['wall_s']:.0f} s")
    return "\n".join(lines)
