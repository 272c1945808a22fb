"""Stiction's line of action test: calibration of the scale-equality test, its power on a shifted
centre of pressure, and the engine's handling of a refuted candidate and of a refit that leaves its
effect off."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from sysid.diagnose import discriminate, engine, report
from sysid.diagnose.candidates import DiagnosisContext, Refit
from sysid.diagnose.stats import scale_equality_test

SIGMA = np.array([0.1, 0.1, 0.2, 4e-4, 4e-4, 4e-4])


def _correlated_noise(rng, T, S, rho=0.6, common=0.5):
    """AR(1) in time, with a factor common to the S series of a sample (as a wrench's axes share)."""
    e = rng.normal(size=(T, S)) + common * rng.normal(size=(T, 1))
    out = np.empty_like(e)
    out[0] = e[0]
    for t in range(1, T):
        out[t] = rho * out[t - 1] + np.sqrt(1 - rho ** 2) * e[t]
    return out


def _wrench_change(T, start=0.3):
    """A smooth whitened wrench change (T, 6) from ``start`` (fraction of the span): force and moment both move."""
    t = np.linspace(0.0, 1.0, T)
    shape = np.clip(t - start, 0.0, None) * 4.0 + (0.5 if start == 0.0 else 0.0)
    return shape[:, None] * np.array([2.0, 0.3, 1.0, 0.4, 1.5, 0.2])[None]


def _columns(d):
    force = np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0])
    return np.stack([d * force, d * (1 - force)], axis=-1)


@pytest.mark.parametrize("rho", [0.0, 0.6, 0.8])
def test_scale_equality_is_calibrated_under_serial_and_cross_correlation(rho):
    rng = np.random.default_rng(11)
    T = 32  # about the samples of a benchmark recording where a refit changes the wrench
    d = _wrench_change(T, start=0.0)
    p = np.array([scale_equality_test(0.8 * d + _correlated_noise(rng, T, 6, rho=rho), _columns(d)).p_value
                  for _ in range(400)])  # one common scale: the null
    # binomial(400, 0.05): sd 0.011 (a Newey-West variance gave 0.19 at rho 0.6 with 24 samples; block
    # sums without prewhitening 0.11 at rho 0.6 and 0.21 at rho 0.8); at the engine's level 0.01 the
    # refutation of a true stiction must stay rare (binomial(400, 0.01): sd 0.005)
    assert 0.01 <= np.mean(p < 0.05) <= 0.08, np.mean(p < 0.05)
    assert np.mean(p < 0.01) <= 0.02, np.mean(p < 0.01)
    if rho == 0.8:
        unfiltered = sum(scale_equality_test(0.8 * d + _correlated_noise(rng, T, 6, rho=rho), _columns(d),
                                             prewhiten=False).p_value < 0.05 for _ in range(400))
        assert unfiltered / 400 > 0.12  # the correction matters


@pytest.mark.parametrize("rho", [0.6, 0.8])
def test_scale_equality_power_at_the_engine_level_exceeds_eight_batch_means(rho):
    """At the engine's level 0.01, a moment at 0.45 of the force's scale (the benchmark's thickness step)
    with the residual correlation of a benchmark recording (its pooled AR(1) estimate: 0.6) is refuted
    in most draws; eight batch means (the previous variance) refuted 65 % (rho 0.6) and 57 % (rho 0.8)
    of these draws at 28 samples."""
    rng = np.random.default_rng(12)
    T = 28
    d = _wrench_change(T, start=0.0)
    moment = np.array([0.0, 0.0, 0.0, 1.0, 1.0, 1.0])
    hits = sum(scale_equality_test(1.2 * d - 0.75 * d * moment + _correlated_noise(rng, T, 6, rho=rho),
                                   _columns(d)).p_value < 0.01 for _ in range(200))
    assert hits / 200 >= 0.72, hits / 200


def test_scale_equality_rejects_degenerate_input():
    with pytest.raises(ValueError, match="at least 2 columns"):
        scale_equality_test(np.zeros((10, 6)), np.ones((10, 6, 1)))
    with pytest.raises(ValueError, match="at least 4 samples"):
        scale_equality_test(np.zeros((3, 6)), np.ones((3, 6, 2)))
    X = np.ones((10, 6, 2))
    X[..., 1] = 0.0
    with pytest.raises(ValueError, match="a column is zero"):
        scale_equality_test(np.zeros((10, 6)), X)
    with pytest.raises(ValueError, match="at least 1 cosine weights"):
        scale_equality_test(np.zeros((10, 6)), np.ones((10, 6, 2)), cosines=0)


def _wrench_ctx(data, pred0):
    T = pred0.shape[0]
    steps = np.arange(T, dtype=np.int64) * 10_000_000
    model = SimpleNamespace(sigma={"wrench": SIGMA.copy()}, data=lambda ch: data, step_times_ns=steps,
                            evidence=SimpleNamespace(t_ns={"wrench": steps}, channels_present=("wrench",)),
                            channels=("wrench",))
    trace = SimpleNamespace(channel=lambda ch: pred0)
    return model, DiagnosisContext(model, {}, trace, {"wrench": pred0}, ("wrench",))


def test_line_of_action_accepts_a_tangential_change_and_refutes_a_shifted_centre_of_pressure():
    rng = np.random.default_rng(13)
    T = 47
    pred0 = np.zeros((T, 6))
    change = 3.0 * _wrench_change(T) * SIGMA  # unwhitened
    refit = {"wrench": pred0 + change}
    noise = _correlated_noise(rng, T, 6, rho=0.3) * SIGMA
    model, ctx = _wrench_ctx(pred0 + 1.1 * change + noise, pred0)
    same = discriminate.line_of_action(model, ctx, refit)
    assert same.p_value > 0.01 and same.coefficients == pytest.approx([1.1, 1.1], abs=0.15)
    shifted = change * np.array([1.2, 1.2, 1.2, 0.45, 0.45, 0.45])
    model, ctx = _wrench_ctx(pred0 + shifted + noise, pred0)
    res = discriminate.line_of_action(model, ctx, refit)
    assert res.p_value < 0.01 and res.coefficients == pytest.approx([1.2, 0.45], abs=0.15)
    assert discriminate.line_of_action(model, ctx, {"markers_xyz": np.zeros((T, 4, 3))}) is None


def _decide(data, pred0, refits, alpha=0.01):
    model, ctx = _wrench_ctx(data, pred0)
    d = engine.BagDiagnosis.__new__(engine.BagDiagnosis)
    d.model, d.settings, d.notes, d.tested, d.heldout = model, engine.Settings(alpha=alpha), [], ("wrench",), []
    T = pred0.shape[0]
    train = {"wrench": np.arange(T) % 2 == 0}
    folds = [engine.heldout.block_fold(model, ctx.prediction, train, refits)]
    return d._decide(ctx, refits, train, folds), d.notes


def test_a_refuted_candidate_is_not_named_and_a_weaker_proxy_is_not_named_in_its_place():
    rng = np.random.default_rng(14)
    T = 47
    pred0 = np.zeros((T, 6))
    change = 3.0 * _wrench_change(T) * SIGMA
    noise = _correlated_noise(rng, T, 6, rho=0.3, common=0.2) * SIGMA
    # the recording: force changes as the stiction refit predicts, the moment at under half of it
    data = pred0 + change * np.array([1.0, 1.0, 1.0, 0.45, 0.45, 0.45]) + noise
    stiction = Refit(np.array([0.02]), {"candidate.stiction": 0.02}, {"wrench": pred0 + change},
                     {"candidate.stiction": 0.02})
    # a weaker candidate whose change is the force part only, at half: it explains part of the same pattern
    proxy = change * np.array([0.5, 0.5, 0.5, 0.0, 0.0, 0.0])
    aniso = Refit(np.array([0.05]), {"candidate.anisotropic_bending": 0.05}, {"wrench": pred0 + proxy},
                  {"candidate.anisotropic_bending": 0.05})
    out, notes = _decide(data, pred0, {"stiction": stiction, "anisotropic_bending": aniso})
    assert out["stiction"]["refuted_by"] == ["line_of_action"] and not out["stiction"]["accepted"]
    assert out["stiction"]["explained_fraction"] > 0.5  # it does describe the mismatch
    assert out["stiction"]["heldout_gain"] > out["anisotropic_bending"]["heldout_gain"]
    assert not out["anisotropic_bending"]["accepted"]
    assert any("line of action" in n for n in notes)
    # the same recording without the refuted candidate: the proxy alone would have been named
    out, _ = _decide(data, pred0, {"anisotropic_bending": aniso})
    assert out["anisotropic_bending"]["accepted"]


def test_real_stiction_passes_the_line_of_action_test():
    rng = np.random.default_rng(15)
    T = 47
    pred0 = np.zeros((T, 6))
    change = 3.0 * _wrench_change(T) * SIGMA
    noise = _correlated_noise(rng, T, 6, rho=0.3, common=0.2) * SIGMA
    stiction = Refit(np.array([0.02]), {"candidate.stiction": 0.02}, {"wrench": pred0 + change},
                     {"candidate.stiction": 0.02})
    out, _ = _decide(pred0 + 1.1 * change + noise, pred0, {"stiction": stiction})
    assert out["stiction"]["accepted"] and "refuted_by" not in out["stiction"]
    assert out["stiction"]["line_of_action_p"] > 0.01


def test_a_candidate_contradicted_on_a_channel_is_not_named_and_a_weaker_proxy_is_not_named_in_its_place():
    """Channel consistency is a discriminating test like the line of action: a refit that explains the
    wrench but moves the sheet where the recording does not (held-out supported scale on the sheet
    under 1/2) is not named, and stays in the acceptance sequence, so that a weaker candidate that only
    follows part of the same wrench change is judged on what it adds beyond it (the benchmark's
    thickness step: stiction contradicted on one channel, anisotropy then named alone)."""
    rng = np.random.default_rng(16)
    T = 47
    sheet_sigma = np.array([5e-5, 5e-5, 5e-5])
    pred0 = {"wrench": np.zeros((T, 6)), "sheet_points": np.zeros((T, 4, 3))}
    change = 3.0 * _wrench_change(T) * SIGMA
    sheet_change = 0.6 * np.clip(np.linspace(-1.0, 3.0, T), 0.0, None)[:, None, None] * sheet_sigma * np.ones((1, 4, 3))
    data = {"wrench": pred0["wrench"] + change + _correlated_noise(rng, T, 6, rho=0.3, common=0.2) * SIGMA,
            "sheet_points": rng.normal(size=(T, 4, 3)) * sheet_sigma}
    steps = np.arange(T, dtype=np.int64) * 10_000_000
    model = SimpleNamespace(sigma={"wrench": SIGMA.copy(), "sheet_points": sheet_sigma.copy()},
                            data=lambda ch: data[ch], step_times_ns=steps,
                            evidence=SimpleNamespace(t_ns={"wrench": steps, "sheet_points": steps},
                                                     channels_present=("wrench", "sheet_points")),
                            channels=("wrench", "sheet_points"))
    trace = SimpleNamespace(channel=lambda ch: pred0[ch])
    ctx = DiagnosisContext(model, {}, trace, dict(pred0), ("wrench", "sheet_points"))
    gel = Refit(np.array([0.1]), {"candidate.gel_viscoelasticity": 0.1},
                {"wrench": pred0["wrench"] + change, "sheet_points": pred0["sheet_points"] + sheet_change},
                {"candidate.gel_viscoelasticity": 0.1})
    aniso = Refit(np.array([0.05]), {"candidate.anisotropic_bending": 0.05}, {"wrench": pred0["wrench"] + 0.6 * change},
                  {"candidate.anisotropic_bending": 0.05})

    def decide(refits):
        d = engine.BagDiagnosis.__new__(engine.BagDiagnosis)
        d.model, d.settings, d.notes, d.tested, d.heldout = model, engine.Settings(), [], ctx.channels, []
        train = {ch: np.arange(T) % 2 == 0 for ch in ctx.channels}
        return d._decide(ctx, refits, train, [engine.heldout.block_fold(model, ctx.prediction, train, refits)])

    out = decide({"gel_viscoelasticity": gel, "anisotropic_bending": aniso})
    assert out["gel_viscoelasticity"]["contradicted_on"] == ["sheet_points"]
    assert out["gel_viscoelasticity"]["refuted_by"] == ["channel_consistency"]
    assert not out["gel_viscoelasticity"]["accepted"]
    assert out["gel_viscoelasticity"]["heldout_gain"] > out["anisotropic_bending"]["heldout_gain"]
    assert not out["anisotropic_bending"]["accepted"]
    assert decide({"anisotropic_bending": aniso})["anisotropic_bending"]["accepted"]  # alone it would be named


def test_a_refit_that_leaves_its_effect_off_is_not_named_nor_put_before_the_effect():
    """Every physics refit re-estimates the nominal parameters with its beta (their directions were projected
    out of the score test); where the training rows ask for a one-sided effect's opposite, beta is clipped to 0
    and the refit's change is that re-estimate alone. It explains the nominal fit's gap, not the effect, so it
    is not named, and it does not take the first place of the acceptance sequence from the effect that is
    there (the demo's DDS recordings: the sheet drag refitted at 0 named beside, or in place of, the gel)."""
    rng = np.random.default_rng(17)
    T = 47
    pred0 = np.zeros((T, 6))
    change = 3.0 * _wrench_change(T) * SIGMA
    data = pred0 + change + _correlated_noise(rng, T, 6, rho=0.3, common=0.2) * SIGMA
    # the drag switched off: its replay moves only the nominal parameters, which follow most of the change
    # (and, on its own rows, a little more of it than the effect's refit: first in the sequence by gain)
    drag_off = Refit(np.array([0.0]), {"candidate.damping": 0.0, "gel.youngs_modulus": 4.2e5},
                     {"wrench": pred0 + 0.97 * change}, {"gel.youngs_modulus": 4.2e5})
    gel = Refit(np.array([0.4]), {"candidate.gel_viscoelasticity": 0.4, "gel.youngs_modulus": 3.6e5},
                {"wrench": pred0 + 0.9 * change}, {"candidate.gel_viscoelasticity": 0.4, "gel.youngs_modulus": 3.6e5})
    refits = {"damping": drag_off, "gel_viscoelasticity": gel}
    model, ctx = _wrench_ctx(data, pred0)
    d = engine.BagDiagnosis.__new__(engine.BagDiagnosis)
    d.model, d.settings, d.notes, d.tested, d.heldout = model, engine.Settings(), [], ("wrench",), []
    train = {"wrench": np.arange(T) % 2 == 0}
    folds = [engine.heldout.block_fold(model, ctx.prediction, train, refits)]
    out = d._decisions = d._decide(ctx, refits, train, folds)
    assert out["damping"]["explained_fraction"] > 0.5 and not out["damping"]["effect_on"]
    assert out["damping"]["effect_gain"] > out["gel_viscoelasticity"]["effect_gain"]
    assert not out["damping"]["accepted"] and not out["damping"]["acceptable_alone"]
    assert out["gel_viscoelasticity"]["accepted"] and out["gel_viscoelasticity"]["scale"] == 1.0
    assert any("damping: its refit leaves the effect off" in n for n in d.notes)
    # no tie with a mechanism that is off, and the report says why it is not named
    assert d._ties(ctx, ["gel_viscoelasticity"], refits, [], train, folds) == []
    assert any("leaves the effect off" in why for why in report._rejections(out["damping"], 0.01, 10.0, 0.25))
    # the same refit with the drag on (any beta > 0) is judged as before: it explains the change and is named
    drag_on = Refit(np.array([1e-3]), {"candidate.damping": 1e-3}, {"wrench": pred0 + 0.97 * change},
                    {"candidate.damping": 1e-3})
    out, _ = _decide(data, pred0, {"damping": drag_on})
    assert out["damping"]["accepted"] and out["damping"]["effect_on"]


def test_a_refit_whose_fit_rides_on_the_nominal_parameters_move_is_not_named_and_the_effect_is():
    """A physics refit's strength is fitted with the nominal parameters' log steps; judged against the nominal
    prediction alone, the parameters' move counts as the effect's. Against the null model (the nominal
    parameters re-estimated without any effect, replayed once: ``engine.NULL_MODEL`` in the folds) a refit
    with a tiny strength that only carries that move adds nothing and is not named, while the effect that
    explains what the re-estimate leaves is named; without the null in the folds both are judged as before."""
    rng = np.random.default_rng(23)
    T = 47
    pred0 = np.zeros((T, 6))
    move = 3.0 * _wrench_change(T, start=0.0) * SIGMA  # what the re-estimated nominal parameters follow
    t = np.linspace(0.0, 1.0, T)
    effect = 1.5 * (np.sin(6.0 * np.pi * t)[:, None] * np.array([1.0, 0.5, 1.0, 0.5, 1.0, 0.5])[None]) * SIGMA
    data = pred0 + move + effect + _correlated_noise(rng, T, 6, rho=0.3, common=0.2) * SIGMA
    null = Refit(np.zeros(0), {"gel.youngs_modulus": 4.0e5}, {"wrench": pred0 + move}, {"gel.youngs_modulus": 4.0e5})
    drag = Refit(np.array([1e-4]), {"candidate.damping": 1e-4, "gel.youngs_modulus": 4.0e5},
                 {"wrench": pred0 + 1.01 * move}, {"candidate.damping": 1e-4, "gel.youngs_modulus": 4.0e5})
    gel = Refit(np.array([0.4]), {"candidate.gel_viscoelasticity": 0.4, "gel.youngs_modulus": 4.0e5},
                {"wrench": pred0 + move + 0.9 * effect},
                {"candidate.gel_viscoelasticity": 0.4, "gel.youngs_modulus": 4.0e5})
    refits = {"damping": drag, "gel_viscoelasticity": gel}
    model, ctx = _wrench_ctx(data, pred0)
    train = {"wrench": np.arange(T) % 2 == 0}

    def decide(with_null):
        d = engine.BagDiagnosis.__new__(engine.BagDiagnosis)
        d.model, d.settings, d.notes, d.tested, d.heldout = model, engine.Settings(), [], ("wrench",), []
        folds = [engine.heldout.block_fold(model, ctx.prediction, train,
                                           {**refits, engine.NULL_MODEL: null} if with_null else refits)]
        d._decisions = d._decide(ctx, refits, train, folds)
        return d, d._decisions

    d, out = decide(with_null=True)
    drag_null, gel_null = out["damping"]["beyond_reestimate"], out["gel_viscoelasticity"]["beyond_reestimate"]
    # against the nominal prediction the drag explains most of the excess; against the null almost nothing
    assert out["damping"]["explained_fraction"] > 0.5 and out["damping"]["effect_on"]
    assert not drag_null["adds"] and drag_null["explained_fraction"] < 0.25
    assert not out["damping"]["accepted"] and not out["damping"]["acceptable_alone"]
    assert any("damping: its refit explains" in n and "re-estimated without it" in n for n in d.notes)
    assert any("the nominal parameters' move carries its fit" in why
               for why in report._rejections(out["damping"], 0.01, 10.0, 0.25))
    # the effect explains what the null leaves: named
    assert gel_null["adds"] and gel_null["explained_fraction"] > 0.5 and gel_null["heldout_p"] < 0.01
    assert out["gel_viscoelasticity"]["accepted"]
    line = report.why_lines({"extra": {"decisions": out, "library": ["gel_viscoelasticity"], "tests": []}})[0]
    assert "gel_viscoelasticity: accepted" in line and "against the nominal parameters re-estimated without it" in line
    # an observation-level refit moves no nominal parameter: no null comparison
    assert d._beyond_null("latency", Refit(np.array([0.01]), {"latency_s": 0.01}, {"wrench": pred0}), ["wrench"],
                          [engine.heldout.block_fold(model, ctx.prediction, train, {engine.NULL_MODEL: null})]) is None
    # without the null in the folds (no nominal parameter projected) the drag is judged against the nominal alone
    _, out = decide(with_null=False)
    assert "beyond_reestimate" not in out["damping"] and out["damping"]["acceptable_alone"]
