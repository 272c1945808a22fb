"""Command lines of the simulator benchmarks: ``thinshell bench forming`` and ``thinshell bench scale``.

``thinshell bench`` (``thinshell_ros.bench``) dispatches to :func:`bench_forming_main` and
:func:`bench_scale_main`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Callable, Sequence

from sim_core.backend import backend_of_arch, resolve_backend
from sim_core.bench.forming import print_forming, repeat_forming, run_forming
from sim_core.bench.scale import SCALE_TARGET_DOFS, run_scale
from sim_core.elastic_worker import ElasticWorker
from sim_core.errors import ConfigError

SUPPORTED_ARCHS = ("numpy", "cpu", "cuda")
"""``numpy``: the NumPy reference potentials; ``cpu`` / ``cuda``: Taichi kernels on that arch."""


def check_arch(arch: str) -> str | None:
    """Validate ``--arch`` and start its backend (:func:`sim_core.backend.resolve_backend`: Taichi
    initialised for ``cpu`` / ``cuda``); an error message or None."""
    if arch not in SUPPORTED_ARCHS:
        return f"--arch {arch}: unknown backend (supported: {', '.join(SUPPORTED_ARCHS)})"
    try:
        resolve_backend(backend_of_arch(arch))
    except ConfigError as err:
        return f"--arch {arch}: {err}"
    return None


def _arch_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--arch", default="cpu",
                   help="numpy (reference potentials) or cpu / cuda (Taichi element kernels); default cpu")
    p.add_argument("--json", action="store_true", help="print one JSON line")


def forming_parser() -> argparse.ArgumentParser:
    """The argument parser of ``thinshell bench forming``."""
    p = argparse.ArgumentParser(prog="thinshell bench forming",
                                description="ThinShellLab Forming scene, 1698 DoF, benchmark trajectory")
    _arch_argument(p)
    p.add_argument("--steps", type=int, default=49, help="steps of the trajectory to run (1..49)")
    p.add_argument("--backward", action="store_true", help="also time the backward pass (sim_core.adjoint)")
    p.add_argument("--scene", default=None, help="scene file (default: the bundled forming.yaml)")
    p.add_argument("--elastic-worker", action="store_true",
                   help="with --arch cpu: evaluate the gel's Stable Neo-Hookean term in a worker process, "
                        "concurrently with the sheet's terms (default off, as the sim node and the tools run: "
                        "it needs an idle second core; +10-23 %% on an idle 2-core VM, 3.3x slower on a loaded one, "
                        "docs/benchmarks.md)")
    p.add_argument("--repeat", type=int, default=1,
                   help="run the trajectory this many times in one process and report the median steps/s "
                        "(a shared VM's speed varies run to run); cold start and JIT are the first run's")
    return p


def scale_parser() -> argparse.ArgumentParser:
    """The argument parser of ``thinshell bench scale``."""
    p = argparse.ArgumentParser(prog="thinshell bench scale", description="flat sheets of ~1k, 10k, 100k DoF under gravity")
    _arch_argument(p)
    p.add_argument("--steps", type=int, default=3, help="steps per case")
    p.add_argument("--max-dofs", type=int, default=max(SCALE_TARGET_DOFS),
                   help="skip cases above this DoF count (default: run all, 1k, 10k and 100k; the 100k case "
                        "takes about a minute and 3 GB)")
    return p


def bench_forming_main(argv: Sequence[str], default_scene: Callable[[], Path]) -> int:
    """``thinshell bench forming``; returns the exit code.

    ``default_scene`` gives the scene file when ``--scene`` is not set (the bundled ``forming.yaml``).

    ``--json`` prints one line with the keys ``dofs``, ``steps_per_s``,
    ``newton_iters_mean``, ``newton_iters_max``, ``factorizations_mean``
    (Newton matrices factorised per step, a projected fallback's failed exact one included),
    ``assembly_share``, ``linear_solve_share``,
    ``cold_start_s``, ``scene_build_s``, ``jit_s``, ``forward_total_s``, ``steps``, ``vertices``, ``arch``,
    ``backend`` (``SolverConfig.backend`` of ``arch``), ``taichi_terms`` (always empty: the solver's
    elastic potentials are the NumPy ones on every backend, the fused kernels evaluate them in the
    Newton loop), ``linear_solver``, ``peak_rss_mib``, ``elastic_worker`` (the gel's term ran in a
    worker process, :mod:`sim_core.elastic_worker`), ``worker_peak_rss_mib`` (that process's peak
    RSS, or null), ``python``, ``python_executable`` (the interpreter binary, symlinks resolved),
    ``numpy`` (and ``backward_*`` with ``--backward``); with ``--repeat`` also ``repeat``,
    ``steps_per_s_runs`` and ``steps_per_s_best`` (:func:`sim_core.bench.forming.repeat_forming`).

    ``--arch``: ``numpy`` runs the NumPy reference potentials (backend ``numpy``); ``cpu`` (default)
    and ``cuda`` run the backends ``taichi-cpu`` / ``taichi-cuda`` (:mod:`sim_core.backend`): the
    Newton loop evaluates the elastic terms with the fused kernels of :mod:`sim_core.fused_elastic` (energy, gradient and exact
    Hessian in one launch per potential, and the projected fallback's values). The kernels are
    compiled before the timed steps (``jit_s``; included in ``cold_start_s``).

    Exit codes: 0 success, 2 unsupported option (unknown ``--arch`` or an arch Taichi cannot start
    on this machine, ``--repeat`` below 1).
    """
    ns = forming_parser().parse_args(list(argv))
    msg = check_arch(ns.arch)
    if msg:
        print(f"thinshell bench forming: {msg}", file=sys.stderr)
        return 2
    if ns.repeat < 1:
        print(f"thinshell bench forming: --repeat must be >= 1, got {ns.repeat}", file=sys.stderr)
        return 2
    scene = ns.scene or default_scene()
    worker = None
    if ns.arch == "cpu" and ns.elastic_worker:
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
        print_forming(result)
    return 0


def bench_scale_main(argv: Sequence[str]) -> int:
    """``thinshell bench scale``; returns the exit code (2: unsupported ``--arch``).

    ``--json`` prints one line ``{"bench": "scale", "cases": [...]}`` (the records of
    :func:`sim_core.bench.scale.run_scale`).
    """
    ns = scale_parser().parse_args(list(argv))
    msg = check_arch(ns.arch)
    if msg:
        print(f"thinshell bench scale: {msg}", file=sys.stderr)
        return 2
    cases = run_scale(ns.max_dofs, ns.steps, ns.arch)
    if ns.json:
        print(json.dumps({"bench": "scale", "cases": cases}))
        return 0
    print(f"thinshell bench scale ({ns.arch}, {ns.steps} steps per case, gravity, edge x0 clamped)")
    print(f"  {'DoF':>8} {'ms/step':>10} {'Newton it':>10} {'assembly':>9} {'lin.solve':>9} {'peak RSS':>10}")
    for c in cases:
        print(f"  {c['dofs']:>8} {1e3 * c['step_time_s']:>10.1f} {c['newton_iters_mean']:>10.2f} "
              f"{100 * c['assembly_share']:>8.1f}% {100 * c['linear_solve_share']:>8.1f}% {c['peak_rss_mib']:>7.0f} MiB")
    skipped = [t for t in SCALE_TARGET_DOFS if t > ns.max_dofs]
    if skipped:
        print(f"  (skipped cases of ~{', '.join(str(t) for t in skipped)} DoF; raise --max-dofs to run them)")
    return 0
