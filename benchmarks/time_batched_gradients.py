"""Wall and CPU time of K reward gradients of a task: one after another (``Episode.reward_gradient``) against
together (``BatchedEpisodeGradients``: one lockstep batch, the adjoint passes run together), and of the same
K episodes' forward passes alone (``Episode.run`` / ``BatchedEvaluator``), so that the reverse passes' share is
the difference. Random actions within 40 % of the bounds (pressing down, as the gradient tests); the kernels
are compiled before the first repetition. ``--arch`` picks the backend (``sim_core.bench.batch.ARCH_BACKENDS``:
``cpu`` taichi-cpu, ``cuda`` taichi-cuda, whose batched adjoint is the batched CG, ``numpy``); ``--K`` may list
several sizes (``8,32``), each timed in turn in the same process (kernels compiled once).

Usage::

    PYTHONPATH=. python benchmarks/time_batched_gradients.py --task forming --K 8 --horizon 10 --reps 3
    PYTHONPATH=. python benchmarks/time_batched_gradients.py --arch cuda --task forming --K 8,32 --horizon 10
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from sim_core.bench.batch import ARCH_BACKENDS
from sim_core.optim.batch_gradient import BatchedEpisodeGradients
from sim_core.optim.episode import Episode
from sim_core.optim.evaluators import BatchedEvaluator
from sim_core.optim.tasks import task_at_horizon
from sim_core.solver_config import SolverConfig


def _actions(task, K: int, press: float) -> list[np.ndarray]:
    out = []
    for seed in range(K):
        rng = np.random.default_rng(seed)
        a = rng.uniform(-0.4, 0.4, size=(task.horizon, task.action_dim)) * task.action_high
        a[:, 2] = -np.abs(a[:, 2]) * (1 - press / 1e-3) - press
        out.append(a)
    return out


def _timed(f):
    w, c = time.perf_counter(), time.process_time()
    result = f()
    return result, time.perf_counter() - w, time.process_time() - c


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--task", default="forming")
    p.add_argument("--K", default="8", help="episodes differentiated together; a comma-separated list times each")
    p.add_argument("--horizon", type=int, default=10)
    p.add_argument("--reps", type=int, default=2)
    p.add_argument("--arch", default="cpu", choices=sorted(ARCH_BACKENDS))
    p.add_argument("--adjoint-solver", help="the batched adjoint's solver (default: BatchedEpisodeGradients')")
    args = p.parse_args()
    backend = ARCH_BACKENDS[args.arch]
    task = task_at_horizon(args.task, args.horizon)
    config = SolverConfig(dt_halvings_on_failure=0, backend=backend)
    sizes = [int(k) for k in str(args.K).split(",")]
    press = 6e-4 if "fold" in args.task else 0.0
    episode = Episode(task, solver_config=config)
    batched = BatchedEpisodeGradients(task, solver_config=config)
    evaluator = BatchedEvaluator(task, solver_config=config)
    solver = args.adjoint_solver or batched.adjoint_solver(backend)
    batched.adjoint_solver = lambda concrete: solver
    warm = _actions(task, 2, press)
    episode.reward_gradient(warm[0])
    batched.reward_gradients(warm)  # kernels compiled, caches warm
    evaluator.evaluate(warm)
    for K in sizes:
        acts = _actions(task, K, press)
        for rep in range(args.reps):
            serial, w_s, c_s = _timed(lambda: [episode.reward_gradient(a) for a in acts])
            _, w_sf, c_sf = _timed(lambda: [episode.run(a) for a in acts])
            together, w_b, c_b = _timed(lambda: batched.reward_gradients(acts))
            _, w_bf, c_bf = _timed(lambda: evaluator.evaluate(acts))
            g_s, g_b = np.array([r[1] for r in serial]), np.array([r[1] for r in together])
            diff = float(np.abs(g_s - g_b).max() / max(np.abs(g_s).max(), 1e-300))
            feasible = sum(r[0].feasible for r in serial), sum(r[0].feasible for r in together)
            print(f"{task.name} K={K} T={args.horizon} {backend} rep {rep}: "
                  f"one after another {w_s:.2f} s wall / {c_s:.2f} s CPU (forward alone {w_sf:.2f} s wall / "
                  f"{c_sf:.2f} s CPU); together [{solver}] {w_b:.2f} s wall / {c_b:.2f} s CPU (forward alone "
                  f"{w_bf:.2f} s wall / {c_bf:.2f} s CPU); feasible {feasible}; gradients' largest difference / "
                  f"largest entry {diff:.1e}", flush=True)

if __name__ == "__main__":
    main()
