"""Diagnosis of recordings the simulator did not make: calibrate, test each effect's signature
against a calibrated null, name, refit the named effect and validate it on held-out data.

The score-test pipeline of :mod:`sysid.diagnose.engine` assumes the nominal model is right up to
the concealed effect; on a real cell (or another engine's recordings) the calibrated nominal model
still leaves a structured gap many times the noise, and every candidate can absorb part of it
(SYSID.md "Model-form gap"). This pipeline names an effect only from its own signature
(:mod:`sysid.diagnose.signatures`), each read where the gap matters least:

1. **Calibrate** (:func:`sysid.calibration.calibrate`): the uncertain simulator parameters (gel
   modulus and Poisson ratio, gel-sheet friction, bending stiffness, sensor normal offset; on request
   the contact's compliance and stick regularisation) by weighted least squares within a replay
   budget (by default the start only: :data:`sysid.calibration.CALIBRATION_REPLAYS`), then the
   sensor calibration in closed form. The whitened RMS per channel before and after goes into
   ``baseline``.
2. **Signature tests** on the recording and its calibrated replay: lens distortion and force bias
   from the sensor's own chain (no replay), latency and gel viscoelasticity from the timing of the
   contact events, gel damping from the contact force leading the replay there (Kelvin-Voigt),
   bending plasticity from the sheet's set after release, adhesion from the sheet carried by the
   gel, stiction from the tangential load's overshoot at each slide's breakaway (the mean marker
   shear and the friction ratio, beyond the normal load's).
3. **Null**: thresholds from the noise model (:func:`signatures.null.default_thresholds`); the
   statistic thresholds raised by the same tests on recordings the user declares normal
   (``--baseline``) when given.
4. **Name** (:func:`signatures.null.decide`), **locate** (the named tests' windows, channels and
   markers) and **refit** each named effect on training data, reporting whitened RMS before and
   after on held-out data: held-out contact events for the timing effects (each event predicted with
   the delay or lag fitted on the others), held-out time blocks for the sensor effects (every other
   of ``2 * holdout_blocks`` blocks), a checkerboard of the sheet grid after the release for
   plasticity (its yield angle refitted by replays, :mod:`sysid.diagnose.plasticity_refit`), and
   the other channel at each breakaway for stiction (:mod:`sysid.diagnose.stiction_refit`); gel damping
   is refitted by replays of the gel's dashpot (:mod:`sysid.diagnose.damping_refit`).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from sim_core.errors import CalibrationError, SimulationDivergedError
from sysid.calibration import (CALIBRATION_PARAMETERS, CALIBRATION_REPLAYS, CalibrationResult, calibrate,
                               kinematic_reference, nominal_sensor_calibration)
from sysid.calibration_secant import SECANT_REPLAYS
from sysid.drive_calibration import fit_drive
from sysid.diagnose.damping_refit import refit_damping
from sysid.diagnose.heldout import leave_one_event_out
from sysid.diagnose.gain_guard import split_by_gain
from sysid.diagnose.plasticity_refit import refit_plasticity
from sysid.diagnose.probe_worker import ProbeWorker, calibration_probe
from sysid.diagnose.signatures import Recording, SignatureResult, run_signature_tests
from sysid.diagnose.stiction_refit import cross_channel_refit
from sysid.diagnose.signatures.null import (Decision, Thresholds, calibrated_thresholds, decide,
                                            default_thresholds)
from sysid.diagnose.signatures.damping import contact_force, lead_recording
from sysid.diagnose.signatures.sensor import apply_force_bias, free_gel_rows, lens_design
from sysid.diagnose.signatures.timing import delayed, first_order, smoothed_replay, timing_fits, timing_signal
from sysid.evidence import load_evidence
from sysid.observation import ObservationModel
from sysid.wrench_check import check_wrench

ENGINE_NAME = "signatures"


@dataclass
class SignatureSettings:
    """Settings of the signature diagnosis.

    Attributes:
        dt: replay step, s.
        t_max: use the first t_max s of each recording (None: all).
        recording_map: recording map file for every recording (docs/recording_map.md); None: each bag's
            own ``recording.yaml``, else the INTERFACES.md topics.
        t_start, t_end: read only the samples from ``t_start`` to ``t_end`` s after each recording's
            first stamp (None: open).
        arch: elastic terms of the replays (``numpy``, ``cpu``, ``cuda``).
        calibrate: fit the simulator parameters (``calibration_params``) as well as the sensor
            calibration; False: the sensor calibration only (one replay).
        calibration_params: simulator parameters of the calibration.
        calibration_max_nfev: function evaluations of its least-squares fit.
        calibration_max_replays: replay budget of that fit (:func:`sysid.fit.fit` ``max_replays``;
            None: none; default :data:`sysid.calibration.CALIBRATION_REPLAYS`): the diagnosis makes
            the same replays, and names the same effects, on any machine.
        calibration_max_time: wall-time budget of that fit, s (None, the default: none; a budget
            makes the result depend on the machine's load).
        calibration_secant_replays: replay budget of the calibration's secant stage (the stick
            regularisation, :mod:`sysid.calibration_secant`; default
            :data:`sysid.calibration_secant.SECANT_REPLAYS`; none when ``calibrate`` is False).
        calibration_drive: calibrate the arm's drive along the sensor normal (a spring about the
            recorded command and a damper, :func:`sysid.drive_calibration.fit_drive`) and replay through
            it where the data choose it (the default); False: the recorded pose driven kinematically.
        baseline_factor: a baseline-calibrated statistic threshold is this factor times the largest
            statistic the test reaches on the baselines (the effect-size thresholds stay the
            instrument's resolution).
        holdout_blocks: held-out time blocks of the sensor effects' refits (every other of
            ``2 * holdout_blocks``).
        simulation: overrides of the scene's ``simulation:`` block for the replays.
        workers: processes for the calibration's batched replays.
        batched, batch_size: the calibration's finite-difference columns replayed as one batch of scene copies
            (:func:`sysid.calibration.calibrate`); the signature tests' replays (resumed, through a drive) are serial.
        plasticity_replays: most replays of the bending-plasticity refit (its yield-angle search).
        plasticity_max_time: wall-time budget of that search, s (None, the default: none; the
            replay count bounds it).
        damping_replays: most replays of the gel damping refit with its term
            (:mod:`sysid.diagnose.damping_refit`; one more without it; 0: the replay's lead fitted instead,
            no replay).
        probe_worker: make the calibration's secant probe in a second process beside its start replay
            (:class:`sysid.diagnose.probe_worker.ProbeWorker`; the same replays, about one replay less
            wall time on two cores), where it applies (:func:`probe_worker_for`); False: one process.
        tack: where the recording shows the card carried by the gel (a lift), the gel's tack is part of the nominal
            model before the calibration (:func:`sysid.diagnose.tack.nominal_tack`, as ``thinshell sysid``: the recording's
            carried rows and the tack margin's null decide; a press-slide without carried rows makes no replay and
            keeps the probe's fork), so the signatures are read against a replay that carries the card (without
            it nominal_s109's pixels are 3.58 after calibration); False (the default): a lift's card stays on the
            table. Not the default: on the reference recordings it takes nominal_s109's pixels to 1.62 and plastic_s102's
            diagnosis to its plasticity alone, but damped_s104 still names ``adhesion`` beside its damping, and a tack made
            nominal wherever the card rises with the gel would leave a concealed adhesion nothing to be named by
            (docs/benchmarks_log.md, session 64, lead).
    """

    dt: float = 0.01
    t_max: float | None = None
    recording_map: str | None = None
    t_start: float | None = None
    t_end: float | None = None
    arch: str = "cpu"
    calibrate: bool = True
    calibration_params: tuple[str, ...] = CALIBRATION_PARAMETERS
    calibration_max_nfev: int = 4
    calibration_max_replays: int | None = CALIBRATION_REPLAYS
    calibration_max_time: float | None = None
    calibration_secant_replays: int = SECANT_REPLAYS
    calibration_drive: bool = True
    baseline_factor: float = 2.0
    holdout_blocks: int = 4
    simulation: dict[str, Any] | None = None
    workers: int = 1
    batched: bool = False
    batch_size: int | str | None = None
    plasticity_replays: int = 5
    damping_replays: int = 2
    plasticity_max_time: float | None = None
    probe_worker: bool = False
    tack: bool = False


@dataclass
class Prepared:
    """A recording read, calibrated and replayed.

    Attributes:
        bag: recording path.
        model: its :class:`~sysid.observation.ObservationModel` (calibrated).
        calibration: the :class:`~sysid.calibration.CalibrationResult`.
        prediction: channel -> calibrated nominal replay aligned to the recording.
        recording: the :class:`~sysid.diagnose.signatures.Recording` the tests read.
        results: effect -> :class:`SignatureResult` (undecided until :func:`decide`).
        wall_s: seconds spent.
        notes: what could not be done, and why.
        refit_predictions: effect -> channel -> the replay with the effect's term, for the refits
            that replay the simulator (the report plots them; the damping refit's ``timing_signal``: the
            normal force or mean marker depth with the fitted dashpot, :mod:`sysid.diagnose.damping_refit`).
        replays: the calibration's probe process, kept for the refits' replays
            (:class:`~sysid.diagnose.probe_worker.ProbeWorker` ``submit`` / ``collect``), or None; closed by
            :func:`diagnose_one` (:func:`without_replays`).
    """

    bag: Path
    model: ObservationModel
    calibration: CalibrationResult
    prediction: dict[str, np.ndarray]
    recording: Recording
    results: dict[str, SignatureResult]
    wall_s: float = 0.0
    notes: list[str] = field(default_factory=list)
    refit_predictions: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    replays: ProbeWorker | None = None


def recording_of(model: ObservationModel, prediction: Mapping[str, np.ndarray] | None,
                 reference: Mapping[str, np.ndarray] | None = None) -> Recording:
    """The :class:`Recording` view of a (calibrated) observation model and its prediction (``reference``:
    :attr:`Recording.reference`)."""
    ev = model.evidence
    t0 = ev.start_ns
    t = {ch: (np.asarray(ev.t_ns[ch], dtype=np.int64) - t0) * 1e-9 for ch in ev.channels_present}
    data = {ch: np.asarray(ev.values(ch), dtype=float) for ch in ev.channels_present if ch != "image"}
    sigma = {ch: np.asarray(s, dtype=float) for ch, s in model.sigma.items()}
    for ch in data:
        if ch not in sigma and ch in ev.noise:
            sigma[ch] = np.asarray(ev.noise[ch], dtype=float)
    cal = model.sensor_calibration
    if cal is not None:
        camera = (float(cal.fx), float(cal.fy), float(cal.cx), float(cal.cy), float(cal.distance))
    else:
        cam = model.scene["sensors"][model.sensor]["camera"]
        camera = (float(cam["fx"]), float(cam["fy"]), float(cam["cx"]), float(cam["cy"]), float(cam["distance"]))
    return Recording(t=t, data=data, prediction=None if prediction is None else dict(prediction), sigma=sigma,
                     camera=camera, name=Path(str(ev.source.bag_path)).name,
                     reference=None if reference is None else dict(reference))


def prepare(bag: str | Path, settings: SignatureSettings) -> Prepared:
    """Read, calibrate and replay one recording, and run the signature tests on it.

    A recording whose replay cannot be calibrated (the replay at the scene values diverges) keeps
    the tests that read the recording alone (lens distortion, force bias on the markers' rest rows);
    ``notes`` says why the others did not run. Where the replay with the recorded pose imposed (the damping
    test's reference through the drive, :func:`sysid.calibration.kinematic_reference`) diverges, the damping
    test reads the drive's replay and ``notes`` says so.

    Raises:
        BagReadError: unreadable recording.
        ConfigError: invalid scene.
    """
    t_start = time.monotonic()
    evidence = load_evidence(bag, include_image="auto", recording_map=settings.recording_map,
                             t_start=settings.t_start, t_end=settings.t_end)
    model = ObservationModel(evidence, dt=settings.dt, t_max=settings.t_max, simulation=settings.simulation,
                             arch=settings.arch)
    params = tuple(settings.calibration_params) if settings.calibrate else ()
    notes: list[str] = []
    wrench = check_wrench(evidence) if "wrench" in model.channels else None
    if wrench is not None and wrench.tripped:  # before the probe's fork: its replays are weighed the same way
        model.row_mask = {"wrench": ~wrench.against}
    if settings.calibration_drive and settings.calibrate:
        # the drive first (closed form, as the calibration fits it again), so that a forked probe replays through it
        drive = fit_drive(model)
        model.set_drive_stiffness(drive.replay_stiffness, drive.replay_damping)
    if settings.tack and settings.calibrate and model.sensor is not None:
        from sysid.diagnose.tack import nominal_tack

        tack = nominal_tack(model)  # the recording decides (no carried row: no replay, the probe still forks)
        if tack.on:
            notes.append(f"{bag}: the gel's tack is part of the nominal model ({tack.why})")
    worker = probe_worker_for(model, params, settings)
    beside: dict[str, Any] = {}

    def kinematic_beside(values: Mapping[str, float]) -> None:
        # a secant replay about to be made here, its probe taken: the kinematic reference at its values in the
        # probe process beside it (taken where these become the calibrated values, as they do when the step is
        # accepted; else replayed after the calibration as before)
        if worker is not None and not beside and math.isfinite(model.drive_stiffness) and worker.submit(
                {n: values[n] for n in params if n in values}, values, kinematic=True):
            beside["values"] = dict(values)

    try:
        cal = calibrate(model, params, max_nfev=settings.calibration_max_nfev, workers=settings.workers,
                        max_time=settings.calibration_max_time, max_replays=settings.calibration_max_replays,
                        secant_replays=settings.calibration_secant_replays if settings.calibrate else 0,
                        drive=settings.calibration_drive and settings.calibrate,
                        secant_first=None if worker is None else worker.result,
                        secant_before=None if worker is None else kinematic_beside, batched=settings.batched,
                        batch_size=settings.batch_size)
    except (CalibrationError, SimulationDivergedError) as err:
        # keep what the recording alone can tell (the sensor-chain tests) and say why the rest is missing
        notes.append(f"{bag}: no calibrated replay ({err}); only the tests that read the recording alone ran")
        model.sensor_calibration = None
        cal = CalibrationResult({}, nominal_sensor_calibration(model), {}, {})
    except BaseException:
        if worker is not None:
            worker.close()
        raise
    made = worker.collect() if beside else None
    if made is not None and beside["values"] != dict(cal.params):
        made = None  # the step was not taken: the calibrated values are another replay's
    if worker is not None and not cal.prediction:
        worker.close()
        worker = None
    prediction = {ch: np.asarray(v, dtype=float) for ch, v in (cal.prediction or {}).items()}
    reference = None
    try:
        reference = kinematic_reference(model, cal, made) if prediction else None
    except SimulationDivergedError as err:
        notes.append(f"{bag}: the replay with the recorded pose imposed diverged ({err}); gel damping is read "
                     "against the drive's replay")
    rec = recording_of(model, prediction or None, reference)
    results = run_signature_tests(rec)
    return Prepared(Path(bag), model, cal, prediction, rec, results, time.monotonic() - t_start, notes,
                    replays=worker)


def without_replays(p: Prepared) -> Prepared:
    """``p`` with its probe process (:attr:`Prepared.replays`) ended and dropped (a recording that makes no
    more replays, or one sent to another process)."""
    if p.replays is not None:
        p.replays.close()
    return dataclasses.replace(p, replays=None)


def probe_worker_for(model: ObservationModel, params: Sequence[str], settings: SignatureSettings) -> ProbeWorker | None:
    """A :class:`~sysid.diagnose.probe_worker.ProbeWorker` for the calibration of ``model``, or None where
    ``settings.probe_worker`` is off, there is no calibration, or :func:`~sysid.diagnose.probe_worker.calibration_probe`
    finds its replay would not be the secant stage's first one or cannot run (no secant replay, a parameter fit
    that may step: a budget other than one replay, or a time budget; Taichi already started here). Through a drive
    the child replays through the one ``model`` holds when it is forked (:func:`prepare` sets it first)."""
    if not (settings.probe_worker and settings.calibrate):
        return None
    return calibration_probe(model, params, secant_replays=settings.calibration_secant_replays,
                             max_replays=settings.calibration_max_replays, max_time=settings.calibration_max_time)


# ================================================================================ refits
def _whitened_rms(residual: np.ndarray, sigma: np.ndarray) -> float:
    r = np.asarray(residual, dtype=float)
    return float(np.sqrt(np.mean((r.reshape(-1, sigma.shape[-1]) / sigma) ** 2))) if r.size else float("nan")


def _blocks(n: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Training and held-out rows: every other of ``2 k`` equal blocks."""
    idx = np.arange(n)
    block = np.minimum(idx * 2 * k // max(n, 1), 2 * k - 1)
    held = block % 2 == 1
    return ~held, held


def refit_lens(p: Prepared, r: SignatureResult, k: int) -> dict[str, Any]:
    """Camera intrinsics with and without the radial terms, fitted on training blocks; held-out RMS
    of the recorded pixels against the camera applied to the recorded positions."""
    rec = p.recording
    xyz, uv = rec.data["markers_xyz"], rec.data["markers_uv"]
    train, held = _blocks(len(xyz), k)
    fx, fy, _, _, d = rec.camera
    w = float(np.median(xyz[..., 2])) + d
    sig = np.sqrt(rec.sigma["markers_uv"] ** 2 + (np.array([fx, fy]) / w) ** 2 * rec.sigma["markers_xyz"][:2] ** 2)

    def fit(rows: np.ndarray, radial: bool) -> np.ndarray:
        A_u, A_v = lens_design(xyz[rows], rec.camera)
        n = A_u.shape[0]
        J = np.zeros((2 * n, 6))
        J[:n, 0:2], J[n:, 2:4] = A_u[:, :2] / sig[0], A_v[:, :2] / sig[1]
        if radial:
            J[:n, 4:6], J[n:, 4:6] = A_u[:, 2:] / sig[0], A_v[:, 2:] / sig[1]
        y = np.concatenate([uv[rows][..., 0].reshape(-1) / sig[0], uv[rows][..., 1].reshape(-1) / sig[1]])
        c, *_ = np.linalg.lstsq(J[:, :6 if radial else 4], y, rcond=None)
        return np.concatenate([c, np.zeros(6 - len(c))])

    def predict(rows: np.ndarray, c: np.ndarray) -> np.ndarray:
        A_u, A_v = lens_design(xyz[rows], rec.camera)
        u = A_u[:, :2] @ c[0:2] + A_u[:, 2:] @ c[4:6]
        v = A_v[:, :2] @ c[2:4] + A_v[:, 2:] @ c[4:6]
        return np.stack([u, v], axis=-1)

    c0, c1 = fit(train, False), fit(train, True)
    obs = uv[held].reshape(-1, 2)
    before = _whitened_rms(obs - predict(held, c0), sig)
    after = _whitened_rms(obs - predict(held, c1), sig)
    return {"params": {"k1": float(c1[4]), "k2": float(c1[5]), "fx": float(c1[0]), "cx": float(c1[1]),
                       "fy": float(c1[2]), "cy": float(c1[3])},
            "observable": "markers_uv against the camera applied to the recorded marker positions",
            "heldout": f"every other of {2 * k} time blocks", "rms": {"markers_uv": after},
            "heldout_rms_before": before, "heldout_rms_after": after}


def refit_force_bias(p: Prepared, r: SignatureResult, k: int) -> dict[str, Any]:
    """Offset and drift fitted on the training blocks of the free-gel rows; held-out RMS of the
    wrench there against the calibrated replay without and with them. The blocks divide the free
    rows themselves (every other of ``2 k`` runs of free samples), so that training and held-out rows
    both span every stretch of free gel: blocks of the whole recording can leave the training rows
    in one stretch (a press-slide is free only before the press and after the lift) and the drift
    extrapolated across the contact."""
    rec = p.recording
    tw = rec.t["wrench"]
    free = free_gel_rows(rec)
    free_idx = np.nonzero(free)[0]
    train_f, held_f = _blocks(len(free_idx), k)
    tr, he = np.zeros_like(free), np.zeros_like(free)
    tr[free_idx[train_f]], he[free_idx[held_f]] = True, True
    heldout_note = f"every other of {2 * k} blocks of the free-gel rows"
    if tr.sum() < 3 or he.sum() < 3:  # the free rows fall in one kind of block: fit on all, no held-out figure
        tr, he, heldout_note = free, np.zeros_like(free), None
    sig = rec.sigma["wrench"]
    w = rec.data["wrench"]
    pred = p.prediction.get("wrench", np.zeros_like(w))
    t_ref = float(np.mean(tw[tr])) if tr.any() else 0.0
    X = np.stack([np.ones(int(tr.sum())), tw[tr] - t_ref], axis=1)
    coef, *_ = np.linalg.lstsq(X, (w - pred)[tr], rcond=None)
    from sysid.diagnose.signatures.sensor import AXES

    est = {**{f"offset_{a}": float(coef[0, i]) for i, a in enumerate(AXES)},
           **{f"drift_{a}_per_s": float(coef[1, i]) for i, a in enumerate(AXES)}, "t_ref_s": t_ref}
    after_pred = apply_force_bias(pred, tw, est)
    fit_rms = _whitened_rms((w - after_pred)[tr], sig)
    if heldout_note is None:
        before = after = None
    else:
        before = _whitened_rms((w - pred)[he], sig)
        after = _whitened_rms((w - after_pred)[he], sig)
    return {"params": est, "observable": "wrench where the gel touches nothing",
            "heldout": heldout_note, "rms": {"wrench": fit_rms},
            "heldout_rms_before": before, "heldout_rms_after": after}


def refit_timing(p: Prepared, r: SignatureResult) -> dict[str, Any]:
    """Delay (latency), first-order lag (gel viscoelasticity) or Kelvin-Voigt time constant (damping:
    the replay's force plus tau times its rate, never tensile: :func:`contact_force`) fitted on all
    contact events but one and evaluated on that one, for every event (leave one event out,
    :func:`leave_one_event_out`)."""
    latency, lead = r.effect == "latency", r.effect == "damping"
    rec = lead_recording(p.recording) if lead else p.recording  # the damping test's replay
    fits = timing_fits(rec)
    events = fits["events"] if fits else []
    channel, t, y, yp, sigma = timing_signal(rec)
    if not lead:  # the delay and the lag read the replay as the tests do (Kelvin-Voigt filters it itself)
        yp = smoothed_replay(t, yp)
    taus = np.arange(0.0, 0.3 + 1e-9, max(rec.sample_period(channel) / 2.0, 1e-3))
    fracs = np.linspace(0.0, 1.0, 11)

    def transformed(theta: tuple[float, float]) -> np.ndarray:
        if lead:
            return contact_force(t, yp[:, None], theta[0])[:, 0]
        return delayed(t, yp[:, None], theta[0])[:, 0] if latency else first_order(t, yp[:, None], theta[0], theta[1])[:, 0]

    grid = [(float(a), 0.0) for a in taus] if latency or lead else [(float(a), float(b)) for a in taus[1:] for b in fracs]
    out = leave_one_event_out(t, y, yp, sigma, [e["window_s"] for e in events], grid, transformed)
    best_all = out.pop("theta")
    params = ({"latency_s": best_all[0]} if latency else {"tau_s": best_all[0]} if lead
              else {"tau_s": best_all[0], "fraction": best_all[1]})
    observable = "normal force" if channel == "wrench" else "mean marker depth"
    return {"params": params, "observable": f"{observable} in the contact events' windows",
            "heldout": "leave one contact event out", "per_event": out.pop("per_event"),
            "rms": {channel: out.pop("rms")}, **out}


def refit_sheet(p: Prepared, r: SignatureResult, settings: SignatureSettings,
                named: Sequence[str] = ()) -> dict[str, Any]:
    """Sheet effects. Bending plasticity: the hinge bending's yield angle refitted by replays with
    the calibrated parameters (:func:`sysid.diagnose.plasticity_refit.refit_plasticity`; training and
    held-out sheet points in a checkerboard of the grid, rows of the effect's windows). Adhesion: the
    carried height located, with the sheet's whitened RMS in its windows, not refitted (its bonds
    are refitted by the score stage, :mod:`sysid.diagnose.engine`). Where adhesion is named too (``named``),
    the plasticity refit starts from the replay in which the gel's tack carries the card up to the
    recorded peel (:func:`sysid.diagnose.plasticity_refit.tack_base`)."""
    rec = p.recording
    if r.effect == "bending_plasticity" and p.calibration.prediction:
        try:
            out = refit_plasticity(p.model, p.calibration.params, rec, p.prediction["sheet_points"], r.windows_s,
                                   settings.plasticity_replays, settings.plasticity_max_time,
                                   carried_by_tack="adhesion" in named, worker=p.replays)
        except ValueError as err:
            p.notes.append(f"bending_plasticity: not refitted ({err})")
        else:
            p.refit_predictions[r.effect] = out.pop("prediction")
            out["params"] = {**r.estimate, **out["params"]}
            return out
    t = rec.t["sheet_points"]
    rows = np.zeros(len(t), bool)
    for a, b in r.windows_s:
        rows |= (t >= a) & (t <= b)
    sig = rec.sigma["sheet_points"]
    before = _whitened_rms((rec.data["sheet_points"] - p.prediction["sheet_points"])[rows], sig)
    return {"params": dict(r.estimate), "observable": "sheet_points in the effect's windows",
            "heldout": None, "rms": {"sheet_points": before}, "heldout_rms_before": before,
            "heldout_rms_after": None, "note": "not refitted with the effect's term in this engine"}


def refit_stiction(p: Prepared, r: SignatureResult) -> dict[str, Any]:
    """Static over kinetic friction from each breakaway's decay, held out across channels: the decay's
    shape (relative excess, decay time) fitted on the friction ratio along the slide predicts the mean
    marker shear against the slide and the other way round, each channel's sliding level and trend fitted
    there before and after alike (:func:`sysid.diagnose.stiction_refit.cross_channel_refit`). The ratio
    is ``1 +`` the marker shear's relative excess minus the normal force's over the same window
    (:func:`~sysid.diagnose.signatures.friction.normal_load_excess`)."""
    out = cross_channel_refit(p.recording)
    return {"params": out["params"], "observable": "tangential load at each breakaway (friction ratio and marker shear)",
            "heldout": "the other channel: the decay fitted on the friction ratio predicts the marker shear and the "
                       "other way round",
            "rms": out["rms"], "heldout_rms_before": out["heldout_rms_before"],
            "heldout_rms_after": out["heldout_rms_after"], "per_breakaway": out["per_breakaway"]}


def refit(p: Prepared, r: SignatureResult, settings: SignatureSettings, named: Sequence[str] = ()) -> dict[str, Any]:
    """The named effect's model fitted on training data and its held-out RMS before and after
    (``named``: every effect the signatures name; :func:`refit_sheet`)."""
    if r.effect == "lens_distortion":
        return refit_lens(p, r, settings.holdout_blocks)
    if r.effect == "force_bias":
        return refit_force_bias(p, r, settings.holdout_blocks)
    if r.effect == "damping" and p.calibration.prediction and settings.damping_replays > 0:
        out = refit_damping(p.model, p.calibration.params, p.recording, r.estimate.get("tau_s"), settings.damping_replays)
        if out is not None:
            p.refit_predictions[r.effect] = out.pop("prediction")
            return out
        p.notes.append("damping: not refitted with the gel's dashpot (no such term, no contact event, or its replay "
                       "diverged); the replay's lead fitted instead")
    if r.effect in ("latency", "gel_viscoelasticity", "damping"):
        return refit_timing(p, r)
    if r.effect == "stiction":
        return refit_stiction(p, r)
    return refit_sheet(p, r, settings, named)


def guard_names(p: Prepared, named: Sequence[str], settings: SignatureSettings,
                effects: Sequence[str] | None = None) -> tuple[list[str], list[dict], dict[str, Any]]:
    """Each named effect refitted with its own term (:func:`refit`), and the names kept only where
    that term gains on held-out data (:func:`sysid.diagnose.gain_guard.split_by_gain`).

    Args:
        p: the prepared recording with its signature results.
        named: the effects the decision names, in rank order.
        settings: the diagnosis settings (the refits' budgets).
        effects: refit only these (the others are kept as named); None: every named effect.

    Returns:
        ``(explained, unexplained, refits)``: the kept names, ``["unexplained"]`` when every name was
        withdrawn; the withdrawn ones with their held-out figures and reason; effect -> refit block.
    """
    refits = {e: refit(p, p.results[e], settings, named) for e in named if effects is None or e in effects}
    explained, unexplained = split_by_gain(named, refits)
    if unexplained and not explained:
        explained = ["unexplained"]
    return explained, unexplained, refits


# ================================================================================ pipeline
def _baseline_block(p: Prepared) -> dict[str, Any]:
    cal = p.calibration.summary()
    rms = {ch: float(v) for ch, v in p.calibration.whitened_rms_after.items()}
    return {"params": dict(p.calibration.params), "rms": rms, "fitted": bool(p.calibration.params),
            "calibration": cal, "whitened_rms_before": dict(p.calibration.whitened_rms_before),
            "whitened_rms_after": rms}


def diagnose_one(bag: str | Path, baselines: Sequence[str | Path] = (), settings: SignatureSettings | None = None,
                 baseline_prepared: Sequence[Prepared] | None = None,
                 prepared: Prepared | None = None) -> tuple[dict[str, Any], Prepared]:
    """Diagnose one recording (SYSID.md output contract; engine details under ``extra``).

    Args:
        bag: recording path.
        baselines: recordings declared normal for this cell (calibrate the null).
        settings: :class:`SignatureSettings`.
        baseline_prepared: already prepared baselines (skips re-reading them; only their signature
            results are read, so a baseline prepared in another process may come without its ``model``,
            :mod:`sysid.diagnose.prepare_pool`).
        prepared: ``bag`` already prepared by :func:`prepare` with these settings.

    Returns:
        ``(report, prepared)``.

    Raises:
        BagReadError, CalibrationError: unreadable recording or a replay that cannot start.
    """
    settings = settings or SignatureSettings()
    t0 = time.monotonic()
    if prepared is not None:
        # decisions set flags on the results: start from undecided copies
        p = Prepared(prepared.bag, prepared.model, prepared.calibration, prepared.prediction, prepared.recording,
                     {e: dataclasses.replace(r, detected=False, threshold={}, reason=r.reason if not r.applicable else "")
                      for e, r in prepared.results.items()}, prepared.wall_s, list(prepared.notes),
                     replays=prepared.replays)
    else:
        p = prepare(bag, settings)
    base = (list(baseline_prepared) if baseline_prepared is not None
            else [without_replays(prepare(b, settings)) for b in baselines])
    th: Thresholds = default_thresholds(p.recording)
    if base:
        th = calibrated_thresholds(th, [b.results for b in base], settings.baseline_factor)
    decision: Decision = decide(p.results, th)
    try:
        explained, unexplained, refits = guard_names(p, decision.explained_by, settings)
    finally:
        p = without_replays(p)
    p.notes.extend(u["reason"] for u in unexplained)
    named = [p.results[e] for e in decision.explained_by]
    windows = sorted({(round(a, 4), round(b, 4)) for r in named for a, b in r.windows_s})
    channels = sorted({ch for r in named for ch in r.channels})
    markers = sorted({m for r in named for m in r.markers})
    top = refits.get(explained[0]) if explained else None
    candidates = []
    for effect, r in sorted(p.results.items(), key=lambda kv: -kv[1].statistic):
        if not r.applicable:
            continue
        thr = r.threshold.get("statistic") or 1.0
        candidates.append({"effect": effect, "statistic": float(r.statistic),
                           # tail bound of the statistic against its threshold's chi-square reference
                           "p_value": float(math.exp(-0.5 * max(r.statistic - thr, 0.0))) if r.detected else 1.0,
                           "detected": r.detected, "effect_size": float(r.effect_size), "effect_unit": r.effect_unit})
    doc: dict[str, Any] = {
        "bag": str(bag),
        "baseline": _baseline_block(p),
        "mismatch": {"detected": bool(decision.explained_by), "windows_s": [list(w) for w in windows],
                     "channels": channels, "markers": markers},
        "candidates": candidates,
        "explained_by": list(explained),
        "refit": {"params": dict(top["params"]) if top else {}, "rms": dict(top["rms"]) if top else {},
                  "heldout_rms_before": None if top is None else top["heldout_rms_before"],
                  "heldout_rms_after": None if top is None else top["heldout_rms_after"],
                  "effects": refits},
        "extra": {"engine": ENGINE_NAME, "signatures": {e: r.as_dict() for e, r in p.results.items()},
                  "ties": decision.ties, "contact_properties": decision.contact_properties,
                  "unexplained": unexplained,
                  "null": {"source": "baseline" if base else "default", "baselines": [str(b.bag) for b in base],
                           "statistic": th.statistic, "effect_size": th.effect_size},
                  "notes": p.notes, "wall_time_s": time.monotonic() - t0 + (p.wall_s if prepared is not None else 0.0),
                  "settings": {"dt": settings.dt, "t_max": settings.t_max, "arch": settings.arch,
                               "calibrate": settings.calibrate}},
    }
    return doc, p


def diagnose(bags: Sequence[str | Path], dt: float = 0.01, heldout: Sequence[str | Path] | None = None,
             **kwargs: Any) -> dict[str, Any]:
    """``python -m benchmarks.diagnose_bench --engine sysid.diagnose.signature_engine:diagnose`` entry: the report
    of the first recording (``heldout`` recordings are not used: the engine holds out events and
    time blocks of the recording itself)."""
    del heldout
    doc, _ = diagnose_one(bags[0], settings=SignatureSettings(dt=dt, **kwargs))
    return doc
