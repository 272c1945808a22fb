"""The envelope Cholesky of each copy (``linear_solver="envelope"``) against the lockstep's batched CG on one real
Newton matrix: ms a factorisation and a solve, threads a copy, float64 and float32 factors, the accuracy.

Usage: ``python benchmarks/bench_envelope.py --arch cuda --B 1024 --lanes 1,32,64,128 --repeat 3``. Builds ``B``
lockstep Forming copies on the batched CG (``parts_lockstep.third_step``: two steps taken, the third set up), takes
the Newton matrix at the third step's first iterate (projected by ``--projection``) and its right-hand side (the
negative gradient on the free DoFs), and prints one JSON line per solver: the CG as the lockstep makes it (its
factorisation, which builds the sheets' band blocks, and its solve to ``LOCKSTEP_CG_RTOL``, its iterations), then the
envelope Cholesky (:class:`~sim_core.ti_kernels.envelope_cholesky.BatchedEnvelope`) with each ``--lanes`` threads a
copy in float64 (each ``--schedules``: how a copy's threads share the factorisation; with ``dots``, ``panels``
and ``blocks`` each ``--groups`` lanes of a dot product; with ``blocks`` each ``--panels`` columns a panel, or the
``--blocks`` pairs of columns and lanes, and its dependent steps a factorisation and a solve against ``dots``') and,
at the first lanes, float32 factors with two refinements: medians of ``--repeat`` (each ended by a synchronisation)
of the factorisation (and, alone, of its gather and elimination kernels: ``eliminate_ms``) and the solve, the
envelope's entries and device MiB a copy, the copies
marked indefinite, and the largest per-copy relative residual ``|A x_c - b_c| / |b_c|`` (the CG's float64 product).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--arch", default="cpu")
    ap.add_argument("--B", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--projection", default="clamp", help="the contact blocks' projection: clamp or none")
    ap.add_argument("--lanes", default="1", help="threads a copy, comma-separated (1: one thread a copy)")
    ap.add_argument("--schedules", default="pairs,rows,dots",
                    help="how a copy's threads share the factorisation (comma-separated)")
    ap.add_argument("--groups", default="",
                    help="lanes of a dot product with the dots schedule, comma-separated (default: the solver's)")
    ap.add_argument("--panels", default="",
                    help="columns a panel with the blocks schedule, comma-separated (default: the solver's)")
    ap.add_argument("--blocks", default="",
                    help="the blocks schedule's variants as PANEL:LANES pairs, comma-separated, in this order "
                         "(in place of --panels x --lanes)")
    ap.add_argument("--cg", action=argparse.BooleanOptionalAction, default=True,
                    help="time the batched CG first (as the lockstep makes it)")
    ap.add_argument("--mixed", action=argparse.BooleanOptionalAction, default=True,
                    help="also float32 factors with two refinements (at the first --lanes)")
    args = ap.parse_args()
    from parts_lockstep import newton_rhs, newton_system, synced_median_ms  # (benchmarks/, the script's folder)

    from sim_core.batch.lockstep import LOCKSTEP_CG_RTOL
    from sim_core.batch.sheet_bands import sheet_band_dofs
    from sim_core.ti_backend import init_backend
    from sim_core.ti_kernels.envelope_blocks import dependent_steps
    from sim_core.ti_kernels.envelope_cholesky import BatchedEnvelope
    from sim_core.ti_kernels.pcg import BatchedPCG

    init_backend(args.arch)
    t0 = time.perf_counter()
    solver, step, x, operator, dof_copy = newton_system(args.B, args.arch, args.projection)
    print(f"set-up {time.perf_counter() - t0:.1f} s", flush=True)
    scene = solver.scene
    b = newton_rhs(solver, step, x)
    b_norm = np.sqrt(np.bincount(dof_copy, weights=b * b))

    def timed(fn) -> float:
        return synced_median_ms(fn, args.repeat)

    reference = BatchedPCG(dof_copy, rtol=1e-10, precision="double")
    reference.factorize(*operator)

    def residual(xs: np.ndarray) -> float:
        r = np.sqrt(np.bincount(dof_copy, weights=(reference.matvec(xs) - b) ** 2)) / np.maximum(b_norm, 1e-300)
        return float(r[b_norm > 0].max())

    def report(record: dict) -> None:
        print(json.dumps({"bench": "envelope", "arch": args.arch, "B": args.B, **record}), flush=True)

    if args.cg:
        cg = BatchedPCG(dof_copy, rtol=LOCKSTEP_CG_RTOL, bands=sheet_band_dofs(scene), precision="mixed")
        cg.factorize(*operator)
        cg.solve(b)  # compilation
        report({"solver": "pcg", "factorize_ms": timed(lambda: cg.factorize(*operator)),
                "solve_ms": timed(lambda: cg.solve(b)), "iterations": cg.iterations,
                "residual": residual(cg.solve(b))})
    lanes_list = [int(v) for v in args.lanes.split(",")]
    schedules = args.schedules.split(",")
    groups = [int(v) for v in args.groups.split(",")] if args.groups else [None]
    panels = [int(v) for v in args.panels.split(",")] if args.panels else [None]
    left = ("dots", "panels", "blocks")
    variants = [(lanes, "double", schedule, group, panel) for schedule in schedules
                for panel in (panels if schedule == "blocks" else [None]) for lanes in lanes_list
                for group in (groups if schedule in left else [None])
                if group is None or (group <= lanes and lanes % group == 0)] + (
        [(lanes_list[0], "mixed", schedules[0], groups[0] if schedules[0] in left else None, panels[0])]
        if args.mixed else [])
    if args.blocks:
        pairs = [tuple(int(v) for v in pair.split(":")) for pair in args.blocks.split(",")]
        variants = [v for v in variants if v[2] != "blocks"] + [
            (lanes, "double", "blocks", group, panel) for panel, lanes in pairs for group in groups
            if group is None or (group <= lanes and lanes % group == 0)]
    for lanes, precision, schedule, group, panel in variants:
        if lanes == 1 and schedule not in (schedules[0], *left):
            continue  # (one thread a copy: the same work for the right-looking schedules)
        env = BatchedEnvelope(dof_copy, precision=precision, lanes=lanes, schedule=schedule, group=group,
                              panel=panel)
        t = time.perf_counter()
        try:
            env.factorize(*operator)  # compilation, the order and the envelope
            xs = env.solve(b)
        except Exception as exc:  # (a variant the device cannot compile or launch: reported, the others still run)
            report({"solver": "envelope", "lanes": lanes, "schedule": schedule, "group": group, "panel": panel,
                    "error": f"{type(exc).__name__}: {exc}"[:300]})
            continue
        first_s = time.perf_counter() - t
        factor_ms = timed(lambda: env.factorize(*operator))
        eliminate_ms = timed(env._eliminate)  # (the gather and the factorisation's kernels alone)
        solve_ms = timed(lambda: env.solve(b))
        xs = env.solve(b)
        bytes_a_copy = env.entries * (4 if precision == "mixed" else 8)
        report({"solver": "envelope", "precision": precision, "lanes": lanes, "schedule": schedule,
                "group": (env._blocks_launch(lanes)[2] if schedule == "blocks" else env.group) if schedule in left
                else None,
                **({"panel": env.panel, "steps": dependent_steps(env._m, env.panel)} if schedule == "blocks" else {}),
                "factorize_ms": factor_ms, "eliminate_ms": eliminate_ms,
                "solve_ms": solve_ms, "first_call_s": first_s, "entries": env.entries, "m": env._m,
                "widest_row": int((np.arange(env._m) - env._first).max()) + 1, "widenings": env.widenings,
                "envelope_mib_a_copy": bytes_a_copy / 2 ** 20, "indefinite": int(env.indefinite.sum()),
                "residual": residual(xs), "iterations": env.iterations})
        del env
    return 0


if __name__ == "__main__":
    sys.exit(main())
