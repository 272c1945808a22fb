"""Bending plasticity refitted on a lift-and-fold whose card the gel's tack carries (the reference world's lift_fold).

Known answer: the benchmark card (9 x 5 grid, clamped at x0) recorded by this simulator with the gel's tack held in
shear by the compliant layer (bonds of 400 card weights a pair, ``k_t`` 3 N/m a pair, released at 0.24 s) and a
yield angle of 0.05 rad: the gel presses, lifts 8 mm, carries the card 8 mm back toward the clamp (the card arches
and folds), waits, lets go and lifts off. The scene file holds neither the tack nor plasticity, as the reference
world's does not. After the release the recorded card keeps a set that the replay without plasticity does not: the
held-out sheet points sit 13.5 noise units off; the recording's own model (the truth with its yield angle) brings
them to 0.9 (measured), so the known model explains all of the held-out excess.

The refit (:func:`sysid.diagnose.plasticity_refit.refit_plasticity`, the diagnosis' call where adhesion is named
too) starts from the tack's replay. With normal-only bonds the carried card slides along the gel, stays a straight
ramp and never folds, so no yield angle gives the set: 0.02 of the held-out excess explained (plastic_s102: 0.11).
With the layer the card folds as recorded and the yield angle comes back within 10 % (0.0548 rad), 0.61 of the
excess explained (its ``k_t``, read from the carried rows without plasticity, is 5.2 against 3: the fold's own
yielding stiffens the carried card's shape, which the layer search leaves out).
"""

from __future__ import annotations

import numpy as np
import pytest

from sim_core.scenes import load_scene
from sim_core.simulation import Simulation
from sysid.diagnose.candidates import adhesion_weight_scale
from sysid.diagnose.peel import ADHESION_PARAMETER, RELEASE_TIME_SETTING
from sysid.diagnose.plasticity_refit import refit_plasticity
from sysid.diagnose.shear_layer import LAYER_BOND_WEIGHTS, SHEAR_STIFFNESS_SETTING
from sysid.diagnose.signature_engine import recording_of
from sysid.evidence import load_evidence
from sysid.observation import ObservationModel
from tests.sysid.simbag import PRESS_ONLY, TRUE_PARAMS, add_noise, scene_with, simulate_streams, targets_from_segments, write_bag

TRUE_YIELD = 0.05
"""Yield angle of the recording, rad."""

LIFT_FOLD = PRESS_ONLY + (((0.0, 0.0, 0.008), 8), ((-0.008, 0.0, 0.0), 8), ((0.0, 0.0, 0.0), 3),
                          ((0.0, 0.0, 0.004), 4), ((0.0, 0.0, 0.0), 20))
"""Press, lift 8 mm, carry the card 8 mm back toward the clamp, wait (the bonds let go at 0.24 s), lift off, wait."""

RELEASE_S = 0.24
"""The recording's peel, s (the step after the wait)."""


@pytest.fixture(scope="module")
def lift_fold(tmp_path_factory):
    scene = scene_with(TRUE_PARAMS)
    dt = float(scene["dt"])
    w = adhesion_weight_scale(Simulation(load_scene(scene), dt=dt).model)
    targets = targets_from_segments(np.asarray(scene["effectors"]["ee"]["initial_pose"]), LIFT_FOLD)
    truth = {**TRUE_PARAMS, ADHESION_PARAMETER: LAYER_BOND_WEIGHTS * w, SHEAR_STIFFNESS_SETTING: 3.0,
             RELEASE_TIME_SETTING: RELEASE_S, "sheet.yield_angle": TRUE_YIELD}
    streams = add_noise(simulate_streams(scene, truth, targets), seed=3)
    return write_bag(tmp_path_factory.mktemp("lift_fold") / "bag", scene, streams), dt


@pytest.fixture(scope="module")
def nominal(lift_fold) -> np.ndarray:
    """The sheet points of the replay at the scene's values (no tack, no plasticity), ``(rows, points, 3)`` m: the
    same replay for both refits (each on a fresh model of the recording), made once."""
    bag, dt = lift_fold
    model = ObservationModel(load_evidence(bag, include_image="auto"), dt=dt)
    return np.asarray(model.predict(model.simulate(TRUE_PARAMS))["sheet_points"], dtype=float)


def _refit(bag, dt, nominal: np.ndarray, shear_layer: bool) -> dict:
    """The diagnosis' refit (adhesion named too) on a fresh model of the recording, from the replay ``nominal``'s
    sheet points; the effect's window is the wait after the lift-off."""
    model = ObservationModel(load_evidence(bag, include_image="auto"), dt=dt)
    rec = recording_of(model, None)
    window = [[RELEASE_S + 0.06, float(rec.t["sheet_points"][-1])]]
    return refit_plasticity(model, TRUE_PARAMS, rec, nominal, window, 5, None, carried_by_tack=True,
                            shear_layer=shear_layer)


def _share(fit: dict) -> float:
    """Fraction of the held-out excess over the noise that the refit explains (the diagnosis' figure)."""
    return (fit["heldout_rms_before"] - fit["heldout_rms_after"]) / (fit["heldout_rms_before"] - 1.0)


def test_the_refit_folds_the_carried_card_and_explains_the_set(lift_fold, nominal):
    bag, dt = lift_fold
    fit = _refit(bag, dt, nominal, shear_layer=True)
    assert fit["heldout_rms_before"] > 10.0  # measured 13.5: the replay's card falls back flat
    assert fit["params"]["shear_stiffness_N_per_m"] > 0.0 and "held in shear" in fit["base"]
    assert fit["params"]["yield_angle_rad"] == pytest.approx(TRUE_YIELD, rel=0.2)  # measured 0.0548
    assert _share(fit) > 0.5  # measured 0.61; the known model 1.0


def test_normal_only_bonds_never_fold_the_card(lift_fold, nominal):
    """The cause of plastic_s102's 0.11: the card carried by normal-only bonds stays a straight ramp."""
    bag, dt = lift_fold
    fit = _refit(bag, dt, nominal, shear_layer=False)
    assert "shear_stiffness_N_per_m" not in fit["params"]
    assert fit["detail"]["theta_max"] < 0.2 * TRUE_YIELD  # the largest dihedral angle of its carried card
    assert _share(fit) < 0.1  # measured 0.02
