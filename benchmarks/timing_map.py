"""Map of the timing decisions (latency / gel viscoelasticity) over delays and creep time constants
applied in memory to saved calibrated replays.

``benchmarks/synthetic_diagnose.py SET OUT`` saves each recording's :class:`Recording` (the recorded
streams and their calibrated nominal replay) as ``OUT/NAME.pkl``. This script applies a tactile
latency or a first-order creep (the data-level effects of :mod:`benchmarks.synthetic_effects`, on the
markers and the wrench) to the recorded streams of each saved recording, keeps its replay (the
timing tests fit a gain and an offset per event window, so the sensor calibration a re-calibration
would refit does not enter them), runs the signature tests and reports the first timing effect
named. A recording that already carries an effect adds it to the applied one.

    python benchmarks/timing_map.py OUT/nominal_s101.pkl OUT/nominal_s109.pkl ...
"""

from __future__ import annotations

import argparse
import dataclasses
import pickle
import sys
from pathlib import Path

import numpy as np

from sysid.diagnose.signatures import run_signature_tests
from sysid.diagnose.signatures.null import decide, default_thresholds
from benchmarks.synthetic_effects import creep, delayed

LATENCIES_S = (0.01, 0.015, 0.02, 0.03, 0.04, 0.06, 0.08)
CREEP_TAUS_S = (0.03, 0.05, 0.065, 0.1, 0.13, 0.2, 0.26)
TIMING = {"latency": "L", "gel_viscoelasticity": "V"}


def with_effect(rec, kind: str, value: float):
    """``rec`` with a latency (s) or a full first-order creep (time constant, s) on its tactile streams."""
    data = dict(rec.data)
    for ch in ("wrench", "markers_xyz", "markers_uv"):
        t_ns = np.round(np.asarray(rec.t[ch]) * 1e9).astype(np.int64)
        data[ch] = delayed(t_ns, data[ch], value) if kind == "latency" else creep(t_ns, data[ch], value, 1.0)
    return dataclasses.replace(rec, data=data)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("pkl", nargs="+", type=Path)
    args = ap.parse_args()
    counts = {"right": 0, "wrong": 0, "none": 0}
    for path in args.pkl:
        base = pickle.loads(path.read_bytes())["recording"]
        cells = []
        for kind, values, truth in (("latency", LATENCIES_S, "latency"), ("creep", CREEP_TAUS_S, "gel_viscoelasticity")):
            for v in values:
                rec = with_effect(base, kind, v)
                results = run_signature_tests(rec)
                named = [e for e in decide(results, default_thresholds(rec)).explained_by if e in TIMING]
                first = named[0] if named else "none"
                counts["right" if first == truth else "none" if first == "none" else "wrong"] += 1
                z = results["latency"].detail.get("shape_z", 0.0)
                cells.append(f"{kind[0]}{1e3 * v:g}:{TIMING.get(first, '.')}({z:.1f})")
        print(f"{path.stem:24s} " + " ".join(cells), flush=True)
    total = sum(counts.values())
    print(f"first timing effect named: right {counts['right']}, wrong {counts['wrong']}, none {counts['none']} of {total}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
