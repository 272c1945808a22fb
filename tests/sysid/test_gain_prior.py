"""The sensor gains' declared prior (sysid.gain_prior): +-15 % by default, per sensor in the sysid config file,
clear errors naming the file and key, and a flag with a physical cause for a gain that stops on a bound."""

from __future__ import annotations

import pytest

from sim_core.errors import ConfigError
from sysid.gain_prior import DEFAULT_HALF_WIDTH, GainPrior, gain_flags, load_gain_prior


def test_the_packaged_config_declares_fifteen_percent_for_every_gain():
    prior = load_gain_prior("tactile")
    assert DEFAULT_HALF_WIDTH == 0.15
    for key in ("force_gain", "marker_scale", "focal"):
        assert prior.bounds(key) == pytest.approx((0.85, 1.15))
    assert prior.source.endswith("default.yaml")


def test_a_sensor_of_the_config_file_takes_its_own_prior_and_others_the_default(tmp_path):
    path = tmp_path / "sysid.yaml"
    path.write_text("calibration:\n  gain_prior:\n    default: {force_gain: 0.1}\n"
                    "    sensors: {left: {force_gain: 0.3, focal: 0.05}}\n")
    left, right = load_gain_prior("left", path), load_gain_prior("right", path)
    assert left.bounds("force_gain") == pytest.approx((0.7, 1.3)) and left.bounds("focal") == pytest.approx((0.95, 1.05))
    assert right.bounds("force_gain") == pytest.approx((0.9, 1.1)) and right.marker_scale == DEFAULT_HALF_WIDTH


@pytest.mark.parametrize("text, match", [
    ("calibration:\n  gain_prior:\n    default: {force_gian: 0.1}\n", r"unknown key calibration.gain_prior.default.force_gian"),
    ("calibration:\n  gain_prior:\n    sensors: {tactile: {focal: 1.5}}\n", r"focal must be a relative half-width in \(0, 1\)"),
    ("calibration:\n  gain_bounds: {}\n", r"unknown key calibration.gain_bounds"),
])
def test_bad_prior_is_one_error_naming_the_file_and_key(tmp_path, text, match):
    path = tmp_path / "sysid.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=match) as err:
        load_gain_prior("tactile", path)
    assert str(path) in str(err.value)


def test_flags_name_the_side_the_asked_value_and_a_physical_cause():
    """A kinematic replay of a compliant arm asks for a force gain of 0.6 (it presses harder than the
    recording): flagged low, 'too stiff'; a marker depth scale of 1.5 asked: flagged high, the gel too stiff in
    compression; a focal length inside its prior (relative to the scene's) is not flagged."""
    fitted = {"force_gain": 0.85, "marker_scale_z": 1.15, "fx": 303.0}
    flags = gain_flags(fitted, {"force_gain": 0.6, "marker_scale_z": 1.5, "fx": 303.0}, {"fx": 300.0}, GainPrior())
    assert flags["force_gain"]["at_bound"] == "low" and flags["force_gain"]["unbounded"] == 0.6
    assert "not a calibration but a model gap" in flags["force_gain"]["cause"]
    assert "drive" in flags["force_gain"]["cause"] and "too stiff" in flags["force_gain"]["cause"]
    assert flags["marker_scale_z"]["at_bound"] == "high" and "compression" in flags["marker_scale_z"]["cause"]
    assert flags["fx"]["at_bound"] is None and flags["fx"]["cause"] is None
    assert flags["fx"]["bounds"] == pytest.approx([255.0, 345.0])
