"""Search coordinates of simulator parameters (sim_core.parameter_coordinates): log space for positive scale
parameters, linear for Poisson ratios, zero starts and the length offsets a caller names, and bounds."""

from __future__ import annotations

import math

import pytest

from sim_core.errors import CalibrationError
from sim_core.parameter_coordinates import LOG_SPAN, bounded_spec, parameter_spec


def test_a_positive_parameter_is_searched_in_log_space_within_a_factor_1000():
    spec = parameter_spec("sheet.bending_stiffness", 8.0e-3)
    assert spec.log and spec.to_u(8.0e-3) == 0.0 and spec.to_value(1.0) == pytest.approx(8.0e-3 * math.e)
    assert spec.to_value(spec.to_u(2.0e-2)) == pytest.approx(2.0e-2)
    assert spec.u_bounds == pytest.approx((-LOG_SPAN, LOG_SPAN)) and spec.upper / spec.lower == pytest.approx(1e6)


def test_an_offset_named_by_the_caller_is_linear_within_a_millimetre():
    """The same name is a log parameter unless the caller declares it a length offset (sysid's sensor offset)."""
    assert parameter_spec("sensor.normal_offset", 2.0e-4).log
    spec = parameter_spec("sensor.normal_offset", 2.0e-4, offsets=("sensor.normal_offset",))
    assert not spec.log and (spec.lower, spec.upper) == pytest.approx((-8.0e-4, 1.2e-3))
    assert spec.to_value(1.0) == pytest.approx(2.0e-4 + 5.0e-5)
    assert spec.u_bounds == pytest.approx((-20.0, 20.0))
    negative = parameter_spec("sensor.normal_offset", -3.0e-4, offsets=("sensor.normal_offset",))
    assert negative.lower == pytest.approx(-1.3e-3)     # an offset may start below zero
    with pytest.raises(CalibrationError, match=r"sensor.normal_offset starts at -0.0003 < 0"):
        parameter_spec("sensor.normal_offset", -3.0e-4)


def test_poisson_ratio_and_zero_start_are_linear():
    nu = parameter_spec("gel.poisson_ratio", 0.45)
    assert not nu.log and (nu.lower, nu.upper, nu.scale) == (0.0, 0.499, 0.05)
    damping = parameter_spec("damping", 0.0)
    assert not damping.log and (damping.lower, damping.upper) == (0.0, math.inf)
    with pytest.raises(CalibrationError, match="non-finite"):
        parameter_spec("sheet.yield_angle", math.inf)


def test_bounds_narrow_the_range_and_refuse_an_empty_one_or_a_start_outside():
    spec = bounded_spec(parameter_spec("contact.stiffness", 2.0e4), (1.0e4, 5.0e4))
    assert (spec.lower, spec.upper) == (1.0e4, 5.0e4) and spec.log
    assert bounded_spec(spec, None) is spec
    with pytest.raises(CalibrationError, match="contact.stiffness: bounds .* leave no range"):
        bounded_spec(spec, (5.0e4, 3.0e4))
    with pytest.raises(CalibrationError, match="contact.stiffness starts at 20000, outside its bounds"):
        bounded_spec(spec, (3.0e4, 4.0e4))
