"""Human-readable diagnosis report: ``report.md``, ``report.html`` and residual plots (PNG).

The plots show the whitened residual (noise units, RMS over the points of each sample) of every
tested channel before and after the refit of the augmented model, with the located windows shaded.
"""

from __future__ import annotations

import html
import json
from pathlib import Path
from typing import Any, Mapping

import numpy as np


def plot_residuals(diagnosis: Any, out_dir: Path) -> list[Path]:
    """One PNG per tested channel: whitened residual RMS per sample before / after, windows shaded.

    Args:
        diagnosis: a finished ``sysid.diagnose.engine.BagDiagnosis``.
        out_dir: existing directory.

    Returns:
        written paths.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sysid.diagnose.residuals import residual

    arrays = diagnosis._arrays
    t0 = int(diagnosis.evidence.t_ns["pose"][0])
    paths = []
    for ch in diagnosis.tested:
        t = (np.asarray(diagnosis.model.evidence.t_ns[ch]) - t0) * 1e-9
        fig, ax = plt.subplots(figsize=(8, 3))
        for key, label in (("prediction_before", "nominal fit"), ("prediction_after", "augmented refit")):
            r = residual(diagnosis.model, ch, arrays[key][ch]).reshape(t.shape[0], -1)
            ax.plot(t, np.sqrt(np.mean(r ** 2, axis=1)), lw=1.0, label=label)
        for a, b in arrays["windows"]:
            ax.axvspan(a, b, color="tab:red", alpha=0.15)
        ax.axhline(1.0, color="k", lw=0.5, ls=":")
        ax.set_xlabel("t [s]")
        ax.set_ylabel(f"{ch} residual [sigma]")
        ax.legend(loc="upper right", fontsize=8)
        fig.tight_layout()
        path = out_dir / f"residual_{ch}.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        paths.append(path)
    return paths


def pipeline_lines(doc: Mapping[str, Any]) -> list[str]:
    """The report's "Pipeline" section: the stage that named and why (``extra.pipeline``,
    :mod:`sysid.diagnose.pipeline`); empty for a report without it."""
    pipe = (doc.get("extra") or {}).get("pipeline")
    if not pipe:
        return []
    drive = pipe.get("drive") or {}
    lines = ["## Pipeline", "", f"- stage: **{pipe['stage']}** ({'score tests and refits of the candidate library' if pipe['stage'] == 'score' else 'signature tests against a calibrated null, refits of the named effects'})",
             f"- why: {pipe['why']}",
             f"- effector drive: {drive.get('decision', '?')} (delta-BIC {drive.get('delta_bic')})"]
    if pipe.get("not_applied"):
        lines.append(f"- options not applied (they act on the other stage): {', '.join(pipe['not_applied'])}")
    check = pipe.get("wrench_check") or {}
    if check.get("tripped"):  # sysid.wrench_check: the recorded force opposes the gel's own marker shear
        spans = ", ".join(f"{a:.2f}-{b:.2f} s" for a, b in check["spans_s"])
        lines.append(f"- **sensor check: the recorded wrench contradicts the gel's markers** in {spans} "
                     f"({check['rows_against']} rows, cosine {check['cosine']:+.2f}): there it is not the force ON the "
                     "gel (INTERFACES.md); fitted as recorded here, left out by `thinshell sysid`")
    return lines + [""]


def _markdown(doc: Mapping[str, Any], images: list[Path]) -> str:
    lines = [f"# Diagnosis of `{doc['bag']}`", ""] + pipeline_lines(doc)
    ex = doc["explained_by"]
    verdict = "nothing detected" if not ex else ("mismatch detected, no candidate explains it" if ex == ["unexplained"]
                                                 else "explained by " + ", ".join(ex))
    lines += [f"**Verdict:** {verdict}.", ""]
    m = doc["mismatch"]
    lines += ["## Where", f"- windows (s): {m['windows_s']}", f"- channels: {m['channels']}",
              f"- markers: {m['markers']}", ""]
    lines += ["## Candidates (score tests, Holm-corrected p-values)", "",
              "| effect | statistic | p (Holm) | channel | delta-BIC | accepted |", "|---|---|---|---|---|---|"]
    for c in doc["candidates"]:
        lines.append(f"| {c['effect']} | {c['statistic']:.4g} | {c['p_value']:.3g} | {c.get('channel', '')} | "
                     f"{c.get('delta_bic', float('nan')):.4g} | {c.get('accepted', '')} |")
    lines += ["", "## Why", ""] + why_lines(doc)
    b, r = doc["baseline"], doc["refit"]
    lines += ["", "## Parameters and RMS", "", f"- baseline parameters: `{json.dumps(b['params'])}`",
              f"- baseline RMS: `{json.dumps(b['rms'])}`", f"- refit parameters: `{json.dumps(r['params'])}`",
              f"- refit RMS: `{json.dumps(r['rms'])}`",
              f"- held-out RMS ({r.get('heldout_unit', '')}): {r['heldout_rms_before']:.4g} -> "
              f"{r['heldout_rms_after']:.4g} ({r.get('heldout', '')})"]
    if r.get("heldout_rms_null") is not None:
        lines.append(f"- held-out RMS of the nominal parameters re-estimated without any effect (the physics refits' "
                     f"null model): {r['heldout_rms_null']:.4g}; a physics effect is named only for what it explains "
                     f"beyond it")
    lines.append("")
    lines += ["## Residuals", ""] + [f"![{p.stem}]({p.name})" for p in images]
    return "\n".join(lines) + "\n"


def why_lines(doc: Mapping[str, Any]) -> list[str]:
    """The reasons behind the verdict, one Markdown bullet per candidate, from the JSON contract.

    For every effect of the library: accepted (with its evidence), or the first tests it failed, in
    the order the diagnosis applies them (SYSID.md steps 3-6: score test after Holm, a refit that
    lowers the training residual, no tested channel moved away from the recording, held-out
    improvement, effect size, delta-BIC); then the unresolved ties. This is where a report that says
    "unexplained" explains its confusion: which effects came close and what ruled each one out.

    Args:
        doc: the report of :func:`sysid.diagnose.engine.diagnose` (``extra.tests``,
            ``extra.decisions``, ``extra.ties``, ``extra.settings``, ``extra.library`` are read when present).

    Returns:
        Markdown lines.
    """
    extra = doc.get("extra", {})
    settings = extra.get("settings", {})
    alpha = float(settings.get("alpha", 0.01))
    bic = float(settings.get("bic_threshold", 10.0))
    floor = settings.get("min_explained")
    tests = extra.get("tests", [])
    decisions = extra.get("decisions", {})
    library = extra.get("library") or sorted({t["effect"] for t in tests} | set(decisions))
    out: list[str] = []
    for effect in library:
        own = [t for t in tests if t.get("effect") == effect]
        best = min(own, key=lambda t: t.get("p_holm", 1.0), default=None)
        d = decisions.get(effect)
        if d is not None and d.get("accepted"):
            out.append(f"- **{effect}: accepted.** Refit {json.dumps(d.get('params', {}))}; delta-BIC "
                       f"{d.get('delta_bic', float('nan')):.4g}; held-out RMS {d.get('heldout_rms_before', float('nan')):.4g}"
                       f" -> {d.get('heldout_rms_after', float('nan')):.4g} (p {d.get('heldout_p', float('nan')):.3g}), "
                       f"{100 * d.get('explained_fraction', float('nan')):.0f} % of the held-out excess explained"
                       + (f"; against the nominal parameters re-estimated without it, held-out RMS "
                          f"{d['beyond_reestimate']['heldout_rms_null']:.4g} -> "
                          f"{d['beyond_reestimate']['heldout_rms_after']:.4g}, "
                          f"{100 * d['beyond_reestimate']['explained_fraction']:.0f} % of what they leave"
                          if d.get("beyond_reestimate") else "") + ".")
            continue
        if best is None:
            out.append(f"- {effect}: not tested (no signature on the tested channels, or its probe diverged; see the notes).")
            continue
        significant = [t["channel"] for t in own if t.get("significant")]
        if not significant:
            white = ""
            if best.get("classical_statistic") is not None and best.get("ar_order"):
                # serially correlated residuals (an engine or model gap) inflate the white-noise score
                white = (f"; S = {best['statistic']:.3g} after AR({best['ar_order']}) prewhitening of the residual, "
                         f"{best['classical_statistic']:.3g} without")
            out.append(f"- {effect}: score test not significant (smallest Holm-adjusted p {best.get('p_holm', 1.0):.3g} "
                       f"on {best.get('channel', '?')}, alpha {alpha:g}{white}): the residual does not look like its "
                       "signature.")
            continue
        why = _rejections(d, alpha, bic, floor)
        out.append(f"- {effect}: significant on {', '.join(significant)} (Holm p {best.get('p_holm', 1.0):.3g}), "
                   f"rejected: {'; '.join(why)}.")
    for tie in extra.get("ties", []):
        pair = " / ".join(tie.get("pair", []))
        out.append(f"- tie {pair}: {'resolved' if tie.get('resolved') else 'not resolved by a discriminating test'}"
                   + (f" ({tie['reason']})" if tie.get("reason") else "") + ".")
    if doc.get("explained_by") == ["unexplained"]:
        out.append("- **Verdict unexplained:** the mismatch above is significant, but no library effect passes every "
                   "test; the missing physics is outside the library, or the recording's engine differs from this "
                   "model in a way no single candidate reproduces.")
    elif not doc.get("explained_by"):
        out.append("- **Nothing detected:** no significant mismatch after the multiple-testing correction.")
    return out


def _rejections(d: Mapping[str, Any] | None, alpha: float, bic: float, floor: Any) -> list[str]:
    """Why a significant candidate's refit (decision ``d``, None: not refitted) was not accepted."""
    if d is None:
        return ["not refitted"]
    why = []
    if not d.get("train_improves", True):
        why.append("its refit does not lower the training residual")
    if d.get("effect_on") is False:
        why.append("its refit leaves the effect off (beta 0): what it explains is the re-estimate of the nominal "
                   "parameters alone")
    null = d.get("beyond_reestimate")
    if d.get("effect_on") is not False and null is not None and not null.get("adds", True):
        why.append(f"against the nominal parameters re-estimated without it (held-out RMS "
                   f"{null['heldout_rms_null']:.4g} -> {null['heldout_rms_after']:.4g}, p {null['heldout_p']:.3g}) it "
                   f"explains {100 * null['explained_fraction']:.0f} % of the held-out excess: the nominal "
                   f"parameters' move carries its fit")
    if d.get("contradicted_on"):
        why.append("its refit moves " + ", ".join(d["contradicted_on"]) + " away from the recording")
    p_h = d.get("heldout_p_holm", d.get("heldout_p"))
    if p_h is not None and p_h > alpha:
        why.append(f"no held-out improvement (held-out RMS {d.get('heldout_rms_before', float('nan')):.4g} -> "
                   f"{d.get('heldout_rms_after', float('nan')):.4g}, p {p_h:.3g})")
    frac = d.get("explained_fraction")
    if floor is not None and frac is not None and frac < float(floor):
        why.append(f"explains {100 * frac:.0f} % of the held-out excess (at least {100 * float(floor):.0f} % needed)")
    if d.get("delta_bic") is not None and d["delta_bic"] < bic:
        why.append(f"delta-BIC {d['delta_bic']:.4g} < {bic:g}")
    return why or ["not accepted conditionally on the effects accepted before it"]


def write_report(doc: Mapping[str, Any], diagnosis: Any, out_dir: str | Path) -> list[Path]:
    """Write ``report.md``, ``report.html``, ``diagnosis.json`` and the residual PNGs into ``out_dir``.

    Returns:
        written paths.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    images = plot_residuals(diagnosis, out)
    return write_report_files(doc, _markdown(doc, images), images, out)


def write_report_files(doc: Mapping[str, Any], md: str, images: list[Path], out: Path) -> list[Path]:
    """Write ``report.md`` (``md``), ``report.html`` (the text and the ``images``) and ``diagnosis.json``
    (``doc``) into ``out``.

    Returns:
        written paths, the images last.
    """
    (out / "report.md").write_text(md)
    body = "".join(f"<p><img src='{html.escape(p.name)}'></p>" for p in images)
    (out / "report.html").write_text("<html><body><pre>" + html.escape(md) + "</pre>" + body + "</body></html>\n")
    (out / "diagnosis.json").write_text(json.dumps(doc, indent=2) + "\n")
    return [out / "report.md", out / "report.html", out / "diagnosis.json", *images]
