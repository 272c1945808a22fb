"""``thinshell bench tasks --reference``: each task's human-designed reference trajectory over its full
horizon, its reward beside Table A's human-designed score, and its simulation time.

Inverse tasks replay their fixed trajectory at the true parameters: their reward, the distance to the
observed motion, is 0 by construction; the line gives their simulation time.
"""

from __future__ import annotations

import argparse
import json
import sys

from sim_core.tasks.registry import load_task, task_names
from sim_core.tasks.rollout import rollout

ARCH_BACKENDS = {"numpy": "numpy", "cpu": "taichi-cpu", "cuda": "taichi-cuda"}


def bench_task_reference(name: str, backend: str = "numpy") -> dict:
    """Run one task's reference trajectory; returns the figures of one report line.

    Returns:
        ``task, kind, reward, units, human_score, success_score, steps, horizon, infeasible, sim_s,
        s_per_step, vertices, backend``.

    Raises:
        ConfigError: unknown task, a task without a reference trajectory.
    """
    from sim_core.errors import ConfigError

    task = load_task(name)
    if task.reference_actions is None:
        raise ConfigError(f"task {task.name} has no reference trajectory")
    res = rollout(task, task.reference_actions, task.true_parameters or None, backend=backend)
    from sim_core.scenes.task_scene import build_task_scene

    return {
        "task": task.name, "kind": task.kind, "reward": res.reward, "units": task.reward_units,
        "human_score": task.human_score, "success_score": task.success_score, "steps": res.steps_done,
        "horizon": task.horizon, "infeasible": res.infeasible, "sim_s": res.sim_time_s,
        "s_per_step": res.sim_time_s / max(res.steps_done, 1),
        "vertices": build_task_scene(dict(task.scene)).vertex_count, "backend": backend,
    }


def _fmt(v, spec: str) -> str:
    return format("-", spec.replace("g", "").replace(".4", "")) if v is None else format(v, spec)


def bench_tasks_main(argv: list[str] | None = None) -> int:
    """Entry point of ``thinshell bench tasks``; returns the exit code (0 when every reference ran
    feasibly over its horizon, 1 otherwise, 2 on a usage error)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(prog="thinshell bench tasks", description=__doc__.splitlines()[0])
    p.add_argument("--reference", action="store_true", required=True,
                   help="run the human-designed reference trajectories (the only mode)")
    p.add_argument("--tasks", default=",".join(task_names()), help="comma-separated task names (default: all ten)")
    p.add_argument("--arch", default="numpy", choices=sorted(ARCH_BACKENDS), help="solver backend (default numpy)")
    p.add_argument("--json", action="store_true", help="print one JSON line per task")
    ns = p.parse_args(argv)
    names = [n.strip() for n in ns.tasks.split(",") if n.strip()]
    unknown = sorted(set(names) - set(task_names()))
    if unknown:
        print(f"thinshell bench tasks: unknown task(s) {unknown}; known: {task_names()}", file=sys.stderr)
        return 2
    if not ns.json:
        print(f"{'task':<13} {'kind':<12} {'reward':>11} {'unit':<4} {'Table A human':>13} {'success':>8} "
              f"{'steps':>7} {'sim s':>7} {'s/step':>7}  infeasible")
    ok = True
    for name in names:
        row = bench_task_reference(name, ARCH_BACKENDS[ns.arch])
        ok &= row["infeasible"] is None and row["steps"] == row["horizon"]
        if ns.json:
            print(json.dumps(row), flush=True)
        else:
            print(f"{row['task']:<13} {row['kind']:<12} {row['reward']:>11.4g} {row['units']:<4} "
                  f"{_fmt(row['human_score'], '>13.4g')} {_fmt(row['success_score'], '>8.4g')} "
                  f"{row['steps']:>3}/{row['horizon']:<3} {row['sim_s']:>7.1f} {row['s_per_step']:>7.3f}  "
                  f"{row['infeasible'] or '-'}", flush=True)
    return 0 if ok else 1
