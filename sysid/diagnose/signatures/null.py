"""Decisions on the signature tests: thresholds from the noise model, or a null calibrated on
recordings the user declares normal.

Every effect is named only when its test passes two thresholds: the **statistic** (whitened SSE the
effect's pattern removes, noise units) must be far beyond what noise gives (a chi-square tail), and
the **effect size** must be physically resolvable (a delay of at least two sample periods of the stream read, a
distortion of at least two pixel-noise sigmas at the markers' radius, a permanent set of at least
ten sheet-tracking sigmas, a static-friction excess at breakaway, beyond the normal load's, of at
least two of its standard deviations propagated from the noise model, ...). The timing effects must
also explain most of the event windows' excess energy (``min_explained``): a systematic gap between
simulator and recording, which even a nominal recording has, leaves most of it in place.

With baseline recordings (``thinshell diagnose BAG --baseline B1 B2``) each statistic threshold is
raised to ``baseline_factor`` times the largest statistic the same test reaches on the baselines:
what is different in this run, beyond the usual gap between the simulator and this cell (SYSID.md
"Model-form gap"). The effect-size thresholds stay what the instrument resolves (sample periods,
noise levels): an effect size is an estimate whose resolution is the sensor's, while how much of
the recording a test's pattern explains on a normal recording of the cell is what the statistic
measures. A size read on a baseline (e.g. a nominal lift's contact force leading its replay by
11 ms) is the cell's gap in that test's pattern; the statistic it gives there is the null the test
recording must exceed. With baselines no threshold is lower than without, so a baseline can only
withdraw a name.

Damping reads the same event windows as the timing effects with the opposite sign (the force leads
the replay instead of following it), so it is not confused with them. Its statistic is already
divided by the windows' dispersion after the lead (:func:`sysid.diagnose.signatures.damping.dispersion`):
a gap the lead leaves in place raises the bar in proportion, so it is not held to ``min_explained``
as well.

Confusable pairs (SYSID.md step 5): latency vs gel viscoelasticity is decided by the events' shape
(a pure delay against a first-order lag, :mod:`sysid.diagnose.signatures.timing`), also when only
one of the two passes its thresholds: the lag, the richer model (a time constant and a share), is
named only when it fits the events significantly better than the delay (the paired ``z`` of the two
fits at least :data:`SHAPE_Z`, one-sided), and then the latency is not; otherwise the lag is not named (for short
delays the two shapes agree to first order, and the delay is the simpler explanation). Both are held
to the same size rule (:func:`sysid.diagnose.signatures.timing.timing_size`) in the same unit, the
response's mean delay: every event delayed (or lagged), and the smallest press's mean over its rising
and falling events (an effect of the stream delays or lags every event; the mean cancels a depth gap
of the calibrated replay, which moves a press's two events in opposite directions).
Adhesion on a lift is a property of the contact (the gel tacks to the sheet in every lift of the
cell): it is named beside another effect, and otherwise reported under ``contact_properties``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from sysid.diagnose.signatures.base import Recording, SignatureResult
from sysid.diagnose.signatures.friction import resolvable_excess
from sysid.diagnose.signatures.sheet import RESOLVABLE_SET_SIGMAS

STATISTIC_THRESHOLD = 50.0
"""Default statistic threshold, noise units: far in the tail of the chi-square laws of the tests
(at most 12 degrees of freedom for the force bias; P(chi2_12 > 50) < 2e-6; the stiction test's
breakaway decay has two in each of its two series, amplitude and decay time searched on a grid of at
most 19 values per series, P(chi2_4 > 50) * 19^2 < 2e-7)."""

SHAPE_Z = 1.645
"""The paired statistic of the first-order lag against the delay
(:func:`sysid.diagnose.signatures.timing.paired_shape_z`) that names the lag: the one-sided 5 % point
of the standard normal."""

MIN_EXPLAINED = 0.5
"""Fraction of the event windows' excess energy (``SSE - samples``) a timing effect must remove."""

SIZE_TOLERANCE = 1e-9
"""Relative tolerance of the effect-size comparison (floating-point rounding of grid values)."""

SECONDARY_EFFECTS = ("adhesion",)
"""Effects named only beside another one (contact properties of the cell)."""


@dataclass
class Thresholds:
    """Statistic and effect-size thresholds per effect.

    Attributes:
        statistic: effect -> minimum statistic (noise units).
        effect_size: effect -> minimum effect size (the test's unit).
        source: effect -> ``"default"`` or ``"baseline"``.
    """

    statistic: dict[str, float] = field(default_factory=dict)
    effect_size: dict[str, float] = field(default_factory=dict)
    source: dict[str, str] = field(default_factory=dict)


def timing_size_threshold(rec: Recording) -> float:
    """Smallest timing effect that is named, s: two sample periods of the stream the timing tests
    read (the wrench, else the markers); the same for a delay (latency), a first-order lag's mean
    delay (gel viscoelasticity) and a lead (damping).

    Derivation: the three tests (:mod:`sysid.diagnose.signatures.timing`,
    :mod:`sysid.diagnose.signatures.damping`) read one stream against the replay in the same event
    windows, so a shift is resolved to that stream's own sample period (the 200 Hz wrench: 5 ms; the
    delay and the lag are searched on a grid of half that period), and two periods keep a one-sample
    misalignment of the event windows (the 5 ms averaging of every tactile sample, the replay step)
    below the threshold."""
    for ch in ("wrench", "markers_xyz"):
        if rec.has(ch) and ch in rec.t and len(rec.t[ch]) > 1:
            return 2.0 * rec.sample_period(ch)
    return 2.0 * 0.01


def default_thresholds(rec: Recording) -> Thresholds:
    """Thresholds from the recording's noise model and sample periods."""
    th = Thresholds()
    timing = timing_size_threshold(rec)
    uv_sigma = float(np.max(rec.sigma["markers_uv"])) if "markers_uv" in rec.sigma else 0.15
    sheet_sigma = float(np.max(rec.sigma["sheet_points"])) if "sheet_points" in rec.sigma else 5e-5
    sizes = {"lens_distortion": 2.0 * uv_sigma, "force_bias": 0.5, "latency": timing,
             "gel_viscoelasticity": timing, "damping": timing,
             "bending_plasticity": RESOLVABLE_SET_SIGMAS * sheet_sigma, "adhesion": RESOLVABLE_SET_SIGMAS * sheet_sigma,
             "stiction": resolvable_excess(rec)}
    for effect, size in sizes.items():
        th.statistic[effect] = STATISTIC_THRESHOLD
        th.effect_size[effect] = float(size)
        th.source[effect] = "default"
    return th


def calibrated_thresholds(default: Thresholds, baselines: Sequence[Mapping[str, SignatureResult]],
                          baseline_factor: float = 2.0) -> Thresholds:
    """Raise the default statistic thresholds to ``baseline_factor`` times the largest statistic
    each test reaches on the baseline recordings (tests not applicable there are skipped); the
    effect-size thresholds stay the default ones, the instrument's resolution (module docstring)."""
    th = Thresholds(dict(default.statistic), dict(default.effect_size), dict(default.source))
    for results in baselines:
        for effect, r in results.items():
            if not r.applicable or effect not in th.statistic:
                continue
            s = baseline_factor * r.statistic
            if s > th.statistic[effect]:
                th.statistic[effect], th.source[effect] = s, "baseline"
    return th


@dataclass
class Decision:
    """What the signature tests say about one recording.

    Attributes:
        explained_by: named effects, strongest first (SYSID.md contract; secondary effects last).
        ties: confusable pairs left undecided, ``[[a, b], ...]``.
        contact_properties: secondary effects found without a primary one (not named).
        detected: every effect whose test passed.
    """

    explained_by: list[str]
    ties: list[list[str]]
    contact_properties: list[str]
    detected: list[str]


def _passes(r: SignatureResult, th: Thresholds) -> bool:
    if not r.applicable:
        return False
    r.threshold = {"statistic": th.statistic.get(r.effect, STATISTIC_THRESHOLD),
                   "effect_size": th.effect_size.get(r.effect, 0.0), "source": th.source.get(r.effect, "default")}
    # sizes read off a grid of sample periods (s) meet a threshold of whole periods: compare them to
    # a part in 1e9 (the bag's nanosecond stamps), not to the float's last bit
    ok = (r.statistic >= r.threshold["statistic"]
          and r.effect_size >= r.threshold["effect_size"] - SIZE_TOLERANCE * abs(r.threshold["effect_size"]))
    if ok and r.effect in ("latency", "gel_viscoelasticity"):
        key = {"latency": "explained_delay", "gel_viscoelasticity": "explained_lag"}[r.effect]
        explained = float(r.detail.get(key, 0.0))
        ok = explained >= MIN_EXPLAINED
        if not ok:
            r.reason = (f"statistic and size pass, but the fitted {key.removeprefix('explained_')} removes "
                        f"{explained:.0%} of the event windows' excess, under the {MIN_EXPLAINED:.0%} a timing "
                        f"effect must explain")
        if ok and r.effect == "gel_viscoelasticity":
            ok = 0.0 < float(r.estimate.get("fraction", 0.0))
    return bool(ok)


def decide(results: Mapping[str, SignatureResult], th: Thresholds) -> Decision:
    """Name the effects whose tests pass; resolve the latency / viscoelasticity pair by shape.

    Sets ``detected`` and ``threshold`` on every result.
    """
    for r in results.values():
        r.detected = _passes(r, th)
    ties: list[list[str]] = []
    lat, visco = results.get("latency"), results.get("gel_viscoelasticity")
    if lat is not None and visco is not None and (lat.detected or visco.detected):
        # one timing pattern, two shapes: the shape decides even when only one of them passes its
        # thresholds (a delay just below its resolvable size is not a lag because the lag passed)
        z = float(lat.detail.get("shape_z", 0.0))
        if z >= SHAPE_Z and lat.detected:
            lat.detected, lat.reason = False, (f"the events fit a first-order lag significantly better than a "
                                               f"delay (paired z {z:.2f}): gel viscoelasticity")
        elif z < SHAPE_Z and visco.detected:
            visco.detected, visco.reason = False, (f"a first-order lag does not fit the events significantly better "
                                                   f"than a pure delay (paired z {z:.2f} < {SHAPE_Z})")
    detected = [e for e, r in results.items() if r.detected]
    ratio = {e: results[e].statistic / max(results[e].threshold["statistic"], 1e-12) for e in detected}
    primary = sorted((e for e in detected if e not in SECONDARY_EFFECTS), key=lambda e: -ratio[e])
    secondary = sorted((e for e in detected if e in SECONDARY_EFFECTS), key=lambda e: -ratio[e])
    if primary:
        return Decision(primary + secondary, ties, [], detected)
    for e in secondary:
        results[e].reason = "a contact property of this cell (named only beside another effect)"
    return Decision([], ties, secondary, detected)
