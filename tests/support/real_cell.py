"""The bundled recording rewritten as a real cell would record it (test support, rosbags' writer).

:func:`write_real_cell_bag` turns a contract bag (INTERFACES.md) into the bag a real cell's
``ros2 bag record --max-bag-size`` would leave, with the recording map that reads it back:

- the effector pose as TF: ``base_link -> shoulder`` and ``shoulder -> flange`` on ``/tf`` (a joint
  turning about z and the rest of the arm), ``flange -> ft_sensor -> tool0 -> gel`` on ``/tf_static``
  (non-identity mounts); the scene's ``world`` sits at :data:`WORLD_IN_BASE` in ``base_link``;
- the command as a Cartesian controller takes it: the pose of ``tool0`` in ``base_link``
  (``/cartesian_motion_controller/target_frame``);
- the wrench in the F/T sensor's frame ``ft_sensor`` (rotated and offset from the gel), plus the
  weight of the tool under it (:data:`TOOL_MASS` at :data:`TOOL_COM`) and a sensor offset :data:`FT_OFFSET`;
- the marker cloud on ``/gelsight/markers`` in ``gel``; the sheet points in ``base_link`` (float64 fields);
- the tactile images (:func:`rendered_frames`, from the recording's marker pixels) as PNG
  ``CompressedImage`` of a ``bgr8`` frame with zero header stamps, plus ``camera_info``;
- every message at its original log time, split into two ``.mcap`` files at the middle of the recording.

:func:`write_plain_bag_with_images` writes the same recording under today's contract with the same
frames as ``mono8`` images on ``<sensor>/image``: the reference the real-cell bag must reproduce.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from sim_core.sensors.camera import PinholeCamera
from sim_core.sensors.image import render_marker_image
from sysid.bagio import codec
from sysid.bagio.tf_buffer import pose_compose, pose_inverse, quat_rotate, wrench_transform

NS = "/thinshell"
WORLD_IN_BASE = np.array([0.42, -0.13, 0.215, 0.0, 0.0, np.sin(0.35), np.cos(0.35)])
"""Pose of the scene's world in ``base_link`` (a table 0.42 m ahead, turned 40 degrees about z)."""
FLANGE_T_FT = np.array([0.0, 0.0, 0.012, 0.0, 0.0, np.sin(np.pi / 8), np.cos(np.pi / 8)])
FT_T_TOOL0 = np.array([0.0, 0.0, 0.035, 0.0, 0.0, 0.0, 1.0])
_A = 0.5 * np.array([0.3, 0.2, 0.9]) / np.linalg.norm([0.3, 0.2, 0.9])
TOOL0_T_GEL = np.array([0.004, -0.003, 0.061, *(np.sin(0.4) * _A / 0.5), np.cos(0.4)])
"""The gel's mount on the tool flange: 6 cm out, tilted 46 degrees about a skew axis."""
TOOL_MASS = 0.31
TOOL_COM = (0.002, -0.001, 0.041)
FT_OFFSET = np.array([1.7, -0.8, 2.3, 0.021, -0.013, 0.007])
"""A sensor offset (N, N m) in ``ft_sensor``, as an untared F/T sensor reads."""
GRAVITY = (0.0, 0.0, -9.80665)
IMAGE_STRIDE = 6
"""One image per this many marker messages (keeps the test CI-sized)."""

TOPICS = {"tf": "/tf", "tf_static": "/tf_static", "pose_cmd": "/cartesian_motion_controller/target_frame",
          "markers": "/gelsight/markers", "image": "/gelsight/image_raw/compressed",
          "camera_info": "/gelsight/camera_info", "wrench": "/ft_sensor/wrench", "sheet_points": "/cell/sheet_points",
          "clock": "/clock"}


def recording_map(tare: str = "offset") -> dict[str, Any]:
    """The recording map of the real-cell bag (YAML content), taring with the known offset or a window."""
    tare_spec = {"offset": [float(v) for v in FT_OFFSET]} if tare == "offset" else {"window": [0.0, 0.05]}
    return {
        "version": 1,
        "frames": {"base": "base_link", "world_in_base": [float(v) for v in WORLD_IN_BASE], "sensor": "gel",
                   "effector": "gel"},
        "pose": {"tf": True},
        "pose_cmd": {"topic": TOPICS["pose_cmd"], "link": "tool0", "stamp": "header"},
        "markers": {"topic": TOPICS["markers"], "stamp": "header"},
        "image": {"topic": TOPICS["image"], "stamp": "auto"},
        "camera_info": {"topic": TOPICS["camera_info"]},
        "wrench": {"topic": TOPICS["wrench"], "frame": "ft_sensor", "stamp": "header", "tare": tare_spec,
                   "tool": {"mass": TOOL_MASS, "com": list(TOOL_COM), "gravity": list(GRAVITY)}},
        "sheet_points": {"topic": TOPICS["sheet_points"], "frame": "base_link", "stamp": "header"},
        "clock": {"topic": TOPICS["clock"]},
    }


def read_messages(bag: Path) -> list[tuple[str, str, int, Any]]:
    """Every message of a bag: ``(topic, msgtype, log_ns, message)`` in file order."""
    from rosbags.rosbag2 import Reader

    out = []
    with Reader(bag) as reader:
        for conn, log_ns, raw in reader.messages():
            out.append((conn.topic, conn.msgtype, int(log_ns), codec.deserialize(raw, conn.msgtype)))
    return out


def rendered_frames(messages: list, scene: dict) -> list[tuple[int, int, np.ndarray]]:
    """``(log_ns, header_ns, mono8 frame)`` rendered from every :data:`IMAGE_STRIDE`-th marker cloud's ``u v``."""
    camera = PinholeCamera(**scene["sensors"]["tactile"]["camera"])
    clouds = [(log, m) for topic, _, log, m in messages if topic == f"{NS}/tactile/markers"]
    out = []
    for log, m in clouds[::IMAGE_STRIDE]:
        t, uv, _ = codec.parse_point_cloud2(m, ("u", "v"))
        out.append((log, t, render_marker_image(uv, camera, marker_radius_px=3.0)))
    return out


class _SplitWriter:
    """Two rosbags MCAP writers (first and second half), joined into one split bag on close."""

    def __init__(self, out_dir: Path, split_ns: int) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer

        self.out_dir, self.split_ns = out_dir, split_ns
        self.parts = [out_dir.parent / f".{out_dir.name}.part{i}" for i in range(2)]
        self.writers = [Writer(p, version=9, storage_plugin=StoragePlugin.MCAP) for p in self.parts]
        for w in self.writers:
            w.open()
        self.conns: list[dict[str, Any]] = [{}, {}]

    def write(self, topic: str, msgtype: str, log_ns: int, msg: Any) -> None:
        i = 0 if log_ns < self.split_ns else 1
        conn = self.conns[i].get(topic)
        if conn is None:
            conn = self.conns[i][topic] = self.writers[i].add_connection(topic, msgtype, typestore=codec.typestore())
        self.writers[i].write(conn, log_ns, codec.serialize(msg, msgtype))

    def close(self, scene_text: str, map_text: str | None) -> None:
        for w in self.writers:
            w.close()
        self.out_dir.mkdir(parents=True)
        metas = []
        for i, part in enumerate(self.parts):
            meta = yaml.safe_load((part / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
            name = f"{self.out_dir.name}_{i}.mcap"
            shutil.move(str(part / meta["relative_file_paths"][0]), self.out_dir / name)
            meta["files"][0]["path"] = name
            metas.append(meta)
            shutil.rmtree(part)
        merged = metas[0]
        counts: dict[str, dict] = {}
        for meta in metas:
            for entry in meta["topics_with_message_count"]:
                name = entry["topic_metadata"]["name"]
                if name in counts:
                    counts[name]["message_count"] += entry["message_count"]
                else:
                    counts[name] = entry
        merged["topics_with_message_count"] = list(counts.values())
        merged["files"] = [m["files"][0] for m in metas]
        merged["relative_file_paths"] = [f["path"] for f in merged["files"]]
        merged["message_count"] = sum(m["message_count"] for m in metas)
        end = max(m["starting_time"]["nanoseconds_since_epoch"] + m["duration"]["nanoseconds"] for m in metas)
        merged["duration"]["nanoseconds"] = end - merged["starting_time"]["nanoseconds_since_epoch"]
        (self.out_dir / "metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information": merged}))
        (self.out_dir / "scene.yaml").write_text(scene_text)
        if map_text is not None:
            (self.out_dir / "recording.yaml").write_text(map_text)


def _shoulder(t_ns: np.ndarray) -> np.ndarray:
    """``base_link -> shoulder``: 0.09 m up, turning about z with time (a joint)."""
    angle = 0.3 + 0.4 * np.sin(2.0 * t_ns * 1e-9)
    return np.stack([np.zeros_like(angle), np.zeros_like(angle), np.full_like(angle, 0.09),
                     np.zeros_like(angle), np.zeros_like(angle), np.sin(angle / 2), np.cos(angle / 2)], axis=1)


def _transform(parent: str, child: str, t_ns: int, pose: np.ndarray) -> Any:
    ts = codec.typestore().types
    return ts["geometry_msgs/msg/TransformStamped"](
        header=codec.pose_stamped(t_ns, pose, parent).header, child_frame_id=child,
        transform=ts["geometry_msgs/msg/Transform"](
            translation=ts["geometry_msgs/msg/Vector3"](x=pose[0], y=pose[1], z=pose[2]),
            rotation=ts["geometry_msgs/msg/Quaternion"](x=pose[3], y=pose[4], z=pose[5], w=pose[6])))


def _tf_message(transforms: list) -> Any:
    return codec.typestore().types["tf2_msgs/msg/TFMessage"](transforms=transforms)


def _cloud64(t_ns: int, xyz: np.ndarray, frame_id: str) -> Any:
    """PointCloud2 with float64 ``x y z`` (no precision lost in the change of frame)."""
    ts = codec.typestore().types
    fields = [ts["sensor_msgs/msg/PointField"](name=n, offset=8 * i, datatype=codec.POINTFIELD_FLOAT64, count=1)
              for i, n in enumerate("xyz")]
    data = np.ascontiguousarray(xyz.astype("<f8")).view(np.uint8).reshape(-1)
    return ts[codec.POINT_CLOUD2](header=codec.pose_stamped(t_ns, np.r_[0, 0, 0, 0, 0, 0, 1.0], frame_id).header,
                                  height=1, width=xyz.shape[0], fields=fields, is_bigendian=False, point_step=24,
                                  row_step=24 * xyz.shape[0], data=data, is_dense=True)


def _compressed(frame: np.ndarray) -> Any:
    import cv2

    ok, png = cv2.imencode(".png", np.repeat(frame[:, :, None], 3, axis=2))  # a bgr8 colour frame
    assert ok
    ts = codec.typestore().types
    return ts["sensor_msgs/msg/CompressedImage"](header=codec.pose_stamped(0, np.r_[0, 0, 0, 0, 0, 0, 1.0],
                                                                           "gel_camera").header,
                                                 format="bgr8; png compressed bgr8", data=png.reshape(-1))


def _camera_info(scene: dict) -> Any:
    cam = scene["sensors"]["tactile"]["camera"]
    ts = codec.typestore().types
    header = codec.pose_stamped(0, np.r_[0, 0, 0, 0, 0, 0, 1.0], "gel_camera").header
    k = np.array([cam["fx"], 0, cam["cx"], 0, cam["fy"], cam["cy"], 0, 0, 1], dtype=np.float64)
    return ts["sensor_msgs/msg/CameraInfo"](
        header=header, height=cam["height"], width=cam["width"], distortion_model="plumb_bob",
        d=np.zeros(5), k=k, r=np.eye(3).reshape(-1), p=np.array([cam["fx"], 0, cam["cx"], 0, 0, cam["fy"], cam["cy"], 0,
                                                                 0, 0, 1, 0], dtype=np.float64),
        binning_x=0, binning_y=0, roi=ts["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0,
                                                                             width=0, do_rectify=False))


def write_plain_bag_with_images(src: Path, out_dir: Path) -> None:
    """The contract bag ``src`` plus its rendered frames as ``mono8`` on ``<sensor>/image`` (header stamped)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    messages = read_messages(src)
    scene = yaml.safe_load((src / "scene.yaml").read_text())
    frames = rendered_frames(messages, scene)
    writer = Writer(out_dir, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    conns: dict[str, Any] = {}
    items = [(topic, msgtype, log, m) for topic, msgtype, log, m in messages]
    items += [(f"{NS}/tactile/image", codec.IMAGE, log, codec.image_mono8(t, img, "tactile")) for log, t, img in frames]
    for topic, msgtype, log, m in sorted(items, key=lambda x: x[2]):
        if topic not in conns:
            conns[topic] = writer.add_connection(topic, msgtype, typestore=codec.typestore())
        writer.write(conns[topic], log, codec.serialize(m, msgtype))
    writer.close()
    shutil.copy(src / "scene.yaml", out_dir / "scene.yaml")


def write_real_cell_bag(src: Path, out_dir: Path, tare: str = "offset", map_beside: bool = True) -> dict[str, Any]:
    """Write the real-cell-shaped copy of the contract bag ``src`` into ``out_dir`` (module docstring).

    Args:
        src: contract bag directory (pose, pose_cmd, markers, wrench, sheet points, clock).
        out_dir: new bag directory (must not exist).
        tare: ``"offset"`` or ``"window"`` for the map's wrench tare.
        map_beside: also write ``recording.yaml`` into the bag directory.

    Returns:
        the recording map (YAML content).
    """
    messages = read_messages(src)
    scene_text = (src / "scene.yaml").read_text()
    scene = yaml.safe_load(scene_text)
    logs = [log for _, _, log, _ in messages]
    writer = _SplitWriter(out_dir, (min(logs) + max(logs)) // 2)
    base_T_world = WORLD_IN_BASE
    flange_T_gel = pose_compose(pose_compose(FLANGE_T_FT, FT_T_TOOL0), TOOL0_T_GEL)
    ft_T_gel = pose_compose(FT_T_TOOL0, TOOL0_T_GEL)
    statics = [("flange", "ft_sensor", FLANGE_T_FT), ("ft_sensor", "tool0", FT_T_TOOL0), ("tool0", "gel", TOOL0_T_GEL)]
    first = min(logs)
    writer.write(TOPICS["tf_static"], "tf2_msgs/msg/TFMessage", first,
                 _tf_message([_transform(p, c, first, pose) for p, c, pose in statics]))
    writer.write(TOPICS["camera_info"], "sensor_msgs/msg/CameraInfo", first, _camera_info(scene))
    pose_by_t: dict[int, np.ndarray] = {}
    for topic, _, _, m in messages:
        if topic == f"{NS}/ee/pose":
            t, pose, _ = codec.parse_pose_stamped(m)
            pose_by_t[t] = pose
    frames = {log: img for log, _, img in rendered_frames(messages, scene)}
    for topic, msgtype, log, m in messages:
        if topic == f"{NS}/ee/pose":
            t, world_T_gel, _ = codec.parse_pose_stamped(m)
            base_T_shoulder = _shoulder(np.array([t]))[0]
            shoulder_T_flange = pose_compose(pose_compose(pose_inverse(base_T_shoulder), base_T_world),
                                             pose_compose(world_T_gel, pose_inverse(flange_T_gel)))
            writer.write(TOPICS["tf"], "tf2_msgs/msg/TFMessage", log, _tf_message(
                [_transform("base_link", "shoulder", t, base_T_shoulder),
                 _transform("shoulder", "flange", t, shoulder_T_flange)]))
        elif topic == f"{NS}/ee/pose_cmd":
            t, world_T_gel, _ = codec.parse_pose_stamped(m)
            base_T_tool0 = pose_compose(pose_compose(base_T_world, world_T_gel), pose_inverse(TOOL0_T_GEL))
            writer.write(TOPICS["pose_cmd"], msgtype, log, codec.pose_stamped(t, base_T_tool0, "base_link"))
        elif topic == f"{NS}/tactile/markers":
            m.header.frame_id = "gel"
            writer.write(TOPICS["markers"], msgtype, log, m)
            if log in frames:
                writer.write(TOPICS["image"], "sensor_msgs/msg/CompressedImage", log, _compressed(frames[log]))
        elif topic == f"{NS}/tactile/wrench":
            t, w_gel, _ = codec.parse_wrench_stamped(m)
            w_ft = wrench_transform(ft_T_gel, w_gel)  # the same wrench, in ft_sensor about its origin
            world_T_ft = pose_compose(pose_by_t[t], pose_inverse(ft_T_gel))
            f_g = quat_rotate(pose_inverse(world_T_ft)[3:], TOOL_MASS * np.asarray(GRAVITY))
            raw = w_ft + np.r_[f_g, np.cross(TOOL_COM, f_g)] + FT_OFFSET
            writer.write(TOPICS["wrench"], msgtype, log, codec.wrench_stamped(t, raw, "ft_sensor"))
        elif topic == f"{NS}/sheet/points":
            t, xyz, _ = codec.parse_point_cloud2(m, ("x", "y", "z"))
            base = base_T_world[:3] + quat_rotate(base_T_world[3:], xyz)
            writer.write(TOPICS["sheet_points"], msgtype, log, _cloud64(t, base, "base_link"))
        elif topic == "/clock":
            writer.write(TOPICS["clock"], msgtype, log, m)
        else:
            raise ValueError(f"{src}: topic {topic} is not part of the rewrite")
    rmap = recording_map(tare)
    writer.close(scene_text, yaml.safe_dump(rmap, sort_keys=False) if map_beside else None)
    return rmap
