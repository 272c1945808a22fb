"""Time the PSD projection's Jacobi kernel (sim_core.ti_kernels.block_projection.jacobi_project_blocks) at a
lockstep batch's block counts, on whichever ``sim_core`` is first on the path (run it with two checkouts' paths to
compare them).

Usage: ``python benchmarks/bench_jacobi.py --arch cuda --blocks 15:161280,6:161280,12:50624 --repeat 3 [--save F]
[--reduce 6:161280,3:161280]``.
Each ``n:count`` is ``count`` symmetric ``n x n`` blocks with entries from a seeded normal distribution (indefinite:
as every reduced Kirchhoff, spring-membrane triangle and contact-pair block of the Forming batch's projected
iterations), in the kernel's layout ``(n, n, count)`` on the device. Prints per size the kernel's ms (each run ended
by a synchronisation; the blocks uploaded again before each) and the smallest eigenvalue of the first 2000 projected
blocks relative to their largest entry; ``--save`` writes those 2000 blocks per size (``.npz``) for a comparison.
"""

import argparse
import time

import numpy as np


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--arch", default="cpu", help="Taichi arch: cpu or cuda")
    ap.add_argument("--blocks", default="15:4096,6:4096,12:4096", help="n:count,... (block size and count)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--save", default=None, help="write the first 2000 projected blocks of each size here (.npz)")
    ap.add_argument("--reduce", default="", help="m:count,... (vertices of a block and count): reduce_block_rows")
    args = ap.parse_args()
    from sim_core.ti_backend import init_backend, ti
    from sim_core.ti_kernels.block_projection import jacobi_project_blocks, reduce_block_rows
    from sim_core.ti_kernels.linalg import helmert_basis
    from sim_core.ti_kernels.device_copy import new_ndarray
    from sim_core.ti_kernels.transfer import download, upload

    init_backend(args.arch)
    saved = {}
    for spec in args.blocks.split(","):
        n, count = (int(v) for v in spec.split(":"))
        a = np.random.default_rng(n).normal(size=(n, n, count))
        host = np.ascontiguousarray(a + np.swapaxes(a, 0, 1))
        blocks, work, vectors = (new_ndarray(ti.f64, host.shape) for _ in range(3))
        times = []
        for run in range(args.repeat + 1):  # the first run compiles
            upload(blocks, host)
            ti.sync()
            start = time.perf_counter()
            jacobi_project_blocks(blocks, work, vectors, count, 1)
            ti.sync()
            times.append(1e3 * (time.perf_counter() - start))
        out = np.empty_like(host)
        download(blocks, out)
        first = np.moveaxis(out[:, :, :2000], -1, 0)
        saved[f"n{n}"] = first
        smallest = (np.linalg.eigvalsh(first).min(axis=1) / np.abs(first).max(axis=(1, 2))).min()
        print(f"n={n} count={count}: ms {' '.join(f'{t:.2f}' for t in times[1:])} (first {times[0]:.0f}),"
              f" smallest eigenvalue / largest entry {smallest:.2e}", flush=True)
    for spec in filter(None, args.reduce.split(",")):
        m, count = (int(v) for v in spec.split(":"))
        a = np.random.default_rng(m).normal(size=(count, 3 * m, 3 * m))
        blocks = new_ndarray(ti.f64, a.shape)
        upload(blocks, np.ascontiguousarray(a + np.swapaxes(a, 1, 2)))
        helmert, rows = new_ndarray(ti.f64, (m, m - 1)), new_ndarray(ti.i32, (count,))
        upload(helmert, np.ascontiguousarray(helmert_basis(m)))
        rows.from_numpy(np.arange(count, dtype=np.int32))
        reduced = new_ndarray(ti.f64, (3 * m - 3, 3 * m - 3, count))
        times = []
        for run in range(args.repeat + 1):  # the first run compiles
            ti.sync()
            start = time.perf_counter()
            reduce_block_rows(blocks, helmert, rows, count, reduced)
            ti.sync()
            times.append(1e3 * (time.perf_counter() - start))
        out = np.empty(tuple(reduced.shape))
        download(reduced, out)
        saved[f"reduced{m}"] = np.moveaxis(out[:, :, :2000], -1, 0)
        print(f"reduce m={m} count={count}: ms {' '.join(f'{t:.2f}' for t in times[1:])} (first {times[0]:.0f})",
              flush=True)
    if args.save:
        np.savez(args.save, **saved)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
