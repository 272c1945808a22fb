"""Pipelined replays: sequential chains of dependent replays, run concurrently on a persistent pool.

The diagnosis replays come in short dependent chains, one per candidate: a probe, a retry when it
diverged, up to two rescaled probes (each sized from the previous one's prediction change); a refit's
verifying replay, then its secant replay. Chains of different candidates are independent. Run in
barrier batches (every candidate's first probe, then every retry, ...), a batch of ``n`` replays on
``w`` workers costs ``ceil(n / w)`` replay times, and a chain waits for the slowest replay of each
batch. :class:`ReplayScheduler` instead keeps ``w`` forked worker processes alive for the whole
diagnosis (the observation model, its cached simulation and the Taichi kernels stay built between
replays) and submits a chain's next replay as soon as its previous one returns, so the workers stay
busy until the last chain ends. Replays whose parameters are known ahead of their chain (the
probes that do not depend on the nominal rollout) can be *prefetched* on the workers the nominal
replay leaves idle; a chain that later asks for the same parameter set takes that replay.

A chain is a generator: it yields one parameter dict (``ObservationModel.simulate`` semantics), or
``(parameters, tag)`` with a tag naming the replay's role for the log, receives the replay's
``(trace, prediction)`` or None (diverged), and returns its result. A chain's
result depends only on its own replays, and replays are deterministic, so the results do not depend
on the number of workers nor on the order in which replays finish.
"""

from __future__ import annotations

import multiprocessing
import time
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Callable, Generator, Mapping, Sequence

from sim_core.errors import CalibrationError
from sysid.diagnose import parallel

_UNKNOWN = object()
"""Marker of a parameter set not replayed yet (a diverged replay is None)."""

Replay = Any
"""``(trace, prediction)`` of one replay, or None when it diverged."""

Chain = Generator[Mapping[str, float], Replay, Any]
"""A generator that yields parameter sets, receives their replays and returns its result."""


def _start(chain: Chain) -> tuple[bool, Any]:
    """``(True, next request)`` or ``(False, result)`` of a chain that has not run yet."""
    try:
        return True, next(chain)
    except StopIteration as stop:
        return False, stop.value


def _advance(chain: Chain, replay: Replay) -> tuple[bool, Any]:
    """Send ``replay`` into ``chain``: ``(True, next request)`` or ``(False, result)``."""
    try:
        return True, chain.send(replay)
    except StopIteration as stop:
        return False, stop.value


def _request(value: Any) -> tuple[dict[str, float], str]:
    """``(parameters, tag)`` of what a chain yielded (a parameter dict, or a ``(dict, tag)`` pair)."""
    if isinstance(value, tuple):
        params, tag = value
        return dict(params), str(tag)
    return dict(value), ""


def run_in_rounds(chains: Sequence[Chain], batch: Callable[[list[dict[str, float]]], list[Replay]]) -> list[Any]:
    """Run ``chains`` by rounds: every pending request of a round in one call of ``batch``.

    For one worker (in-process replays) and for Ray (one batch of tasks per round); the number of
    rounds is the length of the longest chain.

    Args:
        chains: generators (module docstring).
        batch: replays a list of parameter sets, returns one :data:`Replay` per set, in order.

    Returns:
        each chain's result, in the order of ``chains``.
    """
    results: list[Any] = [None] * len(chains)
    pending: dict[int, dict[str, float]] = {}
    for i, ch in enumerate(chains):
        more, value = _start(ch)
        if more:
            pending[i] = _request(value)[0]
        else:
            results[i] = value
    while pending:
        order = sorted(pending)
        outs = batch([pending[i] for i in order])
        pending = {}
        for i, rep in zip(order, outs):
            more, value = _advance(chains[i], rep)
            if more:
                pending[i] = _request(value)[0]
            else:
                results[i] = value
    return results


class ReplayScheduler:
    """Replays of one observation model on a persistent pool of forked workers (module docstring).

    The pool is forked at the first :meth:`run` with more than one worker: the workers keep the model
    as it is then (its simulation, alignment and controls; only those enter a replay) and reuse its
    cached simulation for every later replay. Close it with :meth:`close` (or use as a context
    manager).

    Args:
        model: ``sysid.observation.ObservationModel``.
        workers: processes (1: replays in this process, by rounds).
        ray_address: Ray cluster address: replays as Ray tasks, by rounds (overrides ``workers``).
        batched, batch_size: replays in this process by rounds, each round's replays stepped together as one
            batch of scene copies (:func:`sysid.diagnose.parallel.replay_many` ``batched``; overrides ``workers``).

    Replays are deterministic, so a parameter set is simulated once per scheduler: a request for a
    set already replayed (or handed in with :meth:`remember`, e.g. the nominal replay run in this
    process) is answered with that replay without simulating again. A one-sided candidate whose
    linearised refit clips its strength to 0 asks for exactly the nominal set, for instance.

    A replay known to equal the nominal one up to some step starts from there when
    :attr:`resume` says so (set once the nominal replay is in; :mod:`sysid.diagnose.resume`).

    Attributes:
        replays: replays run so far.
        reused: requests answered with an earlier replay of the same parameter set.
        resume: None, or a callable ``params -> Resume | None`` giving the start of a replay
            (``sysid.observation.Resume``; None: from the initial state).
        sim_s: summed simulation wall time of the finished replays, s (``SimTrace.wall_time_s``).
        log: one record per pooled replay, in finishing order: ``{"label", "chain", "step", "tag",
            "cpu_s", "diverged"}``
            (``cpu_s``: the worker's CPU time for it, all its threads; the work the scheduling packs
            onto the workers, independent of other load on the machine).
    """

    def __init__(self, model: Any, workers: int = 1, ray_address: str | None = None, batched: bool = False,
                 batch_size: int | str | None = None) -> None:
        self.model = model
        self.workers = max(1, int(workers))
        self.ray_address = ray_address
        self.batched, self.batch_size = bool(batched), batch_size
        self.replays = 0
        self.reused = 0
        self.resume: Callable[[Mapping[str, float]], Any] | None = None
        self.sim_s = 0.0
        self.log: list[dict[str, Any]] = []
        self._pool: ProcessPoolExecutor | None = None
        self._prefetched: dict[tuple, Future] = {}  # parameter-set key -> replay submitted ahead of its chain
        self._known: dict[tuple, Replay] = {}  # parameter-set key -> its replay (deterministic: reused)

    @property
    def pooled(self) -> bool:
        """Whether replays go to the persistent process pool (``workers > 1``, no Ray, not batched)."""
        return self.workers > 1 and not self.ray_address and not self.batched

    def remember(self, params: Mapping[str, float], replay: Replay) -> None:
        """Record ``replay`` as the replay of ``params`` (one run elsewhere, e.g. in this process):
        later requests for exactly this set take it."""
        self._known[_key(params)] = replay

    def batch(self, sets: Sequence[Mapping[str, float]]) -> list[Replay]:
        """Replay independent parameter sets (:func:`parallel.replay_many` semantics, on the pool)."""
        if not self.pooled or (self._pool is None and len(sets) <= 1):
            # one replay before the pool exists runs here: the workers forked later inherit its
            # built simulation and compiled kernels
            todo = [p for p in sets if _key(p) not in self._known]
            self._replay_here(todo)
            self.reused += len(sets) - len(todo)
            return [self._known[_key(p)] for p in sets]

        def one(params: Mapping[str, float]) -> Chain:
            return (yield params)

        return self.run([one(p) for p in sets])

    def prefetch(self, sets: Sequence[Mapping[str, float]], reserve: int = 1) -> int:
        """Start replays of parameter sets a later chain is expected to ask for.

        Forks the pool if needed (after compiling the kernels) and submits the first of ``sets``,
        as many as there are workers beyond ``reserve`` and beyond those still busy with earlier
        prefetches (``reserve``: cores this process keeps busy meanwhile, e.g. with the nominal
        replay). A later :meth:`run` whose chain asks for one of these exact sets takes its replay
        instead of submitting it again: the results are those without prefetching. Nothing happens
        without a pool (one worker, Ray).

        Returns:
            the number of replays submitted.
        """
        if not self.pooled:
            return 0
        pool = self._ensure_pool()
        submitted = 0
        for p in sets:
            if self._prefetch_in_flight() >= self.workers - reserve:
                break
            if _key(p) not in self._prefetched and _key(p) not in self._known:
                self._prefetched[_key(p)] = pool.submit(_timed_worker, dict(p), self._resume_of(p))
                self.replays += 1
                submitted += 1
        return submitted

    def run(self, chains: Sequence[Chain], label: str = "", priority: Sequence[Any] | None = None) -> list[Any]:
        """Run ``chains`` concurrently; returns each chain's result in the order of ``chains``.

        ``label`` tags the replays in :attr:`log`. A request whose exact parameter set was
        prefetched (:meth:`prefetch`) takes that replay; one already replayed (or remembered) is
        answered with it at once. A free worker takes the pending request of the chain with the
        most replays done (the longest chains are on the critical path), then the lowest
        ``priority`` (comparable values, default: the chain's index; give the chains expected to run longest a lower
        value, so that they do not start last and leave one worker alone at the end), then the
        lowest index. The order changes when replays run, never what they return.

        Raises:
            CalibrationError: a replay failed in a worker with anything but a divergence (the
                message names the parameter set and the error), or a worker process died.
        """
        if priority is not None and len(priority) != len(chains):
            raise ValueError(f"ReplayScheduler.run: {len(priority)} priorities for {len(chains)} chains")
        rank = list(range(len(chains))) if priority is None else list(priority)
        chains = [self._reusing(ch) for ch in chains]
        if not self.pooled:
            return run_in_rounds(chains, self._replay_here)
        pool = self._ensure_pool()
        results: list[Any] = [None] * len(chains)
        running: dict[Future, tuple[int, dict[str, float], str]] = {}
        pending: dict[int, tuple[dict[str, float], str]] = {}  # chain -> its next request, not submitted
        steps = [0] * len(chains)

        def fill() -> None:
            # requests replayed ahead (prefetch) are taken first: they need no worker
            for i in [j for j in pending if _key(pending[j][0]) in self._prefetched]:
                p, tag = pending.pop(i)
                running[self._prefetched.pop(_key(p))] = (i, p, tag)
            # at most one replay per worker in flight; a chain's later replays before other chains'
            # first ones (the longest chains are on the critical path), then by priority and order
            while pending and len(running) + self._prefetch_in_flight() < self.workers:
                i = min(pending, key=lambda j: (-steps[j], rank[j], j))
                p, tag = pending.pop(i)
                running[pool.submit(_timed_worker, p, self._resume_of(p))] = (i, p, tag)
                self.replays += 1

        try:
            for i, ch in enumerate(chains):
                more, value = _start(ch)
                if more:
                    pending[i] = _request(value)
                else:
                    results[i] = value
            fill()
            while running:
                done, _ = wait(list(running), return_when=FIRST_COMPLETED)
                for fut in sorted(done, key=lambda f: running[f][0]):
                    i, p, tag = running.pop(fut)
                    try:
                        rep, cpu_s = fut.result()
                    except BrokenProcessPool as err:
                        raise CalibrationError(f"a replay worker process died while replaying {_short(p)} "
                                               f"(out of memory or a crash in native code): {err}") from err
                    except Exception as err:  # noqa: BLE001 - re-raised with the parameter set named
                        raise CalibrationError(f"replay of {_short(p)} failed in a worker process: "
                                               f"{type(err).__name__}: {err}") from err
                    self._account([rep])
                    self._known[_key(p)] = rep
                    self.log.append({"label": label, "chain": i, "step": steps[i], "tag": tag, "cpu_s": cpu_s,
                                     "diverged": rep is None})
                    steps[i] += 1
                    more, value = _advance(chains[i], rep)
                    if more:
                        pending[i] = _request(value)
                    else:
                        results[i] = value
                fill()
        except BaseException:
            self.close(cancel=True)
            raise
        return results

    def _replay_here(self, sets: Sequence[Mapping[str, float]]) -> list[Replay]:
        """Replay ``sets`` without the pool (in this process, or as Ray tasks), counted, accounted
        and recorded as known."""
        out = self._account(parallel.replay_many(self.model, sets, self.workers, self.ray_address,
                                                 [self._resume_of(p) for p in sets], self.batched, self.batch_size))
        self.replays += len(sets)
        self._known.update((_key(p), rep) for p, rep in zip(sets, out))
        return out

    def _resume_of(self, params: Mapping[str, float]) -> Any:
        """The start of the replay of ``params`` (:attr:`resume`), None: the initial state."""
        return None if self.resume is None else self.resume(params)

    def _reusing(self, chain: Chain) -> Chain:
        """``chain`` with its requests for already replayed parameter sets answered here."""
        more, value = _start(chain)
        while more:
            known = self._known.get(_key(_request(value)[0]), _UNKNOWN)
            if known is _UNKNOWN:
                replay = yield value
            else:
                self.reused += 1
                replay = known
            more, value = _advance(chain, replay)
        return value

    def _prefetch_in_flight(self) -> int:
        """Prefetched replays not yet taken by a chain that still occupy a worker."""
        return sum(not f.done() for f in self._prefetched.values())

    def _account(self, reps: list[Replay]) -> list[Replay]:
        self.sim_s += sum(float(getattr(r[0], "wall_time_s", 0.0) or 0.0) for r in reps if r is not None)
        return reps

    def _ensure_pool(self) -> ProcessPoolExecutor:
        if self._pool is None:
            parallel.compile_before_fork(self.model)
            ctx = multiprocessing.get_context("fork")
            self._pool = ProcessPoolExecutor(self.workers, mp_context=ctx, initializer=parallel._init,
                                             initargs=(self.model,))
        return self._pool

    def close(self, cancel: bool = False) -> None:
        """Shut the worker processes down (``cancel``: drop queued replays first)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=cancel)
            self._pool = None
        self._prefetched.clear()

    def __enter__(self) -> "ReplayScheduler":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close(cancel=exc[0] is not None)


def _timed_worker(params: Mapping[str, float], resume: Any = None) -> tuple[Replay, float]:
    """A pool worker's replay (from ``resume`` when given) and the CPU time it took (s, all threads
    of the worker process)."""
    t = time.process_time()
    rep = parallel._worker(params, resume)
    return rep, time.process_time() - t


def _key(params: Mapping[str, float]) -> tuple:
    """Hashable identity of a parameter set (same names and values: the same replay)."""
    return tuple(sorted((str(k), v) for k, v in params.items()))


def _short(params: Mapping[str, float]) -> str:
    """The parameter set of a replay for an error message (candidate parameters first)."""
    items = sorted(params.items(), key=lambda kv: (not kv[0].startswith("candidate."), kv[0]))
    return "{" + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v!r}" for k, v in items) + "}"
