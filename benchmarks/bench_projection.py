"""Time the device PSD projection kernels of the projected retries on the block counts of a Forming lockstep batch.

Usage: ``python benchmarks/bench_projection.py --arch cuda --B 1024``. Each kernel of
``sim_core.ti_kernels.block_projection.DEVICE_KERNELS`` (cyclic Jacobi, Householder-QL) projects ("clamp") random
symmetric blocks of the sizes and counts a projected retry of ``B`` copies makes (the reduced Kirchhoff blocks
15 x 15 and the reduced membrane blocks 6 x 6, 210 a copy each; about 50 contact pair blocks 12 x 12 a copy), in the
kernels' layout (block index last), the device synchronised around each launch; prints the median of ``--repeat``
launches after a first one (its compilation) and each kernel's largest error against LAPACK
(``numpy.linalg.eigh``) on the first 2,000 blocks, relative to the largest entry.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

BLOCKS_A_COPY = ((15, 210), (6, 210), (12, 50))
"""``(n, blocks a copy)`` of a Forming projected retry: reduced Kirchhoff, reduced membrane, contact pair blocks."""


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--arch", default="cpu")
    ap.add_argument("--B", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    from sim_core.ti_backend import init_backend, ti

    init_backend(args.arch)
    from sim_core.ti_kernels.block_projection import DEVICE_KERNELS, project_reduced_blocks
    from sim_core.ti_kernels.device_copy import new_ndarray
    from sim_core.ti_kernels.transfer import download, upload

    rng = np.random.default_rng(0)
    for n, per_copy in BLOCKS_A_COPY:
        count = per_copy * args.B
        a = rng.normal(size=(n, n, count))
        host = a + np.swapaxes(a, 0, 1)
        arrays = [new_ndarray(ti.f64, (n, n, count)) for _ in range(3)]
        checked = min(count, 2000)
        want = project_reduced_blocks(np.moveaxis(host[:, :, :checked], -1, 0).copy(), "clamp", method="lapack")
        for name, kernel in DEVICE_KERNELS.items():
            times = []
            for _ in range(args.repeat + 1):
                upload(arrays[0], host)
                ti.sync()
                start = time.perf_counter()
                kernel(arrays[0], arrays[1], arrays[2], count, 1)
                ti.sync()
                times.append(time.perf_counter() - start)
            got = np.moveaxis(download(arrays[0])[:, :, :checked], -1, 0)
            error = np.abs(got - want).max() / np.abs(host).max()
            print(f"n={n:2d} blocks={count:7d} {name:11s} {1e3 * np.median(times[1:]):8.2f} ms "
                  f"(first {1e3 * times[0]:.1f}) largest error vs LAPACK {error:.1e}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
