"""End-to-end ``thinshell diagnose`` on the shared reference bags (slow: several simulator replays)."""

from __future__ import annotations

import json

import pytest

from sysid.diagnose_cli import diagnose_main
from sysid.diagnose.schema import validate_report
from tests.sysid.conftest import reference_bag

pytestmark = pytest.mark.slow


def _run(tmp_path, name, t_max):
    out = tmp_path / f"{name}.json"
    rc = diagnose_main([str(reference_bag(name)), "--t-max", str(t_max), "--workers", "2", "--json", str(out),
                        "--out", str(tmp_path / name)])
    assert rc == 0
    doc = json.loads(out.read_text())
    validate_report(doc)
    assert (tmp_path / name / "report.md").is_file()
    return doc


def test_latency_bag_is_explained_by_latency(tmp_path):
    doc = _run(tmp_path, "latency_s103", 1.5)
    assert doc["explained_by"][0] == "latency"
    assert doc["refit"]["params"]["latency_s"] == pytest.approx(0.04, abs=0.01)
    assert doc["refit"]["heldout_rms_after"] < doc["refit"]["heldout_rms_before"]


def test_nominal_bag_raises_no_alarm(tmp_path):
    doc = _run(tmp_path, "nominal_s101", 1.5)
    assert doc["explained_by"] == []
    assert doc["mismatch"]["detected"] is False
