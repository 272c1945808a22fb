"""The sensor gains profiled out of a material fit: refitted in closed form at every replay.

:func:`sysid.calibration.calibrate` fits the sensor calibration (force gain, marker scales, camera
intrinsics, within their prior) once, at the scene's values. A material fit that then holds those gains
fixed is biased by them wherever the start is off: at a start 20 % off in gel modulus and friction the
gains take up that error (on a recording of this simulator through a concealed 2,000 N/m arm: lateral
marker scale on its 0.85 bound, the data asking 0.66; force gain 0.87), and the fit, holding them, lands
12 % off in friction, 5 robust sigma from the truth (docs/benchmarks_log.md, session 51, 49sysdrive).

:class:`GainProfile` refits the gains to each replay's raw prediction instead (variable projection: the
gains are linear scales of the prediction, so their optimum at given materials is a closed form, and the
materials are fitted on the profiled cost; Golub & Pereyra 1973, "The differentiation of pseudo-inverses and
nonlinear least squares problems whose variables separate", SIAM J. Numer. Anal. 10(2)). It costs no replay:
:meth:`sysid.observation.ObservationModel.predict` calls it. The Jacobian of a joint replay is taken with
the gains of its own point (held there; by the envelope theorem the profiled cost's gradient is then exact
where the gains are inside their prior). The Jacobian is projected onto the complement of the gains'
columns (:meth:`GainProfile.project`, Kaufman 1975, "A variable projection method for solving separable
nonlinear least squares problems", BIT 15): a material direction that a gain inside its prior takes up
then counts for nothing, so the Gauss-Newton step follows the profiled cost and the reported sigma carries
the gains' freedom (the gel modulus and the marker scales trade against each other where the arm, not the
gel, sets the load).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import numpy as np

from sysid.calibration import SensorCalibration, fit_sensor_gains, masked_rows, nominal_sensor_calibration
from sysid.gain_prior import GainPrior, gain_flags


PROFILED_FIELDS = ("force_gain", "marker_scale_xy", "marker_scale_z", "fx", "fy", "cx", "cy",
                   "torque_arm_x", "torque_arm_y", "torque_arm_z")
"""Fields of :class:`~sysid.calibration.SensorCalibration` the closed form fits, whose columns are projected out
(a gain on its prior's bound is held there and is not)."""

GAIN_DIFFERENCE = 1.0e-6
"""Relative step (absolute, m, for a torque arm) of the gains' columns: the calibrated prediction is linear or
nearly so in each of them, so a difference of the closed form needs no replay and no care."""


class GainProfile:
    """Closed-form sensor gains of a raw prediction (module docstring).

    Args:
        model: the calibrated :class:`~sysid.observation.ObservationModel` (its data, noise levels and
            ``marker_rest``).
        prior: the gains' prior (:class:`~sysid.gain_prior.GainPrior`, as the calibration's).

    Attributes:
        last: ``(calibration, asked)`` of the last call: the :class:`~sysid.calibration.SensorCalibration` and,
            per gain, the value the data asked for before the prior bounded it.
    """

    def __init__(self, model, prior: GainPrior) -> None:
        self.model = model
        self.prior = prior
        self.nominal = nominal_sensor_calibration(model)
        self.last: tuple[SensorCalibration, dict[str, float]] | None = None
        self._of: dict[int, tuple[SensorCalibration, dict[str, float]]] = {}

    def __call__(self, raw: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The calibrated prediction of the raw aligned prediction ``raw`` (channel -> array), with the gains
        fitted to it; :attr:`last` holds them, and :meth:`calibration_of` finds them from the returned dict."""
        m = self.model
        data = {ch: m.data(ch) for ch in raw}
        cal, asked = fit_sensor_gains(data, raw, m.sigma, m.marker_rest, self.nominal, masked_rows(m, None),
                                      prior=self.prior)
        out = cal.apply(raw, m.marker_rest)
        self.last = (cal, asked)
        self._of[id(out)] = self.last
        return out

    def calibration_of(self, prediction: Mapping[str, np.ndarray]) -> tuple[SensorCalibration, dict[str, float]] | None:
        """``(calibration, asked)`` that made the calibrated ``prediction`` (a dict this profile returned and that
        is still alive), or None."""
        return self._of.get(id(prediction))

    @staticmethod
    def flags_of(found: tuple[SensorCalibration, dict[str, float]], prior: GainPrior, model) -> dict[str, Any]:
        """:func:`sysid.gain_prior.gain_flags` of ``found`` (:meth:`calibration_of`) under ``prior``."""
        cal, asked = found
        nominal = nominal_sensor_calibration(model)
        return gain_flags(cal.as_dict(), asked, {"fx": nominal.fx, "fy": nominal.fy}, prior)

    def project(self, raw: Mapping[str, np.ndarray], J: np.ndarray) -> np.ndarray:
        """``J`` ``(m, p)`` (the whitened residual's Jacobian at the point whose raw prediction is ``raw``, gains
        held at :attr:`last`) projected onto the complement of the free gains' whitened columns (module
        docstring). Must follow the call that made :attr:`last` from ``raw``."""
        if self.last is None:
            return J
        cal, asked = self.last
        m = self.model
        base = cal.apply(raw, m.marker_rest)
        cols = []
        for name in PROFILED_FIELDS:
            value = float(getattr(cal, name))
            if name in asked and not abs(float(asked[name]) - value) <= 1e-12 * max(abs(value), 1.0):
                continue  # held on its prior's bound
            h = GAIN_DIFFERENCE * (abs(value) if name not in ("torque_arm_x", "torque_arm_y", "torque_arm_z") else 1.0)
            shifted = dataclasses.replace(cal, **{name: value + h}).apply(raw, m.marker_rest)
            col = np.concatenate([m.whiten_derivative(ch, ((shifted[ch] - base[ch]) / h)[..., None])[:, 0]
                                  for ch in m.channels])
            if np.any(col):
                cols.append(col)
        if not cols:
            return J
        q, rr = np.linalg.qr(np.stack(cols, axis=1))
        keep = np.abs(np.diag(rr)) > 1e-10 * np.abs(np.diag(rr)).max()
        q = q[:, keep]
        return J - q @ (q.T @ J)
