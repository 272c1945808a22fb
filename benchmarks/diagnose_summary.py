"""Print one JSON line summarising a `thinshell diagnose` report (for device jobs' results.jsonl).

    python benchmarks/diagnose_summary.py NAME MODE REPORT.json

NAME and MODE (e.g. ``alone`` or ``loo``) label the line; the line holds the names, the wall time, the
calibrated whitened RMS per channel, each signature's [statistic, effect size, detected] and each refitted
effect's held-out RMS before and after.
"""

import json
import sys


def summary(name: str, mode: str, report: dict) -> dict:
    """The summary of one diagnosis report (the JSON of ``thinshell diagnose --json``)."""
    cal = report["baseline"].get("calibration", {})
    extra = report.get("extra", {})
    sig = extra.get("signatures", {})
    effects = report.get("refit", {}).get("effects") or {}
    return {"bag": name, "mode": mode, "explained_by": report["explained_by"], "wall_s": extra.get("wall_time_s"),
            "rms_after": {k: round(v, 2) for k, v in cal.get("whitened_rms_after", {}).items()},
            "sig": {k: [round(v.get("statistic", 0), 1), v.get("effect_size"), v.get("detected")] for k, v in sig.items()},
            "refit": {k: [v.get("heldout_rms_before"), v.get("heldout_rms_after")] for k, v in effects.items()}}


if __name__ == "__main__":
    name, mode, path = sys.argv[1:4]
    with open(path, encoding="utf-8") as fh:
        print(json.dumps(summary(name, mode, json.load(fh))))
