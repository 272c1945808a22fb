"""The trajectory file (sim_core.trajectory_file): round trip, interpolation and every refusal."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from sim_core.errors import ConfigError
from sim_core.trajectory_file import (Trajectory, interpolate_pose, read_trajectory, trajectory_to_document,
                                      write_trajectory)

DOWN = [1.0, 0.0, 0.0, 0.0]  # 180 deg about x: the sensor faces down


def _traj() -> Trajectory:
    t = np.array([0.0, 0.25, 0.5])
    q90 = [0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4)]
    poses = np.array([[0.06, 0.0, 0.004, *DOWN], [0.061, 0.001, 0.003, *DOWN], [0.07, 0.0, 0.003, *q90]])
    return Trajectory(t=t, poses={"ee": poses, "ee2": poses + [0.1, 0, 0, 0, 0, 0, 0]},
                      gripper={"ee": np.array([0.02, 0.015, 0.01])},
                      scene_path="config/scenes/forming.yaml", scene_name="forming",
                      parameters={"sheet.youngs_modulus": 2.0e5, "friction.gel_sheet": 0.45},
                      prediction={"reward": 0.8125, "wrench_peak_N": None, "curve": [1.0, 2.5]},
                      provenance={"tool": "test", "created": "2026-11-25T06:00:00+00:00", "git": "abc", "seed": 3})


def _doc() -> dict:
    return trajectory_to_document(_traj())


def _write_doc(tmp_path, doc) -> str:
    p = tmp_path / "traj.yaml"
    p.write_text(yaml.safe_dump(doc, sort_keys=False))
    return str(p)


def test_round_trip_is_exact(tmp_path):
    traj = _traj()
    path = write_trajectory(tmp_path / "out" / "trajectory.yaml", traj)
    back = read_trajectory(path)
    np.testing.assert_array_equal(back.t, traj.t)
    assert back.effectors == ["ee", "ee2"]
    for e in traj.poses:
        np.testing.assert_array_equal(back.poses[e], traj.poses[e])
    np.testing.assert_array_equal(back.gripper["ee"], traj.gripper["ee"])
    assert "ee2" not in back.gripper
    assert back.scene_path == traj.scene_path and back.scene_name == "forming"
    assert back.parameters == traj.parameters
    assert back.prediction == traj.prediction and back.provenance == traj.provenance
    assert not list(path.parent.glob(".*.tmp")), "the temporary file of the atomic write is left behind"


def test_refuses_overwrite_without_force(tmp_path):
    path = write_trajectory(tmp_path / "t.yaml", _traj())
    with pytest.raises(ConfigError, match="exists; pass force"):
        write_trajectory(path, _traj())
    traj = _traj()
    traj.t = traj.t * 2
    write_trajectory(path, traj, force=True)
    assert read_trajectory(path).duration == pytest.approx(1.0)


def test_write_refuses_invalid_and_writes_nothing(tmp_path):
    traj = _traj()
    traj.poses["ee"][1, 2] = np.nan
    with pytest.raises(ConfigError, match=r"waypoint 1 \(t=0.25 s\), effector 'ee': pose has non-finite"):
        write_trajectory(tmp_path / "t.yaml", traj)
    assert not (tmp_path / "t.yaml").exists()


def test_sampling_interpolates_position_and_slerps_orientation():
    traj = _traj()
    mid = traj.sample_pose("ee", 0.375)
    np.testing.assert_allclose(mid[:3], [0.0655, 0.0005, 0.003])
    # halfway from 180 deg about x to 90 deg about z: the rotation angle to each end is equal
    q0, q1 = traj.poses["ee"][1, 3:], traj.poses["ee"][2, 3:]
    assert abs(np.dot(mid[3:], q0)) == pytest.approx(abs(np.dot(mid[3:], q1)), abs=1e-12)
    assert np.linalg.norm(mid[3:]) == pytest.approx(1.0)
    np.testing.assert_array_equal(traj.sample_pose("ee", -1.0), traj.poses["ee"][0])
    np.testing.assert_array_equal(traj.sample_pose("ee", 9.0), traj.poses["ee"][-1])
    assert traj.sample_gripper("ee", 0.125) == pytest.approx(0.0175)
    assert traj.sample_gripper("ee2", 0.125) is None
    np.testing.assert_allclose(interpolate_pose(traj.poses["ee"][0], traj.poses["ee"][1], 1.0), traj.poses["ee"][1])


def test_quaternion_normalised_on_reading(tmp_path):
    doc = _doc()
    doc["waypoints"][0]["poses"]["ee"][3] = 1.0005
    back = read_trajectory(_write_doc(tmp_path, doc))
    assert np.linalg.norm(back.poses["ee"][0, 3:]) == pytest.approx(1.0, abs=1e-15)


def _mutate(doc, key):
    wp = doc["waypoints"]
    if key == "nan":
        wp[1]["poses"]["ee"][0] = float("nan")
    elif key == "inf_t":
        wp[2]["t"] = float("inf")
    elif key == "non_monotonic":
        wp[2]["t"] = 0.25
    elif key == "negative_t":
        wp[0]["t"] = -0.1
    elif key == "zero_quat":
        wp[2]["poses"]["ee2"][3:] = [0.0, 0.0, 0.0, 0.0]
    elif key == "short_pose":
        wp[1]["poses"]["ee"] = [0.0, 0.0, 0.0]
    elif key == "missing_effector":
        del wp[2]["poses"]["ee2"]
    elif key == "gripper_negative":
        wp[1]["gripper"]["ee"] = -0.01
    elif key == "gripper_missing":
        del wp[2]["gripper"]
    elif key == "string_t":
        wp[1]["t"] = "soon"
    elif key == "unknown_wp_key":
        wp[1]["speed"] = 1.0
    return doc


@pytest.mark.parametrize("key, match", [
    ("nan", r"waypoint 1 \(t=0.25 s\), effector 'ee': pose has non-finite"),
    ("inf_t", r"waypoint 2: time t=inf is not finite"),
    ("non_monotonic", r"waypoint 2: time t=0.25 s is not after waypoint 1's t=0.25 s"),
    ("negative_t", r"waypoint 0: time t=-0.1 s is negative"),
    ("zero_quat", r"waypoint 2 \(t=0.5 s\), effector 'ee2': quaternion .* has norm 0"),
    ("short_pose", r"waypoint 1 \(t=0.25\), effector 'ee': pose must be a list of 7"),
    ("missing_effector", r"waypoint 2 \(t=0.5\): poses must give exactly the effectors"),
    ("gripper_negative", r"waypoint 1 \(t=0.25 s\), effector 'ee': gripper opening -0.01 m"),
    ("gripper_missing", r"waypoint 2: gripper missing"),
    ("string_t", r"waypoint 1: t must be a number"),
    ("unknown_wp_key", r"waypoint 1 must be a mapping with keys t, poses"),
])
def test_bad_waypoints_are_named(tmp_path, key, match):
    path = _write_doc(tmp_path, _mutate(_doc(), key))
    with pytest.raises(ConfigError, match=match) as info:
        read_trajectory(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize("edit, match", [
    (lambda d: d.update(format="other"), "'format' must be 'thinshell-trajectory'"),
    (lambda d: d.update(version=2), "unsupported version 2"),
    (lambda d: d.update(frame="base_link"), "frame must be 'world'"),
    (lambda d: d.update(speed=3), r"unknown keys \['speed'\]"),
    (lambda d: d.pop("waypoints"), r"missing keys \['waypoints'\]"),
    (lambda d: d.update(waypoints=[]), "'waypoints' must be a non-empty list"),
    (lambda d: d.update(effectors=["ee", "ee"]), "distinct names"),
    (lambda d: d["scene"]["parameters"].update({"sheet.youngs_modulus": "big"}), "scene.parameters.sheet.youngs_modulus must be a number"),
    (lambda d: d["prediction"].update(reward="good"), "prediction.reward must be a number"),
    (lambda d: d["scene"].update(mesh="x"), "'scene' must be a mapping with keys"),
])
def test_bad_documents_are_refused(tmp_path, edit, match):
    doc = _doc()
    edit(doc)
    with pytest.raises(ConfigError, match=match):
        read_trajectory(_write_doc(tmp_path, doc))


def test_missing_and_invalid_yaml(tmp_path):
    with pytest.raises(ConfigError, match="trajectory file not found"):
        read_trajectory(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("format: [unclosed\n")
    with pytest.raises(ConfigError, match="invalid YAML"):
        read_trajectory(bad)
