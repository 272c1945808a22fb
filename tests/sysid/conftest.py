"""Fixtures of the sysid tests: the shared reference bags and small synthetic bags."""

from __future__ import annotations

import copy
import shutil
from pathlib import Path

import numpy as np
import pytest

from sysid.bagio import BagWriter

REFERENCE_DIR = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "reference_bags"
REFERENCE_BAGS = ("nominal_s101", "plastic_s102", "latency_s103")
NS = "/thinshell"

SCENE = {
    "version": 1,
    "name": "test_scene",
    "dt": 0.005,
    "gravity": [0.0, 0.0, -9.81],
    "table": {"height": 0.0, "friction": 0.3},
    "sheet": {
        "size": [0.10, 0.06], "resolution": [4, 3], "thickness": 0.0003, "density": 700.0,
        "origin": [0.0, -0.03, 0.00015], "clamped_edge": "x0",
        "material": {"youngs_modulus": 3.0e9, "poisson_ratio": 0.3, "bending_stiffness": 8.0e-3},
    },
    "sensors": {
        "tactile": {
            "effector": "ee", "gel_size": [0.0186, 0.0143, 0.004],
            "gel_material": {"youngs_modulus": 3.0e5, "poisson_ratio": 0.45, "density": 1100.0},
            "friction": 0.8, "marker_grid": [3, 2], "marker_pitch": 0.002,
            "camera": {"fx": 300.0, "fy": 300.0, "cx": 160.0, "cy": 120.0, "width": 320, "height": 240,
                       "distance": 0.025},
        }
    },
    "effectors": {"ee": {"initial_pose": [0.07, 0.0, 0.03, 0.0, 0.0, 0.0, 1.0]}},
}


def reference_bag(name: str) -> Path:
    """Path of a shared reference bag, or skip the test when the shared data is absent."""
    path = (REFERENCE_DIR / name).resolve()
    if not (path / "metadata.yaml").is_file():
        pytest.skip(f"reference bag {name} not found under {REFERENCE_DIR.resolve()}")
    return path


@pytest.fixture
def scene_dict() -> dict:
    """A valid scene v1 dict: 4x3 sheet grid, 3x2 markers (6 points), effector ee, sensor tactile."""
    return copy.deepcopy(SCENE)


@pytest.fixture
def writable_reference(tmp_path):
    """Factory: a writable copy of a reference bag directory."""

    def make(name: str = "nominal_s101") -> Path:
        src = reference_bag(name)
        dst = tmp_path / name
        shutil.copytree(src, dst)
        for f in dst.iterdir():
            f.chmod(0o644)
        return dst

    return make


def synthetic_streams(n: int = 20, seed: int = 0) -> dict:
    """Deterministic synthetic samples at 100 Hz: poses, wrenches, 6 markers (x y z u v), 12 sheet points."""
    rng = np.random.default_rng(seed)
    t_ns = (np.arange(n, dtype=np.int64) * 10_000_000 + 1_000_000_000)
    pose = np.zeros((n, 7))
    pose[:, 0] = 0.05 + 0.01 * np.linspace(0, 1, n)
    pose[:, 2] = 0.004 - 0.001 * np.sin(np.linspace(0, 3, n))
    pose[:, 3] = 1.0
    wrench = rng.normal(size=(n, 6))
    markers = rng.normal(scale=0.004, size=(n, 6, 3))
    markers[..., 2] = -np.abs(markers[..., 2]) * 0.1
    uv = 300.0 * markers[..., :2] / (markers[..., 2:3] + 0.025) + np.array([160.0, 120.0])
    sheet = rng.uniform(0.0, 0.1, size=(n, 12, 3))
    return {"t_ns": t_ns, "pose": pose, "wrench": wrench, "markers": markers, "uv": uv, "sheet": sheet}


def write_synthetic(out_dir: Path, streams: dict, scene: dict | None = None, skip: tuple[str, ...] = (),
                    namespace: str = NS) -> Path:
    """Write the synthetic streams as a bag with the INTERFACES.md topics (``pose_cmd`` from
    ``streams["pose_cmd"]`` when given, else the pose: a kinematic arm)."""
    with BagWriter(out_dir, scene=scene) as bag:
        for i, t in enumerate(streams["t_ns"]):
            t = int(t)
            if "pose" not in skip:
                bag.write_pose(f"{namespace}/ee/pose", t, streams["pose"][i], "world")
            if "pose_cmd" not in skip:
                bag.write_pose(f"{namespace}/ee/pose_cmd", t, streams.get("pose_cmd", streams["pose"])[i], "world")
            if "wrench" not in skip:
                bag.write_wrench(f"{namespace}/tactile/wrench", t, streams["wrench"][i], "tactile")
            if "markers" not in skip:
                bag.write_points(f"{namespace}/tactile/markers", t, streams["markers"][i], "tactile",
                                 extra_fields={"u": streams["uv"][i, :, 0], "v": streams["uv"][i, :, 1]})
            if "sheet_points" not in skip:
                bag.write_points(f"{namespace}/sheet/points", t, streams["sheet"][i], "world")
            if "clock" not in skip:
                bag.write_clock(t)
    return out_dir
