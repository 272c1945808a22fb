"""Report of the signature diagnosis: ``report.md``, ``report.html``, ``diagnosis.json`` and plots.

The plots show, for each named effect, where it was found (its windows shaded) and the recording
against the calibrated replay before and after the effect's refit on the channel it acts on; and
the baseline's whitened RMS per channel before and after calibration.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from sysid.diagnose.report import pipeline_lines, write_report_files
from sysid.diagnose.signatures.damping import contact_force, lead_recording
from sysid.diagnose.signatures.friction import breakaways, decay_columns, decay_taus, fit_breakaway, shear_breakaway
from sysid.diagnose.signatures.sensor import apply_force_bias, apply_lens
from sysid.diagnose.signatures.timing import delayed, first_order, timing_signal


def _plot_effect(doc: Mapping[str, Any], prepared: Any, effect: str, out: Path) -> Path | None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rec = prepared.recording
    sig = doc["extra"]["signatures"][effect]
    fit = doc["refit"]["effects"].get(effect, {})
    params = fit.get("params", {})
    term = getattr(prepared, "refit_predictions", {}).get(effect, {}).get("sheet_points")
    if term is not None:
        fig, (ax, ax_res) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    else:
        fig, ax = plt.subplots(figsize=(9, 3.6))
    if effect in ("latency", "gel_viscoelasticity", "damping"):
        kinematic = effect == "damping" and rec.reference is not None
        channel, t, y, yp, _ = timing_signal(lead_recording(rec) if effect == "damping" else rec)
        if effect == "gel_viscoelasticity":
            after = first_order(t, yp, params.get("tau_s", 0.0), params.get("fraction", 0.0))
        elif effect == "damping":
            replayed = getattr(prepared, "refit_predictions", {}).get(effect, {}).get("timing_signal")
            after = contact_force(t, yp, params.get("tau_s", 0.0)) if replayed is None else replayed
        else:
            after = delayed(t, yp, params.get("latency_s", 0.0))
        ax.plot(t, y, "k.", ms=2, label="recorded")
        ax.plot(t, yp, "C0-", lw=1, label="calibrated replay" + (", recorded pose imposed" if kinematic else ""))
        ax.plot(t, after, "C3-", lw=1, label=f"replay with {effect}")
        ax.set_ylabel("normal force, N" if channel == "wrench" else "mean marker depth, m")
    elif effect == "force_bias":
        t = rec.t["wrench"]
        w = rec.data["wrench"]
        wp = prepared.prediction.get("wrench", np.zeros_like(w))  # no replay: the free gel's zero
        ax.plot(t, w[:, 2], "k.", ms=2, label="recorded F_z")
        ax.plot(t, wp[:, 2], "C0-", lw=1, label="calibrated replay F_z")
        ax.plot(t, apply_force_bias(wp, t, params)[:, 2], "C3-", lw=1, label="replay + bias")
        ax.set_ylabel("F_z (sensor frame), N")
    elif effect == "stiction":
        for i, b0 in enumerate(breakaways(rec)):
            b = shear_breakaway(rec, b0)
            if b is None:
                continue
            f = fit_breakaway(b, decay_taus(rec))
            cols = decay_columns(b.t, b.t0, f["tau_s"])
            c0, c1 = f["coef0"], f["coef1"]
            ax.plot(b.t, b.q * 1e6, "k.", ms=3, label="recorded mean marker shear" if i == 0 else None)
            ax.plot(b.t, (cols[0] * c0[0] + cols[1] * c0[1]) * 1e6, "C0-", lw=1,
                    label="kinetic level (Coulomb)" if i == 0 else None)
            fit = cols[0] * c1[0] + cols[1] * c1[1] + (cols[2] * c1[2] if len(cols) > 2 else 0.0)
            ax.plot(b.t, fit * 1e6, "C3-", lw=1, label="with the breakaway excess" if i == 0 else None)
        ax.set_ylabel("mean marker shear against the slide, um")
    elif effect == "lens_distortion":
        xyz, uv = rec.data["markers_xyz"], rec.data["markers_uv"]
        pin = apply_lens(xyz, rec.camera, {k: v for k, v in params.items() if k not in ("k1", "k2")})
        dist = apply_lens(xyz, rec.camera, params)
        c = np.array(rec.camera[2:4])
        r = np.linalg.norm(pin - c, axis=-1).reshape(-1)
        ax.plot(r, np.linalg.norm(uv - pin, axis=-1).reshape(-1), "k.", ms=1, alpha=0.3, label="|recorded - pinhole|")
        ax.plot(r, np.linalg.norm(uv - dist, axis=-1).reshape(-1), "C3.", ms=1, alpha=0.3, label="|recorded - radial model|")
        ax.set_xlabel("radius from the principal point, px")
        ax.set_ylabel("pixel residual, px")
    else:
        t = rec.t["sheet_points"]
        x, xp = rec.data["sheet_points"], prepared.prediction["sheet_points"]
        ax.plot(t, x[:, :, 2].max(axis=1), "k-", lw=1, label="recorded sheet, highest point")
        ax.plot(t, xp[:, :, 2].max(axis=1), "C0-", lw=1, label="calibrated replay")
        if term is not None:
            y = params.get("yield_angle_rad")
            ax.plot(t, term[:, :, 2].max(axis=1), "C3-", lw=1,
                    label=f"replay with {effect}" + ("" if y is None else f" (yield angle {y:.3g} rad)"))
            held = fit.get("detail", {}).get("heldout_points") or list(range(x.shape[1]))
            s = rec.sigma["sheet_points"]
            per_row = lambda pred: np.sqrt(np.mean(((x[:, held] - pred[:, held]) / s) ** 2, axis=(1, 2)))  # noqa: E731
            ax_res.semilogy(t, per_row(xp), "C0-", lw=1, label="calibrated replay")
            ax_res.semilogy(t, per_row(term), "C3-", lw=1, label=f"replay with {effect}")
            ax_res.set_ylabel("held-out points:\nwhitened RMS")
            ax_res.set_title(f"held-out sheet points in the windows: {fit.get('heldout_rms_before', float('nan')):.3g} -> "
                             f"{fit.get('heldout_rms_after', float('nan')):.3g} (noise units)", fontsize=9)
            for a, b in sig["windows_s"]:
                ax_res.axvspan(a, b, color="C1", alpha=0.15)
            ax_res.set_xlabel("time, s")
            ax_res.legend(fontsize=7)
        ax.set_ylabel("height, m")
    if effect != "lens_distortion":
        for a, b in sig["windows_s"]:
            ax.axvspan(a, b, color="C1", alpha=0.15)
        ax.set_xlabel("time, s")
    ax.set_title(f"{effect}: statistic {sig['statistic']:.3g} (threshold {sig['threshold'].get('statistic', 0):.3g}), "
                 f"effect size {sig['effect_size']:.3g} {sig['effect_unit']}", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    path = out / f"signature_{effect}.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _plot_calibration(doc: Mapping[str, Any], out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    before, after = doc["baseline"]["whitened_rms_before"], doc["baseline"]["whitened_rms_after"]
    chans = list(before)
    fig, ax = plt.subplots(figsize=(6, 3))
    x = np.arange(len(chans))
    ax.bar(x - 0.2, [before[c] for c in chans], 0.4, label="scene values")
    ax.bar(x + 0.2, [after.get(c, np.nan) for c in chans], 0.4, label="calibrated")
    ax.axhline(1.0, color="k", lw=0.8)
    ax.set_xticks(x, chans, fontsize=8)
    ax.set_ylabel("whitened RMS (noise units)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = out / "calibration_rms.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


WORDS = {
    "latency": "the tactile streams arrive late: every contact event is delayed by the same time",
    "gel_viscoelasticity": "the gel creeps: the tactile response follows the contact with a first-order lag and relaxes on plateaus",
    "damping": "the gel is damped: its contact force runs ahead of the deformation at every press and release, "
               "by more the faster it is pressed (a force proportional to the deformation rate)",
    "lens_distortion": "the tactile camera's lens bends the marker pixels radially, growing towards the image edge",
    "force_bias": "the wrench sensor reads an offset that drifts, even when the gel touches nothing",
    "bending_plasticity": "the sheet keeps a fold after the gel lets go of it (plastic bending)",
    "adhesion": "the gel sticks to the sheet and carries it up on a lift (tack)",
    "stiction": "the contact sticks before it slides: at breakaway the friction reaches about {ratio:.2g} times "
                "its sliding (kinetic) level, then falls back (over the whole pad: the pad slips progressively, so "
                "the local static friction is higher still)",
}


def markdown(doc: Mapping[str, Any], images: list[Path]) -> str:
    """The report's text."""
    lines = [f"# Diagnosis of `{doc['bag']}`", ""] + pipeline_lines(doc)
    ex = doc["explained_by"]
    lines.append("**Named:** " + (", ".join(ex) if ex else "nothing (the calibrated model explains the recording)"))
    for e in (e for e in ex if e != "unexplained"):
        ratio = doc["refit"]["effects"].get(e, {}).get("params", {}).get("static_over_kinetic", float("nan"))
        lines.append(f"- **{e}**: {WORDS.get(e, e).format(ratio=ratio)}.")
    for u in doc["extra"].get("unexplained") or []:
        lines.append(f"- not named: {u['reason']}.")
    props = doc["extra"].get("contact_properties") or []
    if props:
        lines.append(f"- contact properties of this cell (not named alone): {', '.join(props)}")
    if doc["extra"].get("ties"):
        lines.append(f"- ties (not resolved by a discriminating test): {doc['extra']['ties']}")
    cal = doc["baseline"].get("calibration") or {}
    weights = cal.get("channel_weights") or {}
    lines += ["", "## Calibration (whitened RMS, noise units)", "",
              "| channel | scene values | calibrated | weight in the fit |", "|---|---|---|---|"]
    for ch, v in doc["baseline"]["whitened_rms_before"].items():
        w = weights.get(ch)
        lines.append(f"| {ch} | {v:.2f} | {doc['baseline']['whitened_rms_after'].get(ch, float('nan')):.2f} | "
                     f"{'-' if w is None else f'{w:.3g}'} |")
    gaps = cal.get("not_followed") or {}
    if gaps:
        lines += ["", "The calibrated model does not follow " + ", ".join(f"{ch} (whitened RMS {v:.3g})" for ch, v in gaps.items())
                  + ": a model-form gap, not noise. The calibration weighed each channel by its gap at the scene values "
                  "(weight 1 / RMS^2), so such a channel did not drive the fitted parameters."]
    if cal.get("status"):
        lines.append(f"\nParameter fit: {cal['status']}, {cal.get('fit_replays')} replays.")
    drive = cal.get("drive")
    if drive:
        def g(key: str, spec: str = ".4g") -> str:
            return "n/a" if drive.get(key) is None else format(drive[key], spec)

        lines.append(f"\nEffector drive: {drive['decision']} (delta-BIC {g('delta_bic')} against a kinematic arm, "
                     f"threshold {drive['min_delta_bic']:g}); k_s {g('stiffness')} +- {g('stiffness_sigma', '.2g')} "
                     f"N/m, c_d {g('damping')} +- {g('damping_sigma', '.2g')} N s/m"
                     + (f"; {drive['why']}" if drive.get("why") else "") + ".")
    gains = cal.get("gains") or {}
    if gains:
        lines += ["", "| sensor gain | fitted | data asked for | prior | on a bound |", "|---|---|---|---|---|"]
        lines += [f"| {g} | {f['value']:.4g} | {f['unbounded']:.4g} | {f['bounds'][0]:.4g}-{f['bounds'][1]:.4g} | "
                  f"{f['at_bound'] or 'no'} |" for g, f in gains.items()]
        lines += [f"- **{g} is not the sensor's gain**: {f['cause']}." for g, f in gains.items() if f.get("at_bound")]
    lines += ["", f"Fitted parameters: `{json.dumps(doc['baseline']['params'])}`", "",
              "## Where", "", f"windows (s): {doc['mismatch']['windows_s']}; channels: {doc['mismatch']['channels']}; "
              f"markers: {doc['mismatch']['markers']}", "", "## Signature tests", "",
              "| effect | statistic | threshold | effect size | min size | detected | note |", "|---|---|---|---|---|---|---|"]
    for e, s in doc["extra"]["signatures"].items():
        th = s.get("threshold") or {}
        lines.append(f"| {e} | {s['statistic']:.3g} | {th.get('statistic', float('nan')):.3g} | {s['effect_size']:.3g} {s['effect_unit']} "
                     f"| {th.get('effect_size', float('nan')):.3g} | {s['detected']} | {s['reason']} |")
    lines += ["", f"Null: {doc['extra']['null']['source']} ({', '.join(doc['extra']['null']['baselines']) or 'noise model'})", "",
              "## Refits (held-out whitened RMS before -> after)", ""]
    for e, r in doc["refit"]["effects"].items():
        b, a = r.get("heldout_rms_before"), r.get("heldout_rms_after")
        lines.append(f"- {e}: params `{json.dumps(r['params'])}`; {r['observable']}; held-out: {r['heldout']}; "
                     f"{'n/a' if b is None else f'{b:.3g}'} -> {'n/a' if a is None else f'{a:.3g}'}")
        if r.get("base"):
            lines.append(f"  - before: the {r['base']}")
        for note in ([r["note"]] if r.get("note") else []) + list((r.get("detail") or {}).get("notes", [])):
            lines.append(f"  - {note}")
    lines += ["", *[f"![{p.stem}]({p.name})" for p in images], ""]
    return "\n".join(lines)


def write_signature_report(doc: Mapping[str, Any], prepared: Any, out_dir: str | Path) -> list[Path]:
    """Write ``report.md``, ``report.html``, ``diagnosis.json`` and the PNGs into ``out_dir``.

    Returns:
        written paths.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    images = [_plot_calibration(doc, out)]
    shown = [e for e in doc["explained_by"] if e != "unexplained"]
    for e in shown + [u["effect"] for u in doc["extra"].get("unexplained") or [] if u["effect"] not in shown]:
        p = _plot_effect(doc, prepared, e, out)
        if p is not None:
            images.append(p)
    return write_report_files(doc, markdown(doc, images), images, out)
