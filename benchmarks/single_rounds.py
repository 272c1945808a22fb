"""Alternate single-environment Forming runs of several trees and archs in rounds, on one machine in one call.

Usage::

    python benchmarks/single_rounds.py --trees main=. branch=/tmp/br --archs cuda cpu \\
        [--rounds 5] [--repeat 3] [--steps 49] [--site /tmp/site] [--out results.jsonl]

One worker process per tree and arch (Taichi initialises one arch per process) runs ``thinshell bench forming``'s
trajectory (:func:`sim_core.bench.forming.run_forming` of the tree, the bundled Forming scene) on request. Each worker
first runs it once untimed (kernels compiled or loaded from the offline cache, one worker at a time), then every round
asks each worker in turn for ``--repeat`` runs, one worker running at a time while the others wait on their input. The
order of the workers turns by one place each round, so no tree or arch always runs first or after the same neighbour.
The worker's code is sent with its command (``python -c``), so a tree needs only ``run_forming`` (a baseline that
predates this script works too); ``--site`` is put before the tree on the workers' ``PYTHONPATH`` (the GPU machine's
Taichi wheels).

Printed, per tree and arch: the median, lowest and highest steps/s of all runs, the median of each round (the spread
between rounds), the Newton iterations a step (the same in every run: the steps are deterministic), and the ms a step
split into the linear solve (factorisations and solves on the host, the same code on both archs) and the rest; per
tree, the
median over rounds of each round's ratio of the first arch's median to the second's (``cuda / cpu``), with its range:
the figure of record, since runs one after another on one machine drift together. Every run is also written as one
JSON line to ``--out`` (keys: ``tree``, ``arch``, ``round``, ``run``, ``steps_per_s``, ``forward_total_s`` (s),
``newton_iters_mean``, ``factorizations_mean``, ``linear_solve_share``, ``linear_solver``, ``backend``).

Exits 1 when a worker fails (its stderr tail printed), or when one tree's runs differ in Newton iterations per step.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys

# The worker: init the arch, run once untimed, then answer each input line "N" with N runs (one JSON line each).
_WORKER = r"""
import json, sys
from sim_core.ti_backend import init_backend
init_backend(sys.argv[1])
from sim_core.bench.forming import run_forming
from thinshell_ros.paths import bundled_scene
scene, steps = bundled_scene("forming"), int(sys.argv[2])
first = run_forming(scene, steps, arch=sys.argv[1])
print("@@" + json.dumps({"ready": True, "jit_s": first["jit_s"], "steps_per_s": first["steps_per_s"]}), flush=True)
keys = ("steps_per_s", "forward_total_s", "newton_iters_mean", "factorizations_mean", "linear_solve_share",
        "linear_solver", "backend")
for line in sys.stdin:
    for _ in range(int(line)):
        r = run_forming(scene, steps, arch=sys.argv[1])
        print("@@" + json.dumps({k: r[k] for k in keys}), flush=True)
"""


class WorkerError(RuntimeError):
    """A worker process exited or answered something else than a result line."""


class _Worker:
    """One tree's process of one arch, started at once and ready after :meth:`wait_ready`."""

    def __init__(self, tree: str, path: str, arch: str, steps: int, site: str | None) -> None:
        self.tree, self.arch = tree, arch
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (site, path) if p)
        env["PYTHONUNBUFFERED"] = "1"
        self.proc = subprocess.Popen([sys.executable, "-c", _WORKER, arch, str(steps)], cwd=path, env=env,
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    def _answer(self) -> dict:
        """The next result line's record (lines without the ``@@`` mark, Taichi's banner, are skipped)."""
        for line in self.proc.stdout:
            if line.startswith("@@"):
                return json.loads(line[2:])
        self.proc.wait()
        tail = self.proc.stderr.read()[-3000:]
        raise WorkerError(f"worker {self.tree}/{self.arch} exited {self.proc.returncode}:\n{tail}")

    def wait_ready(self) -> dict:
        """Wait for the untimed first run; its record (``jit_s``, ``steps_per_s``)."""
        return self._answer()

    def runs(self, count: int) -> list[dict]:
        """``count`` timed runs, one after another; their records."""
        self.proc.stdin.write(f"{count}\n")
        self.proc.stdin.flush()
        return [self._answer() for _ in range(count)]

    def close(self) -> None:
        """End the worker: its input closed, killed if it has not exited 30 s later."""
        if self.proc.poll() is None:
            self.proc.stdin.close()
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()


def _spread(values: list[float], digits: int = 2) -> str:
    """``median (lowest-highest)`` of ``values``."""
    return f"{statistics.median(values):.{digits}f} ({min(values):.{digits}f}-{max(values):.{digits}f})"


def _summary(records: list[dict], trees: list[str], archs: list[str]) -> int:
    """Print the per tree and arch figures and the per-round arch ratios; 1 if a tree's iteration counts differ."""
    status = 0
    print(f"{'tree':12s} {'arch':6s} {'runs':>4s} {'steps/s median (range)':>24s}  round medians"
          f"{'':20s} Newton its/step")
    medians: dict[tuple, dict[int, float]] = {}
    for tree in trees:
        iterations = {round(r["newton_iters_mean"], 6) for r in records if r["tree"] == tree}
        if len(iterations) > 1:
            print(f"{tree}: Newton iterations per step differ between runs: {sorted(iterations)}")
            status = 1
        for arch in archs:
            mine = [r for r in records if r["tree"] == tree and r["arch"] == arch]
            by_round: dict[int, list[float]] = {}
            for r in mine:
                by_round.setdefault(r["round"], []).append(r["steps_per_s"])
            medians[tree, arch] = {k: statistics.median(v) for k, v in by_round.items()}
            rounds = " ".join(f"{medians[tree, arch][k]:.2f}" for k in sorted(by_round))
            its = sorted({r["newton_iters_mean"] for r in mine})
            print(f"{tree:12s} {arch:6s} {len(mine):4d} {_spread([r['steps_per_s'] for r in mine]):>24s}  {rounds:32s} "
                  f"{', '.join(f'{i:.4f}' for i in its)}")
            if all("forward_total_s" in r and "linear_solve_share" in r for r in mine):
                step_ms = [1e3 / r["steps_per_s"] for r in mine]
                solve_ms = [s * r["linear_solve_share"] for s, r in zip(step_ms, mine)]
                print(f"{'':12s} {'':6s} ms a step: {_spread(step_ms)}, of which the linear solve "
                      f"{_spread(solve_ms)} and the rest {_spread([a - b for a, b in zip(step_ms, solve_ms)])}")
    if len(archs) >= 2:
        first, second = archs[0], archs[1]
        for tree in trees:
            a, b = medians[tree, first], medians[tree, second]
            ratios = [a[k] / b[k] for k in sorted(a) if k in b]
            print(f"{tree}: {first} / {second} steps/s, per round: {' '.join(f'{q:.3f}' for q in ratios)}; "
                  f"median {_spread(ratios, 3)}")
    if len(trees) >= 2:
        base = trees[0]
        for tree in trees[1:]:
            for arch in archs:
                a, b = medians[tree, arch], medians[base, arch]
                ratios = [a[k] / b[k] for k in sorted(a) if k in b]
                print(f"{arch}: {tree} / {base} steps/s, per round: {' '.join(f'{q:.3f}' for q in ratios)}; "
                      f"median {_spread(ratios, 3)}")
    return status


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trees", nargs="+", default=["this=."], metavar="NAME=DIR",
                    help="checkouts to run (the first is the baseline of the tree ratios)")
    ap.add_argument("--archs", nargs="+", default=["cuda", "cpu"], choices=("cuda", "cpu"))
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--repeat", type=int, default=3, help="runs of each worker a round")
    ap.add_argument("--steps", type=int, default=49, help="steps of the trajectory (1..49)")
    ap.add_argument("--site", default=None, help="a folder put before each tree on the workers' PYTHONPATH")
    ap.add_argument("--out", default=None, help="append every run as a JSON line to this file")
    args = ap.parse_args(argv)
    if args.rounds < 1 or args.repeat < 1:
        ap.error("--rounds and --repeat must be >= 1")
    trees = [spec.split("=", 1) for spec in args.trees]
    if any(len(t) != 2 for t in trees):
        ap.error("--trees takes NAME=DIR")
    workers = []
    records: list[dict] = []
    try:
        for name, path in trees:  # started and warmed up one at a time: compilations do not overlap
            for arch in args.archs:
                worker = _Worker(name, os.path.abspath(path), arch, args.steps, args.site)
                workers.append(worker)
                ready = worker.wait_ready()
                print(f"ready {name}/{arch}: jit {ready['jit_s']:.1f} s, untimed run {ready['steps_per_s']:.2f} "
                      f"steps/s", flush=True)
        for k in range(args.rounds):
            order = workers[k % len(workers):] + workers[:k % len(workers)]
            for worker in order:
                for n, r in enumerate(worker.runs(args.repeat)):
                    r.update(tree=worker.tree, arch=worker.arch, round=k + 1, run=n + 1)
                    records.append(r)
                    print(json.dumps(r), flush=True)
    except WorkerError as err:
        print(err, file=sys.stderr)
        return 1
    finally:
        for worker in workers:
            worker.close()
        if args.out and records:
            with open(args.out, "a") as f:
                f.writelines(json.dumps(r) + "\n" for r in records)
    return _summary(records, [t[0] for t in trees], args.archs)


if __name__ == "__main__":
    raise SystemExit(main())
