"""Tactile sensor spec from the scene block and a full reading from a synthetic gel state."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from sim_core.errors import ConfigError
from sim_core.sensors.camera import PinholeCamera
from sim_core.sensors.markers import embed_markers, marker_grid
from sim_core.sensors.tactile import TactileSensorSpec, read_tactile
from sim_core.transforms import transform_points

BLOCK = {
    "effector": "ee",
    "gel_size": [0.0186, 0.0143, 0.004],
    "gel_material": {"youngs_modulus": 3.0e5, "poisson_ratio": 0.45, "density": 1100.0},
    "friction": 0.8,
    "marker_grid": [9, 7],
    "marker_pitch": 0.0020,
    "camera": {"fx": 300.0, "fy": 300.0, "cx": 160.0, "cy": 120.0, "width": 320, "height": 240, "distance": 0.025},
    "mount": [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
}
FLIPPED = np.array([0.07, 0.01, 0.03, 1.0, 0.0, 0.0, 0.0])  # gel facing down (sensor z = world -z)


def _gel_face(spec: TactileSensorSpec, res: tuple[int, int] = (10, 8)) -> tuple[np.ndarray, np.ndarray]:
    nx, ny = res
    gx, gy, _ = spec.gel_size
    X, Y = np.meshgrid(np.linspace(-gx / 2, gx / 2, nx), np.linspace(-gy / 2, gy / 2, ny))
    x = np.stack([X.ravel(), Y.ravel(), np.zeros(nx * ny)], axis=1)
    tris = []
    for iy in range(ny - 1):
        for ix in range(nx - 1):
            a = iy * nx + ix
            tris += [(a, a + 1, a + nx + 1), (a, a + nx + 1, a + nx)]
    return x, np.array(tris, dtype=np.int64)


def test_spec_from_scene_block() -> None:
    spec = TactileSensorSpec.from_dict(BLOCK, "tactile")
    assert spec.marker_grid == (9, 7) and spec.marker_count == 63
    assert spec.camera == PinholeCamera.from_dict(BLOCK["camera"])
    np.testing.assert_allclose(spec.mount, [0, 0, 0, 0, 0, 0, 1])
    no_mount = {k: v for k, v in BLOCK.items() if k != "mount"}
    np.testing.assert_allclose(TactileSensorSpec.from_dict(no_mount, "tactile").mount, [0, 0, 0, 0, 0, 0, 1])


@pytest.mark.parametrize(
    "edit,match",
    [
        (lambda b: b.update(colour="red"), r"sensors\.left\.colour: unknown key"),
        (lambda b: b.pop("friction"), r"sensors\.left\.friction: required key is missing"),
        (lambda b: b["gel_material"].update(C10=1.0), r"sensors\.left\.gel_material\.C10: unknown key"),
        (lambda b: b["gel_material"].update(poisson_ratio=0.5), r"sensors\.left\.gel_material\.poisson_ratio"),
        (lambda b: b["camera"].update(zoom=2), r"sensors\.left\.camera\.zoom: unknown key"),
        (lambda b: b["camera"].update(fy=0.0), r"sensors\.left\.camera\.fy must be > 0"),
        (lambda b: b.update(marker_grid=[9]), r"sensors\.left\.marker_grid must be a list of 2"),
        (lambda b: b.update(marker_pitch=0.003), r"sensors\.left\.marker_grid: 9 markers .* wider than gel_size"),
        (lambda b: b.update(mount=[0, 0, 0, 0, 0, 0, 2.0]), r"sensors\.left\.mount: quaternion norm"),
        (lambda b: b.update(friction=-0.1), r"sensors\.left\.friction must be"),
    ],
)
def test_spec_errors_name_the_key(edit, match: str) -> None:
    block = copy.deepcopy(BLOCK)
    edit(block)
    with pytest.raises(ConfigError, match=match):
        TactileSensorSpec.from_dict(block, "left")


def test_reading_at_rest_and_under_a_press() -> None:
    spec = TactileSensorSpec.from_dict(BLOCK, "tactile")
    face_local, tris_local = _gel_face(spec)
    rest = marker_grid(spec.marker_grid, spec.marker_pitch)
    emb = embed_markers(rest, face_local, tris_local)
    # global array: 5 other vertices, then the gel face placed in the world by the sensor pose
    offset = 5
    x = np.vstack([np.zeros((offset, 3)), transform_points(FLIPPED, face_local)])
    gel_vertices = np.arange(offset, x.shape[0])
    forces = np.zeros_like(x)
    reading = read_tactile(spec, spec.camera, emb, x, tris_local + offset, FLIPPED, forces, gel_vertices)
    np.testing.assert_allclose(reading.markers_xyz, rest, atol=1e-12)
    np.testing.assert_allclose(reading.markers_uv, spec.camera.project(rest), atol=1e-9)
    np.testing.assert_allclose(reading.wrench, 0.0)
    assert reading.image is None

    # press: the face is pushed 0.5 mm into the gel (world +z), a 3 N load from below spread on the face
    pressed_local = face_local + np.array([0.0, 0.0, -0.0005])
    x[offset:] = transform_points(FLIPPED, pressed_local)
    forces[offset:] = np.array([0.0, 0.0, 3.0]) / face_local.shape[0]
    reading = read_tactile(
        BLOCK, spec.camera, emb, x, tris_local + offset, FLIPPED, forces, gel_vertices, render_image=True
    )
    np.testing.assert_allclose(reading.markers_xyz[:, 2], -0.0005, atol=1e-12)
    assert reading.wrench[2] == pytest.approx(-3.0)
    # markers move towards the camera: the image of the grid grows by d / (d - 0.5 mm) about (cx, cy)
    centre = np.array([160.0, 120.0])
    np.testing.assert_allclose(
        reading.markers_uv - centre, (spec.camera.project(rest) - centre) * 0.025 / 0.0245, atol=1e-9
    )
    assert reading.image.shape == (240, 320) and reading.image.dtype == np.uint8
    u, v = np.rint(reading.markers_uv[31]).astype(int)  # the central marker is dark in the image
    assert reading.image[v, u] < 100 and reading.image[5, 5] > 150
