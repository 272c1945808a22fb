"""Pinhole camera behind the gel of a vision-based tactile sensor, with radial lens distortion.

The camera centre sits at ``z = -d`` in the sensor frame (``d`` = ``camera.distance``) and looks along
``+z`` (INTERFACES.md). A point ``p = (x, y, z)`` in the sensor frame (m) has the normalised image
coordinates ``x_n = x / (z + d)``, ``y_n = y / (z + d)``; the Brown-Conrady radial model (the first two
radial terms of OpenCV's camera model) scales them by ``1 + k1 r^2 + k2 r^4`` with
``r^2 = x_n^2 + y_n^2``, and the pixel coordinates are

    u = fx * x_n * (1 + k1 r^2 + k2 r^4) + cx,    v = fy * y_n * (1 + k1 r^2 + k2 r^4) + cy.

Pixel convention: OpenCV's, the centre of pixel (row i, column j) is at ``(u, v) = (j, i)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from sim_core.errors import ConfigError, ThinShellError

CAMERA_REQUIRED_KEYS = ("fx", "fy", "cx", "cy", "width", "height", "distance")
CAMERA_OPTIONAL_KEYS = ("k1", "k2")
CAMERA_PARAMETER_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "distance")


def _validated_values(values: dict[str, Any], where: str) -> dict[str, Any]:
    """Check camera values and convert them to float (int for the image size); errors name ``where.key``."""
    out: dict[str, Any] = {}
    for name, value in values.items():
        if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
            raise ConfigError(f"{where}.{name} must be a number, got {value!r}")
        if not math.isfinite(float(value)):
            raise ConfigError(f"{where}.{name} must be finite, got {value!r}")
        out[name] = float(value)
    for name in ("fx", "fy", "distance"):
        if name in out and out[name] <= 0.0:
            raise ConfigError(f"{where}.{name} must be > 0, got {values[name]!r}")
    for name in ("width", "height"):
        if name in out:
            if not out[name].is_integer() or out[name] <= 0:
                raise ConfigError(f"{where}.{name} must be a positive integer (px), got {values[name]!r}")
            out[name] = int(out[name])
    return out


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics of the tactile camera and its distance to the gel contact surface.

    Attributes:
        fx, fy: focal lengths, px (> 0).
        cx, cy: principal point, px.
        width, height: image size, px (> 0).
        distance: distance ``d`` from the camera centre to the undeformed contact surface, m (> 0).
        k1, k2: radial distortion coefficients (dimensionless), default 0.

    Raises:
        ConfigError: a non-finite value, a non-positive focal length / image size / distance; the
            message names the field.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distance: float
    k1: float = 0.0
    k2: float = 0.0

    def __post_init__(self) -> None:
        values = {k: getattr(self, k) for k in CAMERA_PARAMETER_NAMES + ("width", "height")}
        for name, value in _validated_values(values, "camera").items():
            object.__setattr__(self, name, value)

    @classmethod
    def from_dict(cls, cfg: Mapping[str, Any], where: str = "camera") -> "PinholeCamera":
        """Build a camera from a scene's ``camera:`` block.

        Args:
            cfg: mapping with keys ``fx fy cx cy width height distance`` and optional ``k1 k2``.
            where: YAML path of the block, used in error messages (e.g. ``sensors.tactile.camera``).

        Raises:
            ConfigError: missing or unknown key, or an invalid value (the key is named).
        """
        if not isinstance(cfg, Mapping):
            raise ConfigError(f"{where} must be a mapping, got {type(cfg).__name__}")
        known = set(CAMERA_REQUIRED_KEYS) | set(CAMERA_OPTIONAL_KEYS)
        unknown = sorted(set(cfg) - known)
        if unknown:
            raise ConfigError(f"{where}.{unknown[0]}: unknown key (known: {sorted(known)})")
        missing = [k for k in CAMERA_REQUIRED_KEYS if k not in cfg]
        if missing:
            raise ConfigError(f"{where}.{missing[0]}: required key is missing")
        return cls(**_validated_values(dict(cfg), where))

    def to_dict(self) -> dict[str, float | int]:
        """The ``camera:`` block of this camera (inverse of :meth:`from_dict`)."""
        return {k: getattr(self, k) for k in CAMERA_REQUIRED_KEYS + CAMERA_OPTIONAL_KEYS}

    # ------------------------------------------------------------------ projection
    def _normalised(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        p = np.asarray(points, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"points must have shape (k, 3), got {p.shape}")
        w = p[:, 2] + self.distance
        bad = np.nonzero(~(w > 0.0))[0]
        if bad.size:
            i = int(bad[0])
            raise ThinShellError(
                f"camera: point {i} at z = {p[i, 2]:.6g} m is not in front of the camera (z > -{self.distance:.6g} m)"
            )
        return p[:, 0] / w, p[:, 1] / w, w

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixel coordinates of points given in the sensor frame.

        Args:
            points: shape ``(k, 3)``, m, sensor frame.

        Returns:
            ``(u, v)`` per point, shape ``(k, 2)``, px (formula in the module docstring).

        Raises:
            ThinShellError: a point lies at or behind the camera plane ``z = -d`` (index named).
        """
        xn, yn, _ = self._normalised(points)
        r2 = xn * xn + yn * yn
        radial = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
        return np.stack([self.fx * xn * radial + self.cx, self.fy * yn * radial + self.cy], axis=1)

    def project_jacobian(self, points: np.ndarray) -> np.ndarray:
        """Analytic derivative of :meth:`project` w.r.t. the sensor-frame point.

        With ``w = z + d``, ``f = 1 + k1 r^2 + k2 r^4`` and ``f' = k1 + 2 k2 r^2``:
        ``d x_n/d(x, y, z) = (1/w, 0, -x_n/w)``, ``d r^2/d(x, y, z) = (2 x_n, 2 y_n, -2 r^2)/w`` and
        ``du/dp = fx (f d x_n/dp + x_n f' d r^2/dp)`` (likewise ``v`` with ``fy``, ``y_n``).

        Args:
            points: shape ``(k, 3)``, m.

        Returns:
            ``d(u, v)/d(x, y, z)``, shape ``(k, 2, 3)``, px/m.
        """
        xn, yn, w = self._normalised(points)
        r2 = xn * xn + yn * yn
        f = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
        df = self.k1 + 2.0 * self.k2 * r2
        dxn = np.stack([1.0 / w, np.zeros_like(w), -xn / w], axis=1)
        dyn = np.stack([np.zeros_like(w), 1.0 / w, -yn / w], axis=1)
        dr2 = np.stack([2.0 * xn, 2.0 * yn, -2.0 * r2], axis=1) / w[:, None]
        J = np.empty((xn.shape[0], 2, 3))
        J[:, 0, :] = self.fx * (f[:, None] * dxn + (xn * df)[:, None] * dr2)
        J[:, 1, :] = self.fy * (f[:, None] * dyn + (yn * df)[:, None] * dr2)
        return J

    def project_parameter_derivative(self, points: np.ndarray, name: str) -> np.ndarray:
        """Derivative of :meth:`project` w.r.t. one camera parameter, at fixed sensor-frame points.

        Args:
            points: shape ``(k, 3)``, m.
            name: one of ``fx fy cx cy k1 k2 distance``. ``d(u, v)/dk1 = (fx x_n r^2, fy y_n r^2)``,
                ``d(u, v)/dk2 = (fx x_n r^4, fy y_n r^4)``; ``distance`` acts like ``z``.

        Returns:
            shape ``(k, 2)``, px per unit of the parameter.

        Raises:
            KeyError: unknown parameter name.
        """
        if name not in CAMERA_PARAMETER_NAMES:
            raise KeyError(f"camera has no parameter {name!r} (known: {CAMERA_PARAMETER_NAMES})")
        xn, yn, _ = self._normalised(points)
        r2 = xn * xn + yn * yn
        f = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
        zero, one = np.zeros_like(xn), np.ones_like(xn)
        if name == "fx":
            return np.stack([xn * f, zero], axis=1)
        if name == "fy":
            return np.stack([zero, yn * f], axis=1)
        if name == "cx":
            return np.stack([one, zero], axis=1)
        if name == "cy":
            return np.stack([zero, one], axis=1)
        if name == "k1":
            return np.stack([self.fx * xn * r2, self.fy * yn * r2], axis=1)
        if name == "k2":
            return np.stack([self.fx * xn * r2 * r2, self.fy * yn * r2 * r2], axis=1)
        return self.project_jacobian(points)[:, :, 2]

    def unproject(self, uv: np.ndarray, z: np.ndarray | float = 0.0, iterations: int = 20) -> np.ndarray:
        """Sensor-frame points at depth ``z`` that project to the pixels ``uv`` (inverse of :meth:`project`).

        The radial factor is inverted by fixed-point iteration on ``x_n = x_d / f(r^2(x_n))`` (exact in
        one step without distortion; converges for the mild distortion of tactile cameras).

        Args:
            uv: shape ``(k, 2)``, px.
            z: depth of each point in the sensor frame, m, scalar or shape ``(k,)``.
            iterations: fixed-point iterations of the distortion inverse.

        Returns:
            shape ``(k, 3)``, m.
        """
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        z = np.broadcast_to(np.asarray(z, dtype=float), (uv.shape[0],))
        xd = (uv[:, 0] - self.cx) / self.fx
        yd = (uv[:, 1] - self.cy) / self.fy
        xn, yn = xd.copy(), yd.copy()
        if self.k1 != 0.0 or self.k2 != 0.0:
            for _ in range(iterations):
                r2 = xn * xn + yn * yn
                f = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
                xn, yn = xd / f, yd / f
        w = z + self.distance
        return np.stack([xn * w, yn * w, z], axis=1)
