"""A recording and its baselines prepared side by side: the baselines in worker processes or Ray tasks.

``thinshell diagnose BAG --baseline B1 B2`` reads, calibrates and replays every recording
(:func:`sysid.diagnose.signature_engine.prepare`; the calibration's replays are nearly all of a
diagnosis's time) and they do not depend on each other. With more than one worker the baselines are
prepared in worker processes (``fork`` when this process has not started Taichi yet, as in the CLI;
``spawn`` otherwise: Taichi's runtime does not survive ``fork``, :mod:`sysid.diagnose.parallel`), or as
Ray tasks when a cluster address is given, while this process prepares the recording itself. A
baseline comes back without its observation model (the simulator stays in the worker): the decision
reads only its signature results (:func:`sysid.diagnose.signatures.null.calibrated_thresholds`). Each
recording is prepared by the same code whichever process runs it, so the answers are the same.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Sequence

from sysid.diagnose.parallel import connected_ray
from sysid.diagnose.signature_engine import Prepared, SignatureSettings, prepare, without_replays


def prepare_baseline(bag: str | Path, settings: SignatureSettings) -> Prepared:
    """:func:`~sysid.diagnose.signature_engine.prepare` without the simulator in the result: ``model``
    None, no probe process and the calibration without its parameter fit's record (``calibration.fit``
    None: a :class:`sysid.fit.FitResult` holds the model); parameters, sensor calibration, whitened RMS and
    prediction are kept."""
    p = without_replays(prepare(bag, settings))
    return dataclasses.replace(p, model=None, calibration=dataclasses.replace(p.calibration, fit=None))


def _pool_context() -> multiprocessing.context.BaseContext:
    from sim_core.ti_backend import current_arch

    return multiprocessing.get_context("fork" if current_arch() is None else "spawn")


def prepare_with_baselines(bag: str | Path, baselines: Sequence[str | Path], settings: SignatureSettings,
                           workers: int = 1, ray_address: str | None = None) -> tuple[Prepared, list[Prepared]]:
    """Prepare ``bag`` here and ``baselines`` beside it (module docstring).

    Args:
        bag: the recording to diagnose (prepared in this process, with its model).
        baselines: recordings declared normal.
        settings: the diagnosis settings (the same for every recording).
        workers: processes in all, this one included (1: everything here, one after the other).
        ray_address: address of a Ray cluster (``"auto"``, ``"ray://host:10001"``): the baselines are
            Ray tasks; overrides ``workers``.

    Returns:
        ``(prepared bag, prepared baselines in the order given)``; baselines prepared elsewhere have
        ``model`` None.

    Raises:
        CalibrationError: a Ray address is given but ``ray`` is not installed
            (:func:`~sysid.diagnose.parallel.connected_ray`).
        BagReadError, ConfigError: from :func:`~sysid.diagnose.signature_engine.prepare`.
    """
    baselines = list(baselines)
    if ray_address and baselines:
        ray = connected_ray(ray_address)
        task = ray.remote(prepare_baseline)
        refs = [task.remote(str(b), settings) for b in baselines]
        return prepare(bag, settings), list(ray.get(refs))
    if workers <= 1 or not baselines:
        base = [without_replays(prepare(b, settings)) for b in baselines]
        return prepare(bag, settings), base
    # the workers fill the cores: each recording's calibration replays in its own process only
    settings = dataclasses.replace(settings, probe_worker=False)
    with ProcessPoolExecutor(min(workers - 1, len(baselines)), mp_context=_pool_context()) as pool:
        futures = [pool.submit(prepare_baseline, str(b), settings) for b in baselines]
        p = prepare(bag, settings)
        return p, [f.result() for f in futures]
