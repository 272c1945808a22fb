"""The lockstep's batched CG in double and in mixed precision on one real Newton matrix, side by side.

Usage: ``python benchmarks/bench_cg_precision.py --arch cuda --B 1024 --repeat 5``. Builds ``B`` lockstep Forming
copies on the batched CG (``parts_lockstep.third_step``: two steps taken, the third set up), takes the Newton matrix
at the third step's first iterate (the fused elastic values and the contact and friction blocks, projected by
``--projection``), and for each precision (:mod:`sim_core.ti_kernels.precision`) a fresh
:class:`~sim_core.ti_kernels.pcg.BatchedPCG` as the lockstep makes it (each copy's sheet a band block,
``LOCKSTEP_CG_RTOL``) factorises it and solves a right-hand side (seeded, zero on fixed DoFs): ms a factorisation and
a solve (medians of ``--repeat``, each ended by a synchronisation), CG iterations (of the slowest copy), ms a CG
iteration, band blocks not usable, copies unconverged or indefinite, and each precision's largest per-copy relative
residual ``|A x_c - b_c| / |b_c|`` and difference from the double solution ``|A (x_c - x_c^double)| / |b_c|``,
both with the double operator's product. Two more variants tell the parts apart: ``mixed/band64`` (the operator and
the vertex inverses float32, the band tiles float64) and ``double/band32`` (only the band tiles float32).
"""

from __future__ import annotations

import argparse
import sys

import numpy as np


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--arch", default="cpu")
    ap.add_argument("--B", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--projection", default="clamp", help="the contact blocks' projection: clamp or none")
    args = ap.parse_args()
    from parts_lockstep import newton_system, synced_median_ms  # (benchmarks/, the script's folder)

    from sim_core.batch.lockstep import LOCKSTEP_CG_RTOL
    from sim_core.batch.sheet_bands import sheet_band_dofs
    from sim_core.ti_backend import init_backend, ti
    from sim_core.ti_kernels.band_cholesky import BandBlocks
    from sim_core.ti_kernels.pcg import BatchedPCG

    init_backend(args.arch)
    solver, step, x, operator, dof_copy = newton_system(args.B, args.arch, args.projection)
    scene = solver.scene
    b = np.random.default_rng(0).normal(size=dof_copy.size) * step.free

    def timed(fn) -> float:
        return synced_median_ms(fn, args.repeat)

    solutions, reference = {}, None
    variants = {"double": ("double", None), "mixed": ("mixed", None), "mixed/band64": ("mixed", ti.f64),
                "double/band32": ("double", ti.f32)}
    for name, (precision, band_dtype) in variants.items():
        bands = sheet_band_dofs(scene)
        pcg = BatchedPCG(dof_copy, rtol=LOCKSTEP_CG_RTOL, bands=bands, precision=precision)
        if band_dtype is not None:  # the band tiles in the other precision than the rest
            pcg.bands = BandBlocks(bands, dof_copy, dtype=band_dtype)
        pcg.factorize(*operator)  # compilation
        pcg.solve(b)
        factorize_ms = timed(lambda: pcg.factorize(*operator))
        solve_ms = timed(lambda: pcg.solve(b))
        solutions[name] = pcg.solve(b)
        if reference is None:
            reference = pcg  # the double operator's product
        unusable = int((~pcg.bands.usable).sum()) if pcg.bands is not None else -1
        print(f"B={args.B} {name:13s} factorize {factorize_ms:8.2f} ms  solve {solve_ms:8.2f} ms  "
              f"CG iterations {pcg.iterations}  ms an iteration {solve_ms / max(pcg.iterations, 1):.3f}  "
              f"band blocks not usable {unusable}  unconverged {int(pcg.unconverged.sum())}  "
              f"indefinite {int(pcg.indefinite.sum())}", flush=True)
    b_norm = np.sqrt(np.bincount(dof_copy, weights=b * b))
    for name, xs in solutions.items():
        residual = np.sqrt(np.bincount(dof_copy, weights=(reference.matvec(xs) - b) ** 2)) / np.maximum(b_norm, 1e-300)
        diff = reference.matvec(xs - solutions["double"])
        change = np.sqrt(np.bincount(dof_copy, weights=diff * diff)) / np.maximum(b_norm, 1e-300)
        print(f"B={args.B} {name:13s} largest relative residual {residual.max():.3e}  largest |A (x - x_double)| / "
              f"|b| {change.max():.3e}  (rtol {LOCKSTEP_CG_RTOL:g})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
