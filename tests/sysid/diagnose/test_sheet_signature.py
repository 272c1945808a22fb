"""The permanent-set test (:func:`sysid.diagnose.signatures.sheet.plasticity_test`) reads a set only
from a sheet at rest, or from one still moving that stays within the fold the loaded gel made."""

from __future__ import annotations

import numpy as np
import pytest

from sysid.diagnose.signatures import Recording
from sysid.diagnose.signatures.base import marker_displacement
from sysid.diagnose.signatures.sensor import REST_DISPLACEMENT
from sysid.diagnose.signatures.sheet import moving_sheet_check, plasticity_test, resolvable_set
from tests.sysid.diagnose.test_friction_signature import reference_recording
from tests.sysid.diagnose.test_signatures import named, synthetic


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(11)


def _elastic_replay(rec: Recording) -> Recording:
    """``rec`` with the replay of an elastic sheet pressed where the recorded gel is: the sheet at its
    recorded initial shape throughout (mean of the first 0.3 s), the wrench the recorded one where
    the recorded markers are off rest and zero elsewhere."""
    t = rec.t["sheet_points"]
    x = np.asarray(rec.data["sheet_points"], dtype=float)
    flat = np.repeat(x[t < 0.3].mean(axis=0)[None], len(t), axis=0)
    loaded = np.interp(rec.t["wrench"], rec.t["markers_xyz"], marker_displacement(rec) > REST_DISPLACEMENT) > 0.5
    pred = {"sheet_points": flat, "wrench": np.asarray(rec.data["wrench"], dtype=float) * loaded[:, None]}
    return Recording(t=rec.t, data=rec.data, prediction=pred, sigma=rec.sigma, camera=rec.camera, name=rec.name)


def test_a_reference_plastic_fold_at_rest_is_read_as_a_set():
    """MuJoCo's plastic lift-fold (reference plastic_s102, bend yield 0.001): the card keeps a 9.1 mm
    tent, settled 0.07 s after the peel, so the final window holds a rest shape."""
    rec = _elastic_replay(reference_recording("plastic_s102"))
    r = plasticity_test(rec)
    assert r.applicable and r.detail["final_motion_m"] < resolvable_set(rec)
    assert r.effect_size == pytest.approx(9.1e-3, abs=0.5e-3)
    assert "bending_plasticity" in named(rec)


def test_a_reference_elastic_fold_returns_flat_and_names_no_set():
    """MuJoCo's nominal lift-fold (reference nominal_s109): folded 19 mm while the tack holds it,
    flat again (0.04 mm) after the peel."""
    rec = _elastic_replay(reference_recording("nominal_s109"))
    r = plasticity_test(rec)
    assert r.applicable and r.effect_size < resolvable_set(rec)
    assert "bending_plasticity" not in named(rec)


def _flung(rec: Recording, fold_under_load: float = 0.0, creep: float = 0.0) -> Recording:
    """``rec`` (the synthetic press of ``test_signatures``: gel released at 2.5 s) with a recorded
    sheet that, after the release, lifts as a ramp from the clamped edge (x = 0) to 6 mm at the free
    edge and flaps back (a 2 Hz oscillation about 3 mm) to the end of the recording: an elastic card
    flung by the lift. ``fold_under_load``: height of a fold at x = 70 +- 15 mm while the gel presses
    (1.2-2.4 s); ``creep``: instead of the flapping, 0.6 of that fold kept after the release, rising
    by ``creep`` m over the last 0.3 s."""
    t = rec.t["sheet_points"]
    x = np.asarray(rec.data["sheet_points"], dtype=float).copy()
    x0 = x[0]
    fold = np.abs(x0[:, 0] - 0.07) < 0.015
    if fold_under_load:
        loaded = (t > 1.2) & (t < 2.4)
        x[np.ix_(loaded, fold, [2])] += fold_under_load
    after = t > 2.6
    if creep:
        rise = creep * np.clip((t - (t[-1] - 0.3)) / 0.3, 0.0, 1.0)
        x[np.ix_(after, fold, [2])] += (0.6 * fold_under_load + rise[after])[:, None, None]
    else:
        ramp = x0[:, 0] / 0.1                                                          # (p,)
        height = 3e-3 * (1.0 + np.cos(2.0 * np.pi * 2.0 * (t - 2.6)))                   # (n,) 6 mm -> 0
        x[after, :, 2] += height[after, None] * ramp[None, :]
    return Recording(t=rec.t, data=dict(rec.data, sheet_points=x), prediction=rec.prediction, sigma=rec.sigma,
                     camera=rec.camera, name=rec.name)


def test_an_elastic_sheet_still_flapping_at_the_end_is_not_a_set(rng):
    """The card was flat while the gel pressed it, the lift flung it and it still moves at the end
    (MuJoCo's damped_s214: 1.6 mm over the final window, 4.7 mm up at the free edge, 1.0 mm while
    loaded): no rest shape, no set."""
    rec = _flung(synthetic(rng))
    motion, reason = moving_sheet_check(rec, rec.t["sheet_points"] > 3.3, rec.t["sheet_points"] < 0.9)
    assert motion > resolvable_set(rec) and "not a set" in reason
    r = plasticity_test(rec)
    assert not r.applicable and "still moves" in r.reason
    assert "bending_plasticity" not in named(rec)


def test_a_kept_fold_still_creeping_within_the_loaded_fold_is_a_set(rng):
    """A fold of 8 mm under load kept at 4.8 mm after the release, still rising 2 mm over the last
    0.3 s (our MuJoCo world's lift-folds with 1 ms steps after the peel): the sheet moves, but within
    the fold the load made, so the set is read: 4.8 mm plus the final window's mean rise, 1.33 mm."""
    rec = _flung(synthetic(rng), fold_under_load=8e-3, creep=2e-3)
    r = plasticity_test(rec)
    assert r.applicable and r.detail["final_motion_m"] > resolvable_set(rec)
    assert r.effect_size == pytest.approx(6.13e-3, abs=0.2e-3)
    assert named(rec) == ["bending_plasticity"]
