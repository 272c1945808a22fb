"""``thinshell bench batch``: scene-steps per second and memory per copy of a batch against its size ``B``.

Scenes: ``forming`` (the Forming benchmark scene of ``thinshell bench forming``, 1698 DoF: copy ``i``
of ``B`` follows the benchmark trajectory scaled by ``1 - 0.1 i / B``, so the copies differ) or a
task name (``config/tasks``: a population of the task's reference actions with seeded uniform noise
of 20 % of the per-step bounds, clipped, rolled out with
:class:`sim_core.tasks.rollout.PopulationRollout`; inverse tasks at their true parameters).

Per size: ``scene_steps_per_s`` (steps of all copies / wall seconds of the batched steps, the first
step's set-up included), ``steady_scene_steps_per_s`` (the same over the steps after the first: the rate a
long rollout approaches once the first step has built the batch's static pattern, fused binds and first
contact search; None with one step) and ``first_step_s``, ``steps_per_s_per_copy``, the mean Newton iterations,
failed copies, with a lockstep batch's device solver its name (``device_solver``: ``pcg``, ``envelope``) and its
``linear_iterations_per_step`` (CG iterations, or an envelope solve's one plus its refinements, summed over the
step's solves) and ``factorizations_per_step``, ``rss_per_copy_mib`` (growth of
the process's resident memory from before the batch was built to after its steps, divided by ``B``)
and, on CUDA, ``gpu_mib_per_copy`` (growth of this process's GPU memory as ``nvidia-smi`` reports it,
divided by ``B``; Taichi's preallocated memory pool is in the baseline, so this counts only what
the copies add beyond it). The kernels are compiled before the first size by one short batch of one
copy and the projected-Hessian kernels (``jit_s``).

``--sizes auto``: one size, the largest ``B`` that fits (:mod:`sim_core.batch.sizing`): probe batches of
one and two copies, built and stepped after the compilation, give the memory per copy (host: the larger
of resident-set and traced-heap growth; on CUDA also this process's GPU memory, where it grows beyond
Taichi's pool); the free memory (``/proc/meminfo`` ``MemAvailable``;
``nvidia-smi --query-gpu=memory.free``) less a reserve (``--reserve``, default 20 %) over it gives
``B``, at most ``--max-size``. The record adds ``auto_B``, ``auto_limit`` (``host``, ``gpu`` or
``cap``), ``host_mib_per_copy_probe``, ``host_mib_free`` and, on CUDA, ``gpu_mib_per_copy_probe``,
``gpu_mib_free``.
"""

from __future__ import annotations

import argparse
import gc
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

from sim_core.batch.sizing import MIB, gpu_used_bytes, host_used_bytes
from sim_core.bundled import config_dir

ARCH_BACKENDS = {"numpy": "numpy", "cpu": "taichi-cpu", "cuda": "taichi-cuda"}
DEFAULT_SIZES = (1, 2, 4, 8)


def current_rss_mib() -> float:
    """Resident set size of this process now, MiB (``/proc/self/statm``; 0 where unavailable)."""
    used = host_used_bytes()
    return 0.0 if used is None else used / MIB


def gpu_memory_mib() -> float | None:
    """GPU memory used by this process, MiB, as ``nvidia-smi --query-compute-apps`` reports it; None
    where ``nvidia-smi`` is missing or lists no memory for this process."""
    used = gpu_used_bytes()
    return None if used is None else used / MIB


def _forming_scene() -> Path:
    return config_dir() / "scenes" / "forming.yaml"


class _FormingRun:
    """``B`` copies of the Forming benchmark scene on one backend, each on its scaled trajectory."""

    def __init__(self, B: int, steps: int, backend: str, lockstep: bool = False, linear_solver: str | None = None) -> None:
        from sim_core.batch.simulation import BatchedSimulation
        from sim_core.scenes.task_scene import load_task_scene, task_initial_state
        from sim_core.tasks.trajectories import forming_benchmark_offsets, pose_targets

        model = load_task_scene(_forming_scene())
        self.batch = BatchedSimulation.from_model(model, B, solver_config=_config(backend, lockstep, linear_solver),
                                                  state=task_initial_state(model))
        self.effector = next(iter(model.effectors))
        pose0 = model.effectors[self.effector].initial_pose
        offsets = forming_benchmark_offsets(steps)
        self.targets = [pose_targets(pose0, offsets * (1.0 - 0.1 * i / B)) for i in range(B)]
        self.steps = steps

    def run(self) -> tuple[int, list[int], int, list[tuple[int, float]]]:
        """Step; returns (steps done by all copies, Newton iterations of each step, failed copies, per step
        its scene-steps and wall seconds)."""
        from sim_core.control import Control

        self.batch.warm_up()
        done, iterations, per_step = 0, [], []
        for k in range(self.steps):
            res = self.batch.step([Control(effector_pose_target={self.effector: t[k]}) for t in self.targets])
            stepped = [info for info in res.infos if info is not None]
            done += len(stepped)
            iterations += [info.iterations for info in stepped]
            per_step.append((len(stepped), res.wall_s))
        return done, iterations, int((~self.batch.active).sum()), per_step


class _TaskRun:
    """A population of ``B`` perturbed reference trajectories of a task (:class:`PopulationRollout`)."""

    def __init__(self, name: str, B: int, steps: int, backend: str, lockstep: bool = False, seed: int = 0,
                 linear_solver: str | None = None) -> None:
        from sim_core.errors import ConfigError
        from sim_core.tasks.registry import load_task
        from sim_core.tasks.rollout import PopulationRollout

        task = load_task(name)
        if task.reference_actions is None:
            raise ConfigError(f"task {task.name} has no reference trajectory to perturb")
        ref = task.reference_actions[:steps]
        rng = np.random.default_rng(seed)
        span = 0.2 * (task.action_high - task.action_low) / 2.0
        actions = [ref] + [np.clip(ref + rng.uniform(-1.0, 1.0, ref.shape) * span, task.action_low, task.action_high)
                           for _ in range(B - 1)]
        self.population = PopulationRollout(task, actions, task.true_parameters or None, backend=backend,
                                            solver_config=_config(backend, lockstep, linear_solver))
        self.batch = self.population.batch

    def run(self) -> tuple[int, list[int], int, list[tuple[int, float]]]:
        """As :meth:`_FormingRun.run`; a step's wall time is the sum of its members' shares
        (``StepInfo.time_total``: the batched step's wall time divided among the copies it stepped)."""
        results = self.population.run()
        iterations = [info.iterations for r in results for info in r.step_infos]
        failed = sum(1 for r in results if r.infeasible is not None and r.infeasible.startswith("solver failure"))
        per_step: dict[int, list] = {}
        for r in results:
            for k, info in enumerate(r.step_infos):
                count_wall = per_step.setdefault(k, [0, 0.0])
                count_wall[0] += 1
                count_wall[1] += info.time_total
        return (sum(r.steps_done for r in results), iterations, failed,
                [(int(c), float(w)) for _, (c, w) in sorted(per_step.items())])


def _config(backend: str, lockstep: bool, linear_solver: str | None):
    """The copies' :class:`~sim_core.solver_config.SolverConfig`: ``linear_solver`` where given, else the default."""
    from sim_core.solver_config import SolverConfig

    extra = {} if linear_solver is None else {"linear_solver": linear_solver}
    return SolverConfig(backend=backend, lockstep=lockstep, **extra)


def _make_run(scene: str, B: int, steps: int, backend: str, lockstep: bool, linear_solver: str | None = None):
    if scene == "forming":
        return _FormingRun(B, steps, backend, lockstep, linear_solver)
    return _TaskRun(scene, B, steps, backend, lockstep, linear_solver=linear_solver)


def _solver_counts(run) -> tuple[str | None, int, int]:
    """``(name, total linear iterations, factorisations)`` of a lockstep batch's device solver (``(None, 0, 0)``
    without one)."""
    engine = getattr(run.batch, "lockstep", None)
    solver = None if engine is None else engine.solver.pcg
    if solver is None:
        return None, 0, 0
    return solver.name, int(solver.total_iterations), int(solver.factorizations)


def bench_batch(scene: str, sizes: list[int] | str, steps: int, arch: str, on_row=None, lockstep: bool = False,
                max_size: int | None = None, reserve_fraction: float = 0.2,
                linear_solver: str | None = None) -> list[dict]:
    """Time batches of each size in ``sizes`` (one after the other, each built, stepped and dropped).

    Args:
        scene: ``forming`` or a task name.
        sizes: batch sizes ``B >= 1``, or ``"auto"``: the largest ``B`` that fits (module docstring).
        max_size: with ``"auto"``, the largest ``B`` to run (None: no bound but the memory).
        reserve_fraction: with ``"auto"``, the fraction of the free memory left unused.
        steps: steps per copy (Forming: 1..49; a task: 1..horizon).
        arch: ``numpy``, ``cpu`` or ``cuda`` (``SolverConfig.backend`` ``numpy`` / ``taichi-cpu`` /
            ``taichi-cuda``).
        on_row: called with each record as soon as it is measured (a long run keeps what it measured
            when it is stopped), or None.
        lockstep: step the copies together (``SolverConfig.lockstep``, :mod:`sim_core.batch.lockstep`)
            instead of one after another.
        linear_solver: ``SolverConfig.linear_solver`` of the copies (None: its default; a lockstep batch on CUDA
            then takes the envelope Cholesky), e.g. ``"pcg"``.

    Returns:
        one record per size (keys in the module docstring, plus ``B``, ``steps``, ``scene``, ``arch``,
        ``backend``, ``dofs``, ``wall_s``, ``build_s``, ``jit_s`` (first record only)).

    Raises:
        ConfigError: unknown scene, task without reference, arch not available here, bad sizes, a probe
            that measured no memory growth.
        InsufficientMemoryError: ``"auto"`` and not even one copy fits.
    """
    from sim_core.backend import resolve_backend
    from sim_core.errors import ConfigError

    if arch not in ARCH_BACKENDS:
        raise ConfigError(f"--arch must be one of {', '.join(ARCH_BACKENDS)}; got {arch!r}")
    auto = sizes == "auto"
    if not auto and (not sizes or min(sizes) < 1):
        raise ConfigError(f"--sizes must be integers >= 1 or auto, got {sizes}")
    backend = resolve_backend(ARCH_BACKENDS[arch])
    t0 = time.perf_counter()
    warm = _make_run(scene, 1, min(2, steps), backend, lockstep, linear_solver)  # JIT of every kernel the steps call
    warm.run()
    sim0 = warm.batch.sims[0]
    if backend != "numpy":  # the projected-Hessian kernels too, which the short warm-up may not reach
        from sim_core.kernel_compile import compile_kernels

        compile_kernels(sim0.solver.elastic.potentials(sim0.state.hinge_theta_bar), sim0.model.x_rest)
    dofs = int(sim0.model.dof_count)
    del warm
    jit_s = time.perf_counter() - t0
    sizing = None
    if auto:
        from sim_core.batch.sizing import choose_batch_size, measure_per_copy, resources_of

        def probe(B: int):
            run = _make_run(scene, B, steps, backend, lockstep, linear_solver)
            run.run()
            return run

        per_copy = measure_per_copy(probe, resources_of(backend))
        sizing = choose_batch_size(per_copy, max_size, reserve_fraction)
        sizes = [sizing.B]
    out = []
    for B in sizes:
        gc.collect()
        rss0, gpu0 = current_rss_mib(), gpu_memory_mib()
        t0 = time.perf_counter()
        run = _make_run(scene, int(B), steps, backend, lockstep, linear_solver)
        build_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        solver_name, linear0, factorizations0 = _solver_counts(run)
        done, iterations, failed, per_step = run.run()
        wall = time.perf_counter() - t0
        _, linear1, factorizations1 = _solver_counts(run)
        later = per_step[1:]
        later_wall = sum(w for _, w in later)
        rss1, gpu1 = current_rss_mib(), gpu_memory_mib()
        out.append({
            "bench": "batch", "scene": scene, "arch": arch, "backend": backend, "dofs": dofs, "B": int(B),
            "mode": "lockstep" if lockstep else "sequential",
            "steps": steps, "scene_steps": done, "wall_s": wall, "build_s": build_s,
            "scene_steps_per_s": done / wall if wall > 0 else 0.0,
            "steady_scene_steps_per_s": sum(c for c, _ in later) / later_wall if later and later_wall > 0 else None,
            "first_step_s": per_step[0][1] if per_step else None,
            "steps_per_s_per_copy": done / wall / B if wall > 0 else 0.0,
            "newton_iters_mean": float(np.mean(iterations)) if iterations else 0.0, "failed_copies": failed,
            "device_solver": solver_name,
            "linear_iterations_per_step": (linear1 - linear0) / max(len(per_step), 1) if solver_name else None,
            "factorizations_per_step": (factorizations1 - factorizations0) / max(len(per_step), 1) if solver_name
            else None,
            "rss_per_copy_mib": (rss1 - rss0) / B,
            "gpu_mib_per_copy": None if gpu0 is None or gpu1 is None else (gpu1 - gpu0) / B,
            "gpu_mib_process": gpu1, "jit_s": jit_s if not out else 0.0,
            "python": platform.python_version(), "numpy": np.__version__,
        })
        if sizing is not None:
            out[-1].update(sizing.as_record())
        del run
        if on_row is not None:
            on_row(out[-1])
    return out


def bench_batch_main(argv: list[str] | None = None) -> int:
    """Entry point of ``thinshell bench batch``; returns the exit code (0 success, 1 a copy failed,
    2 a usage error or an arch that cannot start here)."""
    from sim_core.errors import ConfigError

    argv = list(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(prog="thinshell bench batch", description=__doc__.splitlines()[0])
    p.add_argument("--arch", default="cpu", choices=sorted(ARCH_BACKENDS), help="backend of every copy (default cpu)")
    p.add_argument("--sizes", nargs="+", default=[str(b) for b in DEFAULT_SIZES],
                   help="batch sizes B (default 1 2 4 8), or auto: the largest B that fits the device's free memory")
    p.add_argument("--max-size", type=int, help="with --sizes auto: the largest B to run")
    p.add_argument("--reserve", type=float, default=0.2,
                   help="with --sizes auto: fraction of the free memory left unused (default 0.2)")
    p.add_argument("--scene", default="forming", help="forming (the benchmark scene) or a task name")
    p.add_argument("--steps", type=int, default=10, help="steps per copy (default 10)")
    p.add_argument("--json", action="store_true", help="print one JSON line per size")
    p.add_argument("--lockstep", action="store_true",
                   help="step the copies together: one Newton iteration for all (SolverConfig.lockstep)")
    p.add_argument("--linear-solver", choices=("pardiso", "scipy", "pcg", "envelope"),
                   help="the copies' linear solver (default: SolverConfig's; a lockstep batch on cuda takes the envelope "
                        "Cholesky): envelope, each copy's system solved directly on the device (a Taichi arch); pcg, "
                        "the batched CG")
    ns = p.parse_args(argv)
    if ns.sizes == ["auto"]:
        sizes: list[int] | str = "auto"
    else:
        try:
            sizes = [int(b) for b in ns.sizes]
        except ValueError:
            print(f"thinshell bench batch: --sizes must be integers >= 1 or auto alone; got {' '.join(ns.sizes)}",
                  file=sys.stderr)
            return 2

    def show(r: dict) -> None:
        if ns.json:
            print(json.dumps(r), flush=True)
            return
        if sizes == "auto":
            gpu_free = r.get("gpu_mib_free")
            print(f"thinshell bench batch: auto size B = {r['auto_B']} (bounded by {r['auto_limit']}): "
                  f"{r.get('host_mib_per_copy_probe', float('nan')):.1f} MiB host per copy, "
                  f"{r.get('host_mib_free', float('nan')):.0f} MiB host free"
                  + ("" if gpu_free is None else f", {r.get('gpu_mib_per_copy_probe', float('nan')):.2f} MiB GPU per copy, "
                                                 f"{gpu_free:.0f} MiB GPU free")
                  + f", reserve {100 * ns.reserve:.0f} %", flush=True)
        if r["B"] == (r["auto_B"] if sizes == "auto" else sizes[0]):
            print(f"thinshell bench batch: scene {r['scene']} ({r['dofs']} DoF), arch {r['arch']}, {r['mode']}, {ns.steps} steps per "
                  f"copy, JIT {r['jit_s']:.1f} s")
            print(f"{'B':>5} {'scene-steps/s':>14} {'steady':>9} {'steps/s/copy':>13} {'iters':>6} {'failed':>6} "
                  f"{'RSS/copy MiB':>13} {'GPU/copy MiB':>13} {'build s':>8}")
        gpu = "-" if r["gpu_mib_per_copy"] is None else f"{r['gpu_mib_per_copy']:.1f}"
        steady = "-" if r["steady_scene_steps_per_s"] is None else f"{r['steady_scene_steps_per_s']:.2f}"
        print(f"{r['B']:>5} {r['scene_steps_per_s']:>14.2f} {steady:>9} {r['steps_per_s_per_copy']:>13.2f} "
              f"{r['newton_iters_mean']:>6.2f} {r['failed_copies']:>6} {r['rss_per_copy_mib']:>13.1f} {gpu:>13} "
              f"{r['build_s']:>8.2f}", flush=True)

    try:
        rows = bench_batch(ns.scene, sizes, ns.steps, ns.arch, on_row=show, lockstep=ns.lockstep,
                           max_size=ns.max_size, reserve_fraction=ns.reserve, linear_solver=ns.linear_solver)
    except ConfigError as err:
        print(f"thinshell bench batch: {err}", file=sys.stderr)
        return 2
    return 1 if any(r["failed_copies"] for r in rows) else 0
