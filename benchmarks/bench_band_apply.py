"""Time the batched CG's band-block product ``z = S^-1 r`` (sim_core.ti_kernels.band_cholesky) on its own, at a
lockstep batch's sizes, against variants of the same pass.

Usage: ``python benchmarks/bench_band_apply.py --arch cuda --B 1024 --m 384 --repeat 30``. Prints ms a pass and
the bytes of the inverse read a second for: the module's pass (float64, one thread a row), the same with the
column loop unrolled by 4, and float32 storage of the inverse (float64 sums), with and without the unrolling.
"""

import argparse
import time

import numpy as np


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--arch", default="cpu")
    ap.add_argument("--B", type=int, default=64)
    ap.add_argument("--m", type=int, default=384)
    ap.add_argument("--repeat", type=int, default=20)
    args = ap.parse_args()
    from sim_core.ti_backend import init_backend, ti

    init_backend(args.arch)
    from sim_core.ti_kernels import band_cholesky as bc
    from sim_core.ti_kernels import device_copy

    nb, m = args.B, args.m
    f64 = ti.types.ndarray(dtype=ti.f64, ndim=1)
    f32 = ti.types.ndarray(dtype=ti.f32, ndim=1)
    i32 = ti.types.ndarray(dtype=ti.i32, ndim=1)

    @ti.kernel
    def fill(x: f64, y: f32, count: ti.i32):
        for k in range(count):
            x[k] = ti.sin(0.001 * k)
            y[k] = ti.cast(x[k], ti.f32)

    @ti.kernel
    def product(inverse: ti.types.ndarray(ndim=1), band_dof: i32, r: f64, z: f64, nb: ti.i32, m: ti.i32,
                unroll: ti.template()):
        """The module's pass with ``unroll`` columns an iteration (independent sums) and any storage type."""
        for b, i in ti.ndrange(nb, m):
            g = band_dof[b * m + i]
            if g >= 0:
                acc = ti.Vector.zero(ti.f64, unroll)
                for q in range(m // unroll):
                    for u in ti.static(range(unroll)):
                        c = unroll * q + u
                        acc[u] += ti.cast(inverse[(b * m + c) * m + i], ti.f64) * r[ti.max(band_dof[b * m + c], 0)]
                z[g] = acc.sum()

    inv64 = device_copy.new_ndarray(ti.f64, (nb * m * m,))
    inv32 = device_copy.new_ndarray(ti.f32, (nb * m * m,))
    fill(inv64, inv32, nb * m * m)
    dof = device_copy.new_ndarray(ti.i32, (nb * m,))
    dof.from_numpy(np.arange(nb * m, dtype=np.int32))
    ones = device_copy.new_ndarray(ti.i32, (nb,))
    ones.from_numpy(np.ones(nb, dtype=np.int32))
    r = device_copy.new_ndarray(ti.f64, (nb * m,))
    r.from_numpy(np.random.default_rng(0).normal(size=nb * m))
    z = device_copy.new_ndarray(ti.f64, (nb * m,))

    runs = {"module (f64)": lambda: bc._apply(inv64, ones, dof, ones, ones, r, z, nb, m),
            "unrolled 4 (f64)": lambda: product(inv64, dof, r, z, nb, m, 4),
            "plain (f32 storage)": lambda: product(inv32, dof, r, z, nb, m, 1),
            "unrolled 4 (f32 storage)": lambda: product(inv32, dof, r, z, nb, m, 4)}
    for name, run in runs.items():
        run()
        ti.sync()
        t = time.perf_counter()
        for _ in range(args.repeat):
            run()
        ti.sync()
        ms = 1e3 * (time.perf_counter() - t) / args.repeat
        size = 8 if "f64" in name else 4
        print(f"B={nb} m={m} {name:26s} {ms:8.3f} ms a pass, {nb * m * m * size / ms / 1e6:8.1f} GB/s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
