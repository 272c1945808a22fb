"""The permanent-set test (:func:`sysid.diagnose.signatures.sheet.plasticity_test`) reads a set from
a sheet at rest over the final window, after the gel's median marker is back at rest, or from a sheet
that still moves where the fold the gel gave it remains."""

from __future__ import annotations

import numpy as np
import pytest

from sysid.diagnose.signatures import Recording
from sysid.diagnose.signatures.base import marker_displacement
from sysid.diagnose.signatures.sensor import REST_DISPLACEMENT
from sim_core.mesh.sheet import grid_sheet
from sysid.diagnose.signatures.sheet import (KEPT_BLOCK_S, MEDIAN_MARKER_AT_REST, final_motion, kept_bend,
                                             line_curvatures, median_marker_displacement, plasticity_test,
                                             resolvable_set, sheet_grid)
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


def _flung(rec: Recording, settle_at: float | None = None) -> Recording:
    """``rec`` (the synthetic press of ``test_signatures``: gel released at 2.5 s, recording to
    3.5 s) with a recorded sheet that, after the release, lifts as a ramp from the clamped edge
    (x = 0) to 6 mm at the free edge and flaps back (a 2 Hz oscillation about 3 mm): an elastic card
    flung by the lift, flapping to the end; or, with ``settle_at``, flapping until then and resting
    from then on with a 4 mm fold at x = 70 +- 15 mm."""
    t = rec.t["sheet_points"]
    x = np.asarray(rec.data["sheet_points"], dtype=float).copy()
    x0 = x[0]
    flap = (t > 2.6) & (t < (settle_at if settle_at is not None else np.inf))
    ramp = x0[:, 0] / 0.1                                                              # (p,)
    height = 3e-3 * (1.0 + np.cos(2.0 * np.pi * 2.0 * (t - 2.6)))                       # (n,) 6 mm -> 0
    x[flap, :, 2] += height[flap, None] * ramp[None, :]
    if settle_at is not None:
        fold = np.abs(x0[:, 0] - 0.07) < 0.015
        x[np.ix_(t >= settle_at, fold, [2])] += 4e-3
    return Recording(t=rec.t, data=dict(rec.data, sheet_points=x), prediction=rec.prediction, sigma=rec.sigma,
                     camera=rec.camera, name=rec.name)


def test_an_elastic_sheet_still_flapping_at_the_end_is_not_a_set(rng):
    """The lift flung the card and it still moves at the end (MuJoCo's damped_s214 and damped_s404:
    1.6 and 3.8 mm over the final window): no rest shape, no set, whatever its height."""
    rec = _flung(synthetic(rng))
    assert final_motion(rec, rec.t["sheet_points"] > 3.29) > resolvable_set(rec)
    r = plasticity_test(rec)
    assert not r.applicable and "still moves" in r.reason
    assert "bending_plasticity" not in named(rec)


def test_a_fold_kept_once_the_sheet_comes_to_rest_is_a_set(rng):
    """The same flapping card coming to rest at 3.0 s with a 4 mm fold: the final window (the last
    0.2 s) holds a rest shape, and the fold is read as a set."""
    rec = _flung(synthetic(rng), settle_at=3.0)
    r = plasticity_test(rec)
    assert r.applicable and r.detail["final_motion_m"] < resolvable_set(rec)
    assert r.effect_size == pytest.approx(4e-3, rel=0.1)
    assert named(rec) == ["bending_plasticity"]


def test_a_fold_the_sheet_springs_back_from_by_the_end_did_not_remain(rng):
    """A card held still with a 4 mm fold for 0.6 s after the release, then brushed by the gel
    (every marker 100 um off rest for 50 ms) and flat from then to the end (MuJoCo's damped_s404: the
    final window before the touch, 5.9 mm, the end 0.07 mm): the fold did not remain, no set."""
    rec = synthetic(rng)
    t = rec.t["sheet_points"]
    x = np.asarray(rec.data["sheet_points"], dtype=float).copy()
    fold = np.abs(x[0, :, 0] - 0.07) < 0.015
    x[np.ix_((t > 2.6) & (t < 3.25), fold, [2])] += 4e-3
    xyz = rec.data["markers_xyz"].copy()
    xyz[(rec.t["markers_xyz"] > 3.25) & (rec.t["markers_xyz"] < 3.3), :, 0] += 1e-4
    sprung = Recording(t=rec.t, data=dict(rec.data, sheet_points=x, markers_xyz=xyz), prediction=rec.prediction,
                       sigma=rec.sigma, camera=rec.camera, name=rec.name)
    r = plasticity_test(sprung)
    assert not r.applicable and "did not remain" in r.reason
    assert "bending_plasticity" not in named(sprung)
    # the same fold kept to the end is a set
    x[np.ix_(t >= 3.25, fold, [2])] += 4e-3
    kept = Recording(t=rec.t, data=dict(sprung.data, sheet_points=x), prediction=rec.prediction, sigma=rec.sigma,
                     camera=rec.camera, name=rec.name)
    assert plasticity_test(kept).effect_size == pytest.approx(4e-3, rel=0.1)


def test_the_set_is_read_after_the_last_contact_not_between_two(rng):
    """A lift-and-fold: the press (1.0-2.5 s), a pause with the card lifted 4 mm (2.6-2.9 s, markers
    at rest), then the tack's hold loading the gel again for 0.45 s (2.95-3.4 s), shorter than the
    press, and 0.2 s of flat card to the end. The set is read after the last contact (flat: no set),
    not in the pause between the two, the last free run of 0.2 s (MuJoCo damped_s304 with 1 ms steps
    read a 3.3 mm 'set' there)."""
    rec = synthetic(rng, duration=3.6)
    t = rec.t["sheet_points"]
    x = np.asarray(rec.data["sheet_points"], dtype=float).copy()
    fold = np.abs(x[0, :, 0] - 0.07) < 0.015
    x[np.ix_((t > 2.6) & (t < 2.9), fold, [2])] += 4e-3
    tm = rec.t["markers_xyz"]
    xyz = rec.data["markers_xyz"].copy()
    xyz[(tm > 2.95) & (tm < 3.4), :, 2] -= 1e-4
    lifted = Recording(t=rec.t, data=dict(rec.data, sheet_points=x, markers_xyz=xyz), prediction=rec.prediction,
                       sigma=rec.sigma, camera=rec.camera, name=rec.name)
    r = plasticity_test(lifted)
    assert r.applicable and r.detail["final_window_s"][0] > 3.4
    assert r.effect_size < resolvable_set(lifted)
    assert "bending_plasticity" not in named(lifted)


def _edge_left_displaced(rec: Recording, sigmas: tuple[float, float, float] = (11.0, 11.5, -16.7)) -> Recording:
    """``rec`` with the markers of the gel's -x edge column (7 of 63) displaced by ``sigmas`` noise
    sigmas per axis from 0.05 s after the recorded gel's last loaded sample to the end, the rest of
    the grid untouched: the gel's edge that did not spring back after the peel in our MuJoCo world
    (plastic_s703: its corner marker 0.17 / 0.17 / -0.34 mm off rest with zero force on the gel from
    the peel to the end; damped_s403: the whole column 35 sigmas)."""
    tm = rec.t["markers_xyz"]
    xyz = np.asarray(rec.data["markers_xyz"], dtype=float).copy()
    released = tm > tm[np.nonzero(marker_displacement(rec) > REST_DISPLACEMENT)[0][-1]] + 0.05
    edge = np.isclose(xyz[0, :, 0], xyz[0, :, 0].min(), atol=5e-4)
    xyz[np.ix_(released, edge)] += np.asarray(sigmas) * rec.sigma["markers_xyz"]
    return Recording(t=rec.t, data=dict(rec.data, markers_xyz=xyz), prediction=rec.prediction, sigma=rec.sigma,
                     camera=rec.camera, name=rec.name)


def test_the_median_marker_of_a_gel_at_rest_is_at_the_noise(rng):
    """Noise alone: a marker's whitened RMS over its axes is sqrt(chi2(3) / 3), whose median is 0.888;
    the threshold is REST_DISPLACEMENT (1.5) times that."""
    rec = synthetic(rng)
    free = np.asarray(rec.prediction["markers_xyz"], dtype=float)
    noise = rng.normal(size=free.shape) * rec.sigma["markers_xyz"]
    at_rest = Recording(t=rec.t, data=dict(rec.data, markers_xyz=free[:1] + noise), prediction=None,
                        sigma=rec.sigma, camera=rec.camera, name=rec.name)
    assert np.median(median_marker_displacement(at_rest)) == pytest.approx(0.888, abs=0.03)
    assert MEDIAN_MARKER_AT_REST == pytest.approx(1.5 * 0.888, abs=1e-3)


def test_a_set_is_read_where_a_gel_edge_stays_displaced_alone():
    """Reference plastic_s102 (9.1 mm tent) with the gel's edge column left displaced after the peel:
    the grid's RMS stays above rest to the end (the old reading: 'the gel does not release the
    sheet'), its median marker is at rest, and the set is read and named."""
    ref = _elastic_replay(reference_recording("plastic_s102"))
    rec = _edge_left_displaced(ref)
    tail = rec.t["markers_xyz"] > rec.t["markers_xyz"][-1] - 0.3
    assert np.all(marker_displacement(rec)[tail] > REST_DISPLACEMENT)
    assert np.all(median_marker_displacement(rec)[tail] < MEDIAN_MARKER_AT_REST)
    r = plasticity_test(rec)
    assert r.applicable and r.effect_size == pytest.approx(9.1e-3, abs=0.5e-3)
    assert r.detail["final_window_s"] == plasticity_test(ref).detail["final_window_s"]
    assert "bending_plasticity" in named(rec)


def test_an_elastic_fold_with_a_gel_edge_left_displaced_names_no_set():
    """Reference nominal_s109 (flat again after the peel) with the same edge column: the window after
    the peel is read and holds no set."""
    rec = _edge_left_displaced(_elastic_replay(reference_recording("nominal_s109")))
    r = plasticity_test(rec)
    assert r.applicable and r.effect_size < resolvable_set(rec)
    assert "bending_plasticity" not in named(rec)


def _rising_after_release(rec: Recording, rate: float = 0.1) -> Recording:
    """``rec`` whose recorded sheet, from the plasticity test's release on, also turns about the clamped
    edge (x = 0) at ``rate`` rad/s: a rigid tilt that lifts the free edge (x = 100 mm) 10 mm/s and
    bends no grid line, so the sheet still moves over the final window (MuJoCo's plastic_s727: its
    kept tent rising 12 mm/s to the end, 0.9 s after the peel)."""
    t = rec.t["sheet_points"]
    x = np.asarray(rec.data["sheet_points"], dtype=float).copy()
    t_release = plasticity_test(rec).detail["release_s"]
    x[:, :, 2] += rate * np.clip(t - t_release, 0.0, None)[:, None] * x[0, :, 0][None, :]
    return Recording(t=rec.t, data=dict(rec.data, sheet_points=x), prediction=rec.prediction, sigma=rec.sigma,
                     camera=rec.camera, name=rec.name)


def test_a_kept_fold_on_a_sheet_that_still_moves_is_a_set():
    """Reference plastic_s102 (its 9.1 mm tent kept at x = 35 mm) tilting on after the peel: the final
    window holds no rest shape (1 mm of motion), but the line the gel bent most keeps that bend, so
    the set is read and named; the tilt bends no line, so the kept curvature stays what it is at the
    release."""
    rest = _elastic_replay(reference_recording("plastic_s102"))
    rec = _rising_after_release(rest)
    assert final_motion(rec, rec.t["sheet_points"] > rec.t["sheet_points"][-1] - 0.2) > resolvable_set(rec)
    r = plasticity_test(rec)
    assert r.applicable and "remains" in r.reason
    fold = r.detail["remaining_fold"]
    assert (fold["along"], fold["line"]) == ("x", 7)
    assert np.sign(fold["released_curvature"]) == np.sign(fold["hold_curvature"])
    assert fold["final_curvature"] == pytest.approx(fold["released_curvature"], rel=0.1)
    assert abs(fold["released_curvature"]) > 10.0 * fold["resolvable_curvature"]
    assert r.effect_size > 9.1e-3
    assert "bending_plasticity" in named(rec)


def test_an_elastic_sheet_that_still_moves_keeps_no_fold():
    """Reference nominal_s109 (folded 19 mm under the tack, flat after the peel) with the same tilt:
    the line the gel bent most is back to flat while the sheet moves, so no set is read."""
    rec = _rising_after_release(_elastic_replay(reference_recording("nominal_s109")))
    r = plasticity_test(rec)
    assert not r.applicable and "no fold remains" in r.reason
    assert "bending_plasticity" not in named(rec)


def test_the_sheet_grid_is_read_from_the_initial_points():
    """The scene's grid sheet (point iy * nx + ix) gives its (nx, ny); shuffled points are no grid."""
    mesh = grid_sheet((0.1, 0.06), (21, 13))
    x0 = np.asarray(mesh.x, dtype=float)
    assert sheet_grid(x0) == (21, 13)
    assert sheet_grid(x0[np.random.default_rng(3).permutation(len(x0))]) is None


def test_line_curvatures_of_a_cylinder_and_their_noise(rng):
    """A cylinder z = c x^2 / 2 bends every line along x by c and none along y (second differences are
    exact on a quadratic); white height noise gives each value the standard error
    sqrt(6) sigma / (h^2 sqrt(lines))."""
    nx, ny, h, c, sigma = 21, 13, 0.005, 30.0, 5e-5
    x0 = np.asarray(grid_sheet((0.1, 0.06), (nx, ny)).x, dtype=float)
    bent = x0.copy()
    bent[:, 2] = 0.5 * c * x0[:, 0] ** 2
    k = line_curvatures(bent[None], (nx, ny), h)[0]
    assert np.allclose(k[: nx - 2], c) and np.allclose(k[nx - 2:], 0.0, atol=1e-9)
    noisy = x0[None] + np.concatenate([np.zeros((4000, len(x0), 2)), rng.normal(0.0, sigma, (4000, len(x0), 1))], 2)
    k = line_curvatures(noisy, (nx, ny), h)
    assert k[:, : nx - 2].std() == pytest.approx(np.sqrt(6.0) * sigma / (h ** 2 * np.sqrt(ny)), rel=0.05)
    assert k[:, nx - 2:].std() == pytest.approx(np.sqrt(6.0) * sigma / (h ** 2 * np.sqrt(nx)), rel=0.05)


def _bent_more_under_the_gel(rec: Recording, curvature: float = 60.0) -> Recording:
    """``rec`` whose recorded sheet, wherever the recorded gel is loaded (median marker off rest), also
    bends by ``curvature`` 1/m over x = 60-75 mm and runs on tangent beyond: an elastic bend the gel
    gives the card beside its tent and takes back at the release, larger than the tent's own bend, so
    that the line bent most under the gel is not the line the card keeps a kink on (MuJoCo's
    plastic_s789: bent most at x = 30 mm under the gel, its kink kept at x = 65 mm)."""
    t = rec.t["sheet_points"]
    x = np.asarray(rec.data["sheet_points"], dtype=float).copy()
    loaded = np.interp(t, rec.t["markers_xyz"], median_marker_displacement(rec) > MEDIAN_MARKER_AT_REST) > 0.0
    s = np.clip(x[0, :, 0] - x[0, :, 0].min() - 0.06, 0.0, None)
    bend = 0.5 * curvature * np.minimum(s, 0.015) ** 2 + curvature * 0.015 * np.clip(s - 0.015, 0.0, None)
    x[np.ix_(loaded, np.arange(x.shape[1]), [2])] += bend[None, :, None]
    return Recording(t=rec.t, data=dict(rec.data, sheet_points=x), prediction=rec.prediction, sigma=rec.sigma,
                     camera=rec.camera, name=rec.name)


def test_a_kink_kept_beside_the_line_bent_most_under_the_gel_is_a_set():
    """Reference plastic_s102 bent more at x = 60-75 mm than at its tent while the gel holds it (that
    bend springs back at the release) and tilting on after the peel: the line bent most under the gel
    keeps nothing, but x line 7 (35 mm) keeps its kink in every 0.05 s block since the gel last touched
    the card, so the set is read from the moving sheet and named. Fails where only the line bent most
    under the gel is followed."""
    rec = _rising_after_release(_bent_more_under_the_gel(_elastic_replay(reference_recording("plastic_s102"))))
    r = plasticity_test(rec)
    assert r.applicable and "a fold remains" in r.reason
    fold = r.detail["remaining_fold"]
    assert fold["along"] == "x" and 12 <= fold["line"] <= 16 and fold["hold_curvature"] > 30.0
    assert abs(fold["released_curvature"]) < fold["resolvable_curvature"]
    assert (fold["kept_along"], fold["kept_line"]) == ("x", 7)
    assert fold["kept_curvature"] < -10.0 * fold["resolvable_curvature"] and fold["kept_ratio"] > 10.0
    assert r.effect_size > 9.1e-3
    assert "bending_plasticity" in named(rec)


def test_an_elastic_sheet_bent_more_under_the_gel_that_still_moves_keeps_no_bend():
    """Reference nominal_s109 with the same larger elastic bend under the gel and the same tilt after
    the peel: no line keeps one bend in every block since the gel last touched the card, not
    applicable, not named."""
    rec = _rising_after_release(_bent_more_under_the_gel(_elastic_replay(reference_recording("nominal_s109"))))
    r = plasticity_test(rec)
    assert not r.applicable and "no fold remains" in r.reason
    assert "bending_plasticity" not in named(rec)


def test_a_kept_bend_holds_its_sign_in_every_block(rng):
    """:func:`kept_bend` on line curvatures with white noise of a tenth of the resolvable curvature:
    a constant bend of 2.5 resolvable curvatures gives about 2.5 (its weakest block a few block
    errors lower); a bend oscillating at 3 Hz through flat about a mean of 2 resolvable curvatures
    (an elastic card flapping) gives below 0 whatever its mean; released rows spanning three blocks
    tell nothing (None)."""
    t = np.arange(0.0, 0.6, 0.0095)
    resolvable = np.array([2.0, 2.0])
    noise = 0.2 * rng.standard_normal((len(t), 2))
    k = np.stack([np.full(len(t), 5.0), 4.0 + 10.0 * np.sin(2.0 * np.pi * 3.0 * t)], axis=1) + noise
    ratio = kept_bend(t, k, np.ones(len(t), bool), resolvable)
    assert 2.2 < ratio[0] <= 2.5 and ratio[1] < 0.0
    assert kept_bend(t, k, t < 3.0 * KEPT_BLOCK_S, resolvable) is None
    assert kept_bend(t, -k, np.ones(len(t), bool), resolvable)[0] == pytest.approx(ratio[0], abs=0.3)


def _patch_pressed_to_the_end(rec: Recording, sigmas: float = -8.0, load_n: float = 0.0) -> Recording:
    """``rec`` whose gel markers with x of -2 mm or more (42 of 63) are pushed
    ``sigmas`` noise sigmas along z from the recorded gel's last loaded sample to the end, and whose
    wrench gains ``load_n`` N along z there: a card's kept fold standing against the lifted gel to the end
    (MuJoCo plastic_s812, yield 0.0006: its tent 23.7 mm high at rest, its edge on the gel, median marker
    1.45-1.77, the wrench 0.4 sigma from its free level), with or without a load."""
    tm = rec.t["markers_xyz"]
    xyz = np.asarray(rec.data["markers_xyz"], dtype=float).copy()
    pressed = tm > tm[np.nonzero(marker_displacement(rec) > REST_DISPLACEMENT)[0][-1]] + 0.05
    patch = xyz[0, :, 0] >= -2.5e-3
    xyz[np.ix_(pressed, patch, [2])] += sigmas * rec.sigma["markers_xyz"][2]
    wrench = np.asarray(rec.data["wrench"], dtype=float).copy()
    tw = rec.t["wrench"]
    wrench[tw > tm[pressed][0], 2] += load_n
    return Recording(t=rec.t, data=dict(rec.data, markers_xyz=xyz, wrench=wrench), prediction=rec.prediction,
                     sigma=rec.sigma, camera=rec.camera, name=rec.name)


def test_a_set_resting_against_the_lifted_gel_without_a_load_is_read():
    """Reference plastic_s102 whose kept tent touches the lifted gel from the peel to the end (more than
    two thirds of the markers 8 sigmas off rest, no force): no free final window, but the sheet rests and the
    wrench is at its free level, so the 9.1 mm set is read over the last 0.2 s and named. Fails where a
    gel loaded to the end stops the test. The same with 1 N on the gel is a load: not applicable."""
    rest = _elastic_replay(reference_recording("plastic_s102"))
    rec = _patch_pressed_to_the_end(rest)
    assert median_marker_displacement(rec)[-20:].min() > MEDIAN_MARKER_AT_REST
    r = plasticity_test(rec)
    assert r.applicable and "kept fold standing against the lifted gel" in r.reason
    assert r.effect_size == pytest.approx(9.1e-3, abs=0.5e-3)
    assert "bending_plasticity" in named(rec)
    loaded = plasticity_test(_patch_pressed_to_the_end(rest, load_n=1.0))
    assert not loaded.applicable and "does not release" in loaded.reason


def test_an_elastic_sheet_flat_under_a_gel_pressed_to_the_end_names_no_set():
    """Reference nominal_s109 with the same markers pushed to the end and no force: read over the last
    0.2 s, its sheet is flat (no set), not named."""
    rec = _patch_pressed_to_the_end(_elastic_replay(reference_recording("nominal_s109")))
    r = plasticity_test(rec)
    assert r.applicable and r.effect_size < resolvable_set(rec)
    assert "bending_plasticity" not in named(rec)
