"""The tack layer's search keeps its best replay, and that replay is the carried and the released one.

:func:`sysid.diagnose.plasticity_refit.with_shear_layer` takes the shear-layer search's own replay at the fitted
``k_t`` (:func:`sysid.diagnose.shear_layer.fit_shear_layer`, ``keep_best``) instead of replaying the layer twice more:
once without the release with its states (the start of the resumes) and once with the release resumed from it
(:func:`sysid.diagnose.plasticity_refit.tack_base`'s prediction). That holds only if the release acts on no step
before its time (:meth:`sim_core.candidates.hook.CandidateHook.released`) and a resumed replay takes the same steps
as one from the start. Known answer in this simulator, to the bit: the benchmark card carried by the gel's tack held
in shear by the layer (k_t 3 N/m a pair, bonds of 400 card weights) and let go at 0.12 s.
"""

from __future__ import annotations

import pathlib
import tempfile

import numpy as np

from sim_core.scenes import load_scene
from sim_core.simulation import Simulation
from sysid.diagnose.candidates import ADHESION_PROBE_WEIGHTS, adhesion_weight_scale
from sysid.diagnose.peel import ADHESION_PARAMETER, RELEASE_TIME_SETTING, tack_with_peel
from sysid.diagnose.plasticity_refit import LAYER_REPLAYS
from sysid.diagnose.resume import resume_before_time
from sysid.diagnose.shear_layer import LAYER_BOND_WEIGHTS, SHEAR_STIFFNESS_SETTING, fit_shear_layer, sheet_rms
from sysid.diagnose.signature_engine import recording_of
from sysid.evidence import load_evidence
from sysid.observation import ObservationModel
from tests.sysid.simbag import (PRESS_ONLY, TRUE_PARAMS, add_noise, scene_with, simulate_streams,
                                targets_from_segments, write_bag)


def _same(a, b) -> bool:
    """Two state fields equal to the bit (arrays, dicts of them, numbers)."""
    if isinstance(a, dict) or isinstance(b, dict):
        return isinstance(a, dict) and isinstance(b, dict) and a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        return a.shape == b.shape and a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True)
    if isinstance(a, (list, tuple)) or isinstance(b, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if hasattr(a, "__dict__") and type(a) is type(b):
        return _same(vars(a), vars(b))
    return a == b


def test_the_layer_searchs_best_replay_is_the_carried_and_the_released_replay_to_the_bit():
    scene = scene_with(TRUE_PARAMS)
    dt = float(scene["dt"])
    w = adhesion_weight_scale(Simulation(load_scene(scene), dt=dt).model)
    lift = PRESS_ONLY + (((0.0, 0.0, 0.003), 6), ((-0.002, 0.0, 0.0), 4), ((0.0, 0.0, 0.003), 4), ((0.0, 0.0, 0.0), 4))
    targets = targets_from_segments(np.asarray(scene["effectors"]["ee"]["initial_pose"]), lift)
    truth = {**TRUE_PARAMS, ADHESION_PARAMETER: LAYER_BOND_WEIGHTS * w, SHEAR_STIFFNESS_SETTING: 3.0,
             RELEASE_TIME_SETTING: 12 * dt}
    bag = write_bag(pathlib.Path(tempfile.mkdtemp()) / "bag", scene, add_noise(simulate_streams(scene, truth, targets), seed=3))
    model = ObservationModel(load_evidence(bag, include_image="auto"), dt=dt)
    rec = recording_of(model, None)
    t, data, sigma = (np.asarray(d["sheet_points"], dtype=float) for d in (rec.t, rec.data, rec.sigma))
    tack = tack_with_peel(model, TRUE_PARAMS, t, data, ADHESION_PROBE_WEIGHTS * w, keep_carried=True)
    assert tack is not None
    rows = t < tack["peel_s"]
    layer = fit_shear_layer(model, tack["params"], tack["beta"], data, sigma, rows, max_replays=LAYER_REPLAYS,
                            keep_best=True)
    assert layer is not None and layer.replay is not None and len(layer.profile) == LAYER_REPLAYS
    # the kept replay is the best one's: its sheet points give the profile's best RMS
    assert sheet_rms(model.predict(layer.replay)["sheet_points"], data, sigma, rows) == layer.rms
    params = {**tack["params"], **layer.settings()}
    release = params[RELEASE_TIME_SETTING]
    held = {k: v for k, v in params.items() if k != RELEASE_TIME_SETTING}
    carried = model.simulate(held, keep_states=True)  # the replay the search's best now stands for
    resume = resume_before_time(carried, release)
    assert resume is not None and resume.step > 0
    # every step the resumes take from it (those before the release) is the carried replay's, to the bit
    for k in range(resume.step + 1):
        assert _same(vars(layer.replay.states[k]), vars(carried.states[k])), f"state {k} differs"
    # and the released replay resumed from the carried one is the search's replay from the start, to the bit
    resumed = model.predict(model.simulate(params, resume=resume))
    kept = model.predict(layer.replay)
    assert resumed.keys() == kept.keys()
    for channel in kept:
        assert np.array_equal(np.asarray(resumed[channel]), np.asarray(kept[channel]), equal_nan=True), channel
    # the release acts: after it the two replays part (the carried card is held, the released one falls)
    assert not np.array_equal(carried.states[-1].x, layer.replay.states[-1].x)
