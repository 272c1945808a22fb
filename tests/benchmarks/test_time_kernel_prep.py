"""The kernel preparation of a process (benchmarks/time_kernel_prep.py), counted, not timed: a Folding-U population
on CUDA's paths with the envelope device solver (the GPU's kernel set, emulated on the CPU arch) prepares each
compiled kernel once (no template instance of a kernel whose compiled code another instance already has: each such
instance costs the frontend again), and a second population built in the same process prepares none; after
``thinshell compile --task``'s warm-up (``sim_core.kernel_compile.compile_task``) the optimiser's batched evaluator
prepares no compiled kernel the warm-up did not (which Taichi's offline cache then holds for the next process)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

AFTER_COMPILE_TASK = """
import numpy as np
from sim_core.ti_backend import init_backend
init_backend("cpu")
from benchmarks.time_kernel_prep import _instrument
from sim_core.kernel_compile import compile_task
from sim_core.optim.evaluators import make_evaluator, optimiser_solver_config
from sim_core.tasks.registry import load_task
records, later, compiled = {}, {}, {}
_instrument(records, later, compiled)
compile_task("folding_u", "cpu", copies=2, steps=2)
warm_up = len(compiled)
records.clear()
task = load_task("folding_u")
rng = np.random.default_rng(3)
span = task.action_high - task.action_low
actions = [np.clip(task.reference_actions[:3] + rng.uniform(-0.2, 0.2, (3, task.action_dim)) * span,
                   task.action_low, task.action_high) for _ in range(3)]
make_evaluator(task, horizon=3, solver_config=optimiser_solver_config("taichi-cpu"), batched=True).evaluate(actions)
print("counts", warm_up, len(compiled) - warm_up, len(records))
"""
"""A process that runs compile_task, then a generation of the optimiser's batched evaluator (another population, one
step longer), and prints the compiled kernels of the warm-up, those new in the generation and the kernel instances
the generation prepared."""


def _run(args: list[str]) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join((str(REPO), str(REPO / "benchmarks"))))
    return subprocess.run([sys.executable, *args], cwd=REPO, env=env, capture_output=True, text=True, timeout=900,
                          check=False)


PART = re.compile(r"^--- (?P<title>[^:]+):[^;\n]*; (?P<instances>\d+) kernel instances of (?P<kernels>\d+) kernels, "
                  r"(?P<compiled>\d+) new compiled kernels", re.M)


def test_a_population_prepares_each_compiled_kernel_once_and_the_next_none():
    run = _run(["benchmarks/time_kernel_prep.py", "--task", "folding_u", "--B", "2", "--steps", "1", "--emulate-cuda",
                "--linear-solver", "envelope", "--populations", "2"])
    assert run.returncode == 0, run.stderr[-3000:]
    parts = {m["title"]: {k: int(m[k]) for k in ("instances", "kernels", "compiled")} for m in PART.finditer(run.stdout)}
    first, second = parts["population 1"], parts["population 2"]
    # the lockstep batch's kernels on CUDA's paths: fused elastic, contact, friction rows, envelope solver, iterates
    assert first["compiled"] >= 30, run.stdout
    assert first["instances"] == first["compiled"], run.stdout  # no kernel's frontend run twice for one compiled code
    assert second == {"instances": 0, "kernels": 0, "compiled": 0}, run.stdout


def test_compile_task_prepares_every_kernel_of_the_optimisers_batched_generation():
    run = _run(["-c", AFTER_COMPILE_TASK])
    assert run.returncode == 0, run.stderr[-3000:]
    warm_up, new, instances = (int(v) for v in run.stdout.split("counts")[-1].split())
    assert warm_up >= 10, run.stdout  # the fused elastic, contact, friction and plasticity kernels of a CPU step
    assert (new, instances) == (0, 0), run.stdout
