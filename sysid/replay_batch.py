"""Replays of one recording at several parameter sets as one batch of scene copies stepped together.

:func:`simulate_batch` is :meth:`sysid.observation.ObservationModel.simulate` for ``B`` parameter sets at once:
one copy of the replayed scene per set (its own model with the set's values, as
:meth:`~sysid.observation.ObservationModel.prepare` sets them on the cached simulation), the same recorded
controls (each copy's own ``sensor.normal_offset``), and the copies advanced together by one
:class:`sim_core.batch.BatchedSimulation` with ``SolverConfig.lockstep`` (:mod:`sim_core.batch.lockstep`: one
Newton solve of all copies a step; on ``taichi-cuda`` its linear systems by one batched conjugate gradient, on the
CPU backends by one stacked direct solve). Every copy is observed after every step by the observation model's
own :meth:`~sysid.observation.ObservationModel.observe_step`, so each trace holds what ``simulate`` gives, to the
Newton tolerance (the lockstep's guarantee, not bit for bit).

What the batch does not do, and what is done instead (through the serial path):

* a copy whose step fails in the batch (the lockstep takes no substep retries, ``dt_halvings_on_failure``)
  goes on alone from its last good state through ``simulate(resume=...)``, which retries the step in
  substeps as a serial replay does; a replay that diverges there too gives None;
* replays the lockstep cannot take (:func:`batch_refusal`: a resumed replay, a series drive, missing-physics
  candidates, which act through a step hook the stacked model does not carry) and batches whose models the
  stacking refuses (e.g. rigid spheres of a task scene; :func:`sim_core.batch.stacked.stack_models`) run
  one after another through ``simulate``;
* the copies share what the stacked model shares (:data:`SHARED_PARAMETERS`): replays that differ there are
  put in separate batches;
* the replays start cold: the observation model's ``warm_start`` (a position guess per step, which the lockstep
  does not take) is not used; every step still converges to the solver's tolerance.

Cost: copies with different material values are different material groups of the stacked model, each with bodies of
its own (:func:`sim_core.batch.stacked.stack_models`), so the elastic terms launch once per copy: 24 Taichi launches
a Newton iteration for 6 distinct copies of the bundled recording's scene against 7.4 for 6 equal ones (taichi-cpu,
``docs/benchmarks_log.md``, session 42). On the 2-core CPU a batch is about as fast as the same replays one after
another. A forward difference of a batch copy against a serial replay divides their gap (the Newton tolerance) by
the step: take both ends of a difference from one batch.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

from sim_core.batch import BatchedSimulation
from sim_core.batch.sizing import choose_batch_size, measure_per_copy, resources_of
from sim_core.errors import ConfigError, SimulationDivergedError
from sim_core.simulation import Simulation
from sysid.replay_trace import Resume, SimTrace

SHARED_PARAMETERS = ("damping", "contact.stiffness", "contact.eps_v")
"""Model parameters every copy of a lockstep batch shares (:func:`sim_core.batch.stacked.stack_models`):
replays with other values of one of them are batched apart."""


@dataclass
class BatchReport:
    """How :func:`simulate_batch` ran its replays.

    Attributes:
        batched: replays stepped in a lockstep batch (to their end, or to a failed step).
        serial: replays run one after another through ``simulate``, with the reason of each
            (:func:`batch_refusal`, or what the stacking refused).
        resumed: replays whose batch copy failed at a step and that went on alone from the step before it
            (``simulate(resume=...)``, with substep retries); their index -> the failed step.
        batches: lockstep batches run (their sizes).
        wall_s: wall-clock seconds of the whole call.
    """

    batched: int = 0
    serial: dict[int, str] = field(default_factory=dict)
    resumed: dict[int, int] = field(default_factory=dict)
    batches: list[int] = field(default_factory=list)
    wall_s: float = 0.0


def batch_refusal(model: Any, params: Mapping[str, float], resume: Resume | None = None) -> str | None:
    """Why the replay of ``params`` (from ``resume``) cannot be a copy of a lockstep batch; None when it can.

    Args:
        model: the ``sysid.observation.ObservationModel``.
        params: the replay's parameter values (``simulate`` semantics).
        resume: the replay's start, or None (the initial state).
    """
    if resume is not None:
        return "a resumed replay (it starts from another replay's state)"
    if not math.isinf(model.drive_stiffness):
        return "a replay through a series drive (its steps are solved, not given by controls)"
    candidates = sorted(n for n in params if n.startswith("candidate."))
    if candidates:
        return f"missing-physics candidates ({', '.join(candidates)}) act through a step hook a batch does not stack"
    return None


def simulate_batch(model: Any, param_sets: Sequence[Mapping[str, float]], batch_size: int | None = None,
                   resumes: Sequence[Resume | None] | None = None,
                   before_prepare: Callable[[Any], None] | None = None) -> tuple[list[SimTrace | None], BatchReport]:
    """Replay ``model``'s recording once per parameter set, as batches of copies stepped together.

    Args:
        model: the ``sysid.observation.ObservationModel`` (its cached simulation is used to build the copies and
            for the serial replays).
        param_sets: per replay, parameter name -> value (``simulate`` semantics: others at their nominal).
        batch_size: the most copies stepped together (a larger set of replays runs in chunks): an integer >= 1,
            ``"auto"`` (:func:`replay_batch_sizing`, measured on the first call and kept as ``model.batch_sizing``)
            or None (all).
        resumes: per replay, None or the :class:`~sysid.replay_trace.Resume` of ``simulate`` (a resumed replay
            runs serially); default none.
        before_prepare: called with ``model`` before each copy's (and each serial replay's) parameters are set
            (e.g. to clear what an earlier replay left on the cached simulation).

    Returns:
        ``(traces, report)``: per set its :class:`~sysid.replay_trace.SimTrace` (``wall_time_s`` its share of
        its batch's wall time; ``step_totals`` its copy's), or None where it diverged; and the
        :class:`BatchReport`.

    Raises:
        ConfigError: a ``batch_size`` that is neither None, ``"auto"`` nor an integer >= 1; resumes not one per
            set; unknown parameters or values outside their physical range (as ``simulate``).
    """
    t0 = time.perf_counter()
    sets = [dict(p) for p in param_sets]
    resumes = [None] * len(sets) if resumes is None else list(resumes)
    if len(resumes) != len(sets):
        raise ConfigError(f"batched replays: {len(resumes)} resumes for {len(sets)} parameter sets")
    if batch_size == "auto":
        if model.batch_sizing is None:
            model.batch_sizing = replay_batch_sizing(model)
        batch_size = model.batch_sizing.B
    elif batch_size is not None and (isinstance(batch_size, str) or int(batch_size) < 1):
        raise ConfigError(f"batched replays: batch_size must be an integer >= 1, 'auto' or None; got {batch_size!r}")
    report = BatchReport()
    out: list[SimTrace | None] = [None] * len(sets)
    groups: dict[tuple, list[int]] = {}
    for i, (p, r) in enumerate(zip(sets, resumes)):
        why = batch_refusal(model, p, r)
        if why is not None:
            report.serial[i] = why
            continue
        groups.setdefault(_shared_key(model, p), []).append(i)
    for members in groups.values():
        size = len(members) if batch_size is None else int(batch_size)
        for start in range(0, len(members), size):
            chunk = members[start:start + size]
            for i, trace in zip(chunk, _run_batch(model, [sets[i] for i in chunk], chunk, report, before_prepare)):
                out[i] = trace
    for i in sorted(report.serial):
        out[i] = _serial(model, sets[i], resumes[i], before_prepare)
    report.wall_s = time.perf_counter() - t0
    return out, report


def _shared_key(model: Any, params: Mapping[str, float]) -> tuple:
    """The values of :data:`SHARED_PARAMETERS` a replay of ``params`` sets (None: its nominal)."""
    return tuple(None if n not in params else float(params[n]) for n in SHARED_PARAMETERS)


def _serial(model: Any, params: Mapping[str, float], resume: Resume | None,
            before_prepare: Callable[[Any], None] | None) -> SimTrace | None:
    """``model.simulate(params, resume=resume)``; None where it diverged."""
    if before_prepare is not None:
        before_prepare(model)
    try:
        return model.simulate(dict(params), resume=resume)
    except SimulationDivergedError:
        return None


def _copies(model: Any, sets: list[dict], before_prepare: Callable[[Any], None] | None) -> tuple[list, list]:
    """One lockstep :class:`Simulation` per set (a copy of the cached simulation's model with the set's values,
    at its initial state) and each set's ``sensor.normal_offset`` (m)."""
    sims, offsets = [], []
    for p in sets:
        if before_prepare is not None:
            before_prepare(model)
        sim = model.prepare(p)  # the cached simulation with this set's values, reset (ConfigError: bad values)
        offsets.append(model.normal_offset)
        sims.append(Simulation(copy.deepcopy(sim.model), dt=model.dt,
                               solver_config=_lockstep_config(sim.solver.config)))
    return sims, offsets


LOCKSTEP_TOL_VELOCITY = 1e-7
"""Newton tolerance (m/s) of a lockstep copy whose replay applies its last update (``SolverConfig.apply_last_update``,
which the lockstep ignores): the tolerance at which a replay that stops without it is converged (nominal_s101,
docs/benchmarks_log.md, session 55, s55-49rest)."""


def _lockstep_config(config: Any) -> Any:
    """The lockstep copies' solver settings from a replay's ``SolverConfig``: its tolerance, or
    :data:`LOCKSTEP_TOL_VELOCITY` where the replay applies its last update (the lockstep stops without it)."""
    if config.apply_last_update:
        return dataclasses.replace(config, lockstep=True, apply_last_update=False,
                                   tol_velocity=min(config.tol_velocity, LOCKSTEP_TOL_VELOCITY))
    return dataclasses.replace(config, lockstep=True)


def replay_batch_sizing(model: Any, cap: int | None = None) -> Any:
    """The most copies of ``model``'s replayed scene that fit the free memory, at most ``cap``
    (:mod:`sim_core.batch.sizing`: probe batches of one and two copies at the nominal values, one replay step
    each; host memory and, on ``taichi-cuda``, GPU memory; a fifth of the free memory left unused).

    Returns:
        the :class:`sim_core.batch.sizing.BatchSizing`.

    Raises:
        ConfigError: the probe measured no memory growth; InsufficientMemoryError: not even one copy fits.
    """
    def probe(B: int) -> BatchedSimulation:
        sims, offsets = _copies(model, [{}] * B, None)
        batch = BatchedSimulation(sims)
        batch.step([model.control(1, None, offset) for offset in offsets])
        return batch

    return choose_batch_size(measure_per_copy(probe, resources_of(model.simulation().solver.backend)), cap)


def _run_batch(model: Any, sets: list[dict], index: list[int], report: BatchReport,
               before_prepare: Callable[[Any], None] | None) -> list[SimTrace | None]:
    """The replays of ``sets`` (their indices ``index`` in the caller's list) as one lockstep batch."""
    t0 = time.perf_counter()
    sims, offsets = _copies(model, sets, before_prepare)
    try:
        batch = BatchedSimulation(sims)
    except ConfigError as err:  # what the stacked model does not take: one replay after another
        report.serial.update({i: f"the lockstep batch refused it: {err}" for i in index})
        return [None] * len(sets)
    report.batches.append(len(sets))
    report.batched += len(sets)
    obs = [[model.observe_step(s)] for s in sims]
    failed_at: dict[int, int] = {}
    K = model.step_count
    for k in range(1, K + 1):
        res = batch.step([model.control(k, None, offsets[j]) if batch.failures[j] is None else None
                          for j in range(len(sims))])
        for j in res.failed_now:
            failed_at[j] = k
        for j, info in enumerate(res.infos):
            if info is not None:
                obs[j].append(model.observe_step(sims[j]))
        if not batch.active.any():
            break
    share = (time.perf_counter() - t0) / len(sets)
    out: list[SimTrace | None] = []
    for j, p in enumerate(sets):
        if j in failed_at:
            report.resumed[index[j]] = failed_at[j]
            state = sims[j].state
            resume = Resume(step=int(state.step_index), state=state, prefix=model.trace_from(obs[j], 0.0))
            out.append(_serial(model, p, resume, before_prepare))
            continue
        trace = model.trace_from(obs[j], share)
        out.append(dataclasses.replace(trace, step_totals=dataclasses.replace(sims[j].step_totals)))
    return out
