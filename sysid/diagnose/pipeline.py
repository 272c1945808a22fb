"""The one diagnosis pipeline behind ``thinshell diagnose``: read, check the score tests' premise, detect,
name, refit, validate on held-out data, one report.

Two ways of naming a missing effect exist in this package, and each holds only where its assumptions do:

- the **score stage** (:mod:`sysid.diagnose.engine`): score tests of every candidate's replayed signature
  against the calibrated nominal replay's residual (``J_theta`` projected out), refits, held-out acceptance.
  Its tests are exact when the nominal replay reproduces the recording up to the missing effect; on this
  simulator's own recordings it names 0.93 / 0.97 of the effects at 2 / 4 noise units (0/18 false alarms),
  where the signature stage names 0.1 (docs/benchmarks_log.md, 2026-11-26, session 38, 23own4s);
- the **signature stage** (:mod:`sysid.diagnose.signature_engine`): each effect read from its own signature
  where a model-form gap matters least, against a calibrated null. On recordings of another engine, whose
  replay keeps a structured gap of several noise units after calibration, it names 7/7 with 0/2 false
  alarms; there the score stage's candidates each absorb part of the gap (on nominal_s101 it named
  ``stiction``: docs/benchmarks_log.md, 2026-11-21).

Which one runs on a recording is decided by the recording, before any replay, from the effector's drive
(:func:`sysid.drive_calibration.fit_drive`, closed form, well under a second): the score tests linearise a
replay that takes the recorded effector pose as its input. Where the measured pose is its command (the drive
stays kinematic: the lag of the pose behind its command tells nothing of the load, delta-BIC at most
:data:`~sysid.drive_calibration.DRIVE_MIN_DELTA_BIC`), that input is the recording's own and the score stage
runs. Where the data choose a compliant drive (a held arm: the pose lags its command by the load over a
spring), the replay's effector is itself a fitted model, and the signature stage runs with that drive in its
calibration. No threshold here is chosen from a recording: the drive's criterion is SYSID.md's delta-BIC
for an added term and nine tenths of the load explained (:mod:`sysid.drive_calibration`). On the nine
reference recordings delta-BIC is 2,304-4,727; on the demo's recording of this simulator -8.9
(docs/benchmarks_log.md, 2026-11-27, session 51, 51pipeline).

Every recording's report has one schema (:mod:`sysid.diagnose.schema`, :data:`SCHEMA_VERSION`): the SYSID.md
contract, ``schema_version``, and ``extra.pipeline`` with the stage that named (``"score"`` or
``"signatures"``), the premise (the drive's decision, delta-BIC and reason) and the options that did not
apply to that stage.

``--gel-element auto`` chooses the gel's law per recording before either stage (:func:`with_gel_law`,
:func:`sysid.gel_law.choose_gel_law`: each law's modulus, friction and stick speed moved from the scene's values by one
Levenberg-Marquardt step predicted on a replay's tangents, sensor gains refitted, a replay with tangents a law, the
scene's law kept unless the other's whitened sum of squares is smaller beyond twice its spread under the null); the
choice is in ``extra.pipeline.gel_law``, and both stages replay that law; where the comparison does not apply (no
tactile channel, a scene naming another law, replays on a gel mesh coarser than the scene's:
:func:`sysid.gel_law.auto_not_applicable`) the scene's law is kept and ``extra.pipeline.gel_law.kept`` says why.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Sequence

from sysid.diagnose.schema import SCHEMA_VERSION, STAGES
from sysid.diagnose.settings import Settings
from sysid.diagnose.signature_engine import SignatureSettings
from sysid.gel_law import AUTO_LAW  # ``--gel-element auto``: :func:`with_gel_law` chooses per recording

SCORE, SIGNATURES = STAGES


@dataclass
class PipelineOptions:
    """Everything ``thinshell diagnose`` takes besides the recordings and the output paths.

    Attributes:
        score: settings of the score stage (:class:`sysid.diagnose.settings.Settings`).
        signatures: settings of the signature stage (:class:`sysid.diagnose.signature_engine.SignatureSettings`).
        baseline: recordings declared normal (the signature stage's null, raised by its tests on them).
        heldout: held-out recordings of the score stage (default: held-out time blocks).
        params: simulator parameters of the calibration (empty: :data:`sysid.calibration.CALIBRATION_PARAMETERS`).
        project: parameters projected out of the score tests (None: ``params``).
        candidates: the score stage's library restricted to these effects (None: the whole library).
        ray_address: Ray cluster of the replays.
        given: option name -> the stage it acts on alone, for each such option the user gave (reported
            under ``extra.pipeline.not_applied`` where that stage did not run).
    """

    score: Settings
    signatures: SignatureSettings
    baseline: Sequence[str] = ()
    heldout: Sequence[str] = ()
    params: Sequence[str] = ()
    project: Sequence[str] | None = None
    candidates: Sequence[str] | None = None
    ray_address: str | None = None
    given: dict[str, str] = field(default_factory=dict)


@dataclass
class Premise:
    """Which stage a recording takes, and why (module docstring).

    Attributes:
        stage: ``"score"`` or ``"signatures"``.
        drive: :meth:`sysid.drive_calibration.DriveCalibration.summary` of the recording.
        why: one sentence for the report.
        wrench_check: :meth:`sysid.wrench_check.WrenchCheck.summary` of the recording (None without a wrench or
            markers), and ``wrench_note`` its warning (empty where nothing contradicts): the report names the rows
            whose recorded force opposes the gel's own marker shear. The diagnosis fits them as recorded (its
            effects are read against a null calibrated the same way); ``thinshell sysid`` leaves them out.
    """

    stage: str
    drive: dict[str, Any]
    why: str
    wrench_check: dict[str, Any] | None = None
    wrench_note: str = ""

    def as_dict(self) -> dict[str, Any]:
        return {"stage": self.stage, "drive": dict(self.drive), "why": self.why, "wrench_check": self.wrench_check}


def premise(bag: str | Path, settings: SignatureSettings) -> Premise:
    """The stage of ``bag`` from its effector's drive (module docstring); reads the recording once (as
    ``settings`` say: recording map, time span, step), no replay.

    Raises:
        BagReadError: unreadable recording.
        ConfigError: invalid scene.
    """
    from sysid.drive_calibration import fit_drive
    from sysid.evidence import load_evidence
    from sysid.observation import ObservationModel
    from sysid.wrench_check import check_wrench

    s = settings
    evidence = load_evidence(bag, include_image=False, recording_map=s.recording_map, t_start=s.t_start,
                             t_end=s.t_end)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        # NumPy terms: the drive's fit replays nothing, and a forked probe process later needs Taichi unstarted
        model = ObservationModel(evidence, dt=s.dt, t_max=s.t_max, simulation=s.simulation, arch="numpy")
    drive = fit_drive(model)
    summary = drive.summary()
    check = check_wrench(evidence)
    sensor = {} if check is None else {"wrench_check": check.summary(), "wrench_note": check.message(str(bag))}
    if drive.compliant:
        return Premise(SIGNATURES, summary,
                       f"the measured pose lags its command as a compliant drive's would (delta-BIC "
                       f"{drive.delta_bic:.0f}, the lag explains {drive.explained:.2f} of the load): the replay's "
                       "effector is a fitted model, so each effect is read from its own signature against a "
                       "calibrated null", **sensor)
    return Premise(SCORE, summary,
                   f"the measured pose is its command ({drive.why}): the replay takes the recording's own effector "
                   "motion, so the candidates' score tests against the calibrated nominal replay are exact up to "
                   "the missing effect", **sensor)


def with_gel_law(bag: str | Path, options: PipelineOptions) -> tuple[PipelineOptions, dict[str, Any] | None]:
    """``(options, report)``: where ``options`` ask for the gel law :data:`AUTO_LAW`, the options with the law the
    recording chooses (:func:`sysid.gel_law.choose_gel_law`, read as the signature stage's settings say) in both
    stages' ``simulation`` and the choice's summary (:meth:`sysid.gel_law.GelLawChoice.summary`), or, where the
    comparison does not apply (:func:`sysid.gel_law.auto_not_applicable`: no tactile channel, a scene naming another
    law, a ``gel_resolution`` coarser than the scene's), the scene's law and ``{"kept": reason}``; else ``options``
    unchanged and None.

    Raises:
        BagReadError: unreadable recording.
        ConfigError: invalid scene.
    """
    from sysid.evidence import load_evidence
    from sysid.gel_law import TACTILE, auto_not_applicable, choose_gel_law, gel_mesh
    from sysid.observation import scene_dict_for

    s = options.signatures
    simulation = dict(s.simulation or {})
    if simulation.get("gel_element") != AUTO_LAW:
        return options, None
    del simulation["gel_element"]
    evidence = load_evidence(bag, include_image="auto", recording_map=s.recording_map, t_start=s.t_start,
                             t_end=s.t_end)
    scene = scene_dict_for(evidence)
    kept = auto_not_applicable(any(ch in evidence.channels_present for ch in TACTILE), False,
                               (scene.get("simulation") or {}).get("gel_element"),
                               mesh=simulation.get("gel_resolution"), scene_mesh=gel_mesh(scene))
    if kept is not None:
        chosen, report = simulation or None, {"kept": kept}
    else:
        choice = choose_gel_law(evidence, dt=s.dt, t_max=s.t_max, arch=s.arch, simulation=simulation)
        chosen, report = {**simulation, "gel_element": choice.chosen}, choice.summary()
    return replace(options, signatures=replace(s, simulation=chosen),
                   score=replace(options.score, simulation=chosen)), report


def _stamp(doc: dict[str, Any], prem: Premise, options: PipelineOptions, wall_s: float) -> dict[str, Any]:
    """``doc`` with the pipeline's keys of the schema (module docstring)."""
    other = SIGNATURES if prem.stage == SCORE else SCORE
    not_applied = sorted(flag for flag, stage in options.given.items() if stage == other)
    extra = dict(doc.get("extra") or {})
    extra.pop("engine", None)
    extra["pipeline"] = {**prem.as_dict(), "not_applied": not_applied, "wall_time_s": wall_s}
    if not_applied:
        extra["notes"] = list(extra.get("notes") or []) + [
            f"{', '.join(not_applied)}: act on the {other} stage, which did not run on this recording"]
    if prem.wrench_note:
        extra["notes"] = list(extra.get("notes") or []) + [prem.wrench_note]
    out = {"schema_version": SCHEMA_VERSION, **{k: v for k, v in doc.items() if k not in ("extra", "schema_version")}}
    out["extra"] = extra
    return out


def diagnose_recordings(bags: Sequence[str | Path], options: PipelineOptions) -> tuple[list[dict[str, Any]], list[Any]]:
    """Diagnose each recording with the stage its premise picks (module docstring).

    Args:
        bags: recordings, each diagnosed on its own.
        options: :class:`PipelineOptions`.

    Returns:
        ``(reports, runs)``: one validated report per recording, and the stage's run behind it (a
        :class:`sysid.diagnose.engine.BagDiagnosis` or a :class:`sysid.diagnose.signature_engine.Prepared`),
        which the report writer plots.

    Raises:
        BagReadError, CalibrationError, ConfigError: unreadable recording, a replay that cannot start, a bad
        scene, or a report that breaks the schema.
    """
    from sysid.diagnose.engine import run_diagnosis
    from sysid.diagnose.prepare_pool import prepare_with_baselines
    from sysid.diagnose.schema import validate_report
    from sysid.diagnose.signature_engine import diagnose_one

    laws = [with_gel_law(b, options) for b in bags]
    premises = [premise(b, law_options.signatures) for b, (law_options, _) in zip(bags, laws)]
    docs: list[dict[str, Any]] = []
    runs: list[Any] = []
    baselines = None
    for bag, prem, (opts, law) in zip(bags, premises, laws):
        t0 = time.monotonic()
        if prem.stage == SCORE:
            doc, (run,) = run_diagnosis([bag], opts.heldout, opts.params, opts.score, opts.project,
                                        opts.candidates)
        else:
            first = None
            if baselines is None:
                first, baselines = prepare_with_baselines(bag, opts.baseline, opts.signatures,
                                                          opts.signatures.workers, opts.ray_address)
            doc, run = diagnose_one(bag, settings=opts.signatures, baseline_prepared=baselines, prepared=first)
        doc = _stamp(doc, prem, opts, time.monotonic() - t0)
        if law is not None:
            doc["extra"]["pipeline"]["gel_law"] = law
        validate_report(doc)
        docs.append(doc)
        runs.append(run)
    return docs, runs


def top_report(docs: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The JSON ``thinshell diagnose`` writes: the first recording's report, the others under ``extra.others``."""
    top = dict(docs[0])
    if len(docs) > 1:
        top["extra"] = dict(top["extra"], others=list(docs[1:]))
    return top


def with_stage(doc: dict[str, Any]) -> str:
    """The stage that made a report (``extra.pipeline.stage``)."""
    return str(doc["extra"]["pipeline"]["stage"])


def write_report(doc: dict[str, Any], run: Any, out_dir: str | Path) -> list[Path]:
    """``report.md``, ``report.html``, ``diagnosis.json`` and the plots of one report into ``out_dir``: the
    pipeline's section, then the stage's own (:func:`sysid.diagnose.report.write_report`: residuals before and
    after the refit; :func:`sysid.diagnose.signature_report.write_signature_report`: the calibration and each
    named effect's signature).

    Returns:
        written paths.
    """
    from sysid.diagnose.report import write_report as write_score_report
    from sysid.diagnose.signature_report import write_signature_report

    if with_stage(doc) == SCORE:
        return write_score_report(doc, run, out_dir)
    return write_signature_report(doc, run, out_dir)


__all__ = ["PipelineOptions", "Premise", "SCHEMA_VERSION", "STAGES", "diagnose_recordings", "premise",
           "top_report", "with_stage", "write_report"]
