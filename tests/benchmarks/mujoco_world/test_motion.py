"""The MuJoCo generator's commanded motions (pure numpy; MuJoCo is not imported)."""

import numpy as np
import pytest

from benchmarks.mujoco_world import motion as mm


def test_min_jerk_peak_speed_is_1p875_times_the_mean():
    # analytic: s'(1/2) = 30 tau^2 - 60 tau^3 + 30 tau^4 at tau = 1/2 = 15/8
    tau = np.linspace(0.0, 1.0, 200001)
    s = mm.min_jerk(tau)
    v = np.gradient(s, tau)
    assert s[0] == 0.0 and s[-1] == pytest.approx(1.0)
    assert v.max() == pytest.approx(1.875, rel=1e-6)
    assert abs(v[0]) < 1e-6 and abs(v[-1]) < 1e-6


def test_press_slide_reaches_depth_slides_and_returns():
    contact_z = 3.0e-4
    m = mm.press_slide((0.05, -0.01), 0.002, (0.015, -0.01), 0.004, 0.008, 0.02, 0.01, contact_z,
                       rests=(0.1, 0.4, 0.3, 0.3))
    press, slide, lift = m.segments
    assert press.duration == pytest.approx(0.006 / 0.008)
    assert slide.duration == pytest.approx(np.hypot(0.015, 0.01) / 0.02)
    start = m.command(0.0)
    pressed = m.command(press.t0 + press.duration + 0.1)
    slid = m.command(slide.t0 + slide.duration + 0.1)
    end = m.command(m.duration_s)
    np.testing.assert_allclose(start, [0.05, -0.01, contact_z + 0.004])
    np.testing.assert_allclose(pressed, [0.05, -0.01, contact_z - 0.002], atol=1e-12)
    np.testing.assert_allclose(slid - pressed, [0.015, -0.01, 0.0], atol=1e-12)
    np.testing.assert_allclose(end, [0.065, -0.02, contact_z + 0.004], atol=1e-12)
    assert m.duration_s == pytest.approx(0.1 + press.duration + 0.4 + slide.duration + 0.3 + lift.duration + 0.3)
    assert m.labels()["depth"] == 0.002 and m.labels()["kind"] == "press_slide"


def test_lift_fold_tacks_before_the_rise_lifts_straight_up_first_and_peels_at_the_last_rise():
    m = mm.lift_fold((0.088, 0.0), 0.0015, 0.012, 0.011, 0.004, 0.006, 0.014, 3.0e-4, lift_first=0.005)
    press, up, fold, peel = m.segments
    assert m.tack_on_s == pytest.approx(up.t0 - 0.05)
    assert m.tack_off_s == pytest.approx(peel.t0)
    np.testing.assert_allclose(up.delta, [0.0, 0.0, 0.005])
    np.testing.assert_allclose(fold.delta, [-0.011, 0.0, 0.0015 + 0.012 - 0.005])
    # back to back at the same mean speed: the two speed peaks are equal (1.875 v_fold)
    assert fold.t0 == pytest.approx(up.t0 + up.duration)
    assert up.duration == pytest.approx(0.005 / 0.014)
    t = np.linspace(up.t0, fold.t0 + fold.duration, 20001)
    speed = np.linalg.norm(np.gradient(m.command(t), t, axis=0), axis=1)
    first, second = speed[t < fold.t0].max(), speed[t > fold.t0].max()
    assert first == pytest.approx(1.875 * 0.014, rel=1e-4) and second == pytest.approx(first, rel=1e-4)
    held = m.command(fold.t0 + fold.duration + 0.01)
    np.testing.assert_allclose(held, [0.088 - 0.011, 0.0, 3.0e-4 + 0.012], atol=1e-12)
    with pytest.raises(ValueError, match="must lie inside the rise"):
        mm.lift_fold((0.088, 0.0), 0.0015, 0.012, 0.011, 0.004, 0.006, 0.014, 3.0e-4, lift_first=0.02)


def test_lift_fold_like_recovers_the_rests_from_the_labels_times():
    m = mm.lift_fold((0.088, 0.003), 0.0018, 0.0153, 0.0103, 0.0041, 0.0082, 0.0138, 3.0e-4,
                     rests=(0.15, 0.31, 0.33, 0.6))
    again = mm.lift_fold_like(m.labels(), 3.0e-4)
    assert again.tack_on_s == pytest.approx(m.tack_on_s) and again.tack_off_s == pytest.approx(m.tack_off_s)
    assert again.duration_s == pytest.approx(m.duration_s)
    t = np.linspace(0.0, m.duration_s, 4001)
    np.testing.assert_allclose(again.command(t), m.command(t), atol=1e-12)
    bad = dict(m.labels(), t_tack_off=m.tack_on_s + 0.1)
    with pytest.raises(ValueError, match="negative rest"):
        mm.lift_fold_like(bad, 3.0e-4)


def test_sampled_slides_stay_on_the_card_and_refuse_bad_moves():
    rng = np.random.default_rng(5)
    for direction in ("+x", "-x", "+y", "-y", "diag"):
        m = mm.sample_press_slide(rng, 3.0e-4, direction)
        end = m.command(m.duration_s)
        assert 0.035 <= end[0] <= 0.085 and -0.018 <= end[1] <= 0.018
        assert 0.001 <= m.params["depth"] <= 0.003
    with pytest.raises(ValueError, match="positive length and speed"):
        mm.press_slide((0.05, 0.0), 0.002, (0.0, 0.0), 0.004, 0.008, 0.02, 0.01, 3.0e-4)


def test_a_short_press_slide_keeps_the_shortest_rests_and_slides_past_gross_slip():
    for seed in range(6):
        m = mm.sample_press_slide(np.random.default_rng(seed), 3.0e-4, None, short=True)
        assert 2.2 < m.duration_s < 2.8  # the bundled CI recording: 2.42 s (tests/data/mujoco_world)
        assert 0.010 <= np.hypot(*m.params["slide"]) <= 0.012
        assert 0.0015 <= m.params["depth"] <= 0.0025
        end = m.command(m.duration_s)
        assert 0.035 <= end[0] <= 0.085 and -0.018 <= end[1] <= 0.018
