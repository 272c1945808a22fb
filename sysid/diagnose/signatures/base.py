"""Common pieces of the signature tests: the recording as the tests see it, and their result.

A signature test looks for one effect's own pattern (SYSID.md "Typical signatures") in a recording,
using the calibrated nominal replay only where the pattern is defined relative to what the
simulator predicts (the timing of contact events, the sheet's shape after release). Each test
returns a :class:`SignatureResult` whose ``statistic`` is a likelihood-ratio statistic in noise
units (the drop of the whitened sum of squares when the effect's pattern is fitted) and whose
``effect_size`` is the fitted pattern's amplitude in the test's own unit; an effect is detected
when both exceed their thresholds (:mod:`sysid.diagnose.signatures.null`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from sysid.runs import segments

TACTILE_CHANNELS = ("markers_xyz", "markers_uv", "wrench")


@dataclass(frozen=True)
class Recording:
    """A recording and its calibrated nominal prediction, as the signature tests read them.

    Attributes:
        t: channel -> sample times, s, shape ``(n,)`` (``"pose"`` included).
        data: channel -> recorded values (``markers_xyz (n, k, 3)`` m in the sensor frame,
            ``markers_uv (n, k, 2)`` px, ``wrench (n, 6)`` N / N m in the sensor frame, ``sheet_points
            (n, p, 3)`` m in world, ``pose`` / ``pose_cmd (n, 7)``).
        prediction: channel -> the calibrated nominal replay aligned to ``data`` (same shapes), or
            None for the data-only tests.
        sigma: channel -> white-noise standard deviation per last axis.
        camera: pinhole intrinsics ``(fx, fy, cx, cy, d)`` (px, px, px, px, m) of the sensor
            calibration in force.
        name: recording name (for messages).
        reference: where ``prediction`` went through the calibrated arm drive (:mod:`sysid.replay_drive`),
            the same calibrated replay with the recorded pose imposed (kinematic), channel -> values as
            ``prediction``: a force read against the recorded deformation (gel damping) reads it; else None.
    """

    t: Mapping[str, np.ndarray]
    data: Mapping[str, np.ndarray]
    prediction: Mapping[str, np.ndarray] | None
    sigma: Mapping[str, np.ndarray]
    camera: tuple[float, float, float, float, float]
    name: str = ""
    reference: Mapping[str, np.ndarray] | None = None

    def has(self, *channels: str) -> bool:
        """Whether every channel is recorded."""
        return all(ch in self.data and self.data[ch] is not None for ch in channels)

    def predicted(self, *channels: str) -> bool:
        """Whether every channel is recorded and predicted."""
        return self.prediction is not None and self.has(*channels) and all(ch in self.prediction for ch in channels)

    def sample_period(self, channel: str) -> float:
        """Median sample period of ``channel``, s."""
        return float(np.median(np.diff(self.t[channel])))

    def tactile_period(self) -> float:
        """The coarsest sample period of the recorded tactile streams, s."""
        return max(self.sample_period(ch) for ch in TACTILE_CHANNELS if self.has(ch))


@dataclass
class SignatureResult:
    """Outcome of one signature test.

    Attributes:
        effect: effect name (SYSID.md vocabulary).
        applicable: whether the recording holds what the test needs (else ``reason`` says why).
        statistic: likelihood-ratio statistic, noise units (whitened SSE removed by the pattern).
        effect_size: amplitude of the fitted pattern in ``effect_unit``.
        effect_unit: unit of ``effect_size``.
        estimate: fitted parameters of the effect's model (name -> value, SI).
        windows_s: time windows where the pattern lives, ``[[t0, t1], ...]`` s.
        channels: channels carrying the pattern.
        markers: marker indices carrying most of it (may be empty).
        detail: further numbers of the test (JSON-ready).
        reason: why the test is not applicable, or a note on its outcome.
        detected: set by the decision (:func:`sysid.diagnose.signatures.null.decide`).
        threshold: statistic and effect-size thresholds used by the decision.
    """

    effect: str
    applicable: bool = True
    statistic: float = 0.0
    effect_size: float = 0.0
    effect_unit: str = ""
    estimate: dict[str, float] = field(default_factory=dict)
    windows_s: list[list[float]] = field(default_factory=list)
    channels: list[str] = field(default_factory=list)
    markers: list[int] = field(default_factory=list)
    detail: dict[str, Any] = field(default_factory=dict)
    reason: str = ""
    detected: bool = False
    threshold: dict[str, float] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {"effect": self.effect, "applicable": self.applicable, "detected": self.detected,
                "statistic": float(self.statistic), "effect_size": float(self.effect_size),
                "effect_unit": self.effect_unit, "threshold": dict(self.threshold),
                "estimate": {k: float(v) for k, v in self.estimate.items()},
                "windows_s": [[float(a), float(b)] for a, b in self.windows_s], "channels": list(self.channels),
                "markers": [int(m) for m in self.markers], "detail": self.detail, "reason": self.reason}


def not_applicable(effect: str, reason: str) -> SignatureResult:
    """A result for a test the recording cannot support."""
    return SignatureResult(effect=effect, applicable=False, reason=reason)


def dilate(mask: np.ndarray, t: np.ndarray, margin_s: float) -> np.ndarray:
    """``mask`` grown by ``margin_s`` seconds on both sides of every True sample."""
    m = np.asarray(mask, dtype=bool)
    out = m.copy()
    for i0, i1 in segments(m):
        out |= (t >= t[i0] - margin_s) & (t <= t[i1 - 1] + margin_s)
    return out


def normal_force(wrench: np.ndarray) -> np.ndarray:
    """Compressive normal force on the gel, N (``-F_z`` in the sensor frame: pressing gives > 0)."""
    return -np.asarray(wrench, dtype=float)[:, 2]


def mean_marker_depth(markers: np.ndarray) -> np.ndarray:
    """Mean marker depth into the gel, m, shape ``(n,)`` from marker positions ``(n, K, 3)`` in the sensor
    frame (``-z`` averaged over the markers: pressing gives > 0)."""
    return -np.asarray(markers, dtype=float)[:, :, 2].mean(axis=1)


def predicted_contact(rec: Recording, channel: str = "wrench", fraction: float = 0.02) -> np.ndarray | None:
    """Samples of ``channel`` where the nominal replay has the gel in contact (net contact force
    above ``fraction`` of its peak, or marker displacement above that fraction of its peak).

    Returns:
        boolean mask ``(n,)`` on ``rec.t[channel]``, or None without a prediction.
    """
    if rec.prediction is None:
        return None
    if "wrench" in rec.prediction:
        f = np.linalg.norm(np.asarray(rec.prediction["wrench"], dtype=float)[:, :3], axis=1)
        tc = rec.t["wrench"]
    elif "markers_xyz" in rec.prediction:
        x = np.asarray(rec.prediction["markers_xyz"], dtype=float)
        f = np.abs(x - x[:1]).max(axis=(1, 2))
        tc = rec.t["markers_xyz"]
    else:
        return None
    peak = float(f.max()) if f.size else 0.0
    on = f > fraction * peak if peak > 0.0 else np.zeros(f.shape, bool)
    return np.interp(rec.t[channel], tc, on.astype(float)) > 0.5


def whitened_marker_offsets(rec: Recording) -> np.ndarray | None:
    """Whitened offsets ``(n, m, 3)`` of the recorded markers from their rest positions, on
    ``rec.t["markers_xyz"]``; the rest positions are the median of the samples where the replay
    predicts no contact (the first 5 % when there is no replay). None without recorded markers."""
    if not rec.has("markers_xyz"):
        return None
    x = np.asarray(rec.data["markers_xyz"], dtype=float)
    free = predicted_contact(rec, "markers_xyz")
    rows = ~free if free is not None and (~free).sum() >= 5 else np.arange(len(x)) < max(5, len(x) // 20)
    return (x - np.median(x[rows], axis=0)) / rec.sigma["markers_xyz"]


def marker_displacement(rec: Recording) -> np.ndarray | None:
    """Whitened RMS displacement of the recorded markers from their rest positions
    (:func:`whitened_marker_offsets`), per sample (about 1 at rest: noise only), on
    ``rec.t["markers_xyz"]``."""
    offsets = whitened_marker_offsets(rec)
    return None if offsets is None else np.sqrt(np.mean(offsets ** 2, axis=(1, 2)))


def dispersion(sse: float, samples: int, params: int) -> float:
    """Dispersion of a whitened residual, ``max(1, sse / (samples - params))``: its variance in
    units of the noise model's (Pearson's estimate, McCullagh & Nelder 1989 sec. 9.2), never
    below one (a residual under the noise level is the noise model's, not a better fit's).

    Args:
        sse: whitened sum of squares after the fit.
        samples: samples fitted.
        params: parameters fitted.

    Raises:
        ValueError: ``samples <= params`` (no degree of freedom left to estimate it).
    """
    dof = int(samples) - int(params)
    if dof <= 0:
        raise ValueError(f"dispersion needs more samples than parameters ({samples} <= {params})")
    return max(1.0, float(sse) / dof)
