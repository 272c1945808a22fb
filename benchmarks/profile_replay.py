"""Profile one replay of a recording as ``thinshell sysid`` makes it: where a step's CPU time goes.

Usage: ``python -m benchmarks.profile_replay BAG [--no-drive] [--tangents] [--dt 0.01] [--arch cpu] [--top 25]
[--out PROF] [--gel-element LAW]``.

Builds the replay as :func:`sysid.fit_recording.fit_recording` does (the bag's scene, ``--dt`` steps, the
effector's drive fitted in closed form unless ``--no-drive``), replays it once untimed (kernels compiled or
loaded from the cache), then once more under ``cProfile`` with the process' CPU clock
(``time.process_time``: the machine is shared, so wall time says little). With ``--tangents`` the timed replay
is the fit's joint replay (:func:`sysid.replay_drive.drive_sensitivities`, or
:func:`sim_core.sensitivity.rollout_sensitivities` for a kinematic drive) with the three default parameters.

Printed: CPU seconds of the replay and per step; step evaluations (the drive's secant evaluations), Newton
iterations, factorisations and PARDISO calls per phase (11: symbolic analysis, 22: numerical factorisation,
33: solve) per step; Taichi kernel launches per step; the CPU seconds of the parts (assembly, linear
solves, line search, contact search, sensor observation, tangents); for the steps without and with a load on the
sensor (a plain replay) their CPU, Newton iterations, PARDISO calls by phase and CPU ms a step, the union pattern's
rebuilds (:mod:`sim_core.dynamic_slots`: each one a new pattern, so a new symbolic analysis), and per body the median
over the steps of its largest Newton update after the step's first (m/s: a body whose block has converged to round-off
is still solved every iteration); and the ``--top`` functions by own time.
"""

from __future__ import annotations

import argparse
import collections
import cProfile
import math
import pstats
import time

import numpy as np

PARTS = {  # part -> (module path fragment, function name): cumulative CPU time of the outermost calls
    "Newton iterations": ("sim_core/solver.py", "_newton_iterations"),
    "step set-up (contact begin, friction)": ("sim_core/solver.py", "_set_up_step"),
    "step finish (forces, record)": ("sim_core/solver.py", "_finish_step"),
    "gradient": ("sim_core/solver.py", "_gradient"),
    "Hessian assembly": ("sim_core/solver.py", "_assemble_hessian"),
    "Newton direction (assembly + factorise + solve)": ("sim_core/solver.py", "_newton_direction"),
    "line search": ("sim_core/solver.py", "_line_search"),
    "PARDISO calls": ("sim_core/linsolve.py", "_call"),
    "Taichi launches": ("sim_core/ti_kernels/launch.py", "launch"),
    "sensor observation": ("sim_core/simulation.py", "observe"),
    "tangents: linearisation": ("sim_core/sensitivity.py", "linearization"),
    "tangents: advance": ("sim_core/sensitivity.py", "advance"),
}


def _options() -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.profile_replay", description=__doc__.split("\n\n")[0])
    parser.add_argument("bag", help="rosbag2 directory with its scene.yaml")
    parser.add_argument("--dt", type=float, default=0.01, help="replay step, s (thinshell sysid's default)")
    parser.add_argument("--no-drive", action="store_true", help="replay the measured pose (kinematic drive)")
    parser.add_argument("--tangents", action="store_true", help="time the fit's joint replay with tangents")
    parser.add_argument("--arch", choices=("numpy", "cpu", "cuda"), default="cpu",
                        help="elastic terms of the replay (thinshell sysid's default: cpu)")
    parser.add_argument("--t-max", type=float, default=None, help="replay only the first T_MAX s")
    parser.add_argument("--gel-element", default=None,
                        help="the gel's element and law (simulation.gel_element; default the scene's)")
    parser.add_argument("--top", type=int, default=25, help="functions listed by own CPU time")
    parser.add_argument("--out", default=None, help="write the cProfile statistics to this file")
    parser.add_argument("--no-profile", action="store_true",
                        help="time the replay without cProfile (its CPU seconds without the profiler's overhead)")
    parser.add_argument("--repeat", type=int, default=1, help="timed replays (the CPU seconds of each are printed)")
    return parser.parse_args()


def _pardiso_counter(counts: collections.Counter):
    """Wrap ``PardisoHandle._call`` to count PARDISO's phases; returns the wrapper's undo."""
    from sim_core.linsolve import PardisoHandle

    original = PardisoHandle._call

    def counted(self, phase, data, b=None):
        key = f"type {self.matrix_type} phase {phase}"
        counts[key] += 1
        counts[f"n {key}"] += self._n
        c0 = time.process_time()
        try:
            return original(self, phase, data, b)
        finally:
            counts[f"cpu {key}"] += time.process_time() - c0

    PardisoHandle._call = counted
    return lambda: setattr(PardisoHandle, "_call", original)


def _step_counter(counts: collections.Counter, updates: dict):
    """Count the union pattern's rebuilds and record each body's largest Newton update (m/s) of each iteration
    (``updates``: body name -> list of per-step lists); returns the wrappers' undo."""
    from sim_core.dynamic_slots import DynamicMerge
    from sim_core.solver import NewtonSolver

    rebuild, direction = DynamicMerge._rebuild, NewtonSolver._newton_direction

    def counted_rebuild(self, *args):
        counts["union rebuilds"] += 1
        return rebuild(self, *args)

    def recorded_direction(self, step, x, g, contact_terms, it, info):
        result = direction(self, step, x, g, contact_terms, it, info)
        d3 = result[0].reshape(-1, 3)
        for body in self.model.bodies.values():
            if body.vertex_stop > body.vertex_start:
                per_step = updates.setdefault(body.name, [[]])
                per_step[-1].append(float(np.abs(d3[body.vertex_start:body.vertex_stop]).max()) / step.dt)
        return result

    DynamicMerge._rebuild, NewtonSolver._newton_direction = counted_rebuild, recorded_direction
    return lambda: (setattr(DynamicMerge, "_rebuild", rebuild), setattr(NewtonSolver, "_newton_direction", direction))


def _launch_counter(counts: collections.Counter):
    from sim_core.ti_kernels import launch

    original = launch.FastKernel.__call__

    def counted(self, *args, **kwargs):
        counts["launches"] += 1
        return original(self, *args, **kwargs)

    launch.FastKernel.__call__ = counted
    return lambda: setattr(launch.FastKernel, "__call__", original)


def main() -> None:
    opts = _options()
    from sim_core.sensitivity import rollout_sensitivities
    from sysid.drive_calibration import fit_drive
    from sysid.evidence import load_evidence
    from sysid.fit import DEFAULT_PARAMETERS
    from sysid.observation import ObservationModel
    from sysid.replay_drive import drive_sensitivities

    evidence = load_evidence(opts.bag, include_image="auto")
    model = ObservationModel(evidence, dt=opts.dt, t_max=opts.t_max, arch=opts.arch,
                             simulation=None if opts.gel_element is None else {"gel_element": opts.gel_element})
    model.compile_kernels()
    if not opts.no_drive and model.sensor is not None:
        drive = fit_drive(model)
        if drive is not None:
            model.set_drive_stiffness(drive.replay_stiffness, drive.replay_damping)
    params = {name: model.parameter_value(name) for name in DEFAULT_PARAMETERS}

    step_cpu = [time.process_time()]
    step_counts: list[collections.Counter] = []  # the counters at the start and after each step of a plain replay
    updates: dict[str, list[list[float]]] = {}  # body -> per step, its largest Newton update of each iteration

    def stepped(k, K):
        step_cpu.append(time.process_time())
        step_counts.append(collections.Counter(counts))
        for per_step in updates.values():
            per_step.append([])

    def replay():
        if not opts.tangents:
            step_cpu[1:] = []
            step_counts[:] = [collections.Counter(counts)]
            updates.clear()
            step_cpu[0] = time.process_time()
            return model.simulate(params, on_step=stepped)
        sim = model.prepare(params)
        if math.isfinite(model.drive_stiffness):
            drive_sensitivities(model, sim, list(params))
        else:
            rollout_sensitivities(sim, model.controls_list(), list(params), contact_force=True)
        return sim

    counts: collections.Counter = collections.Counter()
    replay()  # kernels compiled or loaded; caches warm
    undo = [_pardiso_counter(counts), _launch_counter(counts), _step_counter(counts, updates)]
    profile = cProfile.Profile(time.process_time)
    cpus = []
    for _ in range(max(opts.repeat, 1)):
        c0, w0 = time.process_time(), time.perf_counter()
        if not opts.no_profile:
            profile.enable()
        result = replay()
        profile.disable()
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
        cpus.append(cpu)
    for u in undo:
        u()
    if not opts.tangents:  # the last replay's steps: with and without a load on the sensor
        _print_by_step(np.asarray(result.wrench), np.diff(np.asarray(step_cpu)), step_counts, updates,
                       "" if opts.no_profile else " (profiled)")
    counts = collections.Counter({k: v / len(cpus) for k, v in counts.items()})
    sim = model.simulation() if opts.tangents else None
    totals = (sim.step_totals if sim is not None else result.step_totals)
    K = model.step_count
    print(f"replay of {opts.bag}: {K} steps of {opts.dt:g} s, drive "
          f"{'kinematic' if math.isinf(model.drive_stiffness) else f'{model.drive_stiffness:.0f} N/m'}, "
          f"tangents {opts.tangents}")
    print(f"CPU {', '.join(f'{c:.2f}' for c in cpus)} s (last wall {wall:.2f} s"
          f"{'' if opts.no_profile else ', under the profiler'}): {1e3 * min(cpus) / K:.1f} ms CPU a step (least)")
    print("PARDISO calls a step (type 2: Cholesky, 11: LU; phase 11: analysis, 22: factorisation, 33: solve), "
          "CPU ms a call, mean rows:")
    for key in sorted(k for k in counts if k.startswith("type")):
        print(f"  {key}: {counts[key] / K:.2f} a step, {1e3 * counts['cpu ' + key] / counts[key]:.2f} ms, "
              f"{counts['n ' + key] / counts[key]:.0f} rows")
    if opts.no_profile:
        return
    stats = pstats.Stats(profile)
    if opts.out:
        stats.dump_stats(opts.out)
    raw = stats.stats  # (file, line, name) -> (cc, nc, tt, ct, callers)
    calls = collections.Counter()
    for (file, _, name), (_, nc, _, _, _) in raw.items():
        calls[(file, name)] += nc
    solver_steps = calls[next((k for k in calls if k[0].endswith("sim_core/solver.py") and k[1] == "_single_step"),
                              ("", ""))]
    newton = calls[next((k for k in calls if k[0].endswith("sim_core/solver.py") and k[1] == "_newton_direction"),
                        ("", ""))]
    print(f"step evaluations {solver_steps} ({solver_steps / K:.2f} a step); Newton directions {newton} "
          f"({newton / max(solver_steps, 1):.2f} an evaluation); steps {totals.steps}")
    print(f"Taichi launches a step (FastKernel): {counts['launches'] / K:.0f}")
    print("parts (cumulative CPU s; nested parts overlap):")
    for part, (fragment, fname) in PARTS.items():
        ct = sum(v[3] for (file, _, name), v in raw.items() if file.endswith(fragment) and name == fname)
        print(f"  {part:50s} {ct:8.2f} s  {1e3 * ct / K:7.2f} ms a step")
    if opts.top:
        stats.sort_stats("tottime").print_stats(opts.top)


def _print_by_step(wrench: np.ndarray, per_step: np.ndarray, step_counts: list[collections.Counter],
                   updates: dict[str, list[list[float]]], note: str) -> None:
    """Print the steps without and with a load on the sensor (``wrench`` ``(K + 1, 6)``, the replay's): their CPU
    (``per_step`` s ``(K,)``), Newton iterations, PARDISO calls and CPU by phase and union rebuilds a step
    (``step_counts``: the counters at the replay's start and after each step), and per body the median over the
    steps of its largest Newton update after the step's first iteration (m/s; ``updates``)."""
    loaded = np.linalg.norm(wrench[1:, :3], axis=1) > 0.0
    deltas = [after - before for before, after in zip(step_counts[:-1], step_counts[1:])]
    keys = sorted(k for k in set().union(*deltas) if k.startswith("type 2 phase"))
    for name, mask in (("without contact", ~loaded), ("in contact", loaded)):
        if not mask.any():
            continue
        rows = [d for d, m in zip(deltas, mask) if m]
        n = len(rows)
        iterations = [len(next(iter(updates.values()))[k]) for k in np.flatnonzero(mask)] if updates else [0]
        print(f"steps {name}: {n}, CPU median {1e3 * np.median(per_step[mask]):.1f} ms, mean "
              f"{1e3 * per_step[mask].mean():.1f} ms{note}; Newton directions {np.mean(iterations):.2f} a step")
        phases = ", ".join(f"phase {k.split()[-1]} {sum(r[k] for r in rows) / n:.2f} "
                           f"({1e3 * sum(r['cpu ' + k] for r in rows) / n:.1f} ms)" for k in keys)
        rebuilds = sum(r["union rebuilds"] for r in rows) / n
        print(f"  PARDISO Cholesky a step: {phases}; union pattern rebuilds {rebuilds:.2f}")
        for body, per in updates.items():
            later = [max(per[k][1:]) for k in np.flatnonzero(mask) if len(per[k]) > 1]
            if later:
                print(f"  {body}: largest Newton update after the first iteration, median over the steps "
                      f"{np.median(later):.2e} m/s ({len(later)} steps with more than one)")


if __name__ == "__main__":
    main()
