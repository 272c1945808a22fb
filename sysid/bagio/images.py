"""Camera messages of a real tactile sensor -> the grey ``(h, w)`` uint8 frames the marker tracker reads.

Encodings of ``sensor_msgs/Image`` (REP 104 / ``sensor_msgs/image_encodings``): ``mono8`` / ``8UC1``,
``mono16`` / ``16UC1`` (the high byte: value >> 8), ``rgb8``, ``bgr8`` / ``8UC3`` (OpenCV's channel order,
what GelSight's ROS 2 example publishes), ``rgba8``, ``bgra8`` / ``8UC4``; colour is converted to grey
with OpenCV's ITU-R BT.601 weights (``cv2.cvtColor``: Y = 0.299 R + 0.587 G + 0.114 B). A
``sensor_msgs/CompressedImage`` (``format`` e.g. ``"bgr8; jpeg compressed bgr8"`` or ``"png"``) is
decoded with ``cv2.imdecode`` (a colour JPEG/PNG comes back in BGR order) and converted the same
way. ``sensor_msgs/CameraInfo`` gives the pinhole intrinsics ``K`` and the image size.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from sysid.bagio import codec

IMAGE = codec.IMAGE
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
IMAGE_TYPES = (IMAGE, COMPRESSED_IMAGE)

_CHANNELS = {"mono8": (1, np.uint8, None), "8uc1": (1, np.uint8, None), "mono16": (1, np.uint16, None),
             "16uc1": (1, np.uint16, None), "rgb8": (3, np.uint8, "RGB2GRAY"), "bgr8": (3, np.uint8, "BGR2GRAY"),
             "8uc3": (3, np.uint8, "BGR2GRAY"), "rgba8": (4, np.uint8, "RGBA2GRAY"),
             "bgra8": (4, np.uint8, "BGRA2GRAY"), "8uc4": (4, np.uint8, "BGRA2GRAY")}
ENCODINGS = tuple(_CHANNELS)


def _buffer(data: Any) -> np.ndarray:
    return np.frombuffer(data.tobytes() if isinstance(data, np.ndarray) else bytes(data), dtype=np.uint8)


def _to_grey(img: np.ndarray, conversion: str | None) -> np.ndarray:
    if img.dtype == np.uint16:
        return (img >> 8).astype(np.uint8)
    if conversion is None:
        return img
    import cv2  # optional heavy dependency: OpenCV, for colour and compressed images only

    return cv2.cvtColor(np.ascontiguousarray(img), getattr(cv2, f"COLOR_{conversion}"))


def parse_image_grey(msg: Any) -> tuple[int, np.ndarray, str]:
    """sensor_msgs/Image of any encoding in :data:`ENCODINGS` -> ``(t_ns, grey (h, w) uint8, frame_id)``.

    Raises:
        ValueError: unknown encoding (the message lists the known ones), or data shorter than ``step * height``.
    """
    enc = str(msg.encoding).lower()
    if enc not in _CHANNELS:
        raise ValueError(f"image encoding {msg.encoding!r} is not supported (supported: {', '.join(ENCODINGS)})")
    channels, dtype, conversion = _CHANNELS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = _buffer(msg.data)
    if data.size < h * step:
        raise ValueError(f"image data has {data.size} bytes, {h * step} needed")
    size = np.dtype(dtype).itemsize
    rows = data[: h * step].reshape(h, step)[:, : w * channels * size]
    big = bool(msg.is_bigendian) and size > 1
    img = np.ascontiguousarray(rows).view(np.dtype(dtype).newbyteorder(">" if big else "<")).astype(dtype)
    img = img.reshape(h, w) if channels == 1 else img.reshape(h, w, channels)
    return codec.stamp_to_ns(msg.header.stamp), _to_grey(img, conversion), msg.header.frame_id


def parse_compressed_image_grey(msg: Any) -> tuple[int, np.ndarray, str]:
    """sensor_msgs/CompressedImage -> ``(t_ns, grey (h, w) uint8, frame_id)`` (decoded by ``cv2.imdecode``).

    Raises:
        ValueError: the data cannot be decoded (names the format field).
    """
    import cv2  # optional heavy dependency: OpenCV, for colour and compressed images only

    img = cv2.imdecode(_buffer(msg.data), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"compressed image (format {msg.format!r}) cannot be decoded")
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    elif img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    return codec.stamp_to_ns(msg.header.stamp), img, msg.header.frame_id


def parse_any_image(msgtype: str, msg: Any) -> tuple[int, np.ndarray, str]:
    """Image or CompressedImage (``msgtype``) -> ``(t_ns, grey (h, w) uint8, frame_id)``."""
    if msgtype == COMPRESSED_IMAGE:
        return parse_compressed_image_grey(msg)
    return parse_image_grey(msg)


def parse_camera_info(msg: Any) -> dict[str, float | int]:
    """sensor_msgs/CameraInfo -> ``{fx, fy, cx, cy, width, height}`` (px) from ``K = [fx 0 cx; 0 fy cy; 0 0 1]``.

    Raises:
        ValueError: K is all zero (an uncalibrated camera publishes that).
    """
    k = np.asarray(msg.k, dtype=np.float64).reshape(-1)
    if k.shape != (9,) or not np.all(np.isfinite(k)) or k[0] <= 0.0 or k[4] <= 0.0:
        raise ValueError(f"camera_info K = {k.tolist()} has no positive focal lengths (uncalibrated camera)")
    return {"fx": float(k[0]), "fy": float(k[4]), "cx": float(k[2]), "cy": float(k[5]),
            "width": int(msg.width), "height": int(msg.height)}
