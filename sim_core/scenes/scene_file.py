"""Scene file v1 (``scene.yaml``, INTERFACES.md) loaded and validated into frozen dataclasses.

The scene file describes the physical setup of a simulation or of a recording: time step, gravity,
table, the thin sheet and its material, tactile sensors with their camera, and effectors.
Validation rules (house style, STYLE.md rule 7):

- ``version`` must be 1; any unknown key is rejected with a :class:`ConfigError` naming the dotted
  key (``sensors.tactile.camera.fxx``) and the file;
- every value of the v1 contract is required; only ``sensors.<name>.mount`` (identity when absent)
  and ``sensors.<name>.camera.k1`` / ``k2`` (no distortion when absent) are optional, and they stay
  ``None`` in the dataclasses rather than being filled in;
- numbers must be finite and physically meaningful (positive sizes and moduli, ``-1 < nu < 0.5``,
  unit quaternions to 1e-6);
- the optional ``simulation:`` block is the builder's extension (``sim_core.scenes.tactile_scene``);
  it must be a mapping and is kept verbatim, the builder validates its keys.

This module reads YAML only; it never imports a bag library (the bag reader uses it).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import yaml

from sim_core.errors import ConfigError

SCENE_FILE_VERSION = 1
CLAMPED_EDGES = ("none", "x0", "x1", "y0", "y1")
_QUAT_TOL = 1e-6


# ------------------------------------------------------------------------------------ dataclasses
@dataclass(frozen=True)
class TableSpec:
    """The table plane ``z = height`` (m) and the sheet-table Coulomb coefficient (-)."""

    height: float
    friction: float


@dataclass(frozen=True)
class SheetMaterial:
    """Sheet material: Young's modulus E (Pa), Poisson ratio nu (-), bending stiffness D (N m)."""

    youngs_modulus: float
    poisson_ratio: float
    bending_stiffness: float


@dataclass(frozen=True)
class SheetSpec:
    """The thin sheet as a tracked vertex grid.

    Attributes:
        size: extent along x and y (m), ``(2,)``.
        resolution: vertices along x and y, ``(2,)`` ints >= 2 (vertex ``(ix, iy)`` is ``iy*nx+ix``).
        thickness: m.
        density: kg/m^3.
        origin: world position of vertex (0, 0) (mid-surface), m, ``(3,)``.
        clamped_edge: one of ``none x0 x1 y0 y1``.
        material: :class:`SheetMaterial`.
    """

    size: tuple[float, float]
    resolution: tuple[int, int]
    thickness: float
    density: float
    origin: tuple[float, float, float]
    clamped_edge: str
    material: SheetMaterial


@dataclass(frozen=True)
class GelMaterial:
    """Elastomer material: Young's modulus (Pa), Poisson ratio (-), density (kg/m^3)."""

    youngs_modulus: float
    poisson_ratio: float
    density: float


@dataclass(frozen=True)
class CameraSpec:
    """Pinhole camera of a tactile sensor: ``u = fx x/(z+d) + cx``, ``v = fy y/(z+d) + cy`` (px).

    Attributes:
        fx, fy: focal lengths, px.  cx, cy: principal point, px.
        width, height: image size, px.
        distance: d, camera centre to contact surface, m.
        k1, k2: radial distortion coefficients (-), ``None`` when the file has none.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distance: float
    k1: float | None = None
    k2: float | None = None


@dataclass(frozen=True)
class SensorSpec:
    """A vision-based tactile sensor (INTERFACES.md, sensor frame conventions).

    Attributes:
        name: sensor name (topic prefix).
        effector: name of the effector carrying it.
        gel_size: gel extent along sensor x, y and thickness, m, ``(3,)``.
        gel_material: :class:`GelMaterial`.
        friction: gel-sheet Coulomb coefficient (-).
        marker_grid: markers along x and y, ``(2,)`` ints (marker ``i = iy*nx + ix``).
        marker_pitch: m.
        camera: :class:`CameraSpec`.
        mount: sensor frame in the effector frame ``[x y z qx qy qz qw]``; ``None`` = identity.
    """

    name: str
    effector: str
    gel_size: tuple[float, float, float]
    gel_material: GelMaterial
    friction: float
    marker_grid: tuple[int, int]
    marker_pitch: float
    camera: CameraSpec
    mount: tuple[float, ...] | None = None

    @property
    def marker_count(self) -> int:
        """Number of markers ``nx * ny``."""
        return self.marker_grid[0] * self.marker_grid[1]


@dataclass(frozen=True)
class EffectorSpec:
    """An effector and its initial pose ``[x y z qx qy qz qw]`` in ``world`` (m, unit quaternion)."""

    name: str
    initial_pose: tuple[float, ...]


@dataclass(frozen=True)
class SceneFile:
    """A validated scene file v1.

    Attributes:
        version: always 1.
        name: free text.
        dt: integration step, s.
        gravity: m/s^2, ``(3,)``.
        table, sheet: see :class:`TableSpec`, :class:`SheetSpec`.
        sensors: ``name -> SensorSpec`` in file order.
        effectors: ``name -> EffectorSpec`` in file order.
        simulation: the builder's optional extension block, verbatim (``None`` when absent).
        fitted: what ``thinshell sysid --write-scene`` fitted into this scene (``params``, ``sigma``,
            ``bag``, ``effects``, ...), verbatim, for the record (the values themselves are in the
            scene's keys); ``None`` when absent.
        source: the file it came from (``"<dict>"`` for an in-memory scene); not serialised.
    """

    version: int
    name: str
    dt: float
    gravity: tuple[float, float, float]
    table: TableSpec
    sheet: SheetSpec
    sensors: dict[str, SensorSpec]
    effectors: dict[str, EffectorSpec]
    simulation: dict[str, Any] | None = None
    fitted: dict[str, Any] | None = None
    source: str = field(default="<dict>", compare=False)

    def to_dict(self) -> dict[str, Any]:
        """Plain-YAML form of the scene (lists and Python scalars; optional keys only when set).

        ``load_scene_file(scene.to_dict()) == scene`` holds.
        """
        sheet = self.sheet
        out: dict[str, Any] = {
            "version": self.version,
            "name": self.name,
            "dt": self.dt,
            "gravity": list(self.gravity),
            "table": {"height": self.table.height, "friction": self.table.friction},
            "sheet": {
                "size": list(sheet.size), "resolution": list(sheet.resolution), "thickness": sheet.thickness,
                "density": sheet.density, "origin": list(sheet.origin), "clamped_edge": sheet.clamped_edge,
                "material": {"youngs_modulus": sheet.material.youngs_modulus,
                             "poisson_ratio": sheet.material.poisson_ratio,
                             "bending_stiffness": sheet.material.bending_stiffness},
            },
            "sensors": {},
            "effectors": {n: {"initial_pose": list(e.initial_pose)} for n, e in self.effectors.items()},
        }
        for n, s in self.sensors.items():
            cam = s.camera
            cam_d: dict[str, Any] = {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
                                     "width": cam.width, "height": cam.height, "distance": cam.distance}
            for k in ("k1", "k2"):
                if getattr(cam, k) is not None:
                    cam_d[k] = getattr(cam, k)
            s_d: dict[str, Any] = {
                "effector": s.effector, "gel_size": list(s.gel_size),
                "gel_material": {"youngs_modulus": s.gel_material.youngs_modulus,
                                 "poisson_ratio": s.gel_material.poisson_ratio,
                                 "density": s.gel_material.density},
                "friction": s.friction, "marker_grid": list(s.marker_grid), "marker_pitch": s.marker_pitch,
                "camera": cam_d,
            }
            if s.mount is not None:
                s_d["mount"] = list(s.mount)
            out["sensors"][n] = s_d
        if self.simulation is not None:
            out["simulation"] = dict(self.simulation)
        if self.fitted is not None:
            out["fitted"] = dict(self.fitted)
        return out


# ------------------------------------------------------------------------------------ validation
class _Checker:
    """Typed access to one mapping of the scene, with errors naming ``source`` and the dotted key."""

    def __init__(self, source: str, block: Any, prefix: str, allowed: tuple[str, ...],
                 optional: tuple[str, ...] = ()) -> None:
        self.source = source
        self.prefix = prefix
        where = prefix.rstrip(".") or "top level"
        if not isinstance(block, Mapping):
            self.fail(f"{where} must be a mapping, got {type(block).__name__}")
        unknown = [str(k) for k in block if k not in allowed]
        if unknown:
            self.fail(f"unknown key {prefix}{unknown[0]} (allowed here: {', '.join(allowed)})")
        missing = [k for k in allowed if k not in block and k not in optional]
        if missing:
            self.fail(f"missing required key {prefix}{missing[0]}")
        self.block = block

    def fail(self, message: str) -> None:
        raise ConfigError(f"{self.source}: {message}")

    def has(self, key: str) -> bool:
        return key in self.block and self.block[key] is not None

    def raw(self, key: str) -> Any:
        return self.block[key]

    def number(self, key: str, *, low: float | None = None, high: float | None = None,
               strict_low: bool = True, strict_high: bool = True, value: Any = None, dotted: str | None = None) -> float:
        dotted = dotted or self.prefix + key
        x = self.block[key] if value is None else value
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            self.fail(f"{dotted} must be a number, got {x!r}")
        x = float(x)
        if not math.isfinite(x):
            self.fail(f"{dotted} must be finite, got {x}")
        if low is not None and (x <= low if strict_low else x < low):
            self.fail(f"{dotted} must be {'>' if strict_low else '>='} {low}, got {x}")
        if high is not None and (x >= high if strict_high else x > high):
            self.fail(f"{dotted} must be {'<' if strict_high else '<='} {high}, got {x}")
        return x

    def integer(self, key: str, *, low: int, value: Any = None, dotted: str | None = None) -> int:
        dotted = dotted or self.prefix + key
        x = self.block[key] if value is None else value
        if isinstance(x, bool) or not isinstance(x, int):
            self.fail(f"{dotted} must be an integer, got {x!r}")
        if x < low:
            self.fail(f"{dotted} must be >= {low}, got {x}")
        return int(x)

    def numbers(self, key: str, n: int, **bounds: Any) -> tuple[float, ...]:
        seq = self._sequence(key, n)
        return tuple(self.number(key, value=v, dotted=f"{self.prefix}{key}[{i}]", **bounds) for i, v in enumerate(seq))

    def integers(self, key: str, n: int, *, low: int) -> tuple[int, ...]:
        seq = self._sequence(key, n)
        return tuple(self.integer(key, low=low, value=v, dotted=f"{self.prefix}{key}[{i}]") for i, v in enumerate(seq))

    def pose(self, key: str) -> tuple[float, ...]:
        p = self.numbers(key, 7)
        norm = math.sqrt(sum(q * q for q in p[3:]))
        if abs(norm - 1.0) > _QUAT_TOL:
            self.fail(f"{self.prefix}{key} quaternion (qx qy qz qw) must have unit norm, got {norm:.9g}")
        return p

    def text(self, key: str) -> str:
        x = self.block[key]
        if not isinstance(x, str):
            self.fail(f"{self.prefix}{key} must be a string, got {x!r}")
        return x

    def _sequence(self, key: str, n: int) -> list[Any]:
        seq = self.block[key]
        if not isinstance(seq, (list, tuple)) or len(seq) != n:
            self.fail(f"{self.prefix}{key} must be a list of {n} numbers, got {seq!r}")
        return list(seq)


class YamlLoader(yaml.SafeLoader):
    """PyYAML's safe loader that also reads YAML 1.2 floats such as ``3.0e9`` and ``1e-3``.

    PyYAML implements YAML 1.1, where an exponent needs a sign and a mantissa needs a dot, so
    ``3.0e9`` (as written in INTERFACES.md) would load as a string.
    """


YamlLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                  |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                  |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                  |[-+]?\.(?:inf|Inf|INF)
                  |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."),
)


def load_yaml(text: str) -> Any:
    """Parse YAML text with :class:`YamlLoader` (safe, YAML 1.2 floats)."""
    return yaml.load(text, Loader=YamlLoader)  # noqa: S506 - YamlLoader is a SafeLoader


def _read_yaml(path: Path) -> Any:
    if not path.is_file():
        raise ConfigError(f"{path}: scene file does not exist")
    try:
        return load_yaml(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML ({str(err).splitlines()[0]})") from err


def load_scene_file(scene: str | Path | Mapping[str, Any] | SceneFile) -> SceneFile:
    """Load and validate a scene file v1.

    Args:
        scene: path of a ``scene.yaml``, an already-parsed mapping, or a :class:`SceneFile`
            (returned unchanged).

    Returns:
        the :class:`SceneFile`.

    Raises:
        ConfigError: missing file, invalid YAML, wrong ``version``, unknown or missing key, value of
            the wrong type or out of range; the message names the file and the dotted key.
    """
    if isinstance(scene, SceneFile):
        return scene
    if isinstance(scene, Mapping):
        source, data = "<dict>", scene
    else:
        source, data = str(scene), _read_yaml(Path(scene))
    if not isinstance(data, Mapping):
        raise ConfigError(f"{source}: a scene file must be a YAML mapping, got {type(data).__name__}")
    if "version" not in data:
        raise ConfigError(f"{source}: missing required key version (this reader understands version 1)")
    if data["version"] != SCENE_FILE_VERSION or isinstance(data["version"], bool):
        raise ConfigError(f"{source}: version is {data['version']!r}; this reader understands version {SCENE_FILE_VERSION}")
    top = _Checker(source, data, "", ("version", "name", "dt", "gravity", "table", "sheet", "sensors", "effectors",
                                      "simulation", "fitted"), optional=("simulation", "fitted"))
    table_c = _Checker(source, top.raw("table"), "table.", ("height", "friction"))
    table = TableSpec(height=table_c.number("height"), friction=table_c.number("friction", low=0.0, strict_low=False))
    sheet = _sheet(source, top.raw("sheet"))
    effectors = _effectors(source, top.raw("effectors"))
    sensors = _sensors(source, top.raw("sensors"), effectors)
    simulation = None
    if top.has("simulation"):
        if not isinstance(top.raw("simulation"), Mapping):
            top.fail(f"simulation must be a mapping, got {top.raw('simulation')!r}")
        simulation = dict(top.raw("simulation"))
    fitted = None
    if top.has("fitted"):
        if not isinstance(top.raw("fitted"), Mapping):
            top.fail(f"fitted must be a mapping (what sysid fitted: params, sigma, bag, effects), got {top.raw('fitted')!r}")
        fitted = dict(top.raw("fitted"))
    name = data["name"]
    if not isinstance(name, str):
        name = top.fail(f"name must be a string, got {name!r}")
    return SceneFile(
        version=SCENE_FILE_VERSION, name=name, dt=top.number("dt", low=0.0), gravity=top.numbers("gravity", 3),
        table=table, sheet=sheet, sensors=sensors, effectors=effectors, simulation=simulation, fitted=fitted,
        source=source,
    )


def _sheet(source: str, block: Any) -> SheetSpec:
    c = _Checker(source, block, "sheet.", ("size", "resolution", "thickness", "density", "origin", "clamped_edge",
                                           "material"))
    m = _Checker(source, c.raw("material"), "sheet.material.", ("youngs_modulus", "poisson_ratio",
                                                                 "bending_stiffness"))
    edge = c.text("clamped_edge")
    if edge not in CLAMPED_EDGES:
        c.fail(f"sheet.clamped_edge must be one of {' | '.join(CLAMPED_EDGES)}, got {edge!r}")
    return SheetSpec(
        size=c.numbers("size", 2, low=0.0), resolution=c.integers("resolution", 2, low=2),
        thickness=c.number("thickness", low=0.0), density=c.number("density", low=0.0),
        origin=c.numbers("origin", 3), clamped_edge=edge,
        material=SheetMaterial(
            youngs_modulus=m.number("youngs_modulus", low=0.0),
            poisson_ratio=m.number("poisson_ratio", low=-1.0, high=0.5),
            bending_stiffness=m.number("bending_stiffness", low=0.0, strict_low=False),
        ),
    )


def _effectors(source: str, block: Any) -> dict[str, EffectorSpec]:
    if not isinstance(block, Mapping):
        raise ConfigError(f"{source}: effectors must be a mapping of name -> {{initial_pose}}, got {block!r}")
    out = {}
    for name, eff in block.items():
        c = _Checker(source, eff, f"effectors.{name}.", ("initial_pose",))
        out[str(name)] = EffectorSpec(name=str(name), initial_pose=c.pose("initial_pose"))
    return out


def _sensors(source: str, block: Any, effectors: Mapping[str, EffectorSpec]) -> dict[str, SensorSpec]:
    if not isinstance(block, Mapping):
        raise ConfigError(f"{source}: sensors must be a mapping of name -> sensor, got {block!r}")
    out = {}
    for name, sensor in block.items():
        p = f"sensors.{name}."
        c = _Checker(source, sensor, p, ("effector", "gel_size", "gel_material", "friction", "marker_grid",
                                         "marker_pitch", "camera", "mount"), optional=("mount",))
        effector = c.text("effector")
        if effector not in effectors:
            c.fail(f"{p}effector names unknown effector {effector!r} (effectors: {sorted(effectors)})")
        g = _Checker(source, c.raw("gel_material"), p + "gel_material.", ("youngs_modulus", "poisson_ratio", "density"))
        cam = _Checker(source, c.raw("camera"), p + "camera.",
                       ("fx", "fy", "cx", "cy", "width", "height", "distance", "k1", "k2"), optional=("k1", "k2"))
        out[str(name)] = SensorSpec(
            name=str(name), effector=effector, gel_size=c.numbers("gel_size", 3, low=0.0),
            gel_material=GelMaterial(youngs_modulus=g.number("youngs_modulus", low=0.0),
                                     poisson_ratio=g.number("poisson_ratio", low=-1.0, high=0.5),
                                     density=g.number("density", low=0.0)),
            friction=c.number("friction", low=0.0, strict_low=False),
            marker_grid=c.integers("marker_grid", 2, low=1), marker_pitch=c.number("marker_pitch", low=0.0),
            camera=CameraSpec(
                fx=cam.number("fx", low=0.0), fy=cam.number("fy", low=0.0), cx=cam.number("cx"), cy=cam.number("cy"),
                width=cam.integer("width", low=1), height=cam.integer("height", low=1),
                distance=cam.number("distance", low=0.0),
                k1=cam.number("k1") if cam.has("k1") else None, k2=cam.number("k2") if cam.has("k2") else None,
            ),
            mount=c.pose("mount") if c.has("mount") else None,
        )
    return out
