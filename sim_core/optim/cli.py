"""``thinshell optimise``: optimise a task's trajectory (or identify an inverse task's parameters).

Usage::

    thinshell optimise TASK [--scene SCENE] --method cma|gd|hybrid --episodes N [--workers K]
                       [--address RAY] [--batched [--batch-size N|auto] [--gd-starts K]] [--horizon H]
                       [--seed S] [--population P] [--sigma S]
                       [--control-points K] [--learning-rate A] [--start NAME=VALUE ...]
                       [--max-time S] [--backend numpy|taichi-cpu|taichi-cuda] --out DIR [--force] [--resume]

TASK is a task name (``thinshell optimise forming``) or a task file (``config/tasks/*.yaml``).
``--scene`` runs it on another scene: a ``kind: task`` scene replaces the task's scene; a scene
written by ``thinshell sysid --write-scene`` (with ``fitted: {params: ...}``) sets its fitted values
of the parameters the task's model has. Episodes run serially, or on ``--workers`` local Ray
workers, or on the Ray cluster at ``--address`` (sim_core.optim.evaluators), or as one batch of scene copies
(``--batched``); with ``--batched`` the gradient phase of ``gd`` and ``hybrid`` may follow ``--gd-starts`` K starts
(default 1), their K gradients per step one batched adjoint (sim_core.optim.batch_gradient, sim_core.optim.search).

Outputs in DIR: ``scene.yaml`` (the scene document the run used), ``checkpoint.pkl`` (after every batch; ``--resume`` continues from it, also with a
larger ``--episodes``), and at the end ``trajectory.yaml`` (docs/trajectory_format.md: the best
trajectory's reached effector poses, ``scene.path`` = that ``scene.yaml``, the parameter values, the predicted reward and
the contact summary of :mod:`sim_core.optim.prediction` (effector wrenches, tactile readings); none for a task without effectors),
``result.json`` (summary and reward per episode), ``report.html`` with ``reward.png`` (reward versus
episode) and ``before_after.png`` (final states of the start and of the best trajectory). Every file
is written atomically; an existing DIR with results is refused unless ``--force`` (start again) or
``--resume``.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as _dt
import html
import json
import math
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from sim_core.errors import ConfigError
from sim_core.backend import BACKENDS
from sim_core.optim.search import (CMA_STARTS, METHODS, SearchState, load_checkpoint, new_state, optimise, save_checkpoint)
from sim_core.solver_config import SolverConfig
from sim_core.batch.sizing import batch_size_arg

CHECKPOINT = "checkpoint.pkl"
OUTPUTS = ("scene.yaml", "trajectory.yaml", "result.json", "report.html", "reward.png", "before_after.png")
RESULT_SCHEMA = "thinshell.optimise.result"


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="thinshell optimise", description=__doc__.split("\n\n")[0])
    p.add_argument("task", help="task name (config/tasks) or task file")
    p.add_argument("--scene", help="run on this scene: a kind: task scene, or a sysid-written scene (fitted values)")
    p.add_argument("--method", choices=METHODS, default="hybrid")
    p.add_argument("--episodes", type=int, required=True, help="episode budget (rollouts)")
    p.add_argument("--workers", type=int, default=1, help="parallel Ray workers (1: serial, unless --address)")
    p.add_argument("--address", help="Ray cluster address to join (default: a local Ray instance when --workers > 1)")
    p.add_argument("--batched", action="store_true",
                   help="evaluate each CMA-ES population as one batch of scene copies stepped together "
                        "(sim_core.batch; same episodes as the serial evaluator)")
    p.add_argument("--batch-size", type=batch_size_arg, metavar="N|auto",
                   help="with --batched: the most copies stepped together (a larger population runs in chunks); "
                        "auto: the largest number that fits the device's free memory (sim_core.batch.sizing)")
    p.add_argument("--gd-starts", type=int, metavar="K",
                   help="gd / hybrid with --batched: K gradient runs at once, their K gradients a step evaluated "
                        "together (one batch, its adjoint passes run together): the hybrid's K best feasible CMA-ES "
                        f"candidates, else restarts around the start (default 1: at a fixed episode budget each of K "
                        "runs takes K times fewer steps)")
    p.add_argument("--horizon", type=int, help="steps per episode (default: the task's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--population", type=int, help="CMA-ES population (default: the task's)")
    p.add_argument("--sigma", type=float, help="CMA-ES step (default: the task's)")
    p.add_argument("--control-points", type=int, help="CMA-ES control points (default: the task's)")
    p.add_argument("--learning-rate", type=float, help="Adam step in search coordinates (default 0.5)")
    p.add_argument("--cma-start", choices=CMA_STARTS,
                   help="manipulation tasks: CMA-ES control points added to the zero trajectory or to the task's "
                        "reference (human-designed) trajectory (default: the task file's cma.start)")
    p.add_argument("--start", action="append", default=[], metavar="NAME=VALUE",
                   help="inverse tasks: start value of an identified parameter (repeatable)")
    p.add_argument("--backend", choices=BACKENDS, default="taichi-cpu",
                   help="solver backend (default taichi-cpu: the fused elastic kernels, ~5x numpy on Forming)")
    p.add_argument("--max-time", type=float, help="wall-time limit in s: no new batch starts after it (resumable)")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--force", action="store_true", help="replace an existing output directory")
    p.add_argument("--resume", action="store_true", help="continue from DIR/checkpoint.pkl")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def _pairs(items: list[str], what: str) -> dict[str, float]:
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        try:
            out[name.strip()] = float(value)
        except ValueError:
            sep = ""
        if not sep or not name.strip():
            raise ConfigError(f"{what}: expected NAME=VALUE, got {item!r}")
    return out


def load_target(task_arg: str, scene_arg: str | None, horizon: int | None) -> tuple[Any, dict[str, float], str | None]:
    """The task (at ``horizon``), parameter overrides and the scene path it runs on.

    Raises:
        ConfigError: unknown task, unreadable scene, a task scene without the task's effectors, or a
            sysid scene whose fitted parameters the task's model does not have.
    """
    from sim_core.optim.tasks import task_at_horizon
    from sim_core.scenes.task_scene import build_task_scene

    task = task_at_horizon(task_arg, horizon)
    if scene_arg is None:
        return task, {}, task.path
    path = Path(scene_arg)
    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as err:
        raise ConfigError(f"{path}: cannot read scene ({err})") from err
    if not isinstance(doc, dict):
        raise ConfigError(f"{path}: not a scene mapping")
    if doc.get("kind") == "task":
        doc.setdefault("task", task.scene.get("task"))
        try:
            model = build_task_scene(dict(doc))
        except ConfigError as err:
            raise ConfigError(f"{path}: {err}") from err
        missing = [e for e, _ in task.action_layout if e not in model.effectors]
        if missing:
            raise ConfigError(f"{path}: the scene lacks the effectors {missing} that task {task.name} moves")
        return dataclasses.replace(task, scene=doc), {}, str(path)
    fitted = (doc.get("fitted") or {}).get("params") if isinstance(doc.get("fitted"), dict) else None
    if not isinstance(fitted, dict) or not fitted:
        raise ConfigError(f"{path}: neither a kind: task scene nor a scene with fitted: {{params: ...}} (thinshell sysid)")
    known = set(build_task_scene(dict(task.scene)).parameter_names)
    params = {str(k): float(v) for k, v in fitted.items() if str(k) in known}
    if not params:
        raise ConfigError(f"{path}: none of the fitted parameters {sorted(fitted)} exists in task {task.name}'s scene")
    return task, params, task.path


def _prepare_out(out: Path, force: bool, resume: bool) -> None:
    if resume:
        if not (out / CHECKPOINT).is_file():
            raise ConfigError(f"{out}: no {CHECKPOINT} to resume from")
        return
    if out.exists() and any(out.iterdir()):
        if not force:
            raise ConfigError(f"output directory {out} exists and is not empty (use --force to replace it, --resume to continue)")
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)


def _atomic_write(path: Path, data: bytes | str) -> Path:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(data.encode() if isinstance(data, str) else data)
    tmp.replace(path)
    return path


def optimise_main(argv: list[str]) -> int:
    """Entry point of ``thinshell optimise`` (module docstring); returns the exit code.

    Raises:
        ConfigError: bad task, scene, settings or output directory (reported by ``thinshell``).
    """
    args = _parser().parse_args(argv)
    out = Path(args.out)
    _prepare_out(out, args.force, args.resume)
    task, params, scene_path = load_target(args.task, args.scene, args.horizon)
    horizon = task.horizon
    start = _pairs(args.start, "--start")
    cma_start = args.cma_start or task.cma_start
    if task.kind == "inverse" and args.cma_start:
        raise ConfigError(f"--cma-start applies to manipulation tasks; {task.name} is an inverse task")
    meta = {"task": task.name, "horizon": horizon, "scene": scene_path, "params": params, "start": start,
            "control_points": args.control_points, "backend": args.backend, "cma_start": cma_start}
    if args.resume:
        state = load_checkpoint(out / CHECKPOINT)
        if state.method != args.method or state.meta != meta:
            raise ConfigError(f"{out / CHECKPOINT}: written by another run ({state.method}, {state.meta}); "
                              f"this one is {args.method}, {meta}")
        state.episodes = max(state.episodes, int(args.episodes))
        if state.phase == "done" and state.episodes_done < state.episodes:
            state.phase = "gd" if state.adam is not None or state.adams is not None else "cma"
    else:
        state = new_state(args.method, args.episodes, seed=args.seed, gd_starts=_gd_starts(args),
                          sigma=args.sigma if args.sigma is not None else task.cma_sigma,
                          population=args.population if args.population is not None else task.cma_population,
                          **({"learning_rate": args.learning_rate} if args.learning_rate is not None else {}), meta=meta)
    from sim_core.optim.evaluators import make_evaluator, optimiser_solver_config

    solver_config = optimiser_solver_config(args.backend)
    evaluator = make_evaluator(task, args.workers, horizon, params, args.address, solver_config, batched=args.batched,
                               batch_size=args.batch_size)
    try:
        space = _space(task, evaluator, horizon, params, start, args.control_points, solver_config, cma_start)
        t0 = time.perf_counter()
        deadline = None if args.max_time is None else t0 + float(args.max_time)
        _run(state, space, out, progress=not args.no_progress, deadline=deadline)
        wall = time.perf_counter() - t0
    finally:
        evaluator.close()
    paths = write_outputs(out, task, state, space, params, scene_path, wall, evaluator.workers)
    print(f"thinshell optimise: {task.name} {state.method}: best reward {state.best_reward:.6g} after "
          f"{state.episodes_done} episodes; wrote {', '.join(str(p) for p in paths)}")
    return 0


def _gd_starts(args) -> int:
    """The gradient runs of the gradient phase (``--gd-starts``; module docstring).

    Raises:
        ConfigError: K < 1, or K > 1 without ``--batched`` or with ``--method cma``.
    """
    if args.gd_starts is None:
        return 1
    if args.gd_starts < 1:
        raise ConfigError(f"--gd-starts must be >= 1, got {args.gd_starts}")
    if args.gd_starts > 1 and (not args.batched or args.method == "cma"):
        raise ConfigError("--gd-starts > 1 applies to --method gd or hybrid with --batched")
    return int(args.gd_starts)


def _space(task, evaluator, horizon: int, params: dict, start: dict, control_points: int | None,
           solver_config: SolverConfig, cma_start: str = "zero"):
    if task.kind == "inverse":
        from sim_core.optim.inverse_task import parameter_space

        return parameter_space(task, evaluator, horizon, start, solver_config)
    if start:
        raise ConfigError(f"--start applies to inverse tasks; {task.name} is a {task.kind} task")
    from sim_core.optim.actions import ControlPointDecoder
    from sim_core.optim.search import ActionSpace

    return ActionSpace(ControlPointDecoder.for_task(task, horizon, control_points), evaluator, task, params=params,
                       solver_config=solver_config, start=cma_start)


def _run(state: SearchState, space, out: Path, progress: bool, deadline: float | None = None) -> None:
    from tqdm import tqdm

    bar = tqdm(total=state.episodes, initial=state.episodes_done, unit="episode", disable=not progress,
               desc=f"{state.meta.get('task')} {state.method}")

    def on_batch(st: SearchState, logs) -> None:
        save_checkpoint(out / CHECKPOINT, st)
        bar.total = st.episodes
        bar.update(len(logs))
        bar.set_postfix(best=f"{st.best_reward:.4g}", phase=st.phase)

    try:
        optimise(state, space, on_batch, deadline)
        save_checkpoint(out / CHECKPOINT, state)
    finally:
        bar.close()


# ------------------------------------------------------------------------------------------ outputs
def _episode_of(space, candidate):
    """An in-process episode and the actions / parameters of a candidate."""
    from sim_core.optim.episode import Episode

    if space.task.kind == "inverse":  # candidate = parameter values
        ep = space.episode or Episode(space.task, space.horizon)
        space.episode = ep
        ep.set_parameters(candidate)
        return ep, space.actions()
    ep = space.episode or Episode(space.task, space.decoder.horizon, space.params, space.solver_config)
    space.episode = ep
    return ep, candidate


def _start_candidate(space):
    if space.task.kind == "inverse":
        return space.values(np.zeros(len(space.specs)))  # every identified value (tied followers too)
    return space.decode(np.zeros(space.decoder.dim))  # the CMA-ES mean: zero or the reference trajectory


def write_outputs(out: Path, task, state: SearchState, space, params: dict, scene_path: str | None,
                  wall_s: float, workers: int) -> list[Path]:
    """``trajectory.yaml``, ``result.json``, ``reward.png``, ``before_after.png``, ``report.html``."""
    from sim_core.optim.prediction import contact_summary
    from sim_core.trajectory_file import Trajectory, write_trajectory
    from sim_core.provenance import git_revision

    if state.best_candidate is None:
        raise ConfigError(f"task {task.name}: no episode was evaluated")
    ep, best_actions = _episode_of(space, state.best_candidate)
    best = ep.run(best_actions, keep_states=True)
    ep0, start_actions = _episode_of(space, _start_candidate(space))
    before = ep0.run(start_actions, keep_states=True)
    run_params = dict(params)
    if task.kind == "inverse":
        run_params.update(state.best_candidate)
    scene_file = _atomic_write(out / "scene.yaml", "# the scene this run optimised on (thinshell optimise)\n"
                               + yaml.safe_dump(_plain(task.scene), sort_keys=False))
    t = task.dt * np.arange(best.steps_done + 1)
    traj = Trajectory(
        t=t, poses={k: v for k, v in best.effector_poses.items()}, gripper={k: v for k, v in best.gripper.items()},
        scene_path=str(scene_file.resolve()), scene_name=str(task.scene.get("name", task.name)), parameters=run_params,
        prediction={"reward": _num(best.reward), "score": _num(best.score), "wrench_peak_N": _num(best.wrench_peak_N),
                    "start_reward": _num(before.reward), "success_score": task.success_score,
                    "human_score": task.human_score, **contact_summary(ep.sim, best.states)},
        provenance={"tool": "thinshell optimise", "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                    "git": git_revision()[0] or "", "seed": state.seed, "method": state.method, "task": task.name,
                    "episodes": state.episodes_done, "horizon": task.horizon},
    )
    paths = [scene_file]
    if traj.poses:  # a task without effectors (Bouncing) has no trajectory to write
        paths.append(write_trajectory(out / "trajectory.yaml", traj, force=True))
    doc = {"schema": RESULT_SCHEMA, "schema_version": 1, "task": task.name, "kind": task.kind, "method": state.method,
           "episodes": state.episodes_done, "horizon": task.horizon, "seed": state.seed, "workers": workers,
           "gd_starts": state.gd_starts,
           "backend": state.meta.get("backend"), "stop_reason": state.stop_reason,
           "wall_time_s": wall_s, "rollouts_per_s": state.episodes_done / wall_s if wall_s > 0 else None,
           "best_reward": _num(state.best_reward), "best_score": _num(state.best_score), "start_reward": _num(before.reward),
           "success_score": task.success_score, "human_score": task.human_score,
           "task_file": task.path, "scene_arg": scene_path, "parameters": run_params, "true_parameters": dict(task.true_parameters),
           "history": [{"episode": h.episode, "phase": h.phase, "reward": _num(h.reward), "score": h.score,
                        "infeasible": h.infeasible} for h in state.history]}
    paths.append(_atomic_write(out / "result.json", json.dumps(doc, indent=1)))
    paths += [_plot_reward(out / "reward.png", state, task), _plot_states(out / "before_after.png", ep.model, before, best)]
    paths.append(_atomic_write(out / "report.html", _report_html(doc)))
    return paths


def _plain(value: Any) -> Any:
    """YAML-safe copy of a scene document (arrays to lists, numpy scalars to Python)."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    return value


def _num(v: Any) -> float | None:
    return float(v) if v is not None and math.isfinite(float(v)) else None


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _save_figure(fig, path: Path) -> Path:
    tmp = path.with_name(f".{path.stem}.tmp.png")
    fig.savefig(tmp, dpi=110)
    _pyplot().close(fig)
    tmp.replace(path)
    return path


def _plot_reward(path: Path, state: SearchState, task) -> Path:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 4))
    ep = np.array([h.episode for h in state.history])
    rw = np.array([h.reward if h.infeasible is None else np.nan for h in state.history])
    for phase, color in (("cma", "tab:blue"), ("gd", "tab:orange")):
        m = np.array([h.phase == phase for h in state.history])
        if m.any():
            ax.plot(ep[m], rw[m], ".", color=color, label=f"{phase} episode")
    best = np.fmax.accumulate(np.where(np.isnan(rw), -np.inf, rw))
    ax.plot(ep, np.where(np.isfinite(best), best, np.nan), "-", color="k", label="best so far")
    for value, name, style in ((task.success_score, "success (Table A)", "--"), (task.human_score, "human (Table A)", ":")):
        if value is not None:
            ax.axhline(value, linestyle=style, color="0.4", label=name)
    bad = np.isnan(rw)
    if bad.any():
        ax.plot(ep[bad], np.full(bad.sum(), np.nanmin(rw) if np.isfinite(np.nanmin(rw, initial=np.inf)) else 0.0), "x",
                color="tab:red", label="infeasible")
    ax.set_xlabel("episode")
    ax.set_ylabel(f"reward ({task.reward_units or 'task units'})")
    ax.set_title(f"{task.name}: {state.method}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _save_figure(fig, path)


def _plot_states(path: Path, model, before, after) -> Path:
    """Side (x-z) and top (x-y) views of the final states of the start and of the best episode."""
    plt = _pyplot()
    fig, axes = plt.subplots(2, 2, figsize=(10, 6), sharex=True)
    for col, (res, title) in enumerate(((before, "start"), (after, "best"))):
        x = res.final_state.x
        for name, b in model.bodies.items():
            p = x[b.vertex_start:b.vertex_stop]
            axes[0, col].plot(p[:, 0], p[:, 2], ".", ms=2, label=name)
            axes[1, col].plot(p[:, 0], p[:, 1], ".", ms=2)
        reward = "infeasible" if not res.feasible else f"reward {res.reward:.4g}"
        axes[0, col].set_title(f"{title}: {reward}")
        axes[0, col].set_ylabel("z (m)")
        axes[1, col].set_ylabel("y (m)")
        axes[1, col].set_xlabel("x (m)")
        for ax in axes[:, col]:
            ax.set_aspect("equal", adjustable="datalim")
    axes[0, 0].legend(fontsize=7, markerscale=4)
    fig.tight_layout()
    return _save_figure(fig, path)


def _report_html(doc: dict) -> str:
    e = html.escape
    rows = [("task", doc["task"]), ("method", doc["method"]), ("episodes", doc["episodes"]), ("horizon", doc["horizon"]),
            ("seed", doc["seed"]), ("workers", doc["workers"]), ("ended by", doc["stop_reason"]), ("wall time (s)", f"{doc['wall_time_s']:.1f}"),
            ("start reward", doc["start_reward"]), ("best reward", doc["best_reward"]),
            ("success score (Table A)", doc["success_score"]), ("human score (Table A)", doc["human_score"])]
    rows += [(f"parameter {k}", v) for k, v in doc["parameters"].items()]
    rows += [(f"true {k}", v) for k, v in doc["true_parameters"].items()]
    table = "".join(f"<tr><th>{e(str(k))}</th><td>{e(str(v))}</td></tr>" for k, v in rows)
    return ("<!DOCTYPE html><html><head><meta charset='utf-8'><title>thinshell optimise report</title>"
            "<style>body{font-family:sans-serif;max-width:1100px;margin:auto}table{border-collapse:collapse}"
            "td,th{border:1px solid #bbb;padding:3px 8px;text-align:left}img{max-width:100%}</style></head><body>"
            f"<h1>Optimisation report: {e(doc['task'])}</h1><table>{table}</table>"
            "<h2>Reward versus episode</h2><p><img src='reward.png' alt='reward versus episode'></p>"
            "<h2>Final states: start and best</h2><p><img src='before_after.png' alt='before and after'></p>"
            "<p>Files: trajectory.yaml (docs/trajectory_format.md), result.json, checkpoint.pkl.</p></body></html>")
