"""The evidence bundle: a recording in SI units with integer-nanosecond stamps, ready for fitting.

Fitting and diagnosis read an :class:`Evidence`; they never open a bag (ARCHITECTURE.md). A bundle
holds one array per channel with its own stamps, the parsed scene, provenance (bag path and SHA-256
of its MCAP file) and the white-noise level of every channel estimated from the data itself
(:mod:`sysid.noise`). A channel the recording lacks is ``None``, listed in ``channels_missing``
with the reason, and absent from ``t_ns`` and ``noise``.

Channels (shapes; units):

============== ==================== ===========================================================
channel        array                meaning
============== ==================== ===========================================================
pose           ``(N, 7)``           measured effector pose x y z (m) qx qy qz qw, ``world``
pose_cmd       ``(N, 7)``           commanded effector pose
markers_xyz    ``(M, k, 3)``        marker positions in the sensor frame (m)
markers_uv     ``(M, k, 2)``        marker pixels (px); markers_xyz's stamps, or the images' (read off them)
wrench         ``(W, 6)``           Fx Fy Fz (N) Tx Ty Tz (N m) on the gel, sensor frame
sheet_points   ``(S, p, 3)``        tracked sheet points in ``world`` (m)
image          ``(F, h, w)`` uint8  rendered / camera marker image (optional)
============== ==================== ===========================================================

``markers_uv_weight`` ``(M, k)`` goes with ``markers_uv`` (its stamps): a per-marker, per-sample factor
in ``[0, 1]`` on the inverse variance of both pixel coordinates of that marker, which the fit's whitened
residual is multiplied by the square root of (:meth:`sysid.observation.ObservationModel.residuals`).
Pixels read off images (:func:`markers_from_images`) carry the tracker's weights
(:func:`sysid.markers_image.track_markers`): 1 for a marker found whole, the visible fraction of a
marker cut by the image border, 0 for a marker not seen and interpolated from its lattice neighbours.
Pixels from a markers topic have ``markers_uv_weight = None``, meaning weight 1 everywhere.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Mapping, Sequence

import numpy as np

from sim_core.errors import BagReadError, CalibrationError
from sim_core.scenes.scene_file import SceneFile
from sysid.bagio import BagWarning
from sim_core.scenes.task_file import TaskSceneFile
from sysid.bagio.reader import BagConfig, BagContents, load_bag_config, open_bag, read_effector_streams
from sysid.bagio.recording_map import RecordingMap
from sysid.noise import estimate_noise, noise_config

CHANNELS = ("pose", "pose_cmd", "markers_xyz", "markers_uv", "wrench", "sheet_points", "image")
CHANNEL_ROLE = {"pose": "pose", "pose_cmd": "pose_cmd", "markers_xyz": "markers", "markers_uv": "markers",
                "wrench": "wrench", "sheet_points": "sheet_points", "image": "image"}
POSE_CHANNELS = ("pose", "pose_cmd")


@dataclass(frozen=True)
class EvidenceSource:
    """Provenance of an evidence bundle.

    Attributes:
        bag_path: bag directory or ``.mcap`` file read.
        mcap_path: the MCAP file.
        sha256: hex SHA-256 of the MCAP file.
        scene_path: scene file used, or None.
        topics: channel -> topic it came from.
        recording_map: the recording map the bag was read through (its topics are then the map's,
            not INTERFACES.md's), or None.
    """

    bag_path: Path
    mcap_path: Path
    sha256: str
    scene_path: Path | None
    topics: dict[str, str]
    recording_map: Path | None = None


@dataclass(frozen=True)
class Evidence:
    """One recording as per-channel arrays (see the module docstring for shapes and units).

    Attributes:
        source: :class:`EvidenceSource`.
        scene: the parsed scene file, or None when the bag has none.
        t_ns: channel -> stamps ``(n,)`` int64 ns, strictly increasing (present channels only).
        pose, pose_cmd, markers_xyz, markers_uv, wrench, sheet_points, image: arrays or None.
        markers_uv_weight: ``(M, k)`` per-marker weights in ``[0, 1]`` of ``markers_uv`` (module
            docstring): the tracker's when the pixels were read off images, None (weight 1
            everywhere) when they came from a markers topic.
        clock_t_ns: ``/clock`` values (ns) when recorded, else None.
        noise: channel -> estimated white-noise standard deviation per last axis (SI / px), e.g.
            ``noise["markers_xyz"]`` is ``(3,)`` m and ``noise["wrench"]`` is ``(6,)`` N, N m.
            No entry for the image.
        channels_present: channels with data, in :data:`CHANNELS` order.
        channels_missing: channel -> why it is absent (names the topic).
        notes: warnings raised while reading (dropped samples, re-sorted stamps, missing topics).
        effectors: for a task scene (``kind: task``), every effector's recorded streams: effector ->
            ``"pose"`` / ``"pose_cmd"`` / ``"gripper_cmd"`` -> ``(t_ns (N,), values)``, poses
            ``(N, 7)``, openings ``(N,)`` m (:func:`sysid.bagio.reader.read_effector_streams`);
            empty for a version-1 scene (its one effector is the ``pose`` channel).
        pose_cmd_taken: ``(t_ns (N,), poses (N, 7))``: the ``pose_cmd`` channel's commands stamped with
            when the robot took them (their log time; the last of several taken at one time), the whole
            recording (:attr:`sysid.bagio.reader.BagContents.pose_cmd_taken`); None without commands or
            through a recording map.
    """

    source: EvidenceSource
    scene: SceneFile | None
    t_ns: dict[str, np.ndarray]
    pose: np.ndarray | None = None
    pose_cmd: np.ndarray | None = None
    markers_xyz: np.ndarray | None = None
    markers_uv: np.ndarray | None = None
    wrench: np.ndarray | None = None
    sheet_points: np.ndarray | None = None
    image: np.ndarray | None = None
    markers_uv_weight: np.ndarray | None = None
    clock_t_ns: np.ndarray | None = None
    noise: dict[str, np.ndarray] = field(default_factory=dict)
    channels_present: tuple[str, ...] = ()
    channels_missing: dict[str, str] = field(default_factory=dict)
    notes: tuple[str, ...] = ()
    effectors: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]] = field(default_factory=dict)
    pose_cmd_taken: tuple[np.ndarray, np.ndarray] | None = None

    def values(self, channel: str) -> np.ndarray:
        """The array of ``channel``.

        Raises:
            KeyError: unknown channel, or a channel this recording lacks (message says why).
        """
        if channel not in CHANNELS:
            raise KeyError(f"unknown evidence channel {channel!r} (channels: {', '.join(CHANNELS)})")
        if channel not in self.channels_present:
            raise KeyError(f"{self.source.bag_path}: no {channel} channel ({self.channels_missing.get(channel, '')})")
        return getattr(self, channel)

    @property
    def start_ns(self) -> int:
        """Earliest stamp over all channels, ns."""
        return int(min(t[0] for t in self.t_ns.values()))

    @property
    def end_ns(self) -> int:
        """Latest stamp over all channels, ns."""
        return int(max(t[-1] for t in self.t_ns.values()))

    def crop(self, start_ns: int, end_ns: int) -> "Evidence":
        """The samples with ``start_ns <= t <= end_ns`` of every channel (noise estimates kept).

        Raises:
            ValueError: the window leaves a present channel without samples.
        """
        t_new: dict[str, np.ndarray] = {}
        arrays: dict[str, Any] = {}
        for ch in self.channels_present:
            t = self.t_ns[ch]
            keep = (t >= start_ns) & (t <= end_ns)
            if not keep.any():
                raise ValueError(f"window [{start_ns}, {end_ns}] ns holds no {ch} sample")
            t_new[ch] = _frozen(t[keep])
            arrays[ch] = _frozen(getattr(self, ch)[keep])
            if ch == "markers_uv" and self.markers_uv_weight is not None:
                arrays["markers_uv_weight"] = _frozen(self.markers_uv_weight[keep])
        clock = self.clock_t_ns
        if clock is not None:
            clock = _frozen(clock[(clock >= start_ns) & (clock <= end_ns)])
        return dataclasses.replace(self, t_ns=t_new, clock_t_ns=clock, **arrays)

    def summary(self) -> dict[str, Any]:
        """JSON-friendly description: source, duration, sample counts, noise, missing channels."""
        return {
            "bag": str(self.source.bag_path), "sha256": self.source.sha256,
            "scene": str(self.source.scene_path) if self.source.scene_path else None,
            "duration_s": (self.end_ns - self.start_ns) * 1e-9,
            "samples": {ch: int(self.t_ns[ch].shape[0]) for ch in self.channels_present},
            "noise": {ch: [float(v) for v in s] for ch, s in self.noise.items()},
            "channels_missing": dict(self.channels_missing), "notes": list(self.notes),
        }


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, copy=True)
    a.setflags(write=False)
    return a


def _with_camera(scene: SceneFile, camera: Mapping[str, float]) -> SceneFile:
    """The scene with its only sensor's camera from a recorded camera_info: intrinsics (fx fy cx cy width
    height) and, when the info gives a distortion, the radial ``k1 k2`` (a zero where the scene has none
    stays none: both mean no distortion).

    Raises:
        BagReadError: the scene has not exactly one sensor (which camera the info belongs to is unknown).
    """
    if len(scene.sensors) != 1:
        raise BagReadError(f"{scene.source}: a recorded camera_info needs a scene with one tactile sensor, it has "
                           f"{len(scene.sensors)}")
    name, sensor = next(iter(scene.sensors.items()))
    values: dict[str, Any] = {}
    for key, value in camera.items():
        if key in ("k1", "k2"):
            values[key] = None if value == 0.0 and getattr(sensor.camera, key) is None else float(value)
        else:
            values[key] = type(getattr(sensor.camera, key))(value)
    cam = dataclasses.replace(sensor.camera, **values)
    return dataclasses.replace(scene, sensors={name: dataclasses.replace(sensor, camera=cam)})


def _check_against_scene(bag: BagContents, scene: SceneFile) -> None:
    """Point counts must match the scene (marker grid, sheet resolution)."""
    sensors = [s for s in scene.sensors.values() if bag.roles["markers"].rstrip("/").endswith(f"{s.name}/markers")]
    if bag.recording_map is not None and len(scene.sensors) == 1:  # a map names topics freely: the only sensor
        sensors = list(scene.sensors.values())
    markers = bag.series.get("markers")
    if markers is not None and sensors:
        k = markers.values.shape[1]
        if k != sensors[0].marker_count:
            raise BagReadError(f"topic {markers.topic} has {k} points but sensor {sensors[0].name} of {scene.source} "
                               f"has a {sensors[0].marker_grid[0]}x{sensors[0].marker_grid[1]} marker grid")
    sheet = bag.series.get("sheet_points")
    if sheet is not None and not isinstance(scene, TaskSceneFile):  # a task scene's count is checked on replay
        p = sheet.values.shape[1]
        nx, ny = scene.sheet.resolution
        if p != nx * ny:
            raise BagReadError(f"topic {sheet.topic} has {p} points but the sheet of {scene.source} has a "
                               f"{nx}x{ny} grid")


def load_evidence(bag_path: str | Path, scene_path: str | Path | SceneFile | None = None,
                  roles: Mapping[str, str] | None = None, config: BagConfig | str | Path | None = None,
                  include_image: bool | Literal["auto"] = True,
                  recording_map: str | Path | RecordingMap | None = None,
                  t_start: float | None = None, t_end: float | None = None) -> Evidence:
    """Read a recording into an :class:`Evidence` bundle and estimate each channel's noise.

    Args:
        bag_path: rosbag2 directory or bare ``.mcap`` file.
        scene_path: scene file overriding the ``scene.yaml`` beside the bag.
        roles: role -> topic overrides (see :func:`sysid.bagio.open_bag`).
        config: sysid config (``bag`` and ``noise`` sections); default the packaged ``sysid/data/default.yaml``.
        include_image: decode the image topic when present (True), never (False), or only when the
            recording has no markers topic (``"auto"``: the image stream is then the marker source).
            When the image is decoded and there is no markers topic, ``markers_uv`` is read off the
            frames (:func:`markers_from_images`).
        recording_map: where each role of a real cell's recording comes from (docs/recording_map.md);
            None = ``recording.yaml`` in the bag directory when there is one, else today's contract.
            A ``camera_info`` topic in the map replaces the scene's camera intrinsics and, when it
            gives a distortion, its radial ``k1 k2`` (:func:`sysid.bagio.images.parse_camera_info`).
        t_start, t_end: keep only the samples from ``t_start`` to ``t_end`` s after the recording's
            first stamp (None = open); the noise is estimated inside that window.

    Returns:
        the bundle; arrays are read-only.

    Raises:
        BagReadError: unreadable bag (see :mod:`sysid.bagio.reader`), none of pose, markers, wrench,
            sheet_points present, or point counts that contradict the scene.
        ConfigError: invalid scene or config.
    """
    config_path = config if isinstance(config, (str, Path)) else None
    auto = include_image == "auto"
    window = None if t_start is None and t_end is None else (t_start, t_end)
    bag = open_bag(bag_path, roles=roles, config=config, skip_roles=() if include_image is True else ("image",),
                   scene=scene_path, recording_map=recording_map, window_s=window)
    if auto and "markers" not in bag.series and bag.roles["image"] in bag.topics:
        # no markers topic: the camera frames are the marker source (a real sensor's image stream);
        # the first reading already warned about everything this one would
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            bag = open_bag(bag_path, roles=roles, config=config, scene=scene_path, recording_map=recording_map,
                           window_s=window)
    order = int(noise_config(config_path)["difference_order"])
    scene = bag.scene
    if scene is not None and bag.camera is not None:
        scene = _with_camera(scene, bag.camera)
    if scene is not None:
        _check_against_scene(bag, scene)
    outputs = ("pose", "markers", "wrench", "sheet_points")
    if not any(r in bag.series for r in outputs):
        raise BagReadError(f"{bag.path}: none of the topics {', '.join(bag.roles[r] for r in outputs)} has data; "
                           "nothing to identify from")

    t_ns: dict[str, np.ndarray] = {}
    arrays: dict[str, np.ndarray] = {}
    missing: dict[str, str] = {}
    topics: dict[str, str] = {}
    for ch in CHANNELS:
        role = CHANNEL_ROLE[ch]
        s = bag.series.get(role)
        if s is None:
            skipped = ch == "image" and include_image is not True and bag.roles[role] in bag.topics
            if isinstance(scene, TaskSceneFile) and not scene.sensors and role in ("markers", "wrench", "image"):
                missing[ch] = f"the scene {scene.source} has no tactile sensor"
            else:
                missing[ch] = (f"not decoded (include_image={include_image!r})" if skipped
                               else f"topic {bag.roles[role]} not in the recording")
            continue
        if ch == "markers_xyz":
            value = s.values[..., :3]
        elif ch == "markers_uv":
            if "u" not in s.field_names or "v" not in s.field_names:
                missing[ch] = f"topic {s.topic} has no u v fields"
                continue
            value = s.values[..., [s.field_names.index("u"), s.field_names.index("v")]]
        else:
            value = s.values
        t_ns[ch] = s.t_ns
        arrays[ch] = _frozen(value)
        topics[ch] = s.topic
    notes = list(bag.notes)
    weight = None
    if "markers_uv" not in arrays and "image" in bag.series and scene is not None:
        decoded = markers_from_images(bag.series["image"].t_ns, arrays["image"], scene, bag.roles["image"], notes)
        if decoded is not None:
            t_ns["markers_uv"], arrays["markers_uv"] = decoded[0], _frozen(decoded[1])
            weight = _frozen(decoded[2])
            topics["markers_uv"] = bag.roles["image"]
            missing.pop("markers_uv", None)
    noise = {}
    for ch, value in arrays.items():
        if ch != "image" and value.shape[0] > order:
            noise[ch] = _frozen(estimate_noise(t_ns[ch], value, order))
    clock = bag.series.get("clock")
    present = tuple(ch for ch in CHANNELS if ch in arrays)
    effectors = {}
    if isinstance(scene, TaskSceneFile):
        namespace = config.namespace if isinstance(config, BagConfig) else load_bag_config(config).namespace
        mapped = recording_map if isinstance(recording_map, RecordingMap) else bag.recording_map
        effectors = read_effector_streams(bag.path, scene.effector_names, namespace, recording_map=mapped)
    return Evidence(
        source=EvidenceSource(bag.path, bag.mcap_path, bag.sha256, bag.scene_path, topics, bag.recording_map),
        scene=scene, t_ns=t_ns, clock_t_ns=clock.t_ns if clock is not None else None, noise=noise,
        channels_present=present, channels_missing=missing, notes=tuple(notes), effectors=effectors,
        markers_uv_weight=weight, pose_cmd_taken=(None if bag.pose_cmd_taken is None or "pose_cmd" not in arrays
                                                  else (bag.pose_cmd_taken.t_ns, bag.pose_cmd_taken.values)),
        **arrays,
    )


def markers_from_images(t_ns: np.ndarray, images: np.ndarray, scene: SceneFile, topic: str,
                        notes: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The ``markers_uv`` channel and its weights read off a tactile image stream (OpenCV blob detection
    and frame-to-frame tracking in the fixed marker order, :func:`sysid.markers_image.track_markers`).

    The sensor is the scene's sensor whose name the topic ends with (``<sensor>/image``), or the
    scene's only sensor; its ``marker_grid`` is the expected grid. A marker not seen in a frame but
    interpolated from its lattice neighbours (``INTERPOLATED``) keeps its frame, with weight 0; a
    marker cut by the image border (``CLIPPED``) has the visible fraction of its blob as weight. A
    frame with a marker that could not even be interpolated (``LOST``, no position) is dropped (as
    NaN samples of a topic are). Both are counted in a note.

    Args:
        t_ns: frame stamps ``(F,)`` ns.
        images: frames ``(F, h, w)`` uint8.
        scene: the recording's scene.
        topic: the image topic (for the sensor and the messages).
        notes: the bundle's notes; what was done (or why nothing could be) is appended.

    Returns:
        ``(stamps (M,), uv (M, k, 2) px, weight (M, k) in [0, 1])`` of the frames where every marker
        has a position, or None (with a :class:`~sysid.bagio.BagWarning` naming the topic) when the
        markers cannot be read: no matching sensor, the first frame does not show the grid, or fewer
        than two frames remain.
    """
    # optional heavy dependency: OpenCV (through markers_image), for images only
    from sysid.markers_image import CLIPPED, INTERPOLATED, track_markers

    def give_up(why: str) -> None:
        message = f"topic {topic}: no markers decoded from the images ({why}); the evidence lacks markers_uv"
        notes.append(message)
        warnings.warn(message, BagWarning, stacklevel=3)

    sensors = list(scene.sensors.values())
    named = [s for s in sensors if topic.rstrip("/").endswith(f"/{s.name}/image") or topic == f"{s.name}/image"]
    sensor = named[0] if named else (sensors[0] if len(sensors) == 1 else None)
    if sensor is None:
        give_up(f"no sensor of {scene.source} matches the topic")
        return None
    try:
        tracks = track_markers(images, tuple(sensor.marker_grid))
    except CalibrationError as err:
        give_up(str(err))
        return None
    complete = np.all(np.isfinite(tracks.uv), axis=(1, 2))
    if int(complete.sum()) < 2:
        give_up(f"only {int(complete.sum())} of {tracks.uv.shape[0]} frames have a position for every marker")
        return None
    kept = tracks.status[complete]
    counts = [(int((kept == INTERPOLATED).sum()), "interpolated marker positions with weight 0"),
              (int((kept == CLIPPED).sum()), "border-cut markers weighted by their visible fraction"),
              (int((~complete).sum()), "frames with a lost marker dropped")]
    notes.append(f"topic {topic}: markers_uv decoded from {tracks.uv.shape[0]} images ({sensor.marker_grid[0]}x"
                 f"{sensor.marker_grid[1]} grid of sensor {sensor.name})"
                 + "".join(f"; {n} {what}" for n, what in counts if n))
    return np.asarray(t_ns)[complete], tracks.uv[complete], tracks.weight[complete]


# ---------------------------------------------------------------------------------- alignment
def resample(t_ns_src: np.ndarray, values: np.ndarray, t_ns_dst: np.ndarray,
             outside: Literal["raise", "clamp", "nan"] = "raise") -> np.ndarray:
    """Linear interpolation of samples ``values (N, ...)`` at ``t_ns_src (N,)`` to ``t_ns_dst (D,)``.

    Time is handled as int64 ns offsets from ``t_ns_src[0]`` before conversion to float, so long
    (wall-clock) stamps lose no precision.

    Args:
        t_ns_src: source stamps, strictly increasing.
        values: shape ``(N, ...)``; every trailing entry is interpolated independently.
        t_ns_dst: target stamps, shape ``(D,)``.
        outside: targets outside ``[t_src[0], t_src[-1]]``: ``"raise"``, ``"clamp"`` (hold the end
            value) or ``"nan"``.

    Returns:
        float64 array ``(D, ...)``.

    Raises:
        ValueError: source stamps not strictly increasing, shape mismatch, or a target outside the
            source span with ``outside="raise"``.
    """
    t_src = np.asarray(t_ns_src, dtype=np.int64)
    t_dst = np.asarray(t_ns_dst, dtype=np.int64)
    y = np.asarray(values, dtype=np.float64)
    if t_src.ndim != 1 or y.shape[0] != t_src.shape[0] or t_src.shape[0] == 0:
        raise ValueError(f"source stamps {t_src.shape} and values {y.shape} disagree along axis 0")
    if np.any(np.diff(t_src) <= 0):
        raise ValueError("source stamps must be strictly increasing")
    if outside not in ("raise", "clamp", "nan"):
        raise ValueError(f"outside must be raise|clamp|nan, got {outside!r}")
    out_of_span = (t_dst < t_src[0]) | (t_dst > t_src[-1])
    if outside == "raise" and out_of_span.any():
        raise ValueError(f"{int(out_of_span.sum())} target stamps lie outside the source span "
                         f"[{t_src[0]}, {t_src[-1]}] ns")
    xs = (t_src - t_src[0]).astype(np.float64)
    xd = (t_dst - t_src[0]).astype(np.float64)
    if t_src.shape[0] == 1:
        out = np.repeat(y[:1], t_dst.shape[0], axis=0)
    else:
        i = np.clip(np.searchsorted(xs, xd, side="right") - 1, 0, xs.shape[0] - 2)
        w = np.clip((xd - xs[i]) / (xs[i + 1] - xs[i]), 0.0, 1.0).reshape(-1, *(1,) * (y.ndim - 1))
        out = (1.0 - w) * y[i] + w * y[i + 1]
    if outside == "nan" and out_of_span.any():
        out[out_of_span] = np.nan
    return out


def resample_pose(t_ns_src: np.ndarray, pose: np.ndarray, t_ns_dst: np.ndarray,
                  outside: Literal["raise", "clamp", "nan"] = "raise") -> np.ndarray:
    """:func:`resample` for poses ``(N, 7)``: linear position, normalised-linear (nlerp) quaternion.

    Consecutive quaternions are first put in the same hemisphere (q and -q are one rotation).
    """
    pose = np.array(pose, dtype=np.float64)
    q = pose[:, 3:]
    flip = np.concatenate([[1.0], np.sign(np.einsum("ij,ij->i", q[1:], q[:-1]))])
    flip[flip == 0] = 1.0
    pose[:, 3:] = q * np.cumprod(flip)[:, None]
    out = resample(t_ns_src, pose, t_ns_dst, outside)
    out[:, 3:] /= np.linalg.norm(out[:, 3:], axis=1, keepdims=True)
    return out


def common_time_base(evidence: Evidence, channels: Sequence[str] | None = None,
                     period_ns: int | None = None) -> np.ndarray:
    """A uniform stamp grid inside the span every listed channel covers.

    Args:
        evidence: the bundle.
        channels: channels to cover (default: present channels except the image).
        period_ns: grid step; default the largest median sampling period of those channels (the
            slowest stream, so no channel is upsampled beyond its own rate).

    Returns:
        int64 stamps ``(D,)`` from the latest channel start, step ``period_ns``, not past the earliest end.

    Raises:
        KeyError: a channel is not present.
        ValueError: the channels do not overlap in time.
    """
    channels = list(channels) if channels is not None else [c for c in evidence.channels_present if c != "image"]
    for ch in channels:
        if ch not in evidence.t_ns:
            raise KeyError(f"{evidence.source.bag_path}: no {ch} channel ({evidence.channels_missing.get(ch, '')})")
    start = max(int(evidence.t_ns[ch][0]) for ch in channels)
    end = min(int(evidence.t_ns[ch][-1]) for ch in channels)
    if end < start:
        raise ValueError(f"channels {channels} do not overlap in time")
    if period_ns is None:
        period_ns = max(int(np.median(np.diff(evidence.t_ns[ch]))) if len(evidence.t_ns[ch]) > 1 else 1
                        for ch in channels)
    period_ns = int(period_ns)
    if period_ns <= 0:
        raise ValueError(f"period_ns must be positive, got {period_ns}")
    return start + period_ns * np.arange((end - start) // period_ns + 1, dtype=np.int64)


def align(evidence: Evidence, t_ns_dst: np.ndarray, channels: Sequence[str] | None = None,
          outside: Literal["raise", "clamp", "nan"] = "raise") -> dict[str, np.ndarray]:
    """Every listed channel resampled to ``t_ns_dst`` (poses by :func:`resample_pose`).

    Returns:
        channel -> ``(D, ...)`` float64 arrays.
    """
    channels = list(channels) if channels is not None else [c for c in evidence.channels_present if c != "image"]
    out = {}
    for ch in channels:
        values = evidence.values(ch)
        fn = resample_pose if ch in POSE_CHANNELS else resample
        out[ch] = fn(evidence.t_ns[ch], values, t_ns_dst, outside)
    return out
