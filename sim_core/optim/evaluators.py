"""Evaluate batches of episodes: serially in this process, as one batch of scene copies stepped
together (:class:`BatchedEvaluator`, :mod:`sim_core.batch`), or in parallel on Ray.

Ray (https://docs.ray.io) is an optional, heavy dependency (``requirements.txt``); it is imported
inside :class:`RayEvaluator` only, so that the rest of sim_core, its tests and the ROS nodes never
load it. Each Ray actor builds its own :class:`~sim_core.optim.episode.Episode` once and then rolls
out the candidates it is given; an episode is deterministic (``Simulation.reset`` clears the solver's
caches), so a batch gives the same results in any process and in any order.
"""

from __future__ import annotations

import dataclasses

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from sim_core.errors import ConfigError
from sim_core.optim.episode import Episode, EpisodeResult, episode_horizon
from sim_core.solver_config import SolverConfig


class SerialEvaluator:
    """Episodes one after the other in this process.

    Args:
        task: the task.
        horizon: steps per episode (default the task's).
        params: global parameter values of the episodes (a call's ``params`` replace them for it and
            the calls after it).
        solver_config: Newton settings (:class:`~sim_core.optim.episode.Episode`'s default when None).
    """

    workers = 1

    def __init__(self, task, horizon: int | None = None, params: Mapping[str, float] | None = None,
                 solver_config: SolverConfig | None = None) -> None:
        self.episode = Episode(task, horizon, params, solver_config)

    def evaluate(self, actions: Sequence[np.ndarray], params: Sequence[Mapping[str, float]] | None = None) -> list[EpisodeResult]:
        """Roll out each action sequence (optionally each with its own parameter values).

        Args:
            actions: sequences of shape ``(horizon, action_dim)``.
            params: one mapping of parameter values per sequence, or None.

        Returns:
            one :class:`EpisodeResult` (without states) per sequence, in order.
        """
        out = []
        for i, a in enumerate(actions):
            if params is not None:
                self.episode.set_parameters(params[i])
            out.append(self.episode.run(a).summary())
        return out

    def close(self) -> None:
        """Nothing to release."""


class BatchedEvaluator:
    """A population's episodes as one batch: one copy of the task's scene per sequence, stepped
    together (:class:`sim_core.tasks.rollout.PopulationRollout`, :class:`sim_core.batch.BatchedSimulation`),
    by default in lockstep (``SolverConfig.lockstep``: one Newton solve of all copies per step,
    :mod:`sim_core.batch.lockstep`).

    The batch is built at the first call and kept (resident) for the calls after it: a later population
    of the same size and parameter values runs on the same copies, stacked model and lockstep solver
    (:meth:`sim_core.tasks.rollout.PopulationRollout.restart`: one batched reset, nothing built or
    compiled again), with the results of a batch built for it; other parameter values build a new batch
    in its place (an inverse task's candidates); a population split into chunks keeps one batch per chunk
    size.

    Each sequence gets the :class:`EpisodeResult` (without states) that :class:`SerialEvaluator` gives
    it, to the Newton tolerance (in lockstep; exactly when the copies are stepped one after another):
    the same steps, early stops, reward and score (an infeasible episode's reward NaN, a non-finite
    reward infeasible, ``wrench_peak_N`` over the steps taken).

    Args:
        task, horizon, params, solver_config: as :class:`SerialEvaluator` (the same default solver
            settings: no dt halving).
        lockstep: step the copies in lockstep (default), else one after another; it replaces
            ``solver_config.lockstep``.
        batch_size: the most copies stepped together: a larger population is evaluated in chunks of
            this size, one after another (each a batch of its own). None: the whole population as one
            batch; ``"auto"``: the largest size that fits the device (:mod:`sim_core.batch.sizing`:
            probe batches of one and two copies, one step of the first sequence each, measured on the
            first call; host memory and, on ``taichi-cuda``, GPU memory; ``reserve_fraction`` of
            the free memory left unused).
        reserve_fraction: with ``batch_size="auto"``, as :func:`sim_core.batch.sizing.auto_batch_size`.

    Attributes:
        sizing: with ``batch_size="auto"``, the :class:`sim_core.batch.sizing.BatchSizing` of the first
            call (None before it, and without ``"auto"``).

    Raises:
        ConfigError: a horizon outside ``1..task.horizon``, a ``batch_size`` that is neither None,
            ``"auto"`` nor an integer >= 1.
    """

    workers = 1

    def __init__(self, task, horizon: int | None = None, params: Mapping[str, float] | None = None,
                 solver_config: SolverConfig | None = None, lockstep: bool = True,
                 batch_size: int | str | None = None, reserve_fraction: float = 0.2) -> None:
        self.task = task
        self.horizon = episode_horizon(task, horizon)
        self.params = dict(params or {})
        self.solver_config = dataclasses.replace(solver_config or SolverConfig(dt_halvings_on_failure=0),
                                                 lockstep=bool(lockstep))
        if batch_size is not None and batch_size != "auto" and (isinstance(batch_size, str) or int(batch_size) < 1):
            raise ConfigError(f"batched evaluator: batch_size must be an integer >= 1, 'auto' or None; got {batch_size!r}")
        self.batch_size = batch_size if batch_size in (None, "auto") else int(batch_size)
        self.reserve_fraction = float(reserve_fraction)
        self.sizing = None
        self._resident: dict[int, tuple] = {}  # members -> (their parameter values, PopulationRollout)

    def _chunk_size(self, seqs: list[np.ndarray], plist: list[dict]) -> int:
        """Copies per batch for this call (``len(seqs)`` without a bound)."""
        if self.batch_size is None:
            return max(1, len(seqs))
        if self.batch_size == "auto":
            if self.sizing is None:
                from sim_core.batch.sizing import choose_batch_size, measure_per_copy, resources_of
                from sim_core.tasks.rollout import PopulationRollout

                def probe(B: int):
                    rollout = PopulationRollout(self.task, [seqs[0][:1]] * B, [plist[0]] * B,
                                                solver_config=self.solver_config)
                    rollout.run()
                    return rollout

                per_copy = measure_per_copy(probe, resources_of(self.solver_config.backend))
                self.sizing = choose_batch_size(per_copy, None, self.reserve_fraction)
            return self.sizing.B
        return int(self.batch_size)

    def evaluate(self, actions: Sequence[np.ndarray], params: Sequence[Mapping[str, float]] | None = None) -> list[EpisodeResult]:
        """As :meth:`SerialEvaluator.evaluate` (a call's ``params`` replace the evaluator's for it and
        the calls after it, as the serial evaluator's episode keeps the last values set); in batches
        of at most ``batch_size`` copies.

        Raises:
            ConfigError: bad actions or parameter sets; with ``batch_size="auto"``, a probe that
                measured no memory growth.
            InsufficientMemoryError: with ``batch_size="auto"``, not even one copy fits.
        """
        from sim_core.optim.actions import check_actions

        seqs = [self.task.check_actions(check_actions(a, self.horizon, self.task.action_dim)) for a in actions]
        if params is not None:
            if len(params) != len(seqs):
                raise ConfigError(f"batched evaluator: {len(params)} parameter sets for {len(seqs)} sequences")
            plist = []
            for p in params:
                self.params = {**self.params, **dict(p)}
                plist.append(dict(self.params))
        else:
            plist = [dict(self.params)] * len(seqs)
        if not seqs:
            return []
        size = self._chunk_size(seqs, plist)
        results = []
        for start in range(0, len(seqs), size):
            results += self._rollout(seqs[start:start + size], plist[start:start + size]).run()
        return [episode_result(r, self.horizon) for r in results]

    def _rollout(self, seqs: list[np.ndarray], plist: list[dict]):
        """The :class:`~sim_core.tasks.rollout.PopulationRollout` of one batch, ready to run: the resident
        batch of these parameter values restarted with ``seqs``, else a new batch (kept)."""
        from sim_core.tasks.rollout import PopulationRollout

        values = tuple(tuple(sorted(p.items())) for p in plist)
        kept = self._resident.get(len(seqs))
        if kept is not None and kept[0] == values:
            kept[1].restart(seqs)
            return kept[1]
        self._resident.pop(len(seqs), None)  # a batch of other values (an inverse task's) released before the build
        rollout = PopulationRollout(self.task, seqs, plist, solver_config=self.solver_config)
        self._resident[len(seqs)] = (values, rollout)
        return rollout

    def release(self) -> None:
        """Drop the resident batches (their host and device memory), e.g. before a gradient phase builds its own
        batch; the next call builds a batch again."""
        self._resident.clear()

    def close(self) -> None:
        """Release the resident batches (:meth:`release`)."""
        self.release()


def episode_result(r, horizon: int) -> EpisodeResult:
    """The :class:`EpisodeResult` of a :class:`~sim_core.tasks.rollout.RolloutResult` of an episode of
    ``horizon`` steps (:meth:`Episode._result`'s rules: an infeasible episode's reward NaN, a non-finite
    reward infeasible, ``wrench_peak_N`` over the steps taken)."""
    infeasible = r.infeasible
    reward = float(r.reward) if infeasible is None else float("nan")
    if infeasible is None and not np.isfinite(reward):
        infeasible = f"reward is {reward}"
    peak = max((float(np.linalg.norm(w[k, :3])) for w in r.wrench.values() for k in range(1, w.shape[0])),
               default=0.0)
    return EpisodeResult(reward, r.steps_done, horizon, infeasible, r.effector_poses, r.gripper, wrench_peak_N=peak)


def _actor_class():
    """The Ray actor class (defined on first use: ``ray`` is imported here only)."""
    import ray  # optional heavy dependency: imported only when parallel rollouts are asked for

    @ray.remote(num_cpus=1)
    class RolloutActor:
        def __init__(self, task, horizon, params, solver_config):
            self.evaluator = SerialEvaluator(task, horizon, params, solver_config)

        def evaluate(self, actions, params):
            return self.evaluator.evaluate(actions, params)

    return RolloutActor


class RayEvaluator:
    """Episodes spread over Ray actors (one simulation each).

    Args:
        task: the task (sent to each actor; must be picklable by cloudpickle).
        workers: number of actors K >= 1.
        horizon, params, solver_config: as :class:`SerialEvaluator`.
        address: a Ray cluster address (``ray://host:10001`` or ``host:6379``) to join; None starts
            a local Ray instance with ``workers`` CPUs (or joins the one already running in this
            process).

    Raises:
        ConfigError: ``workers`` < 1, or Ray cannot start / connect (naming the address).
    """

    def __init__(self, task, workers: int, horizon: int | None = None, params: Mapping[str, float] | None = None,
                 address: str | None = None, solver_config: SolverConfig | None = None) -> None:
        import ray  # optional heavy dependency: imported only when parallel rollouts are asked for

        if int(workers) < 1:
            raise ConfigError(f"ray evaluator: workers must be >= 1, got {workers}")
        self.workers = int(workers)
        self._started = False
        if not ray.is_initialized():
            try:
                if address is None:
                    # a local instance sized to the workers; the driver's own process does no rollouts
                    ray.init(num_cpus=self.workers, include_dashboard=False, log_to_driver=False,
                             runtime_env={"env_vars": {"PYTHONPATH": _package_root()}})
                else:
                    ray.init(address=address, log_to_driver=False)
            except (ConnectionError, RuntimeError, ValueError) as err:
                raise ConfigError(f"ray: cannot {'start a local instance' if address is None else f'join {address}'}: {err}") from err
            self._started = True
        actor = _actor_class()
        self.actors = [actor.remote(task, horizon, dict(params or {}), solver_config) for _ in range(self.workers)]

    def evaluate(self, actions: Sequence[np.ndarray], params: Sequence[Mapping[str, float]] | None = None) -> list[EpisodeResult]:
        """As :meth:`SerialEvaluator.evaluate`; sequence ``i`` goes to actor ``i mod K`` (contiguous
        chunks keep each actor's batch in one call)."""
        import ray  # optional heavy dependency

        n = len(actions)
        chunks = np.array_split(np.arange(n), min(self.workers, max(n, 1)))
        refs = []
        for actor, idx in zip(self.actors, chunks):
            if idx.size:
                refs.append(actor.evaluate.remote([actions[i] for i in idx],
                                                  None if params is None else [params[i] for i in idx]))
        out: list[EpisodeResult] = []
        for part in ray.get(refs):
            out.extend(part)
        return out

    def close(self) -> None:
        """Stop the actors, and the local Ray instance when this evaluator started it."""
        import ray  # optional heavy dependency

        for a in self.actors:
            ray.kill(a)
        self.actors = []
        if self._started:
            ray.shutdown()
            self._started = False


def _package_root() -> str:
    """The directory holding this ``sim_core`` package: local Ray workers import the same code as
    the driver (a source checkout run with ``python -m`` or pytest is not on the workers' path)."""
    import sim_core

    return str(Path(sim_core.__file__).resolve().parents[1])


def optimiser_solver_config(backend: str) -> SolverConfig:
    """The solver settings of every rollout ``thinshell optimise`` runs (:func:`sim_core.optim.cli.optimise_main`)
    and :func:`sim_core.kernel_compile.compile_task` prepares the kernels of: ``backend``, no time-step halving after a
    failed step (a failed rollout is infeasible, not retried)."""
    return SolverConfig(backend=backend, dt_halvings_on_failure=0)


def make_evaluator(task, workers: int = 1, horizon: int | None = None, params: Mapping[str, float] | None = None,
                   address: str | None = None, solver_config: SolverConfig | None = None, batched: bool = False,
                   batch_size: int | str | None = None):
    """:class:`BatchedEvaluator` (with ``batch_size``) when ``batched`` (one worker, no cluster address), else
    :class:`SerialEvaluator` for one worker without a cluster address, else :class:`RayEvaluator`.

    Raises:
        ConfigError: ``batched`` with several workers or a cluster address; ``batch_size`` without
            ``batched``.
    """
    if batch_size is not None and not batched:
        raise ConfigError("a batch size (--batch-size) applies to a batched evaluator (--batched) only")
    if batched:
        if int(workers) > 1 or address is not None:
            raise ConfigError("a batched evaluator runs in this process: no --workers > 1 or --address with it")
        return BatchedEvaluator(task, horizon, params, solver_config, batch_size=batch_size)
    if int(workers) <= 1 and address is None:
        return SerialEvaluator(task, horizon, params, solver_config)
    return RayEvaluator(task, max(1, int(workers)), horizon, params, address, solver_config)
