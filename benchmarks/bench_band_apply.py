"""Time the batched CG's band-block product ``z = S^-1 r`` (sim_core.ti_kernels.band_cholesky) on its own, at a
lockstep batch's sizes.

Usage: ``python benchmarks/bench_band_apply.py --arch cuda --B 1024 --m 360 --w 53 --repeat 30``. The blocks are
:func:`bench_band_factor.banded_csr`'s (banded, symmetric, diagonally dominant, the same in every copy), assembled
and factorised by :class:`~sim_core.ti_kernels.band_cholesky.BandBlocks`; prints ms a pass of
:meth:`BandBlocks.apply` over all blocks (mean of ``repeat`` passes after one unmeasured, ended by a synchronisation)
and the largest relative error of the first block's product against NumPy's solve.
"""

import argparse
import time

import numpy as np

from bench_band_factor import banded_csr


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--arch", default="cpu", help="Taichi arch: cpu or cuda")
    ap.add_argument("--B", type=int, default=64, help="blocks (one a copy)")
    ap.add_argument("--m", type=int, default=360, help="DoFs a block")
    ap.add_argument("--w", type=int, default=53, help="half-bandwidth of a block (DoFs)")
    ap.add_argument("--repeat", type=int, default=20, help="passes timed")
    args = ap.parse_args()
    from sim_core.ti_backend import init_backend, ti

    init_backend(args.arch)
    from sim_core.ti_kernels import band_cholesky as bc
    from sim_core.ti_kernels import device_copy

    nb, m = args.B, args.m
    indptr_h, indices_h, data_h, block = banded_csr(nb, m, args.w)
    arrays = []
    for host, dtype in ((indptr_h, ti.i32), (indices_h, ti.i32), (data_h, ti.f64)):
        arr = device_copy.new_ndarray(dtype, host.shape)
        arr.from_numpy(host)
        arrays.append(arr)
    blocks = bc.BandBlocks(np.arange(nb * m).reshape(nb, m), np.repeat(np.arange(nb), m))
    assert blocks.assemble(*arrays, None, object()) and blocks.width == args.w
    r_h = np.random.default_rng(0).normal(size=nb * m)
    r, z, active = (device_copy.new_ndarray(ti.f64, (nb * m,)), device_copy.new_ndarray(ti.f64, (nb * m,)),
                    device_copy.new_ndarray(ti.i32, (nb,)))
    r.from_numpy(r_h)
    active.from_numpy(np.ones(nb, dtype=np.int32))
    blocks.apply(r, z, active)
    ti.sync()
    t = time.perf_counter()
    for _ in range(args.repeat):
        blocks.apply(r, z, active)
    ti.sync()
    ms = 1e3 * (time.perf_counter() - t) / args.repeat
    print(f"B={nb} m={m} w={args.w} band product {ms:8.3f} ms a pass")
    want = np.linalg.solve(block, r_h[:m])
    got = z.to_numpy()[:m]
    print(f"first block's product: largest relative error {np.abs(got - want).max() / np.abs(want).max():.2e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
