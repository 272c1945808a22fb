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


def _same(a, b) -> bool:
    """Two state fields equal to the bit (arrays, dicts and sequences of them, numbers, objects by their fields)."""
    if isinstance(a, dict) or isinstance(b, dict):
        return (isinstance(a, dict) and isinstance(b, dict) and a.keys() == b.keys()
                and all(_same(a[k], b[k]) for k in a))
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        return a.shape == b.shape and a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True)
    if isinstance(a, (list, tuple)) or isinstance(b, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if hasattr(a, "__dict__") and type(a) is type(b):
        return _same(vars(a), vars(b))
    return a == b



def test_the_layer_replay_with_the_release_is_the_carried_one_before_it_and_the_released_one(lift_fold):
    """The refit's base takes the layer search's own replay at the fitted ``k_t`` (a replay with the release, kept
    with its states: :func:`~sysid.diagnose.shear_layer.fit_shear_layer` ``keep_best``) instead of making the layer's
    carried replay (no release, with states) and its released replay (resumed from it) again. That holds where the
    release acts on no step before its time: the carried replay's states that the resumes take (those before the
    release) are the replay's with the release to the bit, and the released replay resumed from them is it to
    round-off (a resumed replay starts the solver's step-to-step caches afresh)."""
    from sysid.diagnose.resume import resume_before_time

    bag, dt = lift_fold
    model = ObservationModel(load_evidence(bag, include_image="auto"), dt=dt)
    w = adhesion_weight_scale(model.simulation().model)
    params = {**TRUE_PARAMS, ADHESION_PARAMETER: LAYER_BOND_WEIGHTS * w, SHEAR_STIFFNESS_SETTING: 3.0,
              RELEASE_TIME_SETTING: RELEASE_S}
    released = model.simulate(params, keep_states=True)  # as the layer search makes and keeps it
    carried = model.simulate({k: v for k, v in params.items() if k != RELEASE_TIME_SETTING}, keep_states=True)
    resume = resume_before_time(carried, RELEASE_S)
    assert resume is not None and resume.step > 0
    bonded = [np.asarray(s.candidate_state.get("adhesion_anchor_triangle", ())).size for s in carried.states]
    assert any(bonded[:resume.step])  # the card is carried by the layer's bonds over the steps compared
    for k in range(resume.step + 1):
        assert _same(vars(released.states[k]), vars(carried.states[k])), f"state {k} differs"
    resumed = np.asarray(model.predict(model.simulate(params, resume=resume))["sheet_points"], dtype=float)
    kept = np.asarray(model.predict(released)["sheet_points"], dtype=float)
    assert np.abs(resumed - kept).max() <= 1e-9 * np.abs(kept).max()


class _Trace:
    """A stand-in replay: the ``k_t`` it was made at."""

    def __init__(self, k: float, states: bool) -> None:
        self.k, self.states = k, ([k] if states else None)


class _Model:
    """A stand-in observation model whose sheet points miss the data by ``ln(k_t / 2)^2`` (+ 0.1 at a bump near
    k_t 0.3, a second pocket): the layer search's cost has a known best near ``k_t`` 2."""

    def __init__(self) -> None:
        self.made: list[_Trace] = []

    def simulate(self, params, keep_states: bool = False) -> _Trace:
        trace = _Trace(float(params[SHEAR_STIFFNESS_SETTING]), keep_states)
        self.made.append(trace)
        return trace

    def predict(self, trace: _Trace) -> dict:
        u = np.log(trace.k)
        miss = 1.0 + (u - np.log(2.0)) ** 2 - 0.5 * np.exp(-((u - np.log(0.3)) / 0.3) ** 2)
        return {"sheet_points": np.full((4, 2, 3), miss)}


def test_the_layer_search_keeps_the_replay_of_its_best():
    from sysid.diagnose.plasticity_refit import LAYER_REPLAYS
    from sysid.diagnose.shear_layer import fit_shear_layer

    model = _Model()
    data, sigma, rows = np.zeros((4, 2, 3)), np.ones(3), np.ones(4, bool)
    layer = fit_shear_layer(model, {}, 1.0, data, sigma, rows, max_replays=LAYER_REPLAYS, keep_best=True)
    assert len(model.made) == LAYER_REPLAYS and all(t.states is not None for t in model.made)
    best = min(model.made, key=lambda t: (float(model.predict(t)["sheet_points"][0, 0, 0]), t.k))
    assert layer.replay is best and layer.stiffness == best.k and 1.0 < best.k < 4.0
    plain = _Model()
    assert fit_shear_layer(plain, {}, 1.0, data, sigma, rows, max_replays=LAYER_REPLAYS).replay is None
    assert all(t.states is None for t in plain.made)
