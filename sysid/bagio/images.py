"""Camera messages of a real tactile sensor -> the grey ``(h, w)`` uint8 frames the marker tracker reads.

Encodings of ``sensor_msgs/Image`` (REP 104 / ``sensor_msgs/image_encodings``): ``mono8`` / ``8UC1``,
``mono16`` / ``16UC1`` (the high byte: value >> 8), ``rgb8``, ``bgr8`` / ``8UC3`` (OpenCV's channel order,
what GelSight's ROS 2 example publishes), ``rgba8``, ``bgra8`` / ``8UC4``; colour is converted to grey
with OpenCV's ITU-R BT.601 weights (``cv2.cvtColor``: Y = 0.299 R + 0.587 G + 0.114 B). A
``sensor_msgs/CompressedImage`` (``format`` e.g. ``"bgr8; jpeg compressed bgr8"`` or ``"png"``) is
decoded with ``cv2.imdecode`` (a colour JPEG/PNG comes back in BGR order) and converted the same
way. ``sensor_msgs/CameraInfo`` gives the pinhole intrinsics ``K``, the image size and the first two
radial distortion terms ``k1 k2`` of ``D`` (:func:`parse_camera_info`).

Distortion: the project's camera (:mod:`sim_core.sensors.camera`) is OpenCV's model with its radial
terms ``k1 k2`` only, on the same normalised coordinates ``x/z, y/z`` as ROS's ``plumb_bob``
(``D = [k1 k2 p1 p2 k3]``) and ``rational_polynomial`` (``D = [k1 k2 p1 p2 k3 k4 k5 k6]``). Those two
models are taken: ``k1 k2`` exactly; the tangential terms ``p1 p2`` and the higher radial terms
``k3`` (``k4 k5 k6``) have no counterpart and are left out, and :func:`distortion_left_out` says how
many pixels that moves the image corners (the reader warns). Another model (``equidistant`` fisheye,
...) with a non-zero ``D`` is refused; an empty ``D`` states nothing about distortion.
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


CAMERA_INFO_MODELS = ("plumb_bob", "rational_polynomial")
"""``distortion_model`` values whose ``k1 k2`` are the project camera's (module docstring)."""
_D_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")


def _distortion(msg: Any) -> dict[str, float]:
    """``D`` of a CameraInfo by name (``k1 k2 p1 p2 k3 [k4 k5 k6]``); empty when ``D`` is empty.

    Raises:
        ValueError: a non-zero ``D`` of a model other than :data:`CAMERA_INFO_MODELS`, more values than the
            model has, or a non-finite value (each names the field).
    """
    d = np.asarray(msg.d, dtype=np.float64).reshape(-1)
    model = str(msg.distortion_model).strip()
    if d.size == 0:
        return {}
    if not np.all(np.isfinite(d)):
        raise ValueError(f"camera_info d = {d.tolist()} is not finite")
    if model not in CAMERA_INFO_MODELS:
        if np.any(d != 0.0):
            raise ValueError(f"camera_info distortion_model {model!r} (d = {d.tolist()}) is not supported: the camera "
                             f"model takes {' or '.join(CAMERA_INFO_MODELS)} (radial k1 k2); give the intrinsics in "
                             "the scene's camera block and leave camera_info out of the recording map")
        return {}
    if d.size > len(_D_NAMES) or (model == "plumb_bob" and d.size > 5):
        raise ValueError(f"camera_info d has {d.size} values, distortion_model {model!r} has "
                         f"{5 if model == 'plumb_bob' else 8}")
    return {name: float(v) for name, v in zip(_D_NAMES, d)}


def parse_camera_info(msg: Any) -> dict[str, float | int]:
    """sensor_msgs/CameraInfo -> ``{fx, fy, cx, cy, width, height}`` (px) from ``K = [fx 0 cx; 0 fy cy; 0 0 1]``,
    plus the radial distortion ``k1 k2`` (-) when ``D`` is given (module docstring).

    Raises:
        ValueError: K is all zero (an uncalibrated camera publishes that); a distortion that the camera
            model cannot take (:func:`_distortion`).
    """
    k = np.asarray(msg.k, dtype=np.float64).reshape(-1)
    if k.shape != (9,) or not np.all(np.isfinite(k)) or k[0] <= 0.0 or k[4] <= 0.0:
        raise ValueError(f"camera_info K = {k.tolist()} has no positive focal lengths (uncalibrated camera)")
    out: dict[str, float | int] = {"fx": float(k[0]), "fy": float(k[4]), "cx": float(k[2]), "cy": float(k[5]),
                                   "width": int(msg.width), "height": int(msg.height)}
    d = _distortion(msg)
    if d:
        out.update(k1=d.get("k1", 0.0), k2=d.get("k2", 0.0))
    return out


def distortion_left_out(msg: Any) -> tuple[dict[str, float], float]:
    """The non-zero terms of ``D`` the camera model lacks (``p1 p2 k3 k4 k5 k6``) and the largest pixel
    displacement they cause at the four image corners.

    The displacement is the difference between the full OpenCV model,
    ``x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)``
    (``y_d`` likewise with ``p1 (r^2 + 2 y^2) + 2 p2 x y``), and its radial ``k1 k2`` part, in px
    (``fx dx, fy dy``), at the normalised coordinates ``((u - cx) / fx, (v - cy) / fy)`` of the corners.

    Returns:
        ``(name -> value of every left-out non-zero term, px)``; ``({}, 0.0)`` when nothing is left out.

    Raises:
        ValueError: as :func:`parse_camera_info`.
    """
    info = parse_camera_info(msg)
    d = _distortion(msg)
    left = {n: v for n, v in d.items() if n not in ("k1", "k2") and v != 0.0}
    if not left:
        return {}, 0.0
    c = {n: d.get(n, 0.0) for n in _D_NAMES}
    u = np.array([0.0, info["width"] - 1.0, 0.0, info["width"] - 1.0])
    v = np.array([0.0, 0.0, info["height"] - 1.0, info["height"] - 1.0])
    x, y = (u - info["cx"]) / info["fx"], (v - info["cy"]) / info["fy"]
    r2 = x * x + y * y
    ours = 1.0 + c["k1"] * r2 + c["k2"] * r2 ** 2
    full = (ours + c["k3"] * r2 ** 3) / (1.0 + c["k4"] * r2 + c["k5"] * r2 ** 2 + c["k6"] * r2 ** 3)
    dx = x * (full - ours) + 2.0 * c["p1"] * x * y + c["p2"] * (r2 + 2.0 * x * x)
    dy = y * (full - ours) + c["p1"] * (r2 + 2.0 * y * y) + 2.0 * c["p2"] * x * y
    return left, float(np.max(np.hypot(info["fx"] * dx, info["fy"] * dy)))
