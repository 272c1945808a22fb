"""A per-phase check of the recorded wrench against the gel's own markers: is it the force ON the gel?

INTERFACES.md: the wrench is the net force exerted ON the gel, in the sensor frame. The gel is an elastic body
bonded to a rigid back, so a tangential force on its face shears the face (and the markers on it) the same way:
for a linear elastic body ``u = C f`` with ``C`` positive definite, so the work ``f . u`` is positive, and the
markers' mean tangential displacement follows the net tangential force (on the reference press-slides the two agree
with a cosine of 1.00 wherever both stand clear of the noise). A recorded force that stands clear of its noise while
the markers, clear of theirs, shear the other way for a sustained time is no force on the gel: a sensor whose sign or
frame is wrong in that phase, a cell that records a force on something else, a cable that pulls the load cell.

Measured (docs/benchmarks_log.md, session 54, s54-49lift): on nominal_s109 (the reference's lift-and-fold) the
carried phase's recorded force is (-0.49, +0.03, -0.31) N (3.0-3.8 s) while the markers shear +122 um along x: cosine
-0.99. The card weighs 0.012 N; 0.49 N is the reference's bond springs stretched by the clamped card, recorded with the
sign of the force on the card (``benchmarks/mujoco_world/README.md``: our own MuJoCo world records either, and its
``physical`` wrench agrees with its markers). No physical tack, which pulls the gel toward the card, can follow
such a channel; a fit that tries spends the materials and the force gain on it (``sysid.diagnose.tack``).

:func:`check_wrench` finds the contradicting rows from the recording alone (no replay, no tuning on a recording:
the thresholds are noise multiples and a duration); ``thinshell sysid`` leaves those rows out of the fit and of the
sensor's gains (:attr:`sysid.observation.ObservationModel.row_mask`) and says so in fit.json
(``diagnostics.wrench_check``) and the report's warnings.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from sysid.evidence import resample
from sysid.runs import segments

CLEAR_SIGMAS = 5.0
"""Both the tangential force and the markers' mean tangential displacement must stand this many of their noise
sigmas clear of zero for a row to be judged."""

AGAINST_COSINE = -0.5
"""A judged row contradicts the contract where the cosine of the recorded tangential force with the markers' mean
tangential displacement is below this (opposite within 60 degrees)."""

WINDOW_S = 0.1
"""Rows are judged by window of this duration, s: the window's mean force against its mean marker shear (a sign
change at a reversal of the load or a noisy row does not trip it)."""


@dataclass(frozen=True)
class WrenchCheck:
    """Rows of the recorded wrench whose tangential force opposes the gel's own marker shear.

    Attributes:
        against: bool ``(n,)`` over the wrench's rows: the force contradicts the markers (by window of
            :data:`WINDOW_S`).
        judged: bool ``(n,)``: rows whose window's means both stand clear of the noise (:data:`CLEAR_SIGMAS`).
        spans: ``((t0, t1), ...)`` s from the recording's start, the contradicting runs.
        force: mean recorded force over the contradicting rows, ``(3,)`` N (nan when none).
        shear: mean marker displacement over those rows, ``(3,)`` m (nan when none).
        cosine: median cosine of force and shear over them (nan when none); over the other judged rows
            ``cosine_agree``.
    """

    against: np.ndarray
    judged: np.ndarray
    spans: tuple[tuple[float, float], ...]
    force: np.ndarray
    shear: np.ndarray
    cosine: float
    cosine_agree: float

    @property
    def tripped(self) -> bool:
        """Some rows contradict the contract."""
        return bool(self.against.any())

    def message(self, bag: str) -> str:
        """The warning a report shows (empty when nothing contradicts)."""
        if not self.tripped:
            return ""
        spans = ", ".join(f"{a:.2f}-{b:.2f} s" for a, b in self.spans)
        f, u = self.force, self.shear * 1e6
        return (f"{bag}: topic wrench contradicts the gel's markers in {spans} ({int(self.against.sum())} rows): the "
                f"recorded force ({f[0]:+.3g}, {f[1]:+.3g}, {f[2]:+.3g}) N while the markers shear ({u[0]:+.3g}, "
                f"{u[1]:+.3g}) um, cosine {self.cosine:+.2f} (elsewhere {self.cosine_agree:+.2f}); a force ON the gel "
                f"(INTERFACES.md) shears it its own way, so in these rows the sensor records something else (a sign "
                f"or frame of that phase, the force on the object held); they are left out of the fit and the "
                f"sensor's gains")

    def summary(self) -> dict[str, Any]:
        """fit.json's ``diagnostics.wrench_check``."""
        def finite(v):
            return None if not np.all(np.isfinite(v)) else [float(x) for x in np.atleast_1d(v)]

        return {"tripped": self.tripped, "rows_against": int(self.against.sum()), "rows_judged": int(self.judged.sum()),
                "rows": int(self.against.size), "spans_s": [list(s) for s in self.spans],
                "force_N": finite(self.force), "marker_shear_m": finite(self.shear),
                "cosine": None if math.isnan(self.cosine) else self.cosine,
                "cosine_elsewhere": None if math.isnan(self.cosine_agree) else self.cosine_agree,
                "thresholds": {"clear_sigmas": CLEAR_SIGMAS, "against_cosine": AGAINST_COSINE,
                               "window_s": WINDOW_S}}


def check_wrench(evidence) -> WrenchCheck | None:
    """Judge every wrench row of ``evidence`` against the markers' mean tangential displacement.

    The markers' mean displacement is taken from their first recorded row (the gel at rest before contact) and
    resampled to the wrench's stamps; the rows are grouped in windows of :data:`WINDOW_S`, and a window is judged
    where its mean tangential force ``|F_t| > CLEAR_SIGMAS sigma_F / sqrt(m)`` (``m`` rows in it) and its mean marker shear
    ``|u_t| > CLEAR_SIGMAS sigma_u / sqrt(k)`` (one row's noise per axis from :attr:`sysid.evidence.Evidence.noise`,
    ``k`` markers); its rows contradict where the cosine of the two is below :data:`AGAINST_COSINE`.

    Args:
        evidence: the recording (:class:`sysid.evidence.Evidence`).

    Returns:
        the :class:`WrenchCheck`, or None where the recording lacks the wrench or the markers' positions.
    """
    present = evidence.channels_present
    if "wrench" not in present or "markers_xyz" not in present:
        return None
    t_w = np.asarray(evidence.t_ns["wrench"], dtype=np.int64)
    t_m = np.asarray(evidence.t_ns["markers_xyz"], dtype=np.int64)
    force = np.asarray(evidence.values("wrench"), dtype=float)[:, :3]
    markers = np.asarray(evidence.values("markers_xyz"), dtype=float)
    shear = resample(t_m, (markers - markers[0]).mean(axis=1), t_w, outside="clamp")  # (n, 3) m
    sigma_f = np.asarray(evidence.noise["wrench"], dtype=float)[:2]
    sigma_u = np.asarray(evidence.noise["markers_xyz"], dtype=float)[:2] / math.sqrt(markers.shape[1])
    t = (t_w - int(evidence.start_ns)) * 1e-9
    window = np.floor((t - t[0]) / WINDOW_S).astype(np.int64)  # (n,) the row's window
    count = np.bincount(window).astype(float)
    f_t = np.stack([np.bincount(window, force[:, a]) for a in range(2)], axis=1) / np.maximum(count, 1.0)[:, None]
    u_t = np.stack([np.bincount(window, shear[:, a]) for a in range(2)], axis=1) / np.maximum(count, 1.0)[:, None]
    clear_f = np.linalg.norm(f_t / np.maximum(sigma_f, 1e-30), axis=1) * np.sqrt(count) > CLEAR_SIGMAS  # mean's noise
    clear_u = np.linalg.norm(u_t / np.maximum(sigma_u, 1e-30), axis=1) > CLEAR_SIGMAS
    judged_w = clear_f & clear_u & (count > 0)
    cos_w = np.full(count.size, np.nan)
    norm = np.linalg.norm(f_t, axis=1) * np.linalg.norm(u_t, axis=1)
    cos_w[judged_w] = np.sum(f_t * u_t, axis=1)[judged_w] / norm[judged_w]
    judged = judged_w[window]
    cos = cos_w[window]
    against = judged & (cos < AGAINST_COSINE)
    spans = tuple((float(t[a]), float(t[b - 1])) for a, b in segments(against))
    agree = judged & ~against
    if against.any():
        return WrenchCheck(against, judged, spans, force[against].mean(axis=0), shear[against].mean(axis=0),
                           float(np.median(cos[against])),
                           float(np.median(cos[agree])) if agree.any() else math.nan)
    nan3 = np.full(3, np.nan)
    return WrenchCheck(against, judged, (), nan3, nan3, math.nan,
                       float(np.median(cos[agree])) if agree.any() else math.nan)
