"""Search coordinates of simulator parameters: how a fit or an optimiser steps one parameter.

A positive scale parameter (modulus, stiffness, density, thickness, friction > 0) is searched in log
space, ``u = ln(theta / theta_0)`` (``theta_0`` the start value, so ``u_0 = 0`` and a unit step is a
factor e), within a factor 1000 of its start (:data:`LOG_SPAN`); a parameter that may be zero or is
bounded on both sides (Poisson ratio, damping, a length offset) is searched linearly,
``u = (theta - theta_0) / s``. ``thinshell sysid`` (:mod:`sysid.fit`) fits a recording in these
coordinates and the inverse tasks (:mod:`sim_core.optim.inverse_task`) search them, so a CMA-ES
step is relative and a gradient step respects the bounds in both.
"""

from __future__ import annotations

import math
from collections.abc import Collection
from dataclasses import dataclass

from sim_core.errors import CalibrationError

LOG_SPAN = math.log(1.0e3)
"""Log-space bound half-width: a positive parameter is searched within a factor 1000 of its start."""


@dataclass(frozen=True)
class ParameterSpec:
    """How one parameter is searched.

    Attributes:
        name: global parameter name (``Model.set_parameter``).
        initial: start value theta_0.
        log: search ``u = ln(theta / theta_0)``; else ``u = (theta - theta_0) / scale``.
        lower, upper: bounds on theta.
        scale: unit of the linear coordinate (1 for log parameters).
    """

    name: str
    initial: float
    log: bool
    lower: float
    upper: float
    scale: float = 1.0

    def to_value(self, u: float) -> float:
        """theta(u)."""
        return float(self.initial * math.exp(u)) if self.log else float(self.initial + self.scale * u)

    def to_u(self, value: float) -> float:
        """u(theta)."""
        return math.log(value / self.initial) if self.log else (value - self.initial) / self.scale

    @property
    def u_bounds(self) -> tuple[float, float]:
        """Bounds of u."""
        if self.log:
            return (math.log(self.lower / self.initial), math.log(self.upper / self.initial))
        return ((self.lower - self.initial) / self.scale, (self.upper - self.initial) / self.scale)


def parameter_spec(name: str, initial: float, offsets: Collection[str] = ()) -> ParameterSpec:
    """The search coordinate of parameter ``name`` starting at ``initial``.

    Positive scale parameters (moduli, stiffnesses, density, thickness, friction > 0): log, within a
    factor 1000. Poisson ratios: linear in [0, 0.499], scale 0.05. A length offset (a name in
    ``offsets``, m): linear within 1 mm of its start, scale 50 um. Zero-start non-negative parameters
    (damping, friction 0): linear in [0, inf), scale 1.

    Args:
        name: global parameter name.
        initial: start value theta_0 (parameter units).
        offsets: names of the length offsets among the parameters (``sysid.fit.parameter_spec`` passes
            the replay's sensor offsets, ``sysid.observation.SENSOR_PARAMETERS``; none for a ``Model``).

    Raises:
        CalibrationError: non-finite start (e.g. an infinite yield angle) or a negative one.
    """
    if not math.isfinite(initial):
        raise CalibrationError(f"parameter {name} starts at {initial}; cannot fit a non-finite value")
    if name.endswith("poisson_ratio"):
        return ParameterSpec(name, initial, False, 0.0, 0.499, 0.05)
    if name in offsets:
        return ParameterSpec(name, initial, False, initial - 1.0e-3, initial + 1.0e-3, 5.0e-5)
    if initial < 0.0:
        raise CalibrationError(f"parameter {name} starts at {initial} < 0")
    if initial == 0.0:
        return ParameterSpec(name, initial, False, 0.0, math.inf, 1.0)
    return ParameterSpec(name, initial, True, initial / math.exp(LOG_SPAN), initial * math.exp(LOG_SPAN))


def bounded_spec(spec: ParameterSpec, bounds: tuple[float, float] | None) -> ParameterSpec:
    """``spec`` with its range narrowed to ``bounds`` ``(lower, upper)`` (parameter units; None: unchanged).

    Raises:
        CalibrationError: bounds that leave no range, or a start value outside them.
    """
    if bounds is None:
        return spec
    lower, upper = max(spec.lower, float(bounds[0])), min(spec.upper, float(bounds[1]))
    if not lower < upper:
        raise CalibrationError(f"parameter {spec.name}: bounds {tuple(bounds)} leave no range within "
                               f"[{spec.lower:.6g}, {spec.upper:.6g}]")
    if not lower <= spec.initial <= upper:
        raise CalibrationError(f"parameter {spec.name} starts at {spec.initial:.6g}, outside its bounds "
                               f"[{lower:.6g}, {upper:.6g}]")
    return ParameterSpec(spec.name, spec.initial, spec.log, lower, upper, spec.scale)
