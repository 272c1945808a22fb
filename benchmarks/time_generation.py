"""Where a batched CMA-ES generation's wall time goes: ``thinshell optimise TASK --method cma --batched`` run as the
command runs it (:func:`sim_core.optim.cli.optimise_main`), ``--repeat`` times in one process, each run timed by part.

Usage: ``python benchmarks/time_generation.py --arch cuda --out DIR [--task folding_u] [--population 40]
[--horizon H] [--repeat 2]``; ``--arch cpu`` runs the ``taichi-cpu`` backend. Each run is one generation
(``--episodes`` = the population) written to ``DIR/runK`` (replaced). The first run pays the kernels' first use
(Taichi's frontend and compilation or offline-cache load); a later run in the same process does not, so the first
run's wall minus a later one's is the compilation and first-launch cost, and a later run's wall is what a
generation costs once the process is warm.

Per run: ``wall_time_s`` (the generations: what ``thinshell optimise`` reports in ``result.json``), each generation's
wall, the best score,
the rollouts' rewards, and the split (inclusive seconds of wrapped parts): the population's build
(:class:`~sim_core.tasks.rollout.PopulationRollout`, of which the lockstep solver's), its stepping (each batched
step's wall: the first, the rest, their mean, the lockstep's Newton iterations a step), the population's host work
around the steps (the episodes' commands, early-stop checks and logs, the rewards), the CMA-ES's own work (ask,
tell, the strategy's build), the checkpoint, the Taichi kernels' frontend (``Kernel.materialize``) and first launches
(compilation or cache load: each kernel instance's first launch), the garbage collector, and the outputs written
after the generation (``write_outputs``: two single-environment replays, the plots, outside ``wall_time_s``).
"""

from __future__ import annotations

import argparse
import functools
import gc
import sys
import time
from pathlib import Path


class _Timers:
    """Inclusive seconds and calls of wrapped callables; nested calls of one name count once (the outermost)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self._depth: dict[str, int] = {}

    def reset(self) -> None:
        self.seconds.clear()
        self.calls.clear()

    def wrap(self, owner, attr: str, name: str, each=None) -> None:
        """Replace ``owner.attr`` by a timed wrapper; ``each(seconds, result)`` is called after every outermost
        call."""
        fn = getattr(owner, attr)

        @functools.wraps(fn)
        def timed(*args, **kwargs):
            depth = self._depth.get(name, 0)
            self._depth[name] = depth + 1
            t = time.perf_counter()
            try:
                result = fn(*args, **kwargs)
            finally:
                self._depth[name] = depth
            if depth == 0:
                dt = time.perf_counter() - t
                self.seconds[name] = self.seconds.get(name, 0.0) + dt
                self.calls[name] = self.calls.get(name, 0) + 1
                if each is not None:
                    each(dt, result)
            return result

        setattr(owner, attr, timed)

    def add(self, name: str, seconds: float) -> None:
        self.seconds[name] = self.seconds.get(name, 0.0) + seconds
        self.calls[name] = self.calls.get(name, 0) + 1


def _instrument(timers: _Timers, steps: list, slow: list, generations: list) -> None:
    """Wrap the generation's parts (module docstring); ``steps`` collects ``(wall s, lockstep Newton iterations,
    mean of the stepped copies' iterations)`` of each batched step, ``slow`` ``(s, kernel name)`` of each kernel
    instance's first launch, ``generations`` each CMA-ES generation's wall (s)."""
    import cma
    from taichi.lang import kernel_impl

    import sim_core.optim.cli as cli
    import sim_core.optim.search as search
    from sim_core.batch.lockstep import LockstepSolver
    from sim_core.batch.simulation import BatchedSimulation
    from sim_core.batch.stacked import StackedScene
    from sim_core.tasks import rollout as ro

    def on_step(dt, res):
        its = [info.iterations for info in res.infos if info is not None]
        steps.append((dt, max(its, default=0), sum(its) / max(len(its), 1)))

    timers.wrap(search, "_cma_generation", "CMA-ES generations", lambda dt, _: generations.append(dt))
    timers.wrap(ro.PopulationRollout, "__init__", "population build")
    if hasattr(ro.PopulationRollout, "restart"):
        timers.wrap(ro.PopulationRollout, "restart", "population restart (resident batch)")
    timers.wrap(ro.PopulationRollout, "run", "population run")
    timers.wrap(ro.TaskEpisode, "__init__", "  episodes' build (TaskEpisode)")
    timers.wrap(BatchedSimulation, "__init__", "  batch build (BatchedSimulation)")
    timers.wrap(LockstepSolver, "__init__", "  lockstep solver build")
    timers.wrap(BatchedSimulation, "step", "batched steps", on_step)
    timers.wrap(LockstepSolver, "step_copies", "  the lockstep solver's steps (step_copies)")
    timers.wrap(StackedScene, "copy_states", "  the copies' states written back (copy_states)")
    timers.wrap(StackedScene, "stack_controls", "  the controls stacked (stack_controls)")
    timers.wrap(StackedScene, "stack_states", "  the states stacked (stack_states)")
    timers.wrap(ro.TaskEpisode, "command", "  host: commands")
    timers.wrap(ro.TaskEpisode, "record_step", "  host: early-stop checks")
    timers.wrap(ro._EpisodeLog, "add", "  host: step logs")
    timers.wrap(ro._EpisodeLog, "result", "  host: results (rewards)")
    timers.wrap(ro.TaskEpisode, "reward", "  host: rewards")
    timers.wrap(cma.CMAEvolutionStrategy, "__init__", "cma: strategy build")
    timers.wrap(cma.CMAEvolutionStrategy, "ask", "cma: ask")
    timers.wrap(cma.CMAEvolutionStrategy, "tell", "cma: tell")
    timers.wrap(cli, "save_checkpoint", "checkpoint")
    timers.wrap(cli, "write_outputs", "outputs (after the generation)")
    timers.wrap(kernel_impl.Kernel, "materialize", "taichi: kernel frontend (materialize)")
    launched: set = set()
    launch = kernel_impl.Kernel.launch_kernel

    @functools.wraps(launch)
    def first_launch(self, t_kernel, *args):
        key = (id(self), id(t_kernel))
        if key in launched:
            return launch(self, t_kernel, *args)
        launched.add(key)
        t = time.perf_counter()
        try:
            return launch(self, t_kernel, *args)
        finally:
            dt = time.perf_counter() - t
            timers.add("taichi: first launches (compile / cache load)", dt)
            slow.append((dt, getattr(self.func, "__qualname__", "?")))

    kernel_impl.Kernel.launch_kernel = first_launch
    gc_start = [0.0]

    def on_gc(phase, info):
        if phase == "start":
            gc_start[0] = time.perf_counter()
        else:
            timers.add("garbage collection", time.perf_counter() - gc_start[0])

    gc.callbacks.append(on_gc)


def _report(title: str, timers: _Timers, steps: list, slow: list) -> None:
    """Print one generation's split (and clear what it gathered)."""
    walls = [s[0] for s in steps]
    print(f"--- {title}")
    if walls:
        rest = walls[1:] or [0.0]
        print(f"steps: {len(walls)}; first {walls[0]:.3f} s ({steps[0][1]} lockstep Newton iterations); the rest "
              f"{sum(rest):.3f} s, mean {sum(rest) / len(rest) * 1e3:.1f} ms; lockstep Newton iterations a step "
              f"{sum(s[1] for s in steps) / len(steps):.2f} (the copies' own {sum(s[2] for s in steps) / len(steps):.2f})")
    if "population run" in timers.seconds:
        host = timers.seconds["population run"] - timers.seconds.get("batched steps", 0.0)
        print(f"population run's host work outside the batched steps: {host:.3f} s")
    for name in sorted(timers.seconds, key=lambda n: -timers.seconds[n]):
        print(f"  {name:55s} {timers.seconds[name]:9.3f} s {timers.calls[name]:7d} calls")
    if slow:
        slow.sort(reverse=True)
        print("slowest first launches: " + ", ".join(f"{name} {dt:.2f} s" for dt, name in slow[:8]))
    sys.stdout.flush()
    timers.reset()
    steps.clear()
    slow.clear()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--arch", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--task", default="folding_u")
    ap.add_argument("--population", type=int, default=40)
    ap.add_argument("--horizon", type=int, default=None, help="steps an episode (default: the task's)")
    ap.add_argument("--generations", type=int, default=1, help="CMA-ES generations a run (episodes = population x this)")
    ap.add_argument("--repeat", type=int, default=2, help="runs of thinshell optimise in this process")
    ap.add_argument("--outputs", choices=("all", "first", "none"), default="all",
                    help="which runs write their outputs (write_outputs: replays and plots); the others skip them")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", required=True, help="directory of the runs' outputs (DIR/runK, replaced)")
    args = ap.parse_args()
    t0 = time.perf_counter()
    import sim_core.optim.cli as cli
    from sim_core.ti_backend import init_backend

    init_backend(args.arch)
    print(f"imports and Taichi init: {time.perf_counter() - t0:.2f} s")
    timers, steps, slow, generations = _Timers(), [], [], []
    _instrument(timers, steps, slow, generations)
    import sim_core.optim.search as search

    write_outputs, run, generation = cli.write_outputs, cli._run, search._cma_generation  # (timed: _instrument)

    def timed_generation(state, space):  # each generation's split printed as it ends
        logs = generation(state, space)
        _report(f"generation {len(generations)}: {generations[-1]:.2f} s",
                timers, steps, slow)
        return logs

    def timed_run(state, *a, **kw):  # what thinshell optimise's wall_time_s times
        t = time.perf_counter()
        run(state, *a, **kw)
        wall = time.perf_counter() - t
        print(f"=== wall_time_s {wall:.2f} (the generations: {len(generations)} of {args.population}: "
              f"{', '.join(f'{g:.2f}' for g in generations)} s); best score {state.best_score!r}")
        print(f"rewards: {[h.reward for h in state.history]!r}")
        sys.stdout.flush()

    search._cma_generation, cli._run = timed_generation, timed_run
    backend = {"cpu": "taichi-cpu", "cuda": "taichi-cuda"}[args.arch]
    for k in range(1, args.repeat + 1):
        timers.reset()
        generations.clear()
        if args.outputs == "none" or (args.outputs == "first" and k > 1):
            cli.write_outputs = lambda *a, **kw: []  # the outputs not written
        else:
            cli.write_outputs = write_outputs
        print(f"====== run {k}")
        out = Path(args.out) / f"run{k}"
        argv = [args.task, "--method", "cma", "--batched", "--backend", backend,
                "--episodes", str(args.population * args.generations),
                "--population", str(args.population), "--seed", str(args.seed), "--out", str(out), "--force",
                "--no-progress"]
        if args.horizon is not None:
            argv += ["--horizon", str(args.horizon)]
        cli.optimise_main(argv)
        if cli.write_outputs is write_outputs:
            _report("after the generations (the outputs)", timers, steps, slow)
    return 0


if __name__ == "__main__":
    sys.exit(main())
