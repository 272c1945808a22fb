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


def _markdown(doc: Mapping[str, Any], images: list[Path]) -> str:
    lines = [f"# Diagnosis of `{doc['bag']}`", ""]
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
    b, r = doc["baseline"], doc["refit"]
    lines += ["", "## Parameters and RMS", "", f"- baseline parameters: `{json.dumps(b['params'])}`",
              f"- baseline RMS: `{json.dumps(b['rms'])}`", f"- refit parameters: `{json.dumps(r['params'])}`",
              f"- refit RMS: `{json.dumps(r['rms'])}`",
              f"- held-out RMS ({r.get('heldout_unit', '')}): {r['heldout_rms_before']:.4g} -> "
              f"{r['heldout_rms_after']:.4g} ({r.get('heldout', '')})", ""]
    lines += ["## Residuals", ""] + [f"![{p.stem}]({p.name})" for p in images]
    return "\n".join(lines) + "\n"


def write_report(doc: Mapping[str, Any], diagnosis: Any, out_dir: str | Path) -> list[Path]:
    """Write ``report.md``, ``report.html``, ``diagnosis.json`` and the residual PNGs into ``out_dir``.

    Returns:
        written paths.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    images = plot_residuals(diagnosis, out)
    md = _markdown(doc, images)
    (out / "report.md").write_text(md)
    body = "".join(f"<p><img src='{html.escape(p.name)}'></p>" for p in images)
    (out / "report.html").write_text("<html><body><pre>" + html.escape(md) + "</pre>" + body + "</body></html>\n")
    (out / "diagnosis.json").write_text(json.dumps(doc, indent=2) + "\n")
    return [out / "report.md", out / "report.html", out / "diagnosis.json", *images]
