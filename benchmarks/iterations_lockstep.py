"""Newton iterations of the Forming copies, lockstep against sequential: per copy and step, and why they differ.

Usage: ``python benchmarks/iterations_lockstep.py --arch cpu --B 8 --steps 5 [--line-search] [--linear-solver
envelope]``. Runs ``B`` copies of
``thinshell bench batch``'s Forming scene (``sim_core.bench.batch._FormingRun``: copy ``i`` on the benchmark trajectory
scaled by ``1 - 0.1 i / B``) for ``--steps`` steps twice, each copy alone (``lockstep=False``: the single
environment's solver) and in one lockstep batch, and prints per step and copy the Newton iterations, the stopping test
(``velo``city, ``simp``lified, ...) and the backtracks (``/bK``), the mean iterations a copy-step and the lockstep's
iterations and factorisations a step (its slowest copy's iterations: what a lockstep step costs), and the largest
distance between the two runs'
positions after each step (m). Also the share of the lockstep's copy-iterations (its iterations times ``B``) that are
the copies' own (the rest: copies that have converged, waiting for the slowest), and with a device solver
(``--linear-solver envelope`` or ``pcg``: the CUDA path's) the copies it factorised against ``B`` a factorisation
(``LockstepSolver.copies_factorized``, where the tree has it).

``--line-search``: also, at every lockstep line search, the trial step of each copy tested both ways, the lockstep's
slope test (the trapezoidal rule's Armijo estimate from the directional derivatives at both ends; its module
docstring) and the Armijo condition on the copy's own measured energy change (its separate run's test, measured here
by moving that copy alone: one energy evaluation per copy), listing the copies where the two disagree.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np


def _run(B: int, steps: int, backend: str, lockstep: bool, on_step=None, linear_solver: str | None = None
         ) -> tuple[np.ndarray, list, list, list]:
    """Iterations ``(steps, B)``, ``stop/backtracks`` labels, the lockstep's (iterations, factorisations, copies
    factorised) a step and the positions; ``on_step(k)`` is called before step ``k``."""
    from sim_core.bench.batch import _FormingRun
    from sim_core.control import Control

    run = _FormingRun(B, steps, backend, lockstep=lockstep, linear_solver=linear_solver)
    run.batch.warm_up()
    iterations = np.zeros((steps, B), dtype=int)
    labels, stacked, positions = [], [], []
    for k in range(steps):
        if on_step is not None:
            on_step(k)
        res = run.batch.step([Control(effector_pose_target={run.effector: t[k]}) for t in run.targets])
        labels.append([f"{info.stop_reason[:4]}" + (f"/b{info.backtracks}" if info.backtracks else "")
                       for info in res.infos])
        iterations[k] = [info.iterations for info in res.infos]
        if lockstep:
            solver = run.batch.lockstep.solver
            done = solver.last_stacked_info
            stacked.append((done.iterations, done.factorizations, getattr(solver, "copies_factorized", None)))
        positions.append(np.array([s.state.x for s in run.batch.sims]))
    return iterations, labels, stacked, positions


def _watch_line_searches(steps_seen: list) -> None:
    """Wrap ``LockstepSolver._line_search_copies`` to print, before each line search, the copies whose slope test
    and own-energy Armijo test disagree at the first trial step."""
    from sim_core.batch import lockstep
    from sim_core.batch.iterates import frozen

    search = lockstep.LockstepSolver._line_search_copies

    def watched(self, step, x, d, alpha, slope, open_, contact_terms, x_search, info):
        c = self.config.armijo_c
        e0 = self._energy(step, x, contact_terms, x_search)
        x_try = frozen(self._runs.moved(x, d, np.where(open_, alpha, 0.0)))
        s_try = self._runs.dot(self._stacked_gradient(step, x_try, info)[2], d)
        for i in np.flatnonzero(open_):
            alone = np.where(np.arange(len(alpha)) == i, alpha, 0.0)
            de = self._energy_with(step, x, d, alone) - e0
            by_energy = de <= c * alpha[i] * slope[i] + 1e-14 * abs(e0)
            by_slope = s_try[i] <= (1.0 - 2.0 * c) * abs(slope[i])
            if by_energy != by_slope:
                print(f"  step {steps_seen[-1]} copy {i}: step {alpha[i]:.3g}, slope {slope[i]:.3e} -> {s_try[i]:.3e} "
                      f"J/m along d, energy change {de:.3e} J (trapezoidal estimate "
                      f"{alpha[i] * (slope[i] + s_try[i]) / 2:.3e} J): energy test {by_energy}, slope test {by_slope}")
        self._trial_energy = None
        return search(self, step, x, d, alpha, slope, open_, contact_terms, x_search, info)

    lockstep.LockstepSolver._line_search_copies = watched


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--arch", default="cpu")
    ap.add_argument("--B", type=int, default=8)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--line-search", action="store_true")
    ap.add_argument("--linear-solver", default=None, help="the copies' SolverConfig.linear_solver (default: its own)")
    args = ap.parse_args()
    from sim_core.bench.batch import ARCH_BACKENDS
    from sim_core.ti_backend import init_backend

    backend = ARCH_BACKENDS[args.arch]
    if backend != "numpy":
        init_backend(args.arch)
    runs = {}
    for lockstep in (False, True):
        name = "lockstep" if lockstep else "sequential"
        steps_seen: list = []
        if lockstep and args.line_search:
            _watch_line_searches(steps_seen)
        t0 = time.perf_counter()
        iterations, labels, stacked, positions = _run(args.B, args.steps, backend, lockstep, steps_seen.append,
                                                      args.linear_solver)
        runs[name] = positions
        print(f"{name}: {time.perf_counter() - t0:.1f} s, {iterations.mean():.3f} Newton iterations a copy-step, "
              f"slowest copy's a step {iterations.max(axis=1).tolist()}")
        if stacked:
            its = [i for i, _, _ in stacked]
            own, slots = int(iterations.sum()), args.B * sum(its)
            print(f"  lockstep steps: {sum(its)} iterations, {sum(f for _, f, _ in stacked)} "
                  f"factorisations (a step: {its}, {[f for _, f, _ in stacked]}); the copies' own iterations "
                  f"{own} of {slots} copy-iterations ({own / slots:.3f})")
            if stacked[-1][2] is not None:
                made = [c for _, _, c in stacked]
                print(f"  copies factorised (device solver): {made[-1]} over the steps, a step "
                      f"{np.diff([0] + made).tolist()}; B a factorisation: {args.B * sum(f for _, f, _ in stacked)}")
        for k in range(args.steps):
            print(f"  step {k}: " + " ".join(f"{n}:{lab}" for n, lab in zip(iterations[k], labels[k])))
    for k in range(args.steps):
        gap = float(np.max(np.abs(runs["sequential"][k] - runs["lockstep"][k])))
        print(f"step {k}: largest |x_sequential - x_lockstep| = {gap:.3e} m")
    return 0


if __name__ == "__main__":
    sys.exit(main())
