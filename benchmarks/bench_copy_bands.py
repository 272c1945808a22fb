"""Band blocks of the lockstep's batched CG side by side on one real Newton matrix: each copy's sheet (today's
``bands``) against each copy's whole free system (sheet and gel in one band block, reverse Cuthill-McKee order).

Usage: ``python benchmarks/bench_copy_bands.py --arch cuda --B 1024 --repeat 5``. Builds ``B`` lockstep Forming
copies on the batched CG (``parts_lockstep.third_step``: two steps taken, the third set up), takes the Newton matrix
at the third step's first iterate (projected by ``--projection``), and for each layout a fresh
:class:`~sim_core.ti_kernels.pcg.BatchedPCG` as the lockstep makes it factorises it and solves the step's own
right-hand side (the negative gradient) to ``--rtol`` (default the lockstep's ``LOCKSTEP_CG_RTOL``) and to 1e-10:
per layout the half-bandwidth ``w`` (DoFs), the tiles (``t`` rows, ``nt`` of them), the band's and tiles' device
MiB a copy, ms a factorisation and a solve (medians of ``--repeat``, each ended by a synchronisation), CG iterations
(of the slowest copy), band blocks not usable, and the largest per-copy relative residual ``|A x_c - b_c| / |b_c|``;
and at the next Newton matrix (a full step along the first solve) the CG iterations with its own band factors and
with the first matrix's kept (``BatchedPCG.factorize(..., keep_bands=True)``: factorised once a step).
The whole copy's order (:func:`sim_core.batch.sheet_bands.copy_band_dofs`) comes from the elastic pattern alone or
with the contact and friction blocks' vertex pairs of this matrix (``copy+contacts``).
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--arch", default="cpu")
    ap.add_argument("--B", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--projection", default="clamp", help="the contact blocks' projection: clamp or none")
    ap.add_argument("--rtol", type=float, default=None)
    ap.add_argument("--layouts", default="sheet,copy,copy+contacts")
    ap.add_argument("--precision", default="mixed")
    args = ap.parse_args()
    from parts_lockstep import newton_rhs, newton_system, synced_median_ms  # (benchmarks/, the script's folder)

    from sim_core.batch.lockstep import LOCKSTEP_CG_RTOL
    from sim_core.batch.sheet_bands import copy_band_dofs, sheet_band_dofs
    from sim_core.ti_backend import init_backend, ti
    from sim_core.ti_kernels.band_cholesky import BandBlocks
    from sim_core.ti_kernels.pcg import BatchedPCG

    init_backend(args.arch)
    t0 = time.perf_counter()
    solver, step, x, operator, dof_copy = newton_system(args.B, args.arch, args.projection)
    print(f"set-up {time.perf_counter() - t0:.1f} s", flush=True)
    blocks = operator[1]
    scene = solver.scene
    b = newton_rhs(solver, step, x)
    rtol = LOCKSTEP_CG_RTOL if args.rtol is None else args.rtol
    pairs = np.zeros((0, 2), dtype=np.int64)  # the contact and friction elements' vertex pairs
    for verts, _ in (blocks.sets or []) if blocks is not None else []:
        k, m = verts.shape
        pairs = np.concatenate([pairs, np.stack([np.repeat(verts, m, axis=1).reshape(-1),
                                                 np.tile(verts, (1, m)).reshape(-1)], axis=1)])
    layouts = {"sheet": lambda: sheet_band_dofs(scene),
               "copy": lambda: copy_band_dofs(scene, step.free, operator[0][0], operator[0][1]),
               "copy+contacts": lambda: copy_band_dofs(scene, step.free, operator[0][0], operator[0][1], pairs)}

    def timed(fn, before=()) -> float:
        return synced_median_ms(fn, args.repeat, before)

    reference = None
    b_norm = np.sqrt(np.bincount(dof_copy, weights=b * b))
    for name in args.layouts.split(","):
        bands = layouts[name]()
        for tol in (rtol, 1e-10):
            pcg = BatchedPCG(dof_copy, rtol=tol, bands=bands, precision=args.precision)
            pcg.bands = BandBlocks(bands, dof_copy, max_width=bands.shape[1], dtype=pcg._dtype)
            pcg.factorize(*operator)  # compilation
            pcg.solve(b)
            factorize_ms = timed(lambda: pcg.factorize(*operator))
            solve_ms = timed(lambda: pcg.solve(b))
            xs = pcg.solve(b)
            iterations = pcg.iterations
            if reference is None:
                reference = pcg  # the operator's product
            residual = np.sqrt(np.bincount(dof_copy, weights=(reference.matvec(xs) - b) ** 2)) / np.maximum(b_norm, 1e-300)
            if tol == rtol:  # the next Newton matrix (a full step along this solve), its bands fresh and kept
                x1 = x + xs.reshape(x.shape)
                terms1 = solver.contact.potentials(x1, step.x_n, step.memory)
                operator1 = solver._device_operator(step, x1, args.projection, terms1 + step.dynamic_terms)
                b1 = newton_rhs(solver, step, x1)
                pcg.factorize(*operator1, keep_bands=True)
                pcg.solve(b1)
                kept = pcg.iterations
                pcg.factorize(*operator1)
                pcg.solve(b1)
                print(f"B={args.B} {name:14s} next Newton matrix: CG iterations {pcg.iterations} with its own band "
                      f"factors, {kept} with the last matrix's kept", flush=True)
                # the matrix at x again (on CUDA the values of the next one were written over its device arrays)
                contact_terms = solver.contact.potentials(x, step.x_n, step.memory)
                operator = solver._device_operator(step, x, args.projection, contact_terms + step.dynamic_terms)
                pcg.factorize(*operator)
            bb = pcg.bands
            if tol == rtol:  # the factorisation's parts: the band's gather, the elimination, the tiles
                a = pcg._arrays
                vertex_blocks = (a["brow"], a["bcol"], a["bval"], a["free"], pcg._nblocks)
                parts = [lambda: bb.gather(a["data"], vertex_blocks), bb.eliminate, bb.invert]
                ms = [timed(parts[k], before=parts[:k]) for k in range(3)]
                print(f"B={args.B} {name:14s} factorisation's parts: gather {ms[0]:.2f} ms, elimination "
                      f"{ms[1]:.2f} ms, tiles {ms[2]:.2f} ms", flush=True)
                pcg.factorize(*operator)
            mib = (bb.size * (bb.width + 1) * 12 + 3 * bb.tiles * bb.tile ** 2 * (4 if bb.dtype == ti.f32 else 8)) \
                / 2 ** 20 * bb.count / max(args.B, 1)
            print(f"B={args.B} {name:14s} rtol {tol:.0e} m {bb.size} w {bb.width} t {bb.tile} nt {bb.tiles} "
                  f"MiB a copy {mib:.2f}  factorize {factorize_ms:8.2f} ms  solve {solve_ms:8.2f} ms  "
                  f"CG iterations {iterations}  ms an iteration {solve_ms / max(iterations, 1):.3f}  "
                  f"not usable {int((~bb.usable).sum())}  unconverged {int(pcg.unconverged.sum())}  "
                  f"largest residual {residual.max():.2e}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
