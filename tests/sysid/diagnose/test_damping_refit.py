"""Gel damping refitted with its physics term (the gel's Kelvin-Voigt dashpot, ``candidate.gel_damping``).

Known answer: the benchmark card pressed 2.2 mm by this simulator's gel (about 25 N) and released,
recorded with a concealed Kelvin-Voigt gel of ``TRUE_ALPHA`` s and the reference bags' noise; the scene
file holds no damping. ``thinshell diagnose`` (signature engine, sensor calibration only) names damping
from the contact force's lead; the refit replays the gel's dashpot, fits its time constant on one
contact event and predicts the other. The replay imposes the recorded pose, whose 5 um noise the
recording's pad did not have, so the held-out floor is above 1.
"""

from __future__ import annotations

import numpy as np
import pytest

from sysid.diagnose.damping_refit import interpolated, refit_gel_damping, smoothed_controls
from sysid.diagnose.signature_engine import SignatureSettings, diagnose_one, refit_timing
from sysid.diagnose.signature_report import write_signature_report
from tests.sysid.simbag import TRUE_PARAMS, add_noise, scene_with, simulate_streams, targets_from_segments, write_bag

TRUE_ALPHA = 0.03
"""Kelvin-Voigt time constant of the recording's gel, s."""

PRESS_RELEASE = (((0.0, 0.0, -0.0009), 3), ((0.0, 0.0, -0.0013), 20), ((0.0, 0.0, 0.0), 30),
                 ((0.0, 0.0, 0.0022), 20), ((0.0, 0.0, 0.0), 25))
"""Approach, press 1.3 mm at 6.5 mm/s, hold 0.3 s, release at 11 mm/s, wait 0.25 s (segments of
:func:`tests.sysid.simbag.targets_from_segments`)."""


@pytest.fixture(scope="module")
def damped_diagnosis(tmp_path_factory):
    scene = scene_with(TRUE_PARAMS)
    targets = targets_from_segments(np.asarray(scene["effectors"]["ee"]["initial_pose"]), PRESS_RELEASE)
    streams = add_noise(simulate_streams(scene, {**TRUE_PARAMS, "candidate.gel_damping": TRUE_ALPHA}, targets), seed=5)
    bag = write_bag(tmp_path_factory.mktemp("damped") / "bag", scene, streams)
    return diagnose_one(bag, settings=SignatureSettings(calibrate=False))


def test_refit_recovers_the_time_constant_and_most_of_the_held_out_excess(damped_diagnosis):
    doc, prepared = damped_diagnosis
    assert doc["explained_by"] == ["damping"]
    fit = doc["refit"]["effects"]["damping"]
    assert fit["model"].startswith("the gel's Kelvin-Voigt dashpot replayed")
    assert fit["params"]["tau_s"] == pytest.approx(TRUE_ALPHA, rel=0.2)
    assert len(fit["detail"]["replayed_s"]) <= 2
    before, after = fit["heldout_rms_before"], fit["heldout_rms_after"]
    assert before > 5.0
    assert (before - after) / (before - 1.0) >= 0.7
    # the first-order lead on the replay's filtered force recovers less of it at its best time constant
    lead = refit_timing(prepared, prepared.results["damping"])
    assert after < lead["heldout_rms_after"]


def test_report_plots_the_replayed_dashpot(damped_diagnosis, tmp_path):
    doc, prepared = damped_diagnosis
    signal = prepared.refit_predictions["damping"]["timing_signal"]
    assert signal.shape == prepared.recording.t["wrench"].shape
    assert tmp_path / "report" / "signature_damping.png" in write_signature_report(doc, prepared, tmp_path / "report")


def test_fit_on_a_signal_linear_in_alpha_finds_it_from_one_probe():
    """Two events of a signal that the dashpot changes linearly (``base + alpha d``): the fit from one probe
    at half the true value finds it, held out, to the grid's step, with one more replay at most."""
    rng = np.random.default_rng(1)
    t = np.arange(0.0, 2.0, 0.005)
    ramp = np.clip((t - 0.3) / 0.2, 0.0, 1.0) - np.clip((t - 1.2) / 0.2, 0.0, 1.0)
    base, d = 3.0 * ramp, 3.0 * np.gradient(ramp, t)
    alpha = 0.024
    y = base + alpha * d + rng.normal(0.0, 0.05, t.size)
    calls = []

    def replay(a):
        calls.append(a)
        return base + a * d

    f = refit_gel_damping(replay, t, y, base, 0.05, [[0.2, 0.7], [1.1, 1.6]], 0.012, np.arange(0.0, 0.1, 0.001))
    assert f["tau_s"] == pytest.approx(alpha, abs=0.0011)
    assert f["heldout_rms_after"] < 1.2 < f["heldout_rms_before"]
    assert calls[0] == 0.012 and len(calls) <= 2
    assert interpolated([0.0, 0.01], [base, base + 0.01 * d])(0.03) == pytest.approx(base + 0.03 * d)


def test_smoothed_controls_keep_a_ramp_and_the_orientation_and_halve_the_pose_noise():
    """The quadratic Savitzky-Golay filter over 50 ms (5 steps of 10 ms) reproduces a press ramp
    exactly and passes white pose noise with a variance of 17/35 (its centre weight)."""
    rng = np.random.default_rng(0)
    k = np.arange(400)
    ramp = np.zeros((400, 7))
    ramp[:, 2] = -1e-5 * k
    ramp[:, 3:7] = [0.0, 0.0, 0.0, 1.0]
    np.testing.assert_allclose(smoothed_controls(ramp, 0.01), ramp, atol=1e-15)
    noisy = ramp.copy()
    noisy[:, :3] += rng.normal(0.0, 5e-6, (400, 3))
    out = smoothed_controls(noisy, 0.01)
    np.testing.assert_array_equal(out[:, 3:7], noisy[:, 3:7])
    assert np.std(out[:, :3] - ramp[:, :3]) ** 2 == pytest.approx(17.0 / 35.0 * 25e-12, rel=0.15)
