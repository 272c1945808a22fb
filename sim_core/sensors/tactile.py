"""The tactile sensor: its scene specification and one reading from a simulated state.

A reading (INTERFACES.md, ``<sensor>/markers``, ``<sensor>/wrench``, ``<sensor>/image``) is a pure
function of the deformed positions, the per-vertex contact forces and the sensor pose:
marker positions interpolated on the deformed contact surface and expressed in the sensor frame,
their pixels through the pinhole camera, the net wrench on the gel, and optionally a rendered
``mono8`` image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping, NamedTuple

import numpy as np

from sim_core.errors import ConfigError
from sim_core.sensors.camera import PinholeCamera
from sim_core.sensors.image import render_marker_image
from sim_core.sensors.markers import MarkerEmbedding, marker_positions
from sim_core.sensors.wrench import net_wrench
from sim_core.transforms import inverse_transform_points, quat_normalize

SENSOR_REQUIRED_KEYS = ("effector", "gel_size", "gel_material", "friction", "marker_grid", "marker_pitch", "camera")
SENSOR_OPTIONAL_KEYS = ("mount",)
GEL_MATERIAL_KEYS = ("youngs_modulus", "poisson_ratio", "density")

MARKER_RADIUS_PER_PITCH = 0.2
"""Rendered marker radius as a fraction of the marker pitch (a GelSight Mini frame shows markers of
about 7 px radius at about 33 px spacing)."""


def _positive(value: Any, where: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"{where} must be a number, got {value!r}") from err
    if not math.isfinite(v) or v <= 0.0:
        raise ConfigError(f"{where} must be a positive finite number, got {value!r}")
    return v


def _vector(value: Any, length: int, where: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"{where} must be a list of {length} numbers, got {value!r}") from err
    if arr.shape != (length,) or not np.all(np.isfinite(arr)):
        raise ConfigError(f"{where} must be a list of {length} finite numbers, got {value!r}")
    return arr


@dataclass(frozen=True)
class TactileSensorSpec:
    """A tactile sensor's ``sensors.<name>`` scene block, validated.

    Attributes:
        name: the sensor's name (the key under ``sensors``).
        effector: name of the effector that carries the gel.
        gel_size: gel pad ``(x, y, thickness)``, m, shape ``(3,)``.
        gel_material: ``{youngs_modulus (Pa), poisson_ratio (-), density (kg/m^3)}`` (nominal values).
        friction: Coulomb coefficient gel-sheet.
        marker_grid: ``(nx, ny)`` markers along sensor x and y.
        marker_pitch: marker spacing, m.
        camera: the pinhole camera behind the gel.
        mount: sensor frame in the effector frame ``[x y z qx qy qz qw]``, identity when absent.
    """

    name: str
    effector: str
    gel_size: np.ndarray
    gel_material: dict[str, float]
    friction: float
    marker_grid: tuple[int, int]
    marker_pitch: float
    camera: PinholeCamera
    mount: np.ndarray

    @property
    def marker_count(self) -> int:
        """Number of markers ``nx * ny``."""
        return self.marker_grid[0] * self.marker_grid[1]

    @classmethod
    def from_dict(cls, block: Mapping[str, Any], name: str) -> "TactileSensorSpec":
        """Validate a ``sensors.<name>`` block (INTERFACES.md, scene version 1).

        Args:
            block: the block as parsed from YAML.
            name: the sensor name, used in error messages as ``sensors.<name>.<key>``.

        Raises:
            ConfigError: missing/unknown key or invalid value, naming ``sensors.<name>.<key>``; a
                marker grid wider than the gel.
        """
        where = f"sensors.{name}"
        if not isinstance(block, Mapping):
            raise ConfigError(f"{where} must be a mapping, got {type(block).__name__}")
        known = set(SENSOR_REQUIRED_KEYS) | set(SENSOR_OPTIONAL_KEYS)
        unknown = sorted(set(block) - known)
        if unknown:
            raise ConfigError(f"{where}.{unknown[0]}: unknown key (known: {sorted(known)})")
        missing = [k for k in SENSOR_REQUIRED_KEYS if k not in block]
        if missing:
            raise ConfigError(f"{where}.{missing[0]}: required key is missing")
        effector = block["effector"]
        if not isinstance(effector, str) or not effector:
            raise ConfigError(f"{where}.effector must be an effector name, got {effector!r}")
        gel_size = _vector(block["gel_size"], 3, f"{where}.gel_size")
        if not np.all(gel_size > 0.0):
            raise ConfigError(f"{where}.gel_size must be positive lengths (m), got {gel_size.tolist()}")
        gm = block["gel_material"]
        if not isinstance(gm, Mapping):
            raise ConfigError(f"{where}.gel_material must be a mapping, got {type(gm).__name__}")
        unknown = sorted(set(gm) - set(GEL_MATERIAL_KEYS))
        if unknown:
            raise ConfigError(f"{where}.gel_material.{unknown[0]}: unknown key (known: {list(GEL_MATERIAL_KEYS)})")
        missing = [k for k in GEL_MATERIAL_KEYS if k not in gm]
        if missing:
            raise ConfigError(f"{where}.gel_material.{missing[0]}: required key is missing")
        material = {
            "youngs_modulus": _positive(gm["youngs_modulus"], f"{where}.gel_material.youngs_modulus"),
            "density": _positive(gm["density"], f"{where}.gel_material.density"),
        }
        nu = float(gm["poisson_ratio"])
        if not -1.0 < nu < 0.5:
            raise ConfigError(f"{where}.gel_material.poisson_ratio must lie in (-1, 0.5), got {gm['poisson_ratio']!r}")
        material["poisson_ratio"] = nu
        friction = float(block["friction"])
        if not math.isfinite(friction) or friction < 0.0:
            raise ConfigError(f"{where}.friction must be a finite number >= 0, got {block['friction']!r}")
        grid = _vector(block["marker_grid"], 2, f"{where}.marker_grid")
        if not np.all(grid == np.round(grid)) or not np.all(grid >= 1):
            raise ConfigError(
                f"{where}.marker_grid must be two positive integers [nx, ny], got {block['marker_grid']!r}"
            )
        marker_grid = (int(grid[0]), int(grid[1]))
        pitch = _positive(block["marker_pitch"], f"{where}.marker_pitch")
        for axis, n in zip("xy", marker_grid):
            span = (n - 1) * pitch
            size = gel_size[0 if axis == "x" else 1]
            if span > size * (1.0 + 1e-9):
                raise ConfigError(
                    f"{where}.marker_grid: {n} markers at pitch {pitch} m span {span:.6g} m along {axis}, "
                    f"wider than gel_size {size:.6g} m"
                )
        camera = PinholeCamera.from_dict(block["camera"], where=f"{where}.camera")
        mount_value = block.get("mount")
        if mount_value is None:
            mount = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
        else:
            mount = _vector(mount_value, 7, f"{where}.mount")
            mount[3:7] = quat_normalize(mount[3:7], where=f"{where}.mount")
        return cls(
            name=name, effector=effector, gel_size=gel_size, gel_material=material, friction=friction,
            marker_grid=marker_grid, marker_pitch=pitch, camera=camera, mount=mount,
        )


class TactileReading(NamedTuple):
    """One tactile reading (INTERFACES.md).

    Attributes:
        markers_xyz: marker positions in the sensor frame, shape ``(k, 3)``, m, order ``iy * nx + ix``.
        markers_uv: their pixel coordinates, shape ``(k, 2)``, px.
        wrench: ``[Fx Fy Fz Tx Ty Tz]`` ON the gel, sensor frame, torque about its origin, N and N*m.
        image: rendered ``mono8`` image ``(height, width)`` uint8, or ``None``.
    """

    markers_xyz: np.ndarray
    markers_uv: np.ndarray
    wrench: np.ndarray
    image: np.ndarray | None = None


def read_tactile(
    spec: TactileSensorSpec | Mapping[str, Any],
    camera: PinholeCamera,
    embedding: MarkerEmbedding,
    x: np.ndarray,
    triangles: np.ndarray,
    sensor_pose: np.ndarray,
    vertex_forces: np.ndarray | None,
    gel_vertices: np.ndarray,
    render_image: bool = False,
) -> TactileReading:
    """Read the tactile sensor in a simulated configuration.

    Args:
        spec: the sensor's spec (a ``sensors.<name>`` mapping is validated on the fly); used for the
            rendered marker size ``MARKER_RADIUS_PER_PITCH * marker_pitch``.
        camera: the sensor's camera.
        embedding: markers embedded in ``triangles`` (:func:`~sim_core.sensors.markers.embed_markers`).
        x: global vertex positions, shape ``(n, 3)``, m, world.
        triangles: the gel contact-surface triangles with global vertex indices, shape ``(t, 3)``.
        sensor_pose: sensor frame in ``world``, ``[x y z qx qy qz qw]``.
        vertex_forces: contact + friction force ON every vertex, shape ``(n, 3)``, N, world; ``None``
            before any step was solved (no contact force known yet: zero wrench).
        gel_vertices: global indices of the gel's vertices, shape ``(g,)``.
        render_image: also render the ``mono8`` marker image.

    Returns:
        the reading.
    """
    if isinstance(spec, Mapping):
        spec = TactileSensorSpec.from_dict(spec, name="<sensor>")
    gel_vertices = np.asarray(gel_vertices, dtype=np.int64)
    x = np.asarray(x, dtype=float)
    markers_world = marker_positions(embedding, x, triangles)
    markers_xyz = inverse_transform_points(sensor_pose, markers_world)
    markers_uv = camera.project(markers_xyz)
    if vertex_forces is None:
        wrench = np.zeros(6)
    else:
        forces = np.asarray(vertex_forces, dtype=float)[gel_vertices]
        wrench = net_wrench(forces, x[gel_vertices], sensor_pose)
    image = None
    if render_image:
        radius_m = MARKER_RADIUS_PER_PITCH * spec.marker_pitch
        radius_px = camera.fx * radius_m / (markers_xyz[:, 2] + camera.distance)
        image = render_marker_image(markers_uv, camera, marker_radius_px=radius_px)
    return TactileReading(markers_xyz=markers_xyz, markers_uv=markers_uv, wrench=wrench, image=image)
