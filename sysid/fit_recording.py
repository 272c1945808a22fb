"""Fit a recording end to end: evidence, observation model, sensor calibration, fit, ``fit.json`` and report.

What ``thinshell sysid`` (:mod:`sysid.cli`) and the sysid node (``thinshell_ros.sysid_node``) both
run: the bag is read into an evidence bundle (:func:`sysid.evidence.load_evidence`), its effector
poses are replayed in the simulator (:class:`sysid.observation.ObservationModel`), the sensor is
calibrated in closed form as ``thinshell diagnose`` does (:func:`sysid.calibration.calibrate`: wrench
gains, marker scales, camera intrinsics; the fit is then judged against the calibrated prediction),
the parameters are fitted (:func:`sysid.fit.fit`) and ``fit.json`` (:mod:`sysid.results`), the
plots, ``report.md`` and ``report.html`` (:mod:`sysid.report`) are written into the output
directory, which appears whole or not at all. On request the fitted scene is written too
(:mod:`sysid.fitted_scene`: the bag's scene with the fitted values, their uncertainty and any
modelled effect).
"""

from __future__ import annotations

import dataclasses
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

from sim_core.elastic import SOLID_ELEMENTS
from sim_core.errors import ConfigError
from sim_core.scenes.tactile_scene import SIMULATION_KEYS
from sysid.calibration import CALIBRATION_BOUNDS, CALIBRATION_REPLAYS, FOLLOWED_RMS, CalibrationResult, calibrate
from sysid.calibration_secant import SECANT_PARAMETERS, SECANT_REPLAYS
from sysid.covariance import DEFAULT_ROBUST_METHOD, ROBUST_METHODS
from sysid.diagnose.probe_worker import calibration_probe
from sysid.drive_calibration import fit_drive
from sysid.evidence import load_evidence
from sysid.gain_prior import GainPrior
from sysid.gain_profile import GainProfile
from sysid.fit import (DEFAULT_NUISANCE, DEFAULT_PARAMETERS, FIRST_STEP, STOP_ROBUST_SIGMA, STOP_SIGMA, SYSID_STOP_RMS, STOP_TRIAL_SIGMA, Evaluation,
                       FitResult, fit, joint_nuisance, joint_tangent_names)
from sysid.identifiability import law_verdict, not_identified_note, prior_ranges
from sysid.gel_law import (AUTO_LAW, ask_beside, auto_not_applicable, choose_at_start, gel_mesh, model_parameters,
                           other_law)
from sysid.fitted_scene import fitted_scene_from_result, write_fitted_scene
from sysid.jacobians import TangentReplay, make_jacobian
from sysid.observation import ObservationModel, SimTrace, scene_dict_for
from sysid.report import write_report
from sysid.results import fit_document, provenance, staged_directory, write_fit_json
from sysid.diagnose.tack import LAYER_RATIO_PRIOR, SHEAR_STIFFNESS_SETTING, nominal_tack
from sysid.jacobians import LAYER_NORMAL_RATIO_SETTING
from sysid.wrench_check import check_wrench

PROFILE_REPLAYS = 0
"""Default replays on each side of each fitted parameter's profile (:attr:`FitOptions.profile_replays`,
:func:`sysid.identifiability.profile_intervals`): none, the linearised rule (the robust 2-sigma interval, floored at
the Gauss-Newton one, against the prior range). ``--profile-replays 2`` replays each side's 2-sigma end and, where the
cost there is within the null's spread, the prior's bound: on nominal_s101 13 replays, 663 CPU s for the whole job
against ~170 without (docs/benchmarks_log.md, session 59, 49ident), too dear for the default."""


def available_cores() -> int:
    """The CPU cores this process may run on (its affinity: ``taskset`` limits it), at least 1."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


@dataclass(frozen=True)
class FitOptions:
    """The settings of one fit (the options of ``thinshell sysid``; see :func:`sysid.fit.fit`).

    Attributes:
        params: global parameter names (default :data:`sysid.fit.DEFAULT_PARAMETERS`).
        scene: scene file overriding the bag's ``scene.yaml``, or None.
        dt: replay step in s.
        t_max: fit only the first ``t_max`` s of the recording (None: all).
        recording_map: recording map file saying where each role of a real cell's bag comes from
            (docs/recording_map.md); None: ``recording.yaml`` in the bag directory, else INTERFACES.md.
        t_start, t_end: read only the samples from ``t_start`` to ``t_end`` s after the recording's
            first stamp (None: open); ``t_max`` counts from that window's start.
        channels: channels to fit (None: all the recording has).
        gel_resolution: gel tet resolution ``(NX, NY, NZ)`` overriding the scene's, or None.
        gel_element: the gel's element and law in every replay, one of :data:`sim_core.elastic.SOLID_ELEMENTS`
            (``green_strain``: the Green-strain law of :mod:`sim_core.energies.green_strain`; ``modified_stvk``:
            its volumetric term in ``ln J``, :mod:`sim_core.energies.modified_stvk`), or
            :data:`sysid.gel_law.AUTO_LAW` (the law the recording chooses at the fit's start: the scene's law
            calibrated, each law's modulus, friction and stick speed stepped once on its start replay's tangents, the
            scene's law kept unless the other is better beyond the comparison's spread under the null,
            :func:`sysid.gel_law.choose_at_start`; one replay with tangents more than the scene's law, which a fit
            with the other law takes as its first; ``thinshell sysid``'s default); the scene's law where the comparison
            does not apply (:func:`sysid.gel_law.auto_not_applicable`: no tactile sensor, the tack on (its layer is
            fitted with the scene's law; the comparison is made on replays without it), a scene naming another law, a
            ``gel_resolution`` coarser than the scene's; ``diagnostics.gel_law.kept`` says why); None: the scene's.
            ``fit.json`` reports it (``diagnostics.gel_law``).
        arch: elastic terms of the replays: ``cpu`` / ``cuda`` (Taichi) or ``numpy``.
        jacobian: Jacobian provider (``auto``, ``sensitivity``, ``fd``).
        fd_step: finite-difference step in log units.
        global_method: global phase before the local least squares (``cma``, ...), None: none.
        global_evals: replay budget of the global phase (None: its default).
        max_time: wall-time budget in s (None: none).
        max_nfev: function evaluations of the local phase.
        stop_sigma, stop_trial_sigma, stop_rms, stop_robust_sigma: stopping rules of :func:`sysid.fit.fit`
            (None: off; ``stop_rms`` default :data:`sysid.fit.SYSID_STOP_RMS`, ``stop_robust_sigma``
            :data:`sysid.fit.STOP_ROBUST_SIGMA`).
        stop_trial_robust: the trial-step stop measured in the robust sigma where larger (:func:`sysid.fit.fit`).
        nuisance: ``(name, prior 1-sigma)`` pairs of fixed parameters whose uncertainty enters the robust
            sigma (:func:`sysid.fit.fit` ``nuisance``); None: :data:`sysid.fit.DEFAULT_NUISANCE` less the
            names the scene lacks; empty: none.
        warm_start: start each replay's Newton solves from the best replay so far (``thinshell sysid --warm-start``).
            False (the default since session 54): every replay cold, a function of its parameters only. A warm replay
            keeps the warming replay's card where the card rests under static friction (nominal_s101 at the scene's
            values warmed from a +30 % replay: the sheet points 0.117 whitened RMS, 0.25 mm at most, from the cold
            replay), so the fit's objective depended on its start (8 % of the cost, bending's identification;
            docs/benchmarks_log.md, session 53, s53-49start, and session 54, s54-49time).
        sensor_calibration: calibrate the sensor in closed form before the fit (False: fit against
            the scene's sensor calibration).
        calibration_params: simulator parameters calibrated with the sensor before the fit
            (:func:`sysid.calibration.calibrate`, as ``thinshell diagnose`` does; ``thinshell sysid
            --calibrate``: :data:`sysid.calibration.CALIBRATION_PARAMETERS`), the fitted ``params``
            left out; their calibrated values are the fit's fixed nominal. Empty: the sensor only.
        calibration_max_time: wall-time budget of that calibration's parameter fit, s (None: none;
            with one, the calibration depends on the machine's load).
        calibration_max_replays: replay budget of that calibration's parameter fit (None: none;
            default :data:`sysid.calibration.CALIBRATION_REPLAYS`, as ``thinshell diagnose``).
        workers: processes for batched replays (finite-difference columns, global populations; ``thinshell sysid``'s
            default: :func:`available_cores`, which also sets :attr:`probe_worker` from 2 on).
        seed: seed of the global phase.
        batched, batch_size: replay the fit's independent replays as batches of scene copies (:func:`sysid.fit.fit`).
        robust: covariance reported beside the Gauss-Newton one (:data:`sysid.covariance.ROBUST_METHODS`,
            default ``hac``; None: none).
        profile_gains: refit the sensor gains (within their prior) to every replay of the fit, in closed form
            (:mod:`sysid.gain_profile`; True, the default), so that gains fitted at an off start do not bias the
            materials; fit.json's sensor calibration is then the one at the fitted values. False: the gains of
            the calibration at the start are held through the fit.
        drive: fit the effector's drive along the sensor normal (:func:`sysid.drive_calibration.fit_drive`: a
            spring and damper, chosen over a kinematic arm by delta-BIC) and make every replay, the calibration's
            and the fit's, take it where the data choose it (True, the default, as in ``thinshell diagnose``);
            the fit's Jacobian is then analytic through the drive (:func:`sysid.replay_drive.drive_sensitivities`).
            False: the recorded pose driven kinematically. (Until session 51 the Jacobian through the drive was
            taken by finite differences, whose columns carry the drive's force tolerance over the difference
            step: on nominal_s101 up to 93 % off the tangent, and the fit did not finish in 560 s;
            docs/benchmarks_log.md, session 51, 49sysdrive.)
        tack: where the recording shows the card carried by the gel (a lift), make the gel's tack part of the
            nominal model, released at the recorded peel, with its compliant shear layer fitted from the carried card
            where it follows better (:func:`sysid.diagnose.tack.nominal_tack`), then its ``k_t`` fitted jointly with the
            materials (its tangent column; each channel weighed by its gap at the fit's start);
            fit.json ``diagnostics.tack`` says what was decided and why. True: the recording decides (no carried
            row: no tack and no replay, the replay backend not started by the decision; carried rows: the tack kept
            by :func:`sysid.diagnose.tack.tack_margin`); nominal_s109's sheet points at the engine's values whitened RMS 82
            without it, 8.4 with the layer (docs/benchmarks_log.md, sessions 56-57). False (the default): no tack,
            a lift's card stays on the table in every replay (nominal_s109's pixels 3.58). Not the default: on a lift
            the gel-card friction then acts only on the bonded patch beside ``k_t`` and carries the layer law's form
            error; with the layer's normal ratio a nuisance of the fit (:data:`sysid.diagnose.tack.LAYER_RATIO_PRIOR`)
            and the split-sample test over the motion's phases (:mod:`sysid.split_sample`), nominal_s109 still reports
            the friction identified and outside its interval (0.8723, [0.755, 0.990] against the engine's 0.734;
            docs/benchmarks_log.md, session 60, 49lift2): an interval a user could not trust.
        hold_unidentified: hold a parameter whose robust 2-sigma interval reaches zero at its start value
            (:func:`sysid.fit.fit` ``hold_unidentified``; True, the default): it is reported at its start, not
            identified, with its interval, instead of where a trust-region step along a direction the data barely
            see happened to land. False: every parameter is stepped.
        profile_replays: replays on each side of each fitted parameter's profile that judge whether the recording
            identifies it (:mod:`sysid.identifiability`; default :data:`PROFILE_REPLAYS`; 0: the linearised rule,
            no replay). Every fitted parameter is judged against its prior range (:data:`sysid.calibration.
            CALIBRATION_BOUNDS` around the fit's start) either way.
        first_step: width of the fit's first trust region per search coordinate (:func:`sysid.fit.fit`
            ``first_step``; default :data:`sysid.fit.FIRST_STEP`, a factor 1.65 on a log parameter); None: the
            method's own (a factor 13.8 within the default bounds).
        fit_eps_v: fit the calibration's secant parameters (the lagged friction's stick regularisation
            ``contact.eps_v``, :mod:`sysid.calibration_secant`) with ``params``, from the calibration's value, where
            the calibration took a value other than the scene's (True, the default; its Jacobian column the replay's
            tangent, :meth:`sim_core.energies.friction.reference.LaggedFriction.eps_v_gradient`, no replay of its own),
            so that the fit's own cost decides it jointly with the materials.
            False: held at the calibration's value, which a 2-replay secant found at the start's materials and so
            carries the start into the answer (1.7 / 2.4 / 3.1 mm/s on nominal_s101 from starts 0.7 / 1.0 / 1.3 x the
            scene's materials; on this simulator's concealed-arm press-slide from 1.3 x, 14.7 mm/s against the
            recording's 10 and the gel modulus 0.835 x the truth, 0.949 x with it fitted; docs/benchmarks_log.md).
        wrench_check: judge the recorded wrench against the gel's own marker shear by window
            (:func:`sysid.wrench_check.check_wrench`) and leave the rows whose force contradicts it (it is then not the
            force ON the gel, INTERFACES.md) out of the fit and the sensor's gains, named in the report's warnings and
            fit.json ``diagnostics.wrench_check`` (True, the default; it trips on no press-slide of the reference set
            and on every lift-and-fold's carried phase, where the reference records its bonds' force with the card's
            sign; docs/benchmarks_log.md, session 54). False (``thinshell sysid --no-wrench-check``): every row fitted.
        probe_worker: make the calibration's secant probe in a second process beside its start replay, as
            ``thinshell diagnose`` does (:func:`sysid.diagnose.probe_worker.calibration_probe`: the same replays
            and values, one replay less wall time on two cores; where it applies), and there, where the gel's law is
            compared, the other law's replays with tangents beside the scene's law's (:func:`sysid.gel_law.ask_beside`:
            up to two replays with tangents less wall time); False (``thinshell sysid --workers 1`` or
            ``--one-process``): every replay in this process.
    """

    params: tuple[str, ...] = DEFAULT_PARAMETERS
    scene: str | None = None
    dt: float = 0.01
    t_max: float | None = None
    recording_map: str | None = None
    t_start: float | None = None
    t_end: float | None = None
    channels: tuple[str, ...] | None = None
    gel_resolution: tuple[int, int, int] | None = None
    gel_element: str | None = None
    arch: str = "cpu"
    jacobian: str = "auto"
    fd_step: float = 0.01
    global_method: str | None = None
    global_evals: int | None = None
    max_time: float | None = None
    max_nfev: int = 30
    stop_sigma: float | None = STOP_SIGMA
    stop_trial_sigma: float | None = STOP_TRIAL_SIGMA
    stop_rms: float | None = SYSID_STOP_RMS
    stop_robust_sigma: float | None = STOP_ROBUST_SIGMA
    stop_trial_robust: bool = True
    nuisance: tuple[tuple[str, float], ...] | None = None
    warm_start: bool = False
    sensor_calibration: bool = True
    calibration_params: tuple[str, ...] = ()
    calibration_max_time: float | None = None
    calibration_max_replays: int | None = CALIBRATION_REPLAYS
    workers: int = 1
    seed: int = 0
    batched: bool = False
    batch_size: int | str | None = None
    robust: str | None = DEFAULT_ROBUST_METHOD
    drive: bool = True
    profile_gains: bool = True
    tack: bool = False
    hold_unidentified: bool = True
    first_step: float | None = FIRST_STEP
    profile_replays: int = PROFILE_REPLAYS
    fit_eps_v: bool = True
    wrench_check: bool = True
    probe_worker: bool = True

    def __post_init__(self) -> None:
        """Validate the values that the fit would otherwise take silently.

        Raises:
            ConfigError: empty parameter list, non-positive ``dt`` / ``t_max`` / ``max_time`` /
                ``calibration_max_time`` /
                ``max_nfev`` / ``workers``, a gel resolution that is not three positive integers.
        """
        if not self.params:
            raise ConfigError("FitOptions: no parameters to fit")
        if self.first_step is not None and not self.first_step > 0:
            raise ConfigError(f"FitOptions: first_step must be > 0 (search-coordinate units), got {self.first_step}")
        for name in ("dt", "t_max", "max_time", "calibration_max_time"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise ConfigError(f"FitOptions: {name} must be > 0 s, got {value}")
        if self.calibration_max_replays is not None and int(self.calibration_max_replays) < 1:
            raise ConfigError(f"FitOptions: calibration_max_replays must be >= 1, got {self.calibration_max_replays}")
        for name in ("max_nfev", "workers"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"FitOptions: {name} must be >= 1, got {getattr(self, name)}")
        for name, prior in self.nuisance or ():
            if not (math.isfinite(float(prior)) and float(prior) > 0.0):
                raise ConfigError(f"FitOptions: nuisance prior of {name} must be a positive number, got {prior!r}")
        if self.robust is not None and self.robust not in ROBUST_METHODS:
            raise ConfigError(f"FitOptions: robust must be one of {', '.join(ROBUST_METHODS)} or None, got {self.robust!r}")
        if self.gel_resolution is not None and (len(self.gel_resolution) != 3
                                                or any(int(n) < 1 for n in self.gel_resolution)):
            raise ConfigError(f"FitOptions: gel_resolution must be three positive integers, got {self.gel_resolution}")
        if self.gel_element is not None and self.gel_element not in (*SOLID_ELEMENTS, AUTO_LAW):
            raise ConfigError(f"FitOptions: gel_element must be one of {', '.join((*SOLID_ELEMENTS, AUTO_LAW))} or None, "
                              f"got {self.gel_element!r}")

    def replace(self, **changes) -> "FitOptions":
        """A copy with ``changes`` (validated again)."""
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True)
class FitOutcome:
    """What :func:`fit_recording` produced.

    Attributes:
        result: the fit (:class:`sysid.fit.FitResult`).
        document: the ``fit.json`` document.
        out: the result directory (``fit.json``, ``report.md``, ``report.html``, plots).
        warnings: what reading the bag and building the model warned about.
        sensor: the sensor calibration (None with ``sensor_calibration=False``).
        scene: the fitted scene file written (None without ``write_scene``).
    """

    result: FitResult
    document: dict
    out: Path
    warnings: tuple[str, ...]
    sensor: CalibrationResult | None = None
    scene: Path | None = None


def nuisance_of(model: ObservationModel, options: FitOptions, layer: bool = False) -> dict[str, float]:
    """The nuisance priors of a fit: ``options.nuisance``, or :data:`sysid.fit.DEFAULT_NUISANCE` less the
    parameters the model's scene does not have (a task scene names its bodies otherwise) and the fitted ones, and
    where the model has the tack's compliant layer (``layer``) its normal ratio
    (:data:`sysid.diagnose.tack.LAYER_RATIO_PRIOR`: the layer's law is not known, and a lift's friction and bending
    take its form error).

    Raises:
        ConfigError: an explicitly named parameter the scene does not have.
    """
    if options.nuisance is not None:
        return {n: float(v) for n, v in options.nuisance if n not in options.params}
    out = {LAYER_NORMAL_RATIO_SETTING: LAYER_RATIO_PRIOR} if layer else {}
    for name, prior in DEFAULT_NUISANCE.items():
        if name in options.params:
            continue
        try:
            model.parameter_value(name)
        except ConfigError:
            continue
        out[name] = prior
    return out


def fit_recording(bag: str | Path, out: str | Path, options: FitOptions = FitOptions(), *, force: bool = False,
                  command: Sequence[str] | None = None, on_eval: Callable[[Evaluation], None] | None = None,
                  on_model: Callable[[ObservationModel, tuple[str, ...]], None] | None = None,
                  on_calibration: Callable[[CalibrationResult], None] | None = None,
                  write_scene: str | Path | None = None) -> FitOutcome:
    """Fit ``options.params`` to the recording ``bag`` and write the result directory ``out``.

    Args:
        bag: rosbag2 directory (or ``.mcap`` file) with its ``scene.yaml``.
        out: result directory, filled in a hidden sibling and renamed into place at the end.
        options: :class:`FitOptions`.
        force: replace an existing ``out``.
        command: the command line recorded in the provenance (default: this call's description).
        on_eval: called after every replay with its :class:`sysid.fit.Evaluation`.
        on_model: called with the observation model and the warnings of reading the bag before the
            fit starts (the CLI prints them).
        on_calibration: called with the sensor calibration before the fit starts.
        write_scene: also write the fitted scene (:func:`sysid.fitted_scene.fitted_scene_from_result`)
            to this YAML file, after the result directory (None: no scene file).

    Returns:
        :class:`FitOutcome`.

    Raises:
        ConfigError: ``bag`` does not exist; ``out`` or ``write_scene`` exists and not ``force``; an
            unknown parameter name; a fitted value the scene has no key for.
        ThinShellError: unreadable bag, invalid scene, failed fit (:class:`~sim_core.errors.BagReadError`,
            :class:`~sim_core.errors.CalibrationError`, ...).
    """
    bag, out = Path(bag), Path(out)
    if not bag.exists():
        raise ConfigError(f"bag not found: {bag}")
    if (out.exists() or out.is_symlink()) and not force:
        raise ConfigError(f"output directory {out} exists (use --force / force=True to replace it)")
    if write_scene is not None and Path(write_scene).exists() and not force:
        raise ConfigError(f"scene file {write_scene} exists (use --force / force=True to replace it)")
    simulation = {} if options.gel_resolution is None else {"gel_resolution": [int(n) for n in options.gel_resolution]}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        evidence = load_evidence(bag, scene_path=options.scene, include_image="auto",
                                 recording_map=options.recording_map, t_start=options.t_start, t_end=options.t_end)
        if options.gel_element not in (None, AUTO_LAW):  # auto: the scene's law calibrated, chosen at the fit's start
            simulation["gel_element"] = options.gel_element
        model = ObservationModel(evidence, scene=options.scene, dt=options.dt, t_max=options.t_max,
                                 channels=None if options.channels is None else list(options.channels),
                                 simulation=simulation or None, arch=options.arch)
    notes = tuple(str(w.message) for w in caught)
    wrench = check_wrench(model.evidence) if options.wrench_check and "wrench" in model.channels else None
    if wrench is not None and wrench.tripped:  # before the probe's fork: its replays are judged the same way
        model.row_mask = {"wrench": ~wrench.against}
    calibrated = tuple(p for p in options.calibration_params if p not in options.params)
    drive = fit_drive(model) if options.drive and model.sensor is not None else None
    if drive is not None:
        model.set_drive_stiffness(drive.replay_stiffness, drive.replay_damping)
    scene_law = (model.scene.get("simulation") or {}).get("gel_element")
    stated = None if model.sensor is None else gel_mesh(scene_dict_for(evidence, options.scene))
    tack = nominal_tack(model) if options.tack and model.sensor is not None else None
    layer_on = tack is not None and SHEAR_STIFFNESS_SETTING in (tack.params or {})
    kept = auto_not_applicable(model.sensor is not None, tack is not None and tack.on, scene_law,
                               mesh=simulation.get("gel_resolution"),
                               scene_mesh=stated) if options.gel_element == AUTO_LAW else None
    if kept is not None and model.sensor is not None:  # without one, reading the bag said so (no gel to choose for)
        notes = (*notes, f"{bag}: --gel-element auto keeps the scene's gel law ({kept})")
    if SHEAR_STIFFNESS_SETTING in options.params and not layer_on:
        raise ConfigError(f"{bag}: --params names {SHEAR_STIFFNESS_SETTING}, but the tack's compliant shear layer "
                          f"is not part of this recording's nominal model (the tack's decision: "
                          f"{'not asked: give --tack (a scene with a tactile sensor)' if tack is None else tack.why})")
    jacobian = options.jacobian
    sensor = None
    calibrating = (options.sensor_calibration or calibrated) and model.sensor is not None  # a task scene may have none
    # the calibration's secant probe forked before this process starts Taichi (reading a parameter does), through
    # the drive, to replay beside the calibration's start replay
    made: list[TangentReplay] = []  # the calibration's secant step, replayed with the fit's first tangents
    # after the calibration the same process makes the other gel law's replays with tangents (sysid.gel_law.ask_beside)
    worker = None if not (calibrating and options.probe_worker) else calibration_probe(
        model, calibrated, secant_replays=SECANT_REPLAYS, max_replays=options.calibration_max_replays,
        max_time=options.calibration_max_time)
    comparing = options.gel_element == AUTO_LAW and kept is None
    try:
        for name in (*options.params, *calibrated):  # an unknown name fails here, before the calibration's replay
            if name != SHEAR_STIFFNESS_SETTING:  # the tack's decision above sets it where the layer is on
                model.parameter_value(name)
        if on_model is not None:
            on_model(model, notes)
        if calibrating:
            sensor = calibrate(model, params=calibrated, max_time=options.calibration_max_time,
                               max_replays=options.calibration_max_replays, drive=options.drive,
                               secant_first=None if worker is None else worker.result,
                               secant_last=_secant_step_with_tangents(model, options, calibrated, made,
                                                                      worker if comparing else None))
        if sensor is not None and on_calibration is not None:
            on_calibration(sensor)
        if sensor is not None and options.profile_gains:
            model.gain_profile = GainProfile(model, sensor.gain_prior)
        # the calibration's secant values fitted with the materials, from where the calibration left them, where it
        # took them (found at the start's materials); a stage that left the scene's values leaves nothing of the start
        stage = None if sensor is None or not options.fit_eps_v else sensor.secant
        secant = stage.names if stage is not None and stage.accepted else ()
        fitted = [*options.params, *(n for n in secant if n not in options.params)]
        nuisance = nuisance_of(model, options, layer_on)
        if layer_on and SHEAR_STIFFNESS_SETTING not in fitted:  # the layer's k_t fitted with the materials (its
            fitted.append(SHEAR_STIFFNESS_SETTING)  # tangent column): held or alternated, it kept the start's (sysid.diagnose.tack)
        start = made.pop() if made else None
        law = None
        if comparing:  # the other law's replay with tangents, its fit's first
            law, model, start = choose_at_start(model, fitted, _law_extra(fitted, nuisance, options), start,
                                                gain_prior=GainPrior() if sensor is None else sensor.gain_prior,
                                                beside=worker)
    finally:
        if worker is not None:
            worker.close()
    # with the layer, the carried card's sheet points (80 % of the residuals, whitened RMS 7 at the engine's values on
    # nominal_s109: the layer's form error) would drive the materials (s109 from -30 %: modulus -64 %, -23 % weighed);
    # each channel is weighed by its gap at the fit's start (sysid.fit.fit reweight_channels); without the layer only
    # a channel the model does not follow there (whitened RMS above FOLLOWED_RMS: a lift's carried card, 82 on
    # nominal_s109, which left every step of the fit within its noise) is, the others keep their noise level
    fit_args = dict(jacobian=jacobian, global_method=options.global_method,
                    global_evals=options.global_evals, max_time=options.max_time, max_nfev=options.max_nfev,
                    fd_step=options.fd_step, workers=options.workers, seed=options.seed, on_eval=on_eval,
                    stop_sigma=options.stop_sigma, stop_trial_sigma=options.stop_trial_sigma,
                    stop_rms=options.stop_rms, warm_start=options.warm_start, batched=options.batched,
                    batch_size=options.batch_size, robust=options.robust, stop_robust_sigma=options.stop_robust_sigma,
                    stop_trial_robust=options.stop_trial_robust, hold_unidentified=options.hold_unidentified,
                    first_step=options.first_step, reweight_channels=True if layer_on else FOLLOWED_RMS,
                    profile_replays=options.profile_replays)
    # judged against what a data sheet leaves open around the fit's start (sysid.identifiability)
    prior = prior_ranges({n: model.parameter_value(n) for n in fitted}, CALIBRATION_BOUNDS)
    result = fit(model, fitted, nuisance=nuisance, made=start, prior=prior, **fit_args)
    fit_replays = [result.sim_runs]
    if law is not None:  # a law the recording does not part from the other carries its own bias into the values
        other = next((k for k in law.fitted if k != law.chosen), law.chosen)
        judged = law_verdict(result.intervals, law.chosen, other, law.decided, law.fitted)
        result.warnings.extend(not_identified_note(judged[n]) for n in judged
                               if judged[n] is not result.intervals[n] and result.intervals[n].identified)
        result.intervals = judged
    result.warnings[:0] = list(notes)
    if wrench is not None and wrench.tripped:
        result.warnings.append(wrench.message(str(bag)))
    if model.gain_profile is not None:  # the gains at the fitted values, as the fit's best replay took them
        found = model.gain_profile.calibration_of(result.prediction_final)
        model.gain_profile = None
        if found is not None:
            model.sensor_calibration = found[0]
            sensor = dataclasses.replace(sensor, sensor=found[0], prediction=dict(result.prediction_final),
                                         gain_flags=GainProfile.flags_of(found, sensor.gain_prior, model),
                                         whitened_rms_after={ch: v["whitened_rms"] for ch, v in result.rms_final.items()})
    if sensor is not None:  # a gain on its prior's bound is a model gap, not the sensor's gain
        result.warnings.extend(f["cause"] for f in (sensor.gain_flags or {}).values() if f.get("at_bound"))
    for ch, before in result.rms_initial.items():
        if ch in result.rms_final and result.rms_final[ch]["rms"] > before["rms"]:
            result.warnings.append(f"the fit does not improve channel {ch}: RMS {before['rms']:.4g} -> "
                                   f"{result.rms_final[ch]['rms']:.4g} {before['unit']} (the fitted "
                                   "parameters cannot follow it; weigh or drop it with --channels)")
    command = list(command) if command is not None else ["sysid.fit_recording", str(bag), repr(options)]
    doc = fit_document(result, provenance(evidence, options.seed, options.t_max, command, options.scene))
    if sensor is not None:
        doc["diagnostics"]["sensor_calibration"] = sensor.summary()
    if drive is not None:
        doc["diagnostics"]["drive"] = drive.summary()
    if tack is not None:
        doc["diagnostics"]["tack"] = {**tack.summary(), "fit_replays": fit_replays}
    if wrench is not None:
        doc["diagnostics"]["wrench_check"] = wrench.summary()
    doc["diagnostics"]["gel_law"] = {"element": (model.scene.get("simulation") or {}).get("gel_element",
                                                                                      SIMULATION_KEYS["gel_element"]),
                                     "requested": options.gel_element or "scene",
                                     "choice": None if law is None else law.summary(),
                                     **({} if kept is None else {"kept": kept})}
    # the fitted scene is built (and checked) before anything is written
    scene_doc = None if write_scene is None else fitted_scene_from_result(
        result, evidence, options.t_max, calibrated=None if sensor is None else sensor.params)
    with staged_directory(out, force) as staging:
        write_fit_json(staging / "fit.json", doc)
        write_report(result, doc, staging)
    scene = None if scene_doc is None else write_fitted_scene(write_scene, scene_doc, force=force)
    return FitOutcome(result, doc, out, notes, sensor, scene)


def _law_extra(fitted: Sequence[str], nuisance: Sequence[str], options: FitOptions) -> list[str]:
    """The nuisance columns a gel law's step asks beside ``fitted`` (:func:`sysid.gel_law.choose_at_start` ``extra``):
    those :func:`sysid.fit.fit` takes in its joint replays (:func:`sysid.fit.joint_nuisance`)."""
    return joint_nuisance(fitted, nuisance, robust=options.robust, warm_start=options.warm_start)


def _secant_step_with_tangents(model: ObservationModel, options: FitOptions, calibrated: Sequence[str],
                               made: list[TangentReplay], beside=None) -> Callable[[dict[str, float]], SimTrace] | None:
    """The calibration's secant step made with the tangents of the fit's first joint replay
    (:func:`sysid.calibration_secant.secant_calibration` ``last``), kept in ``made`` for :func:`sysid.fit.fit`.

    The fit starts at the start's materials and the stick speed of the stage's best replay, which is that step
    where the step improved on the probe; its first joint replay would be the same cold replay again, made for its
    tangents (10-14 % of a default fit of nominal_s101). Made from t = 0 (the stage resumes its plain replays from
    before the gel's first contact: the tangents of the materials are not zero before it). None (the stage's own
    replay) where the fit would not take it: the stick speed not fitted, warm replays, no sensitivity Jacobian.
    The columns are :func:`sysid.fit.joint_tangent_names` of the fit's parameters with the stage's; a fit that ends
    up asking for others (the stage not accepted, a tack layer's nuisance) replays as before.

    With ``beside`` (the calibration's probe process, where the gel's law is compared at the fit's start) the other
    law's start replay with tangents is asked of it before this replay (:func:`sysid.gel_law.ask_beside`), at the
    values the comparison starts from where the stage takes this step: the two replays are made side by side, and
    :func:`sysid.gel_law.choose_at_start` takes the other law's only where it is the replay it would make.
    """
    if not options.fit_eps_v or options.warm_start:
        return None
    if getattr(make_jacobian(options.jacobian, options.fd_step), "joint", None) is None:
        return None
    stage = [n for n in SECANT_PARAMETERS if n not in calibrated and n not in options.params]

    def replay(values: dict[str, float]) -> SimTrace:
        fitted, nuisance = [*options.params, *stage], nuisance_of(model, options)
        names = joint_tangent_names(fitted, nuisance, robust=options.robust, warm_start=options.warm_start)
        if beside is not None:  # the fit's start where the stage takes this step: the scene's values and this step's
            ask_beside(beside, other_law(model), model, fitted, {}, _law_extra(fitted, nuisance, options),
                       parameters={**model_parameters(model), **values})
        made.clear()
        try:
            replayed, trace = TangentReplay.make(model, values, names)
        except ConfigError:  # not differentiable (a step with dt halved): the plain replay the stage would make
            return model.simulate(values)
        made.append(replayed)
        return trace

    return replay

