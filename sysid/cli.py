"""``thinshell sysid``: fit material parameters of the simulator to a recorded bag.

Usage::

    thinshell sysid BAG [--scene S] [--params a,b,c] [--out DIR] [--force] [--global] [--max-time T]
                        [--dt DT] [--t-max SECONDS] [--recording-map FILE] [--t-start S] [--t-end S] [--jacobian auto|fd|sensitivity] [--write-scene S]
                        [--robust hac|block_bootstrap|none] [--nuisance NAME=PRIOR,...|none] [--gel-element LAW|auto|scene] [...]

Parses the options into :class:`sysid.fit_recording.FitOptions` and runs
:func:`sysid.fit_recording.fit_recording`: the bag is read into an evidence bundle, its effector
poses are replayed in the simulator, the parameters are fitted and ``fit.json``, PNG plots,
``report.md`` and ``report.html`` are written into the output directory; ``--write-scene`` also
writes the fitted scene (:mod:`sysid.fitted_scene`: the bag's scene with the fitted values, their
uncertainty and any modelled effect). The directory is filled in a hidden sibling and renamed into place at the end, so
it never holds a half-written result; an existing one is refused unless ``--force``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

from sim_core.elastic import SOLID_ELEMENTS
from sim_core.errors import ConfigError, ThinShellError
from sysid.calibration import CALIBRATION_PARAMETERS, CALIBRATION_REPLAYS
from sysid.covariance import DEFAULT_ROBUST_METHOD, ROBUST_METHODS
from sysid.fit import (DEFAULT_NUISANCE, DEFAULT_PARAMETERS, FIRST_STEP, GLOBAL_METHODS, JACOBIAN_KINDS, STOP_ROBUST_SIGMA, STOP_SIGMA, SYSID_STOP_RMS,
                       STOP_TRIAL_SIGMA)
from sysid.fit_recording import PROFILE_REPLAYS, FitOptions, available_cores, fit_recording
from sysid.gel_law import AUTO_LAW, SCENE_LAW
from sim_core.batch.sizing import batch_size_arg

PROG = "thinshell sysid"


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``thinshell sysid``."""
    p = argparse.ArgumentParser(prog=PROG, description="Fit simulator material parameters to a recorded bag.")
    p.add_argument("bag", help="rosbag2 directory (or .mcap file) with scene.yaml")
    p.add_argument("--scene", help="scene file overriding the bag's scene.yaml")
    p.add_argument("--params", default=",".join(DEFAULT_PARAMETERS),
                   help="comma-separated global parameter names (default: %(default)s)")
    p.add_argument("--out", help="output directory (default: ./sysid_<bag name>)")
    p.add_argument("--force", action="store_true", help="replace an existing output directory (and --write-scene file)")
    p.add_argument("--write-scene", metavar="SCENE_YAML",
                   help="also write the scene with the fitted values, their sigma and any modelled effect "
                        "(loadable by thinshell sim, the sim node and thinshell compare)")
    p.add_argument("--global", dest="global_search", action="store_true",
                   help="global phase (CMA-ES by default) before the local least squares")
    p.add_argument("--global-method", choices=GLOBAL_METHODS, default="cma", help="global phase method")
    p.add_argument("--global-evals", type=int, help="replay budget of the global phase")
    p.add_argument("--max-time", type=float, help="wall-time budget in s (best point so far is reported)")
    p.add_argument("--max-nfev", type=int, default=30, help="function evaluations of the local phase")
    p.add_argument("--stop-sigma", type=float, default=STOP_SIGMA,
                   help="stop once the Gauss-Newton step is below this fraction of 1-sigma in every parameter "
                        "(0: least-squares tolerances only; default: %(default)s)")
    p.add_argument("--stop-trial-sigma", type=float, default=STOP_TRIAL_SIGMA,
                   help="stop when a trial step below this many scaled 1-sigma (sigma_scaled) in every parameter "
                        "does not lower the cost (0: off; default: %(default)s)")
    p.add_argument("--stop-rms", type=float, default=SYSID_STOP_RMS,
                   help="stop when an accepted step lowered the whitened RMS by less than this fraction "
                        "(default: %(default)s = 0.001 %%; 0: off)")
    p.add_argument("--stop-robust-sigma", type=float, default=STOP_ROBUST_SIGMA,
                   help="stop once the Gauss-Newton step is below this fraction of the robust 1-sigma (--robust) in "
                        "every parameter (0: off; default: %(default)s)")
    p.add_argument("--stop-trial-scaled", action="store_true",
                   help="measure --stop-trial-sigma's trial step in the scaled 1-sigma only (default: in the larger of "
                        "it and the robust 1-sigma of --robust)")
    p.add_argument("--warm-start", action=argparse.BooleanOptionalAction, default=False,
                   help="start every replay's Newton solves from the best replay so far (default: off, each step from "
                        "the replay's own last step, so that a replay is a function of its parameters only; a warm "
                        "replay keeps the warming replay's card where it rests under static friction)")
    p.add_argument("--cold-start", dest="warm_start", action="store_false",
                   help="the default (--no-warm-start), kept for older command lines")
    p.add_argument("--dt", type=float, default=0.01, help="simulation step in s (default: %(default)s)")
    p.add_argument("--t-max", type=float, help="fit only the first T seconds of the recording")
    p.add_argument("--recording-map", metavar="FILE",
                   help="recording map of a real cell's bag: where each role comes from (TF, topics, frames, F/T "
                        "tare; docs/recording_map.md); default: recording.yaml in the bag directory, else the "
                        "INTERFACES.md topics")
    p.add_argument("--t-start", type=float, help="read the recording from T_START s after its first stamp")
    p.add_argument("--t-end", type=float, help="read the recording up to T_END s after its first stamp")
    p.add_argument("--jacobian", choices=JACOBIAN_KINDS, default="auto", help="Jacobian provider")
    p.add_argument("--fd-step", type=float, default=0.01, help="finite-difference step (log units)")
    p.add_argument("--channels", help="comma-separated channels to fit (markers_xyz, markers_uv, wrench, sheet_points)")
    p.add_argument("--arch", choices=("numpy", "cpu", "cuda"), default="cpu",
                   help="elastic terms of the replays: Taichi kernels on cpu/cuda (default: %(default)s; "
                        "same values as numpy to round-off, about 1.3x faster replays) or the NumPy reference")
    p.add_argument("--gel-resolution", help="override the gel tet resolution NX,NY,NZ (faster, coarser)")
    p.add_argument("--gel-element", choices=(*SOLID_ELEMENTS, AUTO_LAW, SCENE_LAW), default=AUTO_LAW,
                   help="the gel's element and law in every replay (default: auto; scene: the scene's, else "
                        "stable_neohookean; "
                        "green_strain: Saint Venant-Kirchhoff, whose pressed gel softens while it is sheared, "
                        "docs/known_answers.md; modified_stvk: its shear with a volumetric energy in ln J that keeps "
                        "J > 0 (no collapse in deep presses; not in auto's comparison); auto: the recording's choice "
                        "between stable_neohookean and green_strain "
                        "by delta-BIC, chosen at the fit's start after the scene's law is calibrated, each law's "
                        "modulus, friction and stick speed moved by one Levenberg-Marquardt step predicted on its "
                        "start replay's tangents, sensor gains refitted (one replay with tangents more than the scene's "
                        "law), the scene's law kept unless the other wins beyond twice the delta-BIC's spread under the "
                        "null; the scene's law where the scene has no tactile sensor, with --tack, where it names "
                        "another law, or with a --gel-resolution coarser than the scene's, whose own error outweighs "
                        "the laws' difference); fit.json diagnostics.gel_law reports it")
    p.add_argument("--seed", type=int, default=0, help="seed of the global phase")
    p.add_argument("--workers", type=int, default=available_cores(),
                   help="processes for independent replays (default: the cores this process may run on, "
                        "%(default)s here): from 2 the calibration's secant probe beside its start replay and, where "
                        "the gel's law is compared, the other law's replays with tangents beside the scene's law's "
                        "(a second process, sysid.diagnose.probe_worker), and the finite-difference columns and "
                        "global populations in a pool; 1: every replay in this process, one after the other. The "
                        "same replays and values whatever the count")
    p.add_argument("--batched", action="store_true",
                   help="replay each finite-difference Jacobian's columns and each global population together as one "
                        "batch of scene copies in this process (sim_core.batch lockstep; on --arch cuda one batched "
                        "CG; sysid.replay_batch; overrides --workers). The batch's replays start cold: with "
                        "cold replays (the default) the fit is the serial one (to 3e-9 sigma on the bundled bag)")
    p.add_argument("--batch-size", type=batch_size_arg, metavar="N|auto",
                   help="with --batched: the most copies stepped together; auto: the most that fit the free memory")
    p.add_argument("--robust", choices=(*ROBUST_METHODS, "none"), default=DEFAULT_ROBUST_METHOD,
                   help="uncertainty reported beside the Gauss-Newton sigma, valid when the model does not follow "
                        "the recording exactly (sysid.covariance): hac = Newey-West sandwich over the residuals' "
                        "time correlation, block_bootstrap = moving-block bootstrap over time windows; none: off "
                        "(default: %(default)s)")
    p.add_argument("--nuisance", metavar="NAME=PRIOR,...|none",
                   help="fixed parameters whose prior uncertainty (1-sigma: relative for positive scale parameters, "
                        "in its units for a Poisson ratio) is propagated into the robust sigma, one replay with tangents "
                        "at the optimum (default: " + ",".join(f"{k}={v:g}" for k, v in DEFAULT_NUISANCE.items())
                   + ", less names the scene lacks; none: off)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--calibrate", action="store_true",
                   help="before the fit, calibrate the model as thinshell diagnose does: the simulator parameters of "
                        "sysid.calibration.CALIBRATION_PARAMETERS not in --params (gel, friction, bending, sensor offset) "
                        "and the sensor calibration; the fit then "
                        "starts from the calibrated model")
    p.add_argument("--calibration-replays", type=int, default=CALIBRATION_REPLAYS,
                   help="replay budget of --calibrate's parameter fit (default %(default)s, as thinshell diagnose)")
    p.add_argument("--calibration-time", type=float,
                   help="also a wall-time budget of --calibrate's parameter fit, s (default: none; with one, the "
                        "calibration depends on the machine's load)")
    p.add_argument("--drive", action=argparse.BooleanOptionalAction, default=True,
                   help="fit the arm's impedance along the sensor normal (spring and damper) from the recorded command "
                        "and measured pose (ee/pose_cmd, ee/pose) and the normal load, and replay the pad through it "
                        "where the data choose it (delta-BIC over a kinematic arm > 10; the fit's Jacobian stays "
                        "analytic through the drive); kept kinematic, with the reason in fit.json, elsewhere. "
                        "Default: on, as in thinshell diagnose; --no-drive: the recorded pose driven kinematically")
    p.add_argument("--tack", action=argparse.BooleanOptionalAction, default=False,
                   help="where the recording shows the card carried up by the gel (a lift), replay the gel's tack "
                        "(adhesion bonds of four card weights a pair) released at the peel read from the recording, "
                        "kept where it follows the recorded card better than no tack, with a compliant shear layer "
                        "whose stiffness is fitted from the carried card where it follows better still (sysid.diagnose.tack; "
                        "fit.json diagnostics.tack; the recording decides: no carried row, no tack and no replay). "
                        "Default: off, a lift's card stays on the table (on nominal_s109 the fit with the tack, the "
                        "layer's ratio a nuisance and the split-sample test reports the gel-card friction identified "
                        "and outside its interval: docs/benchmarks_log.md, session 60, 49lift2)")
    p.add_argument("--wrench-check", action=argparse.BooleanOptionalAction, default=True,
                   help="judge the recorded wrench against the gel's own marker shear by 0.1 s window and leave the "
                        "rows where the force opposes it (no force ON the gel does; INTERFACES.md) out of the fit and "
                        "the sensor's gains, named in the report (sysid.wrench_check; fit.json "
                        "diagnostics.wrench_check). Default: on; --no-wrench-check: every row fitted")
    p.add_argument("--first-step", type=float, default=FIRST_STEP,
                   help="width of the fit's first trust region in every parameter's search coordinate (log units for "
                        "a positive parameter: 0.5 is a factor 1.65; default: %(default)s; 0: least_squares' own, a "
                        "factor 13.8 within the default bounds)")
    p.add_argument("--one-process", action="store_true",
                   help="make every replay in this process, one after the other, as --workers 1 (default: with "
                        "--workers 2 or more the calibration's secant probe and the other gel law's replays run in a "
                        "second process, as thinshell diagnose's probe; the same replays and values)")
    p.add_argument("--profile-replays", type=int, default=PROFILE_REPLAYS, metavar="N",
                   help="replays on each side of each fitted parameter's profile that decide whether the recording "
                        "identifies it (its cost against the null's spread within the prior range; sysid."
                        f"identifiability; default {PROFILE_REPLAYS}; 0: the linearised rule, no replay)")
    p.add_argument("--hold-unidentified", action=argparse.BooleanOptionalAction, default=True,
                   help="hold a parameter whose robust 2-sigma interval reaches zero (at the start, or at any accepted "
                        "point) at its start value: no step along a direction the data do not determine; it is "
                        "reported NOT IDENTIFIED at its start with its interval (default: on; "
                        "--no-hold-unidentified: every parameter is stepped)")
    p.add_argument("--fit-eps-v", action=argparse.BooleanOptionalAction, default=True,
                   help="fit the friction's stick regularisation contact.eps_v (calibrated on a secant at the start's "
                        "materials) with the materials, from the calibration's value, so that the start does not leak "
                        "into the answer through it (default: on; --no-fit-eps-v: held at the calibration's value)")
    p.add_argument("--fixed-gains", action="store_true",
                   help="hold the sensor gains of the calibration at the start through the fit (default: refit them, "
                        "within their prior and in closed form, to every replay, so that gains calibrated at an off "
                        "start do not bias the materials: sysid.gain_profile)")
    p.add_argument("--no-sensor-calibration", action="store_true",
                   help="fit against the scene's sensor calibration (default: the wrench gains, marker scales and "
                        "camera intrinsics are first calibrated in closed form, as thinshell diagnose does)")
    return p


def _split(text: str | None) -> list[str] | None:
    if text is None:
        return None
    return [t.strip() for t in text.split(",") if t.strip()]


def _error(message: str) -> int:
    print(f"{PROG}: error: {message}", file=sys.stderr)
    return 2


class _Progress:
    """Progress of the replays (tqdm on stderr): phase and best cost so far."""

    def __init__(self, enabled: bool) -> None:
        self.bar = None
        self.best = float("inf")
        if enabled:
            from tqdm import tqdm  # optional dependency: tqdm, for progress bars only

            self.bar = tqdm(desc="sysid replays", unit="replay", file=sys.stderr, dynamic_ncols=True)

    def __call__(self, ev) -> None:
        self.best = min(self.best, ev.cost)
        if self.bar is not None:
            self.bar.set_postfix_str(f"{ev.phase} cost {ev.cost:.4g} best {self.best:.4g}", refresh=False)
            self.bar.update(1)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def sysid_main(argv: Sequence[str] | None = None) -> int:
    """Run ``thinshell sysid`` with ``argv`` (default ``sys.argv[1:]``).

    Returns:
        0 on success; 2 for a usage error (missing bag, existing output without ``--force``, bad
        option value); 1 for a thinshell error (unreadable bag, invalid scene, failed fit), each
        reported as one line on stderr.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    bag = Path(args.bag)
    if not bag.exists():
        return _error(f"bag not found: {bag}")
    out = Path(args.out) if args.out else Path.cwd() / f"sysid_{bag.resolve().name}"
    if (out.exists() or out.is_symlink()) and not args.force:
        return _error(f"output directory {out} exists (use --force to replace it)")
    if args.write_scene and Path(args.write_scene).exists() and not args.force:
        return _error(f"scene file {args.write_scene} exists (use --force to replace it)")
    if args.t_max is not None and not args.t_max > 0:
        return _error(f"--t-max must be > 0 s, got {args.t_max}")
    if args.recording_map is not None and not Path(args.recording_map).is_file():
        return _error(f"recording map not found: {args.recording_map}")
    if args.max_time is not None and not args.max_time > 0:
        return _error(f"--max-time must be > 0 s, got {args.max_time}")
    try:
        options = fit_options(args)
    except ValueError:
        return _error(f"--gel-resolution must be three integers NX,NY,NZ, got {args.gel_resolution!r}")
    except ConfigError as err:
        return _error(str(err))
    try:
        return _run(args, argv, bag, out, options)
    except ThinShellError as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 1


def _nuisance_arg(text: str | None) -> tuple[tuple[str, float], ...] | None:
    """``--nuisance``: None (default set), () for ``none``, else ``(name, prior)`` pairs.

    Raises:
        ConfigError: an item that is not ``NAME=NUMBER``.
    """
    if text is None:
        return None
    if text.strip().lower() == "none":
        return ()
    out = []
    for item in _split(text) or []:
        name, sep, value = item.partition("=")
        try:
            out.append((name.strip(), float(value)))
        except ValueError:
            sep = ""
        if not sep or not name.strip():
            raise ConfigError(f"--nuisance: {item!r} is not NAME=PRIOR (e.g. friction.sheet_table=0.3)")
    return tuple(out)


def fit_options(args: argparse.Namespace) -> FitOptions:
    """The :class:`~sysid.fit_recording.FitOptions` of parsed ``thinshell sysid`` arguments.

    Raises:
        ValueError: ``--gel-resolution`` is not three integers.
        ConfigError: an option value :class:`~sysid.fit_recording.FitOptions` refuses.
    """
    resolution = None if not args.gel_resolution else tuple(int(v) for v in _split(args.gel_resolution))
    if resolution is not None and len(resolution) != 3:
        raise ValueError(args.gel_resolution)
    channels = _split(args.channels)
    return FitOptions(params=tuple(_split(args.params) or ()), scene=args.scene, dt=args.dt, t_max=args.t_max,
                      recording_map=args.recording_map, t_start=args.t_start, t_end=args.t_end,
                      nuisance=_nuisance_arg(args.nuisance),
                      channels=None if channels is None else tuple(channels), gel_resolution=resolution,
                      gel_element=None if args.gel_element == SCENE_LAW else args.gel_element,
                      arch=args.arch, jacobian=args.jacobian, fd_step=args.fd_step,
                      global_method=args.global_method if args.global_search else None,
                      global_evals=args.global_evals, max_time=args.max_time, max_nfev=args.max_nfev,
                      stop_sigma=args.stop_sigma or None, stop_trial_sigma=args.stop_trial_sigma or None,
                      stop_rms=args.stop_rms or None, stop_robust_sigma=args.stop_robust_sigma or None,
                      stop_trial_robust=not args.stop_trial_scaled,
                      warm_start=args.warm_start,
                      sensor_calibration=not args.no_sensor_calibration, profile_gains=not args.fixed_gains,
                      calibration_params=CALIBRATION_PARAMETERS if args.calibrate else (),
                      calibration_max_time=args.calibration_time, calibration_max_replays=args.calibration_replays,
                      workers=args.workers, seed=args.seed, batched=args.batched, batch_size=args.batch_size,
                      robust=None if args.robust == "none" else args.robust, drive=args.drive,
                      tack=args.tack, hold_unidentified=args.hold_unidentified,
                      profile_replays=args.profile_replays,
                      first_step=args.first_step or None, fit_eps_v=args.fit_eps_v, wrench_check=args.wrench_check,
                      probe_worker=not args.one_process and args.workers > 1)


def _run(args: argparse.Namespace, argv: list[str], bag: Path, out: Path, options: FitOptions) -> int:
    def announce(model, notes: tuple[str, ...]) -> None:
        for note in notes:
            print(f"{PROG}: warning: {note}", file=sys.stderr)
        print(f"{PROG}: {bag}: fitting {', '.join(options.params)} on {', '.join(model.channels)} "
              f"({model.step_count} steps of {options.dt} s, {model.residual_count} residuals)", file=sys.stderr)

    def calibrated(sensor) -> None:
        print(f"{PROG}: sensor calibration: " + ", ".join(f"{k} {v:.4g}" for k, v in sensor.sensor.as_dict().items()),
              file=sys.stderr)
        if sensor.drive is not None:
            d = sensor.drive
            print(f"{PROG}: drive: {'compliant' if d.compliant else 'kinematic'}, k_s {d.stiffness:.4g} +- "
                  f"{d.stiffness_sigma:.2g} N/m, c_d {d.damping:.4g} +- {d.damping_sigma:.2g} N s/m, delta-BIC "
                  f"{d.delta_bic:.4g}" + (f" ({d.why})" if d.why else ""), file=sys.stderr)
        for name, flag in (sensor.gain_flags or {}).items():
            if flag.get("at_bound"):
                print(f"{PROG}: warning: {flag['cause']}", file=sys.stderr)

    progress = _Progress(not args.quiet)
    try:
        outcome = fit_recording(bag, out, options, force=args.force, command=[PROG, *argv], on_eval=progress,
                                on_model=announce, on_calibration=calibrated,
                                write_scene=args.write_scene or None)
    finally:
        progress.close()
    result = outcome.result
    tack = outcome.document["diagnostics"].get("tack")
    if tack is not None:
        print(f"  tack: {'on' if tack['on'] else 'off'} ({tack['why']})")
    if outcome.scene is not None:
        print(f"fitted scene: {outcome.scene}")
    law = outcome.document["diagnostics"]["gel_law"]
    print(f"  gel law: {law['element']}" + (f" (chosen by the recording, delta-BIC {law['choice']['delta_bic']:.4g})"
                                            if law["choice"] else ""))
    print(f"  replayed at dt = {result.dt:g} s ({result.step_count} steps)")
    method = result.robust.method if result.robust is not None else None
    for name in result.names:
        s = result.sigma[name] if result.sigma else None
        sr = (result.sigma_robust or {}).get(name)
        print(f"  {name}: {result.initial[name]:.6g} -> {result.values[name]:.6g}"
              + (f" +- {s:.3g} (Gauss-Newton)" if s is not None else "")
              + (f" +- {sr:.3g} ({method})" if sr is not None else "")
              + (f" NOT IDENTIFIED (the data give [{result.intervals[name].lower:.4g}, "
                 f"{result.intervals[name].upper:.4g}] within the prior range [{result.intervals[name].prior[0]:.4g}, "
                 f"{result.intervals[name].prior[1]:.4g}])" if name in result.not_identified else "")
              + ((" (held at its start)" if result.values[name] == result.initial[name] else " (held there)")
                 if name in result.held else ""))
    for ch, before in result.rms_initial.items():
        print(f"  rms {ch}: {before['rms']:.4g} -> {result.rms_final[ch]['rms']:.4g} {before['unit']}")
    print(f"  status {result.status}, {result.iterations} iterations, {result.sim_runs} replays, "
          f"{result.wall_time_s:.1f} s")
    print(f"report: {out / 'report.html'} (also report.md, fit.json)")
    return 0


def main() -> None:
    """Console entry point (``python -m sysid.cli``)."""
    sys.exit(sysid_main())


if __name__ == "__main__":
    main()
