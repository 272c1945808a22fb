"""The recorded wrench judged against the gel's own markers (sysid.wrench_check) on the reference recordings, and the
rows it leaves out of the fit (ObservationModel.row_mask) and the sensor's gains (sysid.calibration.masked_rows)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sysid.calibration import fit_sensor_gains, masked_rows, nominal_sensor_calibration
from sysid.evidence import load_evidence
from sysid.observation import ObservationModel
from sysid.wrench_check import check_wrench
from tests.sysid.conftest import reference_bag

S109_TACK = (1.6291, 3.81561)
"""nominal_s109's tack on / off, s (shared/data/reference_bags/labels.yaml)."""


@pytest.fixture(scope="module")
def s109():
    return load_evidence(reference_bag("nominal_s109"))


def test_a_press_slide_wrench_agrees_with_its_markers():
    """nominal_s101 (the reference's press-slide): the slide's tangential force and the markers' shear stand clear of
    the noise in hundreds of rows and agree (cosine 1.00): nothing is left out."""
    check = check_wrench(load_evidence(reference_bag("nominal_s101")))
    assert check is not None and not check.tripped and check.message("x") == ""
    assert check.judged.sum() > 200 and check.cosine_agree > 0.95
    assert check.summary()["rows_against"] == 0 and check.summary()["force_N"] is None


def test_the_lift_fold_carried_phase_records_the_force_on_the_card(s109):
    """nominal_s109: while the card is carried, the recorded tangential force opposes the markers' shear (the force on
    the card, 0.4 N: 30 card weights), and only there; the message names the topic, the span and the contract."""
    check = check_wrench(s109)
    assert check.tripped
    t0, t1 = S109_TACK
    for a, b in check.spans:
        assert t0 <= a and b <= t1 + 0.1  # within the carried phase (the peel's own window included)
    assert check.against.sum() >= 200 and check.cosine < -0.95
    assert check.force[0] < -0.3 and check.shear[0] > 50e-6  # -x force, +x shear
    card_weight = 0.10 * 0.06 * 0.0003 * 700.0 * 9.81
    assert abs(check.force[0]) > 20 * card_weight
    msg = check.message("nominal_s109")
    assert "topic wrench contradicts" in msg and "INTERFACES.md" in msg and "left out of the fit" in msg


def test_the_same_phase_recorded_as_the_force_on_the_gel_passes(s109):
    """The same recording with the contradicting rows' tangential force turned to the gel's side (what a sensor that
    keeps the contract records there) trips nothing: the check reads the sign, not the phase or the motion."""
    check = check_wrench(s109)
    wrench = np.array(s109.wrench, dtype=float)
    wrench[check.against, :2] *= -1.0
    again = check_wrench(dataclasses.replace(s109, wrench=wrench))
    assert not again.tripped and again.judged.sum() >= check.judged.sum() and again.cosine_agree > 0.95


def test_left_out_rows_weigh_nothing_in_the_residual_and_the_gains(s109):
    """``row_mask`` zeroes the left-out rows' whitened residuals and derivatives and nothing else; the sensor's gains
    fitted with the mask are the gains fitted on the kept rows alone."""
    model = ObservationModel(s109, dt=0.01, channels=["markers_xyz", "wrench"])
    check = check_wrench(s109)
    rng = np.random.default_rng(0)
    pred = {ch: model.data(ch) + rng.normal(size=model.data(ch).shape) * np.asarray(s109.noise[ch])
            for ch in ("markers_xyz", "markers_uv", "wrench", "sheet_points")}
    full = model.residuals(pred)
    model.row_mask = {"wrench": ~check.against}
    masked = model.residuals(pred)
    w = model.residual_slices()["wrench"]
    per_row = masked[w].reshape(-1, 6)
    assert np.all(per_row[check.against] == 0.0)
    np.testing.assert_array_equal(per_row[~check.against], full[w].reshape(-1, 6)[~check.against])
    np.testing.assert_array_equal(masked[model.residual_slices()["markers_xyz"]],
                                  full[model.residual_slices()["markers_xyz"]])
    d = model.whiten_derivative("wrench", np.ones(model.data("wrench").shape + (2,))).reshape(-1, 6, 2)
    assert np.all(d[check.against] == 0.0) and np.all(d[~check.against] != 0.0)
    # gains: the kept rows' prediction 1.1 x below the record, the left-out rows' 3 x above it
    raw = {"wrench": model.data("wrench") / 1.1}
    raw["wrench"][check.against] *= 3.0 * 1.1
    data = {"wrench": model.data("wrench")}
    masked_cal, asked = fit_sensor_gains(data, raw, model.sigma, None, nominal_sensor_calibration(model),
                                         masked_rows(model, None))
    assert masked_cal.force_gain == pytest.approx(1.1, rel=1e-9) and asked["force_gain"] == pytest.approx(1.1)
    _, unmasked = fit_sensor_gains(data, raw, model.sigma, None, nominal_sensor_calibration(model))
    assert unmasked["force_gain"] < 1.0
    rms = model.channel_rms(pred)["wrench"]
    assert rms["whitened_rms_kept_rows"] == pytest.approx(
        np.sqrt(np.mean(((model.data("wrench") - pred["wrench"])[~check.against] / model.sigma["wrench"]) ** 2)))
    model.row_mask = None
    assert masked_rows(model, None) is None and "whitened_rms_kept_rows" not in model.channel_rms(pred)["wrench"]


def test_thinshell_sysid_checks_the_wrench_by_default():
    """``thinshell sysid`` runs the check unless ``--no-wrench-check`` (``FitOptions.wrench_check``)."""
    from sysid.cli import build_parser, fit_options
    from sysid.fit_recording import FitOptions

    assert FitOptions().wrench_check and fit_options(build_parser().parse_args(["bag"])).wrench_check
    assert not fit_options(build_parser().parse_args(["bag", "--no-wrench-check"])).wrench_check


def test_thinshell_diagnose_leaves_the_same_rows_out_of_its_calibration(monkeypatch, s109):
    """``thinshell diagnose``'s signature stage (:func:`sysid.diagnose.signature_engine.prepare`) hands its calibration,
    and so every later replay and fit of the recording, the model with the contradicting wrench rows left out, as its
    report's note says; a recording whose wrench agrees with its markers keeps every row."""
    from sysid.diagnose import signature_engine
    from sim_core.errors import CalibrationError

    seen = {}

    def calibrate(model, params, **_):
        seen[model.evidence.source.bag_path.name] = None if model.row_mask is None else model.row_mask.get("wrench")
        raise CalibrationError("stopped here: the test reads what the calibration is handed")

    monkeypatch.setattr(signature_engine, "calibrate", calibrate)
    settings = signature_engine.SignatureSettings()
    s109_prepared = signature_engine.prepare(reference_bag("nominal_s109"), settings)
    np.testing.assert_array_equal(seen["nominal_s109"], ~check_wrench(s109).against)
    assert any("no calibrated replay" in n for n in s109_prepared.notes)
    signature_engine.prepare(reference_bag("nominal_s101"), settings)
    assert seen["nominal_s101"] is None
