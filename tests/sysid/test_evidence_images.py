"""Marker pixels read off a recorded image stream (``<sensor>/image``) when a bag has no markers topic:
OpenCV blob detection on the first frame, tracking in the fixed marker order afterwards."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.errors import CalibrationError
from sim_core.sensors.camera import PinholeCamera
from sim_core.sensors.image import render_marker_image
from sim_core.sensors.markers import marker_grid
from sysid.bagio import BagWarning, BagWriter
from sysid.evidence import load_evidence
from sysid.markers_image import track_marker_stream
from sysid.observation import ObservationModel
from tests.sysid.conftest import NS, synthetic_streams

GRID = (9, 7)
PITCH = 0.002


def _scene(scene_dict: dict) -> dict:
    scene_dict["sensors"]["tactile"]["marker_grid"] = list(GRID)
    scene_dict["sensors"]["tactile"]["marker_pitch"] = PITCH
    return scene_dict


def _camera(scene: dict) -> PinholeCamera:
    return PinholeCamera(**scene["sensors"]["tactile"]["camera"])


def _truth(n: int, camera: PinholeCamera) -> np.ndarray:
    """Marker pixels of a press that spreads the grid and slides it 1.5 px per frame, ``(n, 63, 2)``."""
    rest = camera.project(marker_grid(GRID, PITCH))
    centre = np.array([camera.cx, camera.cy])
    frames = []
    for f in range(n):
        spread = 1.0 + 0.002 * f
        frames.append(centre + spread * (rest - centre) + np.array([1.5 * f, -0.4 * f]))
    return np.array(frames)


def _write(path, scene: dict, uv: np.ndarray, lose: tuple[int, int] | None = None) -> None:
    """A bag with poses, wrench and the rendered images of ``uv``; no markers topic."""
    streams = synthetic_streams(uv.shape[0])
    camera = _camera(scene)
    with BagWriter(path, scene=scene) as bag:
        for i, t in enumerate(streams["t_ns"]):
            t = int(t)
            bag.write_pose(f"{NS}/ee/pose", t, streams["pose"][i], "world")
            bag.write_pose(f"{NS}/ee/pose_cmd", t, streams["pose"][i], "world")
            bag.write_wrench(f"{NS}/tactile/wrench", t, streams["wrench"][i], "tactile")
            drawn = uv[i].copy()
            if lose is not None and i == lose[0]:
                drawn[lose[1]] = np.nan  # occluded in this frame
            image = render_marker_image(drawn, camera, marker_radius_px=4.8, blur=0.7, shading=0.2)
            bag.write_image(f"{NS}/tactile/image", t, image, "tactile")
            bag.write_clock(t)


def test_markers_are_read_off_the_images_when_the_bag_has_no_markers_topic(tmp_path, scene_dict):
    scene = _scene(scene_dict)
    truth = _truth(12, _camera(scene))
    _write(tmp_path / "bag", scene, truth)
    ev = load_evidence(tmp_path / "bag", include_image="auto")
    assert "markers_uv" in ev.channels_present and "markers_xyz" not in ev.channels_present
    assert ev.markers_uv.shape == truth.shape
    assert np.max(np.linalg.norm(ev.markers_uv - truth, axis=2)) < 0.2  # px, fixed order kept
    np.testing.assert_array_equal(ev.markers_uv_weight, np.ones(truth.shape[:2]))  # every marker whole
    np.testing.assert_array_equal(ev.t_ns["markers_uv"], ev.t_ns["image"])
    assert ev.source.topics["markers_uv"] == f"{NS}/tactile/image"
    assert np.all(np.isfinite(ev.noise["markers_uv"]))
    assert any("markers_uv decoded from 12 images (9x7 grid of sensor tactile)" in n for n in ev.notes)
    # the fit picks the pixels when there are no 3-D markers
    model = ObservationModel(ev, dt=0.01)
    assert "markers_uv" in model.channels
    # without decoding the images the channel is missing, and the reason says so
    plain = load_evidence(tmp_path / "bag", include_image=False)
    assert "markers_uv" not in plain.channels_present
    assert "not decoded" in plain.channels_missing["image"]


def test_a_frame_with_an_unseen_marker_is_kept_with_the_marker_interpolated_at_weight_zero(tmp_path, scene_dict):
    scene = _scene(scene_dict)
    truth = _truth(10, _camera(scene))
    _write(tmp_path / "bag", scene, truth, lose=(4, 30))
    ev = load_evidence(tmp_path / "bag", include_image="auto")
    assert ev.markers_uv.shape == truth.shape and ev.markers_uv_weight.shape == truth.shape[:2]
    # the occluded marker is interpolated from its lattice neighbours (the press is affine: near exact)
    assert np.max(np.linalg.norm(ev.markers_uv - truth, axis=2)) < 0.2
    assert ev.markers_uv_weight[4, 30] == 0.0
    weight = ev.markers_uv_weight
    assert np.count_nonzero(weight == 0.0) == 1 and np.all(weight[weight > 0.0] == 1.0)
    assert any("1 interpolated marker positions with weight 0" in n for n in ev.notes)


def test_images_without_the_expected_grid_give_a_warning_naming_the_topic(tmp_path, scene_dict):
    scene = _scene(scene_dict)
    truth = _truth(6, _camera(scene))
    scene["sensors"]["tactile"]["marker_grid"] = [8, 7]  # the scene disagrees with the images
    _write(tmp_path / "bag", scene, truth)
    with pytest.warns(BagWarning, match=f"topic {NS}/tactile/image: no markers decoded from the images"):
        ev = load_evidence(tmp_path / "bag", include_image="auto")
    assert "markers_uv" not in ev.channels_present
    assert "wrench" in ev.channels_present


def test_track_marker_stream_rejects_empty_input():
    with pytest.raises(CalibrationError, match="need frames"):
        track_marker_stream(np.zeros((0, 10, 10), np.uint8), GRID)
    with pytest.raises(CalibrationError, match="gate_fraction"):
        track_marker_stream(np.zeros((1, 10, 10), np.uint8), GRID, gate_fraction=0.9)


def test_simulated_image_stream_gives_the_simulated_marker_pixels(tmp_path):
    """End to end: the simulator renders its tactile images into a bag (``thinshell sim --image``);
    read with the markers topic hidden, the pixels decoded from the images match the markers topic."""
    from thinshell_ros.headless import sim_main

    bag = tmp_path / "bag"
    assert sim_main(["--out", str(bag), "--image", "--duration", "0.4", "--rate", "50",
                     "--depth", "0.0008", "--slide", "0.004"]) == 0
    topic = load_evidence(bag, include_image=False)
    with pytest.warns(BagWarning, match="role markers"):
        images = load_evidence(bag, roles={"markers": "tactile/hidden_markers"}, include_image="auto")
    assert "markers_xyz" not in images.channels_present
    np.testing.assert_array_equal(images.t_ns["markers_uv"], topic.t_ns["markers_uv"])
    err = np.linalg.norm(images.markers_uv - topic.markers_uv, axis=2)
    moved = np.linalg.norm(topic.markers_uv - topic.markers_uv[0], axis=2)
    assert moved.max() > 1.0  # the press and slide move the markers by pixels
    assert err.max() < 0.3, f"decoded markers off by {err.max():.3f} px"
