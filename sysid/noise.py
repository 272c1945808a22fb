"""White-noise level of a sampled signal, estimated from the signal itself.

Method: robust scale of k-th order differences (k = 1 or 2). A k-th difference annihilates a
polynomial trend of degree k-1 exactly and a smooth motion nearly (its contribution is
~ |d^k y/dt^k| h^k), while white noise of standard deviation sigma gives differences of standard
deviation ``sigma * sqrt(C(2k, k))`` (sqrt(2) for k = 1, sqrt(6) for k = 2). The scale is the
median absolute deviation times 1.4826 (consistent for Gaussian noise), so the samples taken
during fast or impulsive motion (contact onsets, slip) count as outliers as long as fewer than half
of the differences are dominated by motion (quiet and slowly moving segments being the majority).
This is the difference-based variance estimator of Rice (1984, Ann. Statist. 12) / Gasser, Sroka and
Jennen-Steinmetz (1986, Biometrika 73) made robust with the MAD (Hampel 1974).

For irregular sampling the second difference is taken with the spacings ``h0 = t_i - t_{i-1}``,
``h1 = t_{i+1} - t_i``: ``d_i = h0 (y_{i+1} - y_i) - h1 (y_i - y_{i-1})``, which cancels any linear
trend and has variance ``sigma^2 (h0^2 + (h0 + h1)^2 + h1^2)``; each ``d_i`` is divided by that
square root.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sim_core.errors import ConfigError
from sim_core.scenes.scene_file import load_yaml
from sysid.data import DEFAULT_CONFIG, data_file

MAD_TO_SIGMA = 1.482602218505602  # 1 / Phi^-1(3/4)


def normalized_differences(t_ns: np.ndarray, values: np.ndarray, order: int = 2) -> np.ndarray:
    """Differences of ``values`` along axis 0 scaled to the noise standard deviation.

    Args:
        t_ns: stamps, shape ``(N,)``, increasing (int ns).
        values: samples, shape ``(N, ...)``.
        order: 1 or 2.

    Returns:
        ``(N - order, ...)``; for white noise of standard deviation sigma each entry has standard
        deviation sigma.

    Raises:
        ValueError: unsupported order, shape mismatch, or fewer than ``order + 1`` samples.
    """
    values = np.asarray(values, dtype=np.float64)
    t = np.asarray(t_ns, dtype=np.int64)
    if order not in (1, 2):
        raise ValueError(f"difference order must be 1 or 2, got {order}")
    if t.ndim != 1 or values.shape[0] != t.shape[0]:
        raise ValueError(f"stamps {t.shape} and values {values.shape} disagree along axis 0")
    if t.shape[0] < order + 1:
        raise ValueError(f"need at least {order + 1} samples for order-{order} differences, got {t.shape[0]}")
    if order == 1:
        return np.diff(values, axis=0) / np.sqrt(2.0)
    h = np.diff(t).astype(np.float64)
    h0, h1 = h[:-1], h[1:]
    extra = (1,) * (values.ndim - 1)
    h0, h1 = h0.reshape(-1, *extra), h1.reshape(-1, *extra)
    d = h0 * (values[2:] - values[1:-1]) - h1 * (values[1:-1] - values[:-2])
    return d / np.sqrt(h0 ** 2 + (h0 + h1) ** 2 + h1 ** 2)


def robust_scale(x: np.ndarray) -> float:
    """MAD * 1.4826 of a 1-D sample (falls back to the RMS when the MAD is 0, e.g. quantised data)."""
    x = np.asarray(x, dtype=np.float64).reshape(-1)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return float("nan")
    mad = float(np.median(np.abs(x - np.median(x))))
    if mad > 0.0:
        return MAD_TO_SIGMA * mad
    return float(np.sqrt(np.mean(x ** 2)))


def estimate_noise(t_ns: np.ndarray, values: np.ndarray, order: int = 2) -> np.ndarray:
    """Per-axis white-noise standard deviation of a sampled channel.

    Args:
        t_ns: stamps, shape ``(N,)`` (int ns, increasing).
        values: samples, shape ``(N, ..., A)``; all middle axes (points, markers) are pooled, the
            last axis is kept (e.g. ``(N, k, 3)`` markers -> sigma of x, y, z).
        order: difference order, 1 or 2 (see module docstring).

    Returns:
        sigma, shape ``(A,)``, in the units of ``values``.

    Raises:
        ValueError: see :func:`normalized_differences`.
    """
    values = np.asarray(values, dtype=np.float64)
    if values.ndim == 1:
        values = values[:, None]
    d = normalized_differences(t_ns, values, order)
    axes = d.shape[-1]
    return np.array([robust_scale(d[..., a]) for a in range(axes)])


def noise_config(path: str | Path | None = None) -> dict:
    """The ``noise:`` section of a sysid config file (the packaged ``sysid/data/default.yaml`` by default).

    Returns:
        ``{"difference_order": int}``.

    Raises:
        ConfigError: missing file (the packaged default included), unknown key or bad value (named
            with the file).
    """
    out = {"difference_order": 2}
    path = Path(path) if path is not None else data_file(DEFAULT_CONFIG)
    if not path.is_file():
        raise ConfigError(f"{path}: sysid config file does not exist")
    section = (load_yaml(path.read_text(encoding="utf-8")) or {}).get("noise") or {}
    unknown = [k for k in section if k not in out]
    if unknown:
        raise ConfigError(f"{path}: unknown key noise.{unknown[0]} (allowed: {', '.join(out)})")
    out.update(section)
    if out["difference_order"] not in (1, 2):
        raise ConfigError(f"{path}: noise.difference_order must be 1 or 2, got {out['difference_order']!r}")
    return out
