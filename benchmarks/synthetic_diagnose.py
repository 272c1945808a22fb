"""Run ``thinshell diagnose`` (signature engine, the command's defaults, alone) on every recording of
a labelled set (``labels.yaml`` in the reference set's format, e.g. one written by
``python -m benchmarks.synthetic_effects``), one at a time, and print the confusion table.

    python benchmarks/synthetic_diagnose.py SET_DIR OUT_DIR [--only NAME ...]
    python benchmarks/synthetic_diagnose.py SET_DIR OUT_DIR --table
    python benchmarks/synthetic_diagnose.py SET_DIR OUT_DIR --redecide   # signature tests again on
        the saved calibrated replays, with the gain guard of ``guarded`` (after a change to the decision stage only)
    python benchmarks/synthetic_diagnose.py SET_DIR OUT_DIR --proxy SOURCE_RUNS   # the signature
        tests and the default decision on each recording's own tactile streams (and their noise
        levels) with the calibrated replay saved for its source recording (SOURCE_RUNS/SOURCE.pkl,
        a run of this script on the source set), then the held-out gain guard on the refits that
        read the recording alone (lens, force bias, timing, stiction; a sheet effect's refit
        replays the simulator and is kept): the decision of a full run whose calibration is the
        source's, for the recordings that were not run in full

Each recording goes through the same code as ``thinshell diagnose BAG --json OUT`` (its parser's
defaults, :func:`sysid.diagnose.signature_engine.prepare` then ``diagnose_one``); the report goes to
``OUT_DIR/NAME.json``, the recording view with its calibrated replay (what the signature tests read)
to ``OUT_DIR/NAME.pkl``, and a failure's traceback to ``OUT_DIR/NAME.error``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pickle
import sys
import time
import traceback
from pathlib import Path

import yaml

from sysid.diagnose.cli import build_parser, signature_settings
from sysid.diagnose.signatures.base import TACTILE_CHANNELS
from benchmarks.reference_bench import VARIANT_EFFECT
from sysid.diagnose.signature_engine import Prepared, SignatureSettings, diagnose_one, guard_names, prepare
from sysid.diagnose.signatures import run_signature_tests
from sysid.diagnose.signatures.null import decide, default_thresholds
from sysid.evidence import load_evidence


def run_one(bag: Path, out: Path) -> dict:
    settings = signature_settings(build_parser().parse_args([str(bag)]))
    t0 = time.monotonic()
    doc, p = diagnose_one(bag, settings=settings)
    doc["extra"]["wall_time_s"] = time.monotonic() - t0
    (out / f"{bag.name}.json").write_text(json.dumps(doc, indent=1))
    with open(out / f"{bag.name}.pkl", "wb") as f:
        pickle.dump({"recording": p.recording, "notes": p.notes}, f)
    return doc


def redecide(out: Path, name: str) -> list[str] | None:
    pkl = out / f"{name}.pkl"
    if not pkl.is_file():
        return None
    return guarded(pickle.loads(pkl.read_bytes())["recording"])


def proxy(set_dir: Path, source_runs: Path, name: str, source: str) -> list[str] | None:
    """The default decision on recording ``name``'s tactile streams and noise levels with the
    calibrated replay saved for ``source`` (None when that run is missing).

    Raises:
        ValueError: the recording's streams and the source run's differ in shape (not the same stamps).
    """
    pkl = source_runs / f"{source}.pkl"
    if not pkl.is_file():
        return None
    rec = pickle.loads(pkl.read_bytes())["recording"]
    ev = load_evidence(set_dir / name, include_image=False)
    data, sigma = dict(rec.data), dict(rec.sigma)
    for ch in TACTILE_CHANNELS:
        if ch not in data:
            continue
        v = ev.values(ch)
        if v.shape != data[ch].shape:
            raise ValueError(f"{name}: {ch} {v.shape} against {source}'s {data[ch].shape}")
        data[ch], sigma[ch] = v, ev.noise[ch]
    rec = dataclasses.replace(rec, data=data, sigma=sigma, name=name)
    return guarded(rec)


DATA_REFITS = ("lens_distortion", "force_bias", "latency", "gel_viscoelasticity", "damping", "stiction")
"""Effects whose refit reads the recording and its saved replay alone (no simulator replay)."""


def guarded(rec) -> list[str]:
    """The default decision on a recording with its replay, then the held-out gain guard of
    ``thinshell diagnose`` on the refits of :data:`DATA_REFITS` (other named effects are kept)."""
    results = run_signature_tests(rec)
    named = decide(results, default_thresholds(rec)).explained_by
    p = Prepared(Path(rec.name), None, None, dict(rec.prediction or {}), rec, results)
    return guard_names(p, named, SignatureSettings(), DATA_REFITS)[0]


def table(set_dir: Path, out: Path, redo: bool, source_runs: Path | None = None) -> str:
    labels = yaml.safe_load((set_dir / "labels.yaml").read_text())
    rows = ["| recording | motion | truth | magnitude | visibility (xyz / uv / wrench) | named | wall |",
            "|---|---|---|---|---|---|---|"]
    right = total = alarms = nominals = 0
    for name, lab in labels.items():
        truth = VARIANT_EFFECT[lab["variant"]]
        vis = lab.get("visibility") or {}
        js = out / f"{name}.json"
        if source_runs is not None:
            named = proxy(set_dir, source_runs, name, lab["source"]) if lab.get("source") else redecide(source_runs, name)
            wall = "proxy"
        elif redo:
            named = redecide(out, name)
            wall = "-"
        elif js.is_file():
            doc = json.loads(js.read_text())
            named, wall = doc["explained_by"], f"{doc['extra']['wall_time_s']:.0f} s"
        else:
            named, wall = None, ("error" if (out / f"{name}.error").is_file() else "not run")
        if named is None:
            txt = wall
        else:
            txt = str(named)
            if truth == "none":
                nominals += 1
                alarms += bool(named)
            else:
                total += 1
                right += bool(named) and named[0] == truth
        mag = lab.get("magnitude") or {}
        rows.append(f"| {name} | {lab['motion']['kind']} | {truth} | {', '.join(f'{k} {v:g}' for k, v in mag.items()) or '-'} | "
                    f"{vis.get('markers_xyz', 0):.1f} / {vis.get('markers_uv', 0):.1f} / {vis.get('wrench', 0):.1f} | {txt} | {wall} |")
    rows.append(f"\ntop-1 {right}/{total} on effect recordings, false alarms {alarms}/{nominals} on nominal ones")
    return "\n".join(rows)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("set_dir", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--only", nargs="*")
    ap.add_argument("--table", action="store_true")
    ap.add_argument("--redecide", action="store_true")
    ap.add_argument("--proxy", type=Path, metavar="SOURCE_RUNS")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if args.table or args.redecide or args.proxy:
        print(table(args.set_dir, args.out, args.redecide, args.proxy))
        return 0
    labels = yaml.safe_load((args.set_dir / "labels.yaml").read_text())
    for name in labels:
        if args.only and name not in args.only:
            continue
        if (args.out / f"{name}.json").is_file():
            continue
        t0 = time.monotonic()
        try:
            doc = run_one(args.set_dir / name, args.out)
            print(f"{name}: {doc['explained_by']} ({time.monotonic() - t0:.0f} s)", flush=True)
        except Exception:  # noqa: BLE001 - a benchmark counts a crash and goes on
            (args.out / f"{name}.error").write_text(traceback.format_exc())
            print(f"{name}: ERROR ({time.monotonic() - t0:.0f} s)\n{traceback.format_exc()}", flush=True)
    print(table(args.set_dir, args.out, False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
