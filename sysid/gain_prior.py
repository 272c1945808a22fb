"""The declared prior of a tactile sensor's calibration gains, and what a gain at its bound means.

A sensor's calibration (:mod:`sysid.calibration`: force gain, marker displacement scales, focal lengths)
corrects a data sheet that is close, not a different sensor: a force sensor's gain, a marker
reconstruction's scale and a camera's focal length are known to a few per cent from the maker's
calibration. The fit keeps each gain within a declared prior around 1 (the focal lengths around the
scene's), ``[1 - w, 1 + w]`` with ``w`` the prior's relative half-width, :data:`DEFAULT_HALF_WIDTH` (15 %)
unless the sysid config file says otherwise for that sensor::

    calibration:
      gain_prior:
        default: {force_gain: 0.15, marker_scale: 0.15, focal: 0.15}
        sensors: {tactile: {force_gain: 0.3}}     # sensor name -> overrides of the default

A gain the recording would push past its prior stops on the bound, and the bound is not the answer: the
gap lies in the physics the gain multiplies (issue 49: a force gain of 0.5 on every recording of another
engine was an arm's compliance the replay lacked). :func:`gain_flags` says which gain stopped there, the
value the data asked for, and the likely physical cause (:data:`BOUND_CAUSES`), for the reports.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from sim_core.errors import ConfigError
from sim_core.scenes.scene_file import load_yaml
from sysid.data import DEFAULT_CONFIG, data_file

DEFAULT_HALF_WIDTH = 0.15
"""Relative half-width of every gain's prior by default (-): a maker's calibration is known to a few per
cent; 15 % leaves room for a worn gel or a re-mounted camera, not for a different sensor."""

GAIN_KEYS = ("force_gain", "marker_scale", "focal")
"""The prior's gains: the wrench gain (forces and torques), the marker displacement scales (xy and z) and
the focal lengths (fx, fy: relative to the scene's)."""

BOUND_CAUSES: dict[tuple[str, str], str] = {
    ("force_gain", "low"): ("the replay loads the gel harder than the recording: the contact or the effector's drive "
                            "is too stiff in the model (a compliant arm replayed kinematically, a gel or card "
                            "modulus too high, a normal offset pressing too deep)"),
    ("force_gain", "high"): ("the replay loads the gel less than the recording: the contact or the drive is too "
                             "compliant in the model (a gel or card modulus too low, a normal offset too shallow)"),
    ("marker_scale_xy", "low"): ("the simulated markers move further across the gel than the recorded ones: too much "
                                 "lateral load (friction too high, a too stiff drive) or a gel too soft in shear"),
    ("marker_scale_xy", "high"): ("the simulated markers move less across the gel than the recorded ones: too little "
                                  "lateral load (friction too low) or a gel too stiff in shear (modulus, Poisson "
                                  "ratio, a gel mesh too coarse), or a recorded gel that softens in shear as it "
                                  "slides (a finite-strain law other than the model's: try --gel-element "
                                  "green_strain, or auto to let the recording choose)"),
    ("marker_scale_z", "low"): ("the simulated gel is pressed deeper than the recorded one: too much normal load (a "
                                "too stiff drive or contact) or a gel too soft in compression"),
    ("marker_scale_z", "high"): ("the simulated gel is pressed less deep than the recorded one: too little normal "
                                 "load or a gel too stiff in compression (modulus, Poisson ratio near 0.5, a gel "
                                 "mesh too coarse through its thickness), or a recorded gel that sinks further "
                                 "when it slides at the same load (compare the pressed and the sliding marker "
                                 "depth per newton; a linear-elastic pad stiffens; a gel whose law is written in "
                                 "the Green strain sinks: try --gel-element green_strain, or auto to let the recording "
                                 "choose)"),
    ("fx", "low"): "the camera's focal length or distance in the scene is off (a different lens or mount)",
    ("fx", "high"): "the camera's focal length or distance in the scene is off (a different lens or mount)",
    ("fy", "low"): "the camera's focal length or distance in the scene is off (a different lens or mount)",
    ("fy", "high"): "the camera's focal length or distance in the scene is off (a different lens or mount)",
}
"""(gain, bound) -> the likely physical cause of a gain that stops on that bound of its prior."""

PRIOR_OF = {"force_gain": "force_gain", "marker_scale_xy": "marker_scale", "marker_scale_z": "marker_scale",
            "fx": "focal", "fy": "focal"}
"""Calibration field -> the prior (:data:`GAIN_KEYS`) that bounds it."""


@dataclass(frozen=True)
class GainPrior:
    """Relative half-widths of one sensor's gain priors (each in (0, 1)).

    Attributes:
        force_gain: of the wrench gain (-).
        marker_scale: of the marker displacement scales, xy and z (-).
        focal: of the focal lengths relative to the scene's (-).
        source: where the values came from (a config file, or "default").
    """

    force_gain: float = DEFAULT_HALF_WIDTH
    marker_scale: float = DEFAULT_HALF_WIDTH
    focal: float = DEFAULT_HALF_WIDTH
    source: str = "default"

    def __post_init__(self) -> None:
        for key in GAIN_KEYS:
            w = getattr(self, key)
            if not (isinstance(w, (int, float)) and math.isfinite(w) and 0.0 < w < 1.0):
                raise ConfigError(f"{self.source}: gain prior {key} must be a relative half-width in (0, 1), got {w!r}")

    def bounds(self, key: str) -> tuple[float, float]:
        """``(1 - w, 1 + w)`` of the prior ``key`` (one of :data:`GAIN_KEYS`)."""
        w = float(getattr(self, key))
        return 1.0 - w, 1.0 + w

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready: each half-width, its bounds and the source."""
        return {**{k: {"half_width": float(getattr(self, k)), "bounds": list(self.bounds(k))} for k in GAIN_KEYS},
                "source": self.source}


def load_gain_prior(sensor: str, path: str | Path | None = None) -> GainPrior:
    """The gain prior of ``sensor`` from the ``calibration.gain_prior`` section of a sysid config file
    (module docstring); the packaged ``sysid/data/default.yaml`` when ``path`` is None.

    Raises:
        ConfigError: a missing file, an unknown key, or a half-width outside (0, 1), named with the file.
    """
    file = Path(path) if path is not None else data_file(DEFAULT_CONFIG)
    if not file.is_file():
        raise ConfigError(f"{file}: sysid config file does not exist")
    doc = load_yaml(file.read_text(encoding="utf-8")) or {}
    section = (doc.get("calibration") or {})
    unknown = [k for k in section if k != "gain_prior"]
    if unknown:
        raise ConfigError(f"{file}: unknown key calibration.{unknown[0]} (allowed: gain_prior)")
    prior = section.get("gain_prior") or {}
    unknown = [k for k in prior if k not in ("default", "sensors")]
    if unknown:
        raise ConfigError(f"{file}: unknown key calibration.gain_prior.{unknown[0]} (allowed: default, sensors)")

    def widths(block: Any, where: str) -> dict[str, float]:
        if block is None:
            return {}
        if not isinstance(block, Mapping):
            raise ConfigError(f"{file}: {where} must be a mapping of {', '.join(GAIN_KEYS)}, got {block!r}")
        bad = [k for k in block if k not in GAIN_KEYS]
        if bad:
            raise ConfigError(f"{file}: unknown key {where}.{bad[0]} (allowed: {', '.join(GAIN_KEYS)})")
        return {k: block[k] for k in block}

    values = widths(prior.get("default"), "calibration.gain_prior.default")
    sensors = prior.get("sensors") or {}
    if not isinstance(sensors, Mapping):
        raise ConfigError(f"{file}: calibration.gain_prior.sensors must be a mapping of sensor name -> gains")
    values.update(widths(sensors.get(sensor), f"calibration.gain_prior.sensors.{sensor}"))
    return GainPrior(**values, source=str(file))


def gain_flags(fitted: Mapping[str, float], unbounded: Mapping[str, float], nominal: Mapping[str, float],
               prior: GainPrior) -> dict[str, dict[str, Any]]:
    """Per calibrated gain: its value, the value the data asked for, the prior's bounds, and whether it stopped
    on a bound, with the likely physical cause (:data:`BOUND_CAUSES`).

    Args:
        fitted: calibration field -> the fitted (bounded) value (``force_gain``, ``marker_scale_xy``, ``marker_scale_z``,
            ``fx``, ``fy``).
        unbounded: field -> the value the recording asked for before the prior bounded it (fields not fitted absent).
        nominal: field -> the scene's value the prior is relative to (1 for gains, the scene's focal lengths).
        prior: the :class:`GainPrior`.

    Returns:
        field -> ``{"value", "unbounded", "bounds", "at_bound" ("low" | "high" | None), "cause"}`` for the fields
        in ``unbounded``.
    """
    out: dict[str, dict[str, Any]] = {}
    for field, asked in unbounded.items():
        low, high = (nominal.get(field, 1.0) * b for b in prior.bounds(PRIOR_OF[field]))
        asked = float(asked)
        side = "low" if asked < low else "high" if asked > high else None
        out[field] = {"value": float(fitted[field]), "unbounded": asked, "bounds": [float(low), float(high)],
                      "at_bound": side,
                      "cause": None if side is None else
                      (f"{field} stopped on its prior's {side} bound ({low if side == 'low' else high:.4g}; the data "
                       f"asked for {asked:.4g}): not a calibration but a model gap: {BOUND_CAUSES[(field, side)]}")}
    return out
