"""Rendered ``mono8`` marker image of a vision-based tactile sensor.

Dark round markers on a bright, optionally vignetted background, as a GelSight-type camera sees
the painted marker grid through the gel. Markers are drawn with OpenCV's anti-aliased filled circles
at fixed-point (1/256 px) centres on a canvas ``supersample`` times finer than the image, which is
then box-averaged (``cv2.INTER_AREA``) to the image size: the grey level of an edge pixel is then
close to the fraction of its area the marker covers, so blob centroids recover the marker centres to
a few thousandths of a pixel. Pixel convention: OpenCV's (pixel (row i, column j) centred at
``(u, v) = (j, i)``).
"""

from __future__ import annotations

import numpy as np

from sim_core.errors import ConfigError
from sim_core.sensors.camera import PinholeCamera

_FIXED_POINT_BITS = 8
_AA_RADIUS_EXCESS = 0.6
"""Canvas px by which OpenCV's anti-aliased filled circle overshoots its nominal radius (measured:
the drawn area matches pi r^2 to 0.1 % for r >= 20 canvas px after this correction)."""


def render_marker_image(
    uv: np.ndarray,
    camera: PinholeCamera,
    marker_radius_px: float | np.ndarray = 4.0,
    background: float = 200.0,
    marker_value: float = 40.0,
    blur: float = 0.0,
    shading: float = 0.0,
    supersample: int = 4,
) -> np.ndarray:
    """Render the marker image seen by ``camera``.

    Intensity before quantisation: ``I = L(u, v) * (background (1 - m) + marker_value m)`` where
    ``m`` in [0, 1] is the marker coverage of the pixel and ``L = 1 - shading * rho^2`` a radial
    illumination fall-off, ``rho`` the distance to the principal point divided by the half diagonal.
    Then an optional Gaussian blur (optics), rounding and clipping to uint8.

    Args:
        uv: marker centres, shape ``(k, 2)``, px. Rows with NaN are skipped; markers outside the frame
            are clipped (partly visible ones are drawn partly).
        camera: the image size comes from ``camera.width``, ``camera.height``.
        marker_radius_px: marker radius in px, scalar or shape ``(k,)``, > 0.
        background: grey level of the gel without markers (0..255).
        marker_value: grey level inside a marker (0..255), darker than ``background``.
        blur: standard deviation of the Gaussian blur, px (0 = none).
        shading: illumination fall-off at the image corners, in [0, 1).
        supersample: canvas refinement factor (>= 1).

    Returns:
        image, shape ``(camera.height, camera.width)``, uint8.

    Raises:
        ConfigError: invalid radius, grey levels, blur, shading or supersample (named).
    """
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    radius = np.broadcast_to(np.asarray(marker_radius_px, dtype=float), (uv.shape[0],))
    if uv.shape[0] and not np.all(radius > 0.0):
        raise ConfigError(f"render_marker_image: marker_radius_px must be > 0, got {marker_radius_px!r}")
    for name, value in (("background", background), ("marker_value", marker_value)):
        if not 0.0 <= float(value) <= 255.0:
            raise ConfigError(f"render_marker_image: {name} must lie in [0, 255], got {value!r}")
    if not float(blur) >= 0.0:
        raise ConfigError(f"render_marker_image: blur must be >= 0 px, got {blur!r}")
    if not 0.0 <= float(shading) < 1.0:
        raise ConfigError(f"render_marker_image: shading must lie in [0, 1), got {shading!r}")
    if int(supersample) != supersample or supersample < 1:
        raise ConfigError(f"render_marker_image: supersample must be a positive integer, got {supersample!r}")
    import cv2  # OpenCV is needed only when images are rendered

    S = int(supersample)
    W, H = camera.width, camera.height
    canvas = np.zeros((H * S, W * S), dtype=np.uint8)
    scale = 1 << _FIXED_POINT_BITS
    for (u, v), r in zip(uv, radius):
        if not (np.isfinite(u) and np.isfinite(v)):
            continue
        if u < -r - 1 or u > W + r or v < -r - 1 or v > H + r:
            continue  # entirely outside the frame
        # canvas coordinates of the image point: pixel j covers canvas pixels [j S, (j+1) S)
        cu, cv_ = (u + 0.5) * S - 0.5, (v + 0.5) * S - 0.5
        cv2.circle(
            canvas,
            (int(round(cu * scale)), int(round(cv_ * scale))),
            int(round(max(r * S - _AA_RADIUS_EXCESS, 0.0) * scale)),
            255,
            thickness=-1,
            lineType=cv2.LINE_AA,
            shift=_FIXED_POINT_BITS,
        )
    coverage = canvas.astype(np.float32) / 255.0
    if S > 1:
        coverage = cv2.resize(coverage, (W, H), interpolation=cv2.INTER_AREA)
    image = float(background) * (1.0 - coverage) + float(marker_value) * coverage
    if shading > 0.0:
        vv, uu = np.mgrid[0:H, 0:W].astype(np.float32)
        half_diag2 = 0.25 * (W * W + H * H)
        rho2 = ((uu - camera.cx) ** 2 + (vv - camera.cy) ** 2) / half_diag2
        image *= np.maximum(1.0 - float(shading) * rho2, 0.0)
    if blur > 0.0:
        image = cv2.GaussianBlur(image, (0, 0), sigmaX=float(blur), sigmaY=float(blur), borderType=cv2.BORDER_REFLECT)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)
