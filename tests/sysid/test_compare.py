"""``thinshell compare`` on the bundled recording: RMS per channel, which scene predicts it better, outputs."""

from __future__ import annotations

import json

import yaml

from tests.thinshell_ros.conftest import REPO
from thinshell_ros.cli import main as thinshell_main

FAST = ["--t-max", "0.9", "--dt", "0.05", "--gel-resolution", "5,4,2", "--arch", "numpy"]


def test_compare_ranks_the_true_scene_first_and_writes_the_report(tmp_path, capsys):
    bag = REPO / "bags" / "nominal_s101"  # the bundled recording (contact from 0.7 s)
    doc = yaml.safe_load((bag / "scene.yaml").read_text())
    doc["sensors"]["tactile"]["gel_material"]["youngs_modulus"] *= 3.0  # a wrong gel: stiffer contact
    wrong = tmp_path / "wrong.yaml"
    wrong.write_text(yaml.safe_dump(doc))
    out = tmp_path / "cmp"
    rc = thinshell_main(["compare", str(bag), "--scene", str(wrong), "--out", str(out), *FAST])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    result = json.loads((out / "compare.json").read_text())
    assert set(result["rms"]) == {"scene", "nominal"} and result["scenes"]["nominal"] is None
    channels = {"markers_xyz", "markers_uv", "wrench", "sheet_points"}
    assert set(result["rms"]["scene"]) == channels
    # the recording was made with the bag's scene: the 3x stiffer gel predicts the contact force worse
    # (measured: 2.5 N vs 0.56 N RMS with this coarse gel and step)
    assert result["better"]["wrench"] == "nominal"
    assert result["rms"]["scene"]["wrench"]["rms"] > 3.0 * result["rms"]["nominal"]["wrench"]["rms"]
    for name in ("wrench.png", "markers.png", "sheet_points.png"):
        assert (out / name).stat().st_size > 5000, name
    md = (out / "report.md").read_text()
    assert "| wrench | N |" in md and "![wrench](wrench.png)" in md
    assert (out / "report.html").read_text().startswith("<!DOCTYPE html>")
    assert "scene predicts the recording better than nominal on" in captured.out and "| wrench |" not in captured.out
    # refused without --force; the same scene twice ties
    assert thinshell_main(["compare", str(bag), "--scene", str(wrong), "--out", str(out), *FAST]) == 2
    assert "exists (use --force" in capsys.readouterr().err
    assert thinshell_main(["compare", str(bag), "--scene", str(bag / "scene.yaml"), "--out", str(out), "--force",
                           *FAST]) == 0
    assert set(json.loads((out / "compare.json").read_text())["better"].values()) == {"tie"}


def test_compare_errors_are_one_line(tmp_path, capsys):
    assert thinshell_main(["compare", str(tmp_path / "nope"), "--scene", "x.yaml", "--out", str(tmp_path / "o")]) == 2
    assert "not found" in capsys.readouterr().err
    bag = REPO / "bags" / "nominal_s101"  # the bundled recording (contact from 0.7 s)
    bad = tmp_path / "bad.yaml"
    bad.write_text("version: 1\nname: x\n")
    assert thinshell_main(["compare", str(bag), "--scene", str(bad), "--out", str(tmp_path / "o"), *FAST]) == 1
    assert "error" in capsys.readouterr().err and not (tmp_path / "o").exists()
