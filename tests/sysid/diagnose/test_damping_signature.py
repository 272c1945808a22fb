"""The gel damping signature (:mod:`sysid.diagnose.signatures.damping`): the Kelvin-Voigt contact
force, the windows' dispersion, and the decision on a lead read through a replay with a gap."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sysid.diagnose.signatures.damping import (contact_force, damping_test, dispersion, kelvin_voigt, lead_fits,
                                               lead_recording)
from sysid.diagnose.signatures.null import default_thresholds
from sysid.diagnose.signatures.timing import delayed
from tests.sysid.diagnose.test_signatures import named, press_profile, synthetic


def test_contact_force_is_kelvin_voigt_while_pressing_and_zero_once_the_surfaces_part():
    """A 5 N press with 0.3 s ramps (16.7 N/s) and tau = 30 ms: while pressing the force is
    ``y + tau dy/dt``; on the release the damping force (0.5 N) exceeds the elastic force in its
    last 0.5 N, so the surfaces part tau = 30 ms before the elastic force reaches zero, and the
    force is never tensile."""
    t = np.arange(0.0, 3.5, 0.005)
    y = 5.0 * press_profile(t, t_on=1.0, t_off=2.5, ramp=0.3)
    tau = 0.03
    kv, f = kelvin_voigt(t, y, tau), contact_force(t, y, tau)
    assert f.min() >= 0.0 and kv.min() < -0.2  # without the contact condition: tensile
    pressing = kv > 0.0
    np.testing.assert_array_equal(f[pressing], kv[pressing])
    # on the ramps (farther than the 0.05 s filter's half-span from their corners): value plus tau
    # times the slope, +-0.5 N
    rise, fall = np.abs(t - 1.15) < 0.1, np.abs(t - 2.35) < 0.1
    np.testing.assert_allclose(f[rise], y[rise] + 0.5, atol=1e-9)
    np.testing.assert_allclose(f[fall], y[fall] - 0.5, atol=1e-9)
    # the surfaces part where the elastic force is 0.5 N, tau before it reaches zero
    last_contact = t[np.nonzero(f > 0.0)[0][-1]]
    assert last_contact == pytest.approx(2.5 - tau, abs=0.0051)


def test_dispersion_is_pearsons_variance_estimate_never_below_the_noise():
    rng = np.random.default_rng(3)
    r = 2.0 * rng.normal(size=4000)  # a residual twice the noise model's standard deviation
    assert dispersion(float(r @ r), r.size, 5) == pytest.approx(4.0, rel=0.05)
    quiet = 0.5 * rng.normal(size=4000)
    assert dispersion(float(quiet @ quiet), quiet.size, 5) == 1.0
    with pytest.raises(ValueError, match="more samples than parameters"):
        dispersion(10.0, 5, 5)


def _with_dwell_gap(rec, amplitude_n: float, period_s: float = 0.1):
    """``rec`` whose recorded normal force, while the press dwells, oscillates by ``amplitude_n`` N
    at ``period_s`` (the sheet settling under the pad, say) where its replay is flat: a gap of the
    model in the event windows that no lead of the replay's contact force can explain (the replay's
    rate is zero there)."""
    tw = rec.t["wrench"]
    dwell = press_profile(tw) >= 1.0
    data = dict(rec.data)
    data["wrench"] = rec.data["wrench"].copy()
    data["wrench"][:, 2] -= amplitude_n * np.sin(2.0 * np.pi * tw / period_s) * dwell
    return dataclasses.replace(rec, data=data)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_lead_behind_a_replay_gap_is_judged_against_the_windows_dispersion(seed):
    """A 30 ms Kelvin-Voigt gel whose recording holds, where the press dwells, an oscillation its
    replay lacks (1.2 N amplitude, rms 4.2 noise sigmas): the lead removes less than half of the
    windows' excess, but its drop, divided by the dispersion the gap leaves (about 9 times the
    noise variance), is beyond the threshold: damping is named with its time constant. The same
    gap without damping names nothing: the gap does not look like a lead."""
    rec = _with_dwell_gap(synthetic(np.random.default_rng(seed), damping=0.03), 1.2)
    r = damping_test(rec)
    assert r.detail["explained_lead"] < 0.5
    assert r.detail["dispersion"] > 5.0
    assert r.statistic == pytest.approx(r.detail["sse_removed"] / r.detail["dispersion"])
    assert r.statistic > default_thresholds(rec).statistic["damping"]
    assert r.estimate["tau_s"] == pytest.approx(0.03, abs=0.005)
    assert named(rec) == ["damping"]
    plain = _with_dwell_gap(synthetic(np.random.default_rng(seed + 10)), 1.2)
    assert damping_test(plain).effect_size < default_thresholds(plain).effect_size["damping"]
    assert named(plain) == []


def _replay_late_at_the_release(rec, press_late_s: float, release_late_s: float):
    """``rec`` (the synthetic press, 1.0-2.5 s, 0.15 s ramps) with a replay whose force rises
    ``press_late_s`` late and whose release comes ``release_late_s`` late in force and marker depth
    alike (a replay that keeps the gel deformed longer: its buckled card pushing the lifting pad)."""
    tw, tm = rec.t["wrench"], rec.t["markers_xyz"]
    pred = dict(rec.prediction)
    wrench = pred["wrench"].copy()
    wrench[:, 2] = -5.0 * press_profile(tw, t_on=1.0 + press_late_s, t_off=2.5 + release_late_s)
    rest = pred["markers_xyz"][0]
    depth = pred["markers_xyz"][int(np.argmax(press_profile(tm)))] - rest
    profile = press_profile(tm, t_off=2.5 + release_late_s)
    pred.update(wrench=wrench, markers_xyz=rest[None] + depth[None] * profile[:, None, None])
    return dataclasses.replace(rec, prediction=pred)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_release_lead_the_deformation_shares_is_not_damping(seed):
    """No damping; the replay's force rises 5 ms late (a press gap, as on MuJoCo's nominal
    press-slides) and its release comes 30 ms late in force and deformation alike (MuJoCo dev
    stiction_s401 and plastic_s406: the recorded marker depth 15 and 25 ms ahead at the release).
    Without the deformation check the leads 5 / 30 ms name damping (statistic about 200, size
    17.5 ms); with it the release is left out (deformation lead 30 +- 4 ms) and the press's 5 ms
    names nothing. A 30 ms damped gel through an exact replay (deformation not ahead) is named."""
    rec = _replay_late_at_the_release(synthetic(np.random.default_rng(seed)), 0.005, 0.03)
    r = damping_test(rec)
    (left_out,) = r.detail["events_left_out"]
    assert left_out["direction"] == "falling" and left_out["deformation_lead_s"] == pytest.approx(0.03, abs=4e-3)
    assert r.effect_size < default_thresholds(rec).effect_size["damping"]
    assert "damping" not in named(rec)
    damped = synthetic(np.random.default_rng(seed), damping=0.03)
    assert not damping_test(damped).detail["events_left_out"]
    assert named(damped) == ["damping"]


@pytest.mark.parametrize("seed", [1, 2])
def test_through_the_arm_drive_the_lead_is_read_against_the_recorded_pose(seed):
    """A 30 ms Kelvin-Voigt gel pressed through a 3 N/mm arm on a 36 N/mm contact: the replay through the
    drive (undamped) deforms ``tau k_c / (k_s + k_c)`` = 27.7 ms ahead of the recording and its force leads
    the recorded force by the rest, 2.3 ms, under the 10 ms a lead must reach: read against that replay
    alone damping is not named. Read against the replay with the recorded pose imposed
    (``Recording.reference``, the exact replay here) the lead is the gel's 30 ms: named, as without the
    drive."""
    rec = synthetic(np.random.default_rng(seed), damping=0.03)
    ahead = 0.03 * 36.0 / (3.0 + 36.0)
    driven = {ch: delayed(rec.t[ch], v, -ahead) for ch, v in rec.prediction.items()}
    alone = dataclasses.replace(rec, prediction=driven)
    assert damping_test(alone).effect_size < default_thresholds(alone).effect_size["damping"]
    assert "damping" not in named(alone)
    through_drive = dataclasses.replace(rec, prediction=driven, reference=rec.prediction)
    assert lead_recording(through_drive).prediction is rec.prediction
    r = damping_test(through_drive)
    assert r.estimate["tau_s"] == pytest.approx(0.03, abs=0.005)
    assert named(through_drive) == ["damping"]


def _replay_early_at_the_release(rec, early_s: float, release_travel_m: float | None = None,
                                 card_m: float = 0.004):
    """``rec`` (the synthetic press, 1.0-2.5 s, 0.15 s ramps, the pad pressed 2.5 mm) with a replay that lets
    go of the gel ``early_s`` before the recording, in force and marker depth alike, and of the card tented
    ``card_m`` under the pad (the card falls back as the gel lets go: MuJoCo dev damped_s705, its recorded
    marker depth 13 ms and its card 17 ms behind the replay's at the release, the card falling 4.5 mm).
    ``release_travel_m``: the recorded pad travels this far while the force ramps down (a card lifted with
    the pad carries the travel), instead of the 2.5 mm it pressed."""
    rec = _replay_late_at_the_release(rec, 0.0, -early_s)
    tm = rec.t["sheet_points"]
    under = np.abs(rec.data["sheet_points"][0, :, 0] - 0.07) < 0.01
    data, pred = dict(rec.data), dict(rec.prediction)
    data["sheet_points"], pred["sheet_points"] = data["sheet_points"].copy(), pred["sheet_points"].copy()
    data["sheet_points"][:, under, 2] += card_m * press_profile(tm)[:, None]
    pred["sheet_points"][:, under, 2] += card_m * press_profile(tm, t_off=2.5 - early_s)[:, None]
    if release_travel_m is not None:
        tw = rec.t["pose"]
        pose = rec.data["pose"].copy()
        pose[:, 2] = np.where(tw < 1.75, 0.003 - 0.0025 * press_profile(tw),
                              0.0005 + release_travel_m * (1.0 - press_profile(tw)))
        data.update(pose=pose, pose_cmd=pose)
    return dataclasses.replace(rec, data=data, prediction=pred)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_an_early_release_is_read_against_the_replay_retimed_to_the_recorded_deformation(seed):
    """A 30 ms Kelvin-Voigt gel whose replay lets go 30 ms early in force and deformation alike: against
    the replay as it is, the release shows no lead (30 - 30 ms) and the common lead is about half the gel's
    (the press keeps its 30 ms). The recorded deformation and card run 30 ms behind the replay's there while
    the gel carries the pad's travel as on the press, so the release is read against the replay delayed by
    30 ms: the lead is the gel's 30 ms at both events, and damping is named."""
    rec = _replay_early_at_the_release(synthetic(np.random.default_rng(seed), damping=0.03), 0.03)
    fits = lead_fits(rec)  # the replay as it is
    assert fits["taus_s"][int(np.argmin(fits["sse"].sum(axis=0)))] < 0.022
    r = damping_test(rec)
    (retimed,) = r.detail["releases_retimed"]
    assert retimed["deformation_lead_s"] == pytest.approx(-0.03, abs=4e-3)
    assert retimed["gel_share"] > 0.9  # the replay unloads the gel over the pad's travel as on the press
    assert retimed["card_lead_s"] == pytest.approx(-0.03, abs=4e-3)
    assert [e["lead_s"] for e in r.detail["events"]] == pytest.approx([0.03, 0.03], abs=0.005)
    assert r.estimate["tau_s"] == pytest.approx(0.03, abs=0.005)
    assert named(rec) == ["damping"]


@pytest.mark.parametrize("seed", [1, 2])
def test_an_early_release_without_damping_gains_no_lead_from_the_retiming(seed):
    """No damping, the replay letting go 30 ms early in force and deformation: the re-timed release leads by
    nothing (the recorded force is as late as the recorded deformation) and nothing is named."""
    rec = _replay_early_at_the_release(synthetic(np.random.default_rng(seed)), 0.03)
    r = damping_test(rec)
    assert len(r.detail["releases_retimed"]) == 1
    assert r.estimate["tau_s"] <= 0.005
    assert "damping" not in named(rec)


@pytest.mark.parametrize("seed", [1, 2])
def test_a_release_whose_travel_a_lifted_card_carries_is_not_retimed(seed):
    """The same early release, the recorded pad lifting 25 mm while the force ramps down (ten times its
    press: a card lifted with the pad carries the travel, the gel's share is a tenth of the press's; MuJoCo
    dev damped_s403, damped_s706 and the reference stiction_s105, shares 0.04-0.11): the deformation is no
    timing reference for the gel there, the release is read against the replay as it is (as main)."""
    rec = _replay_early_at_the_release(synthetic(np.random.default_rng(seed), damping=0.03), 0.03, 0.025)
    r = damping_test(rec)
    assert r.detail["releases_retimed"] == []
    plain = lead_fits(rec)
    assert r.estimate["tau_s"] == pytest.approx(plain["taus_s"][int(np.argmin(plain["sse"].sum(axis=0)))])
    assert lead_recording(rec) is rec


@pytest.mark.parametrize("seed", [1, 2])
def test_an_early_release_whose_card_lies_still_is_not_retimed(seed):
    """The same early release over a card lying flat on the table: the gel's deformation alone runs behind
    the replay's, which a damped gel's slow recovery or a calibration's depth gap at the gel does as well (the
    reference nominal_s109 through another calibration: its release's marker depth 14 ms behind, its card
    still), so without the card's timing the release is read against the replay as it is."""
    rec = _replay_early_at_the_release(synthetic(np.random.default_rng(seed), damping=0.03), 0.03, card_m=0.0)
    r = damping_test(rec)
    assert r.detail["releases_retimed"] == []
    assert lead_recording(rec) is rec
