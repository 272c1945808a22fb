"""The kernel preparation of a process (benchmarks/time_kernel_prep.py), counted, not timed: a Folding-U population
on CUDA's paths with the envelope device solver (the GPU's kernel set, emulated on the CPU arch) prepares each
compiled kernel once (no template instance of a kernel whose compiled code another instance already has: each such
instance costs the frontend again), and a second population built in the same process prepares none."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

PART = re.compile(r"^--- (?P<title>[^:]+):[^;\n]*; (?P<instances>\d+) kernel instances of (?P<kernels>\d+) kernels, "
                  r"(?P<compiled>\d+) new compiled kernels", re.M)


def test_a_population_prepares_each_compiled_kernel_once_and_the_next_none():
    env = dict(os.environ, PYTHONPATH=os.pathsep.join((str(REPO), str(REPO / "benchmarks"))))
    run = subprocess.run([sys.executable, "benchmarks/time_kernel_prep.py", "--task", "folding_u", "--B", "2",
                          "--steps", "1", "--emulate-cuda", "--linear-solver", "envelope", "--populations", "2"], cwd=REPO, env=env, capture_output=True, text=True, timeout=900, check=False)
    assert run.returncode == 0, run.stderr[-3000:]
    parts = {m["title"]: {k: int(m[k]) for k in ("instances", "kernels", "compiled")} for m in PART.finditer(run.stdout)}
    first, second = parts["population 1"], parts["population 2"]
    # the lockstep batch's kernels on CUDA's paths: fused elastic, contact, friction rows, envelope solver, iterates
    assert first["compiled"] >= 30, run.stdout
    assert first["instances"] == first["compiled"], run.stdout  # no kernel's frontend run twice for one compiled code
    assert second == {"instances": 0, "kernels": 0, "compiled": 0}, run.stdout
