"""``thinshell bench optimise``: the optimisers on the ThinShellLab tasks, against Table A.

For every task and method (and seed) it runs ``thinshell optimise`` into a temporary directory and
reads its ``result.json``: episodes, wall time, rollouts per second, the best reward, and whether it
reaches the task's Table A success score. ``--markdown FILE`` appends the table (with the date, the
machine and the settings) to FILE, e.g. ``docs/benchmarks.md``. ``--rl`` adds a stable-baselines3
PPO baseline on the task's Gymnasium environment where both are installed (not in CI).

Usage::

    thinshell bench optimise [--tasks a,b] [--methods cma,gd,hybrid] [--episodes N] [--horizon H]
                          [--seeds K] [--first-seed S] [--workers K] [--start-factor F] [--tolerance R] [--json]
                          [--markdown FILE] [--rl]

Inverse tasks (Sliding, Bouncing, Card) start every identified parameter at ``F`` (default 2) times
its hidden true value (``--start``); their ``success`` is every parameter recovered within the
relative ``--tolerance`` (default 5 %), reported as ``parameter_rel_error``.

``--first-seed S`` runs seeds ``S .. S+K-1`` (with ``--seeds K``), so that the seeds of one table
can run in separate processes or on separate machines. The seed drives CMA-ES only (its sampling;
:mod:`sim_core.optim.search`): ``gd`` starts from a fixed point (the task's reference, else zero)
and gives the same episodes for every seed.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import tempfile
from pathlib import Path
from typing import Any

from sim_core.errors import ConfigError


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="thinshell bench optimise", description="optimisers on the ThinShellLab tasks")
    p.add_argument("--tasks", help="comma-separated task names (default: all)")
    p.add_argument("--methods", default="cma,gd,hybrid", help="comma-separated methods")
    p.add_argument("--episodes", type=int, default=40, help="episode budget per run")
    p.add_argument("--horizon", type=int, help="steps per episode (default: each task's)")
    p.add_argument("--seeds", type=int, default=1, help="seeds per task and method (success over seeds)")
    p.add_argument("--first-seed", type=int, default=0, help="the first seed (seeds FIRST .. FIRST+K-1)")
    p.add_argument("--workers", type=int, default=1, help="Ray workers per run")
    p.add_argument("--population", type=int, help="CMA-ES population (default: the task's)")
    p.add_argument("--max-time", type=float, help="wall-time limit per run in s (thinshell optimise --max-time)")
    p.add_argument("--start-factor", type=float, default=2.0,
                   help="inverse tasks: start every identified parameter at this multiple of its true value "
                        "(success: every parameter recovered within --tolerance)")
    p.add_argument("--tolerance", type=float, default=0.05,
                   help="inverse tasks: largest relative parameter error counted as recovered")
    p.add_argument("--method-args", default="", help="further thinshell optimise arguments, space-separated")
    p.add_argument("--json", action="store_true", help="print one JSON line per run")
    p.add_argument("--markdown", help="append the table to this markdown file")
    p.add_argument("--rl", action="store_true", help="also a stable-baselines3 PPO baseline (if installed)")
    return p


def run_one(task: str, method: str, seed: int, args) -> dict[str, Any]:
    """One ``thinshell optimise`` run; its ``result.json`` summary."""
    from sim_core.optim.cli import optimise_main

    with tempfile.TemporaryDirectory(prefix="thinshell-bench-") as tmp:
        out = Path(tmp) / "run"
        argv = [task, "--method", method, "--episodes", str(args.episodes), "--seed", str(seed), "--out", str(out),
                "--no-progress", "--workers", str(args.workers)]
        if args.horizon:
            argv += ["--horizon", str(args.horizon)]
        if args.population:
            argv += ["--population", str(args.population)]
        if args.max_time:
            argv += ["--max-time", str(args.max_time)]
        true = inverse_true_parameters(task)
        for name, value in true.items():
            argv += ["--start", f"{name}={args.start_factor * value!r}"]
        argv += args.method_args.split()
        optimise_main(argv)
        doc = json.loads((out / "result.json").read_text())
    doc.pop("history", None)
    if true:
        doc["parameter_rel_error"] = parameter_error(doc["parameters"], true)
        doc["success"] = bool(doc["parameter_rel_error"] <= args.tolerance)
        return doc
    success = doc.get("success_score")
    # Table A's scores are for the full horizon: no success verdict on a shortened episode
    doc["success"] = (None if success is None or doc["best_reward"] is None or args.horizon
                      else bool(doc["best_reward"] >= success))
    return doc


def inverse_true_parameters(task: str) -> dict[str, float]:
    """The hidden parameter values of an inverse task (its ``true_parameters``); empty for a
    manipulation task."""
    from sim_core.tasks.registry import load_task

    spec = load_task(task)
    return dict(spec.true_parameters) if spec.kind == "inverse" else {}


def parameter_error(found: dict[str, float], true: dict[str, float]) -> float:
    """Largest relative error ``|found - true| / |true|`` over the identified parameters.

    Raises:
        ConfigError: a parameter missing from ``found`` or a true value of zero.
    """
    errors = []
    for name, value in true.items():
        if name not in found or value == 0:
            raise ConfigError(f"bench optimise: parameter {name!r} missing from the result or with true value 0")
        errors.append(abs(float(found[name]) - float(value)) / abs(float(value)))
    return max(errors)


def rl_baseline(task: str, args) -> dict[str, Any] | None:
    """PPO (stable-baselines3) on the task's Gymnasium environment (:class:`sim_core.tasks.env.ThinShellTaskEnv`)
    for ``episodes`` episodes; the summed reward of one deterministic episode after training, or None
    when stable-baselines3 is not installed."""
    try:
        from stable_baselines3 import PPO  # optional heavy dependency: the RL baseline only
    except ImportError as err:
        print(f"thinshell bench optimise: RL baseline unavailable ({err}); pip install stable-baselines3")
        return None
    from sim_core.optim.tasks import task_at_horizon
    from sim_core.tasks.env import ThinShellTaskEnv

    spec = task_at_horizon(task, args.horizon)
    env = ThinShellTaskEnv(spec)
    model = PPO("MlpPolicy", env, n_steps=spec.horizon, batch_size=spec.horizon, seed=0, verbose=0)
    model.learn(total_timesteps=args.episodes * spec.horizon)
    obs, _ = env.reset(seed=0)
    total, done = 0.0, False
    while not done:
        action, _ = model.predict(obs, deterministic=True)
        obs, reward, terminated, truncated, _ = env.step(action)
        total += float(reward)
        done = terminated or truncated
    return {"task": spec.name, "method": "ppo", "episodes": args.episodes, "best_reward": total}


def _machine() -> str:
    return f"{platform.machine()} {os.cpu_count()} cores, Python {platform.python_version()}"


def markdown_table(rows: list[dict[str, Any]], args) -> str:
    """The results as a markdown section."""
    head = (f"\n## Task optimisation (`thinshell bench optimise`), {_dt.date.today().isoformat()}\n\n"
            f"Machine: {_machine()}. Settings: episodes {args.episodes}, horizon {args.horizon or 'task'}, seeds "
            f"{args.seeds} (from {args.first_seed}), workers {args.workers}, population {args.population or 'task'}, backend "
            f"{', '.join(sorted({str(r.get('backend')) for r in rows}))}.\n\n"
            "| task | method | seeds | episodes | wall time (s) | rollouts/s | best reward (mean) | start reward | "
            "Table A human | Table A success | success |\n|---|---|---|---|---|---|---|---|---|---|---|\n")
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        groups.setdefault((r["task"], r["method"]), []).append(r)
    lines = []
    for (task, method), rs in groups.items():
        def mean(key):
            vals = [r[key] for r in rs if r.get(key) is not None]
            return sum(vals) / len(vals) if vals else None
        succ = [r.get("success") for r in rs if r.get("success") is not None]
        lines.append("| " + " | ".join(str(v) for v in (
            task, method, len(rs), rs[0].get("episodes"), _fmt(mean("wall_time_s"), ".0f"), _fmt(mean("rollouts_per_s"), ".2f"),
            _fmt(mean("best_reward"), ".4g"), _fmt(mean("start_reward"), ".4g"), _fmt(rs[0].get("human_score"), ".4g"),
            _fmt(rs[0].get("success_score"), ".4g"), f"{sum(succ)}/{len(succ)}" if succ else "-")) + " |")
    return head + "\n".join(lines) + "\n"


def _fmt(v, spec: str) -> str:
    return "-" if v is None else format(v, spec)


def bench_optimise_main(argv: list[str]) -> int:
    """Entry point of ``thinshell bench optimise`` (module docstring); returns the exit code.

    Raises:
        ConfigError: an unknown task or method, fewer than one seed or a negative first seed.
    """
    from sim_core.optim.search import METHODS
    from sim_core.tasks.registry import task_names

    args = _parser().parse_args(argv)
    tasks = args.tasks.split(",") if args.tasks else task_names()
    methods = args.methods.split(",")
    bad = [m for m in methods if m not in METHODS]
    if bad:
        raise ConfigError(f"bench tasks: unknown methods {bad}; known {METHODS}")
    if args.seeds < 1 or args.first_seed < 0:
        raise ConfigError(f"bench optimise: --seeds >= 1 and --first-seed >= 0 required; got {args.seeds}, {args.first_seed}")
    rows = []
    for task in tasks:
        for method in methods:
            for seed in range(args.first_seed, args.first_seed + args.seeds):
                row = run_one(task, method, seed, args)
                rows.append(row)
                print(json.dumps(row) if args.json else
                      f"{row['task']:12s} {method:6s} seed {seed}: reward {row['best_reward']} (start {row['start_reward']}) "
                      f"in {row['wall_time_s']:.1f} s, {row['rollouts_per_s']:.2f} rollouts/s", flush=True)
        if args.rl:
            row = rl_baseline(task, args)
            if row is not None:
                rows.append(row)
                print(json.dumps(row), flush=True)
    if args.markdown:
        with open(args.markdown, "a", encoding="utf-8") as fh:
            fh.write(markdown_table(rows, args))
    return 0
