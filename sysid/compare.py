"""``thinshell compare``: how well scenes predict a recording (real-to-sim replay of its own motion).

Usage::

    thinshell compare BAG --scene S [--scene-nominal S0] [--label NAME] --out DIR [--force] [--t-max T] [--dt DT]
                          [--arch cpu|numpy] [--gel-resolution NX,NY,NZ] [--task TASK]

Every scene replays the recording's effector motion (the recorded effector poses, kinematically, as
the fitter does: :class:`sysid.observation.ObservationModel` at its values) and predicts every channel
the recording holds (markers ``xyz`` and pixels, wrench, sheet points). For each channel and scene the
report gives the RMS of recording minus prediction (SI units; the wrench over the forces, N) and the
whitened RMS (in units of the recording's noise level, comparable across channels). ``--scene`` is the
scene under test (e.g. ``thinshell sysid --write-scene``'s fitted scene); the nominal one is
``--scene-nominal`` or, by default, the bag's own ``scene.yaml``. A fitted scene's sensor calibration
(``fitted.sensor_calibration``, :mod:`sysid.fitted_scene`) is applied to its predictions, as the fit did.

Outputs in ``DIR`` (filled in a hidden sibling and renamed into place; an existing ``DIR`` is refused
without ``--force``): ``compare.json`` (``rms``: scene -> channel -> entry, ``better``: channel ->
scene with the lower whitened RMS, provenance), ``wrench.png``, ``markers.png``, ``sheet_points.png``
(overlays of the recording and every scene's prediction), ``report.md`` and ``report.html``.

``--task TASK`` (a task-scene recording, e.g. a deployed ``thinshell optimise`` trajectory): the task's
reward achieved on the recording and predicted by every scene, each measured on the sheet points at
the end of the commanded motion (:mod:`sysid.task_reward`), in ``compare.json`` (``reward``) and the
report.
"""

from __future__ import annotations

import argparse
import dataclasses
import html
import json
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from sim_core.errors import ConfigError, ThinShellError
from sysid.evidence import load_evidence
from sysid.fitted_scene import sensor_calibration_of
from sysid.observation import ObservationModel
from sysid.results import staged_directory
from sysid.task_reward import TaskRewardProbe, reward_sample_index

PROG = "thinshell compare"
COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red")
PLOTS = ("wrench.png", "markers.png", "sheet_points.png")


@dataclass
class Comparison:
    """Predictions of one recording by several scenes.

    Attributes:
        bag: the recording.
        labels: scene labels in order (``scene``, ``nominal``).
        scenes: label -> scene file (None: the bag's scene.yaml).
        models: label -> the observation model (its ``evidence`` is the cropped recording).
        predictions: label -> channel -> prediction shaped like the recording's channel.
        rms: label -> channel -> ``ObservationModel.channel_rms`` entry.
        wall_time_s: label -> replay wall time, s.
        replay: label -> how the replay's steps ended (``StepTotals`` as a dict: steps, substep
            retries, relaxed acceptances).
        reward: with a task, ``{"task", "unit", "t_s", "recording", "predicted": {label: value}}``
            (:func:`task_rewards`), else None.
    """

    bag: Path
    labels: list[str]
    scenes: dict[str, str | None]
    models: dict[str, Any]
    predictions: dict[str, dict[str, np.ndarray]]
    rms: dict[str, dict[str, dict[str, Any]]]
    wall_time_s: dict[str, float]
    replay: dict[str, dict[str, Any]] = field(default_factory=dict)
    reward: dict[str, Any] | None = None

    def better(self) -> dict[str, str]:
        """Channel -> label of the scene with the lowest whitened RMS (``tie`` when equal to 1e-9)."""
        out = {}
        for ch in self.rms[self.labels[0]]:
            values = {lab: self.rms[lab][ch]["whitened_rms"] for lab in self.labels}
            best = min(values, key=values.get)
            ties = [lab for lab, v in values.items() if abs(v - values[best]) <= 1e-9 * max(abs(values[best]), 1e-300)]
            out[ch] = "tie" if len(ties) > 1 else best
        return out


def compare_recording(bag: str | Path, scenes: Sequence[tuple[str, str | Path | None]], *, dt: float = 0.01,
                      t_max: float | None = None, arch: str = "cpu",
                      simulation: dict | None = None, task: str | None = None,
                      horizon: int | None = None, recording_map: str | Path | None = None,
                      t_start: float | None = None, t_end: float | None = None) -> Comparison:
    """Replay ``bag``'s motion in every scene and compare the predictions with the recording.

    Args:
        bag: rosbag2 directory or ``.mcap`` file.
        scenes: ``(label, scene file)``; a None file is the bag's ``scene.yaml``.
        dt: replay step, s. t_max: use only the first ``t_max`` s. arch: ``numpy`` | ``cpu`` | ``cuda``.
        simulation: overrides of every scene's ``simulation:`` block (e.g. a coarser ``gel_resolution``).
        task: a task name or file: also the task's reward achieved and predicted (:func:`task_rewards`).
        horizon: the task at this many steps (``thinshell optimise --horizon``; None: the task's).
        recording_map: recording map of a real cell's bag (docs/recording_map.md); None: the bag's
            ``recording.yaml``, else the INTERFACES.md topics.
        t_start, t_end: read only the samples from ``t_start`` to ``t_end`` s after the first stamp.

    Raises:
        BagReadError: unreadable bag. ConfigError: invalid scene, or a task whose reward cannot be
            measured on the recording. CalibrationError: nothing to compare.
        SimulationDivergedError: a replay failed (names the step).
    """
    evidence = load_evidence(bag, include_image="auto", recording_map=recording_map, t_start=t_start, t_end=t_end)
    out = Comparison(Path(bag), [], {}, {}, {}, {}, {})
    for label, scene in scenes:
        model = ObservationModel(evidence, scene=scene, dt=dt, t_max=t_max, simulation=simulation, arch=arch)
        t0 = time.perf_counter()
        trace = model.simulate({})
        calibration = sensor_calibration_of(model.scene)
        if calibration is not None:  # a fitted scene's sensor calibration (thinshell sysid --write-scene)
            raw = model.predict_raw(trace)
            model.marker_rest = np.asarray(raw["markers_xyz"][0], dtype=float) if "markers_xyz" in raw else None
            model.sensor_calibration = calibration
        prediction = model.predict(trace)
        out.wall_time_s[label] = time.perf_counter() - t0
        out.labels.append(label)
        out.scenes[label] = None if scene is None else str(scene)
        out.models[label] = model
        out.predictions[label] = prediction
        out.rms[label] = model.channel_rms(prediction)
        if trace.step_totals is not None:
            out.replay[label] = dataclasses.asdict(trace.step_totals)
    if task is not None:
        out.reward = task_rewards(out, task, horizon)
    return out


def task_rewards(cmp: Comparison, task: str, horizon: int | None = None) -> dict[str, Any]:
    """The task's reward on the recording's sheet points and on every scene's prediction of them, at the
    end of the commanded motion (:mod:`sysid.task_reward`).

    Raises:
        ConfigError: no sheet points, a reward that reads more than them, or no sample after the motion.
    """
    from sim_core.optim.tasks import task_at_horizon

    spec = task_at_horizon(task, horizon)
    model = cmp.models[cmp.labels[0]]
    if "sheet_points" not in cmp.predictions[cmp.labels[0]]:
        raise ConfigError(f"{cmp.bag}: no sheet/points recorded; task {spec.name}'s reward cannot be measured")
    probe = TaskRewardProbe(spec)
    t_ns = model.evidence.t_ns["sheet_points"]
    k = reward_sample_index(model.evidence, t_ns)
    return {"task": spec.name, "unit": spec.reward_units, "t_s": float((t_ns[k] - model.step_times_ns[0]) * 1e-9),
            "recording": probe(model.data("sheet_points")[k]),
            "predicted": {lab: probe(cmp.predictions[lab]["sheet_points"][k]) for lab in cmp.labels},
            "success_score": spec.success_score, "human_score": spec.human_score}


# ----------------------------------------------------------------------------------- plots
def _pyplot():
    import matplotlib  # optional dependency: matplotlib, for plots only

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt  # optional dependency: matplotlib, for plots only

    return plt


def _overlay(ax, t, data, preds: dict[str, np.ndarray], scale: float) -> None:
    ax.plot(t, data * scale, ".", ms=2, color="0.45", label="recording")
    for (label, p), color in zip(preds.items(), COLORS):
        ax.plot(t, p * scale, "-", lw=1.1, color=color, label=label)
    ax.grid(alpha=0.3)


def write_plots(cmp: Comparison, out_dir: Path) -> list[Path]:
    """Overlay plots of the recording and every scene's prediction (wrench, markers, sheet points)."""
    plt = _pyplot()
    model = cmp.models[cmp.labels[0]]
    ev = model.evidence
    written = []

    def seconds(ch: str) -> np.ndarray:
        return (ev.t_ns[ch] - model.step_times_ns[0]) * 1e-9

    if "wrench" in cmp.predictions[cmp.labels[0]]:
        fig, axes = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
        for ax, i, name in zip(axes, (2, 0, 1), ("F_z", "F_x", "F_y")):
            _overlay(ax, seconds("wrench"), model.data("wrench")[:, i],
                     {lab: cmp.predictions[lab]["wrench"][:, i] for lab in cmp.labels}, 1.0)
            ax.set_ylabel(f"{name} (N)")
        axes[0].legend(fontsize=8)
        axes[-1].set_xlabel("time (s)")
        fig.suptitle("wrench on the gel (sensor frame)")
        written.append(_save(plt, fig, out_dir / "wrench.png"))
    mch = [c for c in ("markers_xyz", "markers_uv") if c in cmp.predictions[cmp.labels[0]]]
    if mch:
        ref = model.data(mch[0])
        picks = np.argsort(np.linalg.norm(ref - ref[:1], axis=2).max(axis=0))[::-1][:3]
        rows = ([("markers_xyz", 2, "z (um)", 1e6)] if "markers_xyz" in mch else []) + \
               ([("markers_uv", 0, "u (px)", 1.0), ("markers_uv", 1, "v (px)", 1.0)] if "markers_uv" in mch else [])
        fig, axes = plt.subplots(len(rows), len(picks), figsize=(3.2 * len(picks), 2.3 * len(rows)), squeeze=False)
        for r, (ch, axis, name, scale) in enumerate(rows):
            for c, k in enumerate(picks):
                _overlay(axes[r][c], seconds(ch), model.data(ch)[:, k, axis],
                         {lab: cmp.predictions[lab][ch][:, k, axis] for lab in cmp.labels}, scale)
                axes[r][c].set_title(f"marker {k}: {name}", fontsize=9)
        axes[0][0].legend(fontsize=7)
        written.append(_save(plt, fig, out_dir / "markers.png"))
    if "sheet_points" in cmp.predictions[cmp.labels[0]]:
        d = model.data("sheet_points")
        picks = np.argsort(np.abs(d[..., 2] - d[:1, :, 2]).max(axis=0))[::-1][:4]
        fig, axes = plt.subplots(1, len(picks), figsize=(3.2 * len(picks), 2.8), squeeze=False)
        for ax, k in zip(axes[0], picks):
            _overlay(ax, seconds("sheet_points"), d[:, k, 2],
                     {lab: cmp.predictions[lab]["sheet_points"][:, k, 2] for lab in cmp.labels}, 1e3)
            ax.set_title(f"sheet point {k}: z (mm)", fontsize=9)
            ax.set_xlabel("time (s)")
        axes[0][0].legend(fontsize=7)
        written.append(_save(plt, fig, out_dir / "sheet_points.png"))
    return written


def _save(plt, fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


# ----------------------------------------------------------------------------------- report
def comparison_document(cmp: Comparison, argv: Sequence[str], dt: float, t_max: float | None) -> dict[str, Any]:
    """The ``compare.json`` document."""
    ev = cmp.models[cmp.labels[0]].evidence
    return {"schema": "thinshell-compare/1", "bag": str(ev.source.bag_path), "bag_sha256": ev.source.sha256,
            "scenes": cmp.scenes, "dt": dt, "t_max": t_max, "rms": cmp.rms, "better": cmp.better(),
            "wall_time_s": cmp.wall_time_s, "replay": cmp.replay, "reward": cmp.reward, "command": [PROG, *argv]}


def _table(doc: dict[str, Any]) -> tuple[list[str], list[list[str]]]:
    labels = list(doc["scenes"])
    header = ["channel", "unit", *(f"RMS {lab}" for lab in labels), *(f"whitened {lab}" for lab in labels), "better"]
    rows = []
    for ch in doc["rms"][labels[0]]:
        rms = [doc["rms"][lab][ch] for lab in labels]
        rows.append([ch, rms[0]["unit"], *(f"{r['rms']:.4g}" for r in rms), *(f"{r['whitened_rms']:.4g}" for r in rms),
                     doc["better"][ch]])
    return header, rows


def _summary(doc: dict[str, Any]) -> list[str]:
    labels = list(doc["scenes"])
    lines = [f"recording: {doc['bag']} (sha256 {doc['bag_sha256'][:12]}), replay dt {doc['dt']} s"
             + (f", first {doc['t_max']} s" if doc["t_max"] else "")]
    lines += [f"scene {lab}: {doc['scenes'][lab] or 'the bag scene.yaml'}" for lab in labels]
    if len(labels) > 1:
        wins = sum(1 for lab in doc["better"].values() if lab == labels[0])
        lines.append(f"{labels[0]} predicts the recording better than {', '.join(labels[1:])} on {wins} of "
                     f"{len(doc['better'])} channels (whitened RMS)")
    reward = doc.get("reward")
    if reward:
        lines.append(f"task {reward['task']}: reward achieved on the recording {reward['recording']:.6g} {reward['unit']} "
                     f"(at t = {reward['t_s']:.4f} s, the end of the commanded motion); predicted "
                     + ", ".join(f"{lab} {v:.6g}" for lab, v in reward["predicted"].items())
                     + (f"; Table A success score {reward['success_score']:.6g}" if reward.get("success_score") is not None
                        else ""))
    return lines


def write_report(doc: dict[str, Any], plots: list[Path], out_dir: Path) -> None:
    """``report.md`` and ``report.html`` (same content; plots linked relatively)."""
    header, rows = _table(doc)
    md = ["# Recording vs simulation", ""] + [f"- {s}" for s in _summary(doc)] + ["", "## RMS per channel", "",
                                                                                 "| " + " | ".join(header) + " |",
                                                                                 "|" + "---|" * len(header)]
    md += ["| " + " | ".join(r) + " |" for r in rows]
    md += ["", "Whitened RMS: in units of the recording's noise level per axis (1 = as good as the noise allows).",
           "", "## Plots", ""] + [f"![{p.stem}]({p.name})" for p in plots] + [""]
    (out_dir / "report.md").write_text("\n".join(md), encoding="utf-8")
    e = html.escape
    parts = ["<!DOCTYPE html><html><head><meta charset='utf-8'><title>thinshell compare</title><style>"
             "body{font-family:sans-serif;max-width:1100px;margin:auto}table{border-collapse:collapse}"
             "td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}img{max-width:100%}</style></head><body>",
             "<h1>Recording vs simulation</h1><ul>" + "".join(f"<li>{e(s)}</li>" for s in _summary(doc)) + "</ul>",
             "<h2>RMS per channel</h2><table><tr>" + "".join(f"<th>{e(h)}</th>" for h in header) + "</tr>"]
    parts += ["<tr>" + "".join(f"<td>{e(c)}</td>" for c in r) + "</tr>" for r in rows]
    parts += ["</table><h2>Plots</h2>" + "".join(f"<p><img src='{e(p.name)}' alt='{e(p.stem)}'></p>" for p in plots),
              "</body></html>"]
    (out_dir / "report.html").write_text("\n".join(parts), encoding="utf-8")


# ----------------------------------------------------------------------------------- CLI
def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``thinshell compare``."""
    p = argparse.ArgumentParser(prog=PROG, description="Replay a recording's motion in scene(s) and compare the "
                                                       "predictions with the recording (RMS per channel, plots, report).")
    p.add_argument("bag", help="rosbag2 directory (or .mcap file)")
    p.add_argument("--scene", required=True, help="scene under test (e.g. the fitted scene of thinshell sysid --write-scene)")
    p.add_argument("--scene-nominal", help="nominal scene (default: the bag's scene.yaml)")
    p.add_argument("--label", default="scene", help="name of --scene in the report (e.g. fitted; default: %(default)s)")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--force", action="store_true", help="replace an existing output directory")
    p.add_argument("--dt", type=float, default=0.01, help="replay step in s (default: %(default)s)")
    p.add_argument("--t-max", type=float, help="compare only the first T seconds")
    p.add_argument("--recording-map", metavar="FILE",
                   help="recording map of a real cell's bag (docs/recording_map.md); default: recording.yaml in the "
                        "bag directory, else the INTERFACES.md topics")
    p.add_argument("--t-start", type=float, help="read the recording from T_START s after its first stamp")
    p.add_argument("--t-end", type=float, help="read the recording up to T_END s after its first stamp")
    p.add_argument("--arch", choices=("numpy", "cpu", "cuda"), default="cpu", help="elastic terms of the replays")
    p.add_argument("--gel-resolution", help="override the gel tet resolution NX,NY,NZ of every scene")
    p.add_argument("--task", help="task name or file: also its reward achieved on the recording and predicted by every "
                                  "scene (a task-scene recording)")
    p.add_argument("--horizon", type=int, help="with --task: the task at H steps (as thinshell optimise --horizon)")
    return p


def compare_main(argv: Sequence[str] | None = None) -> int:
    """Run ``thinshell compare``; 0 on success, 2 for a usage error, 1 for a thinshell error (one line)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    out = Path(args.out)
    if (out.exists() or out.is_symlink()) and not args.force:
        print(f"{PROG}: error: output directory {out} exists (use --force to replace it)", file=sys.stderr)
        return 2
    for path in (args.bag, args.scene, args.scene_nominal, args.recording_map):
        if path is not None and not Path(path).exists():
            print(f"{PROG}: error: not found: {path}", file=sys.stderr)
            return 2
    simulation = None
    if args.gel_resolution:
        try:
            simulation = {"gel_resolution": [int(v) for v in args.gel_resolution.split(",")]}
        except ValueError:
            print(f"{PROG}: error: --gel-resolution must be NX,NY,NZ, got {args.gel_resolution!r}", file=sys.stderr)
            return 2
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            if args.label == "nominal":
                raise ThinShellError("--label must differ from 'nominal'")
            cmp = compare_recording(args.bag, [(args.label, args.scene), ("nominal", args.scene_nominal)], dt=args.dt,
                                    t_max=args.t_max, arch=args.arch, simulation=simulation, task=args.task,
                                    horizon=args.horizon, recording_map=args.recording_map,
                                    t_start=args.t_start, t_end=args.t_end)
        for w in caught:
            print(f"{PROG}: warning: {w.message}", file=sys.stderr)
        doc = comparison_document(cmp, argv, args.dt, args.t_max)
        with staged_directory(out, args.force) as staging:
            (staging / "compare.json").write_text(json.dumps(doc, indent=2), encoding="utf-8")
            write_report(doc, write_plots(cmp, staging), staging)
    except ThinShellError as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 1
    header, rows = _table(doc)
    for line in _summary(doc):
        print(line)
    for r in rows:
        print("  " + ", ".join(f"{h} {c}" for h, c in zip(header, r)))
    for label, totals in doc["replay"].items():
        print(f"  replay {label}: {totals['steps']} steps to the end, {totals['retries']} substep retries "
              f"({totals['retried_steps']} steps retried), {totals['relaxed_steps']} accepted at a relaxed tolerance")
    print(f"report: {out / 'report.html'} (also report.md, compare.json)")
    return 0
