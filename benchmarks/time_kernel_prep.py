"""Where a process's Taichi kernel preparation goes, kernel by kernel: the frontend, the compiled kernel's lookup or
compilation, and its first launch (the code generation of the cached module and its load).

Usage: ``python benchmarks/time_kernel_prep.py [--cache DIR] [--arch cpu|cuda] [--task folding_u] [--B 4] [--steps 2]
[--emulate-cuda] [--single]``. Runs a lockstep population of ``B`` perturbed reference trajectories of the task
(``sim_core.bench.batch._TaskRun``), ``--steps`` steps, in this process, with Taichi's offline cache in ``DIR``
(an empty directory: a cold cache; the same directory again in a new process: a warm one; default Taichi's
``~/.cache/taichi/ticache``), and ``--single``
one single environment of the task as well. ``--emulate-cuda`` (CPU arch only) makes every arch query answer
"cuda" (``benchmarks/emulated_cuda.py``, after importing the kernel packages): the kernel set of a CUDA generation,
prepared on the CPU arch. ``--populations N`` builds and runs N populations one after the other (a later one
prepares only kernel instances that the first did not).

For every kernel instance prepared (Taichi ``Kernel`` and its template instance) it reports, in CPU seconds of this
process (``time.process_time``: on a shared machine wall seconds measure the neighbours' load; ``--clock wall`` on
an idle one):

- ``frontend``: ``Kernel.materialize`` (the Python AST walk that builds the kernel's IR, and the C++ IR);
- ``lookup``: ``Program.compile_kernel`` (the offline-cache key, a hash of the IR; then the in-memory cache, the
  cache file read and its LLVM IR text parsed, or on a miss the whole compilation: offloading passes, LLVM code
  generation and optimisation) called once before the first launch;
- ``first launch``: the first ``Program.launch_kernel`` of that compiled kernel (the module's registration: on the
  CPU the ORC JIT's code generation, on CUDA LLVM's O3 passes, PTX emission and the driver's module load; plus
  the launch itself), minus the launch time a later call of the same instance takes.

Then the totals, the number of kernel instances and of compiled kernels new to the process (an instance whose compiled
kernel another instance already brought, under its own offline-cache key, paid the frontend again), and the slowest
kernels.
"""

from __future__ import annotations

import argparse
import functools
import sys
import time

from emulated_cuda import add_emulation_flag, answer_cuda, import_kernel_modules, init_arch  # (the script's folder)

_CLOCKS = {"cpu": time.process_time, "wall": time.perf_counter}
"""The clocks of ``--clock``: by default this process's CPU seconds (on a shared machine wall seconds measure the
neighbours)."""


def _instrument(records: dict, later: dict, compiled: dict, clock=time.process_time) -> None:
    """Wrap Taichi's ``Kernel.materialize`` and ``Kernel.launch_kernel``: ``records[id(instance)]`` gathers each
    kernel instance's ``[name, frontend, lookup, first launch, compiled kernel]`` (s), ``later[name]`` its later
    launches' seconds, ``compiled`` every compiled kernel of the process by id (kept alive: Taichi hands out one object
    per compiled kernel, which template instances of one offline-cache key share); seconds of ``clock``."""
    from taichi.lang import impl, kernel_impl

    materialize, launch = kernel_impl.Kernel.materialize, kernel_impl.Kernel.launch_kernel

    def name_of(kernel) -> str:
        return getattr(kernel.func, "__qualname__", "?")

    @functools.wraps(materialize)
    def timed_materialize(self, key=None, args=None, arg_features=None):
        used = key or (self.func, 0, self.autodiff_mode)
        new = used not in self.compiled_kernels
        t = clock()
        materialize(self, key, args, arg_features)
        if new:
            records[id(self.compiled_kernels[used])] = [name_of(self), clock() - t, 0.0, 0.0, None]

    launched: set = set()

    @functools.wraps(launch)
    def timed_launch(self, t_kernel, *args):
        if id(t_kernel) in launched:
            t = clock()
            result = launch(self, t_kernel, *args)
            later.setdefault(name_of(self), []).append(clock() - t)
            return result
        launched.add(id(t_kernel))
        prog = impl.get_runtime().prog
        t0 = clock()
        ckd = prog.compile_kernel(prog.config(), prog.get_device_caps(), t_kernel)  # kept in Taichi's memory cache
        t1 = clock()
        result = launch(self, t_kernel, *args)
        rec = records.setdefault(id(t_kernel), [name_of(self), 0.0, 0.0, 0.0, None])
        rec[2], rec[3] = t1 - t0, clock() - t1
        if id(ckd) not in compiled:
            compiled[id(ckd)] = rec[4] = ckd  # this instance brought a compiled kernel the process did not have
        return result

    kernel_impl.Kernel.materialize, kernel_impl.Kernel.launch_kernel = timed_materialize, timed_launch


def _report(title: str, records: dict, later: dict, wall: float, shown: int = 12) -> None:
    """Print the kernels prepared since the last report, the ``shown`` slowest (and clear them)."""
    rows = []
    for name, frontend, lookup, first, new in records.values():
        times = sorted(later.get(name, [0.0]))
        first = max(first - times[len(times) // 2], 0.0)  # less a later launch's own time
        rows.append((frontend + lookup + first, name, frontend, lookup, first, new is not None))
    n = len(rows)
    tot = [sum(r[k] for r in rows) for k in (2, 3, 4)]
    print(f"--- {title}: {wall:.2f} s; {n} kernel instances of {len({r[1] for r in rows})} kernels, "
          f"{sum(r[5] for r in rows)} new compiled kernels prepared; "
          f"frontend {tot[0]:.2f} s, lookup {tot[1]:.2f} s, first launch {tot[2]:.2f} s; a kernel "
          f"{(sum(tot) / max(n, 1)) * 1e3:.0f} ms ({tot[0] / max(n, 1) * 1e3:.0f} / {tot[1] / max(n, 1) * 1e3:.0f} / "
          f"{tot[2] / max(n, 1) * 1e3:.0f})")
    for total, name, frontend, lookup, first, new in sorted(rows, reverse=True)[:shown]:
        print(f"  {name:60s} {total:7.3f} s  (frontend {frontend:.3f}, lookup {lookup:.3f}, first launch {first:.3f})"
              + ("" if new else "  [compiled kernel already prepared: the frontend again]"))
    sys.stdout.flush()
    records.clear()
    later.clear()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--arch", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--cache", default=None,
                    help="Taichi's offline cache directory (empty: a cold cache; default: Taichi's own)")
    ap.add_argument("--task", default="folding_u")
    ap.add_argument("--B", type=int, default=4)
    ap.add_argument("--steps", type=int, default=2)
    add_emulation_flag(ap)
    ap.add_argument("--linear-solver", default=None,
                    help="the copies' linear solver (SolverConfig.linear_solver; envelope: CUDA's default device solver)")
    ap.add_argument("--populations", type=int, default=1, help="populations built and run one after the other")
    ap.add_argument("--single", action="store_true", help="also one single environment of the task")
    ap.add_argument("--shown", type=int, default=12, help="kernels listed a part, the slowest first")
    ap.add_argument("--clock", choices=tuple(_CLOCKS), default="cpu", help="CPU seconds of this process, or wall")
    args = ap.parse_args()
    clock = _CLOCKS[args.clock]
    t0 = clock()
    init_arch(ap, args, offline_cache_dir=args.cache)
    from sim_core.bench.batch import ARCH_BACKENDS, _TaskRun

    print(f"imports and Taichi init: {clock() - t0:.2f} s")
    if args.emulate_cuda:
        import_kernel_modules()  # (imported before the arch query changes)
    records: dict = {}
    later: dict = {}
    _instrument(records, later, {}, clock)
    backend = ARCH_BACKENDS[args.arch]
    if args.emulate_cuda:
        answer_cuda()
    for k in range(args.populations):
        t = clock()
        run = _TaskRun(args.task, args.B, args.steps, backend, True, linear_solver=args.linear_solver)
        run.run()
        _report(f"population {k + 1}: B = {args.B}, {args.steps} steps" + (" (CUDA paths emulated)" if args.emulate_cuda
                                                                              else ""),
                records, later, clock() - t, args.shown)
        del run
    if args.single:
        from sim_core.tasks.registry import load_task
        from sim_core.tasks.rollout import rollout

        task = load_task(args.task)
        t = clock()
        rollout(task, task.reference_actions[: args.steps], task.true_parameters or None, backend=backend)
        _report(f"single environment, {args.steps} steps", records, later, clock() - t, args.shown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
