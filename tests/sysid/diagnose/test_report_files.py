"""A short ``thinshell diagnose`` run on the bundled bag writes the whole report (fast; the slow
end-to-end tests check the statistics on the full reference bags)."""

from __future__ import annotations

import json
from pathlib import Path

from sysid.diagnose.cli import diagnose_main
from sysid.diagnose.schema import validate_report

BAG = Path(__file__).resolve().parents[3] / "bags" / "nominal_s101"


def test_short_diagnosis_writes_contract_json_report_and_residual_plots(tmp_path):
    out, js = tmp_path / "report", tmp_path / "diagnosis.json"
    code = diagnose_main([str(BAG), "--t-max", "0.3", "--candidates", "latency", "force_bias",
                          "--gel-resolution", "3", "3", "2", "--out", str(out), "--json", str(js)])
    assert code == 0
    doc = json.loads(js.read_text())
    validate_report(doc)
    assert {"baseline", "mismatch", "candidates", "explained_by", "refit"} <= set(doc)
    pngs = sorted(p.name for p in out.glob("residual_*.png"))
    assert "residual_wrench.png" in pngs and all((out / p).stat().st_size > 0 for p in pngs)
    md = (out / "report.md").read_text()
    assert all(p in md for p in pngs) and (out / "report.html").is_file()
