"""A name stands only where the effect's own term gains on held-out data (sysid.diagnose.gain_guard)."""

from __future__ import annotations

from sysid.diagnose.gain_guard import heldout_gain, split_by_gain


def test_an_effect_whose_refit_gains_nothing_is_left_unexplained():
    refits = {"bending_plasticity": {"heldout_rms_before": 37.106, "heldout_rms_after": 37.106},  # no yield angle fits
              "latency": {"heldout_rms_before": 4.0, "heldout_rms_after": 1.0},
              "adhesion": {"heldout_rms_before": 12.0, "heldout_rms_after": None}}  # located, not refitted
    kept, dropped = split_by_gain(["bending_plasticity", "latency", "adhesion"], refits)
    assert kept == ["latency", "adhesion"]
    assert [d["effect"] for d in dropped] == ["bending_plasticity"]
    assert "unexplained" in dropped[0]["reason"] and dropped[0]["heldout_rms_after"] == 37.106


def test_a_term_that_harms_the_held_out_data_is_dropped_and_a_small_real_gain_is_kept():
    assert heldout_gain({"heldout_rms_before": 2.0, "heldout_rms_after": 2.2}) < 0.0
    assert heldout_gain({"heldout_rms_before": 0.0, "heldout_rms_after": 0.0}) is None
    assert heldout_gain({"heldout_rms_before": None, "heldout_rms_after": 1.0}) is None
    kept, dropped = split_by_gain(["stiction", "force_bias"],
                                  {"stiction": {"heldout_rms_before": 2.0, "heldout_rms_after": 2.2},
                                   "force_bias": {"heldout_rms_before": 2.0, "heldout_rms_after": 1.98}})
    assert kept == ["force_bias"] and dropped[0]["effect"] == "stiction"
