"""Refit of gel damping with its physics term: the gel's Kelvin-Voigt time constant, by replays.

The damping signature (:mod:`sysid.diagnose.signatures.damping`) reads a lead of the contact force
over the calibrated replay and models it as ``y + tau dy/dt`` on that replay's force, its rate read by
a Savitzky-Golay filter. That first-order model is not what a damped gel does where the rate changes
within a few samples (the corners of a press and a release, where a dashpot's force jumps with the
velocity) nor where the contact grows: on this simulator's own press-release with a concealed
Kelvin-Voigt gel of 30 ms (``tests/sysid/diagnose/test_damping_refit.py``) the filtered lead fits 25 ms
and leaves a held-out whitened RMS of 11.6 of 24.7 (0.55 of the excess recovered); the replayed term
fits 30 ms and leaves 5.0 of 24.9 (0.83).
Here the term itself is replayed: the calibrated replay with the gel's dashpot
(:mod:`sim_core.candidates.gel_damping`, parameter ``candidate.gel_damping``, s) at a probe time
constant, then at the first fit where it lies far from the probe; the prediction at any ``alpha`` is
interpolated linearly between the replays (exact to first order in ``alpha``). The replay is the
one the lead is read against: kinematic (the pad imposed) also where the calibrated replay went through
the arm drive (through a drive of 3 N/mm a contact of 35-40 N/mm leads by a tenth of the gel's time
constant, :mod:`sysid.diagnose.signatures.damping`), else the calibrated replay itself.

The replay imposes the recorded pose, noise included: the elastic force carries ``k`` times the pose
noise (on damped_s104, whose contact is about 50 N/mm, the reference force scatters 4.0-5.0 N in the
dwell where the recording is flat at 3.1 +- 0.2 N) and the dashpot ``alpha k`` times its rate (0.7 N,
3.6 noise units, for 20 ms, 5 um of pose noise and 10 ms steps), a force the recorded pad never felt
that grows with ``alpha`` and pulls the fit to a smaller one. Every replay of the refit therefore
imposes the pad's motion, the recorded position read through the damping signature's quadratic
Savitzky-Golay filter (:data:`~sysid.diagnose.signatures.damping.RATE_WINDOW_S`,
:func:`smoothed_controls`), the replay without the term included (one more replay): on damped_s104 the
held-out figures go from 1.320 -> 1.212 (the term's change filtered instead, the pose not) to
1.296 -> 1.158, and the fitted time constant from 17.5 to 15 ms (the engine's excess: 17.4 ms).

Training and held-out data as for the other timing effects: the normal force (else the mean marker
depth) in the contact events' windows, ``alpha`` fitted on all events but one and evaluated on that
one, with a gain and an offset per window before and after alike
(:func:`sysid.diagnose.heldout.leave_one_event_out`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from sim_core.errors import SimulationDivergedError
from sysid.diagnose.heldout import leave_one_event_out

GEL_DAMPING_PARAMETER = "candidate.gel_damping"
"""Simulator parameter of the gel's Kelvin-Voigt time constant, s."""

PROBE_FALLBACK_S = 0.02
"""Probe time constant (s) where the signature gives no positive estimate."""

SECOND_REPLAY_FACTOR = 1.5
"""A second replay is made at the first fit when it lies outside ``[probe / f, probe f]``."""


def interpolated(alphas: Sequence[float], signals: Sequence[np.ndarray]) -> Callable[[float], np.ndarray]:
    """The signal at any ``alpha``, piecewise linear in ``alpha`` between replayed ones (linear beyond
    the last, from the last two).

    Args:
        alphas: replayed time constants, s, ascending, the first 0 (the calibrated replay).
        signals: the replayed signal at each, ``(n,)`` each.
    """
    a = np.asarray(alphas, dtype=float)
    S = np.stack([np.asarray(s, dtype=float) for s in signals])

    def at(alpha: float) -> np.ndarray:
        k = int(np.clip(np.searchsorted(a, alpha, side="right") - 1, 0, len(a) - 2))
        w = (alpha - a[k]) / (a[k + 1] - a[k])
        return S[k] + w * (S[k + 1] - S[k])

    return at


def refit_gel_damping(replay: Callable[[float], np.ndarray | None], t: np.ndarray, y: np.ndarray, base: np.ndarray,
                      sigma: float, windows: Sequence[Sequence[float]], probe_s: float, grid_s: np.ndarray,
                      max_replays: int = 2) -> dict[str, Any]:
    """The gel's Kelvin-Voigt time constant fitted by replays of its term, leave one event out.

    Args:
        replay: ``alpha`` (s) -> the replayed signal ``(n,)`` with the dashpot, or None (diverged).
        t: sample times, s, ``(n,)``.
        y: recorded signal ``(n,)``.
        base: the replay without the term ``(n,)`` (the one the lead is read against).
        sigma: the signal's noise.
        windows: the contact events' windows ``[t0, t1]`` s.
        probe_s: first replayed time constant, s (> 0).
        grid_s: time constants searched, s, ascending from 0.
        max_replays: most replays (>= 1): the probe, then the first fit where it lies outside
            ``[probe / SECOND_REPLAY_FACTOR, probe SECOND_REPLAY_FACTOR]``.

    Returns:
        dict with ``tau_s`` (None when the probe replay diverged), ``replayed_s`` (the time constants
        replayed), ``signal`` (the prediction at ``tau_s``, ``(n,)``), ``per_event``, ``rms``, ``heldout_rms_before`` / ``_after`` (as
        :func:`sysid.diagnose.heldout.leave_one_event_out`) and ``notes``.

    Raises:
        ValueError: ``probe_s`` not > 0 or ``max_replays < 1``.
    """

    if not probe_s > 0.0 or max_replays < 1:
        raise ValueError(f"refit_gel_damping: need probe_s > 0 s and max_replays >= 1 (got {probe_s}, {max_replays})")
    notes: list[str] = []
    alphas, signals = [0.0], [np.asarray(base, dtype=float)]

    def add(alpha: float) -> bool:
        s = replay(alpha)
        if s is None:
            notes.append(f"gel damping {alpha:.4g} s: replay diverged")
            return False
        i = int(np.searchsorted(alphas, alpha))
        alphas.insert(i, float(alpha))
        signals.insert(i, np.asarray(s, dtype=float))
        return True

    if not add(float(probe_s)):
        return {"tau_s": None, "replayed_s": [], "notes": notes}
    grid = [(float(a),) for a in grid_s]

    def fit() -> dict[str, Any]:
        at = interpolated(alphas, signals)
        return leave_one_event_out(t, y, base, sigma, windows, grid, lambda th: at(th[0]))

    out = fit()
    first = out["theta"][0]
    if (max_replays >= 2 and first > 0.0
            and not probe_s / SECOND_REPLAY_FACTOR <= first <= probe_s * SECOND_REPLAY_FACTOR and add(first)):
        out = fit()
    tau = float(out.pop("theta")[0])
    return {"tau_s": tau, "replayed_s": [a for a in alphas if a > 0.0], "notes": notes,
            "signal": interpolated(alphas, signals)(tau), **out}


def smoothed_controls(controls: np.ndarray, dt: float) -> np.ndarray:
    """The recorded pose at the replay's steps ``(K + 1, 7)`` with its position read through the damping
    signature's quadratic Savitzky-Golay filter (:data:`~sysid.diagnose.signatures.damping.RATE_WINDOW_S`):
    the pad's motion without the pose sensor's noise (orientation kept)."""
    from scipy.signal import savgol_filter

    from sysid.diagnose.signatures.damping import RATE_WINDOW_S

    out = np.array(controls, dtype=float, copy=True)
    w = max(int(round(RATE_WINDOW_S / dt)), 5)
    w += 1 - w % 2
    if len(out) >= w:
        out[:, :3] = savgol_filter(out[:, :3], w, 2, axis=0)
    return out


def lead_replay(model: Any, params: Mapping[str, float], through_drive: bool) -> Callable[[float], Mapping[str, np.ndarray] | None]:
    """``alpha`` (s) -> the calibrated replay with the gel's dashpot, channel -> values through the sensor
    calibration in force; the pad moved along the smoothed recorded pose (:func:`smoothed_controls`), also
    where the calibrated replay went through the arm drive (``through_drive``: as
    :func:`sysid.calibration.kinematic_reference`, kinematic); None where the replay diverges.

    Args:
        model: the calibrated :class:`~sysid.observation.ObservationModel`.
        params: its calibrated simulator parameters.
        through_drive: the calibrated replay went through the arm drive.
    """

    def replay(alpha: float) -> Mapping[str, np.ndarray] | None:
        stiffness, damping, controls = model.drive_stiffness, model.drive_damping, model.controls
        if through_drive:
            model.set_drive_stiffness(math.inf)
        model.controls = smoothed_controls(controls, float(model.dt))
        try:
            raw = model.predict_raw(model.simulate({**dict(params), GEL_DAMPING_PARAMETER: float(alpha)}))
        except SimulationDivergedError:
            return None
        finally:
            model.controls = controls
            if through_drive:
                model.set_drive_stiffness(stiffness, damping)
        cal = model.sensor_calibration
        return dict(raw) if cal is None else dict(cal.apply(raw, model.marker_rest))

    return replay


def refit_damping(model: Any, params: Mapping[str, float], recording: Any, estimate_s: float | None,
                  max_replays: int = 2) -> dict[str, Any] | None:
    """Gel damping refitted with its term on a calibrated recording (module docstring).

    Args:
        model: the calibrated :class:`~sysid.observation.ObservationModel`.
        params: its calibrated simulator parameters.
        recording: the :class:`~sysid.diagnose.signatures.Recording` with its calibrated replay (and the
            replay with the recorded pose imposed as ``reference`` where the replay went through the drive).
        estimate_s: the signature's lead estimate, s (the probe; :data:`PROBE_FALLBACK_S` where not > 0).
        max_replays: most replays with the dashpot (:func:`refit_gel_damping`; the replay without it, the pad's
            motion smoothed, comes first).

    Returns:
        the refit block of the report (``params``, ``observable``, ``heldout``, ``rms``,
        ``heldout_rms_before`` / ``_after``, ``detail``) and ``prediction`` (``timing_signal``: the timing
        signal with the fitted term, ``(n,)``; popped by the caller), or None where the simulator has no gel damping,
        the recording no timing signal or no event, or the replay without the term or the probe diverged.
    """
    from sysid.diagnose.signatures.damping import lead_recording
    from sysid.diagnose.signatures.timing import TAU_MAX_S, timing_fits, timing_signal

    try:
        model.simulation().get_parameter(GEL_DAMPING_PARAMETER)
    except Exception:  # noqa: BLE001 -- ConfigError: a simulator without the term
        return None
    rec = lead_recording(recording)
    fits = timing_fits(rec)
    sig = timing_signal(rec)
    if not fits or not fits["events"] or sig is None:
        return None
    channel, t, y, yp, sigma = sig
    through_drive = recording.reference is not None
    replay = lead_replay(model, params, through_drive)
    nominal = replay(0.0)
    if nominal is None:
        return None
    # the replay the lead is read against, with the pad's motion smoothed (see lead_replay); a release the
    # signature re-timed keeps its re-timing
    unretimed = timing_signal(dataclasses.replace(recording, prediction=nominal, reference=None))[3]
    yp = yp + unretimed - timing_signal(dataclasses.replace(recording, prediction=recording.reference, reference=None)
                                        if through_drive else recording)[3]

    def signal(alpha: float) -> np.ndarray | None:
        pred = replay(alpha)
        if pred is None:
            return None
        return yp + timing_signal(dataclasses.replace(recording, prediction=pred, reference=None))[3] - unretimed

    probe = float(estimate_s) if estimate_s is not None and estimate_s > 0.0 else PROBE_FALLBACK_S
    grid = np.arange(0.0, TAU_MAX_S + 1e-9, max(rec.sample_period(channel) / 4.0, 5e-4))
    f = refit_gel_damping(signal, t, y, yp, sigma, [e["window_s"] for e in fits["events"]], probe, grid, max_replays)
    if f["tau_s"] is None:
        return None
    observable = "normal force" if channel == "wrench" else "mean marker depth"
    return {"params": {"tau_s": f["tau_s"]}, "model": "the gel's Kelvin-Voigt dashpot replayed (candidate gel_damping)",
            "observable": f"{observable} in the contact events' windows", "heldout": "leave one contact event out",
            "per_event": f["per_event"], "rms": {channel: f["rms"]}, "heldout_rms_before": f["heldout_rms_before"],
            "heldout_rms_after": f["heldout_rms_after"],
            "detail": {"replayed_s": f["replayed_s"], "probe_s": probe, "notes": f["notes"],
                       "through_drive": through_drive},
            "prediction": {"timing_signal": f["signal"]}}
