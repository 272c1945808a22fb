"""Count the host-device round trips of a single Forming environment's CUDA path, emulated on the CPU arch (or of a
lockstep batch's, ``--B``).

Usage: ``python benchmarks/count_single_syncs.py [--steps 10] [--top 25] [--arch cpu|cuda] [--B 64]``.

``--B`` counts a lockstep batch of ``B`` Forming copies instead (``bench.batch._FormingRun`` with the batched CG, as on
CUDA, or ``--linear-solver envelope``), per Newton iteration, by the Newton loop's phase that asked (the stacked gradient, the line search, the
direction, the step's set-up and finish: the outermost of them on the stack) and by caller; the first step (set-up
included) is not counted.

The arch query of every loaded ``sim_core`` module answers "cuda" (as ``tests/sim_core/ti_kernels/test_device_paths.py``
does; the Taichi program runs on the CPU arch, so the kernels' loops stay serial), the summing kernels' sum arrays
have a GPU's cells (the sums then to round-off), and the Forming trajectory's first ``--steps`` steps are run.
Counted per step (inside the steps only), by the ``sim_core`` function that asked (the innermost one outside the
copy helpers), each of which waits for the kernels queued before it on a real GPU:

- ``download`` / ``upload``: :mod:`sim_core.ti_kernels.device_copy` byte copies (the driver's synchronous copies);
- ``numpy launch``: a kernel launch with a NumPy array argument (Taichi's CUDA launcher copies it to the device and
  back and synchronises);
- ``sum read``: a summing kernel's sum read back (:mod:`sim_core.ti_kernels.launch`; a host array on the CPU arch, a
  device copy on a GPU);
- ``new ndarray``: a device array allocated (Taichi's allocator may synchronise when its cache has no block).

Also printed: planned launches with device arrays only (asynchronous on a GPU) and memsets (asynchronous).
With ``--arch cuda`` (a GPU) nothing is emulated: the same calls are counted and their wall time summed (a copy's
time includes its wait for the kernels queued before it), and the steps' time is printed beside them
(the counting's own time, about 0.1 ms a call, makes the steps slower than the bench's; a call's time excludes it,
but a call made inside another counted call, e.g. a sum read's download, is counted in both).
"""

from __future__ import annotations

import argparse
import collections
import functools
import sys
import time
import traceback


def _caller(skip: tuple[str, ...]) -> str:
    """The innermost ``sim_core`` frame outside the modules ``skip``, as ``module.function``."""
    for frame in reversed(traceback.extract_stack()[:-2]):
        name = frame.filename
        if "sim_core" in name and not any(s in name for s in skip):
            module = name.split("sim_core/")[-1].removesuffix(".py").replace("/", ".")
            return f"{module}.{frame.name}"
    return "?"


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--top", type=int, default=30)
    ap.add_argument("--arch", default="cpu", choices=("cpu", "cuda"))
    ap.add_argument("--B", type=int, default=0, help="count a lockstep batch of B copies (0: one environment)")
    ap.add_argument("--linear-solver", default="pcg", choices=("pcg", "envelope"),
                    help="with --B: the lockstep's device solver (default pcg, the batched CG)")
    args = ap.parse_args()
    from sim_core.ti_backend import init_backend

    init_backend(args.arch)
    import numpy as np

    from emulated_cuda import answer_cuda, gpu_sum_cells  # (benchmarks/, the script's folder)
    from sim_core.bench.forming import run_forming
    from sim_core.ti_kernels import device_copy, launch
    from thinshell_ros.paths import bundled_scene

    counts: collections.Counter = collections.Counter()
    seconds: collections.Counter = collections.Counter()
    enabled = [False]
    phase = ["step"]  # the lockstep phase that asked (--B)
    skip = ("ti_kernels/device_copy", "ti_kernels/transfer", "ti_kernels/buffers", "ti_kernels/launch")

    def timed(kind, call):
        """``call()``, counted (and timed) under ``kind`` and its caller while enabled."""
        if not enabled[0]:
            return call()
        t0 = time.perf_counter()
        try:
            return call()
        finally:
            spent = time.perf_counter() - t0  # (the caller's look-up below is not counted)
            key = (kind, f"{phase[0]:16s} {_caller(skip)}" if args.B else _caller(skip))
            counts[key] += 1
            seconds[key] += spent

    copy = device_copy._copy
    device_copy._copy = lambda array, host, upload, rows=None: timed(
        "upload" if upload else "download", lambda: copy(array, host, upload, rows))
    zero = device_copy.zero
    device_copy.zero = lambda array: timed("memset (async)", lambda: zero(array))
    call = launch.FastKernel.__call__

    def counted_call(self, *a, **k):
        host = any(type(v) is np.ndarray for v in a)
        return timed(f"numpy launch {self.__name__}" if host else "device launch (async)", lambda: call(self, *a, **k))

    launch.FastKernel.__call__ = counted_call
    cells_sum = launch._cells_sum
    launch._cells_sum = lambda array: timed("sum read", lambda: cells_sum(array))
    if args.arch == "cpu":  # a GPU's sum arrays: device arrays of SUM_CELLS cells (the sums to round-off)
        gpu_sum_cells()
    new = device_copy.new_ndarray

    def counted_new(dtype, shape):
        return timed("new ndarray", lambda: new(dtype, shape))

    for module in list(sys.modules.values()):
        if getattr(module, "new_ndarray", None) is new:
            module.new_ndarray = counted_new
    scene = bundled_scene("forming")
    if args.arch == "cpu":  # the emulation: every arch query but the byte copies' answers "cuda"
        if args.B:
            _lockstep_run(1, 2, "cpu").run()  # compile, import
        else:
            run_forming(scene, 2, arch="cpu")  # compile, import
        answer_cuda()
        for module in list(sys.modules.values()):
            if getattr(module, "new_ndarray", None) is new:
                module.new_ndarray = counted_new
    elif args.B:
        _lockstep_run(1, 2, args.arch).run()  # compile, caches
        for module in list(sys.modules.values()):  # (the modules the run imported)
            if getattr(module, "new_ndarray", None) is new:
                module.new_ndarray = counted_new
    else:
        run_forming(scene, args.steps, arch=args.arch)  # compile, caches
    if args.B:
        return _count_lockstep(args, counts, seconds, enabled, phase)
    from sim_core.simulation import Simulation

    step = Simulation.step

    def counted_step(self, *a, **k):  # only the steps counted (not the kernels' compilation before them)
        enabled[0] = True
        try:
            return step(self, *a, **k)
        finally:
            enabled[0] = False

    Simulation.step = counted_step
    result = run_forming(scene, args.steps, arch=args.arch)
    steps = result["steps"]
    wall = result["forward_total_s"]
    print(f"{steps} steps, {result['newton_iters_mean']:.2f} Newton iterations a step, "
          f"{1e3 * wall / steps:.2f} ms a step ({result['steps_per_s']:.2f} steps/s)")
    _print_counts(counts, seconds, steps, "step", args.top)
    return 0


def _lockstep_run(B: int, steps: int, arch: str, linear_solver: str = "pcg"):
    """A lockstep Forming batch of ``B`` copies for ``steps`` steps (``bench.batch._FormingRun``), with the batched CG
    (what a lockstep batch takes on CUDA) on the CPU arch too, or ``linear_solver``."""
    from sim_core.bench.batch import ARCH_BACKENDS, _FormingRun

    return _FormingRun(B, steps, ARCH_BACKENDS[arch], lockstep=True, linear_solver=linear_solver)


def _count_lockstep(args, counts, seconds, enabled: list, phase: list) -> int:
    """``--B``: step a lockstep batch, the first step uncounted, then ``args.steps`` steps counted by phase."""
    from sim_core.batch import lockstep
    from sim_core.batch.line_search import CopyLineSearch
    from sim_core.control import Control
    from sim_core.solver import NewtonSolver

    run = _lockstep_run(args.B, args.steps + 1, args.arch, args.linear_solver)
    for cls, name, label in ((lockstep.LockstepSolver, "_stacked_gradient", "stacked_gradient"),
                             (CopyLineSearch, "_line_search_copies", "line_search"),
                             (lockstep.LockstepSolver, "_direction", "direction"),
                             (NewtonSolver, "_set_up_step", "set_up"), (NewtonSolver, "_finish_step", "finish")):
        def tagged(*a, raw=vars(cls)[name], label=label, **k):
            outer = phase[0]
            phase[0] = label if outer == "step" else outer
            try:
                return raw(*a, **k)
            finally:
                phase[0] = outer

        setattr(cls, name, tagged)
    run.batch.warm_up()
    iterations, wall = 0, 0.0
    for k in range(args.steps + 1):
        enabled[0] = k > 0
        t = time.perf_counter()
        run.batch.step([Control(effector_pose_target={run.effector: tg[k]}) for tg in run.targets])
        enabled[0] = False
        info = run.batch.lockstep.solver.last_stacked_info
        if k > 0:
            iterations += info.iterations
            wall += time.perf_counter() - t
    print(f"B={args.B}: {args.steps} steps, {iterations} Newton iterations, {1e3 * wall / max(iterations, 1):.1f} ms "
          f"an iteration (with the counting)")
    _print_counts(counts, seconds, max(iterations, 1), "Newton iteration", args.top)
    return 0


def _print_counts(counts, seconds, per: int, unit: str, top: int) -> None:
    """The counts and seconds by kind, then by caller, per ``unit`` (``per`` of them)."""
    steps = per
    kinds, kind_s = collections.Counter(), collections.Counter()
    for (kind, _), n in counts.items():
        short = kind.split(" ")[0] if kind.startswith("numpy launch") else kind
        kinds[short] += n
        kind_s[short] += seconds[(kind, _)]
    for kind, n in sorted(kinds.items()):
        print(f"{kind:28s} {n / steps:8.1f} a {unit} {1e3 * kind_s[kind] / steps:8.3f} ms a {unit}")
    syncs = sum(n for kind, n in kinds.items() if kind in ("download", "upload", "numpy"))  # (a sum read: a download)
    print(f"{'round trips (sync)':28s} {syncs / steps:8.1f} a {unit}")
    print(f"by caller (a {unit}: calls, ms):")
    for (kind, where), n in counts.most_common(top):
        print(f"  {n / steps:6.1f} {1e3 * seconds[(kind, where)] / steps:7.3f}  {kind:34s} {where}")


if __name__ == "__main__":
    raise SystemExit(main())
