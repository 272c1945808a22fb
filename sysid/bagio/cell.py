"""A real cell's recording brought to the contract (INTERFACES.md) through a recording map.

:func:`decode_mapped` takes the raw messages of the topics a :class:`~sysid.bagio.recording_map.RecordingMap`
names and returns, per role, the samples the contract would have recorded:

- ``pose``: the effector frame's pose in ``world``: from TF (``world_T_eff = (base_T_world)^-1 base_T_eff(t)``
  at the stamps of the chain's dynamic edges) or from a PoseStamped of a ``link`` in ``base`` / ``world`` /
  any TF frame, carried to the effector frame by TF (``world_T_eff = world_T_link link_T_eff``);
- ``pose_cmd``: the same for the command topic (e.g. a Cartesian controller's target of ``tool0`` in ``base``);
- ``markers``: a PointCloud2 in the sensor frame (checked);
- ``wrench``: the F/T wrench in its own frame, negated when the sensor reports the reaction
  (``sign: on_environment``), tool weight removed by orientation
  (``F_g = R_wf^T m g``, ``tau_g = c x F_g``), tared (known offset, or the mean of the
  weight-compensated samples over a pre-contact window), then carried to the sensor frame
  (``F_s = R F_f``, ``tau_s = R tau_f + t x F_s``, :func:`~sysid.bagio.tf_buffer.wrench_transform`);
- ``sheet_points``: points in any frame, carried to ``world``;
- ``image``: any encoding or CompressedImage, as grey frames;
- ``clock``;
- the camera: the first ``camera_info``'s intrinsics and radial distortion ``k1 k2``
  (:func:`~sysid.bagio.images.parse_camera_info`; other distortion terms left out with a warning).

Every header frame_id is checked against the map: a mismatch is a :class:`BagReadError` naming the
topic and both frames. Stamps follow each topic's policy (``header`` | ``log`` | ``auto``).
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from sim_core.errors import BagReadError
from sysid.bagio import codec, images
from sysid.bagio.recording_map import RecordingMap, TopicSource
from sysid.bagio.tf_buffer import TFBuffer, hemisphere_continuous, pose_compose, pose_inverse, quat_rotate, \
    wrench_transform

TF_MESSAGE = "tf2_msgs/msg/TFMessage"
ROLE_TYPES = {"pose": (codec.POSE_STAMPED,), "pose_cmd": (codec.POSE_STAMPED,), "markers": (codec.POINT_CLOUD2,),
              "wrench": (codec.WRENCH_STAMPED,), "sheet_points": (codec.POINT_CLOUD2,), "image": images.IMAGE_TYPES,
              "clock": (codec.CLOCK,), "camera_info": (images.CAMERA_INFO,), "tf": (TF_MESSAGE,),
              "tf_static": (TF_MESSAGE,)}

Decoded = tuple[np.ndarray, np.ndarray, tuple[str, ...], str]
"""``(t_ns (N,), values (N, ...), field_names, frame_id)`` in file order, as the reader's ``_decode``."""


def wanted_topics(rmap: RecordingMap) -> dict[str, str]:
    """Role -> topic of every topic the map reads."""
    return rmap.topics()


def check_types(rmap: RecordingMap, topic_types: dict[str, str], path: str) -> None:
    """Every mapped topic present in the bag must have a type its role takes.

    Raises:
        BagReadError: names the topic, its type and the types expected.
    """
    for role, topic in rmap.topics().items():
        msgtype = topic_types.get(topic)
        if msgtype is not None and msgtype not in ROLE_TYPES[role]:
            raise BagReadError(f"topic {topic} (role {role} of {rmap.source}) has type {msgtype}, expected "
                               f"{' or '.join(ROLE_TYPES[role])} in {path}")


def build_tf(rmap: RecordingMap, raw: dict[str, list[tuple[int, Any]]], path: str) -> TFBuffer:
    """The TF buffer of ``/tf_static`` and ``/tf`` (header stamps)."""
    tf = TFBuffer(path)
    for topic, static in ((rmap.tf_static_topic, True), (rmap.tf_topic, False)):
        for _, msg in raw.get(topic, []):
            for tr in msg.transforms:
                p, q = tr.transform.translation, tr.transform.rotation
                tf.add(str(tr.header.frame_id), str(tr.child_frame_id), codec.stamp_to_ns(tr.header.stamp),
                       np.array([p.x, p.y, p.z, q.x, q.y, q.z, q.w]), static)
    return tf


def _stamps(src: TopicSource, header_ns: np.ndarray, log_ns: np.ndarray) -> np.ndarray:
    if src.stamp == "log":
        return log_ns
    if src.stamp == "auto" and (np.any(header_ns == 0) or np.any(np.diff(header_ns) <= 0)):
        return log_ns
    return header_ns


def _check_frames(topic: str, frames: set[str], expected: str, what: str) -> None:
    wrong = sorted(f for f in frames if f.lstrip("/") != expected.lstrip("/"))
    if wrong:
        raise BagReadError(f"topic {topic}: header frame_id is {wrong[0]!r} but the recording map says {what} is in "
                           f"{expected!r}")


class _Mapper:
    def __init__(self, rmap: RecordingMap, raw: dict[str, list[tuple[int, Any]]], path: str,
                 warn: Callable[[str], None]) -> None:
        self.rmap, self.raw, self.path, self.warn = rmap, raw, path, warn
        self.tf = build_tf(rmap, raw, path)
        self.world_T_base = pose_inverse(np.asarray(rmap.world_in_base, dtype=np.float64))

    def lookup(self, target: str, source: str, t_ns: np.ndarray) -> np.ndarray:
        if target.lstrip("/") == source.lstrip("/"):
            return np.tile(np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]), (t_ns.shape[0], 1))
        return self.tf.lookup(target, source, t_ns)

    def world_T(self, frame: str, t_ns: np.ndarray) -> np.ndarray:
        """Pose of ``frame`` in world at ``t_ns`` (``world`` itself, else through ``base`` and TF)."""
        if frame.lstrip("/") == self.rmap.world_frame:
            return self.lookup("", "", t_ns)
        return pose_compose(self.world_T_base, self.lookup(self.rmap.base_frame, frame, t_ns))

    def items(self, src: TopicSource) -> list[tuple[int, Any]]:
        return self.raw.get(src.topic, [])

    # ---------------------------------------------------------------------------------- roles
    def pose_from_tf(self, eff: str | None = None) -> Decoded:
        eff = eff or self.rmap.effector_frame
        t = self.tf.dynamic_stamps(self.rmap.base_frame, eff)
        if t.shape[0] == 0:
            raise BagReadError(f"{self.path}: the TF chain {self.rmap.base_frame} -> {eff} has no dynamic samples on "
                               f"{self.rmap.tf_topic}; the effector pose cannot be read (recording map {self.rmap.source})")
        pose = pose_compose(self.world_T_base, self.tf.lookup(self.rmap.base_frame, eff, t))
        return t, hemisphere_continuous(pose), (), self.rmap.world_frame

    def pose_from_topic(self, src: TopicSource, eff: str | None = None) -> Decoded:
        eff = eff or self.rmap.effector_frame
        items = self.items(src)
        parsed = [codec.parse_pose_stamped(m) for _, m in items]
        header = np.asarray([p[0] for p in parsed], dtype=np.int64)
        t = _stamps(src, header, np.asarray([log for log, _ in items], dtype=np.int64))
        frames = {p[2].lstrip("/") for p in parsed}
        allowed = {self.rmap.world_frame, self.rmap.base_frame} | set(self.tf.frames)
        bad = sorted(frames - allowed)
        if bad:
            raise BagReadError(f"topic {src.topic}: header frame_id is {bad[0]!r} but the recording map expects "
                               f"{self.rmap.base_frame!r} or {self.rmap.world_frame!r} (or a TF frame)")
        poses = np.stack([p[1] for p in parsed])
        poses[:, 3:] /= np.linalg.norm(poses[:, 3:], axis=1, keepdims=True)
        world = np.empty_like(poses)
        for frame in frames:
            sel = np.asarray([p[2].lstrip("/") == frame for p in parsed])
            world[sel] = pose_compose(self.world_T(frame, t[sel]), poses[sel])
        link = src.link or eff
        world = pose_compose(world, self.lookup(link, eff, t))
        return t, hemisphere_continuous(world), (), self.rmap.world_frame

    def markers(self, src: TopicSource, decode: Callable[[str, str, list], Decoded]) -> Decoded:
        items = self.items(src)
        _check_frames(src.topic, {str(m.header.frame_id) for _, m in items}, self.rmap.sensor_frame,
                      "the tactile sensor frame")
        t, values, names, frame = decode("markers", src.topic, items)
        return _stamps(src, t, np.asarray([log for log, _ in items], dtype=np.int64)), values, names, frame

    def sheet_points(self, src: TopicSource, decode: Callable[[str, str, list], Decoded]) -> Decoded:
        items = self.items(src)
        frame = src.frame or self.rmap.world_frame
        _check_frames(src.topic, {str(m.header.frame_id) for _, m in items}, frame, "the sheet points")
        t, values, names, _ = decode("sheet_points", src.topic, items)
        t = _stamps(src, t, np.asarray([log for log, _ in items], dtype=np.int64))
        if frame.lstrip("/") != self.rmap.world_frame:
            pose = self.world_T(frame, t)
            values = values.copy()
            values[..., :3] = pose[:, None, :3] + quat_rotate(pose[:, None, 3:], values[..., :3])
        return t, values, names, self.rmap.world_frame

    def wrench(self) -> Decoded:
        src = self.rmap.wrench
        items = self.raw.get(src.topic, [])
        parsed = [codec.parse_wrench_stamped(m) for _, m in items]
        _check_frames(src.topic, {p[2] for p in parsed}, src.frame, "the wrench")
        header = np.asarray([p[0] for p in parsed], dtype=np.int64)
        t = _stamps(TopicSource(src.topic, src.stamp), header, np.asarray([log for log, _ in items], dtype=np.int64))
        w = np.stack([p[1] for p in parsed])
        finite = np.all(np.isfinite(w), axis=1)
        sign = -1.0 if src.sign == "on_environment" else 1.0  # the reaction: negated first (recording_map.py)
        if sign < 0.0:
            w = -w
        if src.tool is not None and src.tool.mass > 0.0:
            world_T_f = self.world_T(src.frame, t)
            weight = src.tool.mass * np.asarray(src.tool.gravity, dtype=np.float64)
            f_g = quat_rotate(pose_inverse(world_T_f)[:, 3:], np.broadcast_to(weight, (t.shape[0], 3)))
            w = w - np.concatenate([f_g, np.cross(np.asarray(src.tool.com), f_g)], axis=1)
        if src.tare_offset is not None:  # in the message's own sign
            w = w - sign * np.asarray(src.tare_offset, dtype=np.float64)
        elif src.tare_window is not None:
            t0 = int(t[finite].min()) if finite.any() else 0
            lo, hi = (t0 + int(round(s * 1e9)) for s in src.tare_window)
            sel = finite & (t >= lo) & (t <= hi)
            if not sel.any():
                raise BagReadError(f"topic {src.topic}: no finite wrench sample in the tare window "
                                   f"{list(src.tare_window)} s of {self.rmap.source}")
            w = w - w[sel].mean(axis=0)
        w = wrench_transform(self.lookup(self.rmap.sensor_frame, src.frame, t), w)
        return t, w, (), self.rmap.sensor_frame

    def image(self, src: TopicSource, msgtype: str) -> Decoded:
        items = self.items(src)
        stamps, frames = [], []
        for _, m in items:
            try:
                t, img, _ = images.parse_any_image(msgtype, m)
            except ValueError as err:
                raise BagReadError(f"topic {src.topic}: {err}") from err
            stamps.append(t)
            frames.append(img)
        shapes = {f.shape for f in frames}
        if len(shapes) > 1:
            raise BagReadError(f"topic {src.topic}: image size changes within the recording ({sorted(shapes)})")
        t = _stamps(src, np.asarray(stamps, dtype=np.int64), np.asarray([log for log, _ in items], dtype=np.int64))
        return t, np.stack(frames), (), ""

    def clock(self, src: TopicSource) -> Decoded:
        t = np.asarray([codec.parse_clock(m) for _, m in self.items(src)], dtype=np.int64)
        return t, t * 1e-9, (), ""


def decode_mapped(rmap: RecordingMap, raw: dict[str, list[tuple[int, Any]]], topic_types: dict[str, str],
                  path: str, decode: Callable[[str, str, list], Decoded], warn: Callable[[str], None],
                  skip_roles: tuple[str, ...] = ()) -> tuple[dict[str, tuple[str, str, Decoded]], dict | None]:
    """Every role the map names, in the contract's frames and units.

    Args:
        rmap: the recording map.
        raw: topic -> ``[(log_ns, message)]`` of the map's topics.
        topic_types: topic -> message type of every topic in the bag.
        path: the bag (for messages).
        decode: the reader's decoder of contract messages (point clouds) ``(role, topic, items) -> Decoded``.
        warn: the reader's warning sink.
        skip_roles: roles not to decode.

    Returns:
        ``(role -> (topic, msgtype, Decoded), camera intrinsics or None)``; roles without messages are absent.

    Raises:
        BagReadError: a type or frame that contradicts the map, a TF lookup outside the recorded
            transforms, an undecodable image (each names the topic or frame).
    """
    check_types(rmap, topic_types, path)
    m = _Mapper(rmap, raw, path, warn)
    out: dict[str, tuple[str, str, Decoded]] = {}

    def has(src: TopicSource | None) -> bool:
        return src is not None and bool(raw.get(src.topic))

    for role in ("pose", "pose_cmd", "markers", "wrench", "sheet_points", "image", "clock"):
        if role in skip_roles:
            continue
        src = getattr(rmap, role)
        if role == "pose" and src == "tf":
            if raw.get(rmap.tf_topic):
                out[role] = (rmap.tf_topic, TF_MESSAGE, m.pose_from_tf())
            continue
        if not has(src):
            continue
        msgtype = topic_types[src.topic]
        if role in ("pose", "pose_cmd"):
            out[role] = (src.topic, msgtype, m.pose_from_topic(src))
        elif role == "markers":
            out[role] = (src.topic, msgtype, m.markers(src, decode))
        elif role == "sheet_points":
            out[role] = (src.topic, msgtype, m.sheet_points(src, decode))
        elif role == "wrench":
            out[role] = (src.topic, msgtype, m.wrench())
        elif role == "image":
            out[role] = (src.topic, msgtype, m.image(src, msgtype))
        else:
            out[role] = (src.topic, msgtype, m.clock(src))
    camera = None
    if has(rmap.camera_info):
        info = raw[rmap.camera_info.topic][0][1]
        try:
            camera = images.parse_camera_info(info)
            left, px = images.distortion_left_out(info)
        except ValueError as err:
            raise BagReadError(f"topic {rmap.camera_info.topic}: {err}") from err
        if left:
            terms = ", ".join(f"{n}={v:.6g}" for n, v in left.items())
            warn(f"topic {rmap.camera_info.topic}: distortion terms {terms} are not in the camera model (radial k1 k2 "
                 f"only) and are left out: they move the image corners by up to {px:.3g} px")
    return out, camera


def decode_mapped_effectors(rmap: RecordingMap, raw: dict[str, list[tuple[int, Any]]], topic_types: dict[str, str],
                            path: str, effectors: list[str]) -> dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """Every effector's streams of a task scene's recording, through the map's ``effectors`` section.

    Per effector (:class:`~sysid.bagio.recording_map.EffectorSource`): ``pose`` in world from TF (at the
    chain's dynamic stamps) or a pose topic (its stamp policy); ``pose_cmd`` carried from its ``link`` to
    the effector frame, stamped with log time (when the robot took it); ``gripper_cmd`` openings (m), log
    time. Samples in file order, not yet cleaned.

    Args:
        rmap: the recording map (``rmap.effectors`` non-empty).
        raw: topic -> ``[(log_ns, message)]`` of the TF topics and the effectors' topics.
        topic_types: topic -> message type of every topic in the bag.
        path: the bag (for messages).
        effectors: the scene's effector names.

    Returns:
        effector -> ``"pose"`` / ``"pose_cmd"`` / ``"gripper_cmd"`` -> ``(t_ns (N,), values)``: poses ``(N, 7)``
        in world, openings ``(N,)``; streams without messages are absent.

    Raises:
        BagReadError: the map names an effector the scene does not have, a topic of another type, a frame
            or TF lookup that contradicts the map (each names the topic, effector or frame).
    """
    unknown = sorted(set(rmap.effectors) - set(effectors))
    if unknown:
        raise BagReadError(f"{rmap.source}: effectors.{unknown[0]} is not an effector of the scene "
                           f"(effectors: {', '.join(effectors)})")
    expected = {"pose": (codec.POSE_STAMPED,), "pose_cmd": (codec.POSE_STAMPED,), "gripper_cmd": (codec.FLOAT64,)}
    m = _Mapper(rmap, raw, path, lambda message: None)
    out: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]] = {}
    for name, spec in rmap.effectors.items():
        streams: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        for kind in ("pose", "pose_cmd", "gripper_cmd"):
            src = getattr(spec, kind)
            if src is None or (src == "tf" and not raw.get(rmap.tf_topic)):
                continue
            if src == "tf":
                t, values, _, _ = m.pose_from_tf(spec.frame)
                streams[kind] = (t, values)
                continue
            items = raw.get(src.topic, [])
            if not items:
                continue
            msgtype = topic_types.get(src.topic)
            if msgtype not in expected[kind]:
                raise BagReadError(f"topic {src.topic} (effectors.{name}.{kind} of {rmap.source}) has type {msgtype}, "
                                   f"expected {expected[kind][0]} in {path}")
            log = np.asarray([t for t, _ in items], dtype=np.int64)
            if kind == "gripper_cmd":
                streams[kind] = (log, np.asarray([codec.parse_float64(msg) for _, msg in items], dtype=np.float64))
                continue
            t, values, _, _ = m.pose_from_topic(src, spec.frame)
            streams[kind] = (log if kind == "pose_cmd" else t, values)
        if streams:
            out[name] = streams
    return out
