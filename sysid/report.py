"""Fit report: PNG plots (matplotlib, Agg) plus ``report.md`` and ``report.html``.

Plots (each written only when its channel was recorded):

- ``wrench.png``: normal force F_z (and the tangential F_x, F_y) vs time, recording / nominal / fitted;
- ``markers.png``: z and u, v of a few markers (the most displaced ones) vs time;
- ``sheet_points.png``: z of the most displaced sheet points vs time;
- ``marker_field.png``: marker displacement field (x, y in the sensor frame, quiver) at peak load,
  recording vs nominal vs fitted;
- ``loss.png``: cost of every replay and the best so far, per phase.
"""

from __future__ import annotations

import html
import math
from pathlib import Path
from typing import Any, Mapping

import numpy as np

PLOT_FILES = ("wrench.png", "markers.png", "sheet_points.png", "marker_field.png", "loss.png")
COLORS = {"data": "0.45", "initial": "tab:orange", "final": "tab:blue"}


def _pyplot():
    import matplotlib  # optional heavy dependency: matplotlib, for plots only

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt  # optional heavy dependency: matplotlib, for plots only

    return plt


def _seconds(model: Any, channel: str) -> np.ndarray:
    t = model.evidence.t_ns[channel]
    return (t - model.step_times_ns[0]) * 1e-9


def _plot_series(ax, t, data, initial, final, label: str, scale: float = 1.0) -> None:
    ax.plot(t, data * scale, ".", ms=2, color=COLORS["data"], label=f"recording {label}")
    ax.plot(t, initial * scale, "-", lw=1, color=COLORS["initial"], label="nominal")
    ax.plot(t, final * scale, "-", lw=1.2, color=COLORS["final"], label="fitted")


def peak_load_index(model: Any) -> int | None:
    """Index of the markers sample nearest in time to the largest |F_z| (or the largest marker
    displacement when no wrench was recorded); None without markers."""
    ev = model.evidence
    if "markers_xyz" not in ev.channels_present:
        return None
    t_m = ev.t_ns["markers_xyz"]
    if "wrench" in ev.channels_present:
        t_peak = ev.t_ns["wrench"][int(np.argmax(np.abs(ev.wrench[:, 2])))]
        return int(np.argmin(np.abs(t_m - t_peak)))
    disp = np.linalg.norm(ev.markers_xyz - ev.markers_xyz[:1], axis=2).max(axis=1)
    return int(np.argmax(disp))


def plot_wrench(result: Any, path: Path) -> Path | None:
    """Force components vs time: recording, nominal and fitted."""
    model = result.model
    if "wrench" not in model.evidence.channels_present:
        return None
    plt = _pyplot()
    t = _seconds(model, "wrench")
    d, a, b = model.data("wrench"), result.prediction_initial["wrench"], result.prediction_final["wrench"]
    fig, axes = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
    for ax, i, name in zip(axes, (2, 0, 1), ("F_z", "F_x", "F_y")):
        _plot_series(ax, t, d[:, i], a[:, i], b[:, i], name)
        ax.set_ylabel(f"{name} (N)")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="best", fontsize=8)
    axes[-1].set_xlabel("time (s)")
    fig.suptitle("wrench on the gel (sensor frame)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_markers(result: Any, path: Path, count: int = 3) -> Path | None:
    """z (um) and u, v (px) of the ``count`` most displaced markers vs time."""
    model = result.model
    ev = model.evidence
    if "markers_xyz" not in ev.channels_present and "markers_uv" not in ev.channels_present:
        return None
    plt = _pyplot()
    channels = [c for c in ("markers_xyz", "markers_uv") if c in ev.channels_present]
    ref = model.data(channels[0])
    disp = np.linalg.norm(ref - ref[:1], axis=2).max(axis=0)
    picks = np.argsort(disp)[::-1][:count]
    rows = []
    if "markers_xyz" in channels:
        rows.append(("markers_xyz", 2, "z (um)", 1e6))
    if "markers_uv" in channels:
        rows += [("markers_uv", 0, "u (px)", 1.0), ("markers_uv", 1, "v (px)", 1.0)]
    fig, axes = plt.subplots(len(rows), len(picks), figsize=(3.2 * len(picks), 2.3 * len(rows)), squeeze=False,
                             sharex=True)
    for r, (ch, axis, label, scale) in enumerate(rows):
        t = _seconds(model, ch)
        d, a, b = model.data(ch), result.prediction_initial[ch], result.prediction_final[ch]
        for c, k in enumerate(picks):
            ax = axes[r][c]
            _plot_series(ax, t, d[:, k, axis], a[:, k, axis], b[:, k, axis], "", scale)
            ax.set_title(f"marker {k}: {label}", fontsize=9)
            ax.grid(alpha=0.3)
    axes[0][0].legend(loc="best", fontsize=7)
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_sheet_points(result: Any, path: Path, count: int = 4) -> Path | None:
    """z (mm) of the ``count`` sheet points that move most vs time."""
    model = result.model
    if "sheet_points" not in model.evidence.channels_present:
        return None
    plt = _pyplot()
    t = _seconds(model, "sheet_points")
    d, a, b = model.data("sheet_points"), result.prediction_initial["sheet_points"], result.prediction_final["sheet_points"]
    picks = np.argsort(np.abs(d[..., 2] - d[:1, :, 2]).max(axis=0))[::-1][:count]
    fig, axes = plt.subplots(1, len(picks), figsize=(3.2 * len(picks), 2.8), squeeze=False)
    for ax, k in zip(axes[0], picks):
        _plot_series(ax, t, d[:, k, 2], a[:, k, 2], b[:, k, 2], "", 1e3)
        ax.set_title(f"sheet point {k}: z (mm)", fontsize=9)
        ax.set_xlabel("time (s)")
        ax.grid(alpha=0.3)
    axes[0][0].legend(loc="best", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_marker_field(result: Any, path: Path) -> Path | None:
    """Quiver of marker displacements (x, y, from the first sample) at peak load."""
    model = result.model
    i = peak_load_index(model)
    if i is None:
        return None
    plt = _pyplot()
    d = model.data("markers_xyz")
    rest = d[0]
    fields = [("recording", d[i] - rest), ("nominal", result.prediction_initial["markers_xyz"][i] - rest),
              ("fitted", result.prediction_final["markers_xyz"][i] - rest)]
    scale = max(float(np.abs(f[:, :2]).max()) for _, f in fields) or 1e-6
    t = float(_seconds(model, "markers_xyz")[i])
    fig, axes = plt.subplots(1, 3, figsize=(12, 4), sharex=True, sharey=True)
    for ax, (name, f) in zip(axes, fields):
        q = ax.quiver(rest[:, 0] * 1e3, rest[:, 1] * 1e3, f[:, 0] * 1e6, f[:, 1] * 1e6, angles="xy",
                      scale_units="xy", scale=scale * 1e6 / 1.5, color=COLORS["data" if name == "recording" else
                                                                        "initial" if name == "nominal" else "final"])
        ax.set_title(f"{name} (t = {t:.2f} s)")
        pad = 2.0
        ax.set_xlim(rest[:, 0].min() * 1e3 - pad, rest[:, 0].max() * 1e3 + pad)
        ax.set_ylim(rest[:, 1].min() * 1e3 - pad, rest[:, 1].max() * 1e3 + pad)
        ax.set_xlabel("x (mm)")
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("y (mm)")
    axes[-1].quiverkey(q, 0.75, -0.18, scale * 1e6, f"{scale * 1e6:.0f} um", labelpos="E")
    fig.suptitle("marker displacement at peak load (sensor frame x, y)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_loss(result: Any, path: Path) -> Path:
    """Cost of every replay (by phase) and the running best."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.8))
    costs = np.array([e.cost if math.isfinite(e.cost) else np.nan for e in result.history])
    idx = np.arange(costs.shape[0])
    for phase, marker in (("initial", "s"), ("global", "^"), ("local", "o"), ("jacobian", ".")):
        sel = np.array([e.phase == phase for e in result.history], dtype=bool)
        if sel.any():
            ax.plot(idx[sel], costs[sel], marker, ms=4, ls="none", label=phase)
    best = np.fmin.accumulate(np.where(np.isfinite(costs), costs, np.inf))
    ax.plot(idx, best, "-", color="k", lw=1, label="best so far")
    if np.all(costs[np.isfinite(costs)] > 0):
        ax.set_yscale("log")
    ax.set_xlabel("replay")
    ax.set_ylabel("cost 0.5 |r|^2 (whitened)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def write_plots(result: Any, out_dir: Path) -> list[Path]:
    """All plots of :data:`PLOT_FILES` that apply; returns the files written."""
    out_dir = Path(out_dir)
    makers = (plot_wrench, plot_markers, plot_sheet_points, plot_marker_field, plot_loss)
    written = []
    for name, maker in zip(PLOT_FILES, makers):
        p = maker(result, out_dir / name)
        if p is not None:
            written.append(p)
    return written


# ------------------------------------------------------------------------------------- text
def _fmt(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def _interval(value: Any, sigma: Any) -> str:
    if value is None or sigma is None:
        return "-"
    return f"[{value - 2.0 * sigma:.4g}, {value + 2.0 * sigma:.4g}]"


def _reported_interval(p: Mapping[str, Any]) -> str:
    """The interval :mod:`sysid.identifiability` reports (the robust 2-sigma one where a document has none)."""
    iv = p.get("interval")
    if not iv:
        return _interval(p["value"], p.get("sigma_robust"))
    return f"[{iv['lower']:.4g}, {iv['upper']:.4g}]" + (" (profile)" if iv["source"] == "profile" else "")


def _verdict(p: Mapping[str, Any]) -> str:
    """``yes``, or NOT IDENTIFIED with the open sides and the prior range."""
    iv = p.get("interval")
    if p.get("identified") is None:
        return "-"
    if p["identified"]:
        return "yes"
    if not iv:
        return "NOT IDENTIFIED"
    sides = [s for s, o in (("below", iv["open_below"]), ("above", iv["open_above"])) if o]
    return (f"NOT IDENTIFIED (open {' and '.join(sides)} within the prior {iv['prior'][0]:.4g}-{iv['prior'][1]:.4g})"
            if sides else "NOT IDENTIFIED (outside the prior range)")


def robust_note(doc: Mapping[str, Any]) -> str:
    """One sentence naming the robust covariance method of a ``fit.json`` document and its lag window."""
    robust = doc["fit"].get("robust")
    if not robust:
        return "No robust covariance was computed."
    what = ("Newey-West (HAC) sandwich H^-1 S H^-1 with Bartlett weights" if robust["method"].startswith("hac")
            else f"moving-block bootstrap ({robust['resamples']} resamples) of the linearised estimate")
    text = (f"The robust 1-sigma ({robust['method']}) is the {what} over the residuals' time correlation (lag "
            f"window {robust['lag_s']:.3g} s = {robust['lag_bins']} bins of {robust['bin_s']:.3g} s, Andrews 1991)")
    prior = robust.get("nuisance_prior")
    if prior:
        text += (", plus the propagated prior uncertainty of the parameters held fixed ("
                 + ", ".join(f"{k} +-{v:g}" for k, v in prior.items()) + "; sysid.covariance.nuisance_covariance): "
                 "the part of a model error the fitted values absorb, which no residual shows")
    return (text + f"; it is {', '.join(f'{v:.3g}' for v in robust['inflation'])} times the Gauss-Newton 1-sigma. "
            "A model error beyond these (a physics the model lacks, a prior that is too narrow) is not in it.")


def _tables(doc: Mapping[str, Any]) -> list[tuple[str, list[str], list[list[str]]]]:
    params = doc["fit"]["parameters"]
    robust = doc["fit"].get("robust")
    p_rows = [[n, _fmt(p["initial"]), _fmt(p["value"]), _fmt(p["sigma"]), _fmt(p["sigma_scaled"]),
               _fmt(p.get("sigma_robust")), _reported_interval(p), _verdict(p), p["space"]]
              for n, p in params.items()]
    m = doc["metrics"]
    r_rows = []
    for ch, before in m["rms_initial"].items():
        after = m["rms_final"][ch]
        r_rows.append([ch, before["unit"], _fmt(before["rms"]), _fmt(after["rms"]), _fmt(before["whitened_rms"]),
                       _fmt(after["whitened_rms"]), "yes" if after["fitted"] else "no"])
    method = robust["method"] if robust else "robust"
    tables = [("Parameters", ["parameter", "nominal", "fitted", "1-sigma (GN)", "1-sigma x sqrt(chi2_red)",
                              f"1-sigma ({method})", "interval (2-sigma, within the prior range)", "identified",
                              "space"], p_rows),
              ("Per-channel RMS (recording - simulation)",
               ["channel", "unit", "RMS nominal", "RMS fitted", "whitened nominal", "whitened fitted", "fitted"], r_rows)]
    gains = (doc["diagnostics"].get("sensor_calibration") or {}).get("gains") or {}
    if gains:
        tables.append(("Sensor gains (within their declared prior)", ["gain", "fitted", "data asked for", "prior",
                                                                       "on a bound"],
                       [[g, _fmt(f["value"]), _fmt(f["unbounded"]), f"{f['bounds'][0]:.4g}-{f['bounds'][1]:.4g}",
                         f["at_bound"] or "no"] for g, f in gains.items()]))
    corr = doc["fit"]["correlation"]
    if corr is not None:
        names = corr["names"]
        tables.append(("Correlation", ["", *names],
                       [[n, *[_fmt(v) for v in row]] for n, row in zip(names, corr["matrix"])]))
    return tables


def _summary_lines(doc: Mapping[str, Any]) -> list[str]:
    d, m, p = doc["diagnostics"], doc["metrics"], doc["provenance"]
    return [
        f"bag: {p['bag']} (sha256 {str(p['bag_sha256'])[:12]}...)",
        f"channels fitted: {', '.join(d['channels'])}; {m['residual_count']} residuals; {d['step_count']} steps of "
        f"dt = {d['dt']} s" + (f"; first {p['t_max']} s of the recording" if p.get("t_max") else ""),
        f"status: {d['status']} ({d['message']}); {d['iterations']} iterations, {d['sim_runs']} replays "
        f"({d['sim_time_s']:.1f} s simulating), wall time {d['wall_time_s']:.1f} s, Jacobian: {d['jacobian']}",
        f"cost 0.5|r|^2: {_fmt(m['cost_initial'])} -> {_fmt(m['cost_final'])}; reduced chi^2 {_fmt(m['reduced_chi2'])}",
        f"git {p['git_revision']}{' (dirty)' if p['git_dirty'] else ''}; seed {p['seed']}",
    ] + ([_drive_line(d["drive"])] if d.get("drive") else [])


def _drive_line(drive: Mapping[str, Any]) -> str:
    """The effector drive's decision and fitted values (:meth:`sysid.drive_calibration.DriveCalibration.summary`)."""
    return (f"effector drive: {drive['decision']} (delta-BIC {_fmt(drive['delta_bic'])} against a kinematic arm, "
            f"threshold {_fmt(drive['min_delta_bic'])}); k_s {_fmt(drive['stiffness'])} +- "
            f"{_fmt(drive['stiffness_sigma'])} N/m, c_d {_fmt(drive['damping'])} +- {_fmt(drive['damping_sigma'])} "
            f"N s/m" + (f"; {drive['why']}" if drive.get("why") else ""))


def write_markdown(doc: Mapping[str, Any], plots: list[Path], path: Path) -> Path:
    """``report.md``: summary, tables, warnings and the plots (relative links)."""
    lines = ["# System identification report", ""]
    lines += [f"- {s}" for s in _summary_lines(doc)] + [""]
    for title, header, rows in _tables(doc):
        lines += [f"## {title}", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        lines += ["| " + " | ".join(r) + " |" for r in rows] + [""]
    warnings = doc["diagnostics"]["warnings"]
    if warnings:
        lines += ["## Warnings", ""] + [f"- {w}" for w in warnings] + [""]
    lines += ["## Plots", ""] + [f"![{p.stem}]({p.name})" for p in plots] + [""]
    lines += ["1-sigma (GN) is the Gauss-Newton estimate (J^T W J)^-1 with the noise levels estimated from the "
              "recording; it assumes white noise and a correct model (see the reduced chi^2). " + robust_note(doc), ""]
    path.write_text("\n".join(lines), encoding="utf-8")
    return path


def write_html(doc: Mapping[str, Any], plots: list[Path], path: Path) -> Path:
    """``report.html``: the same content as the markdown, self-contained except for the PNGs."""
    e = html.escape
    parts = ["<!DOCTYPE html><html><head><meta charset='utf-8'><title>thinshell sysid report</title>",
             "<style>body{font-family:sans-serif;max-width:1100px;margin:auto}table{border-collapse:collapse}"
             "td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}img{max-width:100%}</style></head><body>",
             "<h1>System identification report</h1><ul>"]
    parts += [f"<li>{e(s)}</li>" for s in _summary_lines(doc)] + ["</ul>"]
    for title, header, rows in _tables(doc):
        parts.append(f"<h2>{e(title)}</h2><table><tr>" + "".join(f"<th>{e(h)}</th>" for h in header) + "</tr>")
        parts += ["<tr>" + "".join(f"<td>{e(c)}</td>" for c in r) + "</tr>" for r in rows]
        parts.append("</table>")
    if doc["diagnostics"]["warnings"]:
        parts.append("<h2>Warnings</h2><ul>" + "".join(f"<li>{e(w)}</li>" for w in doc["diagnostics"]["warnings"])
                     + "</ul>")
    parts.append("<h2>Plots</h2>" + "".join(f"<p><img src='{e(p.name)}' alt='{e(p.stem)}'></p>" for p in plots))
    parts.append("</body></html>")
    path.write_text("\n".join(parts), encoding="utf-8")
    return path


def write_report(result: Any, doc: Mapping[str, Any], out_dir: str | Path) -> dict[str, Any]:
    """Plots, ``report.md`` and ``report.html`` into ``out_dir``.

    Returns:
        ``{"plots": [paths], "markdown": path, "html": path}``.
    """
    out_dir = Path(out_dir)
    plots = write_plots(result, out_dir)
    return {"plots": plots, "markdown": write_markdown(doc, plots, out_dir / "report.md"),
            "html": write_html(doc, plots, out_dir / "report.html")}
