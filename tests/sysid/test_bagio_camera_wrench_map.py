"""A recording map's camera_info distortion (radial k1 k2 into the replay's camera) and its wrench sign
(an F/T sensor that reports the reaction), on a small contract bag read through a map."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest
import yaml

from sim_core.errors import BagReadError, ConfigError
from sim_core.scenes import load_scene
from sysid.bagio import BagWarning, BagWriter, codec
from sysid.bagio.recording_map import parse_recording_map
from sysid.evidence import load_evidence
from sysid.observation import scene_dict_for
from tests.sysid.conftest import NS, synthetic_streams, write_synthetic

INFO_TOPIC = "/gelsight/camera_info"
WRENCH_TOPIC = "/ft_sensor/wrench"
OFFSET = np.array([1.5, -0.7, 2.1, 0.02, -0.01, 0.005])
"""An F/T sensor's offset (N, N m) in its message's own sign."""


def _camera_info(cam: dict, model: str, d) -> object:
    ts = codec.typestore().types
    header = codec.pose_stamped(0, np.r_[0, 0, 0, 0, 0, 0, 1.0], "gel_camera").header
    k = np.array([cam["fx"], 0, cam["cx"], 0, cam["fy"], cam["cy"], 0, 0, 1], dtype=np.float64)
    p = np.array([cam["fx"], 0, cam["cx"], 0, 0, cam["fy"], cam["cy"], 0, 0, 0, 1, 0], dtype=np.float64)
    return ts["sensor_msgs/msg/CameraInfo"](
        header=header, height=cam["height"], width=cam["width"], distortion_model=model,
        d=np.asarray(d, dtype=np.float64), k=k, r=np.eye(3).reshape(-1), p=p, binning_x=0, binning_y=0,
        roi=ts["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


def _map(wrench: dict | None = None) -> dict:
    """A map of the contract topics (the world is the base frame, the wrench in the sensor frame), a camera_info."""
    return {
        "version": 1,
        "frames": {"base": "world", "world_in_base": [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], "sensor": "tactile"},
        "pose": {"topic": f"{NS}/ee/pose"},
        "markers": {"topic": f"{NS}/tactile/markers"},
        "camera_info": {"topic": INFO_TOPIC},
        "wrench": {"topic": WRENCH_TOPIC, "frame": "tactile", **(wrench or {})},
    }


def _bag(tmp_path, scene: dict, model: str = "plumb_bob", d=(0.0,) * 5, wrench_sign: float = 1.0,
         offset: np.ndarray | None = None, **map_wrench):
    """The synthetic contract bag, plus a camera_info and the wrench as an F/T sensor reports it (``wrench_sign``
    times the contract's, plus ``offset``), read through a map; returns ``(path of the bag, its streams)``."""
    streams = synthetic_streams(12)
    path = write_synthetic(tmp_path / "bag", streams, scene=scene, skip=("sheet_points",))
    out = tmp_path / "cell"
    with BagWriter(out, scene=scene) as bag:
        for i, t in enumerate(streams["t_ns"]):
            t = int(t)
            if i == 0:
                bag.write_message(INFO_TOPIC, "sensor_msgs/msg/CameraInfo", t, _camera_info(
                    scene["sensors"]["tactile"]["camera"], model, d))
            bag.write_pose(f"{NS}/ee/pose", t, streams["pose"][i], "world")
            bag.write_points(f"{NS}/tactile/markers", t, streams["markers"][i], "tactile",
                             extra_fields={"u": streams["uv"][i, :, 0], "v": streams["uv"][i, :, 1]})
            raw = wrench_sign * streams["wrench"][i] + (0.0 if offset is None else offset)
            bag.write_wrench(WRENCH_TOPIC, t, raw, "tactile")
    (tmp_path / "map.yaml").write_text(yaml.safe_dump(_map(map_wrench or None)))
    return path, out, tmp_path / "map.yaml", streams


def _evidence(path, rmap=None):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_evidence(path, recording_map=rmap, include_image=False)


# ------------------------------------------------------------------------------------ camera_info
def test_camera_info_radial_distortion_reaches_the_replay_camera_as_opencv_projects_it(tmp_path, scene_dict):
    k1, k2 = -0.21, 0.047
    _, cell, rmap, _ = _bag(tmp_path, scene_dict, d=(k1, k2, 0.0, 0.0, 0.0))
    ev = _evidence(cell, rmap)
    cam = ev.scene.sensors["tactile"].camera
    assert (cam.k1, cam.k2) == (k1, k2)
    camera = load_scene(scene_dict_for(ev)).sensors["tactile"].camera  # what the replay projects through
    assert (camera.k1, camera.k2) == (k1, k2)
    # the same pixels as OpenCV's plumb_bob model with D = [k1 k2 0 0 0] (camera centre at z = -d)
    rng = np.random.default_rng(1)
    points = np.c_[rng.uniform(-0.008, 0.008, (20, 2)), rng.uniform(-0.001, 0.0, 20)]
    K = np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1.0]])
    uv_cv, _ = cv2.projectPoints(points + [0.0, 0.0, camera.distance], np.zeros(3), np.zeros(3), K,
                                 np.array([k1, k2, 0.0, 0.0, 0.0]))
    np.testing.assert_allclose(camera.project(points), uv_cv.reshape(-1, 2), rtol=0, atol=1e-9)
    pinhole = load_scene(scene_dict).sensors["tactile"].camera  # the scene's own: no distortion
    assert np.max(np.abs(camera.project(points) - pinhole.project(points))) > 1.0


def test_tangential_and_higher_terms_are_left_out_with_a_warning_giving_their_pixels(tmp_path, scene_dict):
    d = (-0.1, 0.02, 0.0012, -0.0008, 0.004)
    _, cell, rmap, _ = _bag(tmp_path, scene_dict, d=d)
    with pytest.warns(BagWarning, match=rf"topic {INFO_TOPIC}: distortion terms p1=0.0012, p2=-0.0008, k3=0.004 "
                                        r"are not in the camera model .* up to (\S+) px") as got:
        ev = load_evidence(cell, recording_map=rmap, include_image=False)
    assert (ev.scene.sensors["tactile"].camera.k1, ev.scene.sensors["tactile"].camera.k2) == d[:2]
    # the pixels named are OpenCV's full model minus its k1 k2 part at the worst image corner
    cam = scene_dict["sensors"]["tactile"]["camera"]
    K = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1.0]])
    corners = np.array([[0, 0], [cam["width"] - 1, 0], [0, cam["height"] - 1], [cam["width"] - 1, cam["height"] - 1]])
    rays = np.c_[(corners - [cam["cx"], cam["cy"]]) / [cam["fx"], cam["fy"]], np.ones(4)]
    full, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, np.array(d))
    radial, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, np.array([*d[:2], 0.0, 0.0, 0.0]))
    expected = np.max(np.linalg.norm(full.reshape(-1, 2) - radial.reshape(-1, 2), axis=1))
    message = next(str(w.message) for w in got if INFO_TOPIC in str(w.message))
    assert float(message.rsplit("up to ", 1)[1].split(" px")[0]) == pytest.approx(expected, rel=1e-3)
    assert any("k3=0.004" in n for n in ev.notes)


def test_a_zero_distortion_leaves_a_scene_without_k1_as_it_was(tmp_path, scene_dict):
    _, cell, rmap, _ = _bag(tmp_path, scene_dict)
    cam = _evidence(cell, rmap).scene.sensors["tactile"].camera
    assert cam.k1 is None and cam.k2 is None  # 0 and none both mean no distortion


def test_a_fisheye_distortion_is_one_error_naming_the_topic_and_the_model(tmp_path, scene_dict):
    _, cell, rmap, _ = _bag(tmp_path, scene_dict, model="equidistant", d=(0.1, 0.01, 0.0, 0.0))
    with pytest.raises(BagReadError, match=rf"topic {INFO_TOPIC}: camera_info distortion_model 'equidistant' .* is "
                                           "not supported"):
        _evidence(cell, rmap)


# ------------------------------------------------------------------------------------ wrench sign
def test_a_sensor_reporting_the_reaction_gives_the_contract_wrench_with_sign_on_environment(tmp_path, scene_dict):
    plain, cell, rmap, streams = _bag(tmp_path, scene_dict, wrench_sign=-1.0, offset=OFFSET,
                                      sign="on_environment", tare={"offset": [float(v) for v in OFFSET]})
    contract = _evidence(plain)
    mapped = _evidence(cell, rmap)
    np.testing.assert_array_equal(mapped.t_ns["wrench"], contract.t_ns["wrench"])
    np.testing.assert_allclose(mapped.wrench, contract.wrench, rtol=0, atol=1e-12)
    np.testing.assert_allclose(mapped.wrench, streams["wrench"], rtol=0, atol=1e-12)
    # read as the contract's sign (the default, on_gel), the same bag gives the opposite wrench
    (tmp_path / "on_gel.yaml").write_text(yaml.safe_dump(_map({"tare": {"offset": [float(v) for v in OFFSET]}})))
    np.testing.assert_allclose(_evidence(cell, tmp_path / "on_gel.yaml").wrench, -streams["wrench"], rtol=0,
                               atol=1e-12)


def test_wrench_sign_takes_on_gel_or_on_environment_only():
    rmap = _map({"sign": "on_environment"})
    assert parse_recording_map(rmap, "m.yaml").wrench.sign == "on_environment"
    assert parse_recording_map(_map(), "m.yaml").wrench.sign == "on_gel"
    with pytest.raises(ConfigError, match="m.yaml: wrench.sign must be one of on_gel, on_environment, got 'reaction'"):
        parse_recording_map(_map({"sign": "reaction"}), "m.yaml")
