"""``thinshell sysid`` end to end: outputs, atomic publication, refusal, error messages."""

from __future__ import annotations

import json

import pytest

from sysid.cli import sysid_main
from sysid.report import PLOT_FILES
from sysid.results import SECTION_KEYS, load_fit_json
from tests.sysid.conftest import reference_bag
from tests.sysid.simbag import PRESS_ONLY, make_recording

FAST = ["--params", "gel.youngs_modulus", "--max-nfev", "1", "--quiet"]


@pytest.fixture(scope="module")
def press_bag(tmp_path_factory):
    """A 4-step synthetic press whose scene.yaml states a gel modulus 2x the true one."""
    return make_recording(tmp_path_factory.mktemp("cli") / "bag", segments=PRESS_ONLY, seed=4,
                          nominal={"gel.youngs_modulus": 6.0e5})


def test_reference_bag_truncated_runs_end_to_end(tmp_path, capsys):
    bag = reference_bag("nominal_s101")
    out = tmp_path / "fit_nominal"
    rc = sysid_main([str(bag), "--out", str(out), "--t-max", "0.3", "--dt", "0.05", "--gel-resolution", "5,4,2", *FAST])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    doc = load_fit_json(out / "fit.json")
    for section, keys in SECTION_KEYS.items():
        assert set(keys) <= set(doc[section]), section
    assert doc["provenance"]["bag_sha256"] and len(doc["provenance"]["bag_sha256"]) == 64
    assert doc["provenance"]["t_max"] == 0.3 and doc["diagnostics"]["dt"] == 0.05
    assert doc["diagnostics"]["step_count"] == 6
    assert set(doc["metrics"]["rms_final"]) == {"markers_xyz", "markers_uv", "wrench", "sheet_points"}
    for name in PLOT_FILES:
        assert (out / name).stat().st_size > 1000, name
    md = (out / "report.md").read_text()
    assert "gel.youngs_modulus" in md and "wrench.png" in md
    assert (out / "report.html").read_text().startswith("<!DOCTYPE html>")
    assert f"report: {out / 'report.html'}" in captured.out
    assert [p.name for p in tmp_path.iterdir()] == ["fit_nominal"]  # no staging directory left behind
    # the replay step and the robust sigma (time correlation + the default nuisance priors) are reported
    assert "replayed at dt = 0.05 s (6 steps)" in captured.out and "(hac+nuisance)" in captured.out
    robust = doc["fit"]["robust"]
    assert robust["method"] == "hac+nuisance" and set(robust["nuisance_prior"]) == {
        "friction.sheet_table", "gel.poisson_ratio", "contact.stiffness"}
    assert doc["fit"]["parameters"]["gel.youngs_modulus"]["sigma_robust"] > 0.0


def test_existing_output_is_refused_without_force_and_replaced_with_it(press_bag, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("old")
    rc = sysid_main([str(press_bag), "--out", str(out), *FAST])
    err = capsys.readouterr().err
    assert rc == 2 and f"output directory {out} exists" in err and "--force" in err
    assert (out / "keep.txt").read_text() == "old"
    rc = sysid_main([str(press_bag), "--out", str(out), "--force", *FAST, "--max-nfev", "3"])
    assert rc == 0
    assert not (out / "keep.txt").exists()
    doc = json.loads((out / "fit.json").read_text())
    p = doc["fit"]["parameters"]["gel.youngs_modulus"]
    assert p["initial"] == 6.0e5 and p["value"] < 6.0e5  # moved toward the true 3e5
    assert sorted(x.name for x in tmp_path.iterdir()) == ["out"]


def test_bad_nuisance_option_is_one_line_naming_it(press_bag, tmp_path, capsys):
    rc = sysid_main([str(press_bag), "--out", str(tmp_path / "o"), "--nuisance", "gel.poisson_ratio"])
    err = capsys.readouterr().err
    assert rc == 2 and "--nuisance: 'gel.poisson_ratio' is not NAME=PRIOR" in err and err.count("\n") == 1
    rc = sysid_main([str(press_bag), "--out", str(tmp_path / "o"), "--nuisance", "gel.poisson_ratio=-1"])
    err = capsys.readouterr().err
    assert rc == 2 and "nuisance prior of gel.poisson_ratio must be a positive number" in err
    assert not (tmp_path / "o").exists()


def test_missing_bag_is_one_line_naming_it(tmp_path, capsys):
    missing = tmp_path / "no_such_bag"
    rc = sysid_main([str(missing), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.strip().count("\n") == 0 and str(missing) in err and "not found" in err
    assert not (tmp_path / "o").exists()


def test_bag_without_markers_fits_remaining_channels_with_warning(tmp_path, capsys):
    bag = make_recording(tmp_path / "bag", segments=PRESS_ONLY[:1], seed=5, skip=("markers",))
    out = tmp_path / "out"
    rc = sysid_main([str(bag), "--out", str(out), *FAST])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert "warning" in err and "tactile/markers" in err
    doc = load_fit_json(out / "fit.json")
    assert doc["diagnostics"]["channels"] == ["wrench", "sheet_points"]
    assert any("markers" in w for w in doc["diagnostics"]["warnings"])
    assert not (out / "marker_field.png").exists() and (out / "wrench.png").exists()


def test_unknown_parameter_is_one_line_error(press_bag, tmp_path, capsys):
    rc = sysid_main([str(press_bag), "--out", str(tmp_path / "o"), "--params", "gel.hardness", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 1 and "gel.hardness" in err and err.strip().count("\n") <= 1
    assert not (tmp_path / "o").exists()


def test_calibrate_flag_calibrates_the_diagnosis_parameters_not_fitted():
    from sim_core.errors import ConfigError
    from sysid.calibration import CALIBRATION_PARAMETERS
    from sysid.cli import build_parser, fit_options

    options = fit_options(build_parser().parse_args(["bag", "--params", "gel.youngs_modulus", "--calibrate",
                                                     "--calibration-time", "60"]))
    assert options.calibration_params == CALIBRATION_PARAMETERS and options.calibration_max_time == 60.0
    assert fit_options(build_parser().parse_args(["bag"])).calibration_params == ()
    with pytest.raises(ConfigError, match="calibration_max_time must be > 0"):
        fit_options(build_parser().parse_args(["bag", "--calibrate", "--calibration-time", "0"]))
    with pytest.raises(ConfigError, match="calibration_max_replays must be >= 1"):
        fit_options(build_parser().parse_args(["bag", "--calibrate", "--calibration-replays", "0"]))


def test_calibrations_are_bounded_by_a_replay_count_not_by_seconds(capsys):
    """``thinshell sysid --calibrate`` and ``thinshell diagnose`` calibrate within the same replay
    count and no wall-time budget by default (the same answer under any load); seconds are opt-in."""
    from sysid.calibration import CALIBRATION_REPLAYS
    from sysid.cli import build_parser, fit_options
    from sysid.diagnose.cli import build_parser as diagnose_parser, signature_settings
    from sysid.diagnose.settings import Settings
    from sysid.diagnose.signature_engine import SignatureSettings

    options = fit_options(build_parser().parse_args(["bag", "--calibrate"]))
    assert options.calibration_max_replays == CALIBRATION_REPLAYS and options.calibration_max_time is None
    settings = signature_settings(diagnose_parser().parse_args(["bag"]))
    assert settings.calibration_max_replays == CALIBRATION_REPLAYS and settings.calibration_max_time is None
    assert settings.plasticity_max_time is None and settings.plasticity_replays >= 1
    for defaults in (SignatureSettings(), Settings()):
        assert defaults.calibration_max_replays == CALIBRATION_REPLAYS and defaults.calibration_max_time is None
    timed = signature_settings(diagnose_parser().parse_args(["bag", "--calibration-time", "30", "--calibration-replays", "9"]))
    assert timed.calibration_max_time == 30.0 and timed.calibration_max_replays == 9
    from sysid.diagnose.cli import diagnose_main

    assert diagnose_main(["no_such_bag", "--calibration-replays", "0"]) == 2
    assert "--calibration-replays must be > 0" in capsys.readouterr().err
    from sysid.calibration_secant import SECANT_REPLAYS

    assert settings.calibration_secant_replays == SECANT_REPLAYS == SignatureSettings().calibration_secant_replays
    assert signature_settings(diagnose_parser().parse_args(["bag", "--calibration-secant-replays", "0"])
                              ).calibration_secant_replays == 0
    assert diagnose_main(["no_such_bag", "--calibration-secant-replays", "-1"]) == 2
    assert "--calibration-secant-replays must be >= 0" in capsys.readouterr().err


def test_diagnose_and_sysid_take_the_drive_by_default():
    """``thinshell diagnose`` (signatures engine) asks the calibration for the arm's drive by default (the data
    then choose it, :func:`sysid.drive_calibration.fit_drive`), replays the recorded pose kinematically with
    ``--no-drive``, and takes a calibration budget that steps through the drive; so does ``thinshell sysid``
    (``FitOptions.drive``; its Jacobian analytic through the drive, tests/sysid/test_sysid_drive.py)."""
    from sysid.cli import build_parser as sysid_parser, fit_options
    from sysid.diagnose.cli import build_parser as diagnose_parser, signature_settings
    from sysid.diagnose.signature_engine import SignatureSettings
    from sysid.fit_recording import FitOptions

    assert SignatureSettings().calibration_drive and FitOptions().drive
    assert signature_settings(diagnose_parser().parse_args(["bag"])).calibration_drive
    assert signature_settings(diagnose_parser().parse_args(["bag", "--drive"])).calibration_drive
    assert not signature_settings(diagnose_parser().parse_args(["bag", "--no-drive"])).calibration_drive
    stepping = signature_settings(diagnose_parser().parse_args(["bag", "--calibration-replays", "4"]))
    assert stepping.calibration_drive and stepping.calibration_max_replays == 4
    assert fit_options(sysid_parser().parse_args(["bag"])).drive
    assert fit_options(sysid_parser().parse_args(["bag", "--drive"])).drive
    assert not fit_options(sysid_parser().parse_args(["bag", "--no-drive"])).drive
    assert "--no-drive" in diagnose_parser().format_help() and "--no-drive" in sysid_parser().format_help()


def test_the_gel_law_reaches_the_fits_replays_and_fit_json_names_it(press_bag, tmp_path, capsys):
    """``--gel-element green_strain`` replays the gel with that law (the press's first replay differs from the scene's
    Stable Neo-Hookean gel's, ``--gel-element scene``) and fit.json's ``diagnostics.gel_law`` names the law of each fit; an unknown law is
    refused naming the choices. (``auto`` end to end: tests/sysid/test_gel_law.py.)"""
    docs = {}
    for law in ("scene", "green_strain"):
        out = tmp_path / law
        rc = sysid_main([str(press_bag), "--out", str(out), *FAST, "--gel-element", law])
        assert rc == 0, capsys.readouterr().err
        docs[law] = load_fit_json(out / "fit.json")
    assert docs["scene"]["diagnostics"]["gel_law"] == {"element": "stable_neohookean", "requested": "scene", "choice": None}
    assert docs["green_strain"]["diagnostics"]["gel_law"] == {"element": "green_strain", "requested": "green_strain",
                                                              "choice": None}
    assert "gel law: green_strain" in capsys.readouterr().out
    first = {k: d["metrics"]["rms_initial"]["wrench"]["rms"] for k, d in docs.items()}
    assert abs(first["green_strain"] / first["scene"] - 1.0) > 0.1, first  # measured 0.80 / 1.06 N
    with pytest.raises(SystemExit):
        sysid_main([str(press_bag), "--gel-element", "mooney"])
    assert "green_strain" in capsys.readouterr().err
