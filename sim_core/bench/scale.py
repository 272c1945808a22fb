"""``thinshell bench scale``: flat sheets of about 1k, 10k and 100k DoF under gravity, one edge clamped."""

from __future__ import annotations

import time

import numpy as np

from sim_core.bench.forming import bench_simulation, compile_bench_kernels
from sim_core.bench.process import peak_rss_mib
from sim_core.builder import ModelBuilder
from sim_core.mesh.sheet import grid_sheet

SCALE_TARGET_DOFS = (1_000, 10_000, 100_000)
"""The DoF counts of the cases, smallest first."""


def scale_model(target_dofs: int):
    """A flat 0.1 m square paper-like sheet (StVK) with about ``target_dofs`` DoF, edge x0 clamped.

    Returns:
        the Model (gravity -9.81 z, self-contact on, dt 5 ms in ``meta``).
    """
    n = max(2, int(round(np.sqrt(target_dofs / 3.0))))
    mesh = grid_sheet((0.1, 0.1), (n, n), (0.0, 0.0, 0.0))
    b = ModelBuilder()
    clamped = np.flatnonzero(np.arange(n * n) % n == 0)
    b.add_sheet("sheet", mesh, {"youngs_modulus": 3.0e9, "poisson_ratio": 0.3, "thickness": 3.0e-4, "density": 700.0},
                fixed=clamped, grid_shape=(n, n))
    return b.finalize(gravity=(0.0, 0.0, -9.81), meta={"name": f"scale_{n}x{n}", "dt": 0.005})


def run_scale(max_dofs: int, steps: int, arch: str = "numpy") -> list[dict]:
    """Time ``steps`` steps of each scale case up to ``max_dofs`` DoF (cases in increasing size).

    ``arch`` as :func:`sim_core.bench.forming.run_forming`.

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
        compile_bench_kernels(sim, arch)  # JIT outside the timed steps
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
