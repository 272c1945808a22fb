"""Episode-budgeted optimisers: CMA-ES, gradient ascent with Adam through the adjoint, and the hybrid.

* ``cma``: CMA-ES (Hansen 2016) through the ``cma`` package, ask/tell, box bounds, per-task
  population and step size; candidates are ranked by the episode score (ThinShellLab's fitness,
  :mod:`sim_core.optim.episode`: infeasible or early-stopped episodes are penalised as the
  original). One generation costs ``population`` episodes. The run ends when the budget is spent
  or at CMA-ES's own termination criteria in the search space (``es.stop()``: step size, condition
  number, ...; not the score-difference criteria, the rewards not being normalised).
* ``gd``: projected gradient ascent with Adam (Kingma & Ba 2015) on the exact gradient of the
  reward (adjoint). One step costs one episode (rollout + adjoint pass). A step that lands on an
  infeasible episode, or on one scoring no better than the best, halves the learning rate and steps
  again at once from the best point along its (kept) gradient, with Adam's moments restarted
  (backtracking: Adam's step is about ``learning_rate`` per coordinate whatever the gradient's
  size, so near an optimum it overshoots until the step shrinks; an infeasible first step returns
  to the start); a gradient that is exactly zero at the start ends the run (nothing to descend). Adam's
  epsilon is ``1e-8`` times the RMS of the first gradient (rewards come in m^2 or rad: a fixed
  epsilon would swamp small gradients).
* ``hybrid``: CMA-ES for ``hybrid_fraction`` of the episodes (at least one generation), then
  gradient steps from the best feasible candidate (none feasible: from the gradient method's own
  start, the task's reference trajectory). A gradient that is exactly zero there (the effector
  touches nothing: no action changes the reward to first order) hands the rest of the budget back
  to CMA-ES, which continues its search distribution.
* ``gd_starts = K > 1`` (``gd`` and ``hybrid``): the gradient phase follows ``K`` Adam runs at once, each
  with its own moments, step and backtracking as above; every gradient step evaluates their ``K``
  gradients together (:meth:`BatchedGradientSpace.gd_gradients`: one lockstep batch whose adjoint passes
  run together, :mod:`sim_core.optim.batch_gradient`) and costs ``K`` episodes (fewer when less budget
  is left). The starts are the hybrid's ``K`` best feasible CMA-ES candidates (best first); where there
  are fewer (and for ``gd``), the first start and restarts drawn around it, ``y0 + sigma N(0, I)`` clipped
  to the bounds (``sigma`` the CMA-ES step size, seeded by ``seed``). A start whose first gradient is
  exactly zero stops; when every start has stopped, the run goes on as a single start's would.

A :class:`SearchSpace` says what is searched (per-step actions of a manipulation task, material
parameters of an inverse task) in two coordinate systems: the CMA-ES one (control points,
:mod:`sim_core.optim.actions`) and the gradient one (every per-step action). The whole optimiser
state (:class:`SearchState`, including the CMA-ES object) pickles, so a run resumes from a
checkpoint exactly where it stopped.
"""

from __future__ import annotations

import math
import pickle
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol, Sequence

import numpy as np

from sim_core.errors import ConfigError
from sim_core.optim.actions import ControlPointDecoder
from sim_core.optim.episode import Episode, EpisodeResult

METHODS = ("cma", "gd", "hybrid")
CMA_STARTS = ("zero", "reference")
"""What a manipulation task's CMA-ES control points are added to (:class:`ActionSpace`)."""
ADAM_BETAS = (0.9, 0.999)
ADAM_EPS_FRACTION = 1e-8
DEFAULT_LEARNING_RATE = 0.5
"""Adam step in gradient coordinates (for actions: control-point units, 0.5 = 3e-5 m per step)."""
DEFAULT_HYBRID_FRACTION = 0.8
CHECKPOINT_VERSION = 1
FLAT_FITNESS_GENERATIONS = 10**9
"""CMA-ES ``tolflatfitness``: generations of equal scores tolerated (episodes that touch nothing all
score the same; the search goes on, its step size growing)."""


class SearchSpace(Protocol):
    """What an optimiser searches (see the module docstring)."""

    def cma_start(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(x0, low, high)`` of the CMA-ES coordinates."""

    def cma_evaluate(self, points: Sequence[np.ndarray]) -> list[EpisodeResult]:
        """One episode per point."""

    def gd_start(self, cma_point: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(y0, low, high)`` of the gradient coordinates, starting from a CMA-ES point (None: the zero start)."""

    def gd_gradient(self, y: np.ndarray) -> tuple[EpisodeResult, np.ndarray]:
        """The episode at ``y`` and d score / d y (zeros when infeasible)."""

    def candidate(self, phase: str, point: np.ndarray) -> Any:
        """What a point means (per-step actions, parameter values), kept as the best candidate."""


class BatchedGradientSpace(SearchSpace, Protocol):
    """A :class:`SearchSpace` that evaluates several gradients at once (``gd_starts > 1``)."""

    def gd_gradients(self, ys: Sequence[np.ndarray]) -> list[tuple[EpisodeResult, np.ndarray]]:
        """:meth:`SearchSpace.gd_gradient` of every point of ``ys``, evaluated together."""


@dataclass
class ActionSpace:
    """Per-step actions of a manipulation task.

    CMA-ES searches the control points of ``decoder`` around its mean ``z = 0``: with ``start =
    "zero"`` the control points are the actions (``z = 0`` is the zero trajectory, as the original);
    with ``start = "reference"`` they are added to the task's human-designed actions
    (:func:`reference_start`; ``z = 0`` is the reference trajectory, evaluated in the first
    generation), a warm start for tasks where the zero trajectory is far from any good one.
    Gradient ascent searches every step's action in control-point units, ``y = actions / units``
    (shape ``(T * action_dim,)``), from the best CMA-ES point (hybrid), else from the task's
    ``reference_actions``, else from zero.

    Args:
        decoder: the control-point decoder of the task.
        evaluator: batch evaluator (serial or Ray) of the task at the decoder's horizon.
        episode: the in-process episode for gradients (built on first use when None).
        task: the task (for the in-process episode).
        batched_gradients: the :class:`~sim_core.optim.batch_gradient.BatchedEpisodeGradients` of
            :meth:`gd_gradients` (built on first use when None).
        params: global parameter values of the in-process episode (as the evaluator's).
        solver_config: Newton settings of the in-process episode (as the evaluator's).
        start: ``"zero"`` or ``"reference"``: what the CMA-ES control points are added to.

    Raises:
        ConfigError: an unknown ``start``, or ``"reference"`` for a task without reference actions.
    """

    decoder: ControlPointDecoder
    evaluator: Any
    task: Any
    episode: Episode | None = None
    params: dict | None = None
    solver_config: Any = None
    start: str = "zero"
    batched_gradients: Any = None

    def __post_init__(self) -> None:
        if self.start not in CMA_STARTS:
            raise ConfigError(f"task {self.task.name}: CMA-ES start must be one of {CMA_STARTS}, got {self.start!r}")
        if self.start == "reference" and self.task.reference_actions is None:
            raise ConfigError(f"task {self.task.name}: CMA-ES start 'reference' needs the task's reference trajectory")

    @property
    def base_actions(self) -> np.ndarray | None:
        """The actions the CMA-ES control points are added to, shape ``(T, action_dim)``; None: zero."""
        return reference_start(self.task, self.decoder) if self.start == "reference" else None

    @property
    def cma_evaluates_mean(self) -> bool:
        """Whether the first CMA-ES generation evaluates its mean (the warm start itself)."""
        return self.start == "reference"

    def cma_start(self):
        low, high = self.decoder.bounds(warm=self.start == "reference")
        return np.zeros(self.decoder.dim), low, high

    def decode(self, z: np.ndarray) -> np.ndarray:
        """Per-step actions of CMA-ES coordinates ``z``, shape ``(T, action_dim)``."""
        return self.decoder.decode(z, self.base_actions)

    def cma_evaluate(self, points):
        return self.evaluator.evaluate([self.decode(z) for z in points])

    def gd_start(self, cma_point):
        d = self.decoder
        if cma_point is not None:
            start = self.decode(cma_point)
        elif self.task.reference_actions is not None:
            start = reference_start(self.task, d)
        else:
            start = np.zeros((d.horizon, d.action_dim))
        y0 = (start / d.units).reshape(-1)
        return y0, np.tile(d.low / d.units, d.horizon), np.tile(d.high / d.units, d.horizon)

    def actions(self, y: np.ndarray) -> np.ndarray:
        """Per-step actions of gradient coordinates ``y``, shape ``(T, action_dim)``."""
        d = self.decoder
        return np.clip(np.asarray(y).reshape(d.horizon, d.action_dim) * d.units, d.low, d.high)

    def _leave_cma(self) -> None:
        """The CMA-ES populations' resident batch released (a batched evaluator's), so that the gradient phase's
        episode or batch does not share the device with it."""
        release = getattr(self.evaluator, "release", None)
        if release is not None:
            release()

    def gd_gradient(self, y):
        self._leave_cma()
        if self.episode is None:
            self.episode = Episode(self.task, self.decoder.horizon, self.params, self.solver_config)
        res, da, _ = self.episode.reward_gradient(self.actions(y))
        return res.summary(), (da * self.decoder.units).reshape(-1)

    def gd_gradients(self, ys):
        self._leave_cma()
        if self.batched_gradients is None:
            from sim_core.optim.batch_gradient import BatchedEpisodeGradients

            self.batched_gradients = BatchedEpisodeGradients(self.task, self.decoder.horizon, self.params,
                                                             self.solver_config)
        out = self.batched_gradients.reward_gradients([self.actions(y) for y in ys])
        return [(res.summary(), (da * self.decoder.units).reshape(-1)) for res, da, _ in out]

    def candidate(self, phase, point):
        return self.decode(point) if phase == "cma" else self.actions(point)


def reference_start(task, decoder: ControlPointDecoder) -> np.ndarray:
    """The task's human-designed actions cut (or padded with zeros) to the decoder's horizon and
    clipped to the bounds, shape ``(T, action_dim)``: the gradient method's start when there is no
    CMA-ES point (ThinShellLab's trajectory optimisation starts from the human trajectory).

    Raises:
        ConfigError: reference actions of the wrong width.
    """
    ref = np.asarray(task.reference_actions, dtype=float)
    if ref.ndim != 2 or ref.shape[1] != decoder.action_dim:
        raise ConfigError(f"task {task.name}: reference_actions have shape {ref.shape}, "
                          f"expected (steps, {decoder.action_dim})")
    out = np.zeros((decoder.horizon, decoder.action_dim))
    k = min(decoder.horizon, ref.shape[0])
    out[:k] = ref[:k]
    return np.clip(out, decoder.low, decoder.high)


@dataclass
class EpisodeLog:
    """One episode of an optimisation run: index (1-based), phase, reward, score, feasibility."""

    episode: int
    phase: str
    reward: float
    score: float
    infeasible: str | None


@dataclass
class SearchState:
    """Everything an optimisation run needs to continue (pickled into the checkpoint).

    Attributes:
        method: ``cma`` | ``gd`` | ``hybrid``.
        episodes: episode budget.
        seed: random seed (CMA-ES gets ``seed + 1``: the ``cma`` package treats 0 as "random").
        sigma, population: CMA-ES step size (coordinate units) and population.
        learning_rate, hybrid_fraction: Adam step and the CMA-ES share of a hybrid run.
        phase: ``cma`` | ``gd`` | ``cma_rest`` (a hybrid's CMA-ES after a zero gradient) | ``done``.
        history: one :class:`EpisodeLog` per episode.
        best_score, best_reward, best_candidate, best_phase, best_point: the best episode so far
            (score ranks; candidate as :meth:`SearchSpace.candidate`).
        best_cma_point: the best feasible CMA-ES point, where a hybrid's gradient phase starts (None:
            no feasible one; the gradient phase then starts where ``gd`` would).
        es: the ``cma.CMAEvolutionStrategy`` (kept through a hybrid's gradient phase).
        adam: ``{y, m, v, t, lr, eps, best_y, best_score}`` while in the gradient phase.
        gd_starts: Adam runs of the gradient phase ``K`` (module docstring).
        adams: with ``K > 1``, the ``K`` Adam states (as ``adam``, with ``stopped``) in the gradient phase.
        cma_candidates: with ``K > 1``, the ``K`` best feasible CMA-ES ``(score, point)``, best first.
        meta: free description of the problem (task name, horizon, ...) checked on resume.
        stop_reason: how the last :func:`optimise` call ended (``episode budget spent``,
            ``deadline``, or CMA-ES's own termination criteria, e.g. ``{'tolfun': 1e-11}``).
    """

    method: str
    episodes: int
    seed: int
    sigma: float
    population: int
    learning_rate: float = DEFAULT_LEARNING_RATE
    hybrid_fraction: float = DEFAULT_HYBRID_FRACTION
    phase: str = "cma"
    history: list[EpisodeLog] = field(default_factory=list)
    best_score: float = -math.inf
    best_reward: float = math.nan
    best_candidate: Any = None
    best_phase: str | None = None
    best_point: np.ndarray | None = None
    best_cma_point: np.ndarray | None = None
    es: Any = None
    adam: dict | None = None
    meta: dict = field(default_factory=dict)
    stop_reason: str | None = None
    gd_starts: int = 1
    adams: list[dict] | None = None
    cma_candidates: list | None = None

    @property
    def episodes_done(self) -> int:
        """Episodes evaluated so far."""
        return len(self.history)

    @property
    def done(self) -> bool:
        """The budget is spent (or the search stopped)."""
        return self.phase == "done" or self.episodes_done >= self.episodes


def new_state(method: str, episodes: int, *, seed: int = 0, sigma: float = 1.0, population: int = 8,
              learning_rate: float = DEFAULT_LEARNING_RATE, hybrid_fraction: float = DEFAULT_HYBRID_FRACTION,
              meta: dict | None = None, gd_starts: int = 1) -> SearchState:
    """A fresh :class:`SearchState`.

    Raises:
        ConfigError: unknown method or non-positive budget / sigma / population / learning rate, a
            hybrid fraction outside (0, 1), or ``gd_starts`` < 1 (or > 1 with ``cma``).
    """
    if int(gd_starts) < 1 or (method == "cma" and int(gd_starts) > 1):
        raise ConfigError(f"optimiser: gd_starts must be >= 1 (1 with cma), got {gd_starts} with {method!r}")
    if method not in METHODS:
        raise ConfigError(f"optimiser: method must be one of {METHODS}, got {method!r}")
    if int(episodes) < 1 or sigma <= 0 or int(population) < 2 or learning_rate <= 0:
        raise ConfigError(f"optimiser: episodes >= 1, sigma > 0, population >= 2, learning rate > 0 required; got "
                          f"{episodes}, {sigma}, {population}, {learning_rate}")
    if not 0.0 < hybrid_fraction < 1.0:
        raise ConfigError(f"optimiser: hybrid fraction must be in (0, 1), got {hybrid_fraction}")
    return SearchState(method, int(episodes), int(seed), float(sigma), int(population), float(learning_rate),
                       float(hybrid_fraction), phase="gd" if method == "gd" else "cma", meta=dict(meta or {}),
                       gd_starts=int(gd_starts))


def _cma_budget(state: SearchState) -> int:
    if state.method == "cma":
        return state.episodes
    return max(state.population, int(round(state.hybrid_fraction * state.episodes)))


def _record(state: SearchState, phase: str, results: Sequence[EpisodeResult], points: Sequence[np.ndarray]) -> list[EpisodeLog]:
    logs = []
    for res, point in zip(results, points):
        log = EpisodeLog(state.episodes_done + 1, phase, float(res.reward), float(res.score), res.infeasible)
        state.history.append(log)
        logs.append(log)
        if res.score > state.best_score:
            state.best_score, state.best_reward = float(res.score), float(res.reward)
            state.best_phase, state.best_point = phase, np.array(point, dtype=float)
            if phase == "cma" and res.feasible:
                state.best_cma_point = np.array(point, dtype=float)
        if phase == "cma" and res.feasible and state.gd_starts > 1:
            kept = (state.cma_candidates or []) + [(float(res.score), np.array(point, dtype=float))]
            kept.sort(key=lambda entry: -entry[0])
            state.cma_candidates = kept[:state.gd_starts]
    return logs


def _cma_generation(state: SearchState, space: SearchSpace) -> list[EpisodeLog]:
    import cma

    if state.es is None:
        x0, low, high = space.cma_start()
        # no stop on small or flat score differences: rewards come in m^2 (Forming's differ by
        # < 1e-11 near the optimum) and a generation that touches nothing scores flat
        opts = {"popsize": state.population, "bounds": [list(low), list(high)], "seed": state.seed + 1,
                "verbose": -9, "verb_log": 0, "verb_disp": 0, "tolfun": 0.0, "tolfunhist": 0.0,
                "tolflatfitness": FLAT_FITNESS_GENERATIONS}
        state.es = cma.CMAEvolutionStrategy(list(x0), state.sigma, opts)
        if getattr(space, "cma_evaluates_mean", False):
            state.es.inject([np.asarray(x0, dtype=float)], force=True)  # the warm start is the first candidate
    points = [np.asarray(p, dtype=float) for p in state.es.ask()]
    results = space.cma_evaluate(points)
    state.es.tell(points, [-r.score for r in results])
    return _record(state, "cma", results, points)


def _new_adam(state: SearchState, y0: np.ndarray, low: np.ndarray, high: np.ndarray) -> dict:
    """A fresh Adam state at ``y0`` within ``[low, high]``."""
    return {"y": y0, "low": low, "high": high, "m": np.zeros_like(y0), "v": np.zeros_like(y0), "t": 0,
            "lr": state.learning_rate, "eps": None, "best_y": y0.copy(), "best_score": -math.inf}


def _gd_step(state: SearchState, space: SearchSpace) -> list[EpisodeLog]:
    if state.adam is None:
        state.adam = _new_adam(state, *space.gd_start(state.best_cma_point))
    a = state.adam
    y = a["y"].copy()
    res, g = space.gd_gradient(y)
    logs = _record(state, "gd", [res], [y])
    if _adam_update(state, a, y, res, g):
        _all_starts_flat(state)
    return logs


def _all_starts_flat(state: SearchState) -> None:
    """Every start's first gradient was exactly zero: back to CMA-ES (hybrid), else the run is done."""
    if state.es is not None:
        state.phase = "cma_rest"  # nothing to descend at the CMA-ES best: back to CMA-ES
    else:
        state.phase = "done"
        state.stop_reason = "zero gradient at the start: no action changes the reward to first order"


def _adam_update(state: SearchState, a: dict, y: np.ndarray, res: EpisodeResult, g: np.ndarray) -> bool:
    """One Adam step of the run ``a`` from the episode at ``y`` (result ``res``, gradient ``g``), with the
    backtracking of the module docstring; True (and no step) when ``g`` is the run's first and exactly zero."""
    if res.feasible and a["t"] == 0 and not np.any(g):
        return True
    if res.feasible and res.score > a["best_score"]:
        a["best_score"], a["best_y"], a["best_g"] = res.score, y.copy(), g.copy()
    elif a.get("best_g") is not None:
        # infeasible, or no better than the best point: step again from there along its gradient,
        # with half the step and Adam's moments restarted (backtracking)
        y, g = a["best_y"].copy(), a["best_g"]
        a["lr"] *= 0.5
        a["m"], a["v"], a["t"] = np.zeros_like(y), np.zeros_like(y), 0
    else:  # infeasible before any feasible step: back to the start with half the step
        a["y"], a["lr"] = a["best_y"].copy(), 0.5 * a["lr"]
        a["m"][:], a["v"][:] = 0.0, 0.0
        return False
    if a["eps"] is None:
        a["eps"] = ADAM_EPS_FRACTION * max(float(np.sqrt(np.mean(g**2))), np.finfo(float).tiny)
    b1, b2 = ADAM_BETAS
    a["t"] += 1
    a["m"] = b1 * a["m"] + (1 - b1) * g
    a["v"] = b2 * a["v"] + (1 - b2) * g**2
    m_hat, v_hat = a["m"] / (1 - b1 ** a["t"]), a["v"] / (1 - b2 ** a["t"])
    a["y"] = np.clip(y + a["lr"] * m_hat / (np.sqrt(v_hat) + a["eps"]), a["low"], a["high"])
    return False


def _gd_starts(state: SearchState, space: SearchSpace) -> list[dict]:
    """The ``K`` Adam runs of a multi-start gradient phase (module docstring)."""
    points = [p for _, p in (state.cma_candidates or [])][:state.gd_starts]
    starts = [space.gd_start(p) for p in points] or [space.gd_start(state.best_cma_point)]
    y0, low, high = starts[0]
    rng = np.random.default_rng(state.seed + 2)
    while len(starts) < state.gd_starts:
        starts.append((np.clip(y0 + state.sigma * rng.standard_normal(y0.shape), low, high), low, high))
    return [_new_adam(state, *start) for start in starts]


def _gd_batch_step(state: SearchState, space: BatchedGradientSpace) -> list[EpisodeLog]:
    """One step of every running Adam run, their gradients evaluated together (``gd_starts > 1``)."""
    if state.adams is None:
        state.adams = _gd_starts(state, space)
    running = [a for a in state.adams if not a.get("stopped")]
    running = running[:max(1, state.episodes - state.episodes_done)]
    ys = [a["y"].copy() for a in running]
    pairs = space.gd_gradients(ys)
    logs = _record(state, "gd", [res for res, _ in pairs], ys)
    for a, y, (res, g) in zip(running, ys, pairs):
        a["stopped"] = _adam_update(state, a, y, res, g)
    if all(a.get("stopped") for a in state.adams):
        _all_starts_flat(state)
    return logs


def step(state: SearchState, space: SearchSpace) -> list[EpisodeLog]:
    """One batch: a CMA-ES generation or one gradient step (the phase switches as the budget says).

    Returns:
        the episodes of the batch (empty when the run is done).
    """
    if state.done:
        state.phase = "done"
        return []
    if state.phase in ("cma", "cma_rest") and state.es is not None and state.es.stop():
        state.stop_reason = f"CMA-ES termination {dict(state.es.stop())}"
        state.phase = "gd" if state.phase == "cma" and state.method == "hybrid" else "done"
        if state.phase == "done":
            return []
    if state.phase == "cma":
        left = _cma_budget(state) - state.episodes_done
        if left >= state.population or state.episodes_done == 0:
            return _cma_generation(state, space)
        if state.method == "cma":
            state.phase = "done"
            return []
        state.phase = "gd"
    if state.phase == "cma_rest":
        if state.episodes - state.episodes_done >= state.population:
            return _cma_generation(state, space)
        state.phase = "done"
        return []
    return _gd_step(state, space) if state.gd_starts == 1 else _gd_batch_step(state, space)


def optimise(state: SearchState, space: SearchSpace, on_batch: Callable[[SearchState, list[EpisodeLog]], None] | None = None,
             deadline: float | None = None) -> SearchState:
    """Run :func:`step` until the budget is spent, calling ``on_batch(state, logs)`` after each batch
    (progress bars, checkpoints).

    Args:
        state: the search state (fresh or from a checkpoint).
        space: what is searched.
        on_batch: called after every batch.
        deadline: ``time.perf_counter()`` value after which no new batch starts (the state stays
            resumable; a fresh run does at least one batch); None: run to the end of the budget.

    Returns:
        ``state`` (advanced in place).
    """
    state.stop_reason = None
    while not state.done and (deadline is None or state.episodes_done == 0 or time.perf_counter() < deadline):
        logs = step(state, space)
        if not logs:
            break
        if on_batch is not None:
            on_batch(state, logs)
    if state.episodes_done >= state.episodes:
        state.phase, state.stop_reason = "done", "episode budget spent"
    elif state.phase == "done":
        state.stop_reason = state.stop_reason or "episode budget spent (what is left is less than a generation)"
    else:
        state.stop_reason = "deadline"
    if state.best_phase is not None:
        state.best_candidate = space.candidate(state.best_phase, state.best_point)
    return state


def save_checkpoint(path: str | Path, state: SearchState) -> Path:
    """Pickle ``state`` to ``path`` atomically (a temporary file renamed over it)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(pickle.dumps({"version": CHECKPOINT_VERSION, "state": state}))
    tmp.replace(path)
    return path


def load_checkpoint(path: str | Path) -> SearchState:
    """Read a checkpoint written by :func:`save_checkpoint`.

    Raises:
        ConfigError: missing or unreadable file, or another checkpoint version (naming the file).
    """
    path = Path(path)
    try:
        data = pickle.loads(path.read_bytes())
    except (OSError, pickle.UnpicklingError, EOFError, AttributeError) as err:
        raise ConfigError(f"{path}: cannot read optimiser checkpoint ({err})") from err
    if not isinstance(data, dict) or data.get("version") != CHECKPOINT_VERSION:
        raise ConfigError(f"{path}: not a version-{CHECKPOINT_VERSION} optimiser checkpoint")
    return data["state"]
