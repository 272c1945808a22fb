"""NumPy <-> rclpy message conversion for the thinshell topics (INTERFACES.md).

Builders take float64 NumPy arrays in SI units and an integer-nanosecond stamp and return rclpy
message objects; parsers return ``(t_ns, array)``. Poses are ``[x y z qx qy qz qw]``, twists
``[vx vy vz wx wy wz]``, wrenches ``[Fx Fy Fz Tx Ty Tz]``.

PointCloud2 packing follows the ``sensor_msgs/PointField`` layout (one float32 field after the
other, ``point_step = 4 * field_count``, little endian, ``height = 1``, unorganised) and is done with a
NumPy structured dtype, so no ``sensor_msgs_py`` is needed (the Jazzy wheels do not ship it).
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, PoseStamped, TwistStamped, WrenchStamped
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker

MARKER_FIELDS = ("x", "y", "z", "u", "v")
POINT_FIELDS = ("x", "y", "z")
_NS = 1_000_000_000


# ------------------------------------------------------------------------------------- time
def stamp_from_ns(t_ns: int) -> Time:
    """``builtin_interfaces/Time`` of integer nanoseconds ``t_ns >= 0``.

    Raises:
        ValueError: negative or non-integer ``t_ns``.
    """
    if isinstance(t_ns, (float, np.floating)) or int(t_ns) != t_ns or t_ns < 0:
        raise ValueError(f"stamp must be non-negative integer nanoseconds, got {t_ns!r}")
    sec, nanosec = divmod(int(t_ns), _NS)
    return Time(sec=sec, nanosec=nanosec)


def ns_from_stamp(stamp: Time) -> int:
    """Integer nanoseconds of a ``builtin_interfaces/Time``."""
    return int(stamp.sec) * _NS + int(stamp.nanosec)


def seconds_to_ns(t: float) -> int:
    """Seconds -> nearest integer nanoseconds."""
    return int(round(float(t) * _NS))


def clock_msg(t_ns: int) -> Clock:
    """``rosgraph_msgs/Clock`` at ``t_ns``."""
    return Clock(clock=stamp_from_ns(t_ns))


def clock_from_msg(msg: Clock) -> int:
    """Nanoseconds of a ``rosgraph_msgs/Clock``."""
    return ns_from_stamp(msg.clock)


def _vector(values: np.ndarray, n: int, what: str) -> np.ndarray:
    values = np.asarray(values, dtype=float).reshape(-1)
    if values.shape != (n,):
        raise ValueError(f"{what} must have {n} entries, got shape {np.shape(values)}")
    return values


# ------------------------------------------------------------------------------------- geometry
def pose_to_msg(pose: np.ndarray, t_ns: int, frame_id: str = "world") -> PoseStamped:
    """``geometry_msgs/PoseStamped`` of ``pose = [x y z qx qy qz qw]`` (m, unit quaternion).

    Raises:
        ValueError: ``pose`` does not have 7 entries.
    """
    p = _vector(pose, 7, "pose")
    msg = PoseStamped()
    msg.header.stamp = stamp_from_ns(t_ns)
    msg.header.frame_id = frame_id
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (float(v) for v in p[:3])
    o = msg.pose.orientation
    o.x, o.y, o.z, o.w = (float(v) for v in p[3:])
    return msg


def pose_from_msg(msg: PoseStamped) -> tuple[int, np.ndarray]:
    """``(t_ns, [x y z qx qy qz qw])`` of a PoseStamped (no normalisation, no validation)."""
    p, o = msg.pose.position, msg.pose.orientation
    return ns_from_stamp(msg.header.stamp), np.array([p.x, p.y, p.z, o.x, o.y, o.z, o.w], dtype=float)


def twist_to_msg(twist: np.ndarray, t_ns: int, frame_id: str = "world") -> TwistStamped:
    """``geometry_msgs/TwistStamped`` of ``[vx vy vz wx wy wz]`` (m/s, rad/s)."""
    v = _vector(twist, 6, "twist")
    msg = TwistStamped()
    msg.header.stamp = stamp_from_ns(t_ns)
    msg.header.frame_id = frame_id
    msg.twist.linear.x, msg.twist.linear.y, msg.twist.linear.z = (float(a) for a in v[:3])
    msg.twist.angular.x, msg.twist.angular.y, msg.twist.angular.z = (float(a) for a in v[3:])
    return msg


def twist_from_msg(msg: TwistStamped) -> tuple[int, np.ndarray]:
    """``(t_ns, [vx vy vz wx wy wz])`` of a TwistStamped."""
    lin, ang = msg.twist.linear, msg.twist.angular
    return ns_from_stamp(msg.header.stamp), np.array([lin.x, lin.y, lin.z, ang.x, ang.y, ang.z], dtype=float)


def wrench_to_msg(wrench: np.ndarray, t_ns: int, frame_id: str) -> WrenchStamped:
    """``geometry_msgs/WrenchStamped`` of ``[Fx Fy Fz Tx Ty Tz]`` (N, N*m) in frame ``frame_id``."""
    w = _vector(wrench, 6, "wrench")
    msg = WrenchStamped()
    msg.header.stamp = stamp_from_ns(t_ns)
    msg.header.frame_id = frame_id
    msg.wrench.force.x, msg.wrench.force.y, msg.wrench.force.z = (float(a) for a in w[:3])
    msg.wrench.torque.x, msg.wrench.torque.y, msg.wrench.torque.z = (float(a) for a in w[3:])
    return msg


def wrench_from_msg(msg: WrenchStamped) -> tuple[int, np.ndarray]:
    """``(t_ns, [Fx Fy Fz Tx Ty Tz])`` of a WrenchStamped."""
    f, tq = msg.wrench.force, msg.wrench.torque
    return ns_from_stamp(msg.header.stamp), np.array([f.x, f.y, f.z, tq.x, tq.y, tq.z], dtype=float)


# ------------------------------------------------------------------------------------- point clouds
def cloud_to_msg(columns: np.ndarray, field_names: Sequence[str], t_ns: int, frame_id: str) -> PointCloud2:
    """Unorganised ``sensor_msgs/PointCloud2`` with float32 fields.

    Args:
        columns: point values, shape ``(k, len(field_names))`` (cast to float32).
        field_names: names of the fields in column order, e.g. ``("x", "y", "z", "u", "v")``.
        t_ns: stamp in ns.
        frame_id: frame of the points.

    Raises:
        ValueError: shape does not match the field names.
    """
    columns = np.asarray(columns, dtype=float)
    names = tuple(field_names)
    if columns.ndim != 2 or columns.shape[1] != len(names):
        raise ValueError(f"point columns must have shape (k, {len(names)}) for fields {names}, got {columns.shape}")
    data = np.ascontiguousarray(columns, dtype="<f4")
    msg = PointCloud2()
    msg.header.stamp = stamp_from_ns(t_ns)
    msg.header.frame_id = frame_id
    msg.height = 1
    msg.width = int(columns.shape[0])
    msg.fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1) for i, n in enumerate(names)]
    msg.is_bigendian = False
    msg.point_step = 4 * len(names)
    msg.row_step = msg.point_step * msg.width
    msg.data = data.tobytes()
    msg.is_dense = bool(np.all(np.isfinite(columns)))
    return msg


def cloud_from_msg(msg: PointCloud2, field_names: Sequence[str]) -> tuple[int, np.ndarray]:
    """``(t_ns, values (k, len(field_names)) float64)`` of the named float32 fields of a PointCloud2.

    Raises:
        ValueError: a requested field is missing or not float32, or the buffer is too short.
    """
    by_name = {f.name: f for f in msg.fields}
    for name in field_names:
        if name not in by_name:
            raise ValueError(f"PointCloud2 has no field {name!r} (fields: {sorted(by_name)})")
        if by_name[name].datatype != PointField.FLOAT32:
            raise ValueError(f"PointCloud2 field {name!r} has datatype {by_name[name].datatype}, expected FLOAT32 (7)")
    count = int(msg.width) * int(msg.height)
    endian = ">" if msg.is_bigendian else "<"
    dtype = np.dtype({
        "names": list(field_names),
        "formats": [endian + "f4"] * len(field_names),
        "offsets": [int(by_name[n].offset) for n in field_names],
        "itemsize": int(msg.point_step),
    })
    buf = bytes(msg.data)
    if len(buf) < count * int(msg.point_step):
        raise ValueError(f"PointCloud2 data has {len(buf)} bytes, expected {count * int(msg.point_step)}")
    rec = np.frombuffer(buf, dtype=dtype, count=count)
    values = np.stack([rec[n].astype(float) for n in field_names], axis=1) if count else np.zeros((0, len(field_names)))
    return ns_from_stamp(msg.header.stamp), values


def markers_to_msg(markers_xyz: np.ndarray, markers_uv: np.ndarray, t_ns: int, frame_id: str) -> PointCloud2:
    """Marker cloud (fields ``x y z u v``) of positions ``(k, 3)`` m and pixels ``(k, 2)``."""
    return cloud_to_msg(np.hstack([np.asarray(markers_xyz, float), np.asarray(markers_uv, float)]), MARKER_FIELDS, t_ns, frame_id)


def points_to_msg(points: np.ndarray, t_ns: int, frame_id: str = "world") -> PointCloud2:
    """Point cloud (fields ``x y z``) of points ``(p, 3)`` m."""
    return cloud_to_msg(points, POINT_FIELDS, t_ns, frame_id)


# ------------------------------------------------------------------------------------- images
def image_to_msg(image: np.ndarray, t_ns: int, frame_id: str) -> Image:
    """``sensor_msgs/Image`` with encoding ``mono8`` of a ``(h, w)`` uint8 array.

    Raises:
        ValueError: not a 2-D uint8 array.
    """
    image = np.asarray(image)
    if image.ndim != 2 or image.dtype != np.uint8:
        raise ValueError(f"mono8 image must be a 2-D uint8 array, got shape {image.shape} dtype {image.dtype}")
    msg = Image()
    msg.header.stamp = stamp_from_ns(t_ns)
    msg.header.frame_id = frame_id
    msg.height, msg.width = (int(s) for s in image.shape)
    msg.encoding = "mono8"
    msg.is_bigendian = 0
    msg.step = int(image.shape[1])
    msg.data = np.ascontiguousarray(image).tobytes()
    return msg


def camera_info_msg(camera: Any, t_ns: int, frame_id: str) -> CameraInfo:
    """``sensor_msgs/CameraInfo`` of a tactile sensor's pinhole camera (:class:`sim_core.sensors.camera.PinholeCamera`).

    ``K = [fx 0 cx; 0 fy cy; 0 0 1]``, ``distortion_model`` ``plumb_bob`` with ``D = [k1 k2 0 0 0]``
    (the camera's Brown-Conrady radial terms; no tangential terms), ``R = I`` and
    ``P = [fx 0 cx 0; 0 fy cy 0; 0 0 1 0]`` (a monocular camera), ``width``/``height`` in px, no
    binning and a full ROI. Pixel convention: OpenCV's, as the ROS ``CameraInfo`` one. The header's
    frame is the image's (the sensor frame: the camera sits at ``z = -distance`` on its axis and looks
    along ``+z``, sim_core/sensors/camera.py).
    """
    msg = CameraInfo()
    msg.header.stamp = stamp_from_ns(t_ns)
    msg.header.frame_id = frame_id
    msg.width, msg.height = int(camera.width), int(camera.height)
    msg.distortion_model = "plumb_bob"
    msg.d = [float(camera.k1), float(camera.k2), 0.0, 0.0, 0.0]
    fx, fy, cx, cy = (float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy))
    msg.k = [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]
    msg.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    msg.p = [fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    return msg


def image_from_msg(msg: Image) -> tuple[int, np.ndarray]:
    """``(t_ns, (h, w) uint8)`` of a ``mono8`` Image (rows may be padded: ``step >= width``).

    Raises:
        ValueError: encoding other than ``mono8`` or a short buffer.
    """
    if msg.encoding != "mono8":
        raise ValueError(f"image encoding {msg.encoding!r} is not mono8")
    buf = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if buf.size < h * step or step < w:
        raise ValueError(f"image data has {buf.size} bytes, expected {h}x{step} with step >= width {w}")
    return ns_from_stamp(msg.header.stamp), buf[: h * step].reshape(h, step)[:, :w].copy()


# ------------------------------------------------------------------------------------- meshes
def mesh_to_marker(points: np.ndarray, triangles: np.ndarray, t_ns: int, frame_id: str = "world",
                   ns: str = "sheet", marker_id: int = 0,
                   color: tuple[float, float, float, float] = (0.85, 0.75, 0.55, 1.0)) -> Marker:
    """``visualization_msgs/Marker`` TRIANGLE_LIST of a triangle mesh (3 points per triangle).

    Args:
        points: vertex positions in m, shape ``(p, 3)``.
        triangles: vertex indices, shape ``(t, 3)``.
        t_ns: stamp in ns.
        frame_id: frame of ``points``.
        ns, marker_id: marker namespace and id (RViz replaces markers with the same pair).
        color: RGBA in [0, 1].

    Raises:
        ValueError: bad shapes or triangle indices out of range.
    """
    points = np.asarray(points, dtype=float)
    triangles = np.asarray(triangles, dtype=np.int64)
    if points.ndim != 2 or points.shape[1] != 3 or triangles.ndim != 2 or triangles.shape[1] != 3:
        raise ValueError(f"mesh needs points (p, 3) and triangles (t, 3), got {points.shape} and {triangles.shape}")
    if triangles.size and (triangles.min() < 0 or triangles.max() >= points.shape[0]):
        raise ValueError(f"triangle indices must be in [0, {points.shape[0]}), got [{triangles.min()}, {triangles.max()}]")
    msg = Marker()
    msg.header.stamp = stamp_from_ns(t_ns)
    msg.header.frame_id = frame_id
    msg.ns = ns
    msg.id = int(marker_id)
    msg.type = Marker.TRIANGLE_LIST
    msg.action = Marker.ADD
    msg.pose.orientation.w = 1.0
    msg.scale.x = msg.scale.y = msg.scale.z = 1.0
    msg.color = ColorRGBA(r=float(color[0]), g=float(color[1]), b=float(color[2]), a=float(color[3]))
    msg.points = [Point(x=float(a), y=float(b), z=float(c)) for a, b, c in points[triangles.reshape(-1)]]
    return msg


def marker_to_triangles(msg: Marker) -> tuple[int, np.ndarray]:
    """``(t_ns, corners (t, 3, 3))`` of a TRIANGLE_LIST marker (triangle soup, marker pose ignored).

    Raises:
        ValueError: not a TRIANGLE_LIST or a point count not divisible by 3.
    """
    if msg.type != Marker.TRIANGLE_LIST:
        raise ValueError(f"marker type {msg.type} is not TRIANGLE_LIST ({Marker.TRIANGLE_LIST})")
    if len(msg.points) % 3:
        raise ValueError(f"TRIANGLE_LIST marker has {len(msg.points)} points, not a multiple of 3")
    corners = np.array([[p.x, p.y, p.z] for p in msg.points], dtype=float).reshape(-1, 3, 3)
    return ns_from_stamp(msg.header.stamp), corners
