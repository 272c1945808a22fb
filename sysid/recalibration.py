"""The calibration's secant parameters re-estimated at the fitted materials, alternating with the fit until they settle.

:func:`sysid.calibration.calibrate` fits the stick regularisation ``contact.eps_v`` (m/s) of the lagged friction on
a secant (:mod:`sysid.calibration_secant`) at the materials the fit starts from, and the material fit then holds it.
The value it finds depends on those materials, so the start leaks into the answer through it: on nominal_s101
1.7 / 2.4 / 3.1 mm/s from starts at 0.7 / 1.0 / 1.3 x the scene's materials (session 52, 49fit), the gel modulus
then fitted -3.9 / -6.9 / -18.1 % from the engine's.

:func:`alternate` removes that leak at its cause, by block coordinate descent (e.g. Bezdek & Hathaway 2003, "Convergence
of alternating optimization", Neural Parallel Sci. Comput. 11): the secant stage is run again with the fitted
materials as its base, starting from the value the fit held; where it moves the value (the stage's own acceptance
rule: its best replay lowers the stage's whitened RMS by :data:`sysid.calibration_secant.SECANT_MIN_GAIN`, the
replays' numerical noise), the material fit is run again from where it ended with the new value held; until a stage
leaves the value where it is or :data:`ROUNDS` rounds are spent. A fixed point of the alternation no longer depends
on the start (wherever both stages are unique); each round costs the stage's replays plus a refit that starts at the
previous optimum.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import numpy as np

from sysid.calibration import CALIBRATION_BOUNDS, CalibrationResult, fit_sensor_calibration, nominal_sensor_calibration
from sysid.calibration_secant import SECANT_REPLAYS, SecantStage, secant_calibration

ROUNDS = 3
"""Default most rounds of :func:`alternate` (a secant stage and, where it moves the value, a refit each). A count, so
that the result is the same on any machine."""


@dataclass(frozen=True)
class Round:
    """One round of :func:`alternate`.

    Attributes:
        before, after: secant parameter -> value held by the fit before the round / found by its stage (SI).
        accepted: whether the stage moved the values (then the materials were refitted).
        materials: fitted parameter -> value after the round (SI; the previous fit's where not refitted).
        replays: replays of the round (the stage's and the refit's).
        wall_time_s: its wall time, s.
    """

    before: dict[str, float]
    after: dict[str, float]
    accepted: bool
    materials: dict[str, float]
    replays: int
    wall_time_s: float

    def summary(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {"before": dict(self.before), "after": dict(self.after), "accepted": self.accepted,
                "materials": dict(self.materials), "replays": int(self.replays), "wall_time_s": float(self.wall_time_s)}


def secant_bounds(stage: SecantStage) -> dict[str, tuple[float, float]]:
    """The search bounds of ``stage``'s parameters around the scene's values it started from
    (:data:`sysid.calibration.CALIBRATION_BOUNDS`), so that a later stage searches the same prior."""
    out = {}
    for name, start in stage.start.items():
        _, low, high = CALIBRATION_BOUNDS[name]
        out[name] = (start * low, start * high)
    return out


def alternate(model, result, sensor: CalibrationResult, refit: Callable[[Mapping[str, float]], Any],
              raw_of: Callable[[Any], Mapping[str, np.ndarray] | None], rounds: int = ROUNDS,
              replays: int = SECANT_REPLAYS) -> tuple[Any, list[Round]]:
    """Re-estimate the calibration's secant parameters at the fitted materials and refit, until they settle
    (module docstring).

    Args:
        model: the calibrated :class:`~sysid.observation.ObservationModel` (its nominal holds the secant values).
        result: the material fit (:class:`sysid.fit.FitResult`) at the calibration's secant values.
        sensor: the calibration (its :attr:`~sysid.calibration.CalibrationResult.secant` stage; None: nothing to do).
        refit: fitted values -> the material fit started there, at the model's current nominal.
        raw_of: a fit -> the uncalibrated prediction at its fitted values (None: replayed here).
        rounds: most rounds (0: none).
        replays: replay budget of each round's secant stage.

    Returns:
        ``(fit, rounds)``: the last fit, its ``initial`` / ``cost_initial`` / ``rms_initial`` /
        ``prediction_initial`` those of ``result`` (the user's start), its replays and times the sums over every fit
        and stage; and the :class:`Round` of each round made. ``sensor.params`` is updated in place.
    """
    first = sensor.secant if sensor is not None else None
    if first is None or not first.accepted or rounds < 1:
        return result, []
    names = tuple(first.names)
    bounds = secant_bounds(first)
    data = {ch: model.data(ch) for ch in model.channels}
    nominal = nominal_sensor_calibration(model)

    def sensor_calibrated(prediction):
        cal = fit_sensor_calibration(data, prediction, model.sigma, model.marker_rest, nominal, None,
                                     prior=sensor.gain_prior)
        return cal.apply(prediction, model.marker_rest)

    made: list[Round] = []
    current, extra_runs, extra_time, fits = result, 0, 0.0, [result]
    for _ in range(int(rounds)):
        t0 = time.perf_counter()
        before = {n: float(model.parameter_value(n)) for n in names}
        raw = raw_of(current)
        runs = 0
        if raw is None:
            raw = model.predict_raw(model.simulate(dict(current.values)))
            runs += 1
        stage = secant_calibration(model, dict(current.values), raw, sensor_calibrated, names, bounds, replays)
        runs += int(stage.result.evaluations)
        accepted = stage.accepted and any(stage.values[n] != before[n] for n in names)
        if accepted:
            model.set_nominal(stage.values)
            sensor.params.update(stage.values)
            current = refit(dict(current.values))
            fits.append(current)
        extra_runs += runs
        extra_time += time.perf_counter() - t0
        made.append(Round(before, dict(stage.values) if accepted else before, accepted, dict(current.values),
                          runs + (current.sim_runs if accepted else 0), time.perf_counter() - t0))
        if not accepted:
            break
    if len(fits) == 1:
        return result, made
    merged = dataclasses.replace(
        current, initial=dict(result.initial), cost_initial=result.cost_initial, rms_initial=result.rms_initial,
        prediction_initial=result.prediction_initial, history=[e for f in fits for e in f.history],
        sim_runs=sum(f.sim_runs for f in fits) + extra_runs,
        sim_time_s=sum(f.sim_time_s for f in fits), wall_time_s=result.wall_time_s + extra_time,
        warnings=list(current.warnings) + [
            f"the calibration's {', '.join(names)} re-estimated at the fitted materials and the materials refitted, "
            f"{len(fits) - 1} time(s): " + "; ".join(
                ", ".join(f"{n} {r.before[n]:.4g} -> {r.after[n]:.4g}" for n in names) for r in made)])
    return merged, made

