"""Independent replays of one observation model, run serially, in processes, on a Ray cluster or as a batch.

Every candidate probe, finite-difference column and candidate refit is one replay of the recording
with its own parameter values; they do not depend on each other, so they are mapped over a
``concurrent.futures.ProcessPoolExecutor`` (fork start: the workers inherit the model), over Ray tasks
when a Ray address is given (``ray`` imported only then), or stepped together as copies of the scene in
one lockstep batch (:func:`sysid.replay_batch.simulate_batch`).
"""

from __future__ import annotations

import copy
import math
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from typing import Any, Mapping, Sequence

import numpy as np

from sim_core.errors import CalibrationError, SimulationDivergedError
from sysid.replay_batch import simulate_batch

_MODEL: dict[str, Any] = {}
"""Per-process observation model of a pool worker (set by the pool initializer)."""


def _init(model: Any) -> None:
    _MODEL["model"] = model


def _reset_candidates(model: Any) -> None:
    """Switch every physics candidate off on the cached simulation.

    ``ObservationModel.prepare`` resets only the parameters listed in ``Model.parameter_names``; the
    ``candidate.<name>`` parameters are not among them, so a probe's beta would otherwise leak into
    every later replay of the same (cached) simulation.

    Likewise a non-finite nominal value (``sheet.yield_angle = inf``: no plasticity) cannot be
    restored through ``Model.set_parameter``, which rejects non-finite values; it is written back
    into the body's material directly.
    """
    sim = getattr(model, "_sim", None)
    inner = getattr(sim, "model", None)
    if inner is None:
        return
    if getattr(inner, "candidates", None):
        inner.candidates = {}
        inner.revision += 1
    for name, nominal in (getattr(model, "_nominal", None) or {}).items():
        if math.isfinite(nominal) or sim.get_parameter(name) == nominal:
            continue
        body, _, key = name.partition(".")
        if body in inner.bodies and key in inner.bodies[body].material:
            inner.bodies[body].material[key] = nominal
            inner.revision += 1


def compile_before_fork(model: Any) -> None:
    """Compile the model's Taichi kernels in this process before worker processes are forked from it
    (``ObservationModel.compile_kernels``; a kernel first compiled inside a forked child hangs it:
    Taichi's compile thread pool does not survive ``fork``). Models without that method are left as
    they are."""
    warm = getattr(model, "compile_kernels", None)
    if callable(warm):
        warm()


def _replay(model: Any, params: Mapping[str, float], resume: Any = None) -> tuple[Any, dict[str, np.ndarray]] | None:
    _reset_candidates(model)
    try:
        trace = model.simulate(dict(params)) if resume is None else model.simulate(dict(params), resume=resume)
    except SimulationDivergedError:
        return None
    return trace, model.predict(trace)


def _worker(params: Mapping[str, float], resume: Any = None) -> tuple[Any, dict[str, np.ndarray]] | None:
    return _replay(_MODEL["model"], params, resume)


def connected_ray(ray_address: str) -> Any:
    """The ``ray`` module, connected to the cluster at ``ray_address`` (``ray.init`` once per process).

    Raises:
        CalibrationError: ``ray`` is not installed.
    """
    try:
        import ray
    except ImportError as err:
        raise CalibrationError(f"--ray-address {ray_address} given but the 'ray' package is not installed "
                               "(pip install 'ray[default]'), or drop --ray-address to use --workers") from err
    if not ray.is_initialized():
        ray.init(address=ray_address, ignore_reinit_error=True)
    return ray


def replay_many(model: Any, param_sets: Sequence[Mapping[str, float]], workers: int = 1,
                ray_address: str | None = None, resumes: Sequence[Any] | None = None, batched: bool = False,
                batch_size: int | str | None = None) -> list[tuple[Any, dict[str, np.ndarray]] | None]:
    """Replay ``model`` once per parameter set.

    Args:
        model: ``sysid.observation.ObservationModel``.
        param_sets: parameter dicts (``ObservationModel.simulate`` semantics).
        workers: processes (1: in this process).
        ray_address: address of a Ray cluster (``"auto"``, ``"ray://host:10001"``); overrides workers.
        resumes: per set, None or a ``sysid.observation.Resume`` to start that replay from
            (``ObservationModel.simulate(resume=...)``); default: none.
        batched: with more than one set and no Ray address, step the replays together in this process as copies
            of the scene (:func:`sysid.replay_batch.simulate_batch`, ``SolverConfig.lockstep``; ``workers`` is
            then not used). The replays a batch cannot take run one after another here instead (the module
            docstring of :mod:`sysid.replay_batch`: resumed replays, a series drive, missing-physics candidates,
            models the stacking refuses), as does a copy's rest after a step that failed in the batch.
        batch_size: with ``batched``, the most copies stepped together: an integer >= 1, ``"auto"`` (the most that
            fit the device's free memory, :func:`sysid.replay_batch.auto_batch_size`) or None (all sets).

    Returns:
        ``(trace, prediction)`` per set, None where the replay diverged.

    Raises:
        CalibrationError: a Ray address is given but ``ray`` is not installed.
    """
    sets = [dict(p) for p in param_sets]
    if not sets:
        return []
    resumes = list(resumes) if resumes is not None else [None] * len(sets)
    if len(resumes) != len(sets):
        raise ValueError(f"replay_many: {len(resumes)} resumes for {len(sets)} parameter sets")
    if ray_address:
        ray = connected_ray(ray_address)
        portable = copy.copy(model)
        portable._sim = None  # the simulator is rebuilt on the worker
        task = ray.remote(_replay)
        ref = ray.put(portable)
        return list(ray.get([task.remote(ref, p, r) for p, r in zip(sets, resumes)]))
    if batched and len(sets) > 1:
        traces, _ = simulate_batch(model, sets, batch_size, resumes, before_prepare=_reset_candidates)
        return [None if t is None else (t, model.predict(t)) for t in traces]
    if workers <= 1 or len(sets) == 1:
        return [_replay(model, p, r) for p, r in zip(sets, resumes)]
    compile_before_fork(model)
    ctx = multiprocessing.get_context("fork")
    with ProcessPoolExecutor(min(workers, len(sets)), mp_context=ctx, initializer=_init, initargs=(model,)) as pool:
        return list(pool.map(_worker, sets, resumes))
