"""Settings of the missing-physics diagnosis (:mod:`sysid.diagnose.engine`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from sysid.calibration import CALIBRATION_REPLAYS


@dataclass
class Settings:
    """Diagnosis settings.

    Attributes:
        dt: simulation step, s.
        t_max: use the first t_max s of each recording (None: all).
        recording_map: recording map file for every recording (docs/recording_map.md); None: each bag's
            own ``recording.yaml``, else the INTERFACES.md topics.
        t_start, t_end: read only the samples from ``t_start`` to ``t_end`` s after each recording's
            first stamp (None: open).
        alpha: family-wise error rate of the Holm correction.
        bic_threshold: delta-BIC needed to accept a later candidate conditionally on the accepted
            ones when held-out bags are given (otherwise acceptance is by the held-out test).
        holdout_blocks: held-out time blocks when no held-out bag is given.
        fit_max_nfev: function evaluations of the nominal fit.
        fd_step: log step of the J_theta forward differences.
        workers: processes for independent replays; ray_address: Ray cluster instead.
        batched, batch_size: step independent replays together as one batch of scene copies, at most
            ``batch_size`` (an integer, ``"auto"`` or None: all) at a time, in this process
            (:func:`sysid.diagnose.parallel.replay_many`; the calibration's fit too, :func:`sysid.fit.fit`). The
            J_theta forward differences are taken against the nominal replayed in their own batch: a batch copy
            differs from the serial replay by the Newton tolerance, which a difference would divide by ``fd_step``.
        min_explained: effect-size criterion: a refit is accepted only when it removes at least this
            fraction of the held-out excess energy ``rms^2 - 1`` (whitened, noise units) on its
            channels; a systematic model gap that a candidate merely correlates with fails it.
        min_excess: a mismatch is declared only when a channel with a significant test carries a
            whitened excess ``mean(r^2) - 1`` above this (significance alone is not enough).
        simulation: overrides of the scene's ``simulation:`` block for the replays (e.g.
            ``{"gel_resolution": [5, 4, 2]}`` for a coarse, fast gel).
        arch: elastic terms of the replays (:class:`sysid.observation.ObservationModel`):
            ``"numpy"`` or ``"cpu"`` / ``"cuda"`` (fused Taichi kernels, same values to round-off).
        noise_from_residual: raise the declared noise to the white part of the nominal residual
            (:func:`sysid.diagnose.noise.raise_to_white_residual`).
        denoise_window: Savitzky-Golay window (pose samples) of the tracking-error smoothing of the
            replayed poses (:func:`sysid.diagnose.noise.denoise_controls`; 0 = replay the measured poses).
        min_gain: effect-size criterion in absolute terms: the held-out whitened energy per value
            ``rms_before^2 - rms_after^2`` must drop by at least this (noise variance units).
        probe_target: whitened RMS change (noise units, strongest channel) a physics probe should
            reach; a probe outside [1/4, 4] times it is rescaled (:meth:`BagDiagnosis._calibrate_probes`).
        probe_max_growth: largest factor (up or down) of one probe rescaling round.
        secant: refine physics refits by one more replay at the minimiser of a parabola through
            the training SSE at beta = 0, the probe beta and the linearised estimate.
        warm_start: start every replay after the nominal one, step by step, from the nominal
            replay's vertex positions (``ObservationModel.warm_start``). Off by default: with the
            candidates' non-convex terms (stiction's bump, adhesion's bonds) Newton from the
            nominal solution often fails where it converges from the previous step (latency_s103:
            13 of 26 replays diverged, and the report changed; docs/benchmarks_log.md, 2026-11-22).
        calibrate: calibrate the replay before diagnosing (:func:`sysid.calibration.calibrate`:
            the sensor calibration and, when no ``params`` are given,
            :data:`sysid.calibration.CALIBRATION_PARAMETERS`); False: the scene values. Off in the
            library (the own-simulator benchmark's recordings are made by the nominal scene); on by
            default in ``thinshell diagnose`` (``--no-calibrate`` turns it off).
        calibration_max_replays: replay budget of the calibration's parameter fit (the best point
            so far is used when it is spent; None: no budget). A count, so that the calibration is
            the same on any machine.
        calibration_max_time: wall-time budget of that fit, s (None, the default: none; with one,
            the result depends on the machine's load).
    """

    dt: float = 0.01
    t_max: float | None = None
    recording_map: str | None = None
    t_start: float | None = None
    t_end: float | None = None
    alpha: float = 0.01
    bic_threshold: float = 10.0
    holdout_blocks: int = 4
    fit_max_nfev: int = 8
    fd_step: float = 0.05
    workers: int = 1
    ray_address: str | None = None
    batched: bool = False
    batch_size: int | str | None = None
    min_explained: float = 0.25
    min_excess: float = 0.1
    secant: bool = True
    noise_from_residual: bool = True
    denoise_window: int = 11
    min_gain: float = 0.25
    simulation: dict[str, Any] | None = None
    arch: str = "numpy"
    probe_target: float = 2.0
    probe_max_growth: float = 1000.0
    warm_start: bool = False
    calibrate: bool = False
    calibration_max_replays: int | None = CALIBRATION_REPLAYS
    calibration_max_time: float | None = None

    def replay_options(self) -> dict[str, Any]:
        """How independent replays run: the keywords ``workers``, ``ray_address``, ``batched`` and ``batch_size``
        of :func:`sysid.diagnose.parallel.replay_many` and :class:`sysid.diagnose.schedule.ReplayScheduler`."""
        return {"workers": self.workers, "ray_address": self.ray_address, "batched": self.batched,
                "batch_size": self.batch_size}
