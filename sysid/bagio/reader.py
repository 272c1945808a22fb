"""Read thinshell recordings (rosbag2 MCAP directories or bare ``.mcap`` files) into NumPy series.

``open_bag(path)`` reads every topic that plays a *role* (pose, pose_cmd, markers, wrench,
sheet_points, image, clock; INTERFACES.md) into a :class:`Series` of integer-nanosecond stamps and
float64 SI values, checks it, and returns them with the bag's topic table and its ``scene.yaml``.

Topic of each role: ``<namespace>/<effector>/pose``, ``<namespace>/<effector>/pose_cmd``,
``<namespace>/<sensor>/markers``, ``<namespace>/<sensor>/wrench``, ``<namespace>/sheet/points``,
``<namespace>/<sensor>/image``, ``/clock``. Names are resolved in this order: the ``roles`` argument
(role -> topic), the ``bag.topics`` overrides of ``sysid/data/default.yaml``, then the templates
with ``bag.namespace`` and ``bag.effector`` / ``bag.sensor`` from that file, or, where those are
null, the scene's only sensor and its effector, or ``ee`` / ``tactile``.

Checks (errors are :class:`BagReadError`, one line naming the file or topic; repairs are
:class:`BagWarning` through ``warnings`` and are also kept in ``BagContents.notes``):

- missing path, unreadable / truncated / corrupt MCAP, fewer messages than ``metadata.yaml`` lists,
  an empty bag -> error;
- a role topic with another message type -> error; a markers cloud without ``x y z`` -> error;
- samples with NaN/inf -> dropped with a warning giving the count; all samples non-finite -> error;
- stamps out of order -> sorted (stable) with a warning; repeated stamps -> later copies dropped;
- a measurement role (pose, pose_cmd, markers, wrench, sheet_points) absent or without messages ->
  warning naming the topic; the series is simply missing from ``BagContents.series``.

Stamps are header stamps (the time the quantity was true), log time for messages without header;
``/clock`` is stamped with the clock value it carries.

Images may be ``sensor_msgs/Image`` of any encoding of :data:`sysid.bagio.images.ENCODINGS` or
``sensor_msgs/CompressedImage``; they are read as grey frames. A measured pose whose header frame_id
is not ``world`` is an error naming the topic and both frames; so are commands all in another frame,
while a few commands in another frame among ``world`` ones (refused by the robot, kept by the
recorder) are dropped with a warning.

A real cell's recording is read through a **recording map** (:mod:`sysid.bagio.recording_map`):
``recording_map=`` or a ``recording.yaml`` in the bag directory; the roles then come from the
map's topics and TF (:mod:`sysid.bagio.cell`) instead of the topic names above. A bag split into
several ``.mcap`` files (``ros2 bag record --max-bag-size``) is read through its ``metadata.yaml``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from sim_core.errors import BagReadError, ConfigError
from sim_core.scenes.scene_file import SceneFile, load_yaml
from sim_core.scenes.task_file import TaskSceneFile, load_any_scene_file
from sysid.bagio import cell, codec, images
from sysid.bagio.errors import BagWarning
from sysid.bagio.recording_map import RecordingMap, find_recording_map, load_recording_map
from sysid.data import DEFAULT_CONFIG, data_file

ROLES = ("pose", "pose_cmd", "markers", "wrench", "sheet_points", "image", "clock")
MEASUREMENT_ROLES = ("pose", "pose_cmd", "markers", "wrench", "sheet_points")
ROLE_MSGTYPES = {
    "pose": codec.POSE_STAMPED, "pose_cmd": codec.POSE_STAMPED, "markers": codec.POINT_CLOUD2,
    "wrench": codec.WRENCH_STAMPED, "sheet_points": codec.POINT_CLOUD2, "image": codec.IMAGE, "clock": codec.CLOCK,
}
ROLE_ACCEPTED = {**{r: (t,) for r, t in ROLE_MSGTYPES.items()}, "image": images.IMAGE_TYPES}
"""Message types each role takes (an image may also be a ``sensor_msgs/CompressedImage``)."""
WORLD_FRAME = "world"
"""Frame of a PoseStamped under today's contract (no recording map)."""
ROLE_TEMPLATES = {
    "pose": "{effector}/pose", "pose_cmd": "{effector}/pose_cmd", "markers": "{sensor}/markers",
    "wrench": "{sensor}/wrench", "sheet_points": "sheet/points", "image": "{sensor}/image", "clock": "/clock",
}
SCENE_FILENAME = "scene.yaml"
_BAG_CONFIG_KEYS = ("namespace", "effector", "sensor", "topics")


# ------------------------------------------------------------------------------------- records
@dataclass(frozen=True)
class TopicInfo:
    """One topic of a bag: name, message type (``pkg/msg/Type``) and message count."""

    topic: str
    msgtype: str
    message_count: int


@dataclass(frozen=True)
class Series:
    """The samples of one role topic, sorted by stamp, non-finite samples removed.

    Attributes:
        role: role name (:data:`ROLES`).
        topic: topic name.
        msgtype: message type.
        t_ns: stamps, int64 ns, shape ``(N,)``, strictly increasing.
        values: float64 samples, shape ``(N, ...)``: pose ``(N, 7)`` [x y z qx qy qz qw];
            wrench ``(N, 6)``; point clouds ``(N, p, len(field_names))``; image ``(N, h, w)`` uint8;
            clock ``(N,)`` (the clock in s, equal to ``t_ns * 1e-9``).
        field_names: point-cloud field names (column order of ``values``), else ``()``.
        frame_id: header frame of the first sample (``""`` without header).
        dropped_nonfinite: number of samples dropped for NaN/inf.
        resorted: True when stamps were out of order in the file.
    """

    role: str
    topic: str
    msgtype: str
    t_ns: np.ndarray
    values: np.ndarray
    field_names: tuple[str, ...] = ()
    frame_id: str = ""
    dropped_nonfinite: int = 0
    resorted: bool = False

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    def field(self, name: str) -> np.ndarray:
        """Point-cloud field ``name`` as ``(N, p)``.

        Raises:
            KeyError: no such field (names the topic).
        """
        if name not in self.field_names:
            raise KeyError(f"topic {self.topic} has no point field {name!r} (fields: {self.field_names})")
        return self.values[..., self.field_names.index(name)]


@dataclass(frozen=True)
class BagContents:
    """What :func:`open_bag` read.

    Attributes:
        path: the path given (bag directory or ``.mcap`` file), absolute.
        mcap_path: the MCAP file read (the first one of a split bag).
        sha256: hex SHA-256 of the MCAP file (of the files' bytes in order, for a split bag).
        topics: every topic in the bag, ``name -> TopicInfo``.
        roles: role -> topic name used for this bag.
        series: role -> :class:`Series` for every role topic present with usable samples.
        missing_roles: roles whose topic is absent or empty.
        scene: the ``scene.yaml`` beside the bag, parsed, or None.
        scene_path: where it was read from, or None.
        start_ns, end_ns: first and last stamp over all role series, ns.
        notes: the warnings emitted while reading, as text.
        mcap_paths: every MCAP file of the bag, in ``metadata.yaml`` order.
        recording_map: the recording map file used, or None (today's contract).
        camera: intrinsics from the map's ``camera_info`` topic (``fx fy cx cy width height``, and ``k1 k2``
            when it gives a distortion), or None.
        pose_cmd_taken: the ``pose_cmd`` role's commands stamped with their log time, when the robot took
            them (the sim node logs a command at the sim time it takes it, between steps; a commander that
            falls behind a fast robot makes these a step or more later than the commands' header stamps,
            several at one time), the last of several taken at one time kept (the one in force), the
            whole recording (not cut to ``window_s``: a command taken before the window is in force in
            it); None through a recording map or without commands.
    """

    path: Path
    mcap_path: Path
    sha256: str
    topics: dict[str, TopicInfo]
    roles: dict[str, str]
    series: dict[str, Series]
    missing_roles: tuple[str, ...]
    scene: SceneFile | None
    scene_path: Path | None
    start_ns: int
    end_ns: int
    notes: tuple[str, ...] = field(default=())
    mcap_paths: tuple[Path, ...] = ()
    recording_map: Path | None = None
    camera: dict[str, float] | None = None
    pose_cmd_taken: Series | None = None

    @property
    def message_count(self) -> int:
        """Messages in the bag over all topics."""
        return sum(t.message_count for t in self.topics.values())


# -------------------------------------------------------------------------------------- config
@dataclass(frozen=True)
class BagConfig:
    """The ``bag:`` section of ``sysid/data/default.yaml``.

    Attributes:
        namespace: namespace of relative topic names (default ``/thinshell``).
        effector, sensor: names for the role templates; ``None`` = from the scene, else ``ee`` / ``tactile``.
        topics: role -> topic overrides (relative names are joined to ``namespace``).
    """

    namespace: str = "/thinshell"
    effector: str | None = None
    sensor: str | None = None
    topics: dict[str, str] = field(default_factory=dict)


def load_bag_config(path: str | Path | None = None) -> BagConfig:
    """Read the ``bag:`` section of a sysid config file (other sections are left to their readers).

    Args:
        path: config file; default the packaged ``sysid/data/default.yaml``
            (:func:`sysid.data.data_file`).

    Raises:
        ConfigError: unreadable or missing file (the packaged default included), unknown key in
            ``bag`` (named), unknown role in ``bag.topics``.
    """
    path = data_file(DEFAULT_CONFIG) if path is None else Path(path)
    try:
        data = load_yaml(path.read_text(encoding="utf-8")) or {}
    except (OSError, ValueError) as err:
        raise ConfigError(f"{path}: cannot read sysid config ({err})") from err
    section = data.get("bag") or {}
    if not isinstance(section, Mapping):
        raise ConfigError(f"{path}: bag must be a mapping")
    unknown = [k for k in section if k not in _BAG_CONFIG_KEYS]
    if unknown:
        raise ConfigError(f"{path}: unknown key bag.{unknown[0]} (allowed: {', '.join(_BAG_CONFIG_KEYS)})")
    topics = dict(section.get("topics") or {})
    bad = [r for r in topics if r not in ROLES]
    if bad:
        raise ConfigError(f"{path}: unknown role bag.topics.{bad[0]} (roles: {', '.join(ROLES)})")
    return BagConfig(namespace=str(section.get("namespace") or "/thinshell"), effector=section.get("effector"),
                     sensor=section.get("sensor"), topics={k: str(v) for k, v in topics.items()})


def _join(namespace: str, topic: str) -> str:
    if topic.startswith("/"):
        return topic
    return "/" + "/".join(p for p in (namespace.strip("/"), topic.strip("/")) if p)


def resolve_roles(config: BagConfig | None = None, scene: SceneFile | None = None,
                  roles: Mapping[str, str] | None = None) -> dict[str, str]:
    """Topic name of every role (see the module docstring for the precedence).

    Raises:
        ConfigError: ``roles`` names an unknown role.
    """
    config = config or BagConfig()
    effector, sensor = config.effector, config.sensor
    if scene is not None and len(scene.sensors) == 1:
        only = next(iter(scene.sensors.values()))
        sensor = sensor or only.name
        effector = effector or only.effector
    if isinstance(scene, TaskSceneFile) and scene.effector_names:
        effector = effector or scene.effector_names[0]
    effector, sensor = effector or "ee", sensor or "tactile"
    out = {r: _join(config.namespace, ROLE_TEMPLATES[r].format(effector=effector, sensor=sensor)) for r in ROLES}
    for source in (config.topics, roles or {}):
        for role, topic in source.items():
            if role not in ROLES:
                raise ConfigError(f"unknown bag role {role!r} (roles: {', '.join(ROLES)})")
            out[role] = _join(config.namespace, topic)
    return out


# ------------------------------------------------------------------------------- raw reading
def _read_rosbags(path: Path, wanted: set[str]) -> tuple[dict[str, TopicInfo], dict[str, list[tuple[int, Any]]]]:
    """All connections, and ``(log_ns, message)`` of the wanted topics, via rosbags."""
    from rosbags.rosbag2 import Reader  # optional heavy dependency: bag libraries, loaded on first use

    topics: dict[str, TopicInfo] = {}
    msgs: dict[str, list[tuple[int, Any]]] = {}
    with Reader(path) as reader:
        for conn in reader.connections:
            prev = topics.get(conn.topic)
            count = conn.msgcount + (prev.message_count if prev else 0)
            topics[conn.topic] = TopicInfo(conn.topic, conn.msgtype, count)
        selected = [c for c in reader.connections if c.topic in wanted]
        store = codec.typestore()
        for conn, log_ns, raw in reader.messages(connections=selected):
            msgs.setdefault(conn.topic, []).append((int(log_ns), store.deserialize_cdr(raw, conn.msgtype)))
    return topics, msgs


def _read_mcap_library(path: Path, wanted: set[str]) -> tuple[dict[str, TopicInfo], dict[str, list[tuple[int, Any]]]]:
    """Same as :func:`_read_rosbags` with the ``mcap`` reader and the ``mcap_ros2`` decoder."""
    from mcap.reader import make_reader  # optional heavy dependency: bag libraries, loaded on first use
    from mcap_ros2.decoder import DecoderFactory

    msgs: dict[str, list[tuple[int, Any]]] = {}
    counts: dict[str, int] = {}
    types: dict[str, str] = {}
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        if summary is not None:
            for ch in summary.channels.values():
                types[ch.topic] = codec.normalize_msgtype(summary.schemas[ch.schema_id].name)
                counts.setdefault(ch.topic, 0)
        for schema, channel, message, decoded in reader.iter_decoded_messages(topics=sorted(wanted)):
            types[channel.topic] = codec.normalize_msgtype(schema.name)
            msgs.setdefault(channel.topic, []).append((int(message.log_time), decoded))
        if summary is not None and summary.statistics is not None:
            for cid, n in summary.statistics.channel_message_counts.items():
                counts[summary.channels[cid].topic] = counts.get(summary.channels[cid].topic, 0) + n
    topics = {t: TopicInfo(t, types[t], counts.get(t, len(msgs.get(t, [])))) for t in types}
    return topics, msgs


def _metadata_counts(bag_dir: Path) -> dict[str, int] | None:
    meta = bag_dir / "metadata.yaml"
    if not meta.is_file():
        return None
    try:
        info = load_yaml(meta.read_text(encoding="utf-8"))["rosbag2_bagfile_information"]
        return {t["topic_metadata"]["name"]: int(t["message_count"]) for t in info["topics_with_message_count"]}
    except (KeyError, TypeError, ValueError) as err:
        raise BagReadError(f"{meta}: unreadable rosbag2 metadata ({err})") from err


def _metadata_files(bag_dir: Path) -> list[str]:
    meta = bag_dir / "metadata.yaml"
    try:
        info = load_yaml(meta.read_text(encoding="utf-8"))["rosbag2_bagfile_information"]
        return [str(p) for p in (info.get("relative_file_paths") or [])]
    except (OSError, KeyError, TypeError, ValueError, AttributeError) as err:
        raise BagReadError(f"{meta}: unreadable rosbag2 metadata ({err})") from err


def locate_files(path: Path) -> tuple[list[Path], Path, Path | None]:
    """``(mcap files in order, directory holding scene.yaml, metadata dir or None)``.

    A directory holds one ``.mcap`` file, or several (a split bag) when ``metadata.yaml`` lists
    exactly those in ``relative_file_paths``.

    Raises:
        BagReadError: missing path, no ``metadata.yaml``, files that disagree with it.
    """
    if not path.exists():
        raise BagReadError(f"{path}: bag path does not exist")
    if path.is_dir():
        if not (path / "metadata.yaml").is_file():
            raise BagReadError(f"{path}: not a rosbag2 directory (no metadata.yaml)")
        mcaps = sorted(path.glob("*.mcap"))
        if len(mcaps) > 1:
            listed = _metadata_files(path)
            if sorted(listed) != sorted(p.name for p in mcaps):
                raise BagReadError(f"{path}: {len(mcaps)} .mcap files in the bag directory but metadata.yaml lists "
                                   f"{listed} (relative_file_paths)")
            return [path / name for name in listed], path, path
        if len(mcaps) != 1:
            raise BagReadError(f"{path}: expected one .mcap file in the bag directory, found {len(mcaps)}")
        return mcaps, path, path
    if path.suffix != ".mcap":
        raise BagReadError(f"{path}: not a bag directory nor a .mcap file")
    return [path], path.parent, None


def _locate(path: Path) -> tuple[Path, Path, Path | None]:
    """``(first mcap_path, directory holding scene.yaml, metadata dir or None)``."""
    files, scene_dir, meta_dir = locate_files(path)
    return files[0], scene_dir, meta_dir


def _read_raw(path: Path, mcap_path: Path, is_dir: bool, wanted: set[str]) -> tuple[dict[str, TopicInfo], dict]:
    errors = []
    readers: list[tuple[str, Callable[..., Any], Path]] = [("rosbags", _read_rosbags, path)]
    if not is_dir:
        readers.append(("mcap", _read_mcap_library, mcap_path))
    for name, read, target in readers:
        try:
            return read(target, wanted)
        except Exception as err:  # noqa: BLE001 - any decoder failure means an unreadable file
            errors.append(f"{name}: {type(err).__name__}: {' '.join(str(err).split())}")
    raise BagReadError(f"{mcap_path}: corrupt or truncated MCAP file ({'; '.join(errors)})")


def sha256_file(path: Path | Sequence[Path], chunk: int = 1 << 20) -> str:
    """Hex SHA-256 of a file (or of several files' bytes, in the given order)."""
    h = hashlib.sha256()
    for one in ([path] if isinstance(path, (str, Path)) else path):
        with open(one, "rb") as fh:
            for block in iter(lambda: fh.read(chunk), b""):
                h.update(block)
    return h.hexdigest()


# ------------------------------------------------------------------------------------ decoding
def _decode(role: str, topic: str, items: list[tuple[int, Any]], msgtype: str = "",
            check_world: bool = False) -> tuple[np.ndarray, np.ndarray, tuple[str, ...], str]:
    """Decode messages of one role into ``(t_ns, values, field_names, frame_id)`` (file order).

    ``msgtype`` tells an Image from a CompressedImage; ``check_world`` makes a pose in another frame
    than ``world`` an error."""
    stamps: list[int] = []
    rows: list[np.ndarray] = []
    names: tuple[str, ...] = ()
    frame = ""
    if role in ("pose", "pose_cmd"):
        for _, m in items:
            t, v, frame = codec.parse_pose_stamped(m)
            if check_world and frame != WORLD_FRAME:
                raise BagReadError(f"topic {topic}: header frame_id is {frame!r} at stamp {t} ns, expected "
                                   f"{WORLD_FRAME!r} (INTERFACES.md); a pose in another frame needs a recording map "
                                   "(docs/recording_map.md)")
            stamps.append(t)
            rows.append(v)
    elif role == "wrench":
        for _, m in items:
            t, v, frame = codec.parse_wrench_stamped(m)
            stamps.append(t)
            rows.append(v)
    elif role in ("markers", "sheet_points"):
        present = codec.cloud_field_names(items[0][1])
        if not {"x", "y", "z"} <= set(present):
            raise BagReadError(f"topic {topic}: point cloud fields are {present}; x y z are required")
        names = ("x", "y", "z") + tuple(n for n in ("u", "v") if n in present and role == "markers")
        width = None
        for _, m in items:
            try:
                t, v, frame = codec.parse_point_cloud2(m, names)
            except (KeyError, ValueError) as err:
                raise BagReadError(f"topic {topic}: bad point cloud at stamp {codec.stamp_to_ns(m.header.stamp)} ns "
                                   f"({err})") from err
            if width is None:
                width = v.shape[0]
            elif v.shape[0] != width:
                raise BagReadError(f"topic {topic}: point count changes from {width} to {v.shape[0]} at stamp {t} ns "
                                   "(the point order must be fixed)")
            stamps.append(t)
            rows.append(v)
    elif role == "image":
        for _, m in items:
            try:
                t, img, frame = images.parse_any_image(msgtype or codec.IMAGE, m)
            except ValueError as err:
                raise BagReadError(f"topic {topic}: {err}") from err
            stamps.append(t)
            rows.append(img)
    elif role == "clock":
        for _, m in items:
            t = codec.parse_clock(m)
            stamps.append(t)
            rows.append(np.asarray(t * 1e-9))
    else:
        raise ValueError(f"unknown role {role!r}")
    return np.asarray(stamps, dtype=np.int64), np.stack(rows), names, frame


def _clean(role: str, topic: str, t_ns: np.ndarray, values: np.ndarray,
           warn: Callable[[str], None], keep: str = "first") -> tuple[np.ndarray, np.ndarray, int, bool]:
    """Drop non-finite samples, sort by stamp (stable), drop repeated stamps but the ``keep`` one of each
    (``"first"``; ``"last"`` for commands by log time: of several taken at one time the last is in force)."""
    n = t_ns.shape[0]
    finite = np.ones(n, dtype=bool) if values.dtype == np.uint8 else \
        np.all(np.isfinite(values.reshape(n, -1)), axis=1)
    dropped = int(n - finite.sum())
    if dropped == n:
        raise BagReadError(f"topic {topic}: all {n} samples contain NaN/inf")
    if dropped:
        warn(f"topic {topic}: dropped {dropped} of {n} samples containing NaN/inf")
        t_ns, values = t_ns[finite], values[finite]
    resorted = bool(np.any(np.diff(t_ns) < 0))
    if resorted:
        order = np.argsort(t_ns, kind="stable")
        warn(f"topic {topic}: {int(np.sum(np.diff(t_ns) < 0))} stamps out of order; samples sorted by stamp")
        t_ns, values = t_ns[order], values[order]
    same = np.diff(t_ns) == 0
    if same.any():
        if keep == "first":  # a sensor sample stamped twice is an anomaly worth a warning
            repeated = np.concatenate([[False], same])
            warn(f"topic {topic}: dropped {int(repeated.sum())} samples with a repeated stamp (kept the first)")
        else:  # commands by log time: several taken between two steps, the last one is in force
            repeated = np.concatenate([same, [False]])
        t_ns, values = t_ns[~repeated], values[~repeated]
    return t_ns, values, dropped, resorted


# ------------------------------------------------------------------------------------- facade
def open_bag(path: str | Path, roles: Mapping[str, str] | None = None, config: BagConfig | str | Path | None = None,
             skip_roles: tuple[str, ...] = (), scene: str | Path | SceneFile | None = None,
             recording_map: str | Path | RecordingMap | None = None,
             window_s: tuple[float | None, float | None] | None = None) -> BagContents:
    """Open a recording and read its role topics.

    Args:
        path: rosbag2 directory (``metadata.yaml`` + one ``.mcap``, or the several files of a split
            bag that ``metadata.yaml`` lists) or a bare ``.mcap`` file.
        roles: role -> topic overrides for this call (relative names join the namespace); not with a map.
        config: :class:`BagConfig`, a sysid config file, or None for ``sysid/data/default.yaml``.
        skip_roles: roles not to decode (e.g. ``("image",)`` to save time).
        scene: scene file (or parsed scene) to use instead of the ``scene.yaml`` beside the bag.
        recording_map: recording map (file or parsed) saying where each role comes from
            (:mod:`sysid.bagio.recording_map`); None = ``recording.yaml`` in the bag directory when
            there is one, else today's contract (INTERFACES.md).
        window_s: ``(t_start, t_end)`` s after the recording's first role stamp (either None = open):
            only the samples inside are kept.

    Returns:
        :class:`BagContents`.

    Raises:
        BagReadError: see the module docstring (each message names the file or the topic).
        ConfigError: invalid ``scene.yaml`` beside the bag, invalid role overrides, an invalid recording
            map, or an empty / inverted window.
    """
    path = Path(path).absolute()
    notes: list[str] = []

    def warn(message: str) -> None:
        notes.append(message)
        warnings.warn(message, BagWarning, stacklevel=3)

    files, scene_dir, meta_dir = locate_files(path)
    mcap_path = files[0]
    if scene is not None:
        scene_path = Path(scene.source) if isinstance(scene, (SceneFile, TaskSceneFile)) else Path(scene).absolute()
        scene = load_any_scene_file(scene)
    else:
        scene_path = scene_dir / SCENE_FILENAME
        scene = load_any_scene_file(scene_path) if scene_path.is_file() else None
    if isinstance(scene, TaskSceneFile) and not scene.sensors:
        skip_roles = (*skip_roles, "markers", "wrench", "image")  # a task scene without a tactile sensor
    map_path = None
    if recording_map is None and meta_dir is not None:
        recording_map = find_recording_map(meta_dir)
    if recording_map is not None:
        map_path = Path(recording_map.source) if isinstance(recording_map, RecordingMap) else Path(recording_map)
        recording_map = load_recording_map(recording_map)
        if roles:
            raise ConfigError(f"role topic overrides ({', '.join(roles)}) and a recording map ({map_path}) exclude "
                              "each other: name the topics in the map")
    if not isinstance(config, BagConfig):
        config = load_bag_config(config)
    if recording_map is not None:
        mapped = recording_map.topics()
        role_topics = {r: mapped.get(r, "") for r in ROLES}
        if recording_map.pose == "tf":
            role_topics["pose"] = recording_map.tf_topic
        wanted = {t for r, t in mapped.items() if r not in skip_roles}
    else:
        role_topics = resolve_roles(config, scene, roles)
        wanted = {t for r, t in role_topics.items() if r not in skip_roles}
    topics, raw = _read_raw(path, mcap_path, meta_dir is not None, wanted)

    if meta_dir is not None:
        for topic, count in (_metadata_counts(meta_dir) or {}).items():
            if topic in wanted and len(raw.get(topic, [])) != count:
                raise BagReadError(f"{mcap_path}: truncated or inconsistent: metadata.yaml lists {count} messages on "
                                   f"{topic}, the file holds {len(raw.get(topic, []))}")
    if sum(t.message_count for t in topics.values()) == 0:
        raise BagReadError(f"{path}: bag is empty (no messages)")

    decoded: dict[str, tuple[str, str, tuple]] = {}
    camera = None
    taken = None
    if recording_map is not None:
        decoded, camera = cell.decode_mapped(recording_map, raw, {t: i.msgtype for t, i in topics.items()}, str(path),
                                             _decode, warn, skip_roles)
    else:
        for role in ROLES:
            topic = role_topics[role]
            if role in skip_roles:
                continue
            info = topics.get(topic)
            if info is not None and info.msgtype not in ROLE_ACCEPTED[role]:
                raise BagReadError(f"topic {topic} (role {role}) has type {info.msgtype}, expected "
                                   f"{' or '.join(ROLE_ACCEPTED[role])} in {path}")
            items = raw.get(topic, [])
            if role == "pose_cmd" and items:
                items = _commands_in_world(topic, items, warn)
            if items:
                decoded[role] = (topic, info.msgtype, _decode(role, topic, items, info.msgtype, check_world=True))
            if role == "pose_cmd" and items:
                taken = _taken(topic, info.msgtype, items, decoded[role][2])

    series: dict[str, Series] = {}
    missing: list[str] = []
    for role in ROLES:
        if role in skip_roles:
            continue
        if role not in decoded:
            missing.append(role)
            topic = role_topics[role]
            if role in MEASUREMENT_ROLES:
                if not topic:
                    warn(f"role {role} has no topic in the recording map {map_path}; the evidence lacks that channel")
                else:
                    state = "has no messages" if topic in topics else "is missing"
                    warn(f"topic {topic} (role {role}) {state} in {path}; the evidence lacks that channel")
            continue
        topic, msgtype, (t_ns, values, names, frame) = decoded[role]
        t_ns, values, dropped, resorted = _clean(role, topic, t_ns, values, warn)
        series[role] = Series(role, topic, msgtype, t_ns, values, names, frame, dropped, resorted)

    if window_s is not None and series:
        series = _window(series, window_s, path)
        for role in decoded:
            if role not in series:
                missing.append(role)
                warn(f"topic {decoded[role][0]} (role {role}) has no sample in the time window {list(window_s)} s; "
                     "the evidence lacks that channel")
    for s in series.values():
        s.t_ns.setflags(write=False)
        s.values.setflags(write=False)
    stamps = [s.t_ns for s in series.values()]
    start = int(min(s[0] for s in stamps)) if stamps else 0
    end = int(max(s[-1] for s in stamps)) if stamps else 0
    return BagContents(
        path=path, mcap_path=mcap_path, sha256=sha256_file(files), topics=topics, roles=role_topics,
        series=series, missing_roles=tuple(missing), scene=scene, scene_path=scene_path if scene else None,
        start_ns=start, end_ns=end, notes=tuple(notes), mcap_paths=tuple(files),
        recording_map=map_path.absolute() if map_path is not None else None, camera=camera, pose_cmd_taken=taken,
    )


def _taken(topic: str, msgtype: str, items: list[tuple[int, Any]], decoded: tuple) -> Series:
    """The commands ``items`` (decoded by :func:`_decode`, file order) stamped with their log times, cleaned
    as :func:`read_effector_streams` cleans them (the last of several taken at one time kept; their
    warnings were given for the header stamps already)."""
    _, values, names, frame = decoded
    t_log = np.asarray([log for log, _ in items], dtype=np.int64)
    t_ns, values, dropped, resorted = _clean("pose_cmd", topic, t_log, values, lambda _m: None, keep="last")
    t_ns.setflags(write=False)
    values.setflags(write=False)
    return Series("pose_cmd", topic, msgtype, t_ns, values, names, frame, dropped, resorted)


def _commands_in_world(topic: str, items: list[tuple[int, Any]], warn: Callable[[str], None]) -> list[tuple[int, Any]]:
    """The commands stamped in ``world``; the others (a robot refuses them, a recorder keeps them) dropped
    with a warning. All in another frame: left for :func:`_decode` to refuse (a recording map is needed)."""
    frames = [str(m.header.frame_id) for _, m in items]
    keep = [f == WORLD_FRAME for f in frames]
    if any(keep) and not all(keep):
        other = sorted({f for f, k in zip(frames, keep) if not k})
        warn(f"topic {topic}: dropped {len(keep) - sum(keep)} of {len(keep)} commands in frame(s) {other} instead of "
             f"{WORLD_FRAME!r}")
        return [item for item, k in zip(items, keep) if k]
    return items


def _window(series: dict[str, Series], window_s: tuple[float | None, float | None], path: Path) -> dict[str, Series]:
    """Every series cut to ``[start + t_start, start + t_end]`` (start: the first role stamp).

    Raises:
        ConfigError: ``t_end <= t_start`` or a negative bound.
        BagReadError: the window holds no sample of any role.
    """
    t_start, t_end = window_s
    if (t_start is not None and t_start < 0) or (t_end is not None and t_end <= 0) or \
            (t_start is not None and t_end is not None and t_end <= t_start):
        raise ConfigError(f"time window --t-start {t_start} / --t-end {t_end} s must satisfy 0 <= t_start < t_end")
    first = min(int(s.t_ns[0]) for s in series.values())
    lo = first + (int(round(t_start * 1e9)) if t_start is not None else 0)
    hi = first + int(round(t_end * 1e9)) if t_end is not None else np.iinfo(np.int64).max
    out = {}
    for role, s in series.items():
        keep = (s.t_ns >= lo) & (s.t_ns <= hi)
        if keep.any():
            out[role] = dataclasses.replace(s, t_ns=s.t_ns[keep], values=s.values[keep])
    if not out:
        raise BagReadError(f"{path}: no sample in the time window [{t_start}, {t_end}] s after the first stamp")
    return out


EFFECTOR_STREAMS = {"pose": codec.POSE_STAMPED, "pose_cmd": codec.POSE_STAMPED, "gripper_cmd": codec.FLOAT64}
"""Per-effector streams of a task-scene recording (``<namespace>/<effector>/<stream>``) and their types."""


def read_effector_streams(path: str | Path, effectors: list[str], namespace: str = "/thinshell",
                          recording_map: str | Path | RecordingMap | None = None
                          ) -> dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """Every effector's ``pose``, ``pose_cmd`` and ``gripper_cmd`` stream of a recording.

    A task scene moves several effectors (and grippers); :func:`open_bag` reads the role topics of
    one effector only, this reads them all. Samples are cleaned as :func:`open_bag` does.

    Args:
        path: rosbag2 directory or ``.mcap`` file.
        effectors: effector names of the scene.
        namespace: topic prefix.
        recording_map: a real cell's map whose ``effectors`` section says where each effector's streams
            come from (TF or pose topics in any frame, commands of another link;
            :func:`sysid.bagio.cell.decode_mapped_effectors`); None, or a map without that section: the
            topics above.

    Returns:
        effector -> stream -> ``(t_ns (N,) int64, values)``, values ``(N, 7)`` poses [x y z qx qy
        qz qw] (m) or ``(N,)`` finger openings (m); streams not in the bag are absent. ``pose`` is
        stamped with its header stamp (when it was measured); the commands ``pose_cmd`` and
        ``gripper_cmd`` with their log time: when the robot took them (the sim node logs a command
        at the sim time it takes it, between steps), not when a commander scheduled them (its header
        stamp, which a robot that steps faster than its commander receives a step or two late). Of
        several commands taken at one time (queued during a step) the last, the one in force, is kept.

    Raises:
        BagReadError: unreadable bag, or a stream topic of another message type (names the topic).
    """
    path = Path(path).absolute()
    mcap_path, _, meta_dir = _locate(path)
    rmap = load_recording_map(recording_map) if recording_map is not None else None
    if rmap is not None and rmap.effectors:
        return _read_mapped_effector_streams(path, mcap_path, meta_dir is not None, rmap, effectors)
    topic_of = {(e, k): _join(namespace, f"{e}/{k}") for e in effectors for k in EFFECTOR_STREAMS}
    topics, raw = _read_raw(path, mcap_path, meta_dir is not None, set(topic_of.values()))
    out: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]] = {}
    for (effector, kind), topic in topic_of.items():
        items = raw.get(topic, [])
        if not items:
            continue
        if topics[topic].msgtype != EFFECTOR_STREAMS[kind]:
            raise BagReadError(f"topic {topic} has type {topics[topic].msgtype}, expected {EFFECTOR_STREAMS[kind]} "
                               f"in {path}")
        if kind == "gripper_cmd":
            t_ns = np.asarray([log for log, _ in items], dtype=np.int64)
            values = np.asarray([codec.parse_float64(m) for _, m in items], dtype=np.float64)
        else:
            t_ns, values, _, _ = _decode("pose", topic, items)
            if kind == "pose_cmd":  # a command's time is when the robot took it (docstring)
                t_ns = np.asarray([log for log, _ in items], dtype=np.int64)
        t_ns, values, _, _ = _clean(kind, topic, t_ns, values, lambda m: warnings.warn(m, BagWarning, stacklevel=3),
                                    keep="first" if kind == "pose" else "last")
        out.setdefault(effector, {})[kind] = (t_ns, values)
    return out


def _read_mapped_effector_streams(path: Path, mcap_path: Path, is_dir: bool, rmap: RecordingMap,
                                  effectors: list[str]) -> dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """:func:`read_effector_streams` through a recording map's ``effectors`` section (cleaned the same way)."""
    wanted = {rmap.tf_topic, rmap.tf_static_topic}
    for spec in rmap.effectors.values():
        wanted |= {src.topic for src in (spec.pose, spec.pose_cmd, spec.gripper_cmd)
                   if src is not None and not isinstance(src, str)}
    topics, raw = _read_raw(path, mcap_path, is_dir, wanted)
    decoded = cell.decode_mapped_effectors(rmap, raw, {t: i.msgtype for t, i in topics.items()}, str(path), effectors)
    out: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]] = {}
    for effector, streams in decoded.items():
        for kind, (t_ns, values) in streams.items():
            t_ns, values, _, _ = _clean(kind, f"effectors.{effector}.{kind} of {rmap.source}", t_ns, values,
                                        lambda m: warnings.warn(m, BagWarning, stacklevel=3),
                                        keep="first" if kind == "pose" else "last")
            out.setdefault(effector, {})[kind] = (t_ns, values)
    return out
