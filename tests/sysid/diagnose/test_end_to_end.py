"""End-to-end ``thinshell diagnose`` on the shared reference bags (slow: tens of simulator replays).

These bags come from an independent engine (MuJoCo), so our simulator differs from them even after
the nominal fit (whitened wrench RMS about 5 on the coarse gel used here). What holds, and is asserted:
the report satisfies the contract; the nominal fit ran; the latency's discriminating test measures
the tactile delay (cross-correlation of recorded vs predicted rates); the 40 ms delay is not swapped
for another *observation* effect on either bag; and the nominal bag names neither latency nor lens
distortion. Issue 23's checks on these recordings (none / latency / bending_plasticity named by
``thinshell diagnose`` with its default calibration) are not asserted here yet: see
docs/benchmarks.md (2026-11-25) for what the calibrated diagnosis gives on them.
"""

from __future__ import annotations

import json

import pytest

from sysid.diagnose_cli import diagnose_main
from sysid.diagnose.schema import validate_report
from tests.sysid.conftest import reference_bag

pytestmark = pytest.mark.slow

ARGS = ["--t-max", "1.5", "--dt", "0.01", "--gel-resolution", "5", "4", "2", "--params", "gel.youngs_modulus",
        "--project", "gel.youngs_modulus", "friction.gel_sheet", "sheet.bending_stiffness", "--fit-max-nfev", "5",
        "--workers", "2"]


def _run(tmp_path, name):
    out = tmp_path / f"{name}.json"
    rc = diagnose_main([str(reference_bag(name)), *ARGS, "--json", str(out), "--out", str(tmp_path / name)])
    assert rc == 0
    doc = json.loads(out.read_text())
    validate_report(doc)
    assert (tmp_path / name / "report.md").is_file()
    assert doc["baseline"]["fitted"] is True
    return doc


def test_latency_bag_delay_is_measured_by_the_discriminating_test(tmp_path):
    doc = _run(tmp_path, "latency_s103")
    assert doc["mismatch"]["detected"] is True
    lat = doc["extra"]["decisions"]["latency"]
    # truth: 0.04 s late; the nominal bag shows a systematic ~0.027 s lag of MuJoCo behind our
    # simulator (measured), so the delayed bag must lag clearly more than that
    assert 0.045 < lat["xcorr_lag_s"]["markers_xyz"] < 0.1
    assert "lens_distortion" not in doc["explained_by"]


def test_nominal_bag_names_no_observation_effect(tmp_path):
    doc = _run(tmp_path, "nominal_s101")
    assert not {"latency", "lens_distortion", "force_bias"} & set(doc["explained_by"])
    # a recording with nothing concealed: no delay is confirmed by the cross-correlation test
    assert doc["extra"]["decisions"]["latency"]["xcorr_agrees"] is False
