"""Time the lockstep's gradient terms at a Forming iterate: the host path against the device path (DeviceGradient).

Usage: ``python benchmarks/device_gradient_terms.py --arch cuda --B 256 1024 [--repeat 5] [--kernel-profiler]``.

For each ``B``: builds ``B`` Forming copies, takes two lockstep steps (compilation, contacts), sets up the third
step (as ``benchmarks/parts_lockstep.py``) and times, at new positions each repetition (a fresh evaluation; median
of ``--repeat``, in ms):

- **host**: each Newton-loop term's gradient as :func:`sim_core.batch.iterates.summed_gradient` takes it (the fused
  elastic terms' ``gradient``, the friction's ``gradient_rows``), added into an ``(N, 3)`` host sum;
- **device** (where the code has :class:`~sim_core.energies.base.DeviceGradient`): ``add_gradient_on_device`` at
  device positions into a device array, until the device is idle (``ti.sync``);
- on a GPU, the fused elastic terms' device evaluation split into the host's launches (the fills, the parts' kernels
  in their :class:`~sim_core.ti_kernels.launch.DeferredSums` block), the wait for their energy sums (the first read
  waits for the kernels), the gradient's add and the final synchronisation; each part's kernel alone and its
  energy-only kernel, until the device is idle; and a loop of 250,000 / 1,000,000 terms summed into one cell against
  1024 (the cost of same-address atomic additions).

``--kernel-profiler``: Taichi's per-task device times of the device path's launches (CUDA).
"""

# No ``from __future__ import annotations`` here: Taichi reads the kernel annotations of _atomic_sums as objects.

import argparse
import sys
import time

import numpy as np

from parts_lockstep import _median_ms as median_ms, third_step  # (benchmarks/, the script's folder)


def _median_ms(fn, repeat: int) -> float:
    """:func:`parts_lockstep._median_ms` after one call (compilation, warm-up)."""
    fn()
    return median_ms(fn, repeat)


def _fused_split(fused, x: np.ndarray, xd, gd, repeat: int) -> dict:
    """The fused device evaluation's parts (module docstring), ms, medians over ``repeat`` fresh evaluations; then
    each part's kernel alone until the device is idle (``part <name>``)."""
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels.launch import DeferredSums
    from sim_core.ti_kernels.transfer import fill
    try:
        from sim_core.ti_kernels.transfer import add_into
    except ImportError:  # a tree without it (the baseline): the device gradient's add not timed
        add_into = None

    _, gdev, vdev = fused._device_buffers(x.shape, fused.pattern.keys.size)
    times: dict[str, list] = {"launches": [], "sums read (waits for the kernels)": [], "gradient added": [],
                              "sync": []}
    counts = {}
    for k in range(repeat + 1):
        ti.sync()
        t0 = time.perf_counter()
        fill(gdev, 0.0)
        fill(vdev, 0.0)
        sums = fused._sums = fused._sums or DeferredSums()
        with sums:
            for part in fused._parts:
                part.evaluate(xd, gdev, vdev)
        t1 = time.perf_counter()
        sum(sums.values())
        t2 = time.perf_counter()
        if add_into is not None:
            add_into(gd, gdev)
        t3 = time.perf_counter()
        ti.sync()
        t4 = time.perf_counter()
        counts = {"summing kernels": sums.launches, "parts": len(fused._parts)}
        if k:
            for name, (a, b) in zip(times, ((t0, t1), (t1, t2), (t2, t3), (t3, t4))):
                times[name].append(1e3 * (b - a))
    for part in fused._parts:
        def alone(part=part):
            part.evaluate(xd, gdev, vdev)
            ti.sync()

        times[f"part {type(part).__name__} ({part.element_count} elements)"] = [_median_ms(alone, repeat)]
        times[f"energy only {type(part).__name__}"] = [_median_ms(lambda part=part: (part.energy(xd), ti.sync()),
                                                                  repeat)]
    fused._kept = None
    return {**{name: float(np.median(v)) for name, v in times.items()}, **counts}


def _atomic_sums(n: int, repeat: int) -> dict:
    """ms of a parallel loop over ``n`` float64 entries adding ``x[k]^2`` into one cell (``energy[0]``) against
    ``k % cells`` of 1024 cells, until the device is idle: the cost of same-address atomic additions."""
    from sim_core.ti_backend import ti
    from sim_core.ti_kernels.device_copy import new_ndarray
    from sim_core.ti_kernels.launch import fast_kernel
    from sim_core.ti_kernels.transfer import upload

    F64_1 = ti.types.ndarray(dtype=ti.f64, ndim=1)

    @fast_kernel
    def spread_sum(x: F64_1, energy: F64_1):
        for k in range(x.shape[0]):
            energy[k % energy.shape[0]] += x[k] * x[k]

    x = upload(new_ndarray(ti.f64, (n,)), np.random.default_rng(0).normal(size=n))
    out = {}
    for cells in (1, 1024):
        energy = new_ndarray(ti.f64, (cells,))
        out[f"{n} terms into {cells} cell(s)"] = _median_ms(lambda: (spread_sum(x, energy), ti.sync()), repeat)
    return out


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--arch", default="cpu")
    ap.add_argument("--B", type=int, nargs="+", default=[4])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--kernel-profiler", action="store_true")
    args = ap.parse_args()
    from sim_core.batch.iterates import frozen
    from sim_core.energies.base import DeviceGradient, SparseGradient, declares
    from sim_core.ti_backend import init_backend, ti
    from sim_core.ti_kernels.device_copy import new_ndarray
    from sim_core.ti_kernels.transfer import upload

    init_backend(args.arch, kernel_profiler=args.kernel_profiler)
    for B in args.B:
        solver, step, x = third_step(B, args.arch)
        N = x.shape[0]
        shift = iter(np.arange(1, 10 ** 6) * 1e-13)  # new positions each call: no kept evaluation is reused

        def moved():
            return frozen(x + next(shift))

        total = np.zeros_like(x)
        gd = new_ndarray(ti.f64, x.shape)
        rows = []
        for term in step.loop_terms:
            name = type(term).__name__
            if declares(term, SparseGradient):
                def host(term=term):
                    v, r = term.gradient_rows(moved())
                    if v is None:
                        total.__iadd__(r)
                    else:
                        total[v] += r
            else:
                def host(term=term):
                    total.__iadd__(term.gradient(moved()))
            rows.append((f"host   {name}", _median_ms(host, args.repeat)))
            if declares(term, DeviceGradient):
                ys = [moved() for _ in range(args.repeat + 1)]
                pairs = [(y, upload(new_ndarray(ti.f64, x.shape), y)) for y in ys]
                it = iter(pairs)

                def device(term=term, it=it):
                    y, yd = next(it)
                    term.add_gradient_on_device(y, yd, gd)
                    ti.sync()

                if args.kernel_profiler:
                    ti.profiler.clear_kernel_profiler_info()
                rows.append((f"device {name}", _median_ms(device, args.repeat)))
                if args.kernel_profiler:
                    print(f"--- B={B} kernel profile of device {name} ({args.repeat + 1} calls)")
                    ti.profiler.print_kernel_profiler_info("count")
        print(f"B={B} arch={args.arch} vertices={N} pairs(friction)="
              f"{sum(t.vertices.shape[0] for t in step.loop_terms if type(t).__name__ == 'TiLaggedFriction')}")
        for name, ms in rows:
            print(f"  {name:50s} {ms:9.3f} ms")
        fused = step.fused
        if fused is not None and fused._on_device():
            y = moved()
            split = _fused_split(fused, y, upload(new_ndarray(ti.f64, x.shape), y), gd, args.repeat)
            for k, v in split.items():
                print(f"  fused device evaluation: {k:60s} " + (f"{v:9.3f} ms" if isinstance(v, float) else f"{v}"))
    if args.arch != "cpu":
        for n in (250_000, 1_000_000):
            for k, v in _atomic_sums(n, args.repeat).items():
                print(f"  atomic sums: {k:40s} {v:9.3f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
