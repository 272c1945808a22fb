"""Profile one Forming environment (``thinshell bench forming``'s trajectory): where a step's wall time goes.

Usage: ``python benchmarks/profile_single.py --arch cuda [--steps 49] [--kernel-profiler]``.

Runs the trajectory once (kernels compiled or loaded, untimed), then again with the parts wrapped in
wall-clock timers. A part's time is counted only where no other timed part encloses it (the outermost
timed call wins), so the parts add up to at most the steps' wall time; the rest is Python and NumPy
of the Newton loop. Parts:

- ``kernel launch``: Taichi kernel calls (:class:`sim_core.ti_kernels.launch.FastKernel` and Taichi's
  own ``Kernel.__call__``): on CUDA the device time plus, per NumPy array argument, a device buffer,
  its copy to the device, a synchronisation and the copy back (Taichi's CUDA launcher does this for
  every host array, read or written);
- ``ndarray transfer``: ``from_numpy`` / ``to_numpy`` of Taichi ndarrays, and the byte copies and zero fills
  (memset) of :mod:`sim_core.ti_kernels.device_copy`;
- ``linear solve``: the symmetric solver's ``factorize`` / ``solve`` and the general LU's.

With ``--launch-costs``: the host time of planned launches of one and ten ndarray arguments and of one and three
loops, of a launch context with its arguments set, of Taichi's launch call, of a download, a memset and an allocation
(on CUDA then again with the device's default memory pool keeping freed memory).

With ``--phases`` the trajectory runs once more with inclusive wall-clock timers (each call timed whole, nested
ones too) on the Newton loop's parts (``NewtonSolver._gradient``, ``_newton_direction``, ``_line_search``, ...), the
linear solver, the fused elastic terms, the contact set, the pair batch and pair terms, the friction, the device
copies and the kernel launches: calls a step, ms a step and us a call of each, to set the CUDA and CPU paths side by
side (docs/benchmarks_log.md, session 45, 28single).

Also printed: kernel calls and NumPy array arguments per step; with ``--kernel-profiler`` Taichi's
per-kernel device time (it synchronises every launch: the timed run is then slower than the bench's);
a launch micro-benchmark (one kernel, one array of 5,094 float64 passed as a NumPy array vs as a
Taichi ndarray, us per launch) and a transfer micro-benchmark (that array to and from a Taichi ndarray by
:mod:`sim_core.ti_kernels.device_copy`'s byte copies and by a planned copy kernel, us per copy).
"""

# no `from __future__ import annotations`: the micro-benchmark's Taichi kernel needs evaluated annotations
import argparse
import functools
import time


class _Parts:
    """Outermost-wins wall-clock accumulators: name -> [calls, seconds]; with ``inclusive`` every call is timed
    whole, nested ones too (``--phases``)."""

    def __init__(self, inclusive: bool = False) -> None:
        self.totals: dict[str, list] = {}
        self.depth = 0
        self.arrays = 0
        self.inclusive = inclusive

    def wrap(self, owner, attribute: str, name: str, count_arrays: bool = False) -> None:
        original = getattr(owner, attribute)
        record = self.totals.setdefault(name, [0, 0.0])
        parts = self

        @functools.wraps(original)
        def timed(*args, **kwargs):
            if parts.depth and not parts.inclusive:
                return original(*args, **kwargs)
            if count_arrays:
                import numpy as np

                parts.arrays += sum(type(a) is np.ndarray for a in args)
            parts.depth += 1
            t0 = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                record[1] += time.perf_counter() - t0
                record[0] += 1
                parts.depth -= 1

        setattr(owner, attribute, timed)

    def reset(self) -> None:
        for record in self.totals.values():
            record[0], record[1] = 0, 0.0
        self.arrays = 0


def _launch_costs(ti, repeats: int = 1000) -> None:
    """Host time of planned launches by argument and loop count, of their parts (a launch context and its
    arguments, Taichi's launch), of a download, a memset and an allocation; on CUDA again with the device's
    default memory pool keeping freed memory (Taichi's CUDA launcher allocates and frees a result and an argument
    buffer at every launch from that pool)."""
    import ctypes

    import numpy as np

    from sim_core.ti_backend import current_arch
    from sim_core.ti_kernels import device_copy
    from sim_core.ti_kernels.launch import fast_kernel

    a1 = ti.types.ndarray(dtype=ti.f64, ndim=1)

    def one(a0: a1, s: ti.f64, n: ti.i32):
        for i in range(n):
            a0[i] += s

    def three_loops(a0: a1, s: ti.f64, n: ti.i32):
        for i in range(n):
            a0[i] += s
        for i in range(n):
            a0[i] += s
        for i in range(n):
            a0[i] += s

    def ten(a0: a1, b1: a1, b2: a1, b3: a1, b4: a1, b5: a1, b6: a1, b7: a1, b8: a1, b9: a1, s: ti.f64, n: ti.i32):
        for i in range(n):
            a0[i] += s * (b1[i] + b2[i] + b3[i] + b4[i] + b5[i] + b6[i] + b7[i] + b8[i] + b9[i])

    k1, k3, k10 = fast_kernel(one), fast_kernel(three_loops), fast_kernel(ten)
    arrays = [device_copy.new_ndarray(ti.f64, (5094,)) for _ in range(10)]
    host = np.zeros(5094)
    for _ in range(2):  # Taichi's own call, then the plan's first launch (which compiles the plan)
        k10(*arrays, 1.0, 16)
    plan = k10._last_plan
    prog = ti.lang.impl.get_runtime().prog

    def context():
        ctx = plan.t_kernel.make_launch_context()
        for i, a in enumerate(arrays):
            ctx.set_arg_ndarray((i,), a.arr)
        ctx.set_arg_float((10,), 1.0)
        ctx.set_arg_int((11,), 16)
        return ctx

    cases = (("1 ndarray, 1 loop", lambda: k1(arrays[0], 1.0, 16)),
             ("1 ndarray, 3 loops", lambda: k3(arrays[0], 1.0, 16)),
             ("10 ndarrays, 1 loop", lambda: k10(*arrays, 1.0, 16)),
             ("10 ndarrays: launch context and arguments only", context),
             ("10 ndarrays: context, arguments, Program.launch_kernel", lambda: prog.launch_kernel(plan.compiled,
                                                                                                  context())),
             ("10 ndarrays, then a download of 5,094 float64", lambda: (k10(*arrays, 1.0, 16),
                                                                     device_copy.to_host(host, arrays[0]))),
             ("10 ndarrays, then ti.sync() (where a memory pool releases freed memory)",
              lambda: (k10(*arrays, 1.0, 16), ti.sync())),
             ("download of 5,094 float64", lambda: device_copy.to_host(host, arrays[0])),
             ("memset of 5,094 float64", lambda: device_copy.zero(arrays[1])),
             ("new_ndarray of 5,094 float64 (and its release)", lambda: device_copy.new_ndarray(ti.f64, (5094,))))

    def run(prefix: str) -> None:
        for label, call in cases:
            call()
            ti.sync()
            t0 = time.perf_counter()
            for _ in range(repeats):
                call()
            t1 = time.perf_counter()
            ti.sync()
            print(f"launch costs{prefix}, {label}: {1e6 * (t1 - t0) / repeats:.1f} us a call "
                  f"(then {1e6 * (time.perf_counter() - t1):.0f} us to synchronise)")

    run("")
    lib = device_copy._driver() if current_arch() == "cuda" else None
    if lib is None or not hasattr(lib, "cuDeviceGetDefaultMemPool"):  # (a driver before CUDA 11.2 has no pools)
        return
    device, pool, threshold = ctypes.c_int(), ctypes.c_void_p(), ctypes.c_uint64()
    attribute = 4  # CU_MEMPOOL_ATTR_RELEASE_THRESHOLD
    codes = (lib.cuCtxGetDevice(ctypes.byref(device)), lib.cuDeviceGetDefaultMemPool(ctypes.byref(pool), device),
             lib.cuMemPoolGetAttribute(pool, attribute, ctypes.byref(threshold)))
    print(f"launch costs: default memory pool release threshold {threshold.value} bytes (driver codes {codes})")
    threshold.value = 2 ** 63
    if lib.cuMemPoolSetAttribute(pool, attribute, ctypes.byref(threshold)) == 0:
        run(" (pool keeping freed memory)")


def _phase_timers() -> dict[str, list]:
    """Wrap the parts ``--phases`` times with inclusive timers; name -> [calls, seconds], zeroed."""
    from taichi.lang import kernel_impl

    from sim_core import contact_set, fused_elastic, linsolve, solver
    from sim_core.energies.contact import batch_kernel, reference
    from sim_core.energies.friction import kernel as friction_kernel
    from sim_core.ti_kernels import device_copy, launch

    parts = _Parts(inclusive=True)
    targets = [(solver.NewtonSolver, ("_set_up_step", "_gradient", "_assemble_hessian", "_newton_direction", "_energy",
                                      "_line_search", "_finish_step", "_simplified_correction"), "solver"),
               (fused_elastic.FusedElastic, ("evaluate", "energy", "gradient", "hessian_values",
                                             "projected_hessian_values"), "fused"),
               (contact_set.ContactSet, ("covers", "potentials", "friction", "end_step"), "contact_set"),
               (batch_kernel.PairBatch, ("evaluate",), "PairBatch"),
               (reference._PairPenalty, ("keep_derivatives", "energy", "gradient", "hessian"), "pairs"),
               (friction_kernel.TiLaggedFriction, ("_launch", "keep_derivatives", "energy", "gradient", "hessian"),
                "friction"),
               (device_copy, ("to_device", "to_host", "zero", "new_ndarray"), "device_copy"),
               (launch.FastKernel, ("__call__",), "FastKernel"), (kernel_impl.Kernel, ("__call__",), "ti.Kernel")]
    for cls in (linsolve.PardisoCholesky, linsolve.ScipySymmetric, linsolve.PardisoSolver, linsolve.ScipySolver):
        targets.append((cls, ("factorize", "solve"), cls.__name__))
    for owner, attributes, label in targets:
        for attribute in attributes:
            parts.wrap(owner, attribute, f"{label}.{attribute}")
    return parts.totals


def _print_phases(totals: dict[str, list], result: dict) -> None:
    """The inclusive timers of one run, most time first."""
    steps = result["steps"]
    print(f"phases (inclusive): {result['steps_per_s']:.2f} steps/s, "
          f"{1e3 * result['forward_total_s'] / steps:.2f} ms/step, {result['newton_iters_mean']:.4f} Newton "
          f"iterations a step")
    print(f"{'part':44s} {'calls/step':>10s} {'ms/step':>8s} {'us/call':>8s}")
    for name, (calls, seconds) in sorted(totals.items(), key=lambda kv: -kv[1][1]):
        if calls:
            print(f"{name:44s} {calls / steps:10.2f} {1e3 * seconds / steps:8.3f} {1e6 * seconds / calls:8.1f}")


def _launch_microbenchmark(ti, repeats: int = 500) -> None:
    import numpy as np

    from sim_core.ti_kernels.launch import fast_kernel

    def scale(a: ti.types.ndarray(dtype=ti.f64, ndim=1), s: ti.f64):
        for i in range(a.shape[0]):
            a[i] = a[i] * s

    host = np.ones(5094)
    device = ti.ndarray(dtype=ti.f64, shape=host.shape)
    planned = fast_kernel(scale)
    for label, kernel, arg in (("NumPy array (fast_kernel)", planned, host),
                               ("Taichi ndarray (Taichi's call)", ti.kernel(scale), device)):
        kernel(arg, 1.0)
        kernel(arg, 1.0)
        ti.sync()
        t0 = time.perf_counter()
        for _ in range(repeats):
            kernel(arg, 1.0)
        ti.sync()
        print(f"launch micro-benchmark, one {label} argument: {1e6 * (time.perf_counter() - t0) / repeats:.1f} us")
    from sim_core.ti_kernels import device_copy, transfer

    copies = (("upload, byte copy (device_copy.to_device)", lambda: device_copy.to_device(device, host)),
              ("download, byte copy (device_copy.to_host)", lambda: device_copy.to_host(host, device)),
              ("upload, planned copy kernel", lambda: transfer._copy_f64(host, device)),
              ("download, planned copy kernel", lambda: transfer._copy_f64(device, host)))
    for label, copy in copies:
        made = copy()
        t0 = time.perf_counter()
        for _ in range(repeats):
            copy()
        print(f"transfer micro-benchmark, 5,094 float64, {label}: {1e6 * (time.perf_counter() - t0) / repeats:.1f} us"
              + ("" if made is not False else " (declined: no byte copy on this thread)"))


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--arch", default="cpu")
    ap.add_argument("--steps", type=int, default=49)
    ap.add_argument("--kernel-profiler", action="store_true")
    ap.add_argument("--cprofile", type=int, default=0, metavar="N",
                    help="run the trajectory a third time under cProfile; print its N functions of most own time")
    ap.add_argument("--launch-costs", action="store_true",
                    help="time planned launches, their parts, copies, memsets and allocations (and on CUDA with the "
                         "default memory pool keeping freed memory) after the runs")
    ap.add_argument("--phases", action="store_true",
                    help="run the trajectory once more with inclusive timers of the solver's parts (module docstring)")
    args = ap.parse_args()
    from sim_core.ti_backend import init_backend, ti

    init_backend(args.arch, kernel_profiler=args.kernel_profiler)
    from taichi.lang import _ndarray, kernel_impl

    from sim_core import linsolve
    from sim_core.bench.forming import run_forming
    from sim_core.ti_kernels import device_copy, launch
    from thinshell_ros.paths import bundled_scene

    scene = bundled_scene("forming")
    t0 = time.perf_counter()
    first = run_forming(scene, args.steps, arch=args.arch)
    print(f"untimed run: {time.perf_counter() - t0:.1f} s, {first['steps_per_s']:.2f} steps/s, "
          f"jit {first['jit_s']:.1f} s, linear solver {first['linear_solver']}, backend {first['backend']}")
    parts = _Parts()
    parts.wrap(launch.FastKernel, "__call__", "kernel launch", count_arrays=True)
    parts.wrap(kernel_impl.Kernel, "__call__", "kernel launch", count_arrays=True)
    for method in ("_ndarray_from_numpy", "_ndarray_to_numpy", "_ndarray_matrix_from_numpy",
                   "_ndarray_matrix_to_numpy"):
        parts.wrap(_ndarray.Ndarray, method, "ndarray transfer")
    for function in ("to_device", "to_host", "zero"):
        parts.wrap(device_copy, function, "ndarray transfer")
    for cls in (linsolve.PardisoCholesky, linsolve.ScipySymmetric, linsolve.PardisoSolver, linsolve.ScipySolver):
        for method in ("factorize", "solve"):
            parts.wrap(cls, method, "linear solve")
    parts.reset()
    if args.kernel_profiler:
        ti.profiler.clear_kernel_profiler_info()
    result = run_forming(scene, args.steps, arch=args.arch)
    wall = result["forward_total_s"]
    steps = result["steps"]
    print(f"timed run: {result['steps_per_s']:.2f} steps/s ({1e3 * wall / steps:.1f} ms/step), "
          f"{result['newton_iters_mean']:.2f} Newton iterations and {result['factorizations_mean']:.2f} "
          f"factorisations per step")
    counted = 0.0
    print(f"{'part (ms per step)':24s} {'calls/step':>10s} {'ms/step':>8s} {'% wall':>7s}")
    for name, (calls, total) in parts.totals.items():
        counted += total
        print(f"{name:24s} {calls / steps:10.1f} {1e3 * total / steps:8.2f} {100 * total / wall:7.1f}")
    rest = wall - counted
    print(f"{'rest (Python, NumPy)':24s} {'':10s} {1e3 * rest / steps:8.2f} {100 * rest / wall:7.1f}")
    print(f"NumPy array arguments of kernel calls per step: {parts.arrays / steps:.1f}")
    if args.kernel_profiler:
        device = ti.profiler.get_kernel_profiler_total_time()
        print(f"kernel device time (Taichi kernel profiler): {1e3 * device / steps:.2f} ms/step")
        ti.profiler.print_kernel_profiler_info("count")
    _launch_microbenchmark(ti)
    if args.launch_costs:
        _launch_costs(ti)
    if args.phases:
        totals = _phase_timers()
        _print_phases(totals, run_forming(scene, args.steps, arch=args.arch))
    if args.cprofile:
        import cProfile
        import pstats

        profiler = cProfile.Profile()
        profiler.runcall(run_forming, scene, args.steps, arch=args.arch)
        pstats.Stats(profiler).sort_stats("tottime").print_stats(args.cprofile)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
