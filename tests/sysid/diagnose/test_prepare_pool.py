"""A recording and its baselines prepared side by side (sysid.diagnose.prepare_pool): the baseline
prepared in a worker process gives the same signature results as prepared here, and comes back
without its simulator."""

from __future__ import annotations

import pytest

from sim_core.errors import CalibrationError
from sysid.diagnose.prepare_pool import prepare_with_baselines
from sysid.diagnose.signature_engine import SignatureSettings
from tests.sysid.simbag import PRESS_ONLY, make_recording


@pytest.fixture(scope="module")
def two_recordings(tmp_path_factory):
    root = tmp_path_factory.mktemp("pool")
    return (make_recording(root / "bag", seed=1, segments=PRESS_ONLY),
            make_recording(root / "baseline", seed=2, segments=PRESS_ONLY))


def test_a_baseline_prepared_in_a_worker_equals_the_one_prepared_here(two_recordings):
    bag, baseline = two_recordings
    settings = SignatureSettings()  # calibrated, as by default: its fit record stays in the worker
    pooled, [base_pooled] = prepare_with_baselines(bag, [baseline], settings, workers=2)
    here, [base_here] = prepare_with_baselines(bag, [baseline], settings, workers=1)
    assert base_here.model is not None and base_pooled.model is None and pooled.model is not None
    assert base_pooled.calibration.fit is None and base_pooled.calibration.params == base_here.calibration.params
    assert base_pooled.bag == base_here.bag
    for p, q in ((here, pooled), (base_here, base_pooled)):
        assert set(p.results) == set(q.results)
        for effect, r in p.results.items():
            assert (r.statistic, r.effect_size, r.applicable) == (q.results[effect].statistic,
                                                                  q.results[effect].effect_size,
                                                                  q.results[effect].applicable), effect
        assert p.calibration.whitened_rms_after == q.calibration.whitened_rms_after


def test_no_baseline_prepares_the_recording_alone_and_a_ray_address_needs_ray(two_recordings, monkeypatch):
    import builtins

    bag, baseline = two_recordings
    settings = SignatureSettings(calibrate=False)
    p, base = prepare_with_baselines(bag, [], settings, workers=2)
    assert base == [] and p.model is not None
    real_import = builtins.__import__

    def no_ray(name, *args, **kwargs):
        if name == "ray":
            raise ImportError("No module named 'ray'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_ray)
    with pytest.raises(CalibrationError, match="ray-address auto given but the 'ray' package is not installed"):
        prepare_with_baselines(bag, [baseline], settings, ray_address="auto")


def test_a_diverged_kinematic_reference_is_noted_and_the_diagnosis_goes_on(two_recordings, monkeypatch):
    """Where the replay with the recorded pose imposed (the damping test's reference through the drive)
    diverges, the recording is still prepared: the tests run on the calibrated replay and ``notes`` says why
    the reference is missing."""
    from sim_core.errors import SimulationDivergedError
    from sysid.diagnose import signature_engine

    def diverged(*args, **kwargs):
        raise SimulationDivergedError("step 339 (t = 3.39 s): Newton failed")

    monkeypatch.setattr(signature_engine, "kinematic_reference", diverged)
    bag, _ = two_recordings
    p = signature_engine.prepare(bag, SignatureSettings(calibrate=False))
    assert p.recording.reference is None and p.recording.prediction is not None
    assert any("recorded pose imposed diverged" in n and "step 339" in n for n in p.notes)
    assert "damping" in p.results and "lens_distortion" in p.results
