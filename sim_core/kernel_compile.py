"""Ahead-of-time compilation of the Taichi kernels a Newton step runs: the fused elastic parts, their projected
Hessians, the contact, broad-phase, candidate and friction kernels (:func:`compile_kernels`), and the kernels an
elastic worker runs (:func:`compile_offload_kernels`), those of a simulator node's scene (:func:`compile_scene`) and of
a task's batched optimiser (:func:`compile_task`). Taichi compiles a kernel at its first call; running these first
keeps the compilation out of the first step and lets a parent compile before it forks its workers.
"""

from __future__ import annotations

import time
from typing import Sequence

import numpy as np

from sim_core.assembly import HessianAssembler
from sim_core.energies.kirchhoff_bending.reference import KirchhoffBending
from sim_core.energies.membrane.reference import SpringMembrane
from sim_core.energies.neohookean.reference import StableNeoHookean
from sim_core.fused_elastic import FusedElastic
from sim_core.mesh.sheet import grid_sheet, sheet_topology
from sim_core.mesh.tet import tet_box


def compile_kernels(potentials: Sequence, x: np.ndarray, projection: str = "clamp") -> float:
    """JIT-compile (or load from Taichi's offline cache) the kernels a Newton step on ``potentials`` uses.

    Taichi compiles a kernel on its first call, so the first Newton step would otherwise pay for it:
    this runs the fused kernels once at ``x``, their ``projection`` Hessian of the projected
    fallback (and that of the potentials that are Taichi twins, ``sim_core/energies/<energy>/kernel.py``; on CUDA
    also the device projection's kernels of a lockstep batch, :func:`sim_core.ti_kernels.block_projection.
    compile_kernels`), and the contact distance kernels (:mod:`sim_core.energies.contact.distance_kernel`), the
    broad phase (and its candidate-list kernel, :mod:`sim_core.ti_kernels.sweep_candidates`) and friction kernels.
    Kernels take ``ti.types.ndarray`` arguments, so they compile once per dtype and rank, not per problem size.

    Args:
        potentials: the elastic potentials (:meth:`sim_core.elastic.ElasticTerms.potentials`).
        x: positions ``(n, 3)`` in m (the rest shape will do).
        projection: the solver's PSD projection.

    Returns:
        seconds spent.

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """
    # optional heavy dependency: Taichi, loaded on a Taichi backend only
    from sim_core.ti_backend import require_backend

    require_backend("compile_kernels")
    t0 = time.perf_counter()
    x = np.ascontiguousarray(x, dtype=np.float64)
    fused = FusedElastic(potentials)
    fused.bind(HessianAssembler(x.size).static_pattern(fused.block_vertex_arrays(x), np.ones(x.size, bool)))
    fused.gradient(x)
    fused._kept = None
    fused.energy(x)
    if projection != "none":
        fused.projected_hessian_values(x, projection)
    for p in potentials:
        if type(p).__module__.endswith(".kernel"):  # a Taichi twin (sim_core/energies/<energy>/kernel.py)
            p.hessian(x, projection)
    # optional heavy dependency: Taichi, loaded on a Taichi backend only
    from sim_core.energies.contact import batch_kernel as contact_batch
    from sim_core.energies.contact import distance_kernel as contact_distance
    from sim_core.energies.contact import setup_kernel as contact_setup
    from sim_core.energies.friction import rows_kernel as friction_rows
    from sim_core.energies.friction import kernel as friction
    from sim_core.energies.hinge_bending import fused_kernel as fused_hinge
    from sim_core.ti_kernels import block_projection, broad_phase, compaction, hash_candidates, sweep_candidates

    fused_hinge.compile_kernels()  # the anisotropic bending candidate's part
    contact_distance.compile_kernels()
    contact_batch.compile_kernels()
    contact_setup.compile_kernels()
    broad_phase.compile_kernels()
    sweep_candidates.compile_kernels()
    hash_candidates.compile_kernels()
    compaction.compile_kernels()
    friction.compile_kernels()
    friction_rows.compile_kernels()  # the friction rows built on the device (a CUDA step's set-up)
    if projection != "none":
        block_projection.compile_kernels()  # on CUDA: the device projection of a lockstep batch's blocks
    return time.perf_counter() - t0


def compile_offload_kernels() -> float:
    """JIT-compile (or load from Taichi's offline cache) the kernels an
    :class:`~sim_core.elastic_worker.ElasticWorker` may run (the parts with an ``offload_recipe``:
    spring membrane, Kirchhoff bending and Stable Neo-Hookean, the last also projected), on a small
    sheet and tet box; seconds spent (the worker does this before it reports ready).

    Raises:
        ConfigError: the Taichi backend is not initialised.
    """
    # optional heavy dependency: Taichi, loaded on a Taichi backend only
    from sim_core.ti_backend import require_backend

    require_backend("compile_offload_kernels")
    t0 = time.perf_counter()
    sheet = grid_sheet((0.02, 0.02), (3, 3), (0.0, 0.0, 0.0))
    topo = sheet_topology(sheet.triangles)
    box = tet_box((0.01, 0.01, 0.01), (2, 2, 2), (0.0, 0.0, 0.02))
    x = np.concatenate([sheet.x, box.x])
    tets = box.tets + sheet.x.shape[0]
    terms = [SpringMembrane(sheet.triangles, topo.edges, sheet.x, 1000.0, 800.0),
             KirchhoffBending(sheet.triangles, topo.hinges, sheet.x, 2e-3, 0.3, np.zeros(topo.hinges.shape[0])),
             StableNeoHookean(tets, x, 3e5, 0.45)]
    fused = FusedElastic(terms)
    fused.bind(HessianAssembler(x.size).static_pattern(fused.block_vertex_arrays(x), np.ones(x.size, bool)))
    fused.gradient(x)
    for projection in ("clamp", "abs"):
        fused.projected_hessian_values(x, projection)
    return time.perf_counter() - t0


COMPILE_SCENES: tuple[str, ...] = ("scenes/press_slide.yaml", "scenes/forming.yaml")
"""The bundled scenes (relative to :func:`sim_core.bundled.config_dir`) whose kernels ``thinshell compile``
compiles by default: the tactile scene of the sim node, sysid and the main job, and a ThinShellLab task scene."""


def compile_scene(scene, steps: int = 4, press: float = 2.0e-4, arch: str = "cpu") -> dict:
    """Compile (or load from the offline cache) the Taichi kernels a simulator node on ``scene`` runs.

    Builds the simulation as the sim node does (``SolverConfig`` with fixed points, sleeping and the
    carried start; :meth:`Simulation.warm_up`), runs :func:`compile_kernels` on its elastic potentials
    and takes ``steps`` steps with every effector moved ``press`` m a step along -z of ``world``
    (towards the table in the bundled scenes), so the step's own paths run once.

    Args:
        scene: scene file path.
        steps: steps to take (>= 0).
        press: effector displacement a step, m.
        arch: ``cpu`` or ``cuda``.

    Returns:
        ``{"scene": name, "compile_s": s, "steps_s": s}``.

    Raises:
        ConfigError: invalid scene, or the Taichi backend cannot start.
    """
    # optional heavy dependency: the simulation and its solver settings, loaded when compiling
    from sim_core.backend import backend_of_arch
    from sim_core.control import Control
    from sim_core.simulation import Simulation
    from sim_core.solver_config import SolverConfig

    t0 = time.perf_counter()
    sim = Simulation.from_scene(scene, solver_config=SolverConfig(
        backend=backend_of_arch(arch), repeat_fixed_points=True, sleeping=True, carried_start=True))
    sim.warm_up()
    compile_kernels(sim.solver.elastic.potentials(sim.state.hinge_theta_bar), sim.state.x, sim.solver.config.projection)
    t1 = time.perf_counter()
    start = {name: np.array(sim.state.effector_pose[name], dtype=float) for name in sim.effector_names}
    for k in range(1, steps + 1):
        target = {name: pose + np.array([0.0, 0.0, -press * k, 0.0, 0.0, 0.0, 0.0]) for name, pose in start.items()}
        sim.step(Control(effector_pose_target=target))
    return {"scene": str(getattr(scene, "name", scene)), "compile_s": t1 - t0, "steps_s": time.perf_counter() - t1}


def compile_task(name: str, arch: str = "cpu", copies: int = 2, steps: int = 2, seed: int = 0) -> dict:
    """Compile (or load from the offline cache) the Taichi kernels that ``thinshell optimise NAME --batched`` runs:
    the optimiser's own batched evaluator (:func:`sim_core.optim.evaluators.make_evaluator`, the solver settings of
    :func:`~sim_core.optim.evaluators.optimiser_solver_config`: on ``cuda`` the lockstep's device solver, its contact,
    friction and iterate kernels) on a population of ``copies`` action sequences of ``steps`` steps, then one single
    environment of the same sequence (the replays ``thinshell optimise`` writes its outputs with).

    Taichi writes the kernels a process compiled into its offline cache (at exit:
    :func:`sim_core.ti_backend.write_offline_cache`), so an optimiser started after this compiles none of them; each
    process still generates their code from the cache at their first launch (docs/benchmarks_log.md, session 56).

    Args:
        name: a task name (``config/tasks``) or a task file.
        arch: ``cpu`` or ``cuda``.
        copies: copies of the population (>= 2: a lockstep batch).
        steps: steps of each sequence, 1 .. the task's horizon.
        seed: seed of the copies' perturbations.

    Returns:
        ``{"task": name, "kernels_s": s}``.

    Raises:
        ConfigError: unknown task, ``copies`` < 2, ``steps`` outside 1 .. the horizon, or the Taichi backend cannot
            start.
    """
    # optional heavy dependency: the tasks and the optimiser's evaluators, loaded when compiling
    from sim_core.backend import backend_of_arch
    from sim_core.errors import ConfigError
    from sim_core.optim.evaluators import make_evaluator, optimiser_solver_config
    from sim_core.tasks.registry import load_task

    task = load_task(name)
    if copies < 2:
        raise ConfigError(f"compile_task: {copies} copies; a lockstep batch needs at least 2")
    if not 1 <= steps <= task.horizon:
        raise ConfigError(f"compile_task: {steps} steps; task {task.name} takes 1 .. {task.horizon}")
    t0 = time.perf_counter()
    config = optimiser_solver_config(backend_of_arch(arch))
    low, high = task.action_low, task.action_high
    start = task.reference_actions[:steps] if task.reference_actions is not None else \
        np.tile((low + high) / 2.0, (steps, 1))
    rng = np.random.default_rng(seed)
    actions = [start] + [np.clip(start + rng.uniform(-0.1, 0.1, start.shape) * (high - low), low, high)
                         for _ in range(copies - 1)]
    make_evaluator(task, horizon=steps, solver_config=config, batched=True).evaluate(actions)
    make_evaluator(task, horizon=steps, solver_config=config).evaluate(actions[:1])
    return {"task": task.name, "kernels_s": time.perf_counter() - t0}


def compile_main(argv: Sequence[str]) -> int:
    """``thinshell compile [--scene S ...] [--task T ...] [--arch cpu|cuda] [--steps N]``: compile the simulator's
    Taichi kernels once, ahead of the first run, into Taichi's offline cache (``make setup`` runs it for the bundled
    scenes); later processes load them instead of compiling. ``--task``: the kernels of ``thinshell optimise T
    --batched`` on that arch (:func:`compile_task`), instead of the bundled scenes unless ``--scene`` is given too.
    Prints one line a scene or task and the total time."""
    import argparse

    # optional heavy dependency: the bundled scenes and the Taichi runtime, loaded when compiling
    from sim_core.bundled import config_dir
    from sim_core.ti_backend import init_backend

    p = argparse.ArgumentParser(prog="thinshell compile", description=compile_main.__doc__.split("\n")[0])
    p.add_argument("--scene", nargs="+", default=None, help="scene files (default: the bundled "
                   + ", ".join(COMPILE_SCENES) + ")")
    p.add_argument("--task", nargs="+", default=[],
                   help="tasks whose batched optimiser's kernels to compile (thinshell optimise TASK --batched)")
    p.add_argument("--arch", choices=("cpu", "cuda"), default="cpu")
    p.add_argument("--steps", type=int, default=4, help="steps taken on each scene after compiling (default 4)")
    args = p.parse_args(list(argv))
    if args.steps < 0:
        p.error("--steps must be >= 0")
    scenes = args.scene or ([] if args.task else [config_dir() / name for name in COMPILE_SCENES])
    t0 = time.perf_counter()
    init_backend(args.arch)
    print(f"thinshell compile: compiling the simulator's kernels for {len(scenes)} scene(s) and {len(args.task)} "
          f"task(s) into Taichi's offline cache (once per machine; later runs load them)", flush=True)
    if scenes:
        t_offload = compile_offload_kernels()
        print(f"  elastic worker kernels: {t_offload:.1f} s", flush=True)
    for name in args.task:
        out = compile_task(name, arch=args.arch)
        print(f"  task {out['task']} (batched optimiser): {out['kernels_s']:.1f} s", flush=True)
    for scene in scenes:
        out = compile_scene(scene, steps=args.steps, arch=args.arch)
        print(f"  {out['scene']}: {out['compile_s']:.1f} s compile, {out['steps_s']:.1f} s for {args.steps} steps",
              flush=True)
    print(f"thinshell compile: done in {time.perf_counter() - t0:.1f} s", flush=True)
    return 0
