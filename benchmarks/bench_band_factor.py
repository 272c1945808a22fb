"""Time the batched CG's band blocks (sim_core.ti_kernels.band_cholesky) at a lockstep batch's sizes: the
factorisation phase by phase (the band gathered from the CSR values, the blocked banded elimination with the scaling
into ``L``, and what the product takes of the factor, :meth:`BandBlocks.invert`), then the product ``z = S^-1 r``
that the CG takes at each iteration (:meth:`BandBlocks.apply`).

Usage: ``python benchmarks/bench_band_factor.py --arch cuda --B 1024 --m 360 --w 53 --repeat 3 --products 30``. The
matrix of a block is banded (half-bandwidth ``w``), symmetric and diagonally dominant (positive definite), the same
in every copy. Prints ms a phase (mean of ``repeat`` runs, each ended by a synchronisation), ms a product (mean of
``products`` after one unmeasured, ended by a synchronisation) and the largest relative error of the first block's
product against NumPy's solve. ``--precision mixed``: the tiles stored as float32 (the batched CG's mixed precision,
:mod:`sim_core.ti_kernels.precision`), on a tree that has it.
"""

import argparse
import time

import numpy as np


def banded_csr(copies: int, m: int, w: int) -> tuple:
    """Both-triangle CSR arrays ``(indptr, indices, data)`` of ``copies`` equal blocks of size ``m``: ``S_ij =
    -(1 + (i + j) % 7) / (8 w)`` for ``0 < |i - j| <= w`` and ``S_ii = 2`` (diagonally dominant), and the block."""
    i, j = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")
    block = np.where(np.abs(i - j) <= w, -(1.0 + (i + j) % 7) / (8.0 * w), 0.0)
    np.fill_diagonal(block, 2.0)
    rows, cols = np.nonzero(block)
    per = rows.size
    counts = np.bincount(rows, minlength=m)
    indptr = np.zeros(copies * m + 1, dtype=np.int64)
    np.cumsum(np.tile(counts, copies), out=indptr[1:])
    indices = (cols[None, :] + m * np.arange(copies)[:, None]).reshape(-1)
    data = np.tile(block[rows, cols], copies)
    assert indptr[-1] == per * copies
    return indptr.astype(np.int32), indices.astype(np.int32), data, block


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--arch", default="cpu", help="Taichi arch: cpu or cuda")
    ap.add_argument("--B", type=int, default=64, help="blocks (one a copy)")
    ap.add_argument("--m", type=int, default=360, help="DoFs a block")
    ap.add_argument("--w", type=int, default=53, help="half-bandwidth of a block (DoFs)")
    ap.add_argument("--repeat", type=int, default=3, help="runs of each phase")
    ap.add_argument("--products", type=int, default=20, help="products timed")
    ap.add_argument("--tiles", type=int, default=None,
                    help="band_cholesky.TILES for this run (the tiled product's largest tile count), where it has one")
    ap.add_argument("--precision", default=None, help="double or mixed: the tiles' storage, where the tree has it")
    args = ap.parse_args()
    from sim_core.ti_backend import init_backend, ti

    init_backend(args.arch)
    from sim_core.ti_kernels import band_cholesky as bc
    from sim_core.ti_kernels import device_copy

    if args.tiles is not None:  # read when the kernels compile, below
        bc.TILES = args.tiles

    nb, m = args.B, args.m
    indptr_h, indices_h, data_h, block = banded_csr(nb, m, args.w)
    arrays = []
    for host, dtype in ((indptr_h, ti.i32), (indices_h, ti.i32), (data_h, ti.f64)):
        arr = device_copy.new_ndarray(dtype, host.shape)
        arr.from_numpy(host)
        arrays.append(arr)
    indptr, indices, data = arrays
    options = {}
    if args.precision is not None:
        from sim_core.ti_kernels.precision import storage_dtype

        options["dtype"] = storage_dtype(args.precision)
    blocks = bc.BandBlocks(np.arange(nb * m).reshape(nb, m), np.repeat(np.arange(nb), m), **options)
    key = object()
    assert blocks.assemble(indptr, indices, data, None, key) and blocks.width == args.w
    w = blocks.width
    phases = {
        "band gathered": lambda: blocks.gather(data, None),
        "elimination": blocks.eliminate,
        "invert": blocks.invert,
    }
    times = {name: 0.0 for name in phases}
    for _ in range(args.repeat):
        for name, run in phases.items():
            ti.sync()
            t = time.perf_counter()
            run()
            ti.sync()
            times[name] += time.perf_counter() - t
    for name, total in times.items():
        print(f"B={nb} m={m} w={w} {name:14s} {1e3 * total / args.repeat:9.3f} ms {args.precision or ''}")
    print(f"B={nb} m={m} w={w} {'all':14s} {1e3 * sum(times.values()) / args.repeat:9.3f} ms")
    r_h = np.random.default_rng(0).normal(size=nb * m)
    r, z, active = (device_copy.new_ndarray(ti.f64, (nb * m,)), device_copy.new_ndarray(ti.f64, (nb * m,)),
                    device_copy.new_ndarray(ti.i32, (nb,)))
    r.from_numpy(r_h)
    active.from_numpy(np.ones(nb, dtype=np.int32))
    blocks.apply(r, z, active)
    ti.sync()
    t = time.perf_counter()
    for _ in range(args.products):
        blocks.apply(r, z, active)
    ti.sync()
    print(f"B={nb} m={m} w={w} {'product':14s} {1e3 * (time.perf_counter() - t) / max(args.products, 1):9.3f} ms "
          f"{args.precision or ''}")
    want = np.linalg.solve(block, r_h[:m])
    got = z.to_numpy()[:m]
    print(f"first block's product: largest relative error {np.abs(got - want).max() / np.abs(want).max():.2e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
