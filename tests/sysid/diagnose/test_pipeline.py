"""The one diagnosis pipeline behind ``thinshell diagnose`` (:mod:`sysid.diagnose.pipeline`).

- One option set: both stages take the same calibration from it; an option of one stage alone is recorded, and
  the removed ``--engine`` is refused with one line saying why.
- The premise decides the stage from the recording: this simulator's own recording (pose = command + pose
  noise) takes the score stage; the same recording with its pose lagging the command by the normal load over a
  3,000 N/m spring (an impedance-held arm, as the reference engine's) takes the signature stage; so does the
  independent engine's nominal press-slide.
- End to end with the defaults on this simulator's own press-slide with a concealed force-sensor drift (a
  CI-sized recording): the score stage names ``force_bias`` alone, its refit lowers the held-out RMS, and the
  report (one schema, the pipeline's section) is written.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sysid.diagnose.cli import build_parser, diagnose_main, options_from_args
from sysid.diagnose.pipeline import premise
from sysid.diagnose.schema import SCHEMA_VERSION, validate_report
from sysid.diagnose.signature_engine import SignatureSettings
from tests.sysid.conftest import reference_bag
from tests.sysid.simbag import (NOISE, PRESS_SLIDE, TRUE_PARAMS, add_noise, scene_with,
                                simulate_streams, targets_from_segments, write_bag)

DRIFT_N = 1.2
"""Concealed drift of the force sensor's F_z over the recording, N: 6 of its noise levels (0.2 N) at the end."""

SLOW_PRESS_SLIDE = tuple((displacement, 2 * steps) for displacement, steps in PRESS_SLIDE)
""":data:`tests.sysid.simbag.PRESS_SLIDE` at half the speed (57 steps): enough samples under load for the
drive's criterion (:data:`sysid.drive_calibration.DRIVE_MIN_LOADED_SAMPLES`)."""


@pytest.fixture(scope="module")
def streams():
    """Noisy streams of this simulator's press-slide of the card scene (pose = command + pose noise)."""
    scene = scene_with(TRUE_PARAMS)
    targets = targets_from_segments(np.asarray(scene["effectors"]["ee"]["initial_pose"]), SLOW_PRESS_SLIDE)
    return add_noise(simulate_streams(scene, TRUE_PARAMS, targets), seed=3)


def _bag(tmp_path: Path, streams: dict, name: str) -> Path:
    return write_bag(tmp_path / name, scene_with(TRUE_PARAMS), streams)


def _options(bag: Path) -> SignatureSettings:
    return options_from_args(build_parser().parse_args([str(bag)])).signatures


def test_one_option_set_gives_both_stages_the_same_calibration(capsys):
    args = build_parser().parse_args(["bag"])
    opts = options_from_args(args)
    score, sig = opts.score, opts.signatures
    for a, b in (("dt", "dt"), ("t_max", "t_max"), ("arch", "arch"), ("calibrate", "calibrate"),
                 ("calibration_max_replays", "calibration_max_replays"),
                 ("calibration_max_time", "calibration_max_time"), ("fit_max_nfev", "calibration_max_nfev"),
                 ("workers", "workers"), ("batched", "batched"), ("simulation", "simulation")):
        assert getattr(score, a) == getattr(sig, b), a
    assert score.calibrate and sig.calibration_drive and opts.given == {}
    assert opts.candidates is None  # the whole library by default
    given = options_from_args(build_parser().parse_args(
        ["bag", "--candidates", "latency", "--baseline", "b", "--no-drive", "--calibration-replays", "3"])).given
    assert given == {"--candidates": "score", "--baseline": "signatures", "--no-drive": "signatures"}
    assert "--engine" not in build_parser().format_help()
    assert diagnose_main(["bag", "--engine", "score"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--engine is gone" in err and "drive" in err


def test_the_gel_element_reaches_both_stages_replays(capsys):
    """``--gel-element`` (with or without ``--gel-resolution``) sets the ``simulation`` overrides of both stages'
    replays; an unknown law is refused naming the choices."""
    opts = options_from_args(build_parser().parse_args(["bag", "--gel-element", "green_strain"]))
    assert opts.score.simulation == opts.signatures.simulation == {"gel_element": "green_strain"}
    opts = options_from_args(build_parser().parse_args(["bag", "--gel-resolution", "10", "8", "5",
                                                        "--gel-element", "nodal_pressure_neohookean"]))
    assert opts.signatures.simulation == {"gel_resolution": [10, 8, 5], "gel_element": "nodal_pressure_neohookean"}
    assert options_from_args(build_parser().parse_args(["bag"])).signatures.simulation is None
    with pytest.raises(SystemExit):
        build_parser().parse_args(["bag", "--gel-element", "mooney"])
    assert "green_strain" in capsys.readouterr().err


def test_the_recording_decides_the_stage(tmp_path, streams):
    from sysid.drive_calibration import DRIVE_MIN_DELTA_BIC, fit_drive  # noqa: F401  (the criterion's module)
    from sysid.evidence import load_evidence
    from sysid.observation import ObservationModel

    own = _bag(tmp_path, streams, "own")
    p = premise(own, _options(own))
    assert p.stage == "score" and p.drive["decision"] == "kinematic", p
    assert "pose is its command" in p.why

    # the same press held by a 3,000 N/m spring: the measured pose lags its command by F_n / k along the normal
    model = ObservationModel(load_evidence(own, include_image=False), dt=0.01, arch="numpy")
    normal = model.sensor_normal(streams["pose_cmd"][0])
    load = -streams["wrench"][:, 2]
    held = dict(streams)
    held["pose"] = streams["pose"].copy()
    held["pose"][:, :3] = (streams["pose_cmd"][:, :3] - np.outer(load / 3000.0, normal)
                           + np.random.default_rng(5).normal(0.0, NOISE["pose"], (len(load), 3)))
    arm = _bag(tmp_path, held, "arm")
    q = premise(arm, _options(arm))
    assert q.stage == "signatures" and q.drive["delta_bic"] > DRIVE_MIN_DELTA_BIC, q
    assert q.drive["stiffness"] == pytest.approx(3000.0, rel=0.15), q.drive

    ref = reference_bag("nominal_s101")
    r = premise(ref, _options(ref))
    assert r.stage == "signatures" and r.drive["delta_bic"] > DRIVE_MIN_DELTA_BIC, r


def test_the_report_names_a_wrench_that_contradicts_the_gels_markers():
    """nominal_s109 (the reference's lift-and-fold): the premise's sensor check finds the carried phase's recorded
    force opposing the markers' shear; the stamped report carries the note and the pipeline section names it.
    nominal_s101 (a press-slide) has no note."""
    from sysid.diagnose.pipeline import PipelineOptions, _stamp
    from sysid.diagnose.report import pipeline_lines

    lift = reference_bag("nominal_s109")
    p = premise(lift, _options(lift))
    assert p.wrench_check["tripped"] and p.wrench_check["rows_against"] > 100
    opts = options_from_args(build_parser().parse_args([str(lift)]))
    doc = _stamp({"bag": str(lift), "extra": {}}, p, opts, 0.0)
    assert any("topic wrench contradicts" in n for n in doc["extra"]["notes"])
    assert doc["extra"]["pipeline"]["wrench_check"]["tripped"]
    assert any("recorded wrench contradicts the gel's markers" in line for line in pipeline_lines(doc))
    ref = reference_bag("nominal_s101")
    r = premise(ref, _options(ref))
    assert not r.wrench_check["tripped"] and r.wrench_note == ""
    assert isinstance(opts, PipelineOptions)


@pytest.mark.parametrize("drift", [0.0, DRIFT_N], ids=["nominal", "drift"])
def test_defaults_name_a_concealed_force_drift_on_this_simulators_recording(tmp_path, streams, drift):
    drifted = dict(streams)
    w = streams["wrench"].copy()
    t = streams["t_ns"] * 1e-9
    w[:, 2] += drift * t / t[-1]
    drifted["wrench"] = w
    bag = _bag(tmp_path, drifted, "drift")
    out, js = tmp_path / "report", tmp_path / "diagnosis.json"
    assert diagnose_main([str(bag), "--json", str(js), "--out", str(out)]) == 0
    doc = json.loads(js.read_text())
    validate_report(doc)
    assert doc["schema_version"] == SCHEMA_VERSION and doc["extra"]["pipeline"]["stage"] == "score"
    # every candidate of the library was tested: none hand-picked
    assert len(doc["extra"]["library"]) >= 8
    md = (out / "report.md").read_text()
    assert "## Pipeline" in md and "stage: **score**" in md and "pose is its command" in md
    assert json.loads((out / "diagnosis.json").read_text()) == doc
    if not drift:  # the same recording without the drift: no false alarm
        assert doc["explained_by"] == [], (doc["explained_by"], doc["candidates"])
        return
    assert doc["explained_by"] == ["force_bias"], (doc["explained_by"], doc["candidates"])
    assert doc["refit"]["heldout_rms_after"] < doc["refit"]["heldout_rms_before"], doc["refit"]
    # the refitted drift of F_z is the concealed one (N over the recording), within a third
    fitted = doc["refit"]["params"].get("drift_fz")
    assert fitted is not None and fitted == pytest.approx(DRIFT_N, rel=0.35), doc["refit"]["params"]
