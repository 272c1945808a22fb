"""The calibration's stage for parameters without tangents: the stick regularisation of the
lagged friction, fitted on secants with the sensor calibration projected out.

``contact.eps_v`` (m/s) is the slip speed below which the lagged friction of the simulator's contact
(IPC's smoothed Coulomb friction, Li et al. 2020, "Incremental Potential Contact", sec. 5) treats a
contact as stuck: a sheared gel held by static friction creeps back at about that speed. It is a
regularisation whose physical limit is exact Coulomb stick (``eps_v -> 0``), so a real cell's value is
not on any data sheet, and on a press-and-slide it decides how much shear the gel keeps once the slide
stops. It has no forward sensitivity (its column is a difference), so instead of a fresh difference
column at every step it is fitted by Gauss-Newton on a secant column with Broyden updates
(:func:`sysid.secant.secant_least_squares`): a first probe a factor :data:`SECANT_FIRST_FACTOR` towards
exact stick, then one replay per step. Each replay's residual is taken after the closed-form sensor
calibration fitted to that replay (variable projection, Golub & Pereyra 1973, "The differentiation of
pseudo-inverses and nonlinear least squares problems whose variables separate", SIAM J. Numer. Anal.
10), so a gain or a marker scale does not stand in for the shear the friction keeps.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from sim_core.errors import SimulationDivergedError
from sysid.secant import SecantResult, secant_least_squares

SECANT_PARAMETERS = ("contact.eps_v",)
"""Calibration parameters fitted on secants by default (no tangents: a difference column each)."""

SECANT_FIRST_FACTOR = 1.0 / 3.0
"""Factor of the first probe on a secant parameter's scene value, and the largest factor of one
Gauss-Newton step: towards exact stick for ``contact.eps_v`` (its physical limit is 0), one third of
the factor-of-10 range a regularisation is known to (``CALIBRATION_BOUNDS``: 1 % to 10x)."""

SECANT_MIN_GAIN = 5.0e-4
"""Fraction by which the stage's best replay must lower the whitened RMS of its cost for its values to
be taken (:attr:`SecantStage.accepted`): the scale of the replays' numerical noise, as
:data:`sysid.fit.STOP_RMS` (Newton tolerance, contact set changes). A smaller gain is a flat cost,
where the values would follow the noise."""

SECANT_REPLAYS = 2
"""Default replay budget of the secant stage: the probe and one Gauss-Newton step on its secant. A
count, so that the calibration is the same on any machine; each replay is a plain one (no tangents)."""


@dataclass
class SecantStage:
    """What :func:`secant_calibration` fitted.

    Attributes:
        names: the parameters fitted.
        values: name -> the best value replayed (SI); the start's values when no replay was better.
        start: name -> the start value (SI).
        raw: channel -> the uncalibrated prediction at ``values``.
        result: the :class:`sysid.secant.SecantResult` (search coordinates ``log(value / start)``).
        channel_scale: channel -> the factor on its noise level in the stage's cost: its whitened
            RMS at the start times ``sqrt(n / mean n)`` (``n`` its sample count), so that every
            channel enters the start's cost with the same weight (:func:`secant_calibration`).
        wall_time_s: the stage's wall time, s.
    """

    names: tuple[str, ...]
    values: dict[str, float]
    start: dict[str, float]
    raw: dict[str, np.ndarray]
    result: SecantResult
    channel_scale: dict[str, float]
    wall_time_s: float

    @property
    def accepted(self) -> bool:
        """Whether the best replay lowered the stage's whitened RMS by :data:`SECANT_MIN_GAIN` or more."""
        r = self.result
        return r.cost_initial > 0.0 and 1.0 - math.sqrt(r.cost / r.cost_initial) >= SECANT_MIN_GAIN

    def summary(self) -> dict[str, Any]:
        """JSON-ready: parameters, start values, replays, status, whether the values were taken, cost
        before and after (in the stage's reweighted units) and the channel factors."""
        return {"fitted": list(self.names), "values": dict(self.values), "start": dict(self.start),
                "accepted": self.accepted,
                "replays": int(self.result.evaluations), "status": self.result.status,
                "cost_initial": float(self.result.cost_initial), "cost_final": float(self.result.cost),
                "channel_scale": dict(self.channel_scale), "wall_time_s": float(self.wall_time_s)}


def secant_calibration(model, base: Mapping[str, float], raw0: Mapping[str, np.ndarray],
                       calibrated: Callable[[Mapping[str, np.ndarray]], Mapping[str, np.ndarray]],
                       names: Sequence[str], bounds: Mapping[str, tuple[float, float]],
                       max_replays: int) -> SecantStage:
    """Fit the positive parameters ``names`` of ``model`` on secants (module docstring).

    Args:
        model: the :class:`~sysid.observation.ObservationModel` (its nominal values are the start).
        base: parameter values every replay of the stage sets (the calibration's other parameters).
        raw0: channel -> the uncalibrated prediction at the start (already replayed).
        calibrated: raw prediction -> calibrated prediction (the sensor calibration fitted to it).
        names: the parameters (positive; searched in ``log(value / start)``).
        bounds: name -> ``(lower, upper)`` SI, containing the start.
        max_replays: replays allowed (the probes included; fewer than ``len(names)``: none made).

    The cost gives every fitted channel one vote: each channel's whitened residual is divided by its
    RMS at the start and by ``sqrt`` of its sample count relative to the mean count. The model's gap,
    not the sensor noise, sets a channel's residual here, and its samples are far from independent
    (the card's points move as one body, the markers with the gel), so neither the noise level nor
    the sample count measures how much a channel tells: weighted by counts, the card's 273 points per
    frame would outvote the 63 markers and the wrench on nominal_s101 (80 % of the cost).

    Returns:
        the :class:`SecantStage`.

    Raises:
        ValueError: a start or bound that is not positive.
    """
    t0 = time.perf_counter()
    names = tuple(names)
    start = {n: float(model.parameter_value(n)) for n in names}
    if any(v <= 0.0 for v in start.values()) or any(bounds[n][0] <= 0.0 for n in names):
        raise ValueError("secant parameters are searched in log space: positive starts and bounds needed "
                         f"({start}, {bounds})")
    lower = np.array([math.log(bounds[n][0] / start[n]) for n in names])
    upper = np.array([math.log(bounds[n][1] / start[n]) for n in names])
    channels = tuple(model.channels)
    data = {ch: model.data(ch) for ch in channels}

    def whitened(raw: Mapping[str, np.ndarray], scale: Mapping[str, float]) -> np.ndarray:
        pred = calibrated(raw)
        return np.concatenate([((data[ch] - pred[ch]) / (model.sigma[ch] * scale[ch])).reshape(-1) for ch in channels])

    unit = {ch: 1.0 for ch in channels}
    r_unit = whitened(raw0, unit)
    scale, offset = {}, 0
    sizes = [data[ch].size for ch in channels if data[ch].size]
    reference = float(np.mean(sizes)) if sizes else 1.0
    for ch in channels:
        n = data[ch].size
        rms = float(np.sqrt(np.mean(r_unit[offset:offset + n] ** 2))) if n else 1.0
        scale[ch] = max(rms, 1e-12) * math.sqrt(n / reference) if n else 1.0
        offset += n
    r0 = whitened(raw0, scale)
    raws: dict[bytes, dict[str, np.ndarray]] = {np.zeros(len(names)).tobytes(): dict(raw0)}

    def residual(u: np.ndarray) -> np.ndarray | None:
        values = {**dict(base), **{n: start[n] * math.exp(float(x)) for n, x in zip(names, u)}}
        try:
            raw = model.predict_raw(model.simulate(values))
        except SimulationDivergedError:
            return None
        raws[np.asarray(u, dtype=float).tobytes()] = raw
        return whitened(raw, scale)

    steps = np.full(len(names), math.log(SECANT_FIRST_FACTOR))
    result = secant_least_squares(residual, np.zeros(len(names)), r0, steps, lower, upper, max_replays,
                                  max_step=np.abs(steps))
    values = {n: start[n] * math.exp(float(x)) for n, x in zip(names, result.u)}
    return SecantStage(names, values, start, raws[np.asarray(result.u, dtype=float).tobytes()], result, scale,
                       time.perf_counter() - t0)
