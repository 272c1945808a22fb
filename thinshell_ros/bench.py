"""``thinshell bench``: speed benchmarks of the simulator (no ROS needed).

* ``bench forming``: ThinShellLab's Forming scene (``config/scenes/forming.yaml``, 1698 DoF) driven
  by the benchmark trajectory of DESIGN.md (49 steps); prints DoF, steps/s, Newton iterations per
  step, the shares of assembly and linear solve, and the cold start (process start to the end of
  the first step). ``--json`` prints one JSON line instead.
* ``bench scale``: flat sheets of about 1k, 10k and 100k DoF under gravity, one edge clamped; time
  per step and peak resident memory; all three by default, ``--max-dofs`` skips the larger cases.
* ``--arch``: ``numpy``, ``cpu`` (default) or ``cuda``: the solver backend ``numpy``, ``taichi-cpu``
  or ``taichi-cuda`` (``SolverConfig.backend``, :mod:`sim_core.backend`; the Taichi ones run the fused
  elastic kernels of ``sim_core.fused_elastic`` in the Newton loop, compiled before the timed steps).
  The sim node runs the same backends (its ``backend`` parameter).
* ``bench node`` / ``bench diagnose`` / ``bench tasks`` / ``bench optimise`` / ``bench batch``: dispatched to
  ``thinshell_ros.bench_node.bench_node_main``, ``sysid.diagnose_bench.bench_diagnose_main``,
  ``sim_core.tasks.bench.bench_tasks_main``, ``sysid.optimise_bench.bench_optimise_main`` and
  ``sim_core.batch.bench.bench_batch_main``.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import platform
import resource
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from sim_core.elastic_worker import ElasticWorker

_IMPORT_TIME = time.time()
SUPPORTED_ARCHS = ("numpy", "cpu", "cuda")
"""``numpy``: the NumPy reference potentials; ``cpu`` / ``cuda``: Taichi kernels on that arch."""
SCALE_TARGET_DOFS = (1_000, 10_000, 100_000)


def process_start_time() -> float:
    """Wall-clock time (s since the epoch) at which this process started.

    Read from ``/proc/self/stat`` (start time in clock ticks after boot) and ``/proc/stat`` (boot
    time); falls back to the time this module was imported where ``/proc`` is unavailable.
    """
    try:
        fields = Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()
        start_ticks = int(fields[19])  # field 22 of stat(5); fields[0] is field 3
        btime = next(int(line.split()[1]) for line in Path("/proc/stat").read_text().splitlines() if line.startswith("btime"))
        return btime + start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, StopIteration):
        return _IMPORT_TIME


def peak_rss_mib() -> float:
    """Peak resident set size of this process so far, MiB (``getrusage``; KiB on Linux)."""
    kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kib / 1024.0 if sys.platform != "darwin" else kib / 2**20


def _default_scene(name: str) -> Path:
    from thinshell_ros.paths import bundled_scene

    try:
        return bundled_scene(name)
    except OSError:  # ament_index raises when AMENT_PREFIX_PATH is unset: use the source tree
        return Path(__file__).resolve().parents[1] / "config" / "scenes" / f"{name}.yaml"


def _check_arch(arch: str) -> str | None:
    """Validate ``--arch`` and start its backend (:func:`sim_core.backend.resolve_backend`: Taichi
    initialised for ``cpu`` / ``cuda``); an error message or None."""
    if arch not in SUPPORTED_ARCHS:
        return f"--arch {arch}: unknown backend (supported: {', '.join(SUPPORTED_ARCHS)})"
    from sim_core.backend import backend_of_arch, resolve_backend
    from sim_core.errors import ConfigError

    try:
        resolve_backend(backend_of_arch(arch))
    except ConfigError as err:
        return f"--arch {arch}: {err}"
    return None


def bench_simulation(model, arch: str):
    """The :class:`sim_core.simulation.Simulation` of ``model`` on the backend of ``arch`` (``numpy``,
    ``cpu``, ``cuda``: ``SolverConfig.backend`` ``numpy``, ``taichi-cpu``, ``taichi-cuda``), the
    solver's other settings at their defaults (what the sim node runs with ``backend`` set alike).

    Raises:
        ConfigError: unknown arch, or a Taichi arch that cannot start here.
    """
    from sim_core.backend import backend_of_arch
    from sim_core.simulation import Simulation
    from sim_core.solver import SolverConfig

    return Simulation(model, solver_config=SolverConfig(backend=backend_of_arch(arch)))


def _compile_kernels(sim, arch: str) -> float:
    """JIT the Taichi kernels the steps will call (fused elastic terms, projected fallback) and build the
    solver's per-model structures (:meth:`Simulation.warm_up`: the fused evaluator on its sparsity
    pattern); seconds.

    Kept out of the timed steps (reported as ``jit_s``; ``cold_start_s`` still includes it).
    """
    if arch == "numpy":
        return 0.0
    from sim_core.fused_elastic import compile_kernels

    t0 = time.perf_counter()
    compile_kernels(sim.solver.elastic.potentials(sim.state.hinge_theta_bar), sim.state.x, sim.solver.config.projection)
    sim.warm_up()
    return time.perf_counter() - t0


# ------------------------------------------------------------------------------------ forming
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
        the result record (see :func:`bench_main` for its keys).

    Raises:
        ConfigError: bad scene or step count; ImportError: ``backward`` without ``sim_core.adjoint``.
    """
    from sim_core.control import Control
    from sim_core.scenes.task_scene import load_task_scene, task_initial_state
    from sim_core.tasks.trajectories import forming_benchmark_offsets, pose_targets

    t_build = time.perf_counter()
    model = load_task_scene(scene)
    sim = bench_simulation(model, arch)
    sim.state = task_initial_state(model)
    sim.solver.elastic_worker = elastic_worker
    jit_s = _compile_kernels(sim, arch)
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
        adjoint = importlib.import_module("sim_core.adjoint")
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


def _print_forming(r: dict) -> None:
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


# ------------------------------------------------------------------------------------ scale
def scale_model(target_dofs: int):
    """A flat 0.1 m square paper-like sheet (StVK) with about ``target_dofs`` DoF, edge x0 clamped.

    Returns:
        the Model (gravity -9.81 z, self-contact on, dt 5 ms in ``meta``).
    """
    from sim_core.builder import ModelBuilder
    from sim_core.mesh.sheet import grid_sheet

    n = max(2, int(round(np.sqrt(target_dofs / 3.0))))
    mesh = grid_sheet((0.1, 0.1), (n, n), (0.0, 0.0, 0.0))
    b = ModelBuilder()
    clamped = np.flatnonzero(np.arange(n * n) % n == 0)
    b.add_sheet("sheet", mesh, {"youngs_modulus": 3.0e9, "poisson_ratio": 0.3, "thickness": 3.0e-4, "density": 700.0},
                fixed=clamped, grid_shape=(n, n))
    return b.finalize(gravity=(0.0, 0.0, -9.81), meta={"name": f"scale_{n}x{n}", "dt": 0.005})


def run_scale(max_dofs: int, steps: int, arch: str = "numpy") -> list[dict]:
    """Time ``steps`` steps of each scale case up to ``max_dofs`` DoF (cases in increasing size).

    ``arch`` as :func:`run_forming`.

    Returns:
        one record per case: ``dofs``, ``step_time_s`` (mean), ``newton_iters_mean``, shares,
        ``peak_rss_mib`` (process peak after the case; cases run smallest first).
    """
    out = []
    for target in SCALE_TARGET_DOFS:
        if target > max_dofs:
            continue
        model = scale_model(target)
        sim = bench_simulation(model, arch)
        _compile_kernels(sim, arch)  # JIT outside the timed steps
        times, iters, ta, tl = [], [], 0.0, 0.0
        for _ in range(steps):
            t0 = time.perf_counter()
            info = sim.step()
            times.append(time.perf_counter() - t0)
            iters.append(info.iterations)
            ta += info.time_assembly
            tl += info.time_linear_solve
        total = float(sum(times))
        out.append({"target_dofs": target, "dofs": int(model.dof_count), "steps": steps, "step_time_s": total / steps,
                    "newton_iters_mean": float(np.mean(iters)), "assembly_share": ta / total,
                    "linear_solve_share": tl / total, "peak_rss_mib": peak_rss_mib()})
    return out


# ------------------------------------------------------------------------------------ CLI
def _delegate(module: str, func: str, argv: list[str], what: str) -> int:
    try:
        entry = getattr(importlib.import_module(module), func)
    except (ImportError, AttributeError) as err:
        print(f"thinshell bench {what}: not available in this installation ({module}.{func}: {err})", file=sys.stderr)
        return 2
    return int(entry(argv) or 0)


def bench_main(argv: list[str] | None = None) -> int:
    """Entry point of ``thinshell bench {forming,scale,node,diagnose,sysid,tasks,optimise,batch}``; returns the exit code.

    ``--json`` output of ``forming`` is one line with the keys ``dofs``, ``steps_per_s``,
    ``newton_iters_mean``, ``newton_iters_max``, ``factorizations_mean``
    (Newton matrices factorised per step, a projected fallback's failed exact one included),
    ``assembly_share``, ``linear_solve_share``,
    ``cold_start_s``, ``scene_build_s``, ``jit_s``, ``forward_total_s``, ``steps``, ``vertices``, ``arch``,
    ``backend`` (``SolverConfig.backend`` of ``arch``), ``taichi_terms`` (always empty: the solver's
    elastic potentials are the NumPy ones on every backend, the fused kernels evaluate them in the Newton loop), ``linear_solver``, ``peak_rss_mib``, ``elastic_worker`` (the gel's term ran in a
    worker process, :mod:`sim_core.elastic_worker`), ``worker_peak_rss_mib`` (that process's peak
    RSS, or null), ``python``, ``python_executable`` (the
    interpreter binary, symlinks resolved), ``numpy`` (and ``backward_*`` with ``--backward``); of
    ``scale`` one line ``{"bench": "scale", "cases": [...]}``.

    ``--arch``: ``numpy`` runs the NumPy reference potentials (backend ``numpy``); ``cpu`` (default)
    and ``cuda`` run the backends ``taichi-cpu`` / ``taichi-cuda`` (:mod:`sim_core.backend`): the Newton loop evaluates the
    elastic terms with the fused kernels of :mod:`sim_core.fused_elastic` (energy, gradient and exact
    Hessian in one launch per potential, and the projected fallback's values). The kernels are
    compiled before the timed steps (``jit_s``; included in ``cold_start_s``).

    Exit codes: 0 success, 2 unsupported option (unknown ``--arch`` or an arch Taichi cannot start
    on this machine, ``--backward`` without ``sim_core.adjoint``) or missing sub-benchmark.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(prog="thinshell bench", description="speed benchmarks")
    sub = parser.add_subparsers(dest="which", required=True)
    p = sub.add_parser("forming", help="ThinShellLab Forming scene, 1698 DoF, benchmark trajectory")
    p.add_argument("--arch", default="cpu",
                   help="numpy (reference potentials) or cpu / cuda (Taichi element kernels); default cpu")
    p.add_argument("--json", action="store_true", help="print one JSON line")
    p.add_argument("--steps", type=int, default=49, help="steps of the trajectory to run (1..49)")
    p.add_argument("--backward", action="store_true", help="also time the backward pass (needs sim_core.adjoint)")
    p.add_argument("--scene", default=None, help="scene file (default: the bundled forming.yaml)")
    p.add_argument("--no-elastic-worker", action="store_true",
                   help="evaluate every elastic term in this process (default with --arch cpu: the gel's Stable "
                        "Neo-Hookean term in a worker process, concurrently with the sheet's terms)")
    p.add_argument("--repeat", type=int, default=1,
                   help="run the trajectory this many times in one process and report the median steps/s "
                        "(a shared VM's speed varies run to run); cold start and JIT are the first run's")
    s = sub.add_parser("scale", help="flat sheets of ~1k, 10k, 100k DoF under gravity")
    s.add_argument("--arch", default="cpu",
                   help="numpy (reference potentials) or cpu / cuda (Taichi element kernels); default cpu")
    s.add_argument("--json", action="store_true", help="print one JSON line")
    s.add_argument("--steps", type=int, default=3, help="steps per case")
    s.add_argument("--max-dofs", type=int, default=max(SCALE_TARGET_DOFS),
                   help="skip cases above this DoF count (default: run all, 1k, 10k and 100k; the 100k case "
                        "takes about a minute and 3 GB)")
    sub.add_parser("node", help="ROS node benchmark", add_help=False)
    sub.add_parser("diagnose", help="missing-physics diagnosis benchmark", add_help=False)
    sub.add_parser("sysid", help="3-parameter material fit on a whole recording", add_help=False)
    sub.add_parser("tasks", help="the ten ThinShellLab tasks: reference trajectories' rewards vs Table A", add_help=False)
    sub.add_parser("optimise", help="the optimisers (cma, gd, hybrid; PPO with --rl) on the tasks vs Table A", add_help=False)
    sub.add_parser("batch", help="B copies of a scene stepped together: scene-steps/s and memory per copy vs B",
                   add_help=False)
    delegated = {"node": ("thinshell_ros.bench_node", "bench_node_main"),
                 "tasks": ("sim_core.tasks.bench", "bench_tasks_main"),
                 "optimise": ("sysid.optimise_bench", "bench_optimise_main"),
                 "batch": ("sim_core.batch.bench", "bench_batch_main"),
                 "diagnose": ("sysid.diagnose_bench", "bench_diagnose_main"),
                 "sysid": ("sysid.bench_fit", "bench_sysid_main")}
    if argv and argv[0] in delegated:
        module, func = delegated[argv[0]]
        return _delegate(module, func, argv[1:], argv[0])
    ns = parser.parse_args(argv)
    msg = _check_arch(ns.arch)
    if msg:
        print(f"thinshell bench {ns.which}: {msg}", file=sys.stderr)
        return 2
    if ns.which == "forming":
        if ns.backward:
            try:
                adjoint = importlib.import_module("sim_core.adjoint")
            except ImportError:
                adjoint = None
            if adjoint is None or not hasattr(adjoint, "rollout_gradient"):
                print("thinshell bench forming: --backward needs sim_core.adjoint.rollout_gradient, "
                      "which is not available in this installation", file=sys.stderr)
                return 2
        if ns.repeat < 1:
            print(f"thinshell bench forming: --repeat must be >= 1, got {ns.repeat}", file=sys.stderr)
            return 2
        scene = ns.scene or _default_scene("forming")
        worker = None
        if ns.arch == "cpu" and not ns.no_elastic_worker:
            from sim_core.elastic_worker import ElasticWorker

            worker = ElasticWorker()  # starts now: its Taichi start overlaps this process's
        try:
            result = repeat_forming([run_forming(scene, ns.steps, ns.backward, ns.arch, worker)
                                     for _ in range(ns.repeat)])
        finally:
            if worker is not None:
                worker.close()
        if ns.json:
            print(json.dumps(result))
        else:
            _print_forming(result)
        return 0
    cases = run_scale(ns.max_dofs, ns.steps, ns.arch)
    if ns.json:
        print(json.dumps({"bench": "scale", "cases": cases}))
    else:
        print(f"thinshell bench scale ({ns.arch}, {ns.steps} steps per case, gravity, edge x0 clamped)")
        print(f"  {'DoF':>8} {'ms/step':>10} {'Newton it':>10} {'assembly':>9} {'lin.solve':>9} {'peak RSS':>10}")
        for c in cases:
            print(f"  {c['dofs']:>8} {1e3 * c['step_time_s']:>10.1f} {c['newton_iters_mean']:>10.2f} "
                  f"{100 * c['assembly_share']:>8.1f}% {100 * c['linear_solve_share']:>8.1f}% {c['peak_rss_mib']:>7.0f} MiB")
        skipped = [t for t in SCALE_TARGET_DOFS if t > ns.max_dofs]
        if skipped:
            print(f"  (skipped cases of ~{', '.join(str(t) for t in skipped)} DoF; raise --max-dofs to run them)")
    return 0


if __name__ == "__main__":
    sys.exit(bench_main())
