"""Rendered mono8 marker image: levels, sub-pixel placement, clipping, errors."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.errors import ConfigError
from sim_core.sensors.camera import PinholeCamera
from sim_core.sensors.image import render_marker_image

CAM = PinholeCamera(fx=300, fy=300, cx=40, cy=30, width=80, height=60, distance=0.025)


def _centroid(image: np.ndarray, background: float) -> np.ndarray:
    w = background - image.astype(float)
    vv, uu = np.mgrid[: image.shape[0], : image.shape[1]]
    return np.array([(w * uu).sum(), (w * vv).sum()]) / w.sum()


def test_levels_shape_and_dtype() -> None:
    img = render_marker_image(np.array([[20.0, 30.0]]), CAM, marker_radius_px=5.0, background=200, marker_value=40)
    assert img.shape == (60, 80) and img.dtype == np.uint8
    assert img[30, 20] == 40 and img[0, 0] == 200 and img[30, 60] == 200
    # the dark area is the disc area (pi r^2) in pixel units
    coverage = (200.0 - img.astype(float)).sum() / 160.0
    assert coverage == pytest.approx(np.pi * 25.0, rel=0.01)


def test_subpixel_marker_centres() -> None:
    rng = np.random.default_rng(0)
    for _ in range(10):
        c = rng.uniform(25, 35, size=2)
        img = render_marker_image(c[None], CAM, marker_radius_px=4.3, background=200, marker_value=40)
        assert np.linalg.norm(_centroid(img, 200.0) - c) < 0.02


def test_markers_outside_the_frame_are_clipped_and_nan_skipped() -> None:
    uv = np.array([[-3.0, 30.0], [500.0, 30.0], [np.nan, 10.0], [-1e9, 1e9]])
    img = render_marker_image(uv, CAM, marker_radius_px=5.0, background=200, marker_value=40)
    assert img[30, 0] == 40  # the left marker is half visible
    assert img[:, 5:].min() == 200


def test_shading_and_blur() -> None:
    img = render_marker_image(np.zeros((0, 2)), CAM, background=200, shading=0.3)
    assert img[30, 40] == 200 and img[0, 0] == pytest.approx(140, abs=1)
    sharp = render_marker_image(np.array([[40.0, 30.0]]), CAM, marker_radius_px=5.0)
    soft = render_marker_image(np.array([[40.0, 30.0]]), CAM, marker_radius_px=5.0, blur=1.5)
    assert sharp[30, 40] == 40 and abs(int(soft[30, 40]) - 40) <= 2
    assert sharp[30, 46] == 200 and soft[30, 46] < 200  # blur spreads the edge


def test_invalid_arguments_are_named() -> None:
    with pytest.raises(ConfigError, match="marker_radius_px must be > 0"):
        render_marker_image(np.zeros((1, 2)), CAM, marker_radius_px=0.0)
    with pytest.raises(ConfigError, match="shading must lie in"):
        render_marker_image(np.zeros((1, 2)), CAM, shading=1.5)
    with pytest.raises(ConfigError, match="background must lie in"):
        render_marker_image(np.zeros((1, 2)), CAM, background=300)
