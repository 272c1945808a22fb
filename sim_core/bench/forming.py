"""``thinshell bench forming``: ThinShellLab's Forming scene along the benchmark trajectory, timed.

The scene (``config/scenes/forming.yaml``, 1698 DoF) is driven by the benchmark trajectory of
DESIGN.md (49 steps, :func:`sim_core.tasks.trajectories.forming_benchmark_offsets`) on the solver
backend of ``arch`` (what the sim node runs with its ``backend`` parameter set alike). The record's
keys are listed in :func:`sim_core.bench.cli.bench_forming_main`.
"""

from __future__ import annotations

import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from sim_core import adjoint
from sim_core.backend import backend_of_arch
from sim_core.bench.process import peak_rss_mib, process_start_time
from sim_core.control import Control
from sim_core.elastic_worker import ElasticWorker
from sim_core.kernel_compile import compile_kernels
from sim_core.scenes.task_scene import load_task_scene, task_initial_state
from sim_core.simulation import Simulation
from sim_core.solver import SolverConfig
from sim_core.tasks.trajectories import forming_benchmark_offsets, pose_targets


def bench_simulation(model, arch: str):
    """The :class:`sim_core.simulation.Simulation` of ``model`` on the backend of ``arch`` (``numpy``,
    ``cpu``, ``cuda``: ``SolverConfig.backend`` ``numpy``, ``taichi-cpu``, ``taichi-cuda``), the
    solver's other settings at their defaults (what the sim node runs with ``backend`` set alike).

    Raises:
        ConfigError: unknown arch, or a Taichi arch that cannot start here.
    """
    return Simulation(model, solver_config=SolverConfig(backend=backend_of_arch(arch)))


def compile_bench_kernels(sim, arch: str) -> float:
    """JIT the Taichi kernels the steps will call (fused elastic terms, projected fallback) and build the
    solver's per-model structures (:meth:`Simulation.warm_up`: the fused evaluator on its sparsity
    pattern); seconds.

    Kept out of the timed steps (reported as ``jit_s``; ``cold_start_s`` still includes it).
    """
    if arch == "numpy":
        return 0.0
    t0 = time.perf_counter()
    compile_kernels(sim.solver.elastic.potentials(sim.state.hinge_theta_bar), sim.state.x, sim.solver.config.projection)
    sim.warm_up()
    return time.perf_counter() - t0


def run_forming(scene: str | Path, steps: int, backward: bool = False, arch: str = "numpy",
                elastic_worker: ElasticWorker | None = None) -> dict:
    """Step the Forming scene along the benchmark trajectory and time it.

    Args:
        scene: path of the Forming scene file.
        steps: number of steps (1..49).
        backward: also time a backward pass with ``sim_core.adjoint.rollout_gradient``.
        arch: ``numpy`` or, after ``init_backend``, ``cpu`` / ``cuda`` (Taichi element kernels).
        elastic_worker: a :class:`sim_core.elastic_worker.ElasticWorker` for the solver (``cpu``
            only; the steps start once it is ready, its start-up counted in ``jit_s``), or None.

    Returns:
        the result record (keys: :func:`sim_core.bench.cli.bench_forming_main`).

    Raises:
        ConfigError: bad scene or step count.
    """

    t_build = time.perf_counter()
    model = load_task_scene(scene)
    sim = bench_simulation(model, arch)
    sim.state = task_initial_state(model)
    sim.solver.elastic_worker = elastic_worker
    jit_s = compile_bench_kernels(sim, arch)
    if elastic_worker is not None:
        t_ready = time.perf_counter()
        elastic_worker.wait_ready()
        jit_s += time.perf_counter() - t_ready
    build_s = time.perf_counter() - t_build - jit_s
    effector = next(iter(model.effectors))
    targets = pose_targets(model.effectors[effector].initial_pose, forming_benchmark_offsets(steps))
    iterations, factorizations, t_assembly, t_linear, step_times = [], [], 0.0, 0.0, []
    states, controls, records = [sim.state.copy()], [], []
    cold_start = None
    for k in range(steps):
        control = Control()
        control.effector_pose_target[effector] = targets[k]
        t0 = time.perf_counter()
        info = sim.step(control)
        step_times.append(time.perf_counter() - t0)
        if cold_start is None:
            cold_start = time.time() - process_start_time()
        iterations.append(info.iterations)
        factorizations.append(info.factorizations)
        t_assembly += info.time_assembly
        t_linear += info.time_linear_solve
        controls.append(control)
        states.append(sim.state.copy())
        if backward:
            records.append(sim.solver.last_record)
    total = float(sum(step_times))
    result = {
        "bench": "forming",
        "dofs": int(model.dof_count),
        "vertices": int(model.vertex_count),
        "steps": int(steps),
        "steps_per_s": steps / total,
        "step_time_mean_s": total / steps,
        "newton_iters_mean": float(np.mean(iterations)),
        "newton_iters_max": int(np.max(iterations)),
        "factorizations_mean": float(np.mean(factorizations)),
        "assembly_share": t_assembly / total,
        "linear_solve_share": t_linear / total,
        "cold_start_s": float(cold_start),
        "scene_build_s": build_s,
        "jit_s": jit_s,
        "forward_total_s": total,
        "arch": arch,
        "backend": sim.solver.backend,
        "taichi_terms": [],  # kept in the schema; no elastic potential is swapped for its Taichi twin
        "linear_solver": sim.solver.linear_solver.name,
        "peak_rss_mib": peak_rss_mib(),
        # the worker process of the gel's elastic term (sim_core.elastic_worker): used, and its memory
        "elastic_worker": bool(elastic_worker is not None and elastic_worker.ready),
        "worker_peak_rss_mib": None if elastic_worker is None else elastic_worker.peak_rss_mib(),
        "python": platform.python_version(),
        # the interpreter binary: its build (static or shared libpython) moves the bench by ~10 %
        "python_executable": os.path.realpath(sys.executable),
        "numpy": np.__version__,
    }
    if backward:
        sheet = model.bodies["sheet"]
        trajectory = adjoint.Trajectory(states=states, records=records, controls=controls,
                                        model_revision=model.revision)
        dl_dx = np.zeros((steps + 1,) + sim.state.x.shape)
        dl_dx[-1, sheet.vertex_start : sheet.vertex_stop] = 1.0  # loss: sum of final sheet coordinates
        t0 = time.perf_counter()
        adjoint.rollout_gradient(sim, trajectory, dl_dx)
        t_back = time.perf_counter() - t0
        result["backward_total_s"] = t_back
        result["backward_steps_per_s"] = steps / t_back
    return result


def repeat_forming(runs: list[dict]) -> dict:
    """One record of several :func:`run_forming` runs of the same process, first run first.

    The first run's record (its cold start and JIT time: later runs find the kernels compiled) with
    the speed figures of the median run (by ``steps_per_s``; the lower middle one of an even count):
    ``steps_per_s``, ``step_time_mean_s``, ``forward_total_s`` and the shares; plus ``repeat``,
    ``steps_per_s_runs`` (every run's, in order) and ``steps_per_s_best``. Newton iteration counts
    are the same in every run (the steps are deterministic).

    Raises:
        ValueError: no runs.
    """
    if not runs:
        raise ValueError("repeat_forming: no runs")
    rates = [r["steps_per_s"] for r in runs]
    median = sorted(runs, key=lambda r: r["steps_per_s"])[(len(runs) - 1) // 2]
    out = dict(runs[0])
    for key in ("steps_per_s", "step_time_mean_s", "forward_total_s", "assembly_share", "linear_solve_share"):
        out[key] = median[key]
    worker_rss = [r["worker_peak_rss_mib"] for r in runs if r.get("worker_peak_rss_mib") is not None]
    out.update(repeat=len(runs), steps_per_s_runs=rates, steps_per_s_best=max(rates),
               peak_rss_mib=max(r["peak_rss_mib"] for r in runs),
               elastic_worker=all(r.get("elastic_worker", False) for r in runs),
               worker_peak_rss_mib=max(worker_rss) if worker_rss else None)
    return out


def print_forming(r: dict) -> None:
    print(f"thinshell bench forming ({r['arch']}, linear solver {r['linear_solver']}, Python {r['python']}, NumPy {r['numpy']})")
    print(f"  DoF                      {r['dofs']} ({r['vertices']} vertices)")
    print(f"  steps                    {r['steps']}")
    print(f"  steps/s                  {r['steps_per_s']:.3f}  ({1e3 * r['step_time_mean_s']:.1f} ms/step)")
    if r.get("repeat", 1) > 1:
        print(f"    median of {r['repeat']} runs: " + ", ".join(f"{v:.1f}" for v in r["steps_per_s_runs"])
              + f" (best {r['steps_per_s_best']:.1f})")
    print(f"  Newton iterations/step   {r['newton_iters_mean']:.2f} (max {r['newton_iters_max']}; "
          f"{r['factorizations_mean']:.2f} factorisations)")
    print(f"  assembly share           {100 * r['assembly_share']:.1f} %")
    print(f"  linear-solve share       {100 * r['linear_solve_share']:.1f} %")
    print(f"  cold start               {r['cold_start_s']:.2f} s (process start to end of first step; "
          f"Taichi JIT {r['jit_s']:.2f} s)")
    print(f"  peak RSS                 {r['peak_rss_mib']:.0f} MiB")
    if r.get("elastic_worker"):
        print(f"  elastic worker           on (gel term in a second process, peak RSS {r['worker_peak_rss_mib'] or 0:.0f} MiB)")
    else:
        print("  elastic worker           off")
    if "backward_total_s" in r:
        print(f"  backward                 {r['backward_steps_per_s']:.3f} steps/s ({r['backward_total_s']:.2f} s)")
