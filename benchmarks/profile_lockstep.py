"""Profile a lockstep batch of the Forming scene or of a task's population: where the wall time of a Newton
iteration and of a step goes.

Usage: ``python benchmarks/profile_lockstep.py --arch cuda --B 256 --steps 4 [--linear-solver pcg] [--task
folding_u]``; ``--arch cpu --emulate-cuda`` runs the CUDA paths on the CPU arch (every ``sim_core`` arch query
answering "cuda", :mod:`emulated_cuda`). ``--task NAME`` profiles the task's population of ``thinshell bench batch
--scene NAME`` (``_TaskRun``: perturbed reference actions, stepped by
:class:`~sim_core.tasks.rollout.PopulationRollout` as the optimiser steps it, without a separate warm-up) and times
its build by part too (the episodes' scenes, the stacking, the lockstep solver), and the population's host work
around each batched step (its episodes' commands and early-stop checks), and per step the copies' own Newton
iterations beside the lockstep's (a lockstep step runs as many as its slowest copy); ``--B 16,64,256`` profiles each
size in turn in one process (kernels compiled once), each part also per Newton iteration (ms), so that what grows
with ``B`` shows by part.

Compiles the kernels on one copy first (as ``thinshell bench batch``: two steps and the projected Hessian's
kernels), builds ``B`` copies (``sim_core.bench.batch._FormingRun``), sets up and steps once (timed by part), then
times ``--steps`` more steps (``--kernel-profiler``: with Taichi's per-task device times): per step its wall time,
Newton iterations, CG iterations and assembly / solve times, and over all of them the inclusive wall time and calls
of the solver's parts (wrapped with timers: the gradient with its contact search, the Newton matrix, the CG's set-up
and solve, the line search and its energies, the step's set-up and finish) and the CG's iterations per solve.

Forming: each step's wall time is also split into exclusive phases that add up to it (``_StepPhases``): the Newton
iterations (the stacked gradient, the line search, the factorisation, the CG, the projected retries' elastic
Hessian and pair blocks, the rest), the step's set-up (boundary, the contact set's ``begin_step`` and
``friction``, the rest), its finish (the contact potentials, the energy, the contact force, ``end_step``, the
plastic update, the rest), the engine's and the batch's work around the solver (``_sync``, ``stack_controls``,
``copy_states``, the per-copy write-back), the run loop's controls and the garbage collector; per step and as a
mean, with the steady rate that ``thinshell bench batch`` reports for the same steps (``--steps 4``: its steady steps
of ``--steps 5``). ``--copy-sites`` adds, for each phase, its synchronous copies by call site (each copy's direction and
its innermost ``sim_core`` frames, a copy a step and MB a step), which shows which copies carry whole arrays.
``--account`` (Forming) gives a steady step's account (issue 52 item 1, docs/gpu_roofline.md): finer phases (the fused
elastic kernels' gradient and Hessian values, the pair batch, the friction's gradient, the envelope's gather and
factorisation and its substitution, the trial positions, the per-copy scalars' reads, the per-copy energies, the
candidate lists) with the kernel launches each made, and after the steps of each size it names (``--account 1024``)
a new batch of that size stepped again with the device synchronised at every phase change (``ti.sync``), so that
each phase is charged the device work it queued rather than the phase that next waits (that pass's rate is not the
bench's: the synchronisations serialise host and device). ``--schedules dots,panels,...`` (one for each entry of
``--B``; a size may repeat) sets the envelope Cholesky's schedule on CUDA (``envelope_cholesky.CUDA_SCHEDULE``, and
``SCHEDULE`` for the CPU arch) before each entry's batch is built, so that schedules are compared in one process, each
(size, schedule) accounted once; ``panels:rows``, ``panels:vertices`` set the substitution of ``"dots"`` /
``"panels"`` too (``envelope_cholesky.SUBSTITUTION``). ``--edge-edge-rows rows,takes,...`` (one for each entry of
``--B``) reads the contact set's edge-edge potential's pairs and sides by rows (``ListRows``) or takes every kept row on
the host at each step's set-up (``contact_set.ListRows`` replaced by ``np.take``), set before each entry's batch is
built. ``--simplified-compare every,whole,...`` (one for each entry of ``--B``): the device solvers' simplified Newton
test compares the copies' touching contacts only where every open copy is ready and only until one open copy differs
(``every``), or every ready copy's at every iterate (``whole``: ``SimplifiedNewtonTest.candidates`` without its
``every``; the same tests made). After each size a memory line: this process's GPU memory (``nvidia-smi``, as
``thinshell bench batch``'s ``gpu_mib_per_copy``) and resident host memory after its steps, their growth over the size
and per copy, and the GPU memory free. ``--cprofile`` adds cProfile's tables (incomplete on Python 3.12 with Taichi's
compiler in the profiled region).
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import time

from emulated_cuda import add_emulation_flag, init_arch  # (benchmarks/, the script's folder)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--arch", default="cpu")
    ap.add_argument("--B", default="8", help="copies; a comma-separated list profiles each size in turn")
    ap.add_argument("--steps", type=int, default=4,
                    help="timed steps after the first (default 4: the steady steps of thinshell bench batch --steps 5)")
    ap.add_argument("--linear-solver", default=None)
    ap.add_argument("--top", type=int, default=45)
    ap.add_argument("--task", default=None, help="a task name: profile its population (default: Forming)")
    ap.add_argument("--out", default=None, help="write the pstats file here")
    ap.add_argument("--cprofile", action="store_true")
    ap.add_argument("--copy-sites", type=int, default=0, metavar="FRAMES",
                    help="Forming: each phase's synchronous copies by call site (this many sim_core frames)")
    ap.add_argument("--account", default=None, metavar="SIZES",
                    help="Forming: the step's account (issue 52 item 1): finer phases (the element kernels, the pair "
                         "batch, the friction, the envelope's gather and factorisation, its substitution, the trial "
                         "points, the per-copy scalars, the energies) and the kernel launches by phase; after the "
                         "steps of each size in SIZES (comma-separated, among --B), a new batch of that size stepped "
                         "again with the device synchronised at every phase change, so that each phase is charged its "
                         "own device work")
    ap.add_argument("--schedules", default=None, metavar="NAMES",
                    help="Forming: the envelope Cholesky's schedule on CUDA for each entry of --B in turn "
                         "(comma-separated, e.g. dots,panels: envelope_cholesky.CUDA_SCHEDULE, and SCHEDULE for the CPU "
                         "arch, set before the entry's batch is built), so that schedules are compared in one process; with --account a size is "
                         "accounted once per schedule; dots:rows, panels:vertices, ... set the substitution too "
                         "(envelope_cholesky.SUBSTITUTION)")
    ap.add_argument("--edge-edge-rows", default=None, metavar="NAMES",
                    help="Forming: for each entry of --B in turn (comma-separated) 'rows' (the contact set's "
                         "edge-edge potential's pairs and sides as ListRows, read by rows) or 'takes' (the host's "
                         "np.take of every kept row at each step's set-up: contact_set.ListRows replaced), set before "
                         "the entry's batch is built, so that both are compared in one process; with --account a size "
                         "is accounted once per name")
    ap.add_argument("--simplified-compare", default=None, metavar="NAMES",
                    help="Forming: for each entry of --B in turn (comma-separated) 'every' (the device solvers' "
                         "simplified Newton test compares the copies' touching contacts only where every open copy is "
                         "ready, and only until one open copy differs) or 'whole' (every ready copy's contacts "
                         "compared at every iterate: SimplifiedNewtonTest.candidates without its 'every'), set before "
                         "the entry's batch is built, so that both are compared in one process")
    ap.add_argument("--kernel-profiler", action="store_true",
                    help="print the device time of each Taichi kernel task over the timed steps")
    add_emulation_flag(ap)
    args = ap.parse_args()
    init_arch(ap, args, kernel_profiler=args.kernel_profiler)
    from sim_core.bench.batch import ARCH_BACKENDS, _FormingRun, _TaskRun

    backend = ARCH_BACKENDS[args.arch]

    extra = {"linear_solver": args.linear_solver} if args.linear_solver else {}
    import sim_core.solver_config as sc

    orig = sc.SolverConfig
    def config(**kw):  # the runs import it at call time; only the lockstep batch's settings take --linear-solver
        return orig(**kw, **(extra if kw.get("lockstep") else {}))

    sc.SolverConfig = config
    try:
        if backend != "numpy":  # every kernel compiled or loaded first, the projected Hessian's too (as bench batch)
            from sim_core.kernel_compile import compile_kernels

            warm = _TaskRun(args.task, 1, 2, backend, True) if args.task else _FormingRun(1, 2, backend, lockstep=True)
            warm.run()
            sim0 = warm.batch.sims[0]
            compile_kernels(sim0.solver.elastic.potentials(sim0.state.hinge_theta_bar), sim0.model.x_rest)
            del warm
    finally:
        sc.SolverConfig = orig
    if args.emulate_cuda:  # after the compilation run: the modules the steps call are imported
        from emulated_cuda import answer_cuda  # (benchmarks/, the script's folder)

        answer_cuda()
    timers = _wrap_parts(backend)
    phases = _StepPhases(_phase_specs(backend) + (_account_specs() if args.account else []), args.copy_sites)
    if args.account:
        _count_launches(phases)
    cg_iterations = _count_cg_iterations()
    memory = _Memory()
    sizes = _sizes(args.B)
    schedules = _schedules(args.schedules, len(sizes), ap)
    rows_modes = _edge_edge_rows(args.edge_edge_rows, len(sizes), ap)
    compares = _named(args.simplified_compare, len(sizes), ap, "--simplified-compare", ("every", "whole"))
    accounted: set = set()
    from sim_core.batch.simplified import SimplifiedNewtonTest

    candidates = SimplifiedNewtonTest.candidates
    for B, schedule, rows_mode, compare in zip(sizes, schedules, rows_modes, compares):
        if compare is not None:
            SimplifiedNewtonTest.candidates = candidates if compare == "every" else (
                lambda test, open_, terms, x, every=False: candidates(test, open_, terms, x))
            print(f"B={B}: the simplified test's contacts compared by {compare}", flush=True)
        if rows_mode is not None:
            import numpy as np

            from sim_core import contact_set
            from sim_core.energies.contact.reference import ListRows

            contact_set.ListRows = ListRows if rows_mode == "rows" else (
                lambda base, kept: np.take(base, kept, axis=0))
            print(f"B={B}: the edge-edge potential's pairs and sides by {rows_mode}", flush=True)
        if schedule is not None:
            from sim_core.ti_kernels import envelope_cholesky

            name, _, substitution = schedule.partition(":")
            envelope_cholesky.CUDA_SCHEDULE = envelope_cholesky.SCHEDULE = name  # (SCHEDULE: on the CPU arch)
            if substitution:
                envelope_cholesky.SUBSTITUTION = substitution
            print(f"B={B}: the envelope's schedule on CUDA {schedule}", flush=True)
        label = str(B) if schedule is None else f"{B} {schedule}"
        label = label if rows_mode is None else f"{label} {rows_mode}"
        label = label if compare is None else f"{label} {compare}"
        sc.SolverConfig = config
        for rec in timers.values():
            rec[0], rec[1] = 0, 0.0
        memory.before()
        t0 = time.perf_counter()
        try:
            run = _TaskRun(args.task, B, args.steps + 1, backend, True) if args.task else \
                _FormingRun(B, args.steps + 1, backend, lockstep=True)
        finally:
            sc.SolverConfig = orig
        _print_parts(f"B={B} build", timers, time.perf_counter() - t0)
        if schedule is not None:
            solver = run.batch.lockstep.solver if run.batch.lockstep is not None else None
            pcg = getattr(solver, 'pcg', None)
            print(f"B={label}: the batch's envelope schedule {getattr(pcg, 'schedule', None)}, substitution "
                  f"{getattr(pcg, 'substitution', None)}", flush=True)
        if args.task:
            _profile_population(run, B, args, timers, cg_iterations)
        else:
            _profile_size(run, B, args, timers, cg_iterations, phases, label)
        memory.after(B)
        del run
        if (args.account and not args.task and B in _sizes(args.account)
                and (B, schedule, rows_mode, compare) not in accounted):
            accounted.add((B, schedule, rows_mode, compare))  # again, the device synchronised
            run = _with_config(config, orig, lambda: _FormingRun(B, args.steps + 1, backend, lockstep=True))
            phases.sync = _device_sync()
            _profile_size(run, B, args, timers, cg_iterations, phases, f"{label} (account: synchronised phases)")
            phases.sync = None
            del run
    return 0


class _Memory:
    """This process's GPU memory (``nvidia-smi``, as ``thinshell bench batch``'s ``gpu_mib_per_copy``) and resident
    host memory around each size's build and steps, printed per size: the process's totals after the steps, their
    growth over the size and per copy, and the free GPU memory left. Taichi keeps freed device memory for reuse, so
    after a larger size the growth of a smaller one reads low: the sizes run in increasing order, where the growth of
    each is what it adds beyond the largest before it, and the total after it bounds its own use from above."""

    def __init__(self) -> None:
        from sim_core.batch.sizing import MIB, gpu_free_bytes, gpu_used_bytes, host_used_bytes

        self._mib, self._gpu, self._host, self._free = MIB, gpu_used_bytes, host_used_bytes, gpu_free_bytes
        self._start = (None, None)

    def before(self) -> None:
        """Record the memories before a size's build."""
        self._start = (self._gpu(), self._host())

    def after(self, B: int) -> None:
        """Print the memories after size ``B``'s steps against :meth:`before`'s."""
        (gpu0, host0), gpu1, host1, free = self._start, self._gpu(), self._host(), self._free()
        mib = self._mib

        def part(name, a, b):
            if a is None or b is None:
                return f"{name} unknown"
            return (f"{name} {b / mib:.0f} MiB after the steps (+{(b - a) / mib:.0f} over this size, "
                    f"{(b - a) / mib / B:.2f} MiB a copy; {b / mib / B:.2f} MiB a copy of the process's total)")

        print(f"B={B} memory: {part('GPU', gpu0, gpu1)}; {part('host RSS', host0, host1)}; GPU free "
              + ("unknown" if free is None else f"{free / mib:.0f} MiB"), flush=True)


def _profile_population(run, B: int, args, timers: dict, cg_iterations: list) -> None:
    """Step a task population ``run`` (``bench.batch._TaskRun``) as :meth:`PopulationRollout.run` does: the first
    step (set-up included) by part, then ``args.steps`` steps by part, and the population's host work outside the
    batched steps (its episodes' commands, early-stop checks and logs)."""
    walls: list = []
    iterations, copy_iterations = [0], [0.0]
    mark = [0.0]
    prof = cProfile.Profile() if args.cprofile else None

    def step(controls, mask):
        k = len(walls)
        if k == 1:  # the first step's parts, then the timed steps' from zero
            _print_parts(f"B={B} step 0 (set-up included)", timers, walls[0])
            for rec in timers.values():
                rec[0], rec[1] = 0, 0.0
            _start_timed(args, cg_iterations)
            if prof:
                prof.enable()
            mark[0] = time.perf_counter()
        t = time.perf_counter()
        res = run.batch.step(controls, mask)
        walls.append(time.perf_counter() - t)
        info = run.batch.lockstep.solver.last_stacked_info
        own = [i.iterations for i in res.infos if i is not None]  # each stepped copy's own Newton iterations
        if k >= 1:
            iterations[0] += getattr(info, "iterations", 0) or 0
            copy_iterations[0] += sum(own) / max(len(own), 1)
        print(f"B={B} step {k}: {walls[-1]:.3f} s, iterations {getattr(info, 'iterations', None)} (the copies' own: "
              f"mean {sum(own) / max(len(own), 1):.2f}, max {max(own, default=0)}), {int(mask.sum())} copies",
              flush=True)
        return res

    for rec in timers.values():
        rec[0], rec[1] = 0, 0.0
    run.population.run(step=step)
    if prof:
        prof.disable()
    wall = time.perf_counter() - mark[0]
    stepped = sum(walls[1:])
    print(f"B={B} {len(walls) - 1} steps in {wall:.3f} s ({stepped:.3f} s in the batched steps, {wall - stepped:.3f} s "
          f"the population's host work around them): {B * (len(walls) - 1) / wall:.2f} scene-steps/s, "
          f"{iterations[0]} Newton iterations, {1e3 * stepped / max(iterations[0], 1):.1f} ms an iteration; the "
          f"copies' own iterations {copy_iterations[0]:.1f} (mean over copies, summed over steps: "
          f"{100 * copy_iterations[0] / max(iterations[0], 1):.0f} % of the lockstep's)")
    _print_parts(f"B={B} {len(walls) - 1} timed steps", timers, wall, iterations[0])
    _print_timed(B, args, cg_iterations, prof)


def _profile_size(run, B: int, args, timers: dict, cg_iterations: list, phases: _StepPhases,
                  name: str | None = None) -> None:
    """Set up and step ``run`` (``B`` copies) once, then time ``args.steps`` steps by part: each step's wall time
    split into its phases (:class:`_StepPhases`), and the steady rate ``thinshell bench batch`` reports for the same
    steps (its ``steady_scene_steps_per_s``: the stepped copies over ``BatchStep.wall_s``). ``name``: the size's
    name in the printed lines (default ``B``)."""
    from sim_core.control import Control

    name = str(B) if name is None else name

    iterations = [0]
    per_step: list = []  # the timed steps' (phases, wall, BatchStep.wall_s, stepped copies, iterations)
    step_copies: list = []  # the timed steps' synchronous copies by phase (_StepPhases.copies)
    step_sites: list = []  # and by call site (_StepPhases.sites, with --copy-sites)
    step_launches: list = []  # the timed steps' kernel launches by phase (_StepPhases.launches, with --account)
    lines: list = []  # the timed steps' summary lines, printed again at the end (a tail of the output holds them)

    counted = ("LockstepSolver._stacked_gradient (in _line_search_copies)", "ContactSet._search_position",
               "ContactSet._search_position (in _line_search_copies)",
               "ContactSet._candidate_pairs (in _line_search_copies)", "ContactSet._search (in _line_search_copies)",
               "Taichi launches", "Taichi new ndarrays")

    def step(k):
        solves = len(cg_iterations)
        before = [list(timers.get(label, (0, 0.0))) for label in counted]
        phases.mark(_LOOP)
        t = time.perf_counter()
        res = run.batch.step([Control(effector_pose_target={run.effector: tg[k]}) for tg in run.targets])
        wall = time.perf_counter() - t
        parts = phases.take()
        trials, searches, in_ls, pairs_ls, search_ls, launches, made = (
            [a - b for a, b in zip(timers.get(label, (0, 0.0)), rec)] for label, rec in zip(counted, before))
        copies = {label: list(rec) for label, rec in phases.copies.items()}
        if k > 0:
            step_launches.append(dict(phases.launches))
        sites = {key: list(rec) for key, rec in phases.sites.items()}
        eng = run.batch.lockstep
        info = eng.solver.last_stacked_info if eng is not None else None
        its = getattr(info, "iterations", 0) or 0
        iterations[0] += its
        own = [i.iterations for i in res.infos if i is not None]
        print(f"B={name} step {k}: {wall:.3f} s, iterations {getattr(info, 'iterations', None)} (the copies' own: mean "
              f"{sum(own) / max(len(own), 1):.2f}), assembly "
              f"{getattr(info, 'time_assembly', 0):.3f} s, solve {getattr(info, 'time_linear_solve', 0):.3f} s, "
              f"factorizations {getattr(info, 'factorizations', None)}", flush=True)
        g = _group_phases(parts)
        retries = (getattr(info, "factorizations", 0) or 0) - its  # the projected retries' factorisations
        kind = f"projection step ({retries} projected retries)" if retries > 0 else "no projection"
        line = (f"B={name} step {k}: {kind}; wall {1e3 * wall:.1f} ms: {its} Newton iterations "
                f"{1e3 * g['iterations']:.1f} ({1e3 * g['iterations'] / max(its, 1):.1f} ms each), set-up "
                f"{1e3 * g['set-up']:.1f}, finish {1e3 * g['finish']:.1f}, outside the solver "
                f"{1e3 * g['outside']:.1f}, garbage collection {1e3 * g['gc']:.1f}"
                + (f", the account's finer phases {1e3 * g['account']:.1f}" if g["account"] else "")
                + f" (the phases' sum {1e3 * sum(g.values()):.1f}); the bench's wall_s {1e3 * res.wall_s:.1f}; "
                f"CG iterations "
                f"{sum(cg_iterations[solves:])} in {len(cg_iterations) - solves} solves; synchronous copies "
                f"{sum(c[0] for c in copies.values())}, {sum(c[1] for c in copies.values()) / 1e6:.1f} MB, "
                f"{1e3 * sum(c[2] for c in copies.values()):.1f} ms; line search: {trials[0]} trial points, "
                f"{getattr(info, 'backtracks', 0)} backtracks (copies), candidate searches {searches[0]} "
                f"({in_ls[0]} at its trial points: {1e3 * pairs_ls[1]:.1f} ms in _candidate_pairs, "
                f"{1e3 * search_ls[1]:.1f} in _search); Taichi launches {launches[0]}, new ndarrays {made[0]}")
        print(line, flush=True)
        if k > 0:
            per_step.append((parts, wall, res.wall_s, len(own), its))
            step_copies.append(copies)
            step_sites.append(sites)
            lines.append(line)
        return res

    for rec in timers.values():
        rec[0], rec[1] = 0, 0.0
    t0 = time.perf_counter()
    run.batch.warm_up()
    step(0)
    _print_parts(f"B={name} set-up and step 0", timers, time.perf_counter() - t0)
    for rec in timers.values():
        rec[0], rec[1] = 0, 0.0
    iterations[0] = 0
    _start_timed(args, cg_iterations)
    prof = cProfile.Profile() if args.cprofile else None
    t0 = time.perf_counter()
    if prof:
        prof.enable()
    for k in range(1, args.steps + 1):
        step(k)
    if prof:
        prof.disable()
    wall = time.perf_counter() - t0
    print(f"B={name} {args.steps} steps in {wall:.3f} s: {B * args.steps / wall:.2f} scene-steps/s, "
          f"{iterations[0]} Newton iterations, {1e3 * wall / max(iterations[0], 1):.1f} ms an iteration")
    _print_parts(f"B={name} {args.steps} timed steps", timers, wall, iterations[0])
    _print_phases(name, [p for p, *_ in per_step], [w for _, w, *_ in per_step], step_copies,
                  step_launches if args.account else None)
    if args.copy_sites:
        _print_sites(name, step_sites)
    print("\n".join(lines))
    groups = [_group_phases(p) for p, *_ in per_step]
    n = max(len(per_step), 1)
    bench_wall = sum(b for _, _, b, _, _ in per_step)
    print(f"B={name} per step (mean of steps 1-{args.steps}): wall {1e3 * wall / n:.1f} ms, of it Newton iterations "
          f"{1e3 * sum(g['iterations'] for g in groups) / n:.1f} ({iterations[0] / n:.2f} a step), set-up "
          f"{1e3 * sum(g['set-up'] for g in groups) / n:.1f}, finish {1e3 * sum(g['finish'] for g in groups) / n:.1f}, "
          f"outside the solver {1e3 * sum(g['outside'] for g in groups) / n:.1f}, garbage collection "
          f"{1e3 * sum(g['gc'] for g in groups) / n:.1f}, the account's finer phases "
          f"{1e3 * sum(g['account'] for g in groups) / n:.1f} ms")
    print(f"B={name} steps 1-{args.steps}: {B * args.steps / wall:.2f} scene-steps/s over the run loop's wall; "
          f"thinshell bench batch would report steady {sum(c for *_, c, _ in per_step) / bench_wall:.2f} "
          f"(the stepped copies over BatchStep.wall_s, {bench_wall:.3f} s; with --steps 4 these are the bench's "
          f"steady steps of --steps 5)")
    _print_timed(name, args, cg_iterations, prof)


class _StepPhases:
    """A step's wall time split into exclusive phases that add up to it: each wrapped function is a phase (where
    the phase it is called from is one of its ``parents``), its time less its inner phases' its own; Python's
    garbage collections are a phase of their own. :meth:`mark` starts a step's phases from zero under the
    outermost phase ``label`` (the run loop's own work) and :meth:`take` returns label -> seconds since then."""

    def __init__(self, specs: list, site_frames: int = 0, sync=None) -> None:
        import gc

        self.sync = sync  # called at every phase change (the device's queued work charged to the running phase)
        self.launches: dict = {}  # phase -> kernel launches (with sync)
        self.stack: list = []
        self.seconds: dict = {}
        self._busy = False
        self.last = time.perf_counter()
        for owner, name, label, parents in specs:
            raw = vars(owner)[name] if isinstance(owner, type) else getattr(owner, name)
            setattr(owner, name, self._phase(raw, label, parents))
        gc.callbacks.append(self._collector)
        self.copies: dict = {}  # phase -> [calls, bytes, seconds] of the synchronous byte copies (device_copy._copy)
        self.site_frames = site_frames
        self.sites: dict = {}  # (phase, direction, call site) -> [calls, bytes], with site_frames > 0
        self._count_copies()

    def _count_copies(self) -> None:
        """Count each synchronous byte copy to or from the device (``device_copy._copy``: calls, bytes, seconds) under
        the phase that made it, and with :attr:`site_frames` by call site (:attr:`sites`)."""
        from sim_core.ti_kernels import device_copy

        copy = device_copy._copy

        def rec_bytes(host, rows):
            return host.nbytes if rows is None or not host.ndim else host.nbytes // max(len(host), 1) * rows

        def counted(array, host, upload, rows=None):
            t = time.perf_counter()
            try:
                return copy(array, host, upload, rows)
            finally:
                if self.stack:
                    rec = self.copies.setdefault(self.stack[-1], [0, 0, 0.0])
                    rec[0] += 1
                    rec[1] += rec_bytes(host, rows)
                    rec[2] += time.perf_counter() - t
                    if self.site_frames:
                        site = self.sites.setdefault((self.stack[-1], "up" if upload else "down", _site(
                            self.site_frames)), [0, 0])
                        site[0] += 1
                        site[1] += rec_bytes(host, rows)

        device_copy._copy = counted

    def _switch(self, push: str | None) -> None:
        """Close the running phase's interval, then enter ``push`` (None: leave the running phase). A collection
        that starts in here is left to the running phase (``_busy``: the stack is being changed)."""
        self._busy = True
        try:
            if self.sync is not None:
                self.sync()
            now = time.perf_counter()
            if self.stack:
                top = self.stack[-1]
                self.seconds[top] = self.seconds.get(top, 0.0) + now - self.last
            self.last = now
            if push is None:
                self.stack.pop()
            else:
                self.stack.append(push)
        finally:
            self._busy = False

    def _phase(self, fn, label: str, parents):
        import functools

        @functools.wraps(fn)
        def wrapped(*a, **kw):
            if not self.stack or (parents is not None and self.stack[-1] not in parents):
                return fn(*a, **kw)
            self._switch(label)
            try:
                return fn(*a, **kw)
            finally:
                self._switch(None)
        return wrapped

    def _collector(self, event: str, info: dict) -> None:
        if self._busy or not self.stack:
            return
        if event == "start":
            self._switch(f"garbage collection (generation {info['generation']})")
        elif event == "stop" and self.stack[-1].startswith("garbage collection"):
            self._switch(None)

    def mark(self, label: str) -> None:
        if self.sync is not None:
            self.sync()
        self.stack, self.seconds, self.copies, self.last = [label], {}, {}, time.perf_counter()
        self.sites, self.launches = {}, {}

    def count_launch(self) -> None:
        """One kernel launch under the running phase (:attr:`launches`)."""
        if self.stack:
            self.launches[self.stack[-1]] = self.launches.get(self.stack[-1], 0) + 1

    def take(self) -> dict:
        """The step's phases: label -> seconds (its synchronous byte copies stay in :attr:`copies` until the next
        :meth:`mark`)."""
        self._switch(None)
        seconds, self.stack, self.seconds = self.seconds, [], {}
        return seconds


_LOOP = "run loop: the copies' controls (outside BatchedSimulation.step)"
_SET_UP = "set-up: the rest (inertia, gravity, elastic terms, fused start, lumped terms)"
_NEWTON = "Newton: the rest (the exact operator, the per-copy tests, the loop's own)"
_FINISH = "finish: the rest (StepRecord, velocities, poses)"
_ENGINE = "engine: the rest (output state, per-copy write-back, StepTotals)"


def _phase_specs(backend: str) -> list:
    """``(owner, name, label, parents)`` of :class:`_StepPhases`: a lockstep step's set-up, Newton iterations and
    finish, the engine's and the batch's work around the solver, each with its larger parts."""
    from sim_core.batch import lockstep
    from sim_core.batch.simulation import BatchedSimulation
    from sim_core.batch.stacked import StackedScene
    from sim_core.contact_set import ContactSet
    from sim_core.elastic import ElasticTerms
    from sim_core.solver import NewtonSolver

    from sim_core.batch.plasticity import StackedElasticTerms

    engine, setup, finish = _ENGINE, _SET_UP, _FINISH
    batch = "BatchedSimulation.step: the controls' checks"
    specs = [(BatchedSimulation, "step", batch, {_LOOP}),
             (lockstep.LockstepEngine, "step", engine, {batch}),
             (lockstep.LockstepEngine, "_sync", "engine: _sync", {engine}),
             (StackedScene, "stack_controls", "engine: stack_controls", {engine}),
             (StackedScene, "copy_states", "engine: copy_states", {engine}),
             # the copies' rows gathered on the device where the step kept its state there (their downloads)
             (lockstep.LockstepSolver, "resident_rows", "engine: copy_states", {engine}),
             (lockstep.LockstepSolver, "step_copies", "solver: step_copies (outside the attempt)", {engine}),
             (lockstep.LockstepSolver, "_lockstep_step", _NEWTON, None),
             (lockstep.LockstepSolver, "_set_up_step", setup, {_NEWTON}),
             (lockstep.LockstepSolver, "boundary", "set-up: boundary (effectors)", {setup}),
             (ContactSet, "begin_step", "set-up: ContactSet.begin_step", {setup}),
             (ContactSet, "friction", "set-up: ContactSet.friction", {setup}),
             (NewtonSolver, "_finish_step", finish, {_NEWTON}),
             (ContactSet, "potentials", "finish: ContactSet.potentials", {finish}),
             (NewtonSolver, "_energy", "finish: the energy", {finish}),
             (NewtonSolver, "_contact_force", "finish: contact force", {finish}),
             (lockstep.LockstepSolver, "_contact_force", "finish: contact force", {finish}),
             (ContactSet, "end_step", "finish: ContactSet.end_step", {finish})]
    specs += [(cls, "plastic_update", "finish: plastic update", {finish})
              for cls in (ElasticTerms, StackedElasticTerms)]
    # the Newton iterations' larger parts (the projected retry's elastic Hessian and pair blocks apart)
    from sim_core.batch.line_search import CopyLineSearch
    from sim_core.fused_elastic import FusedElastic

    specs += [(lockstep.LockstepSolver, "_stacked_gradient", "Newton: the stacked gradient", {_NEWTON}),
              (CopyLineSearch, "_line_search_copies", "Newton: the line search", {_NEWTON}),
              (FusedElastic, "projected_hessian_values", "Newton: the projected elastic Hessian (retries)", {_NEWTON}),
              (FusedElastic, "projected_hessian_values_device", "Newton: the projected elastic Hessian (retries)",
               {_NEWTON}),
              (lockstep, "projected_subset_blocks", "Newton: the projected pair blocks (retries)", {_NEWTON})]
    # the friction's set-up by part: the step's pair potentials (their sides at x^n apart) and the friction rows
    friction, search = "set-up: ContactSet.friction", "set-up: friction: the pair potentials (ContactSet._search)"
    specs += [(ContactSet, "_search", search, {friction}),
              (ContactSet, "_pair_sides", "set-up: friction: the pairs' sides at x^n (ContactSet._pair_sides)",
               {search}),
              (ContactSet, "_pair_friction", "set-up: friction: the rows (ContactSet._pair_friction)", {friction})]
    if backend != "numpy":
        from sim_core.ti_kernels import envelope_cholesky, pcg
        from sim_core.ti_kernels.block_projection import BlockRowsProjector

        pairs = "Newton: the projected pair blocks (retries)"
        specs += [(pcg.BatchedPCG, "factorize", "Newton: BatchedPCG.factorize", {_NEWTON}),
                  (envelope_cholesky.BatchedEnvelope, "factorize", "Newton: BatchedEnvelope.factorize", {_NEWTON}),
                  (pcg.BatchedPCG, "solve_on_device", "Newton: BatchedPCG.solve_on_device", {_NEWTON}),
                  (BlockRowsProjector, "project", "Newton: retries: the pair blocks' Jacobi projection", {pairs})]
    return specs


def _sizes(text) -> list[int]:
    """Batch sizes from a comma-separated ``text`` (``--B``, ``--account``)."""
    return [int(b) for b in str(text).split(",")]


def _schedules(text, count: int, ap) -> list:
    """The envelope schedules of ``--schedules`` (``text``, comma-separated, one for each of the ``count`` entries of
    ``--B``; ``dots`` and ``panels`` may name a substitution after a colon, ``panels:rows``), or ``count`` Nones
    without it; ``ap.error`` on a count that differs or an unknown name."""
    if text is None:
        return [None] * count
    names = [name.strip() for name in str(text).split(",")]
    known = ("pairs", "rows", "dots", "panels", "blocks")
    substitutions = ("", "rows", "vertices", "vertices-ahead")

    def _known(name):
        schedule, colon, substitution = name.partition(":")
        return schedule in known and substitution in substitutions and (not colon or substitution and schedule in (
            "dots", "panels"))

    if len(names) != count or not all(_known(name) for name in names):
        ap.error(f"--schedules needs one of {'|'.join(known)} (dots and panels with :rows, :vertices or :vertices-ahead, optional) for "
                 f"each of the {count} entries of --B; got {text!r}")
    return names


def _edge_edge_rows(text, count: int, ap) -> list:
    """The names of ``--edge-edge-rows`` (``text``, comma-separated ``rows`` / ``takes``, one for each of the ``count``
    entries of ``--B``), or ``count`` Nones without it; ``ap.error`` on a count that differs or an unknown name."""
    if text is None:
        return [None] * count
    names = [name.strip() for name in str(text).split(",")]
    if len(names) != count or not all(name in ("rows", "takes") for name in names):
        ap.error(f"--edge-edge-rows needs rows|takes for each of the {count} entries of --B; got {text!r}")
    return names


def _named(text, count: int, ap, flag: str, known: tuple) -> list:
    """The names of ``flag`` (``text``, comma-separated, one of ``known`` for each of the ``count`` entries of ``--B``),
    or ``count`` Nones without it; ``ap.error`` on a count that differs or an unknown name."""
    if text is None:
        return [None] * count
    names = [name.strip() for name in str(text).split(",")]
    if len(names) != count or not all(name in known for name in names):
        ap.error(f"{flag} needs {'|'.join(known)} for each of the {count} entries of --B; got {text!r}")
    return names


def _with_config(config, orig, make):
    """``make()`` with ``SolverConfig`` replaced by ``config`` (the lockstep batch's ``--linear-solver``), then
    restored to ``orig``."""
    import sim_core.solver_config as sc

    sc.SolverConfig = config
    try:
        return make()
    finally:
        sc.SolverConfig = orig


def _device_sync():
    """Taichi's ``sync`` (every queued kernel and copy finished), for :class:`_StepPhases` with ``--account``."""
    from sim_core.ti_backend import ti

    return ti.sync


def _account_specs() -> list:
    """The finer phases of ``--account`` (issue 52 item 1: a steady step's phases beside their roofline floors), each
    a phase wherever it is called from: the element kernels (the fused elastic terms' gradient and Hessian values),
    the pair batch's evaluations, the friction's device gradient, the envelope's gather and elimination and its
    substitution, the trial points' positions (moved and downloaded), the per-copy scalars (the slope, convergence
    and finite tests' reads), the per-copy energies, and the candidate lists (their cover test at every iterate and
    trial point; a build where the cover fails, the lists' own mission)."""
    from sim_core.batch.device_iterates import DeviceIterates
    from sim_core.batch.line_search import CopyLineSearch
    from sim_core.contact_set import ContactSet
    from sim_core.energies.contact.batch_kernel import PairBatch
    from sim_core.energies.friction.kernel import TiLaggedFriction
    from sim_core.fused_elastic import FusedElastic
    from sim_core.ti_kernels.copy_vectors import CopyVectors
    from sim_core.ti_kernels.envelope_cholesky import BatchedEnvelope

    elements, pairs = "account: element gradient and Hessian values (fused kernels)", "account: the pair batch"
    return [(FusedElastic, "_evaluate", elements, None), (FusedElastic, "add_gradient_on_device", elements, None),
            (FusedElastic, "hessian_values_device", elements, None),
            (PairBatch, "evaluate", pairs, None),
            (TiLaggedFriction, "add_gradient_on_device", "account: the friction's gradient", None),
            (BatchedEnvelope, "_eliminate", "account: envelope gather and factorisation (kernels)", None),
            (BatchedEnvelope, "_solve_into", "account: envelope substitution (kernels)", None),
            (DeviceIterates, "trial", "account: trial positions (moved, downloaded)", None),
            (DeviceIterates, "trial_by", "account: trial positions (moved, downloaded)", None),
            (CopyVectors, "scalars", "account: per-copy scalars read (slopes, norms, tests)", None),
            (CopyVectors, "_extremes", "account: per-copy scalars read (slopes, norms, tests)", None),
            (CopyLineSearch, "_launch_copy_energies", "account: per-copy energies", None),
            (ContactSet, "_candidate_pairs", "account: the candidate lists (their cover test; a build)", None)
            ] + _loop_specs()


def _loop_specs() -> list:
    """The Newton loop's host rest split by part for ``--account`` (issue 52 item 3: what a resident Newton loop would
    remove): the simplified Newton test's touching contacts (:class:`~sim_core.batch.simplified.SimplifiedNewtonTest`,
    measured at every iterate), the operator's contact and friction blocks (:meth:`LockstepSolver._term_hessian`,
    the blocks' host form where one is asked for), the operator's rest (:meth:`LockstepSolver._device_operator`'s own:
    the element values' handles, the blocks' sets), the per-copy stopping tests and acceptances
    (:class:`~sim_core.batch.copy_outcomes.CopyOutcomes`), the iterates' vector kernels (copies, blends, zeroed copies
    and DoFs), the released stale sides, the device solver's copies to factorise."""
    from sim_core.batch import lockstep, simplified
    from sim_core.batch.copy_outcomes import CopyOutcomes
    from sim_core.contact_set import ContactSet
    from sim_core.ti_kernels.copy_vectors import CopyVectors
    from sim_core.ti_kernels.pcg import VertexBlocks

    active = "account: Newton: the simplified test's touching contacts (host)"
    blocks = "account: Newton: the operator's contact and friction blocks"
    vectors = "account: Newton: the iterates' vector kernels (copy, blend, zeroed copies and DoFs)"
    specs = [(simplified.SimplifiedNewtonTest, "_active", active, None),
             (simplified, "same_active_sets", active, None),
             (lockstep.LockstepSolver, "_term_hessian", blocks, None),
             (VertexBlocks, "_vertex_blocks", blocks, None),
             (lockstep.LockstepSolver, "_device_operator", "account: Newton: the operator's rest", None),
             (lockstep.LockstepSolver, "_copies_to_factorize", "account: Newton: the copies to factorise", None),
             (CopyOutcomes, "stop_tests", "account: Newton: the per-copy tests and outcomes", None),
             (CopyOutcomes, "accept", "account: Newton: the per-copy tests and outcomes", None),
             (ContactSet, "release_stale_sides", "account: Newton: stale sides released", None)]
    specs += [(CopyVectors, name, vectors, None)
              for name in ("new", "copy", "blend", "blend_actions", "zero_copies", "copy_where", "zero_dofs")]
    return specs


def _count_launches(phases: _StepPhases) -> None:
    """Charge each Taichi kernel launch to the running phase of ``phases`` (:meth:`_StepPhases.count_launch`)."""
    from taichi._lib.core.taichi_python import Program

    launch = Program.launch_kernel

    def counted(self, *a, **kw):
        phases.count_launch()
        return launch(self, *a, **kw)
    Program.launch_kernel = counted


def _print_phases(B: int | str, per_step: list, walls: list, copies: list, launches: list | None = None) -> None:
    """The timed steps' phases (:class:`_StepPhases`), ms a step (mean) and per step, with the synchronous byte
    copies each made (calls and MB a step, their ms a step: ``copies``, one dict a step) and, given ``launches``
    (one dict a step, ``--account``), the kernel launches a step."""
    steps = max(len(per_step), 1)
    labels = sorted({k for p in per_step for k in p}, key=lambda k: -sum(p.get(k, 0.0) for p in per_step))
    total = sum(walls)
    print(f"{'phase (exclusive), B=' + str(B):66s} {'ms/step':>9s} {'% wall':>7s} {'copies':>7s} {'MB':>7s} "
          f"{'ms':>7s} " + (f"{'launch':>7s} " if launches is not None else "") + " per step (ms)")
    for label in labels:
        each = [1e3 * p.get(label, 0.0) for p in per_step]
        calls, nbytes, secs = (sum(c.get(label, [0, 0, 0.0])[j] for c in copies) / steps for j in range(3))
        launched = "" if launches is None else f"{sum(n.get(label, 0) for n in launches) / steps:7.1f} "
        print(f"{label:66s} {sum(each) / steps:9.2f} {100 * sum(each) / 1e3 / total:7.1f} {calls:7.1f} "
              f"{nbytes / 1e6:7.1f} {1e3 * secs:7.2f} {launched} " + " ".join(f"{e:8.2f}" for e in each))
    print(f"{'sum of the phases':66s} {1e3 * sum(sum(p.values()) for p in per_step) / steps:9.2f}"
          f" {100 * sum(sum(p.values()) for p in per_step) / total:7.1f}")


def _site(frames: int) -> str:
    """The caller's innermost ``frames`` frames in ``sim_core`` (outside ``device_copy.py``), outermost first:
    ``module.function:line`` joined by `` > ``."""
    import traceback

    found = []
    for f in reversed(traceback.extract_stack()):
        path = f.filename.replace("\\", "/")
        if "/sim_core/" in path and not path.endswith("/device_copy.py"):
            found.append(f"{path.rsplit('/sim_core/', 1)[1][:-3].replace('/', '.')}.{f.name}:{f.lineno}")
            if len(found) == frames:
                break
    return " > ".join(reversed(found)) or "(outside sim_core)"


def _print_sites(B: int | str, per_step: list) -> None:
    """The timed steps' synchronous copies by phase, direction and call site (``--copy-sites``): calls and MB a
    step (mean), the phases in order of their MB, each phase's sites in order of their MB then calls."""
    steps = max(len(per_step), 1)
    keys = {k for s in per_step for k in s}
    total = {k: [sum(s.get(k, [0, 0])[j] for s in per_step) / steps for j in range(2)] for k in keys}
    by_phase: dict = {}
    for (phase, direction, site), (calls, nbytes) in total.items():
        by_phase.setdefault(phase, []).append((nbytes, calls, direction, site))
    print(f"synchronous copies by call site, B={B} (a step, mean of {len(per_step)}): copies, MB, direction, site")
    for phase, rows in sorted(by_phase.items(), key=lambda kv: -sum(r[0] for r in kv[1])):
        print(f"  {phase}")
        for nbytes, calls, direction, site in sorted(rows, key=lambda r: (-r[0], -r[1])):
            print(f"    {calls:6.1f} {nbytes / 1e6:8.2f}  {direction:4s} {site}")


def _group_phases(phases: dict) -> dict:
    """A step's phases (:class:`_StepPhases`) in the groups of the step's summary line: Newton iterations, set-up,
    finish, outside the solver (the engine, the batch, the run loop), the garbage collector, and ``--account``'s finer
    phases (wherever they ran: most in the Newton iterations)."""
    groups = {"iterations": 0.0, "set-up": 0.0, "finish": 0.0, "outside": 0.0, "gc": 0.0, "account": 0.0}
    for label, s in phases.items():
        key = ("iterations" if label.startswith("Newton:") else "set-up" if label.startswith("set-up") else
               "finish" if label.startswith("finish") else "gc" if label.startswith("garbage") else
               "account" if label.startswith("account:") else "outside")
        groups[key] += s
    return groups


def _start_timed(args, cg_iterations: list) -> None:
    """Before the timed steps: the CG's iteration counts and (``--kernel-profiler``) the kernel times from zero."""
    cg_iterations.clear()
    if args.kernel_profiler:
        from sim_core.ti_backend import ti

        ti.profiler.clear_kernel_profiler_info()


def _print_timed(B: int | str, args, cg_iterations: list, prof) -> None:
    """After the timed steps: the CG's iterations per solve, (``--kernel-profiler``) the kernel times and
    (``--cprofile``) cProfile's tables (written to ``--out`` too)."""
    if cg_iterations:
        print(f"B={B} CG iterations per solve: mean {sum(cg_iterations) / len(cg_iterations):.1f}, "
              f"{min(cg_iterations)}-{max(cg_iterations)} over {len(cg_iterations)} solves")
    if args.kernel_profiler:
        from sim_core.ti_backend import ti

        ti.profiler.print_kernel_profiler_info("count")
    if prof:
        st = pstats.Stats(prof, stream=sys.stdout)
        st.sort_stats("cumulative").print_stats(args.top)
        st.sort_stats("tottime").print_stats(args.top)
        if args.out:
            st.dump_stats(f"{args.out}.B{str(B).split()[0]}")


def _print_parts(title: str, timers: dict, wall: float, iterations: int = 0) -> None:
    """The parts that ran (inclusive wall seconds, calls, share of ``wall``, and with ``iterations`` the ms per
    Newton iteration), longest first."""
    print(f"{'part (inclusive), ' + title:58s} {'calls':>6s} {'s':>8s} {'% wall':>7s} {'ms/it':>8s}")
    for name, (calls, total) in sorted(timers.items(), key=lambda kv: -kv[1][1]):
        if calls:
            per_it = f"{1e3 * total / iterations:8.2f}" if iterations else ""
            print(f"{name:58s} {calls:6d} {total:8.3f} {100 * total / wall:7.1f} {per_it}")


def _count_cg_iterations() -> list:
    """Record each batched CG solve's iterations (``BatchedPCG.iterations``) in the returned list."""
    from sim_core.ti_kernels import pcg

    counts: list = []
    run = pcg.BatchedPCG._run  # the CG iterations of a host or a device solve

    def counted(self):
        run(self)
        counts.append(self.iterations)

    pcg.BatchedPCG._run = counted
    return counts


def _wrap_parts(backend: str) -> dict:
    """Wrap the solver's parts with wall-clock timers (the device vectors' too on a Taichi ``backend``); returns
    name -> [calls, seconds] (filled as they run)."""

    from sim_core.batch import lockstep
    from sim_core.assembly import HessianAssembler
    from sim_core.contact_set import ContactSet
    from sim_core.energies.contact.reference import _PairPenalty
    from sim_core.energies.friction.kernel import TiLaggedFriction
    from sim_core.energies.kirchhoff_bending.fused_kernel import FusedKirchhoffBending
    from sim_core.energies.membrane.fused_spring_kernel import FusedSpringMembrane
    from sim_core.energies.neohookean.fused_kernel import FusedStableNeoHookean
    from sim_core.static_pattern import StaticPattern
    from sim_core.fused_elastic import FusedElastic
    from sim_core.solver import NewtonSolver
    from sim_core.ti_kernels import pcg

    timers: dict = {}
    from sim_core.batch.line_search import CopyLineSearch

    parts = [(lockstep.LockstepSolver, n) for n in ("_stacked_gradient", "_direction", "_device_operator")]
    parts += [(CopyLineSearch, n) for n in ("_line_search_copies", "_backtrack_on_device", "_energy_with")]
    parts += [(NewtonSolver, n) for n in ("_set_up_step", "_finish_step", "_assemble_hessian", "_energy")]
    parts += [(ContactSet, n) for n in ("potentials", "begin_step", "friction", "end_step")]
    parts += [(FusedElastic, n) for n in ("_evaluate", "energy", "projected_hessian_values",
                                          "projected_hessian_values_device")]
    parts += [(pcg.BatchedPCG, n) for n in ("factorize", "solve", "solve_on_device")]
    parts += [(pcg.VertexBlocks, "from_element_blocks")]
    parts += [(cls, n) for cls in (FusedKirchhoffBending, FusedSpringMembrane, FusedStableNeoHookean)
              for n in ("add_projected", "add_projected_on_device")]
    parts += [(cls, "bind") for cls in (FusedKirchhoffBending, FusedSpringMembrane, FusedStableNeoHookean)]
    parts += [(_PairPenalty, "hessian"), (TiLaggedFriction, "hessian"), (HessianAssembler, "static_pattern"),
              (StaticPattern, "__init__"), (StaticPattern, "slot_map")]
    parts += [(lockstep.LockstepEngine, "_sync"), (NewtonSolver, "warm_up"), (NewtonSolver, "_fused_elastic")]
    # the stacked gradient's and the energies' terms
    from sim_core.energies.contact.batch_kernel import PairBatch
    from sim_core.energies.inertia.reference import InertiaPotential

    from sim_core.batch.lumped import LumpedQuadratic
    from sim_core.energies.gravity.reference import GravityPotential

    parts += [(cls, n) for cls in (InertiaPotential, GravityPotential, LumpedQuadratic, _PairPenalty, TiLaggedFriction)
              for n in ("gradient", "energy")]
    parts += [(FusedElastic, "gradient"), (PairBatch, "evaluate"), (ContactSet, "covers"),
              (lockstep, "projected_subset_blocks")]
    # the line search's per-copy energies (each term's split by copy) and its trial points' own work
    from sim_core.energies.contact.reference import PlaneContact
    from sim_core.energies.friction.reference import LaggedFriction
    from sim_core.energies.sphere_contact.reference import SphereContact

    parts += [(CopyLineSearch, "_copy_energies")]
    parts += [(cls, "copy_energies") for cls in (LumpedQuadratic, FusedElastic, _PairPenalty, LaggedFriction,
                                                 PlaneContact, SphereContact, FusedKirchhoffBending,
                                                 FusedSpringMembrane, FusedStableNeoHookean)]
    parts += [(cls, "add_copy_energies_on_device") for cls in (LumpedQuadratic, FusedElastic, TiLaggedFriction)]
    from sim_core.batch import iterates
    from sim_core.batch.copy_runs import CopyRuns  # the per-copy reductions over the stacked arrays (host NumPy)

    parts += [(iterates, "summed_gradient"), (iterates.HostIterates, "gradient")]
    parts += [(CopyRuns, n) for n in ("dot", "any_dof", "all_finite", "largest_norm", "largest_abs", "per_dof",
                                       "moved")]
    if backend != "numpy":  # the same on the device's vectors (the batched CG's path)
        from sim_core.batch.device_iterates import DeviceIterates
        from sim_core.ti_kernels.copy_vectors import CopyVectors

        parts += [(DeviceIterates, n) for n in ("gradient", "trial", "start", "slope_and_largest")]
        parts += [(CopyVectors, n) for n in ("dot", "largest_abs", "largest_norm", "blend", "moved", "download",
                                             "upload", "add", "add_rows", "zero_dofs", "copy", "new")]
        parts += [(LumpedQuadratic, "add_gradient_on_device")]
        from sim_core.ti_kernels import copy_vectors

        copy_sums = getattr(copy_vectors, "CopySums", None)  # the per-copy energies' one read (where there is one)
        parts += [(copy_sums, "read")] if copy_sums is not None else []
    parts += [(lockstep.LockstepSolver, "_direction_pcg"), (lockstep.LockstepSolver, "_term_hessian")]
    # the contact set's own parts: the search, the step's potentials and pair batch, friction set-up, the step's end
    from sim_core import contact_set
    from sim_core.energies.contact import pair_lists, setup_kernel
    from sim_core.ti_kernels import hash_grid

    parts += [(ContactSet, n) for n in ("_candidate_pairs", "_search", "_pair_sides", "_pair_geometry",
                                        "_list_vertices", "_pair_friction", "_end_geometry_of")]
    parts += [(hash_grid.HashGrid, "pairs"), (hash_grid, "sorted_pairs_and_keys"), (PairBatch, "__init__"),
              (PairBatch, "_launch"), (pair_lists.CandidateVertices, "__init__"),
              (pair_lists.CandidateVertices, "batch_indices"), (setup_kernel, "friction_frames"),
              (pair_lists, "lookup_pairs"), (pair_lists, "merge_rows"), (pair_lists.CandidateVertices, "batch_layout"),
              (pair_lists.CandidateVertices, "keys"), (setup_kernel, "pair_codes")]
    if backend != "numpy":
        from sim_core.energies.contact import batch_kernel
        from sim_core.ti_kernels.displacement_bounds import DisplacementBounds

        parts += [(batch_kernel, "_sorted_found"), (PairBatch, "_device_arguments"), (DisplacementBounds, "__call__")]
        from sim_core.ti_kernels import compaction

        # CUDA: the search's device parts
        parts += [(hash_grid, "sorted_on_device"), (compaction, "compact_on_device")]
    # the step's host work outside the Newton loop, and the synchronous copies to and from the device
    from sim_core.batch.stacked import StackedScene
    from sim_core.elastic import ElasticTerms
    from sim_core.ti_kernels import device_copy

    from sim_core.batch.plasticity import StackedElasticTerms

    # a task population's build and host work around its steps (--task)
    from sim_core.batch import stacked
    from sim_core.batch.simulation import BatchedSimulation
    from sim_core.tasks import rollout

    parts += [(rollout.TaskEpisode, n) for n in ("__init__", "command", "record_step", "wrenches")]
    parts += [(rollout._EpisodeLog, n) for n in ("__init__", "add")]
    parts += [(rollout, "build_task_simulation"), (rollout, "build_task_scene"), (rollout, "task_initial_state"),
              (BatchedSimulation, "__init__"), (stacked, "stack_models"), (lockstep.LockstepEngine, "__init__"),
              (lockstep.LockstepSolver, "__init__"), (StackedScene, "stack_states")]
    parts += [(lockstep.LockstepEngine, "step"), (StackedScene, "copy_states"), (StackedScene, "stack_controls"),
              (NewtonSolver, "boundary"), (ElasticTerms, "plastic_update"), (device_copy, "_copy"),
              (lockstep.LockstepSolver, "boundary"), (StackedElasticTerms, "plastic_update")]
    for cls, name in parts:
        if name not in vars(cls):
            continue
        fn = vars(cls)[name]
        label = f"{getattr(cls, '__name__', cls)}.{name}"
        timers[label] = [0, 0.0]
        is_cm = isinstance(fn, classmethod)
        raw = fn.__func__ if is_cm else fn

        wrapped = _timed(raw, timers[label])
        setattr(cls, name, classmethod(wrapped) if is_cm else wrapped)
    _time_within(timers, CopyLineSearch, "_line_search_copies", lockstep.LockstepSolver, "_stacked_gradient")
    _time_within(timers, CopyLineSearch, "_line_search_copies", device_copy, "_copy")
    # the candidate searches (one _search_position each), those of the line search's trial points apart
    timers["ContactSet._search_position"] = [0, 0.0]
    setattr(ContactSet, "_search_position", _timed(vars(ContactSet)["_search_position"],
                                                   timers["ContactSet._search_position"]))
    for name in ("_search_position", "_candidate_pairs", "_search"):
        _time_within(timers, CopyLineSearch, "_line_search_copies", ContactSet, name)
    # a trial point's own parts (the line search's time by part: its positions, contact potentials, gradient, energies,
    # the slope read or the device backtrack's decision)
    within = [(ContactSet, "potentials"), (ContactSet, "covers"), (PairBatch, "evaluate"),
              (CopyLineSearch, "_launch_copy_energies")]
    if backend != "numpy":
        within += [(DeviceIterates, n) for n in ("gradient", "trial", "trial_by")]
        within += [(CopyVectors, "scalars")]
        from importlib.util import find_spec

        if find_spec("sim_core.ti_kernels.backtrack") is not None:  # (a tree with the device backtrack)
            from sim_core.ti_kernels.backtrack import DeviceBacktrack

            within += [(DeviceBacktrack, "decide"), (DeviceBacktrack, "start")]
    for cls, name in within:
        if name in vars(cls):
            _time_within(timers, CopyLineSearch, "_line_search_copies", cls, name)
    timers.update(_count_taichi_calls())
    # module functions the contact set calls by the names it imported
    for name in ("lookup_pairs", "merge_rows"):
        if hasattr(contact_set, name):
            setattr(contact_set, name, getattr(pair_lists, name))
    return timers


def _count_taichi_calls() -> dict:
    """Count Taichi's kernel launches and new ndarrays (``Program.launch_kernel`` / ``create_ndarray``, through which
    every launch and device array goes); returns ``{"Taichi launches": [calls, 0.0], "Taichi new ndarrays": ...}``."""
    from taichi._lib.core.taichi_python import Program

    counts = {}
    for label, name in (("Taichi launches", "launch_kernel"), ("Taichi new ndarrays", "create_ndarray")):
        record = counts[label] = [0, 0.0]

        def counted(self, *a, _fn=getattr(Program, name), _record=record, **kw):
            _record[0] += 1
            return _fn(self, *a, **kw)
        setattr(Program, name, counted)
    return counts


def _timed(fn, record: list):
    """``fn`` wrapped to add each call to ``record`` (``[calls, seconds]``)."""
    import functools

    @functools.wraps(fn)
    def wrapped(*a, **kw):
        t = time.perf_counter()
        try:
            return fn(*a, **kw)
        finally:
            record[0] += 1
            record[1] += time.perf_counter() - t
    return wrapped


def _time_within(timers: dict, outer_cls, outer: str, cls, name: str) -> None:
    """Add a timer ``cls.name (in outer)`` of the (wrapped) ``cls.name``'s calls made while the (wrapped)
    ``outer_cls.outer`` runs, e.g. the line search's trial points' gradients apart from the Newton iterates'."""
    import functools

    label = f"{getattr(cls, '__name__', cls)}.{name} (in {outer})"
    timers[label] = [0, 0.0]
    depth = [0]
    outer_fn, inner_fn = vars(outer_cls)[outer], vars(cls)[name]

    @functools.wraps(outer_fn)
    def outer_wrapped(*a, **kw):
        depth[0] += 1
        try:
            return outer_fn(*a, **kw)
        finally:
            depth[0] -= 1

    timed = _timed(inner_fn, timers[label])

    @functools.wraps(inner_fn)
    def inner_wrapped(*a, **kw):
        return (timed if depth[0] else inner_fn)(*a, **kw)

    setattr(outer_cls, outer, outer_wrapped)
    setattr(cls, name, inner_wrapped)


if __name__ == "__main__":
    sys.exit(main())
