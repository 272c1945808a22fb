"""Pinhole camera: projection formula, inverse, analytic derivatives, configuration errors."""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.errors import ConfigError, ThinShellError
from sim_core.sensors.camera import PinholeCamera

SCENE_CAMERA = {"fx": 300.0, "fy": 310.0, "cx": 160.0, "cy": 120.0, "width": 320, "height": 240, "distance": 0.025}


def _points(rng: np.random.Generator, k: int = 7) -> np.ndarray:
    p = rng.uniform(-0.008, 0.008, size=(k, 3))
    p[:, 2] = rng.uniform(-0.003, 0.001, size=k)
    return p


def test_projection_matches_hand_values() -> None:
    cam = PinholeCamera.from_dict(SCENE_CAMERA)
    p = np.array([[0.0, 0.0, 0.0], [0.005, -0.0025, 0.0], [0.002, 0.001, -0.005]])
    uv = cam.project(p)
    # u = 300 * 0.005 / 0.025 + 160 = 220, v = 310 * (-0.0025) / 0.025 + 120 = 89
    # third: w = 0.020 -> u = 300 * 0.1 + 160 = 190, v = 310 * 0.05 + 120 = 135.5
    np.testing.assert_allclose(uv, [[160.0, 120.0], [220.0, 89.0], [190.0, 135.5]], atol=1e-12)


def test_distortion_matches_hand_values() -> None:
    cam = PinholeCamera(fx=300, fy=300, cx=160, cy=120, width=320, height=240, distance=0.025, k1=0.1, k2=-0.05)
    p = np.array([[0.005, 0.0025, 0.0]])
    xn, yn = 0.2, 0.1
    r2 = xn**2 + yn**2
    f = 1 + 0.1 * r2 - 0.05 * r2**2
    np.testing.assert_allclose(cam.project(p), [[300 * xn * f + 160, 300 * yn * f + 120]], rtol=1e-14)


@pytest.mark.parametrize("k1,k2", [(0.0, 0.0), (0.15, -0.08)])
def test_unproject_round_trip(k1: float, k2: float) -> None:
    cam = PinholeCamera(**SCENE_CAMERA, k1=k1, k2=k2)
    p = _points(np.random.default_rng(0), 20)
    back = cam.unproject(cam.project(p), p[:, 2], iterations=50)
    np.testing.assert_allclose(back, p, atol=1e-12)


@pytest.mark.parametrize("k1,k2", [(0.0, 0.0), (0.3, -0.2)])
def test_project_jacobian_matches_central_differences(k1: float, k2: float) -> None:
    cam = PinholeCamera(**SCENE_CAMERA, k1=k1, k2=k2)
    p = _points(np.random.default_rng(1))
    J = cam.project_jacobian(p)
    h = 1e-7
    J_fd = np.zeros_like(J)
    for d in range(3):
        dp = np.zeros(3)
        dp[d] = h
        J_fd[:, :, d] = (cam.project(p + dp) - cam.project(p - dp)) / (2 * h)
    assert np.max(np.abs(J - J_fd)) / np.max(np.abs(J_fd)) < 1e-7


@pytest.mark.parametrize("name", ["k1", "k2", "fx", "fy", "cx", "cy", "distance"])
def test_parameter_derivative_matches_central_differences(name: str) -> None:
    base = dict(SCENE_CAMERA, k1=0.2, k2=-0.1)
    p = _points(np.random.default_rng(2))
    h = 1e-6 * max(1.0, abs(base[name]))
    up = PinholeCamera(**dict(base, **{name: base[name] + h}))
    down = PinholeCamera(**dict(base, **{name: base[name] - h}))
    fd = (up.project(p) - down.project(p)) / (2 * h)
    analytic = PinholeCamera(**base).project_parameter_derivative(p, name)
    assert np.max(np.abs(analytic - fd)) <= 1e-6 * max(np.max(np.abs(fd)), 1e-3)
    assert np.max(np.abs(analytic)) > 0.0


def test_distortion_derivative_is_nonzero_off_axis() -> None:
    cam = PinholeCamera(**SCENE_CAMERA)
    d = cam.project_parameter_derivative(np.array([[0.0, 0.0, 0.0], [0.005, 0.0, 0.0]]), "k1")
    np.testing.assert_allclose(d[0], 0.0)
    np.testing.assert_allclose(d[1], [300 * 0.2 * 0.04, 0.0])


def test_point_behind_camera_is_rejected() -> None:
    cam = PinholeCamera(**SCENE_CAMERA)
    with pytest.raises(ThinShellError, match="point 1 .* not in front of the camera"):
        cam.project(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -0.03]]))


def test_from_dict_round_trip_and_errors() -> None:
    cam = PinholeCamera.from_dict(dict(SCENE_CAMERA, k1=0.1))
    assert PinholeCamera.from_dict(cam.to_dict()) == cam
    with pytest.raises(ConfigError, match=r"sensors\.tactile\.camera\.focal: unknown key"):
        PinholeCamera.from_dict(dict(SCENE_CAMERA, focal=1.0), where="sensors.tactile.camera")
    with pytest.raises(ConfigError, match=r"camera\.distance: required key is missing"):
        PinholeCamera.from_dict({k: v for k, v in SCENE_CAMERA.items() if k != "distance"})
    with pytest.raises(ConfigError, match=r"sensors\.s\.camera\.fx must be > 0"):
        PinholeCamera.from_dict(dict(SCENE_CAMERA, fx=-1.0), where="sensors.s.camera")
    with pytest.raises(ConfigError, match=r"camera\.width must be a positive integer"):
        PinholeCamera(**dict(SCENE_CAMERA, width=320.5))
    with pytest.raises(ConfigError, match=r"camera\.distance must be > 0"):
        PinholeCamera(**dict(SCENE_CAMERA, distance=0.0))
    with pytest.raises(ConfigError, match=r"camera\.k1 must be finite"):
        PinholeCamera(**SCENE_CAMERA, k1=float("nan"))
