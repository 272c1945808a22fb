"""``thinshell diagnose BAG [BAG...]``: missing-physics diagnosis of recordings, JSON + report.

One pipeline (:mod:`sysid.diagnose.pipeline`): each recording takes the score stage or the signature stage
as its effector's drive decides; one set of options, one report, one JSON schema. An option that acts on one
stage alone says so in its help, and a report whose recording took the other stage lists it under
``extra.pipeline.not_applied``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

from sim_core.errors import ThinShellError

if TYPE_CHECKING:
    from sysid.diagnose.pipeline import PipelineOptions
    from sysid.diagnose.settings import Settings
    from sysid.diagnose.signature_engine import SignatureSettings

SCORE_ONLY = {"heldout": "--heldout", "candidates": "--candidates", "project": "--project",
              "warm_start": "--warm-start"}
"""Options of the score stage alone (argparse name -> flag)."""

SIGNATURES_ONLY = {"baseline": "--baseline", "one_process": "--one-process"}
"""Options of the signature stage alone (argparse name -> flag); ``--no-drive`` and a non-default
``--calibration-secant-replays`` too (:func:`options_from_args`)."""


def build_parser() -> argparse.ArgumentParser:
    """Argument parser of ``thinshell diagnose``."""
    from sysid.calibration import CALIBRATION_REPLAYS
    from sysid.calibration_secant import SECANT_REPLAYS
    from sim_core.batch.sizing import batch_size_arg
    from sim_core.elastic import SOLID_ELEMENTS
    from sysid.diagnose.pipeline import AUTO_LAW

    p = argparse.ArgumentParser(
        prog="thinshell diagnose",
        description="Locate and name missing physics in recordings: calibrate, detect, name, refit, validate on "
                    "held-out data. Each recording takes the score stage (score tests of the whole candidate library "
                    "against the calibrated replay) where its measured pose is its command, else the signature stage "
                    "(each effect's own signature against a calibrated null, through the fitted drive); "
                    "docs/diagnose.md.")
    p.add_argument("bags", nargs="+", help="rosbag2 directories (the first one is reported at the top level)")
    p.add_argument("--baseline", nargs="*", default=[],
                   help="recordings of the same cell declared normal: they raise the signature stage's null")
    p.add_argument("--calibration-replays", type=int, default=CALIBRATION_REPLAYS,
                   help="replay budget of the calibration's parameter fit (default %(default)s: the start only, no step; "
                        "a count, so the same answer on any machine; each Gauss-Newton step costs a trial replay and one "
                        "replay per parameter without tangents, sensor.normal_offset and contact.eps_v)")
    p.add_argument("--calibration-secant-replays", type=int, default=SECANT_REPLAYS,
                   help="replay budget of the calibration's stage for the stick regularisation contact.eps_v "
                        "(default %(default)s: a probe at a third of the scene's value, then one Gauss-Newton step on "
                        "the secant; each more replay is a Broyden-updated step; 0: none)")
    p.add_argument("--tack", action=argparse.BooleanOptionalAction, default=False,
                   help="signature stage: where the recording shows the card carried up by the gel (a lift), the "
                        "gel's tack (bonds released at the recorded peel, its compliant shear layer fitted from the "
                        "carried card) is part of the nominal model before the calibration, as in thinshell sysid "
                        "(sysid.diagnose.tack; the recording decides: no carried row, no tack and no replay). Default: off "
                        "(opt-in, as in thinshell sysid): a lift's card stays on the table")
    p.add_argument("--drive", action=argparse.BooleanOptionalAction, default=True,
                   help="signature stage: calibrate the arm's impedance along the sensor normal (spring and damper) "
                        "from the recorded command and measured pose (ee/pose_cmd, ee/pose) and the normal load, and "
                        "replay the pad through it where the data choose it (delta-BIC over a kinematic arm > 10 and "
                        "the lag explaining 0.9 of the load; gel damping is then read against a replay with the "
                        "recorded pose imposed); kept kinematic, with the reason in the report, elsewhere (this "
                        "simulator's own recordings: the pose is its command). Default: on; --no-drive: the recorded "
                        "pose driven kinematically")
    p.add_argument("--calibration-time", type=float, default=None,
                   help="also stop the calibration's parameter fit after this many seconds (default: no time budget; "
                        "with one, the answer depends on the machine's speed and load)")
    p.add_argument("--heldout", nargs="*", default=[],
                   help="score stage: held-out recordings (default: held-out time blocks; the signature stage holds "
                        "out contact events and time blocks of the recording itself)")
    p.add_argument("--json", type=Path, help="write the JSON report here")
    p.add_argument("--out", type=Path, help="report directory (report.md, report.html, PNGs)")
    p.add_argument("--force", action="store_true", help="write into a non-empty --out directory / over --json")
    p.add_argument("--workers", type=int, default=1,
                   help="processes for independent replays (score stage: the candidates' replays; signature stage: the "
                        "--baseline recordings prepared in WORKERS - 1 processes beside the recording's own)")
    p.add_argument("--batched", action="store_true",
                   help="step independent replays together as one batch of scene copies in this process "
                        "(sim_core.batch lockstep; on --arch cuda one batched CG): the score stage's rounds of "
                        "replays and, in both stages, the calibration's finite-difference columns. Replays a batch cannot "
                        "take (candidates' physics, resumed replays, a drive) run one after another "
                        "(sysid.replay_batch; overrides --workers)")
    p.add_argument("--batch-size", type=batch_size_arg, metavar="N|auto",
                   help="with --batched: the most copies stepped together; auto: the most that fit the free memory")
    p.add_argument("--one-process", action="store_true",
                   help="signature stage: make the calibration's replays one after the other in this process (default: "
                        "its secant probe runs in a second process beside its start replay; the same replays and answer)")
    p.add_argument("--ray-address", help="run the replays (signature stage: the --baseline recordings' "
                                         "preparation) as Ray tasks on this cluster")
    p.add_argument("--t-max", type=float, help="use only the first T_MAX s of each recording")
    p.add_argument("--recording-map", metavar="FILE",
                   help="recording map for every recording (a real cell's topics, TF, frames, F/T tare; "
                        "docs/recording_map.md); default: each bag's recording.yaml, else the INTERFACES.md topics")
    p.add_argument("--t-start", type=float, help="read each recording from T_START s after its first stamp")
    p.add_argument("--t-end", type=float, help="read each recording up to T_END s after its first stamp")
    p.add_argument("--dt", type=float, default=0.01, help="simulation step, s (default 0.01)")
    p.add_argument("--params", nargs="*", default=[],
                   help="simulator parameters of the calibration (default: sysid.calibration.CALIBRATION_PARAMETERS: "
                        "gel modulus and Poisson ratio, gel-sheet friction, sheet bending stiffness, sensor normal offset; "
                        "add contact.stiffness contact.eps_v for the contact's compliance, with --calibration-replays 4 or more "
                        "for a step)")
    p.add_argument("--no-calibrate", action="store_true",
                   help="diagnose against the scene values and the scene's sensor calibration (no calibration)")
    p.add_argument("--project", nargs="*", help="score stage: parameters projected out of the score tests (default: --params)")
    p.add_argument("--alpha", type=float, default=0.01, help="score stage: family-wise error rate (Holm)")
    p.add_argument("--candidates", nargs="*", help="score stage: restrict the candidate library to these effects (default: the whole library)")
    p.add_argument("--gel-resolution", type=int, nargs=3, metavar=("NX", "NY", "NZ"),
                   help="gel mesh resolution of the replays (coarser = faster; default: the scene's)")
    p.add_argument("--gel-element", choices=(*SOLID_ELEMENTS, AUTO_LAW),
                   help="the gel's element and law in the replays (default: the scene's, else stable_neohookean; "
                        "green_strain: Saint Venant-Kirchhoff, the Green-strain law whose pressed gel softens while it "
                        "is sheared, docs/known_answers.md; modified_stvk: its shear with a volumetric energy in ln J "
                        "that keeps J > 0 (no collapse in deep presses; not in auto's comparison); auto: each "
                        "recording's choice between the two laws by "
                        "delta-BIC, each law's modulus, friction and stick speed moved first by one Levenberg-Marquardt step "
                        "predicted on its start replay's tangents, sensor gains refitted (a replay with tangents a law), "
                        "the scene's law kept unless the other wins beyond twice the delta-BIC's spread under the "
                        "null; reported in "
                        "extra.pipeline.gel_law)")
    p.add_argument("--fit-max-nfev", type=int, default=8, help="function evaluations of the calibration's fit")
    p.add_argument("--arch", choices=("numpy", "cpu", "cuda"), default="cpu",
                   help="elastic terms of the replays: fused Taichi kernels on cpu/cuda (default: %(default)s; same "
                        "values as numpy to round-off) or the NumPy reference")
    p.add_argument("--warm-start", action="store_true",
                   help="score stage: start every replay's Newton solves from the nominal replay's positions (fewer iterations; "
                        "fails more often with non-convex candidates)")
    return p


def diagnose_main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns the exit status (0 ok, 2 usage / input error)."""
    from sysid.diagnose.pipeline import diagnose_recordings, top_report, write_report
    from sysid.results import staged_directory

    argv = list(sys.argv[1:] if argv is None else argv)
    if any(a == "--engine" or a.startswith("--engine=") for a in argv):
        print("thinshell diagnose: --engine is gone: one pipeline picks the score or the signature stage for each "
              "recording from its effector's drive (docs/diagnose.md); drop the option", file=sys.stderr)
        return 2
    args = build_parser().parse_args(argv)
    if args.out is not None and args.out.exists() and any(args.out.iterdir()) and not args.force:
        print(f"thinshell diagnose: output directory {args.out} is not empty (use --force)", file=sys.stderr)
        return 2
    if args.json is not None and args.json.exists() and not args.force:
        print(f"thinshell diagnose: {args.json} exists (use --force)", file=sys.stderr)
        return 2
    for flag, value in (("--calibration-replays", args.calibration_replays), ("--calibration-time", args.calibration_time)):
        if value is not None and not value > 0:
            print(f"thinshell diagnose: {flag} must be > 0, got {value}", file=sys.stderr)
            return 2
    if args.calibration_secant_replays < 0:
        print(f"thinshell diagnose: --calibration-secant-replays must be >= 0, got {args.calibration_secant_replays}",
              file=sys.stderr)
        return 2
    try:
        docs, runs = diagnose_recordings(args.bags, options_from_args(args))
    except ThinShellError as err:
        print(f"thinshell diagnose: {err}", file=sys.stderr)
        return 2
    text = json.dumps(top_report(docs), indent=2)
    if args.json is not None:
        _write_json_atomic(args.json, text)
    else:
        print(text)
    if args.out is not None:
        with staged_directory(args.out, args.force) as stage:
            write_report(docs[0], runs[0], stage)
    for doc in docs:
        print(f"{doc['bag']}: explained_by: {doc['explained_by']} ({doc['extra']['pipeline']['stage']} stage)",
              file=sys.stderr)
    return 0


def _write_json_atomic(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text + "\n")
    tmp.replace(path)


def signature_settings(args: argparse.Namespace) -> SignatureSettings:
    """The signature stage's settings of parsed ``thinshell diagnose`` arguments
    (``build_parser().parse_args([BAG])`` gives the command's defaults)."""
    from sysid.calibration import CALIBRATION_PARAMETERS
    from sysid.diagnose.signature_engine import SignatureSettings

    return SignatureSettings(
        dt=args.dt, t_max=args.t_max, recording_map=args.recording_map, t_start=args.t_start, t_end=args.t_end,
        arch=args.arch, calibrate=not args.no_calibrate,
        calibration_params=tuple(args.params) if args.params else CALIBRATION_PARAMETERS,
        calibration_max_nfev=args.fit_max_nfev, calibration_max_time=args.calibration_time,
        calibration_max_replays=args.calibration_replays, calibration_secant_replays=args.calibration_secant_replays,
        calibration_drive=args.drive, workers=max(1, args.workers), probe_worker=not args.one_process, tack=args.tack,
        batched=args.batched, batch_size=args.batch_size,
        simulation=simulation_overrides(args))


def simulation_overrides(args: argparse.Namespace) -> dict[str, Any] | None:
    """The replays' overrides of the scene's ``simulation:`` block from ``--gel-resolution`` and ``--gel-element``
    (None: neither given)."""
    out: dict[str, Any] = {}
    if args.gel_resolution is not None:
        out["gel_resolution"] = list(args.gel_resolution)
    if args.gel_element is not None:
        out["gel_element"] = args.gel_element
    return out or None


def score_settings(args: argparse.Namespace) -> Settings:
    """The score stage's settings of parsed ``thinshell diagnose`` arguments (the same calibration options)."""
    from sysid.diagnose.settings import Settings

    return Settings(dt=args.dt, t_max=args.t_max, recording_map=args.recording_map, t_start=args.t_start,
                    t_end=args.t_end, alpha=args.alpha, workers=max(1, args.workers), ray_address=args.ray_address,
                    batched=args.batched, batch_size=args.batch_size, fit_max_nfev=args.fit_max_nfev, arch=args.arch,
                    calibrate=not args.no_calibrate, calibration_max_time=args.calibration_time,
                    calibration_max_replays=args.calibration_replays, warm_start=args.warm_start,
                    simulation=simulation_overrides(args))


def options_from_args(args: argparse.Namespace) -> PipelineOptions:
    """The pipeline's options of parsed ``thinshell diagnose`` arguments, with each given option that acts on
    one stage alone (:data:`SCORE_ONLY`, :data:`SIGNATURES_ONLY`, ``--no-drive``, a non-default
    ``--calibration-secant-replays``) in :attr:`~sysid.diagnose.pipeline.PipelineOptions.given`."""
    from sysid.calibration_secant import SECANT_REPLAYS
    from sysid.diagnose.pipeline import SCORE, SIGNATURES, PipelineOptions

    given = {flag: SCORE for name, flag in SCORE_ONLY.items() if getattr(args, name)}
    given.update({flag: SIGNATURES for name, flag in SIGNATURES_ONLY.items() if getattr(args, name)})
    if not args.drive:
        given["--no-drive"] = SIGNATURES
    if args.calibration_secant_replays != SECANT_REPLAYS:
        given["--calibration-secant-replays"] = SIGNATURES
    return PipelineOptions(score=score_settings(args), signatures=signature_settings(args),
                           baseline=list(args.baseline), heldout=list(args.heldout), params=list(args.params),
                           project=args.project, candidates=args.candidates, ray_address=args.ray_address,
                           given=given)


def diagnose(bags: Sequence[str | Path], dt: float = 0.01, heldout: Sequence[str | Path] | None = None,
             **kwargs: Any) -> dict[str, Any]:
    """``python -m benchmarks.diagnose_bench``'s default engine (``sysid.diagnose.cli:diagnose``): the first
    recording's report with ``thinshell diagnose``'s defaults (``kwargs``: other command-line options by their
    ``argparse`` names, e.g. ``workers=2``).

    Raises:
        TypeError: an unknown option.
    """
    from sysid.diagnose.pipeline import diagnose_recordings

    args = build_parser().parse_args([str(b) for b in bags])
    args.dt, args.heldout = dt, [str(h) for h in (heldout or ())]
    for k, v in kwargs.items():
        if not hasattr(args, k):
            raise TypeError(f"diagnose: unknown option {k!r}")
        setattr(args, k, v)
    docs, _ = diagnose_recordings(args.bags, options_from_args(args))
    return docs[0]


if __name__ == "__main__":
    raise SystemExit(diagnose_main())
