"""``thinshell sysid`` on bags that ``thinshell sim`` wrote from task scenes (``kind: task``): the replay
drives every effector (and gripper) from the recorded streams and fits a global parameter."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import yaml

from sim_core.errors import CalibrationError
from sim_core.scenes import load_scene
from sim_core.simulation import Simulation
from sim_core.solver_config import SolverConfig
from sysid.calibration import calibrate
from sysid.cli import sysid_main
from sysid.evidence import load_evidence
from sysid.observation import ObservationModel, ObservationWarning
from tests.sim_core.scenes.test_task_scene_v2 import v2_scene
from thinshell_ros.headless import sim_main
from thinshell_ros.paths import config_dir

FOLDING = config_dir() / "scenes" / "folding.yaml"
DOME_START = [-0.0144833, 0.0, 0.0212333, 1.0, 0.0, 0.0, 0.0]

RECORDER_STOP = SolverConfig().tol_velocity * 0.005
"""m: how far a recorded step (the simulator's default Newton tolerance, dt 5 ms) may stop from its minimiser."""


def _folding_bag(tmp_path, *extra):
    """Ten 5 ms steps of the Folding scene's dome pressing 2 mm down and 2 mm along x into the strip."""
    traj = tmp_path / "press.yaml"
    end = [DOME_START[0] + 0.002, 0.0, DOME_START[2] - 0.002, 1.0, 0.0, 0.0, 0.0]
    traj.write_text(yaml.safe_dump({"version": 1, "effector": "dome", "waypoints": [
        {"t": 0.0, "pose": DOME_START}, {"t": 0.05, "pose": end}]}))
    bag = tmp_path / "bag"
    assert sim_main(["--scene", str(FOLDING), "--trajectory", str(traj), "--out", str(bag), *extra]) == 0
    return bag


def test_sysid_recovers_the_bending_stiffness_of_a_folding_bag(tmp_path, capsys):
    bag = _folding_bag(tmp_path)
    off = yaml.safe_load(FOLDING.read_text())
    off["sheets"]["sheet"]["bending"]["k_bend_thinshelllab"] = 250.0   # 2.5x the recorded 100
    start = tmp_path / "off.yaml"
    start.write_text(yaml.safe_dump(off, sort_keys=False))
    out = tmp_path / "fit"
    rc = sysid_main([str(bag), "--scene", str(start), "--params", "sheet.bending_stiffness", "--dt", "0.005",
                     "--arch", "numpy", "--out", str(out), "--quiet", "--write-scene", str(tmp_path / "fitted.yaml")])
    assert rc == 0
    err = capsys.readouterr().err
    assert err.count("has no tactile sensor") == 1                      # said once
    fitted = json.loads((out / "fit.json").read_text())["fit"]["parameters"]["sheet.bending_stiffness"]
    true_k = Simulation.from_scene(FOLDING).get_parameter("sheet.bending_stiffness")   # k_bend 100 of the bag
    assert fitted["initial"] == pytest.approx(2.5 * true_k, rel=1e-9)
    assert fitted["sigma"] is not None and 0.0 < fitted["sigma"] < 0.01 * true_k
    value = fitted["value"]
    assert abs(value / true_k - 1.0) < 0.02                            # from 2.5x off to within 2 %
    # the fitted task scene: the start scene with D in sheets.sheet.bending; it loads, reads back the fitted
    # value and replays the bag with the fit's final RMS
    doc = yaml.safe_load((tmp_path / "fitted.yaml").read_text())
    assert doc["kind"] == "task" and doc["sheets"]["sheet"]["bending"] == {"bending_stiffness": value}
    assert doc["fitted"]["params"] == {"sheet.bending_stiffness": value} and doc["fitted"]["sigma"]["sheet.bending_stiffness"] > 0
    assert doc["friction"] == off["friction"]
    assert {k: float(v) for k, v in doc["effectors"]["dome"]["material"].items()} == {
        k: float(v) for k, v in off["effectors"]["dome"]["material"].items()}
    assert load_scene(tmp_path / "fitted.yaml").get_parameter("sheet.bending_stiffness") == value
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ObservationWarning)
        replay = ObservationModel(load_evidence(bag), scene=tmp_path / "fitted.yaml", dt=0.005, arch="numpy")
    rms = replay.channel_rms(replay.predict(replay.simulate({})))["sheet_points"]["rms"]
    metrics = json.loads((out / "fit.json").read_text())["metrics"]
    assert rms == pytest.approx(metrics["rms_final"]["sheet_points"]["rms"], rel=0.02)
    assert rms < 0.05 * metrics["rms_initial"]["sheet_points"]["rms"]   # the start scene's RMS


def test_task_replay_reproduces_the_recording_and_rejects_tactile_channels(tmp_path):
    bag = _folding_bag(tmp_path, "--rate", "100")   # outputs every other step; commands every step
    with pytest.warns(ObservationWarning, match="no tactile sensor"):
        model = ObservationModel(load_evidence(bag), dt=0.005)
    assert model.channels == ("sheet_points",) and model.sensor is None
    assert model.data("sheet_points").shape == (6, 64, 3) and model.step_count == 10
    trace = model.simulate({})
    rms = model.channel_rms(model.predict(trace))["sheet_points"]["rms"]
    # the same scene and commands give the recorded points, to the recorder's stopping error: its steps stop within
    # tol_velocity * dt of their minimisers, the replay's are solved to sysid.observation.REPLAY_TOL_VELOCITY
    assert rms < RECORDER_STOP
    with pytest.raises(CalibrationError, match="no tactile sensor; channels wrench cannot be fitted"):
        ObservationModel(load_evidence(bag), dt=0.005, channels=["sheet_points", "wrench"])
    with pytest.raises(CalibrationError, match="no tactile sensor, so there is no sensor calibration"):
        calibrate(model)                                   # thinshell diagnose: one clear line, no KeyError


def test_gripper_cmd_and_every_effector_are_replayed_and_a_missing_effector_is_named(tmp_path):
    scene = tmp_path / "scene.yaml"
    scene.write_text(yaml.safe_dump(v2_scene(), sort_keys=False))
    traj = tmp_path / "traj.yaml"
    traj.write_text("version: 1\neffector: grip\nwaypoints:\n"
                    "  - {t: 0.0, pose: [0.0, 0.0, 0.02, 0, 0, 0, 1], gripper: 0.012}\n"
                    "  - {t: 0.015, pose: [0.0, 0.0, 0.018, 0, 0, 0, 1], gripper: 0.009}\n")
    bag = tmp_path / "bag"
    assert sim_main(["--scene", str(scene), "--trajectory", str(traj), "--out", str(bag)]) == 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ObservationWarning)
        model = ObservationModel(load_evidence(bag), dt=0.005)
    last = model.control(model.step_count)
    assert abs(last.gripper_target["grip"] - 0.009) < 1e-12
    assert abs(last.effector_pose_target["grip"][2] - 0.018) < 1e-12
    trace = model.simulate({})
    assert np.sqrt(np.mean((model.predict(trace)["sheet_points"] - model.data("sheet_points")) ** 2)) < RECORDER_STOP
    doc = v2_scene()
    doc["effectors"]["spare"] = dict(doc["effectors"]["grip"], initial_pose=[0.05, 0.0, 0.02, 0.0, 0.0, 0.0, 1.0])
    other = tmp_path / "other.yaml"
    other.write_text(yaml.safe_dump(doc, sort_keys=False))
    with pytest.raises(CalibrationError, match=r"effector 'spare' of .*other.yaml has no recorded pose or pose_cmd"):
        ObservationModel(load_evidence(bag, scene_path=other), scene=other, dt=0.005)


def test_a_sheet_of_another_name_is_tracked_and_fitted(tmp_path, capsys):
    doc = v2_scene()
    doc["sheets"] = {"cloth": doc["sheets"].pop("sheet")}  # no body named sheet: every sheet body is tracked
    doc["friction"] = [{"pair": ["grip", "cube"], "mu": 1.0}, {"pair": ["table", "cloth"], "mu": 0.5}]
    scene = tmp_path / "scene.yaml"
    scene.write_text(yaml.safe_dump(doc, sort_keys=False))
    bag = tmp_path / "bag"
    traj = tmp_path / "traj.yaml"
    traj.write_text("version: 1\neffector: grip\nwaypoints:\n  - {t: 0.0, pose: [0.0, 0.0, 0.02, 0, 0, 0, 1]}\n"
                    "  - {t: 0.01, pose: [0.0, 0.0, 0.019, 0, 0, 0, 1]}\n")
    assert sim_main(["--scene", str(scene), "--trajectory", str(traj), "--out", str(bag)]) == 0
    rc = sysid_main([str(bag), "--params", "cloth.bending_stiffness", "--dt", "0.005", "--arch", "numpy",
                     "--out", str(tmp_path / "fit"), "--quiet"])
    assert rc == 0, capsys.readouterr().err
    assert (tmp_path / "fit" / "fit.json").is_file()
