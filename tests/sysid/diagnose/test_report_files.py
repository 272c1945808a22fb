"""A short ``thinshell diagnose`` run of the score stage on this simulator's own short press writes the whole
report (fast; the end-to-end tests check the statistics: test_pipeline.py on this simulator's recording,
test_end_to_end.py on the reference bags)."""

from __future__ import annotations

import json

from sysid.diagnose.cli import diagnose_main
from sysid.diagnose.schema import validate_report
from tests.sysid.simbag import PRESS_ONLY, make_recording


def test_short_diagnosis_writes_contract_json_report_and_residual_plots(tmp_path):
    bag = make_recording(tmp_path / "press", segments=PRESS_ONLY, seed=2)  # pose = command: the score stage
    out, js = tmp_path / "report", tmp_path / "diagnosis.json"
    code = diagnose_main([str(bag), "--candidates", "latency", "force_bias", "--no-calibrate",
                          "--out", str(out), "--json", str(js)])
    assert code == 0
    doc = json.loads(js.read_text())
    validate_report(doc)
    assert {"baseline", "mismatch", "candidates", "explained_by", "refit"} <= set(doc)
    assert doc["extra"]["pipeline"]["stage"] == "score" and doc["extra"]["pipeline"]["not_applied"] == []
    pngs = sorted(p.name for p in out.glob("residual_*.png"))
    assert "residual_wrench.png" in pngs and all((out / p).stat().st_size > 0 for p in pngs)
    md = (out / "report.md").read_text()
    assert all(p in md for p in pngs) and (out / "report.html").is_file()
    assert "## Why" in md and "- latency:" in md and "- force_bias:" in md


def _test(effect, channel, p_holm, significant, statistic=2.0, classical=None, ar=0):
    return {"effect": effect, "channel": channel, "statistic": statistic, "p_value": p_holm, "p_holm": p_holm,
            "significant": significant, "classical_statistic": classical, "ar_order": ar}


def test_why_section_names_what_ruled_each_candidate_out():
    """The report's reasons come from the contract's tests and decisions: a non-significant score test
    (with the prewhitening that made it so), a contradicted channel, no held-out gain, too small an
    effect, an accepted effect with its evidence, and the final verdict."""
    from sysid.diagnose.report import why_lines

    doc = {
        "explained_by": ["unexplained"],
        "extra": {
            "library": ["latency", "damping", "stiction", "force_bias"],
            "settings": {"alpha": 0.01, "bic_threshold": 10.0, "min_explained": 0.25},
            "tests": [_test("latency", "markers_uv", 1.0, False, 1.9, 328.0, 1),
                      _test("damping", "wrench", 1e-6, True), _test("stiction", "wrench", 1e-4, True)],
            "decisions": {
                "damping": {"accepted": False, "train_improves": True, "contradicted_on": ["sheet_points"],
                            "heldout_p": 0.7, "heldout_rms_before": 7.0, "heldout_rms_after": 20.7,
                            "explained_fraction": -7.9, "delta_bic": 26.0},
                "stiction": {"accepted": False, "train_improves": True, "contradicted_on": [], "heldout_p": 1e-5,
                             "heldout_rms_before": 7.0, "heldout_rms_after": 6.6, "explained_fraction": 0.1,
                             "delta_bic": 40.0},
            },
            "ties": [{"pair": ["damping", "gel_viscoelasticity"], "resolved": False}],
        },
    }
    lines = why_lines(doc)
    text = "\n".join(lines)
    assert lines[0].startswith("- latency: score test not significant") and "AR(1) prewhitening" in lines[0]
    assert "328 without" in lines[0]
    damping = next(x for x in lines if x.startswith("- damping"))
    assert "moves sheet_points away" in damping and "no held-out improvement" in damping
    stiction = next(x for x in lines if x.startswith("- stiction"))
    assert "explains 10 % of the held-out excess (at least 25 % needed)" in stiction
    assert "moves" not in stiction and "held-out improvement" not in stiction
    assert "- force_bias: not tested" in text and "tie damping / gel_viscoelasticity" in text
    assert lines[-1].startswith("- **Verdict unexplained:**")
    doc["explained_by"] = ["stiction"]
    doc["extra"]["decisions"]["stiction"].update(accepted=True, params={"candidate.stiction": 0.3})
    accepted = next(x for x in why_lines(doc) if x.startswith("- **stiction: accepted.**"))
    assert "delta-BIC 40" in accepted and "held-out RMS 7 -> 6.6" in accepted
