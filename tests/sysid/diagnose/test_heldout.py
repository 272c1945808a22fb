"""Held-out evaluation (time blocks or held-out recordings) and the engine's conditional acceptance on it."""

from __future__ import annotations

import numpy as np
import pytest

from sysid.diagnose import engine, heldout, stats
from sysid.diagnose.candidates import Refit
from tests.sysid.diagnose.test_discriminate import SIGMA, _wrench_change, _wrench_ctx

T = 47


def _second_change():
    """A wrench change unlike :func:`_wrench_change`: an oscillation on fx and tz only (whitened)."""
    t = np.linspace(0.0, 1.0, T)
    return np.sin(6 * np.pi * t)[:, None] * np.array([1.5, 0.0, 0.0, 0.0, 0.0, 1.5])[None]


def test_evaluate_combines_refits_to_first_order_on_the_heldout_rows():
    rng = np.random.default_rng(1)
    pred0 = np.zeros((T, 6))
    c1, c2 = 2.0 * _wrench_change(T) * SIGMA, 2.0 * _second_change() * SIGMA
    model, _ = _wrench_ctx(pred0 + c1 + 0.5 * c2 + rng.normal(size=(T, 6)) * SIGMA, pred0)
    train = {"wrench": np.arange(T) % 2 == 0}
    fold = heldout.block_fold(model, {"wrench": pred0}, train,
                              {"a": Refit(np.zeros(1), {}, {"wrench": pred0 + c1}),
                               "b": Refit(np.zeros(1), {}, {"wrench": pred0 + c2})})
    before, after, (a, b, c, n), per = heldout.evaluate([fold], {"a": 1.0}, {"a": 1.0, "b": 0.5}, ["wrench"])
    rows = ~train["wrench"]
    r0 = (model.data("wrench") - pred0 - c1)[rows] / SIGMA
    r1 = r0 - (0.5 * c2)[rows] / SIGMA
    assert before == pytest.approx(np.sqrt(np.mean(r0 ** 2))) and after == pytest.approx(np.sqrt(np.mean(r1 ** 2)))
    assert a.shape == (rows.sum(),) and b.sum() == pytest.approx(np.sum((0.5 * c2[rows] / SIGMA) ** 2))
    assert set(per) == {"wrench"}


def _decide_with_heldout_recording(heldout_data, pred0, refits):
    model, ctx = _wrench_ctx(heldout_data[0], pred0)
    hmodel, _ = _wrench_ctx(heldout_data[1], pred0)
    d = engine.BagDiagnosis.__new__(engine.BagDiagnosis)
    d.model, d.settings, d.notes, d.tested, d.heldout = model, engine.Settings(alpha=0.01), [], ("wrench",), ["h"]
    train = {"wrench": np.ones(T, dtype=bool)}  # with held-out recordings the whole recording trains
    fold = heldout.HeldoutFold(hmodel, {"wrench": pred0}, None,
                               {e: {"wrench": rf.prediction["wrench"] - pred0} for e, rf in refits.items()})
    return d._decide(ctx, refits, train, [fold])


def test_a_second_candidate_needs_the_heldout_recording_to_support_it():
    """In-sample a second change fits (its conditional delta-BIC is far above 10); named only when the
    held-out recording carries it too (before: the delta-BIC alone decided with held-out recordings)."""
    rng = np.random.default_rng(2)
    pred0 = np.zeros((T, 6))
    c1, c2 = 3.0 * _wrench_change(T) * SIGMA, 4.0 * _second_change() * SIGMA
    refits = {"gel_viscoelasticity": Refit(np.array([0.4]), {}, {"wrench": pred0 + c1}),
              "damping": Refit(np.array([50.0]), {}, {"wrench": pred0 + 0.8 * c1 + c2})}
    noise = lambda: rng.normal(size=(T, 6)) * SIGMA  # noqa: E731
    primary = pred0 + 1.3 * c1 + c2 + noise()
    out = _decide_with_heldout_recording((primary, pred0 + 1.3 * c1 + noise()), pred0, refits)
    first, second = out["order"]
    assert out[first]["accepted"] and out[second]["conditional_delta_bic"] > 10.0
    assert not out[second]["accepted"]  # the held-out recording does not carry enough of it
    both = _decide_with_heldout_recording((primary, pred0 + 1.3 * c1 + c2 + noise()), pred0, refits)
    assert both["gel_viscoelasticity"]["accepted"] and both["damping"]["accepted"]


def test_nested_heldout_comparison_resolves_a_confusable_pair_and_reports_its_statistics():
    """Stiction's change moves force and moment; an anisotropy that reproduces the force part (and a
    third of the moment) explains much of it alone. Given the anisotropy, stiction still adds on the
    held-out rows; given stiction, the anisotropy adds nothing: resolved for stiction, both
    conditional tests reported."""
    rng = np.random.default_rng(4)
    pred0 = np.zeros((T, 6))
    c = 3.0 * _wrench_change(T) * SIGMA
    model, ctx = _wrench_ctx(pred0 + c + rng.normal(size=(T, 6)) * SIGMA, pred0)
    refits = {"stiction": Refit(np.array([0.02]), {}, {"wrench": pred0 + c}, {"candidate.stiction": 0.02}),
              "anisotropic_bending": Refit(np.array([0.05]), {}, {"wrench": pred0 + c * np.array([1, 1, 1, .3, .3, .3])},
                                           {"candidate.anisotropic_bending": 0.05})}
    d = engine.BagDiagnosis.__new__(engine.BagDiagnosis)
    d.model, d.settings, d.notes, d.tested, d.heldout = model, engine.Settings(alpha=0.01), [], ("wrench",), []
    train = {"wrench": np.arange(T) % 2 == 0}
    folds = [heldout.block_fold(model, ctx.prediction, train, refits)]
    d._decisions = d._decide(ctx, refits, train, folds)
    assert d._decisions["anisotropic_bending"]["acceptable_alone"]
    ties = d._ties(ctx, ["stiction"], refits, [], train, folds)
    tie = next(t for t in ties if set(t["pair"]) == {"stiction", "anisotropic_bending"})
    assert tie["resolved"] and tie["winner"] == "stiction" and tie["test"] == "nested_heldout"
    nested = tie["nested"]
    assert nested["stiction_given_anisotropic_bending"]["adds"]
    assert nested["stiction_given_anisotropic_bending"]["heldout_p"] < 0.01
    assert not nested["anisotropic_bending_given_stiction"]["adds"]


def test_a_change_rescaled_to_almost_nothing_does_not_resolve_a_pair():
    """The held-out test is blind to the scale: given the anisotropy, a stiction change that the
    training recording supports at 3 % of its size can be significant on a held-out recording that
    carries more of it, yet adds nothing at that scale. It must also remove min_explained of what
    the anisotropy leaves, else it cannot win the pair."""
    rng = np.random.default_rng(5)
    pred0 = np.zeros((T, 6))
    c, e = 3.0 * _wrench_change(T) * SIGMA, 3.0 * _second_change() * SIGMA
    refits = {"anisotropic_bending": Refit(np.array([0.05]), {}, {"wrench": pred0 + c}, {}),
              "stiction": Refit(np.array([0.02]), {}, {"wrench": pred0 + e}, {})}
    model, ctx = _wrench_ctx(pred0 + c + 0.03 * e + rng.normal(size=(T, 6)) * SIGMA * 0.2, pred0)
    hmodel, _ = _wrench_ctx(pred0 + c + 1.0 * e + rng.normal(size=(T, 6)) * SIGMA, pred0)
    d = engine.BagDiagnosis.__new__(engine.BagDiagnosis)
    d.model, d.settings, d.notes, d.tested, d.heldout = model, engine.Settings(alpha=0.01), [], ("wrench",), ["h"]
    train = {"wrench": np.ones(T, dtype=bool)}
    folds = [heldout.HeldoutFold(hmodel, {"wrench": pred0}, None,
                                 {k: {"wrench": rf.prediction["wrench"] - pred0} for k, rf in refits.items()})]
    d._decisions = {k: {"acceptable_alone": True} for k in refits}
    tie = next(t for t in d._ties(ctx, ["anisotropic_bending"], refits, [], train, folds)
               if set(t["pair"]) == {"stiction", "anisotropic_bending"})
    given = tie["nested"]["stiction_given_anisotropic_bending"]
    assert 0.0 < given["scale"] < 0.1 and given["heldout_p"] < 0.01  # significant, but tiny
    assert not given["adds"] and tie.get("winner") != "stiction"


def _products(r: np.ndarray, d: np.ndarray) -> heldout.Products:
    """Per-time products ``(a, b, c, n)`` of whitened residuals ``r`` and changes ``d``, both ``(T, m)``."""
    return (np.sum(r * d, axis=1), np.sum(d * d, axis=1), np.sum(r * r, axis=1), np.full(r.shape[0], float(r.shape[1])))


def test_supported_effect_weighs_each_supporting_channel_once_and_leaves_out_an_unsupported_one():
    """Three channels as in the main job's recording: markers (30 values a sample) and a sheet (200) whose
    held-out residual holds the refit's change, and a wrench (6) that the calibrated model does not follow
    (a gap of 4 noise units) whose held-out data do not support the change of 5 noise units per value. Pooled
    over values the sheet outweighs the markers; weighted equally with the wrench, the wrench's doubled
    mean square cancels both; weighted equally over the supporting channels the figures are the
    channels' own."""
    rng = np.random.default_rng(5)
    t = np.linspace(0.0, 1.0, 24)[:, None]
    d_m = 1.2 * np.sin(2 * np.pi * t + np.linspace(0, 3, 30)[None])
    d_s = 0.4 * np.cos(2 * np.pi * t + np.linspace(0, 3, 200)[None])
    d_w = 5.0 * np.sin(4 * np.pi * t + np.linspace(0, 1, 6)[None])
    gap_w = 4.0 * np.cos(7 * np.pi * t + np.linspace(0, 1, 6)[None])
    per = {"markers": _products(d_m + rng.normal(size=d_m.shape), d_m),
           "sheet": _products(d_s + rng.normal(size=d_s.shape), d_s),
           "wrench": _products(gap_w + rng.normal(size=d_w.shape), d_w)}
    supports = lambda p: stats.heldout_test(*p[:2], 0.0, *p[2:]).p_value <= 0.01  # noqa: E731
    assert [supports(per[ch]) for ch in ("markers", "sheet", "wrench")] == [True, True, False]
    eff = heldout.supported_effect(per, supports)
    ms = {ch: (np.sum(c) / np.sum(n), (np.sum(c) - 2 * np.sum(a) + np.sum(b)) / np.sum(n))
          for ch, (a, b, c, n) in per.items()}
    assert eff.channels == ("markers", "sheet")
    assert eff.rms_before == pytest.approx(np.sqrt(np.mean([ms["markers"][0], ms["sheet"][0]])))
    assert eff.rms_after == pytest.approx(np.sqrt(np.mean([ms["markers"][1], ms["sheet"][1]])))
    assert eff.gain == pytest.approx(sum(ms[ch][0] - ms[ch][1] for ch in ("markers", "sheet")))
    assert eff.gain == pytest.approx(0.72 + 0.08, abs=0.1)  # the changes' mean squares: 1.2^2 / 2 and 0.4^2 / 2
    assert sum(ms[ch][0] - ms[ch][1] for ch in per) < 0  # the wrench, weighted equally, cancels both
    figures = eff.figures()
    assert figures["supported_on"] == ["markers", "sheet"] and figures["effect_gain"] == eff.gain
    assert figures["supported_ms_removed"] == pytest.approx(eff.gain / 2)
    assert figures["explained_fraction"] > 0.9
    none = heldout.supported_effect(per, lambda p: False)
    assert none.channels == () and none.gain == 0.0 and np.isnan(none.rms_before)
    assert none.figures() == {"explained_fraction": 0.0, "supported_ms_removed": 0.0, "supported_on": [],
                              "supported_rms": [], "effect_gain": 0.0}
