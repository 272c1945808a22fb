"""Bending plasticity refitted with its physics term (the hinge bending's yield angle).

Known answer: the benchmark card (9 x 5 sheet grid) recorded by this simulator with a yield angle
of 0.05 rad; the gel presses, slides toward the clamp (the card buckles), lifts off and waits. The
scene file holds no plasticity, so the calibrated replay lets the card spring back flat, the
recording keeps a buckle of about 4.5 mm. ``thinshell diagnose`` (signature engine, sensor
calibration only) names bending_plasticity, refits the yield angle on half the sheet points and
predicts the held-out half at the noise level.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from sysid.diagnose.plasticity_refit import checkerboard, fit_yield_angle
from sysid.diagnose.signature_engine import SignatureSettings, diagnose_one
from sysid.diagnose.signature_report import write_signature_report
from tests.sysid.simbag import (PRESS_SLIDE, TRUE_PARAMS, add_noise, scene_with, simulate_streams,
                                targets_from_segments, write_bag)

TRUE_YIELD = 0.05
"""Yield angle of the recording, rad."""

LIFT_AND_WAIT = (((0.0, 0.0, 0.004), 6), ((0.0, 0.0, 0.0), 22))
"""Lift 4 mm off the card, then hold 0.22 s (the free final window of the set test)."""


@pytest.fixture(scope="module")
def plastic_diagnosis(tmp_path_factory):
    scene = scene_with(TRUE_PARAMS)
    targets = targets_from_segments(np.asarray(scene["effectors"]["ee"]["initial_pose"]), PRESS_SLIDE + LIFT_AND_WAIT)
    streams = add_noise(simulate_streams(scene, {**TRUE_PARAMS, "sheet.yield_angle": TRUE_YIELD}, targets), seed=3)
    bag = write_bag(tmp_path_factory.mktemp("plastic") / "bag", scene, streams)
    doc, prepared = diagnose_one(bag, settings=SignatureSettings(calibrate=False, plasticity_replays=5))
    return doc, prepared


def test_refit_recovers_the_yield_angle_and_predicts_held_out_sheet_points(plastic_diagnosis):
    doc, _ = plastic_diagnosis
    assert doc["explained_by"] == ["bending_plasticity"]
    fit = doc["refit"]["effects"]["bending_plasticity"]
    assert fit["params"]["yield_angle_rad"] == pytest.approx(TRUE_YIELD, rel=0.25)
    assert len(fit["detail"]["evaluations"]) <= 5
    # held-out points: the elastic replay misses the 4.5 mm buckle by tens of noise units; with the
    # fitted term the residual is about the noise (1)
    assert fit["heldout_rms_before"] > 10.0
    assert fit["heldout_rms_after"] < 2.0
    assert fit["detail"]["heldout_rms_all_rows_after"] < 0.2 * fit["detail"]["heldout_rms_all_rows_before"]
    assert doc["refit"]["heldout_rms_after"] == fit["heldout_rms_after"]
    assert fit["heldout"].startswith("checkerboard")


def test_report_plots_the_held_out_residuals_before_and_after(plastic_diagnosis, tmp_path):
    doc, prepared = plastic_diagnosis
    assert prepared.refit_predictions["bending_plasticity"]["sheet_points"].shape == prepared.prediction["sheet_points"].shape
    paths = write_signature_report(doc, prepared, tmp_path / "report")
    assert tmp_path / "report" / "signature_bending_plasticity.png" in paths
    assert "yield_angle_rad" in (tmp_path / "report" / "report.md").read_text()


def test_checkerboard_alternates_on_the_grid_and_falls_back_to_alternate_points():
    m = checkerboard(12, (4, 3)).reshape(3, 4)
    assert m[0].tolist() == [True, False, True, False] and m[1].tolist() == [False, True, False, True]
    assert checkerboard(5, (4, 3)).tolist() == [True, False, True, False, True]


def test_fit_keeps_the_elastic_model_when_no_yield_angle_fits_better():
    """A recording without a set: every plastic replay is worse than the elastic one, so nothing is fitted."""
    rng = np.random.default_rng(0)
    sigma = np.full(3, 1e-4)
    nominal = np.zeros((20, 6, 3))
    data = nominal + rng.normal(0.0, 1e-4, nominal.shape)
    calls = []

    def replay(y: float) -> np.ndarray:
        calls.append(y)
        return nominal + 1e-3 * (0.2 / y)  # a set that grows as the yield angle falls

    f = fit_yield_angle(replay, data, nominal, sigma, np.ones(20, bool), checkerboard(6, (3, 2)), 0.2, max_replays=3)
    assert f["yield_angle"] is None and f["heldout_rms_after"] == f["heldout_rms_before"]
    assert len(calls) <= 3 and f["evaluations"]
    with pytest.raises(ValueError, match="theta_max"):
        fit_yield_angle(replay, data, nominal, sigma, np.ones(20, bool), checkerboard(6, (3, 2)), 0.0)


def test_brent_first_points_are_the_first_two_that_bounded_minimisation_evaluates():
    """Computed as SciPy computes them (bit for bit), for the refit's own interval and others."""
    from scipy.optimize import minimize_scalar

    from sysid.diagnose.plasticity_refit import LOWEST_FRACTION, XATOL, brent_first_points

    for lo, hi, xatol in ((math.log(LOWEST_FRACTION), 0.0, XATOL), (-1.0, 3.0, 1e-5), (2.0, 2.5, 0.3)):
        calls: list[float] = []
        minimize_scalar(lambda u: calls.append(float(u)) or (u - hi) ** 2, bounds=(lo, hi), method="bounded",
                        options={"xatol": xatol, "maxiter": 4})
        assert brent_first_points(lo, hi, xatol) == (calls[0], calls[1])


def test_the_search_prefetches_its_second_replay_before_its_first():
    order: list[tuple[str, float]] = []
    data = np.zeros((4, 6, 3))

    def replay(y: float) -> np.ndarray:
        order.append(("replay", y))
        return data + 1e-3 * math.log(y)

    fit_yield_angle(replay, data, data + 0.01, np.full(3, 1e-3), np.ones(4, bool), np.arange(6) % 2 == 0, 0.5,
                    max_replays=3, prefetch=lambda y: order.append(("prefetch", y)))
    assert [kind for kind, _ in order] == ["prefetch", "replay", "replay", "replay"]
    assert order[0][1] == order[2][1]  # the second replay is the prefetched angle, bit for bit
