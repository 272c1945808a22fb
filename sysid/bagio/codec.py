"""NumPy <-> ROS 2 message conversion for the message types thinshell records (INTERFACES.md).

Builders return ``rosbags`` message objects of the ROS 2 Jazzy type store; parsers accept any object
with the ROS field names (``rosbags`` messages or the dynamic classes of ``mcap_ros2.decoder``), so
that the reader can use either decoder. Stamps are integer nanoseconds everywhere; values are
float64 NumPy arrays in SI units. CDR (de)serialisation goes through :func:`serialize` /
:func:`deserialize` so that no other module touches the type store.

Message layouts follow the standard ROS 2 definitions (geometry_msgs, sensor_msgs, std_msgs,
rosgraph_msgs); PointCloud2 field layout follows REP 0118-style ``PointField`` offsets.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any, Mapping

import numpy as np

POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"
WRENCH_STAMPED = "geometry_msgs/msg/WrenchStamped"
FLOAT64 = "std_msgs/msg/Float64"
STRING = "std_msgs/msg/String"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
IMAGE = "sensor_msgs/msg/Image"
CLOCK = "rosgraph_msgs/msg/Clock"

POINTFIELD_FLOAT32 = 7
POINTFIELD_FLOAT64 = 8
_POINTFIELD_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


@lru_cache(maxsize=1)
def typestore() -> Any:
    """The ROS 2 Jazzy type store of ``rosbags`` (built once, cached)."""
    from rosbags.typesys import Stores, get_typestore  # optional heavy dependency: bag libraries, loaded on first use

    return get_typestore(Stores.ROS2_JAZZY)


def normalize_msgtype(msgtype: str) -> str:
    """``pkg/Type`` or ``pkg/msg/Type`` -> ``pkg/msg/Type``.

    Raises:
        ValueError: not of either form.
    """
    parts = msgtype.strip("/").split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    if len(parts) == 3:
        return "/".join(parts)
    raise ValueError(f"message type {msgtype!r} is not of the form pkg/msg/Type")


def serialize(msg: Any, msgtype: str) -> bytes:
    """CDR bytes (with encapsulation header, little endian) of a ``rosbags`` message."""
    return bytes(typestore().serialize_cdr(msg, msgtype))


def deserialize(raw: bytes | memoryview, msgtype: str) -> Any:
    """A ``rosbags`` message from CDR bytes."""
    return typestore().deserialize_cdr(raw, msgtype)


# ---------------------------------------------------------------------------------------- stamps
def stamp_to_ns(stamp: Any) -> int:
    """``builtin_interfaces/Time`` -> integer nanoseconds (``sec * 1e9 + nanosec``)."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(t_ns: int) -> Any:
    """Integer nanoseconds -> ``builtin_interfaces/msg/Time`` (``nanosec`` in ``[0, 1e9)``).

    Raises:
        ValueError: ``t_ns`` is negative (ROS time cannot be) or not an integer.
    """
    if isinstance(t_ns, (float, np.floating)) or int(t_ns) != t_ns:
        raise ValueError(f"stamp must be integer nanoseconds, got {t_ns!r}")
    t_ns = int(t_ns)
    if t_ns < 0:
        raise ValueError(f"stamp must be >= 0 ns, got {t_ns}")
    Time = typestore().types["builtin_interfaces/msg/Time"]
    sec, nanosec = divmod(t_ns, 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def _header(t_ns: int, frame_id: str) -> Any:
    Header = typestore().types["std_msgs/msg/Header"]
    return Header(stamp=ns_to_stamp(t_ns), frame_id=str(frame_id))


def _vector(values: np.ndarray, n: int, what: str) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64).reshape(-1)
    if arr.shape != (n,):
        raise ValueError(f"{what} must have {n} values, got shape {np.shape(values)}")
    return arr


# ------------------------------------------------------------------------------------ geometry
def pose_stamped(t_ns: int, pose7: np.ndarray, frame_id: str) -> Any:
    """PoseStamped from ``pose7 = [x y z qx qy qz qw]`` (m, unit quaternion)."""
    p = _vector(pose7, 7, "pose")
    ts = typestore().types
    pose = ts["geometry_msgs/msg/Pose"](
        position=ts["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
        orientation=ts["geometry_msgs/msg/Quaternion"](x=p[3], y=p[4], z=p[5], w=p[6]),
    )
    return ts[POSE_STAMPED](header=_header(t_ns, frame_id), pose=pose)


def parse_pose_stamped(msg: Any) -> tuple[int, np.ndarray, str]:
    """PoseStamped -> ``(t_ns, pose7 (7,), frame_id)``."""
    p, q = msg.pose.position, msg.pose.orientation
    return stamp_to_ns(msg.header.stamp), np.array([p.x, p.y, p.z, q.x, q.y, q.z, q.w]), msg.header.frame_id


def _vector3(v: np.ndarray) -> Any:
    return typestore().types["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))


def twist_stamped(t_ns: int, twist6: np.ndarray, frame_id: str) -> Any:
    """TwistStamped from ``twist6 = [vx vy vz wx wy wz]`` (m/s, rad/s)."""
    v = _vector(twist6, 6, "twist")
    ts = typestore().types
    twist = ts["geometry_msgs/msg/Twist"](linear=_vector3(v[:3]), angular=_vector3(v[3:]))
    return ts[TWIST_STAMPED](header=_header(t_ns, frame_id), twist=twist)


def parse_twist_stamped(msg: Any) -> tuple[int, np.ndarray, str]:
    """TwistStamped -> ``(t_ns, twist6 (6,), frame_id)``."""
    a, b = msg.twist.linear, msg.twist.angular
    return stamp_to_ns(msg.header.stamp), np.array([a.x, a.y, a.z, b.x, b.y, b.z]), msg.header.frame_id


def wrench_stamped(t_ns: int, wrench6: np.ndarray, frame_id: str) -> Any:
    """WrenchStamped from ``wrench6 = [Fx Fy Fz Tx Ty Tz]`` (N, N m)."""
    w = _vector(wrench6, 6, "wrench")
    ts = typestore().types
    wrench = ts["geometry_msgs/msg/Wrench"](force=_vector3(w[:3]), torque=_vector3(w[3:]))
    return ts[WRENCH_STAMPED](header=_header(t_ns, frame_id), wrench=wrench)


def parse_wrench_stamped(msg: Any) -> tuple[int, np.ndarray, str]:
    """WrenchStamped -> ``(t_ns, wrench6 (6,), frame_id)``."""
    f, m = msg.wrench.force, msg.wrench.torque
    return stamp_to_ns(msg.header.stamp), np.array([f.x, f.y, f.z, m.x, m.y, m.z]), msg.header.frame_id


# --------------------------------------------------------------------------------------- scalars
def float64(value: float) -> Any:
    """std_msgs/Float64."""
    return typestore().types[FLOAT64](data=float(value))


def parse_float64(msg: Any) -> float:
    """std_msgs/Float64 -> float."""
    return float(msg.data)


def string(text: str) -> Any:
    """std_msgs/String."""
    return typestore().types[STRING](data=str(text))


def parse_string(msg: Any) -> str:
    """std_msgs/String -> str."""
    return str(msg.data)


def clock(t_ns: int) -> Any:
    """rosgraph_msgs/Clock at ``t_ns``."""
    return typestore().types[CLOCK](clock=ns_to_stamp(t_ns))


def parse_clock(msg: Any) -> int:
    """rosgraph_msgs/Clock -> integer nanoseconds."""
    return stamp_to_ns(msg.clock)


# ---------------------------------------------------------------------------------- point clouds
def point_cloud2(t_ns: int, fields: Mapping[str, np.ndarray], frame_id: str) -> Any:
    """Unorganised PointCloud2 (height 1) with one float32 field per entry of ``fields``.

    Args:
        t_ns: stamp, ns.
        fields: ordered ``name -> values (p,)``; e.g. ``{"x": .., "y": .., "z": .., "u": .., "v": ..}``.
            All entries must have the same length ``p``.
        frame_id: frame of the points.

    Returns:
        the message; point ``i`` is row ``i`` of the inputs, fields packed in the given order at
        4-byte offsets, little endian, ``is_dense`` False when any value is not finite.

    Raises:
        ValueError: no fields, unequal lengths or a non-1-D field.
    """
    if not fields:
        raise ValueError("point cloud needs at least one field")
    names = list(fields)
    cols = [np.asarray(fields[n], dtype=np.float32) for n in names]
    p = cols[0].shape[0] if cols[0].ndim == 1 else -1
    for n, c in zip(names, cols):
        if c.ndim != 1 or c.shape[0] != p:
            raise ValueError(f"point cloud field {n!r} must have shape ({p},), got {c.shape}")
    packed = np.ascontiguousarray(np.stack(cols, axis=1).astype("<f4"))
    ts = typestore().types
    PointField = ts["sensor_msgs/msg/PointField"]
    pfields = [PointField(name=n, offset=4 * i, datatype=POINTFIELD_FLOAT32, count=1) for i, n in enumerate(names)]
    step = 4 * len(names)
    return ts[POINT_CLOUD2](
        header=_header(t_ns, frame_id), height=1, width=p, fields=pfields, is_bigendian=False,
        point_step=step, row_step=step * p, data=packed.view(np.uint8).reshape(-1),
        is_dense=bool(np.all(np.isfinite(packed))),
    )


def xyz_cloud(t_ns: int, xyz: np.ndarray, frame_id: str, extra_fields: Mapping[str, np.ndarray] | None = None) -> Any:
    """PointCloud2 with fields ``x y z`` from ``xyz (p, 3)`` followed by ``extra_fields`` (each ``(p,)``).

    Raises:
        ValueError: ``xyz`` is not ``(p, 3)``, or an extra field is named x, y or z.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"points must have shape (p, 3), got {xyz.shape}")
    fields: dict[str, np.ndarray] = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}
    for name, values in (extra_fields or {}).items():
        if name in fields:
            raise ValueError(f"extra point field {name!r} clashes with x y z")
        fields[name] = np.asarray(values)
    return point_cloud2(t_ns, fields, frame_id)


def cloud_field_names(msg: Any) -> tuple[str, ...]:
    """Names of a PointCloud2's fields, in declaration order."""
    return tuple(str(f.name) for f in msg.fields)


def parse_point_cloud2(msg: Any, names: tuple[str, ...] | None = None) -> tuple[int, np.ndarray, str]:
    """PointCloud2 -> ``(t_ns, values (p, len(names)) float64, frame_id)``.

    Args:
        msg: the message (any numeric field type, either endianness, padded point steps).
        names: fields to extract, in this column order; all fields when None.

    Raises:
        KeyError: a requested field is absent (message lists the fields present).
        ValueError: a field has ``count != 1`` or an unknown datatype, or the data is too short.
    """
    by_name = {str(f.name): f for f in msg.fields}
    names = tuple(by_name) if names is None else tuple(names)
    missing = [n for n in names if n not in by_name]
    if missing:
        raise KeyError(f"point cloud lacks field(s) {missing}; it has {sorted(by_name)}")
    p = int(msg.width) * int(msg.height)
    step = int(msg.point_step)
    order = ">" if msg.is_bigendian else "<"
    formats, offsets = [], []
    for n in names:
        f = by_name[n]
        if int(f.count) != 1 or int(f.datatype) not in _POINTFIELD_DTYPES:
            raise ValueError(f"point field {n!r}: unsupported count {f.count} / datatype {f.datatype}")
        formats.append(order + _POINTFIELD_DTYPES[int(f.datatype)])
        offsets.append(int(f.offset))
    dtype = np.dtype({"names": list(names), "formats": formats, "offsets": offsets, "itemsize": step})
    raw = np.frombuffer(bytes(msg.data) if not isinstance(msg.data, np.ndarray) else msg.data.tobytes(), dtype=np.uint8)
    if p == 0:
        return stamp_to_ns(msg.header.stamp), np.zeros((0, len(names))), msg.header.frame_id
    if raw.size < step * p:
        raise ValueError(f"point cloud data has {raw.size} bytes, {step * p} needed for {p} points")
    if msg.height > 1 and int(msg.row_step) != step * int(msg.width):
        rows = raw[: int(msg.row_step) * int(msg.height)].reshape(int(msg.height), int(msg.row_step))
        raw = np.ascontiguousarray(rows[:, : step * int(msg.width)]).reshape(-1)
    rec = raw[: step * p].view(dtype)
    values = np.stack([rec[n].astype(np.float64) for n in names], axis=1)
    return stamp_to_ns(msg.header.stamp), values, msg.header.frame_id


# ---------------------------------------------------------------------------------------- images
def image_mono8(t_ns: int, image: np.ndarray, frame_id: str) -> Any:
    """sensor_msgs/Image, encoding ``mono8``, from a ``(height, width)`` uint8 array.

    Raises:
        ValueError: not 2-D or not uint8.
    """
    img = np.asarray(image)
    if img.ndim != 2 or img.dtype != np.uint8:
        raise ValueError(f"mono8 image must be a 2-D uint8 array, got {img.dtype} {img.shape}")
    h, w = img.shape
    return typestore().types[IMAGE](
        header=_header(t_ns, frame_id), height=h, width=w, encoding="mono8", is_bigendian=0,
        step=w, data=np.ascontiguousarray(img).reshape(-1),
    )


def parse_image_mono8(msg: Any) -> tuple[int, np.ndarray, str]:
    """sensor_msgs/Image (``mono8`` / ``8UC1``) -> ``(t_ns, image (h, w) uint8, frame_id)``.

    Raises:
        ValueError: another encoding, or the data is shorter than ``step * height``.
    """
    if str(msg.encoding).lower() not in ("mono8", "8uc1"):
        raise ValueError(f"image encoding {msg.encoding!r} is not mono8")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.frombuffer(bytes(msg.data) if not isinstance(msg.data, np.ndarray) else msg.data.tobytes(), np.uint8)
    if data.size < h * step:
        raise ValueError(f"image data has {data.size} bytes, {h * step} needed")
    img = data[: h * step].reshape(h, step)[:, :w].copy()
    return stamp_to_ns(msg.header.stamp), img, msg.header.frame_id
