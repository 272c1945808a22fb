"""The recording map (``recording.yaml``): where each role of a real cell's recording comes from.

A bag that follows INTERFACES.md needs no map. A real cell records other topic names, gives the
effector pose as TF in the robot's base frame, a wrench in the F/T sensor's own frame, colour or
compressed images with zero header stamps; the map says how to bring each of those to the contract
(docs/recording_map.md has the full schema and a real-cell example). It is read into the frozen
dataclasses below; unknown keys are errors (house rule 7). Schema version 1::

    version: 1
    frames:
      base: base_link                 # the robot's base frame (TF)
      world_in_base: [x, y, z, qx, qy, qz, qw]   # where the scene's world sits in base (measured)
      world: world                    # name a PoseStamped in world carries (default "world")
      sensor: gel                     # TF frame of the tactile sensor frame <sensor>
      effector: gel                   # TF frame of the scene's effector frame (default: sensor)
    pose: {tf: true}                  # or {topic: T, link: L, stamp: header}
    pose_cmd: {topic: T, link: tool0, stamp: header}
    markers: {topic: T, stamp: header}
    image: {topic: T, stamp: auto}
    camera_info: {topic: T}
    wrench:
      topic: T
      frame: ft_sensor
      stamp: header
      sign: on_gel                    # or on_environment: the sensor reports the reaction
      tare: {window: [0.0, 0.2]}      # s after the first wrench sample; or {offset: [6 values]}
      tool: {mass: 0.25, com: [0, 0, 0.03], gravity: [0, 0, -9.81]}
    sheet_points: {topic: T, frame: base_link, stamp: header}
    clock: {topic: /clock}
    tf: {dynamic: /tf, static: /tf_static}
    effectors:                        # a task scene's (kind: task) effectors, each on its own
      left:
        frame: left_gel               # TF frame of the effector's frame
        pose: {tf: true}              # or {topic: T, link: L, stamp: header}
        pose_cmd: {topic: T, link: left_tool0}    # taken at its log time
        gripper_cmd: {topic: T}                   # std_msgs/Float64 opening (m), taken at its log time

Stamp policies: ``header`` (the header stamp, today's contract), ``log`` (the time the recorder
logged the message), ``auto`` (log time for a topic whose header stamps are zero or not increasing,
else the header stamp).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from sim_core.errors import ConfigError
from sim_core.scenes.scene_file import load_yaml

MAP_VERSION = 1
MAP_FILENAME = "recording.yaml"
STAMP_POLICIES = ("header", "log", "auto")
IDENTITY_POSE = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
STANDARD_GRAVITY = (0.0, 0.0, -9.80665)
WRENCH_SIGNS = ("on_gel", "on_environment")
"""``wrench.sign``: the message is the wrench ON the tool side (the gel, the contract's sign), or the
wrench the tool exerts ON the environment (the reaction, its negative)."""

_TOP_KEYS = ("version", "frames", "pose", "pose_cmd", "markers", "image", "camera_info", "wrench", "sheet_points",
             "clock", "tf", "effectors")
_FRAME_KEYS = ("base", "world_in_base", "world", "sensor", "effector")


@dataclass(frozen=True)
class TopicSource:
    """A role read from a topic.

    Attributes:
        topic: absolute topic name.
        stamp: ``header`` | ``log`` | ``auto`` (module docstring).
        link: for poses, the frame (TF name) whose pose the message carries; ``None`` = the effector frame.
        frame: for the wrench and sheet points, the frame the message is in (its header frame_id must match).
    """

    topic: str
    stamp: str = "header"
    link: str | None = None
    frame: str | None = None


@dataclass(frozen=True)
class ToolWeight:
    """Weight of what hangs between the F/T sensor and the gel.

    Attributes:
        mass: kg.
        com: centre of mass in the wrench frame, m, ``(3,)``.
        gravity: gravity in ``world``, m/s^2, ``(3,)``.
    """

    mass: float
    com: tuple[float, float, float]
    gravity: tuple[float, float, float] = STANDARD_GRAVITY


@dataclass(frozen=True)
class WrenchSource:
    """The F/T sensor's wrench topic and how it becomes the contract's wrench on the gel.

    Attributes:
        topic, stamp: as :class:`TopicSource`.
        frame: the wrench's frame (header frame_id must match); carried to the sensor frame through TF.
        tare_window: ``(t0, t1)`` s after the first wrench sample: its mean (tool weight removed) is the
            sensor's offset, subtracted from every sample; ``None`` with ``tare_offset`` or no tare.
        tare_offset: a known offset ``(6,)`` N, N m in ``frame``, subtracted from every sample.
        tool: :class:`ToolWeight` compensated by orientation, or None.
        sign: ``on_gel`` (default): the message is the force and torque the tool side receives (the
            contract's sign: pressing gives F_z < 0 in the sensor frame); ``on_environment``: the sensor
            reports the reaction, the wrench the tool exerts on what it touches, and the reader negates it
            before the tool weight and the tare (``tare_offset`` stays in the message's own sign).
    """

    topic: str
    frame: str
    stamp: str = "header"
    tare_window: tuple[float, float] | None = None
    tare_offset: tuple[float, ...] | None = None
    tool: ToolWeight | None = None
    sign: str = "on_gel"


@dataclass(frozen=True)
class EffectorSource:
    """One effector of a task scene (``kind: task``) in a real cell's recording.

    Attributes:
        frame: TF frame of the effector's frame (the frame ``effectors.<e>.initial_pose`` places in world).
        pose: ``"tf"`` (the TF chain ``base -> frame``, sampled at the chain's dynamic edges' stamps), a
            :class:`TopicSource` (a PoseStamped of ``link``, default ``frame``), or None.
        pose_cmd: :class:`TopicSource` of the command, a PoseStamped of ``link`` (e.g. ``tool0``) carried to
            ``frame`` by TF; stamped with its log time (when the robot took it), as the contract's task reader.
        gripper_cmd: :class:`TopicSource` of ``std_msgs/Float64`` finger openings (m), stamped with log time.
    """

    frame: str
    pose: str | TopicSource | None = None
    pose_cmd: TopicSource | None = None
    gripper_cmd: TopicSource | None = None


@dataclass(frozen=True)
class RecordingMap:
    """A validated recording map (module docstring; docs/recording_map.md).

    Attributes:
        base_frame: the robot's base frame.
        world_in_base: pose of the scene's ``world`` in ``base_frame`` ``(7,)``.
        world_frame: the frame name of ``world`` in messages.
        sensor_frame, effector_frame: TF names of the tactile sensor frame and the scene's effector frame.
        pose: effector pose source: ``"tf"`` or a :class:`TopicSource`; None = not recorded.
        pose_cmd, markers, image, camera_info, sheet_points, clock: :class:`TopicSource` or None.
        wrench: :class:`WrenchSource` or None.
        tf_topic, tf_static_topic: TF topics.
        source: the file it came from.
        effectors: of a task scene, effector name -> :class:`EffectorSource` (empty: the task scene's
            effector streams come from INTERFACES.md's topics).
    """

    base_frame: str
    world_in_base: tuple[float, ...]
    world_frame: str
    sensor_frame: str
    effector_frame: str
    pose: str | TopicSource | None
    pose_cmd: TopicSource | None
    markers: TopicSource | None
    image: TopicSource | None
    camera_info: TopicSource | None
    wrench: WrenchSource | None
    sheet_points: TopicSource | None
    clock: TopicSource | None
    tf_topic: str = "/tf"
    tf_static_topic: str = "/tf_static"
    source: str = "<dict>"
    effectors: dict[str, EffectorSource] = field(default_factory=dict)

    def topics(self) -> dict[str, str]:
        """Every topic the map reads: role -> topic (``tf`` / ``tf_static`` included)."""
        out = {"tf": self.tf_topic, "tf_static": self.tf_static_topic}
        for role in ("pose", "pose_cmd", "markers", "image", "camera_info", "wrench", "sheet_points", "clock"):
            src = getattr(self, role)
            if src is not None and not isinstance(src, str):
                out[role] = src.topic
        return out


class _Section:
    """Typed access to one mapping of the map, errors naming the file and the dotted key."""

    def __init__(self, source: str, where: str, data: Any, allowed: tuple[str, ...]) -> None:
        if not isinstance(data, Mapping):
            raise ConfigError(f"{source}: {where} must be a mapping, got {type(data).__name__}")
        unknown = [k for k in data if k not in allowed]
        if unknown:
            raise ConfigError(f"{source}: unknown key {where}.{unknown[0]} (allowed: {', '.join(allowed)})")
        self.source, self.where, self.data = source, where, data

    def _name(self, key: str) -> str:
        return f"{self.where}.{key}" if self.where else key

    def text(self, key: str, default: str | None = None, required: bool = False) -> str | None:
        value = self.data.get(key, default)
        if value is None:
            if required:
                raise ConfigError(f"{self.source}: {self._name(key)} is required")
            return None
        if not isinstance(value, str) or not value.strip():
            raise ConfigError(f"{self.source}: {self._name(key)} must be a non-empty string, got {value!r}")
        return value.strip()

    def numbers(self, key: str, n: int, default: tuple[float, ...] | None = None,
                required: bool = False) -> tuple[float, ...] | None:
        value = self.data.get(key)
        if value is None:
            if required:
                raise ConfigError(f"{self.source}: {self._name(key)} is required ({n} numbers)")
            return default
        try:
            out = tuple(float(v) for v in value)
        except (TypeError, ValueError):
            out = ()
        if len(out) != n or not all(math.isfinite(v) for v in out) or isinstance(value, (str, bytes)):
            raise ConfigError(f"{self.source}: {self._name(key)} must be {n} finite numbers, got {value!r}")
        return out

    def stamp(self) -> str:
        value = self.data.get("stamp", "header")
        if value not in STAMP_POLICIES:
            raise ConfigError(f"{self.source}: {self._name('stamp')} must be one of {', '.join(STAMP_POLICIES)}, "
                              f"got {value!r}")
        return value


def _pose7(source: str, where: str, values: tuple[float, ...]) -> tuple[float, ...]:
    norm = math.sqrt(sum(v * v for v in values[3:]))
    if abs(norm - 1.0) > 1e-3:
        raise ConfigError(f"{source}: {where} quaternion has norm {norm:.6g}, expected 1")
    return values[:3] + tuple(v / norm for v in values[3:])


def _topic(source: str, role: str, data: Any, allowed: tuple[str, ...]) -> TopicSource | None:
    if data is None:
        return None
    s = _Section(source, role, data, allowed)
    topic = s.text("topic", required=True)
    if not topic.startswith("/"):
        raise ConfigError(f"{source}: {role}.topic must be an absolute topic name (starting with /), got {topic!r}")
    return TopicSource(topic=topic, stamp=s.stamp() if "stamp" in allowed else "header",
                       link=s.text("link") if "link" in allowed else None,
                       frame=s.text("frame") if "frame" in allowed else None)


def _wrench(source: str, data: Any) -> WrenchSource | None:
    if data is None:
        return None
    s = _Section(source, "wrench", data, ("topic", "frame", "stamp", "sign", "tare", "tool"))
    sign = data.get("sign", "on_gel")
    if sign not in WRENCH_SIGNS:
        raise ConfigError(f"{source}: wrench.sign must be one of {', '.join(WRENCH_SIGNS)}, got {sign!r}")
    base = _topic(source, "wrench", {k: v for k, v in data.items() if k in ("topic", "stamp")}, ("topic", "stamp"))
    window = offset = None
    if data.get("tare") is not None:
        tare = _Section(source, "wrench.tare", data["tare"], ("window", "offset"))
        window = tare.numbers("window", 2)
        offset = tare.numbers("offset", 6)
        if (window is None) == (offset is None):
            raise ConfigError(f"{source}: wrench.tare needs exactly one of window (s) or offset (6 values)")
        if window is not None and not 0.0 <= window[0] < window[1]:
            raise ConfigError(f"{source}: wrench.tare.window must be [t0, t1] s with 0 <= t0 < t1, got {list(window)}")
    tool = None
    if data.get("tool") is not None:
        t = _Section(source, "wrench.tool", data["tool"], ("mass", "com", "gravity"))
        mass = t.data.get("mass")
        if isinstance(mass, bool) or not isinstance(mass, (int, float)) or not (math.isfinite(mass) and mass >= 0.0):
            raise ConfigError(f"{source}: wrench.tool.mass must be a number of kg >= 0, got {mass!r}")
        tool = ToolWeight(mass=float(mass), com=t.numbers("com", 3, required=True),
                          gravity=t.numbers("gravity", 3, default=STANDARD_GRAVITY))
    return WrenchSource(topic=base.topic, frame=s.text("frame", required=True), stamp=base.stamp,
                        tare_window=window, tare_offset=offset, tool=tool, sign=sign)


def _pose_source(source: str, where: str, data: Any) -> str | TopicSource | None:
    """``{tf: true}`` -> ``"tf"``, else a pose topic ``{topic, link, stamp}``."""
    if isinstance(data, Mapping) and set(data) == {"tf"}:
        if data["tf"] is not True:
            raise ConfigError(f"{source}: {where}.tf must be true (or give {where}.topic)")
        return "tf"
    return _topic(source, where, data, ("topic", "link", "stamp"))


def _effectors(source: str, data: Any) -> dict[str, EffectorSource]:
    if data is None:
        return {}
    if not isinstance(data, Mapping) or not data:
        raise ConfigError(f"{source}: effectors must be a mapping of effector names, got {data!r}")
    out = {}
    for name, spec in data.items():
        where = f"effectors.{name}"
        s = _Section(source, where, spec, ("frame", "pose", "pose_cmd", "gripper_cmd"))
        effector = EffectorSource(
            frame=s.text("frame", required=True), pose=_pose_source(source, f"{where}.pose", spec.get("pose")),
            pose_cmd=_topic(source, f"{where}.pose_cmd", spec.get("pose_cmd"), ("topic", "link")),
            gripper_cmd=_topic(source, f"{where}.gripper_cmd", spec.get("gripper_cmd"), ("topic",)))
        if effector.pose is None and effector.pose_cmd is None:
            raise ConfigError(f"{source}: {where} needs pose or pose_cmd (its motion cannot be replayed without)")
        out[str(name)] = effector
    return out


def parse_recording_map(data: Mapping[str, Any], source: str = "<dict>") -> RecordingMap:
    """Validate a recording map's YAML content.

    Raises:
        ConfigError: wrong or missing version, unknown key, malformed value (each names the file and key).
    """
    top = _Section(source, "", data, _TOP_KEYS)
    if data.get("version") != MAP_VERSION:
        raise ConfigError(f"{source}: version must be {MAP_VERSION}, got {data.get('version')!r}")
    frames = _Section(source, "frames", data.get("frames") or {}, _FRAME_KEYS)
    base = frames.text("base", required=True)
    world_in_base = _pose7(source, "frames.world_in_base",
                           frames.numbers("world_in_base", 7, required=True))
    sensor = frames.text("sensor", required=True)
    pose = _pose_source(source, "pose", data.get("pose"))
    tf = _Section(source, "tf", data.get("tf") or {}, ("dynamic", "static"))
    del top
    return RecordingMap(
        base_frame=base, world_in_base=world_in_base, world_frame=frames.text("world", default="world"),
        sensor_frame=sensor, effector_frame=frames.text("effector", default=sensor), pose=pose,
        pose_cmd=_topic(source, "pose_cmd", data.get("pose_cmd"), ("topic", "link", "stamp")),
        markers=_topic(source, "markers", data.get("markers"), ("topic", "stamp")),
        image=_topic(source, "image", data.get("image"), ("topic", "stamp")),
        camera_info=_topic(source, "camera_info", data.get("camera_info"), ("topic",)),
        wrench=_wrench(source, data.get("wrench")),
        sheet_points=_topic(source, "sheet_points", data.get("sheet_points"), ("topic", "frame", "stamp")),
        clock=_topic(source, "clock", data.get("clock"), ("topic",)),
        tf_topic=tf.text("dynamic", default="/tf"), tf_static_topic=tf.text("static", default="/tf_static"),
        source=source, effectors=_effectors(source, data.get("effectors")),
    )


def load_recording_map(path: str | Path | RecordingMap) -> RecordingMap:
    """Read ``recording.yaml`` (or any map file).

    Raises:
        ConfigError: unreadable file or invalid content (names the file and the key).
    """
    if isinstance(path, RecordingMap):
        return path
    path = Path(path).absolute()
    try:
        data = load_yaml(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as err:
        raise ConfigError(f"{path}: cannot read recording map ({err})") from err
    if not isinstance(data, Mapping):
        raise ConfigError(f"{path}: a recording map must be a YAML mapping")
    return parse_recording_map(data, str(path))


def find_recording_map(bag_dir: Path) -> Path | None:
    """``recording.yaml`` beside the bag's ``scene.yaml`` (in the bag directory), or None."""
    candidate = bag_dir / MAP_FILENAME
    return candidate if candidate.is_file() else None
