"""Write ``benchmarks/device_cpu.sh`` job lines that generate one recording of a plan and diagnose it at once.

    python benchmarks/mujoco_world/plan_jobs.py PLAN [SETS] [--diag-args "..."] > DIR/jobs.txt

Unlike ``device_set.sh`` (all recordings first, then all diagnoses) each line makes one recording and runs
``thinshell diagnose`` (defaults, plus ``--diag-args``) on it, so a machine of N cores keeps N such pipelines
busy, and each line copies its report to ``$OUT/reports/NAME.json`` as soon as it is written (what a call cut
at its time limit has finished still comes back). A job prints the one summary line of
``benchmarks/diagnose_summary.py``. On the device, from the checkout's root, with DIR carried (its wheels:
``device_cpu.sh prepare taichi-slim rosbags`` plus MuJoCo's, see ``device_set.sh prepare``; DIR/data/scene.yaml
the scene of ``../shared/data/reference_bags/nominal_s101``)::

    bash DIR/src/benchmarks/device_cpu.sh run DIR

Plan lines as ``plans/session37.txt``: ``set name variant magnitude ('-': none) motion seed [direction ('-':
drawn)] [short] [load]`` (``short``: ``generate --short``; ``load``: ``generate --stiction-switch=load``); SETS
is a regex over the first column (default: every set).
"""

from __future__ import annotations

import argparse
import re
import shlex
import sys
from pathlib import Path


def job_lines(plan: Path, sets: str = ".*", diag_args: str = "") -> list[str]:
    """One shell line per plan line whose set matches ``sets``.

    Raises:
        ValueError: a plan line with too few or unknown fields (names the file and line).
    """
    out = []
    for k, raw in enumerate(plan.read_text(encoding="utf-8").splitlines(), 1):
        f = raw.split()
        if not f or raw.lstrip().startswith("#"):
            continue
        if len(f) < 6 or not set(f[7:]) <= {"short", "load"}:
            raise ValueError(f"{plan}:{k}: expected 'set name variant magnitude motion seed [direction] [short] "
                             f"[load]', got {raw!r}")
        if not re.fullmatch(sets, f[0]):
            continue
        name, variant, mag, motion, seed = f[1:6]
        gen = ["python", "-m", "benchmarks.mujoco_world.generate", f"/tmp/gen/{name}", "--scene", "$DATA/scene.yaml",
               "--variant", variant, "--motion", motion, "--seed", seed]
        if mag != "-":
            gen += ["--magnitude", mag]
        if len(f) >= 7 and f[6] != "-":
            gen.append(f"--direction={f[6]}")
        if "short" in f[7:]:
            gen.append("--short")
        if "load" in f[7:]:
            gen.append("--stiction-switch=load")
        g = " ".join(a if a.startswith("$") else shlex.quote(a) for a in gen)
        rep = f"/tmp/rep/{name}.json"
        out.append(f"mkdir -p /tmp/gen /tmp/rep $OUT/reports && MUJOCO_GL=disable {g} > /tmp/gen/{name}.log 2>&1 && "
                   f"python -m thinshell_ros.cli diagnose /tmp/gen/{name} {diag_args} --json {rep} --force; "
                   f"cp {rep} $OUT/reports/ 2>/dev/null; "
                   f"cp /tmp/gen/{name}/label.yaml $OUT/reports/{name}.label.yaml; "
                   f"python benchmarks/diagnose_summary.py {name} alone {rep}")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("plan", type=Path)
    ap.add_argument("sets", nargs="?", default=".*", help="regex over the plan's first column")
    ap.add_argument("--diag-args", default="", help="more `thinshell diagnose` arguments")
    a = ap.parse_args(argv)
    print("\n".join(job_lines(a.plan, a.sets, a.diag_args)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
