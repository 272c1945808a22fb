"""Grey frames from every image encoding a real tactile sensor publishes (sysid.bagio.images)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from sysid.bagio import codec, images


def _image(encoding: str, pixels: np.ndarray, bigendian: bool = False):
    h, w = pixels.shape[:2]
    data = np.ascontiguousarray(pixels.astype(pixels.dtype.newbyteorder(">" if bigendian else "<")))
    return codec.typestore().types[codec.IMAGE](
        header=codec.pose_stamped(5, np.r_[0, 0, 0, 0, 0, 0, 1.0], "cam").header, height=h, width=w,
        encoding=encoding, is_bigendian=int(bigendian), step=data.nbytes // h, data=data.view(np.uint8).reshape(-1))


@pytest.fixture(scope="module")
def bgr():
    rng = np.random.default_rng(0)
    return rng.integers(0, 256, size=(6, 7, 3), dtype=np.uint8)


def test_colour_encodings_give_opencv_grey(bgr):
    grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    rgb = bgr[:, :, ::-1]
    bgra = np.concatenate([bgr, np.full((6, 7, 1), 255, np.uint8)], axis=2)
    for encoding, pixels in (("bgr8", bgr), ("8UC3", bgr), ("rgb8", rgb), ("bgra8", bgra),
                             ("rgba8", np.concatenate([rgb, bgra[:, :, 3:]], axis=2))):
        t, got, frame = images.parse_image_grey(_image(encoding, np.ascontiguousarray(pixels)))
        assert (t, frame) == (5, "cam")
        np.testing.assert_array_equal(got, grey, err_msg=encoding)


def test_mono_encodings(bgr):
    mono = bgr[:, :, 0]
    np.testing.assert_array_equal(images.parse_image_grey(_image("mono8", mono))[1], mono)
    wide = mono.astype(np.uint16) * 256 + 77
    for big in (False, True):
        np.testing.assert_array_equal(images.parse_image_grey(_image("mono16", wide, big))[1], mono)


def test_compressed_png_and_jpeg(bgr):
    grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    ts = codec.typestore().types
    header = codec.pose_stamped(0, np.r_[0, 0, 0, 0, 0, 0, 1.0], "cam").header
    png = cv2.imencode(".png", bgr)[1].reshape(-1)
    msg = ts["sensor_msgs/msg/CompressedImage"](header=header, format="bgr8; png compressed bgr8", data=png)
    np.testing.assert_array_equal(images.parse_compressed_image_grey(msg)[1], grey)
    smooth = np.full((16, 16, 3), (40, 120, 200), np.uint8)
    jpeg = cv2.imencode(".jpg", smooth, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].reshape(-1)
    msg = ts["sensor_msgs/msg/CompressedImage"](header=header, format="jpeg", data=jpeg)
    assert np.abs(images.parse_compressed_image_grey(msg)[1].astype(int)
                  - int(cv2.cvtColor(smooth, cv2.COLOR_BGR2GRAY)[0, 0])).max() <= 2
    msg = ts["sensor_msgs/msg/CompressedImage"](header=header, format="jpeg", data=np.zeros(10, np.uint8))
    with pytest.raises(ValueError, match="compressed image \\(format 'jpeg'\\) cannot be decoded"):
        images.parse_compressed_image_grey(msg)


def test_unknown_encoding_names_the_supported_ones(bgr):
    with pytest.raises(ValueError, match="image encoding 'yuv422' is not supported \\(supported: mono8"):
        images.parse_image_grey(_image("yuv422", bgr[:, :, 0]))
