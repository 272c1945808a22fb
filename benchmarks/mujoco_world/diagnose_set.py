"""Run ``thinshell diagnose`` (defaults) on every recording of a generated set and print the table.

``ok``: the first named effect (``none`` when nothing is named) is the label's effect
(``EXPECTED``, the vocabulary of ``benchmarks.reference_bench.VARIANT_EFFECT``); on a lift-fold
an ``adhesion`` beside it is not counted (issue 23: adhesion may be named beside the effect on a lift).

    python benchmarks/mujoco_world/diagnose_set.py SET_DIR RUNS_DIR [--python PY] [--wait N] [--jobs N]

Runs the project's CLI in a subprocess (``PY -m thinshell_ros.cli diagnose BAG --json RUNS/NAME.json
--force``) for each ``SET_DIR/*/label.yaml`` without a JSON yet (``--wait N``: poll up to N s for
recordings still being generated), and prints truth / named / wall / load (1-min load average at the
start and end of the run) as a Markdown table. ``--jobs N`` runs up to N diagnoses at a time (each in
its own process). Imports nothing of the project (stdlib + pyyaml).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import yaml

EXPECTED = {"nominal": "none", "stiction": "stiction", "damped": "damping", "plastic": "bending_plasticity",
            "latency": "latency", "lens": "lens_distortion", "force_bias": "force_bias",
            "gel_creep": "gel_viscoelasticity"}
"""Variant -> the effect name the diagnosis should give (``none``: nothing named)."""


def _load() -> float:
    return os.getloadavg()[0]


def run_one(bag: Path, runs: Path, python: str) -> dict:
    out = runs / f"{bag.name}.json"
    load0, t0 = _load(), time.perf_counter()
    proc = subprocess.run([python, "-m", "thinshell_ros.cli", "diagnose", str(bag), "--json", str(out), "--force"],
                          capture_output=True, text=True)
    wall = time.perf_counter() - t0
    (runs / f"{bag.name}.log").write_text(proc.stdout + proc.stderr, encoding="utf-8")
    rec = {"bag": bag.name, "rc": proc.returncode, "wall_s": round(wall, 1), "load": [round(load0, 1), round(_load(), 1)]}
    if out.exists():
        rec["explained_by"] = json.loads(out.read_text(encoding="utf-8")).get("explained_by")
    (runs / f"{bag.name}.run.json").write_text(json.dumps(rec), encoding="utf-8")
    return rec


def table(set_dir: Path, runs: Path) -> str:
    rows = ["| recording | motion | truth | magnitude | expected | named | ok | wall | load |", "|---|---|---|---|---|---|---|---|---|"]
    for lab_path in sorted(set_dir.glob("*/label.yaml")):
        name, lab = next(iter(yaml.safe_load(lab_path.read_text(encoding="utf-8")).items()))
        run_path = runs / f"{name}.run.json"
        if not run_path.exists():
            continue
        r = json.loads(run_path.read_text(encoding="utf-8"))
        named = r.get("explained_by")
        exp = EXPECTED[lab["variant"]]
        # adhesion may be named beside the effect on a lift (issue 23): not counted there
        kept = [e for e in (named or []) if not (lab["motion"]["kind"] == "lift_fold" and e == "adhesion")]
        top = kept[0] if kept else "none"
        ok = "rc!=0" if r["rc"] else ("yes" if top == exp else "no")
        mag = "-" if lab["magnitude"] is None else ", ".join(f"{k} {v:.4g}" for k, v in lab["magnitude"].items())
        rows.append(f"| {name} | {lab['motion']['kind']} | {lab['variant']} | {mag} | {exp} | {named} | {ok} | "
                    f"{r['wall_s']:.0f} s | {r['load'][0]}-{r['load'][1]} |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("set_dir", type=Path)
    ap.add_argument("runs_dir", type=Path)
    ap.add_argument("--python", default=sys.executable)
    ap.add_argument("--wait", type=float, default=0.0, help="poll this long (s) for recordings still being generated")
    ap.add_argument("--expect", type=int, default=0, help="number of recordings to wait for")
    ap.add_argument("--jobs", type=int, default=1, help="diagnoses run at a time")
    a = ap.parse_args(argv)
    a.runs_dir.mkdir(parents=True, exist_ok=True)
    deadline = time.time() + a.wait
    started: set[str] = set()
    with ThreadPoolExecutor(max_workers=max(1, a.jobs)) as pool:
        pending = []
        while True:
            todo = [p.parent for p in sorted(a.set_dir.glob("*/label.yaml"))
                    if p.parent.name not in started and not (a.runs_dir / f"{p.parent.name}.run.json").exists()]
            for bag in todo:
                started.add(bag.name)
                pending.append(pool.submit(run_one, bag, a.runs_dir, a.python))
            for fut in [f for f in pending if f.done()]:
                pending.remove(fut)
                print(json.dumps(fut.result()), flush=True)
            n = len(list(a.runs_dir.glob("*.run.json")))
            if (n >= a.expect or time.time() > deadline) and not pending:
                break
            time.sleep(5 if pending else 20)
    print(table(a.set_dir, a.runs_dir))
    return 0


if __name__ == "__main__":
    sys.exit(main())
